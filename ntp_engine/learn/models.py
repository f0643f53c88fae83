"""Shipped trace networks (``assets/models/NAME/``): export from a training run, load for inference.

A model folder holds ``model.pt`` (float16 state dict; the lighting layer in float32),
``config.json`` (network config, the device it was trained for and that device's gain and exposure
limit: the exposure its inputs are normalised to), ``pattern.csv`` (the learned pattern, float) and
``summary.json`` (training steps, data seed, final validation losses, wall time) and, optionally,
``specular_basis.pt``: the subspace the specular head's outputs live in (``specular_basis``), with
which ``load`` replaces the head's last layer — the network's largest — by two thin ones
(``TraceNet.compress_specular``: about 5x less work on that layer, outputs within
``BASIS_TOLERANCE`` of the full layer's on synthetic traces).

One home for the pattern: a network measures with the pattern it was trained with (its lighting
layer), so a capture must have been lit by that pattern. Loading a model for a scanner whose
pattern differs by more than the driver's 8-bit quantisation is an error naming both files.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch
from torch import Tensor, nn

from ..io.assets import MODELS_DIR
from ..io.atomic import atomic_path, write_text_atomic
from ..io.errors import NtpInputError
from ..scanner.device_file import load_scanner
from ..scanner.pattern import QUANTUM, patterns_agree
from ..scanner.scanner import Scanner
from .network import NetworkConfig, TraceNet
from .synthetic import SyntheticConfig, sample_batch

DEFAULT_MODEL = "compact"
# buffers derived from the device file at load time, not stored with the weights
DEVICE_BUFFERS = ("color_matrix", "gain", "max_exposure", "pos_matrix", "pos_center")
SPECULAR_BASIS = "specular_basis.pt"
# the specular basis: the fewest output directions that keep every calibration trace's log1p
# specular lumitexel within this of the full layer's, at every light (docs/performance.md)
BASIS_TOLERANCE = 0.01
BASIS_TRACES = 16384  # synthetic calibration traces (64 views each) for the basis


def resolve(name_or_path: str | Path | None) -> Path:
    """A model folder: a shipped model's name (default ``compact``) or a path."""
    p = Path(name_or_path) if name_or_path else MODELS_DIR / DEFAULT_MODEL
    if not p.exists() and (MODELS_DIR / str(name_or_path)).exists():
        p = MODELS_DIR / str(name_or_path)
    if not (p / "model.pt").exists():
        raise NtpInputError(
            p,
            "not a model folder (no model.pt); shipped models: "
            + ", ".join(sorted(q.name for q in MODELS_DIR.glob("*") if (q / "model.pt").exists())),
        )
    return p


def load(
    name_or_path: str | Path | None = None,
    scanner: Scanner | None = None,
    map_location: str | torch.device = "cpu",
    exact: bool = False,
) -> tuple[TraceNet, dict]:
    """(network in eval mode, float32, metadata dict with the model's ``folder``) for measurements
    taken by ``scanner``; its specular head compressed to the folder's ``specular_basis.pt`` if
    there is one, unless ``exact`` (``meta["specular_basis"]``: its rank, or None).

    With a ``scanner`` (a capture's device), its pattern must be the network's, to 8-bit
    quantisation (else ``NtpInputError`` naming the model's ``pattern.csv`` and the device file).
    Without one, the default device's geometry is used with the network's own pattern — for
    synthetic evaluation, where the network's pattern is the truth."""
    folder = resolve(name_or_path)
    try:
        meta = json.loads((folder / "config.json").read_text(encoding="utf-8"))
        cfg = NetworkConfig(**meta["network"])
    except (OSError, ValueError, KeyError, TypeError) as err:
        raise NtpInputError(
            folder / "config.json", f"not a model configuration ({type(err).__name__}: {err})"
        ) from None
    net = TraceNet(cfg, scanner or load_scanner())
    try:
        state = torch.load(folder / "model.pt", map_location=map_location, weights_only=True)
    except Exception as err:  # noqa: BLE001 - torch raises many types for a damaged file
        first = str(err).split(". ")[0]  # torch explains at length
        raise NtpInputError(folder / "model.pt", f"cannot read the weights ({type(err).__name__}: {first})") from None
    missing, unexpected = net.load_state_dict({k: v.float() for k, v in state.items()}, strict=False)
    if unexpected or set(missing) - set(DEVICE_BUFFERS):
        raise NtpInputError(
            folder / "model.pt", f"weights do not match the config (missing {missing}, unexpected {unexpected})"
        )
    if "device_gain" in meta:  # the exposure the network was trained with, whatever device is passed
        net.gain.fill_(float(meta["device_gain"]))
    if "device_max_exposure" in meta:
        net.max_exposure.fill_(float(meta["device_max_exposure"]))
    if scanner is not None:
        check_pattern(net, folder, scanner)
    summary = folder / "summary.json"
    meta["summary"] = json.loads(summary.read_text()) if summary.exists() else {}
    meta["folder"] = str(folder)
    meta["specular_basis"] = None
    if (folder / SPECULAR_BASIS).exists() and not exact:
        try:
            basis = torch.load(folder / SPECULAR_BASIS, map_location="cpu", weights_only=True)
            net.compress_specular(basis["basis"].float(), basis["hidden_mean"].float())
        except Exception as err:  # noqa: BLE001 - as for model.pt
            first = str(err).split(". ")[0]
            raise NtpInputError(
                folder / SPECULAR_BASIS, f"not a specular basis ({type(err).__name__}: {first})"
            ) from None
        meta["specular_basis"] = int(basis["basis"].shape[1])
    return net.to(map_location).eval(), meta


def model_files(folder: Path) -> list[Path]:
    """The files whose content is the model's answer (cache keys hash them)."""
    return [folder / name for name in ("config.json", "model.pt", SPECULAR_BASIS) if (folder / name).exists()]


@torch.no_grad()
def specular_basis(
    net: TraceNet, scanner: Scanner, traces: int = BASIS_TRACES, tolerance: float = BASIS_TOLERANCE, seed: int = 0
) -> dict[str, Tensor | float | int]:
    """The subspace of the specular head's outputs on ``traces`` synthetic 64-view traces (the
    training distribution, measured through ``net``'s sensor): the principal directions of W h
    (W the last layer, h its input) from h's covariance, as few as keep every calibration output
    within ``tolerance`` (log1p units, any light) of the full layer's; a fresh seeded half of
    the traces checks it. Returns basis ``(6144, r)``, hidden_mean ``(1024,)``, r and the worst
    error on both halves."""
    net = net.eval()
    last = net.specular_head[-1]
    assert isinstance(last, nn.Linear), "the specular head is already compressed"
    hidden: list[Tensor] = []
    hook = last.register_forward_hook(lambda _m, inp, _out: hidden.append(inp[0].detach().double()))
    gen = torch.Generator().manual_seed(seed)
    try:
        for i in range(0, traces, 256):
            b = sample_batch(scanner, min(256, traces - i), gen, SyntheticConfig(), views=64)
            pixel, valid = net.measure_batch(b, gen)
            net(net.entries(pixel, b.position, b.normal_geo, b.tangent_geo), valid)
    finally:
        hook.remove()
    h = torch.cat(hidden)
    fit, check = h[: len(h) // 2], h[len(h) // 2 :]
    mean = fit.mean(0)
    w = last.weight.detach().double()
    cov = (fit - mean).T @ (fit - mean) / len(fit)
    evals, evecs = torch.linalg.eigh(cov)
    root = evecs * evals.clamp_min(0).sqrt()  # cov = root root^T
    u, _, _ = torch.linalg.svd(w @ root, full_matrices=False)  # output directions by variance

    y_fit, y_check = ((part - mean) @ w.T for part in (fit, check))

    def worst(y: Tensor, r: int) -> float:
        p = u[:, :r]
        return float(((y @ p) @ p.T - y).abs().max())

    lo, hi = 1, u.shape[1]  # the fewest directions within the tolerance (the error falls with r)
    while lo < hi:
        mid = (lo + hi) // 2
        lo, hi = (lo, mid) if worst(y_fit, mid) <= tolerance else (mid + 1, hi)
    return {
        "basis": u[:, :lo].float(),
        "hidden_mean": mean.float(),
        "rank": lo,
        "worst_fit": worst(y_fit, lo),
        "worst_check": worst(y_check, lo),
    }


def write_specular_basis(folder: Path, scanner: Scanner | None = None, **kw) -> dict:
    """``specular_basis`` of the model in ``folder`` written to its ``specular_basis.pt``; returns
    the rank and the errors."""
    net, _ = load(folder, exact=True)
    found = specular_basis(net, scanner or load_scanner(), **kw)
    with atomic_path(folder / SPECULAR_BASIS) as tmp:
        torch.save({"basis": found["basis"], "hidden_mean": found["hidden_mean"]}, tmp)
    return {k: v for k, v in found.items() if k not in ("basis", "hidden_mean")}


def check_pattern(net: TraceNet, folder: Path, scanner: Scanner) -> None:
    """Raise ``NtpInputError`` unless ``scanner``'s pattern is ``net``'s to 8-bit quantisation."""
    ours = net.pattern().detach().double().cpu().numpy()
    if patterns_agree(ours, scanner.pattern):
        return
    worst = float(np.abs(ours - scanner.pattern).max())  # same shape: the net was built for this scanner
    raise NtpInputError(
        folder / "pattern.csv",
        f"the network was trained with another lighting pattern than "
        f"{scanner.source or scanner.name} lights (differs by up to {worst / QUANTUM:.1f}/255): "
        "use the model trained for this pattern, or write its pattern into the device file "
        "(ntp train --export-pattern-to-device)",
    )


def export(checkpoint: Path, folder: Path, summary: dict) -> None:
    """Write a model folder from a training checkpoint (weights as float16)."""
    ck = torch.load(checkpoint, map_location="cpu", weights_only=False)
    folder.mkdir(parents=True, exist_ok=True)
    # device-derived buffers (colour matrix, gain, box) come from the device file at load time
    state = {
        k: (v.half() if v.is_floating_point() and k != "pattern_logits" else v)
        for k, v in ck["model"].items()
        if k not in DEVICE_BUFFERS
    }
    with atomic_path(folder / "model.pt") as tmp:
        torch.save(state, tmp)
    pattern = torch.sigmoid(ck["model"]["pattern_logits"].float()).numpy()
    with atomic_path(folder / "pattern.csv") as tmp:
        np.savetxt(tmp, pattern, delimiter=",", fmt="%.6f")
    write_text_atomic(
        folder / "config.json",
        json.dumps(
            {
                "network": ck["network"],
                "device": ck["device"],
                "device_gain": float(ck["model"]["gain"]),
                "device_max_exposure": float(ck["model"]["max_exposure"]),
            },
            indent=2,
        ),
    )
    write_text_atomic(
        folder / "summary.json",
        json.dumps(
            {
                "steps": ck["step"],
                "data_seed": ck["train"]["seed"],
                "batch": ck["train"]["batch"],
                "lr": ck["train"]["lr"],
                "sweep_fraction": ck["train"].get("sweep_fraction", 0.0),
                **summary,
            },
            indent=2,
        ),
    )


def pattern_of(name_or_path: str | Path | None = None) -> np.ndarray:
    """The lighting pattern ``(L, 3)`` a model was trained with (its ``pattern.csv``)."""
    return np.loadtxt(resolve(name_or_path) / "pattern.csv", delimiter=",", ndmin=2)
