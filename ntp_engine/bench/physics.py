"""``ntp bench physics``: throughput of the forward model on this machine, float32 vs float64."""

from __future__ import annotations

import argparse
import math
from pathlib import Path
from typing import Any

import torch

from ..physics.brdf import ggx
from ..physics.lumitexel import render_lumitexels
from ..physics.measurement import measure, physical_lumitexel
from ..scanner.device_file import load_scanner
from . import dump_json, print_table, timed


def _brdf_inputs(n: int, dtype, gen) -> tuple:
    wi = torch.nn.functional.normalize(torch.randn(n, 3, generator=gen, dtype=torch.float64), dim=-1)
    wo = torch.nn.functional.normalize(torch.randn(n, 3, generator=gen, dtype=torch.float64), dim=-1)
    wi[:, 2], wo[:, 2] = wi[:, 2].abs(), wo[:, 2].abs()
    a = torch.exp(math.log(0.006) + math.log(0.5 / 0.006) * torch.rand(2, n, generator=gen, dtype=torch.float64))
    rho = torch.rand(2, n, 3, generator=gen, dtype=torch.float64)
    return tuple(v.to(dtype) for v in (wi, wo, rho[0], 10 * rho[1], a[0], a[1]))


def _frames(n: int, dtype, gen) -> tuple:
    nrm = torch.nn.functional.normalize(
        torch.randn(n, 3, generator=gen, dtype=torch.float64) * 0.2 + torch.tensor([0, 0, 1.0], dtype=torch.float64),
        dim=-1,
    )
    t = torch.randn(n, 3, generator=gen, dtype=torch.float64)
    return nrm.to(dtype), t.to(dtype)


def run(brdf_batch: int = 1 << 20, lumitexel_batch: int = 256, point_batch: int = 1024, json_path=None) -> dict:
    """BRDF evaluations, lumitexels and measurements per second in float32 and float64; printed and returned."""
    gen = torch.Generator().manual_seed(0)
    scanner = load_scanner()
    rows: list[tuple] = []
    result: dict[str, Any] = {"threads": torch.get_num_threads()}
    for dtype in (torch.float32, torch.float64):
        name = str(dtype).replace("torch.", "")
        args = _brdf_inputs(brdf_batch, dtype, gen)
        t_brdf = timed(lambda: ggx(*args))
        n, t = _frames(lumitexel_batch, dtype, gen)
        rd, rs = torch.rand(2, lumitexel_batch, 1, generator=gen, dtype=torch.float64).to(dtype)
        ax, ay = torch.full((2, lumitexel_batch), 0.1, dtype=dtype)
        t_lumi = timed(lambda: render_lumitexels(n, t, rd, 10 * rs, ax, ay))
        x = torch.as_tensor(scanner.valid_center, dtype=dtype).expand(point_batch, 3).clone()
        x = x + 0.05 * torch.randn(point_batch, 3, generator=gen, dtype=torch.float64).to(dtype)
        nc, tc = _frames(point_batch, dtype, gen)
        nc = -nc  # facing the camera (camera space z points away from it)
        r3 = torch.rand(point_batch, 3, generator=gen, dtype=torch.float64).to(dtype)
        a3 = torch.full((point_batch,), 0.1, dtype=dtype)
        t_meas = timed(lambda: measure(scanner, physical_lumitexel(scanner, x, nc, tc, r3, r3, a3, a3)))
        r = {
            "brdf_evals_per_s": brdf_batch / t_brdf,
            "lumitexels_per_s": lumitexel_batch / t_lumi,
            "measurements_per_s": point_batch / t_meas,
        }
        result[name] = r
        rows.append(
            (
                name,
                f"{r['brdf_evals_per_s'] / 1e6:.1f} M",
                f"{r['lumitexels_per_s']:.0f}",
                f"{r['measurements_per_s']:.0f}",
            )
        )
    print(
        f"physics throughput ({result['threads']} threads; lumitexel = diffuse 384 + specular 6144 lights; "
        f"measurement = one point under the {scanner.num_emitters}-LED default device, RGB)"
    )
    print_table(rows, ("dtype", "BRDF evals/s", "lumitexels/s", "measurements/s"))
    dump_json(json_path, result)
    return result


HELP = "BRDF evaluations/s, lumitexels/s, measurements/s (f32 vs f64)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """``ntp bench physics``'s options."""
    parser.add_argument("--json", type=Path, default=None)


def command(args: argparse.Namespace) -> int:
    """``ntp bench physics``: the benchmark with the command line's options; the exit code."""
    run(json_path=args.json)
    return 0
