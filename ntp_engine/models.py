"""Shipped trace networks (``assets/models/NAME/``): export from a training run, load for inference.

A model folder holds ``model.pt`` (float16 state dict), ``config.json`` (network config, the
device it was trained for and that device's gain and exposure limit: the exposure its inputs are
normalised to), ``pattern.csv`` (the learned pattern, float) and ``summary.json``
(training steps, data seed, final validation losses, wall time).
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import torch

from .atomic import atomic_path, write_text_atomic
from .device import ASSETS, Device
from .errors import NtpInputError
from .network import NetworkConfig, TraceNet

MODELS_DIR = ASSETS / "models"
DEFAULT_MODEL = "compact"
# buffers derived from the device file at load time, not stored with the weights
DEVICE_BUFFERS = ("color_matrix", "gain", "max_exposure", "pos_matrix", "pos_center")


def resolve(name_or_path: str | Path | None) -> Path:
    """A model folder: a shipped model's name (default ``compact``) or a path."""
    p = Path(name_or_path) if name_or_path else MODELS_DIR / DEFAULT_MODEL
    if not p.exists() and (MODELS_DIR / str(name_or_path)).exists():
        p = MODELS_DIR / str(name_or_path)
    if not (p / "model.pt").exists():
        raise NtpInputError(p, "not a model folder (no model.pt); shipped models: "
                            + ", ".join(sorted(q.name for q in MODELS_DIR.glob("*") if (q / "model.pt").exists())))
    return p


def load(name_or_path: str | Path | None = None, device: Device | None = None,
         map_location: str | torch.device = "cpu") -> tuple[TraceNet, dict]:
    """(network in eval mode, float32, metadata dict). ``device`` defaults to the default device."""
    folder = resolve(name_or_path)
    meta = json.loads((folder / "config.json").read_text())
    cfg = NetworkConfig(**meta["network"])
    net = TraceNet(cfg, device or Device.load())
    state = torch.load(folder / "model.pt", map_location=map_location, weights_only=True)
    missing, unexpected = net.load_state_dict({k: v.float() for k, v in state.items()}, strict=False)
    if unexpected or set(missing) - set(DEVICE_BUFFERS):
        raise NtpInputError(folder / "model.pt", f"weights do not match the config (missing {missing}, "
                            f"unexpected {unexpected})")
    if "device_gain" in meta:  # the exposure the network was trained with, whatever device is passed
        net.gain.fill_(float(meta["device_gain"]))
    if "device_max_exposure" in meta:
        net.max_exposure.fill_(float(meta["device_max_exposure"]))
    summary = folder / "summary.json"
    meta["summary"] = json.loads(summary.read_text()) if summary.exists() else {}
    return net.to(map_location).eval(), meta


def export(checkpoint: Path, folder: Path, summary: dict) -> None:
    """Write a model folder from a training checkpoint (weights as float16)."""
    ck = torch.load(checkpoint, map_location="cpu", weights_only=False)
    folder.mkdir(parents=True, exist_ok=True)
    # device-derived buffers (colour matrix, gain, box) come from the device file at load time
    state = {k: (v.half() if v.is_floating_point() and k != "pattern_logits" else v)
             for k, v in ck["model"].items() if k not in DEVICE_BUFFERS}
    with atomic_path(folder / "model.pt") as tmp:
        torch.save(state, tmp)
    pattern = torch.sigmoid(ck["model"]["pattern_logits"].float()).numpy()
    with atomic_path(folder / "pattern.csv") as tmp:
        np.savetxt(tmp, pattern, delimiter=",", fmt="%.6f")
    write_text_atomic(folder / "config.json", json.dumps({
        "network": ck["network"], "device": ck["device"], "device_gain": float(ck["model"]["gain"]),
        "device_max_exposure": float(ck["model"]["max_exposure"])}, indent=2))
    write_text_atomic(folder / "summary.json", json.dumps({"steps": ck["step"], "data_seed": ck["train"]["seed"],
                                                           "batch": ck["train"]["batch"], "lr": ck["train"]["lr"],
                                                           "sweep_fraction": ck["train"].get("sweep_fraction", 0.0),
                                                           **summary}, indent=2))


def quantise_pattern(pattern: np.ndarray) -> np.ndarray:
    """8 bits per channel, as the LED driver's PWM projects it."""
    return np.round(np.clip(pattern, 0, 1) * 255) / 255


def write_pattern_to_device(pattern: np.ndarray, device_file: Path) -> Path:
    """Store the 8-bit-quantised pattern beside ``device_file`` and point its ``pattern`` key at it."""
    csv_path = device_file.with_name(device_file.stem + "_pattern.csv")
    with atomic_path(csv_path) as tmp:
        np.savetxt(tmp, quantise_pattern(pattern), delimiter=",", fmt="%.8f")
    text = device_file.read_text()
    lines = [ln for ln in text.splitlines()]
    for i, ln in enumerate(lines):
        if ln.startswith("pattern ="):
            lines[i] = f'pattern = "{csv_path.name}"  # learned pattern, quantised to 8 bits (k/255) per LED and colour'
            break
    else:
        raise NtpInputError(device_file, "no top-level 'pattern =' line to replace")
    write_text_atomic(device_file, "\n".join(lines) + "\n")
    Device.load(device_file)  # must still parse
    return csv_path
