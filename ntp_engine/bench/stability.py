"""``ntp bench stability``: the BRDF's values and gradients in float32 over random and adversarial
inputs; counts non-finite or negative results (must be 0) and the error against float64 evaluated
on the very same (float32-rounded) inputs."""

from __future__ import annotations

import argparse
import math
import time
from pathlib import Path
from typing import Any

import torch
from tqdm import tqdm

from ..physics.brdf import ALPHA_MAX, ALPHA_MIN, RHO_S_MAX, ggx
from ..physics.frame import reflect
from . import dump_json, print_table

CASES = (
    "random",
    "grazing_z0",
    "near_grazing",
    "below_horizon",
    "mirror_peak",
    "wi_eq_wo",
    "wi_opposite_wo",
    "alpha_bounds",
)


def _unit(v: torch.Tensor) -> torch.Tensor:
    return v / v.norm(dim=-1, keepdim=True)


def sample(case: str, n: int, gen: torch.Generator) -> dict[str, torch.Tensor]:
    """``n`` float64 inputs of one case (later rounded to float32)."""
    f64: dict[str, Any] = dict(dtype=torch.float64, generator=gen)
    wi, wo = _unit(torch.randn(n, 3, **f64)), _unit(torch.randn(n, 3, **f64))
    wo[:, 2] = wo[:, 2].abs()
    wo = _unit(wo)
    la, lb = math.log(ALPHA_MIN), math.log(ALPHA_MAX)
    ax = torch.exp(la + (lb - la) * torch.rand(n, **f64))
    ay = torch.exp(la + (lb - la) * torch.rand(n, **f64))
    if case == "grazing_z0":
        which = torch.randint(0, 3, (n,), generator=gen)
        wi[which != 1, 2] = 0.0
        wo[which != 0, 2] = 0.0
        wi, wo = _unit(wi), _unit(wo)
    elif case == "near_grazing":
        z = 10 ** (-8 + 5 * torch.rand(n, **f64))
        sgn = torch.where(torch.rand(n, **f64) < 0.5, -1.0, 1.0).to(torch.float64)
        wi[:, 2] = sgn * z
        wo[:, 2] = 10 ** (-8 + 5 * torch.rand(n, **f64))
        wi, wo = _unit(wi), _unit(wo)
    elif case == "below_horizon":
        wi[:, 2] = -wi[:, 2].abs()
        wo[:, 2] = torch.where(torch.rand(n, **f64) < 0.5, -wo[:, 2], wo[:, 2])
    elif case == "mirror_peak":
        h = _unit(torch.cat([1e-3 * torch.randn(n, 2, **f64), torch.ones(n, 1, dtype=torch.float64)], -1))
        wi = reflect(wo, h)
        ax = torch.where(torch.rand(n, **f64) < 0.5, torch.full_like(ax, ALPHA_MIN), ax)
    elif case == "wi_eq_wo":
        wi = wo.clone()
    elif case == "wi_opposite_wo":
        # opposite in the tangent plane, on or just above the horizon: wi + wo ~ 0
        z = torch.where(torch.rand(n, **f64) < 0.5, 0.0, 1e-7).to(torch.float64)
        wo = _unit(torch.cat([wo[:, :2], z[:, None]], -1))
        wi = torch.cat([-wo[:, :2], wo[:, 2:]], -1)
    elif case == "alpha_bounds":
        choice = torch.tensor([ALPHA_MIN, ALPHA_MAX], dtype=torch.float64)
        ax = choice[torch.randint(0, 2, (n,), generator=gen)]
        ay = choice[torch.randint(0, 2, (n,), generator=gen)]
    rho_d = torch.rand(n, 3, **f64)
    rho_s = RHO_S_MAX * torch.rand(n, 3, **f64)
    return dict(wi=wi, wo=wo, rho_d=rho_d, rho_s=rho_s, alpha_x=ax, alpha_y=ay)


def _eval(inputs: dict[str, torch.Tensor], dtype) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
    leaves = {k: v.to(dtype).detach().requires_grad_(True) for k, v in inputs.items()}
    f = ggx(**leaves)
    f.sum().backward()
    return f.detach(), {k: v.grad for k, v in leaves.items() if v.grad is not None}


def run(samples: int = 10_000_000, batch: int = 500_000, seed: int = 0, json_path=None) -> dict:
    """GGX float32 values and gradients against float64 on ``samples`` inputs over every case; printed and returned."""
    gen = torch.Generator().manual_seed(seed)
    per_case = {
        c: dict(
            samples=0, nonfinite_values=0, negative_values=0, nonfinite_grads=0, max_rel_err=0.0, max_grad_rel_err=0.0
        )
        for c in CASES
    }
    t0 = time.perf_counter()
    batch = min(batch, max(1, math.ceil(samples / len(CASES))))  # every case runs, even in small runs
    n_batches = math.ceil(samples / batch)
    for b in tqdm(range(n_batches), desc="stability", unit="batch"):
        case = CASES[b % len(CASES)]
        n = min(batch, samples - b * batch)
        x32 = {k: v.to(torch.float32) for k, v in sample(case, n, gen).items()}
        f32, g32 = _eval(x32, torch.float32)
        f64, g64 = _eval(x32, torch.float64)  # the same rounded inputs in float64
        s = per_case[case]
        s["samples"] += n
        s["nonfinite_values"] += int((~torch.isfinite(f32)).sum())
        s["negative_values"] += int((f32 < 0).sum())
        s["nonfinite_grads"] += int(sum((~torch.isfinite(g)).sum() for g in g32.values()))
        rel = (f32.double() - f64).abs() / f64.abs().clamp_min(1e-30)
        rel = torch.where(f64 == 0, (f32 != 0).double(), rel)
        s["max_rel_err"] = max(s["max_rel_err"], float(rel.max()))
        # per-sample relative error of the whole gradient vector (all inputs)
        gv32 = torch.cat([g32[k].double().reshape(n, -1) for k in g32], -1)
        gv64 = torch.cat([g64[k].reshape(n, -1) for k in g64], -1)
        gerr = (gv32 - gv64).norm(dim=-1) / gv64.norm(dim=-1).clamp_min(1e-30)
        gerr = torch.where(gv64.norm(dim=-1) == 0, (gv32.norm(dim=-1) != 0).double(), gerr)
        s["max_grad_rel_err"] = max(s["max_grad_rel_err"], float(gerr.max()))
    seconds = time.perf_counter() - t0
    total = {
        k: sum(s[k] for s in per_case.values())
        for k in ("samples", "nonfinite_values", "negative_values", "nonfinite_grads")
    }
    total["max_rel_err"] = max(s["max_rel_err"] for s in per_case.values())
    total["max_grad_rel_err"] = max(s["max_grad_rel_err"] for s in per_case.values())
    rows: list[tuple] = [
        (
            c,
            s["samples"],
            s["nonfinite_values"],
            s["negative_values"],
            s["nonfinite_grads"],
            f"{s['max_rel_err']:.2e}",
            f"{s['max_grad_rel_err']:.2e}",
        )
        for c, s in per_case.items()
    ]
    rows.append(
        (
            "TOTAL",
            *(total[k] for k in ("samples", "nonfinite_values", "negative_values", "nonfinite_grads")),
            f"{total['max_rel_err']:.2e}",
            f"{total['max_grad_rel_err']:.2e}",
        )
    )
    print(
        f"GGX float32 stability: {total['samples']:,} samples in {seconds:.1f} s (error vs float64 on the same inputs)"
    )
    print_table(
        rows, ("case", "samples", "nonfinite f", "negative f", "nonfinite grad", "max rel err f", "max rel err grad")
    )
    result = {
        "samples": total["samples"],
        "nonfinite": total["nonfinite_values"] + total["nonfinite_grads"],
        "total": total,
        "cases": per_case,
        "seconds": seconds,
    }
    dump_json(json_path, result)
    return result


HELP = "GGX float32 values/gradients vs float64 over >= 1e7 samples"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """``ntp bench stability``'s options."""
    parser.add_argument("--samples", type=int, default=10_000_000)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--json", type=Path, default=None)


def command(args: argparse.Namespace) -> int:
    """``ntp bench stability``: the benchmark with the command line's options; the exit code."""
    r = run(samples=args.samples, seed=args.seed, json_path=args.json)
    return 1 if r["nonfinite"] or r["total"]["negative_values"] else 0
