"""``ntp bench fit``: the batched fitter against per-texel scipy L-BFGS-B, in one run, on the same
synthetic lumitexels: exact ones, and the network's predictions for the same points (the noise a
network leaves; log-space Gaussian noise if no trained model is shipped yet). Errors are compared on
the texels both methods fitted; texels/s of each from its own run.

Then the whole fit stage as the pipeline runs it (``pipeline.fit_traces``: network, geometry fit,
highlight check and RGB albedo) on synthetic 64-view traces measured through the shipped model's
sensor: texels/s and the share of each part — the geometry fit alone is not the stage's speed."""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Any

import torch

from ..fit.baseline import fit_geometry_lbfgsb
from ..fit.geometry import GeometryFit, fit_geometry, lumitexel_log_rmse
from ..learn import models
from ..learn.inference import predict
from ..learn.ragged import RaggedTraces
from ..learn.synthetic import SyntheticConfig, sample_batch
from ..pipeline.fit_traces import fit_traces
from ..pipeline.settings import TUNING as PIPELINE_TUNING
from ..scanner.device_file import load_scanner
from . import dump_json, print_table


def _cases(n: int, seed: int, chunk: int = 128) -> dict:
    """Ground truth and the two inputs for ``n`` synthetic points."""
    scanner = load_scanner()
    model, source = None, "log-normal noise sigma 0.05 (no shipped model)"
    try:
        model, meta = models.load(None, scanner)
        source = f"network '{meta['network']['preset']}' on 64-view synthetic traces"
    except Exception:  # noqa: BLE001 - the benchmark still runs before a model is shipped
        model = None
    gen = torch.Generator().manual_seed(seed)
    gt: dict[str, Any] = {k: [] for k in ("n", "t", "ax", "ay", "exact", "noisy")}
    for i in range(0, n, chunk):
        b = sample_batch(scanner, min(chunk, n - i), gen, SyntheticConfig(), views=64)
        gt["n"].append(b.params["n_local"])
        gt["t"].append(b.params["t_local"])
        gt["ax"].append(b.params["alpha_x"])
        gt["ay"].append(b.params["alpha_y"])
        gt["exact"].append(b.label_specular)
        if model is not None:
            with torch.no_grad():
                pixel, valid = model.measure_batch(b, gen)
                _, s = model(model.entries(pixel, b.position, b.normal_geo, b.tangent_geo), valid)
            gt["noisy"].append(torch.expm1(s.clamp_min(0)))
        else:
            noise = 0.05 * torch.randn(b.label_specular.shape, generator=gen)
            gt["noisy"].append(torch.expm1(torch.log1p(b.label_specular) + noise).clamp_min(0))
    out: dict[str, Any] = {k: torch.cat(v) for k, v in gt.items()}
    out["source"] = source
    return out


def _errors(fit: GeometryFit, gt: dict, inp: torch.Tensor, sel: slice) -> dict:
    n_gt, t_gt = gt["n"][sel], gt["t"][sel]
    ax_gt, ay_gt = gt["ax"][sel], gt["ay"][sel]
    swap = ay_gt > ax_gt
    b_gt = torch.linalg.cross(n_gt, t_gt, dim=-1)
    t_gt = torch.where(swap[:, None], b_gt, t_gt)
    ax_gt, ay_gt = torch.maximum(ax_gt, ay_gt), torch.minimum(ax_gt, ay_gt)
    normal_deg = torch.rad2deg(torch.acos((fit.normal[sel] * n_gt).sum(-1).clamp(-1, 1)))
    tan_deg = torch.rad2deg(torch.acos((fit.tangent[sel] * t_gt).sum(-1).abs().clamp(0, 1)))
    aniso = ax_gt > 2 * ay_gt
    ex = (fit.alpha_x[sel].log() - ax_gt.log()).abs()
    ey = (fit.alpha_y[sel].log() - ay_gt.log()).abs()
    sub = fit.rows(sel)
    rmse_in = lumitexel_log_rmse(sub, inp[sel])
    rmse_gt = lumitexel_log_rmse(sub, gt["exact"][sel])
    return {
        "lumitexel_log_rmse": float(rmse_in.mean()),
        "lumitexel_log_rmse_vs_truth": float(rmse_gt.mean()),
        "normal_deg_median": float(normal_deg.median()),
        "normal_deg_p90": float(normal_deg.quantile(0.9)),
        "tangent_deg_median_anisotropic": float(tan_deg[aniso].median()) if aniso.any() else float("nan"),
        "alpha_x_log_err_median": float(ex.median()),
        "alpha_y_log_err_median": float(ey.median()),
        "flagged": int((fit.flags[sel] != 0).sum()),
    }


def whole_fit(texels: int, seed: int, chunk: int = 256) -> dict:
    """The fit stage (``fit_traces``) on ``texels`` synthetic 64-view traces: texels/s and the
    seconds of network, geometry fit and highlight check + albedo."""
    scanner = load_scanner()
    net, meta = models.load(None, scanner)
    gen = torch.Generator().manual_seed(seed)
    entries, masks = [], []
    for i in range(0, texels, chunk):
        b = sample_batch(scanner, min(chunk, texels - i), gen, SyntheticConfig(), views=64)
        with torch.no_grad():
            pixel, valid = net.measure_batch(b, gen)
        entries.append(torch.cat([pixel, b.position, b.normal_geo, b.tangent_geo], -1))
        masks.append(valid)
    traces = RaggedTraces.from_padded(torch.cat(entries), torch.cat(masks))
    fit_traces(net, scanner, traces.block(0, min(64, texels)), 1.0)  # warm-up (allocator, the compiled loop)
    seconds: dict[str, float] = {}
    t0 = time.perf_counter()
    fit_traces(net, scanner, traces, 1.0, seconds=seconds)
    total = time.perf_counter() - t0
    return {
        "texels": texels,
        "model": meta["network"]["preset"],
        "texels_per_s": texels / total,
        "seconds": {"total": total, **seconds},
        "share": {k: v / total for k, v in seconds.items()},
        "specular_basis": _compressed_vs_exact(net, meta, scanner, traces),
    }


def _compressed_vs_exact(net, meta: dict, scanner, traces: RaggedTraces) -> dict | None:
    """The network with its compressed specular head (``models.specular_basis``) against the full
    layer on the same traces: seconds of each (best of two, alternating) and the log1p error."""
    if meta["specular_basis"] is None:
        return None
    exact, _ = models.load(meta["folder"], scanner, exact=True)
    best = {"exact": float("inf"), "compressed": float("inf")}
    out = {}
    for _ in range(2):
        for name, model in (("exact", exact), ("compressed", net)):
            t0 = time.perf_counter()
            out[name] = torch.cat(
                [s for _, _, s in predict(model, traces, max_views=PIPELINE_TUNING.fit.network_views)]
            )
            best[name] = min(best[name], time.perf_counter() - t0)
    err = (torch.log1p(out["compressed"]) - torch.log1p(out["exact"])).abs()
    return {
        "rank": meta["specular_basis"],
        "seconds": best,
        "speedup": best["exact"] / best["compressed"],
        "log1p_error_max": float(err.max()),
        "log1p_error_mean": float(err.mean()),
    }


def run(
    quick: bool = False, texels: int | None = None, baseline_texels: int | None = None, seed: int = 7, json_path=None
) -> dict:
    """Fit ``texels`` synthetic lumitexels batched and ``baseline_texels`` by L-BFGS-B; print and return both."""
    texels = texels or (2048 if quick else 16384)
    baseline_texels = baseline_texels or (32 if quick else 192)
    gt = _cases(texels, seed)
    print(f"ntp bench fit: {texels} texels batched, {baseline_texels} by the baseline; noisy input: {gt['source']}")
    result: dict = {"texels": texels, "baseline_texels": baseline_texels, "noise_source": gt["source"]}
    common = slice(0, baseline_texels)
    rows = []
    for kind in ("exact", "noisy"):
        inp = gt[kind]
        fit_geometry(inp[:64])  # warm-up (allocator, lazy tables)
        t0 = time.perf_counter()
        batched = fit_geometry(inp)
        t_b = time.perf_counter() - t0
        t0 = time.perf_counter()
        base = fit_geometry_lbfgsb(inp[common])
        t_l = time.perf_counter() - t0
        eb = {"texels_per_s": texels / t_b, **_errors(batched, gt, inp, common)}
        eb["all_texels"] = _errors(batched, gt, inp, slice(0, texels))
        el = {"texels_per_s": baseline_texels / t_l, **_errors(base, gt, inp, common)}
        result[kind] = {"batched": eb, "baseline": el, "speedup": eb["texels_per_s"] / el["texels_per_s"]}
        for name, e in (("batched", eb), ("baseline", el)):
            rows.append(
                (
                    kind,
                    name,
                    f"{e['texels_per_s']:.0f}",
                    f"{e['lumitexel_log_rmse']:.2e}",
                    f"{e['lumitexel_log_rmse_vs_truth']:.2e}",
                    f"{e['normal_deg_median']:.3f}",
                    f"{e['normal_deg_p90']:.3f}",
                    f"{e['alpha_x_log_err_median']:.3f}",
                    f"{e['alpha_y_log_err_median']:.3f}",
                    f"{e['tangent_deg_median_anisotropic']:.2f}",
                )
            )
    print_table(
        rows,
        (
            "input",
            "method",
            "texels/s",
            "log-RMSE",
            "log-RMSE vs truth",
            "normal med deg",
            "normal p90",
            "|dlog ax|",
            "|dlog ay|",
            "tangent deg (aniso)",
        ),
    )
    for kind in ("exact", "noisy"):
        print(f"{kind}: batched is {result[kind]['speedup']:.0f}x the baseline's texels/s")
    whole = whole_fit(min(texels, 4096), seed)
    result["whole_fit"] = whole
    split = ", ".join(f"{k} {100 * v:.0f}%" for k, v in whole["share"].items())
    print(
        f"whole fit stage (network + geometry + highlight check + albedo, pipeline.fit_traces) on "
        f"{whole['texels']} 64-view traces: {whole['texels_per_s']:.0f} texels/s ({split}); the geometry "
        f"fit alone on the network's lumitexels: {result['noisy']['batched']['texels_per_s']:.0f} texels/s"
    )
    sb = whole["specular_basis"]
    if sb:
        print(
            f"network, specular head compressed to {sb['rank']} directions: {sb['seconds']['compressed']:.2f} s "
            f"vs {sb['seconds']['exact']:.2f} s exact (x{sb['speedup']:.2f}); log1p lumitexel error max "
            f"{sb['log1p_error_max']:.4f}, mean {sb['log1p_error_mean']:.5f}"
        )
    # the keys: batched/baseline with texels_per_s and lumitexel_log_rmse (exact input),
    # the noisy-input figures beside them
    for name in ("batched", "baseline"):
        result[name] = {
            "texels_per_s": result["exact"][name]["texels_per_s"],
            "lumitexel_log_rmse": result["exact"][name]["lumitexel_log_rmse"],
            "texels_per_s_noisy": result["noisy"][name]["texels_per_s"],
            "lumitexel_log_rmse_noisy": result["noisy"][name]["lumitexel_log_rmse"],
        }
    dump_json(json_path, result)
    return result


HELP = "batched GGX fitter vs per-texel scipy L-BFGS-B (speed and error)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """``ntp bench fit``'s options."""
    parser.add_argument("--quick", action="store_true", help="2048 texels (baseline on 32) instead of 16384 (192)")
    parser.add_argument("--texels", type=int, default=None)
    parser.add_argument("--baseline-texels", type=int, default=None)
    parser.add_argument("--json", type=Path, default=None)


def command(args: argparse.Namespace) -> int:
    """``ntp bench fit``: the benchmark with the command line's options; the exit code."""
    run(quick=args.quick, texels=args.texels, baseline_texels=args.baseline_texels, json_path=args.json)
    return 0
