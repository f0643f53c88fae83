"""``ntp train``: joint training of the trace network and the lighting pattern (paper §6.5).

Every step's data comes from a generator seeded with (seed, step), so an interrupted run resumed
from its checkpoint sees exactly the data it would have seen. Validation uses a fixed, separately
seeded set (also its noise), evaluated with dropout off. Files in OUT: ``checkpoint.pt`` (model,
optimiser, step; written atomically every ``checkpoint_every`` steps), ``log.csv`` (step, train
and validation losses), ``config.json``.
"""

from __future__ import annotations

import csv
import json
import math
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch

from ..io.atomic import atomic_path, write_text_atomic
from ..io.errors import NtpInputError
from ..io.progress import QUIET, Progress
from ..physics.confidence import confidence_from_ratios
from ..scanner.device_file import load_scanner
from ..scanner.pattern import named_pattern
from ..scanner.scanner import Scanner
from .models import DEVICE_BUFFERS
from .network import NetworkConfig, TraceNet, lumitexel_loss, num_parameters
from .synthetic import SyntheticConfig, TraceBatch, sample_batch

VAL_SEED_OFFSET = 1_000_003
PATTERN_INIT_MARGIN = 0.1  # a learned pattern started from a given one is clipped to [0.1, 0.9]


@dataclass
class TrainConfig:
    """Training settings: steps, batch, learning rates, seeds, validation and checkpoint cadence, data mix."""

    steps: int = 20000
    batch: int = 64
    lr: float = 3e-4
    pattern_lr: float | None = None  # a separate learning rate for the lighting layer (None: lr)
    seed: int = 0
    validate_every: int = 500
    checkpoint_every: int = 250
    val_batches: int = 8
    views_max: int = 64
    sweep_fraction: float = 0.5  # traces whose views come from a correlated hand-held sweep
    pattern_init: str | None = None  # a learned pattern's start (a frozen-pattern name or file); None: 0.5
    lr_schedule: str = "constant"  # "cosine": every rate falls to 0 at ``steps`` (a settled last checkpoint)
    schedule_start: int = 0  # the step the run began at (a warm start's), where the cosine starts


LR_SCHEDULES = ("constant", "cosine")


def lr_factor(tcfg: TrainConfig, step: int) -> float:
    """The multiplier on every learning rate before ``step``'s update: 1 for a constant schedule;
    for a cosine one 0.5 (1 + cos(pi f)), f the fraction of the run from ``schedule_start`` to
    ``steps`` done (1 at the start, 0 at the last step)."""
    if tcfg.lr_schedule == "constant":
        return 1.0
    span = max(tcfg.steps - tcfg.schedule_start, 1)
    f = min(max((step - tcfg.schedule_start) / span, 0.0), 1.0)
    return 0.5 * (1.0 + math.cos(math.pi * f))


def _step_generator(seed: int, step: int, device) -> torch.Generator:
    g = torch.Generator(device=device)
    g.manual_seed(seed * 1_000_000_007 + step)
    return g


def batch_loss(model: TraceNet, batch: TraceBatch, gen: torch.Generator, noise: bool = True):
    """Measure, filter, predict and score one batch: (loss, diffuse part, specular part, valid mask)."""
    pixel, valid = model.measure_batch(batch, gen, noise=noise)
    beta = confidence_from_ratios(batch.highlight_ratio, valid)
    entries = model.entries(pixel, batch.position, batch.normal_geo, batch.tangent_geo)
    pred_d, pred_s = model(entries, valid)
    # a trace left with no valid view still counts: the network answers it from the pooled zeros
    # (its prior), so a pattern that leaves traces empty pays for them (Fig. 14)
    total, ld, ls = lumitexel_loss(pred_d, pred_s, batch.label_diffuse, batch.label_specular, beta)
    return total, ld, ls, valid


@torch.no_grad()
def validate(
    model: TraceNet,
    scanner: Scanner,
    tcfg: TrainConfig,
    scfg: SyntheticConfig,
    torch_device,
    views: int | None = None,
    batches: int | None = None,
    seed: int | None = None,
) -> dict[str, float]:
    """Mean Eq. 5 loss on a seeded set (dropout off): by default the run's fixed validation set
    (data seed + VAL_SEED_OFFSET); ``seed`` picks another. ``views`` fixes the trace length."""
    was_training = model.training
    model.eval()
    per_batch = np.zeros((batches or tcfg.val_batches, 3))
    valid_frac = 0.0
    for k in range(len(per_batch)):
        gen = _step_generator(tcfg.seed + VAL_SEED_OFFSET if seed is None else seed, k, torch_device)
        batch = sample_batch(scanner, tcfg.batch, gen, scfg, device=torch_device, views=views)
        total, ld, ls, valid = batch_loss(model, batch, gen)
        per_batch[k] = [float(total), float(ld), float(ls)]
        valid_frac += float(valid.float().sum() / batch.length_mask.float().sum())
    model.train(was_training)
    sums = per_batch.mean(0)
    return {
        "val_loss": sums[0],
        "val_diffuse": sums[1],
        "val_specular": sums[2],
        "val_valid_views": valid_frac / len(per_batch),
        "val_loss_per_batch": per_batch[:, 0].tolist(),
    }


def _match_optimizer_order(state: dict, opt: torch.optim.Optimizer) -> dict:
    """The checkpoint's optimiser state re-indexed to ``opt``'s parameter order. Checkpoints from
    before ``--pattern-lr`` list the lighting layer first (module order), newer ones last; Adam's
    state is by position, so each current parameter takes the first unused state of its shape."""
    current = [p for g in opt.param_groups for p in g["params"]]
    old_ids = [i for g in state["param_groups"] for i in g["params"]]
    shapes = {i: tuple(state["state"][i]["exp_avg"].shape) for i in old_ids if i in state["state"]}
    if [shapes.get(i) for i in old_ids] == [tuple(p.shape) for p in current] or len(old_ids) != len(current):
        return state
    unused, new_state = list(old_ids), {}
    for k, p in enumerate(current):
        j = next((i for i in unused if shapes.get(i) == tuple(p.shape)), None)
        if j is None:
            return state  # cannot match: let load_state_dict report it
        unused.remove(j)
        new_state[k] = state["state"][j]
    groups, k = [], 0
    for g in state["param_groups"]:
        groups.append({**g, "params": list(range(k, k + len(g["params"])))})
        k += len(g["params"])
    return {"state": new_state, "param_groups": groups}


def _load_state(model: TraceNet, state: dict) -> None:
    """A checkpoint's weights and buffers into ``model``; a device buffer the state lacks keeps the
    model's (the device's): an exported model folder has none, a run from before the exposure limit
    no ``max_exposure``. A missing weight is still an error."""
    own = model.state_dict()
    model.load_state_dict({**{k: own[k] for k in DEVICE_BUFFERS}, **state})


def _source_checkpoint(source: Path, torch_device) -> tuple[Path, dict]:
    """(path, checkpoint-like dict with ``network``, ``model``, ``step``, ``train.seed``) of a run
    folder, a checkpoint file, or an exported model folder (``config.json`` + float16 ``model.pt``;
    its step and data seed from ``summary.json``), so a shipped model can be trained on."""
    if source.is_dir() and (source / "model.pt").is_file() and not (source / "checkpoint.pt").exists():
        try:
            meta = json.loads((source / "config.json").read_text(encoding="utf-8"))
            summary = json.loads((source / "summary.json").read_text(encoding="utf-8"))
            state = torch.load(source / "model.pt", map_location=torch_device, weights_only=True)
            ck = {
                "network": meta["network"],
                "model": {k: v.float() if v.is_floating_point() else v for k, v in state.items()},
                "step": int(summary["steps"]),
                "train": {"seed": int(summary["data_seed"])},
            }
        except (OSError, ValueError, KeyError, TypeError) as err:
            raise NtpInputError(source, f"not a model folder to start from ({type(err).__name__}: {err})") from None
        return source / "model.pt", ck
    path = source / "checkpoint.pt" if source.is_dir() else source
    if not path.is_file():
        raise NtpInputError(path, "no checkpoint to start from")
    return path, torch.load(path, map_location=torch_device, weights_only=False)


def _warm_start(model: TraceNet, ncfg: NetworkConfig, source: Path, torch_device) -> tuple[int, int]:
    """Load another run's (or a model folder's) weights into ``model`` (same preset, any pattern
    setting); returns its (step, data seed) so the new run continues its data stream. A learned new
    pattern starts at the source's: as it was where the source learned it too (so the device file
    written from it stays the one the network reads), scaled to a maximum of 0.5 where the source's
    was frozen — auto-exposure measures a scaled pattern identically (while its exposure stays
    under the device's limit: full-on at 0.5 needs 2x), and at 0.5 the sigmoid's gradient is
    largest (a full-on source, frozen at 1, would otherwise never move). A frozen new pattern keeps
    its own value. The optimiser starts afresh."""
    path, ck = _source_checkpoint(source, torch_device)
    other = {k: v for k, v in ck["network"].items() if k != "frozen_pattern"}
    if other != {k: v for k, v in ncfg.to_dict().items() if k != "frozen_pattern"}:
        raise NtpInputError(path, "trained with a different network config (only the pattern may differ)")
    own = model.pattern_logits.detach().clone()
    _load_state(model, ck["model"])
    if ncfg.frozen_pattern is not None:  # a frozen pattern keeps its own value
        with torch.no_grad():
            model.pattern_logits.copy_(own)
    elif ck["network"].get("frozen_pattern") is not None:
        p = torch.sigmoid(ck["model"]["pattern_logits"].double())
        model.set_pattern((0.5 * p / p.max().clamp_min(1e-12)).cpu().numpy())
    return int(ck["step"]), int(ck["train"]["seed"])


def train(
    out: Path,
    ncfg: NetworkConfig,
    tcfg: TrainConfig,
    device_path: Path | None = None,
    resume: bool = False,
    progress: Progress = QUIET,
    init_from: Path | None = None,
) -> dict:
    """Train into ``out`` (see the module docstring). ``init_from``: a run folder or checkpoint whose
    weights and step start this new run (``_warm_start``); ignored when resuming."""
    if tcfg.lr_schedule not in LR_SCHEDULES:
        raise ValueError(f"lr_schedule {tcfg.lr_schedule!r}: expected one of {LR_SCHEDULES}")
    out.mkdir(parents=True, exist_ok=True)
    torch_device = torch.device("cuda" if torch.cuda.is_available() else "cpu")
    scanner = load_scanner(device_path)
    scfg = SyntheticConfig(
        views_min=min(16, tcfg.views_max), views_max=tcfg.views_max, sweep_fraction=tcfg.sweep_fraction
    )
    ckpt_path = out / "checkpoint.pt"
    model = TraceNet(ncfg, scanner).to(torch_device)
    opt = _optimizer(model, tcfg)
    step, elapsed = 0, 0.0
    if resume and ckpt_path.exists():
        step, elapsed = _resume(ckpt_path, model, opt, ncfg, tcfg, torch_device)
        print(f"resuming {ckpt_path} at step {step}")
    elif ckpt_path.exists() and not resume:
        raise NtpInputError(ckpt_path, "exists; pass --resume to continue it or choose another --out")
    else:
        if init_from is not None:
            step, tcfg.seed = _warm_start(model, ncfg, Path(init_from), torch_device)
            tcfg.schedule_start = step
            print(f"starting from {init_from} at step {step}")
        if tcfg.pattern_init is not None and ncfg.frozen_pattern is None:
            # kept off 0 and 1, where the sigmoid's gradient vanishes
            model.set_pattern(named_pattern(tcfg.pattern_init, scanner), margin=PATTERN_INIT_MARGIN)
    run_info = {"network": ncfg.to_dict(), "train": asdict(tcfg), "device": scanner.name}
    write_text_atomic(out / "config.json", json.dumps({**run_info, "parameters": num_parameters(model)}, indent=2))

    model.train()
    running, count = 0.0, 0
    last: dict = {}
    t_last = time.perf_counter()
    # the schedule scales the configured rates (a resumed optimiser holds the last scaled ones)
    base_lrs = [tcfg.lr] if len(opt.param_groups) == 1 else [tcfg.lr, float(tcfg.pattern_lr or 0.0)]
    with _Log(out / "log.csv") as log, progress.counter("train", tcfg.steps, "step") as bar:
        bar.update(step)
        while step < tcfg.steps:
            gen = _step_generator(tcfg.seed, step, torch_device)
            batch = sample_batch(scanner, tcfg.batch, gen, scfg, device=torch_device)
            loss, _, _, _ = batch_loss(model, batch, gen)
            for group, base in zip(opt.param_groups, base_lrs, strict=True):
                group["lr"] = base * lr_factor(tcfg, step)
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            step += 1
            running, count = running + loss.item(), count + 1
            now = time.perf_counter()
            elapsed, t_last = elapsed + (now - t_last), now
            bar.update()
            if step % tcfg.validate_every == 0 or step == tcfg.steps:
                last = validate(model, scanner, tcfg, scfg, torch_device)
                log.row(step, running / max(count, 1), last, elapsed)
                running, count = 0.0, 0
            if step % tcfg.checkpoint_every == 0 or step == tcfg.steps:
                checkpoint = {"model": model.state_dict(), "optimizer": opt.state_dict(), "step": step}
                with atomic_path(ckpt_path) as tmp:
                    torch.save({**checkpoint, **run_info, "elapsed_s": elapsed}, tmp)
    if not last:
        last = validate(model, scanner, tcfg, scfg, torch_device)
    last.pop("val_loss_per_batch")
    return {"step": step, "elapsed_s": elapsed, **last}


def _optimizer(model: TraceNet, tcfg: TrainConfig) -> torch.optim.Adam:
    """Adam over the network; the lighting layer in its own group when it has its own rate."""
    params = [p for n, p in model.named_parameters() if p.requires_grad and n != "pattern_logits"]
    groups: list[dict] = [{"params": params}]
    if model.pattern_logits.requires_grad:
        if tcfg.pattern_lr is None:
            groups[0]["params"] = params + [model.pattern_logits]
        else:  # the pattern's logits get tiny gradients: they need their own, larger step
            groups.append({"params": [model.pattern_logits], "lr": tcfg.pattern_lr})
    return torch.optim.Adam(groups, lr=tcfg.lr, betas=(0.9, 0.999))


def _resume(
    ckpt_path: Path,
    model: TraceNet,
    opt: torch.optim.Optimizer,
    ncfg: NetworkConfig,
    tcfg: TrainConfig,
    torch_device: torch.device,
) -> tuple[int, float]:
    """Load a run's checkpoint into ``model`` and ``opt`` (and its data seed into ``tcfg``); returns
    (step, elapsed seconds)."""
    ck = torch.load(ckpt_path, map_location=torch_device, weights_only=False)
    if ck["network"] != ncfg.to_dict():
        raise NtpInputError(ckpt_path, "checkpoint was trained with a different network config")
    _load_state(model, ck["model"])
    if len(ck["optimizer"]["param_groups"]) != len(opt.param_groups):
        raise NtpInputError(
            ckpt_path,
            f"the checkpoint's optimiser has {len(ck['optimizer']['param_groups'])} "
            "parameter group(s); resume with the same --pattern-lr setting",
        )
    opt.load_state_dict(_match_optimizer_order(ck["optimizer"], opt))
    tcfg.seed = ck["train"]["seed"]
    tcfg.schedule_start = ck["train"].get("schedule_start", 0)
    return ck["step"], ck.get("elapsed_s", 0.0)


class _Log:
    """``log.csv``: one row per validation (appended; the header once)."""

    HEADER = ["step", "train_loss", "val_loss", "val_diffuse", "val_specular", "val_valid_views", "elapsed_s"]

    def __init__(self, path: Path):
        new = not path.exists()
        self.file = open(path, "a", newline="")
        self.writer = csv.writer(self.file)
        if new:
            self.writer.writerow(self.HEADER)

    def row(self, step: int, train_loss: float, val: dict, elapsed: float) -> None:
        values = (f"{val[k]:.6g}" for k in ("val_loss", "val_diffuse", "val_specular", "val_valid_views"))
        self.writer.writerow([step, train_loss, *values, f"{elapsed:.1f}"])
        self.file.flush()

    def __enter__(self) -> _Log:
        return self

    def __exit__(self, *exc: object) -> None:
        self.file.close()
