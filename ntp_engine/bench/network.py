"""``ntp bench network``: what the lighting pattern and the trace length do to the network's error,
and the shipped model's inference rate.

- ``val_loss_by_pattern``: Eq. 5 validation loss of three networks that differ only in their
  pattern (jointly optimised, fixed full-on, fixed single point light; paper Fig. 14). ``--quick``
  reads the comparison networks shipped in ``assets/models/compare_*``; otherwise they are trained
  here first (``--steps`` each, ``small`` preset): full-on and point for half the steps, then every
  network goes on from there for the other half (``train --init-from``, fresh Adam) — the optimised
  one from the full-on network with its pattern learning (``PATTERN_LR``), starting from what
  auto-exposure measures as full-on. So optimised and full-on differ only in what the pattern
  learning did. Either way they are evaluated on ``PATTERN_BATCHES`` batches of validation data
  generated now, with a seed no training run used; the same batches for each, so
  ``val_loss_minus_full_on`` gives each difference with its paired standard error over batches,
  and ``valid_views_by_pattern`` the fraction of views in [32, 224] under the exposure limit.
- ``val_loss_by_test_views``: the shipped model on traces of exactly 8 ... 128 views (Fig. 16).
- ``traces_per_s``: the shipped model on 64-view traces through the inference API.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

from ..io.assets import MODELS_DIR
from ..learn import models
from ..learn.inference import predict_all
from ..learn.network import NetworkConfig
from ..learn.ragged import RaggedTraces
from ..learn.synthetic import SyntheticConfig, sample_batch
from ..learn.train import TrainConfig, train, validate
from ..scanner.device_file import load_scanner
from ..scanner.scanner import Scanner
from . import dump_json, print_table

PATTERNS = {"optimized": "learned", "full_on": "full_on", "point": "point"}
BENCH_SEED = 424_242  # training uses seeds 0.., validation 1_000_003..: this data is new to every model
PATTERN_LR = 3e-3  # the lighting layer's own learning rate in the comparison (docs/network.md)
PATTERN_BATCHES = 64  # 4096 traces: the three losses differ by less than 8 batches' noise


def evaluate(model, scanner: Scanner, views: int | None, batches: int, batch: int = 64, seed: int = BENCH_SEED) -> dict:
    """``train.validate`` on ``batches`` fresh batches (a seed no training run uses): every model
    sees the same traces, so per-batch losses pair up across models."""
    tcfg = TrainConfig(batch=batch, val_batches=batches)
    return validate(model, scanner, tcfg, SyntheticConfig(), torch.device("cpu"), views=views, seed=seed)


def paired_difference(a: list[float], b: list[float]) -> tuple[float, float]:
    """Mean and standard error of ``a - b`` over the same validation batches."""
    d = np.asarray(a) - np.asarray(b)
    return float(d.mean()), float(d.std(ddof=1) / np.sqrt(len(d))) if len(d) > 1 else float("nan")


def _comparison_models(quick: bool, steps: int) -> dict:
    """The three pattern networks (each with its own pattern: loaded without a capture's scanner)."""
    if quick:
        return {name: models.load(MODELS_DIR / f"compare_{name}")[0] for name in PATTERNS}
    root = Path(tempfile.mkdtemp(prefix="ntp-bench-network-"))

    def tc(n, **kw):
        return TrainConfig(steps=n, validate_every=max(n // 4, 1), val_batches=2, **kw)  # log only

    for name in ("full_on", "point"):  # first half
        train(
            root / f"{name}_half",
            NetworkConfig(preset="small", frozen_pattern=name),
            tc(steps // 2, sweep_fraction=0.0),
        )
    out = {}
    for name, pattern in PATTERNS.items():  # second half, every network from a half-way checkpoint
        frozen = None if pattern == "learned" else pattern
        source = root / ("point_half" if name == "point" else "full_on_half")
        train(
            root / name,
            NetworkConfig(preset="small", frozen_pattern=frozen),
            tc(steps, pattern_lr=PATTERN_LR if frozen is None else None),
            init_from=source,
        )
        models.export(root / name / "checkpoint.pt", root / name / "model", {})
        out[name] = models.load(root / name / "model")[0]
    return out


def traces_per_second(model, scanner: Scanner, traces: int = 4096, views: int = 64) -> float:
    """Traces per second of ``model`` on ``traces`` synthetic traces of ``views`` views."""
    gen = torch.Generator().manual_seed(1)
    b = sample_batch(scanner, 64, gen, SyntheticConfig(), views=views)
    with torch.no_grad():
        pixel, _ = model.measure_batch(b, gen)
    raw = torch.cat([pixel, b.position, b.normal_geo, b.tangent_geo], -1)  # (64, V, 12)
    raw = raw.repeat(traces // 64, 1, 1)
    tr = RaggedTraces.from_padded(raw, torch.ones(raw.shape[:2], dtype=torch.bool))
    predict_all(model, tr, max_entries=1 << 16)  # warm-up
    t0 = time.perf_counter()
    predict_all(model, tr, max_entries=1 << 16)
    return traces / (time.perf_counter() - t0)


def run(
    quick: bool = False, steps: int = 3000, json_path=None, batches: int | None = None, rate_traces: int = 4096
) -> dict:
    """Pattern comparison, losses by trace length and inference rate; printed and returned (JSON optional)."""
    scanner = load_scanner()
    pattern_batches = batches or PATTERN_BATCHES
    batches = batches or (16 if quick else 32)
    nets = _comparison_models(quick, steps)
    stats = {name: evaluate(net, scanner, None, pattern_batches) for name, net in nets.items()}
    by_pattern = {name: st["val_loss"] for name, st in stats.items()}
    vs_full_on = {
        name: paired_difference(stats[name]["val_loss_per_batch"], stats["full_on"]["val_loss_per_batch"])
        for name in ("optimized", "point")
    }
    shipped, meta = models.load(None, scanner)
    by_views = {
        str(v): evaluate(shipped, scanner, v, batches if v <= 64 else max(batches // 2, 1))["val_loss"]
        for v in (8, 16, 32, 64, 128)
    }
    rate = traces_per_second(shipped, scanner, traces=rate_traces)
    print(f"validation loss (Eq. 5) on fresh traces: {pattern_batches * 64} per pattern, {batches * 64} per view count")
    print_table(
        [
            (
                k,
                f"{v:.4f}",
                f"{stats[k]['val_valid_views']:.1%}",
                "" if k == "full_on" else f"{vs_full_on[k][0]:+.4f} ± {vs_full_on[k][1]:.4f}",
            )
            for k, v in by_pattern.items()
        ],
        ("pattern (preset small)", "val loss", "valid views", "- full-on (paired, ± s.e.)"),
    )
    print()
    print_table(
        [(k, f"{v:.4f}") for k, v in by_views.items()], (f"test views ({meta['network']['preset']})", "val loss")
    )
    print(
        f"\ninference: {rate:.0f} traces/s (64 views, {torch.get_num_threads()} threads, "
        f"preset {meta['network']['preset']})"
    )
    result = {
        "val_loss_by_pattern": by_pattern,
        "val_loss_by_test_views": by_views,
        "traces_per_s": rate,
        "valid_views_by_pattern": {k: st["val_valid_views"] for k, st in stats.items()},
        "val_loss_minus_full_on": {k: {"mean": m, "standard_error": se} for k, (m, se) in vs_full_on.items()},
        "shipped_model": meta.get("summary", {}),
        "threads": torch.get_num_threads(),
    }
    dump_json(json_path, result)
    return result


HELP = "val. loss by pattern and by test views; inference traces/s"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """``ntp bench network``'s options."""
    parser.add_argument("--quick", action="store_true", help="use the shipped comparison networks (no training)")
    parser.add_argument("--steps", type=int, default=3000, help="training steps per comparison network")
    parser.add_argument("--json", type=Path, default=None)


def command(args: argparse.Namespace) -> int:
    """``ntp bench network``: the benchmark with the command line's options; the exit code."""
    run(quick=args.quick, steps=args.steps, json_path=args.json)
    return 0
