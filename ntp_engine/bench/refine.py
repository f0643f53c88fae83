"""``ntp bench refine``: the analysis-by-synthesis refinement's error against its time, on the gallery.

Per gallery scan (true poses; the dome is the demo's object), a seeded sample of observed texels per
material starts from the network's fit (``reconstruct``'s cache) and is refined with a ladder of
budgets (``VARIANTS``: rounds x LM iterations, the first round being the multi-start), with and
without the weak priors; errors against the truth per material (``sim.evaluate.parameter_errors``)
and texels per second. Baseline in the same run: scipy's ``least_squares`` per texel on the same
objective (every emitter sample summed exactly, the same residuals, censoring, Cauchy loss, bounds
and priors, finite-difference Jacobians) from the same start, on a few texels per scan: its
seconds per texel and its errors beside ours on those texels.
"""

from __future__ import annotations

import argparse
import json
import math
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np
import torch
from scipy.optimize import least_squares

from ..fit.texel_fit import TexelFit
from ..io.atomic import write_text_atomic
from ..io.maps import SVBRDFMaps
from ..io.mesh import load_mesh
from ..io.output_folder import claim
from ..io.progress import QUIET, Progress, add_progress_arguments, progress_from_args
from ..io.texels import Texels, rasterize
from ..physics.brdf import ALPHA_MAX, ALPHA_MIN
from ..physics.frame import frame_from_normal_tangent
from ..pipeline.stages import cached_fit, reconstruct
from ..refine.footprint import Footprint
from ..refine.inputs import refine_inputs
from ..refine.model import P_LOGA, P_OMEGA, Observations, Round, Start, Trace, fold, residuals
from ..refine.policy import calibrated, refine
from ..refine.priors import normal_prior, prior_normal_in
from ..refine.settings import RefineSettings, SensorNoise
from ..scanner.scan_folder import load_scan
from ..scanner.scanner import Scanner
from ..sim.evaluate import parameter_errors, truth_at_texels
from ..sim.gallery import GALLERY, build_asset, object_set
from ..sim.materials import load_labels
from . import gallery as bench_gallery
from . import tune_validate

# (label, settings): the ladder of budgets; "priors off" drops the weak normal and alpha priors
VARIANTS: tuple[tuple[str, RefineSettings], ...] = (
    ("1 LM iteration", RefineSettings(rounds=1, iterations=1, starts=False)),
    ("2 LM iterations", RefineSettings(rounds=1, iterations=2, starts=False)),
    ("5 (multi-start 3 + 2)", RefineSettings(rounds=2, iterations=2)),
    ("9 (default: 3 rounds x 3)", RefineSettings()),
    ("default, priors off", RefineSettings(log_alpha_prior_sigma=1e6, normal_prior_deg=1e6)),
    ("12 (4 rounds x 3)", RefineSettings(rounds=4)),
)
DEFAULT_LABEL = "9 (default: 3 rounds x 3)"


@dataclass
class RefineBench:
    """What one run covers: gallery scans (made with ``gallery``'s settings), texels sampled per material."""

    gallery: bench_gallery.GallerySettings = bench_gallery.DEFAULT
    objects: tuple[str, ...] = tuple(GALLERY)
    scanners: tuple[str, ...] = bench_gallery.SCANNERS
    per_material: int = 128  # sampled texels per material and scan
    baseline_texels: int = 6  # texels per scan for the scipy baseline
    seed: int = 0


def _truth_in_texel_frames(tex: Texels, scan_dir: Path) -> tuple[dict, np.ndarray, list[dict], np.ndarray]:
    """The truth at the centre of every texel of ``tex`` (``truth_at_texels``), its labels and the
    texels' geometric frames (rows t^, b^, n^)."""
    uv = tex.uv
    gt = scan_dir / "ground_truth"
    labels, table = load_labels(gt)
    true, label = truth_at_texels(SVBRDFMaps.load(gt), labels, uv)
    frame = np.stack([tex.tangent, np.cross(tex.normal, tex.tangent), tex.normal], 1)
    return true, label, table, frame


def _as_maps(frame: np.ndarray, n_loc, t_loc, alpha, rho_d, rho_s) -> dict[str, np.ndarray]:
    """Per-texel parameters (geometric frame) as object-space map values."""
    return {
        "normal": np.einsum("tji,tj->ti", frame, n_loc),
        "tangent": np.einsum("tji,tj->ti", frame, t_loc),
        "roughness": alpha,
        "diffuse_albedo": rho_d,
        "specular_albedo": rho_s,
    }


def run(out: Path, bench: RefineBench | None = None, json_path: Path | None = None, progress: Progress = QUIET) -> dict:
    """The benchmark into ``out`` (the gallery's folder: scans are shared, built if missing)."""
    bench = bench or RefineBench()
    settings = bench.gallery
    out = Path(out)
    rows, speed, baseline = [], [], []
    rng = np.random.default_rng(bench.seed)
    with claim(out, "gallery"):
        for name in bench.objects:
            asset = build_asset(name, out / "assets" / name)
            for scanner in bench.scanners:
                scan_dir = bench_gallery.scan_folder(out, settings, name, scanner)
                bench_gallery.scan_object(settings, name, scanner, scan_dir, asset, progress)
                result = bench_gallery.result_folder(out, settings, name, scanner, "true", settings.views)
                scan = load_scan(scan_dir, scan_dir / "ground_truth" / "poses.json")
                reconstruct(scan, result, resolution=settings.resolution, progress=progress)
                traces, fit = cached_fit(result)
                res = (settings.resolution, settings.resolution)
                texels = rasterize(load_mesh(result / "mesh.obj"), res, curvature=True)
                true, label, table, frame = _truth_in_texel_frames(texels, scan_dir)
                observed = traces.lengths.numpy() > 0
                picks = []
                for k in range(len(table)):
                    cand = np.nonzero((label == k) & observed)[0]
                    picks.append(np.sort(rng.choice(cand, min(bench.per_material, len(cand)), replace=False)))
                sel = np.concatenate(picks)
                # the cache holds pixels as captured
                inp = refine_inputs(scan.scanner, traces, torch.as_tensor(sel), fit, None, texels)
                obs, start, specular = inp.obs, inp.start, inp.specular
                ent, mask, footprint = obs.entries, obs.mask, obs.footprint
                assert obs.shadow is not None  # refine_inputs reads every entry's shadow
                shadow = obs.shadow
                tuned = calibrated(obs, start, specular, RefineSettings())
                noise = tuned.noise
                answers = {
                    "network + fit": (
                        fit.n_loc[sel],
                        fit.t_loc[sel],
                        fit.alpha[sel],
                        fit.rho_d[sel],
                        fit.rho_s[sel],
                    )
                }
                for label_v, st in VARIANTS:
                    st = replace(st, noise=noise, normal_prior_at_mesh=tuned.normal_prior_at_mesh)
                    t0 = time.perf_counter()
                    r = refine(obs, start, specular, st)
                    seconds = time.perf_counter() - t0
                    speed.append(
                        {
                            "noise_scale": noise.relative / SensorNoise().relative,
                            "object": name,
                            "scanner": scanner,
                            "variant": label_v,
                            "texels": len(sel),
                            "texels_per_s": len(sel) / seconds,
                        }
                    )
                    answers[label_v] = (
                        r.frame[:, 2].numpy(),
                        r.frame[:, 0].numpy(),
                        r.log_alpha.exp().numpy(),
                        r.rho_d.numpy(),
                        r.rho_s.numpy(),
                    )
                offset = 0
                for k, mat in enumerate(table):
                    n_k = len(picks[k])
                    part = slice(offset, offset + n_k)
                    offset += n_k
                    if n_k == 0:
                        continue
                    truth = {key: v[picks[k]] for key, v in true.items()}
                    for label_v, ans in answers.items():
                        rec = _as_maps(frame[picks[k]], *(a[part] for a in ans))
                        rows.append(
                            {
                                "object": name,
                                "set": object_set(name),
                                "scanner": scanner,
                                "material": mat["name"],
                                "kind": mat.get("kind"),
                                "variant": label_v,
                                "texels": n_k,
                                **parameter_errors(rec, truth, mat["matte"]),
                            }
                        )
                baseline.append(
                    _baseline(
                        tuned, scan.scanner, ent, mask, shadow, footprint, fit, sel, specular, frame, true, bench, rng
                    )
                )
    record = {"bench": asdict(bench), "rows": rows, "speed": speed, "baseline": baseline}
    text = markdown(record)
    write_text_atomic(out / "refine.md", text)
    write_text_atomic(out / "refine.json", json.dumps(record, indent=1, default=float))
    if json_path:
        write_text_atomic(json_path, json.dumps(record, indent=1, default=float))
    print(text)
    return record


def _baseline(
    tuned: RefineSettings,
    scanner: Scanner,
    ent: torch.Tensor,
    mask: torch.Tensor,
    shadow: torch.Tensor,
    footprint: Footprint | None,
    fit: TexelFit,
    sel: np.ndarray,
    specular: torch.Tensor,
    frame: np.ndarray,
    true: dict[str, np.ndarray],
    bench: RefineBench,
    rng: np.random.Generator,
) -> dict:
    """scipy least_squares per texel (exact model) on ``bench.baseline_texels`` sampled texels with a
    lobe; seconds per texel for it and for ours on the same texels, and both answers' errors."""
    spec_idx = np.nonzero(specular.numpy())[0]
    pick = np.sort(rng.choice(spec_idx, min(bench.baseline_texels, len(spec_idx)), replace=False))
    if len(pick) == 0:
        return {}
    st = RefineSettings(noise=tuned.noise, normal_prior_at_mesh=tuned.normal_prior_at_mesh)
    sub_ent, sub_mask = ent[pick].double(), mask[pick]
    idx = sel[pick]
    t0 = time.perf_counter()
    lobe = torch.ones(len(pick), dtype=torch.bool)
    spread = None if footprint is None else footprint.rows(pick)
    obs = Observations(scanner, ent[pick], mask[pick], shadow[pick], None, spread)
    ours = refine(obs, Start.from_fit(fit, idx), lobe, st)
    t_ours = (time.perf_counter() - t0) / len(pick)
    t0 = time.perf_counter()
    res = [
        _scipy_texel(
            scanner,
            sub_ent[i : i + 1],
            sub_mask[i : i + 1],
            shadow[pick[i : i + 1]],
            {k: getattr(fit, k)[idx[i : i + 1]] for k in ("n_loc", "t_loc", "alpha", "rho_d", "rho_s")},
            st,
            None if spread is None else spread.rows(slice(i, i + 1)),
        )
        for i in range(len(pick))
    ]
    t_scipy = (time.perf_counter() - t0) / len(pick)
    truth = {key: v[idx] for key, v in true.items()}
    mine = _as_maps(
        frame[idx],
        ours.frame[:, 2].numpy(),
        ours.frame[:, 0].numpy(),
        ours.log_alpha.exp().numpy(),
        ours.rho_d.numpy(),
        ours.rho_s.numpy(),
    )
    theirs = _as_maps(frame[idx], *(np.concatenate([r[j] for r in res]) for j in range(5)))
    matte = False
    return {
        "texels": len(pick),
        "seconds_per_texel_ours": t_ours,
        "seconds_per_texel_scipy": t_scipy,
        "speed_ratio": t_scipy / max(t_ours, 1e-12),
        "ours": parameter_errors(mine, truth, matte),
        "scipy": parameter_errors(theirs, truth, matte),
        "cost_ours": float(ours.cost.mean()),
        "cost_scipy": float(np.mean([r[5] for r in res])),
    }


def _scipy_texel(
    scanner,
    ent: torch.Tensor,
    mask: torch.Tensor,
    shadow: torch.Tensor,
    start: dict,
    st: RefineSettings,
    footprint: Footprint | None = None,
) -> tuple:
    """One texel by scipy least_squares on the refinement's objective with every sample exact."""
    tr = Trace(scanner, ent, mask, st.noise, None, shadow, None, footprint)  # no blocks: every sample exact
    frame0 = frame_from_normal_tangent(torch.as_tensor(start["n_loc"]), torch.as_tensor(start["t_loc"]))
    la0 = torch.as_tensor(np.log(np.clip(start["alpha"], ALPHA_MIN, ALPHA_MAX)))
    rnd = Round(tr, frame0, la0, True)
    c, sa, sn = st.noise.robust, st.log_alpha_prior_sigma, math.radians(st.normal_prior_deg)
    n_prior = normal_prior(frame0, st)

    def fun(x: np.ndarray) -> np.ndarray:
        q = torch.as_tensor(x)[None]
        d, s = rnd.bases(q[:, P_OMEGA], q[:, P_LOGA])
        r, _ = residuals(tr, d, s, q)
        u = prior_normal_in(fold(frame0, q[:, P_OMEGA]), n_prior)
        return np.concatenate([r.flatten().numpy(), ((q[0, P_LOGA] - la0[0]) / sa).numpy(), (u[0, :2] / sn).numpy()])

    x0 = np.concatenate(
        [[0, 0, 0], la0[0].numpy(), np.clip(start["rho_d"][0], 0, 1), np.clip(start["rho_s"][0], 0, 10)]
    )
    lo = np.array([-np.pi] * 3 + [math.log(ALPHA_MIN)] * 2 + [0] * 6)
    hi = np.array([np.pi] * 3 + [math.log(ALPHA_MAX)] * 2 + [1] * 3 + [10] * 3)
    x0 = np.clip(x0, lo + 1e-9, hi - 1e-9)
    # the data residuals get the Cauchy loss, the priors too (scipy applies one loss to all): a priori
    # small, so the difference is negligible
    sol = least_squares(fun, x0, bounds=(lo, hi), loss="cauchy", f_scale=c, x_scale="jac", max_nfev=400)
    q = torch.as_tensor(sol.x)[None]
    frame = fold(frame0, q[:, P_OMEGA])
    a = np.exp(sol.x[3:5])[None]
    return frame[:, 2].numpy(), frame[:, 0].numpy(), a, sol.x[5:8][None], sol.x[8:11][None], float(sol.cost)


def markdown(record: dict) -> str:
    """The tables: errors per object x scanner x material x variant, speed, and the baseline."""
    metrics = ("normal_deg", "tangent_deg", "log_alpha", "log_rho_s", "rho_d_rmse", "spurious_lobe")
    lines = [
        "| object | scanner | material | variant | " + " | ".join(metrics) + " |",
        "|" + "---|" * (4 + len(metrics)),
    ]
    for r in record["rows"]:
        vals = [
            ("-" if (v := r.get(m)) is None or (isinstance(v, float) and math.isnan(v)) else f"{v:.3g}")
            for m in metrics
        ]
        lines.append(
            f"| {r['object']} | {r['scanner']} | {r['material']} | {r['variant']} | " + " | ".join(vals) + " |"
        )
    lines += ["", *_set_lines(record["rows"], metrics)]
    lines += ["", "| object | scanner | noise scale | variant | texels | texels/s |", "|---|---|---|---|---|---|"]
    for s in record["speed"]:
        lines.append(
            f"| {s['object']} | {s['scanner']} | {s['noise_scale']:.2f} | {s['variant']} | {s['texels']} "
            f"| {s['texels_per_s']:.0f} |"
        )
    lines += [
        "",
        "| object | scanner | texels | s/texel ours | s/texel scipy | ratio | normal ours / scipy "
        "| log alpha ours / scipy | cost ours / scipy |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for (o, sc), b in zip(((r["object"], r["scanner"]) for r in _scans(record)), record["baseline"]):
        if not b:
            continue
        lines.append(
            f"| {o} | {sc} | {b['texels']} | {b['seconds_per_texel_ours']:.3f} | {b['seconds_per_texel_scipy']:.2f} | "
            f"{b['speed_ratio']:.0f}x | {b['ours']['normal_deg']:.2f} / {b['scipy']['normal_deg']:.2f} | "
            f"{b['ours']['log_alpha']:.2f} / {b['scipy']['log_alpha']:.2f} | "
            f"{b['cost_ours']:.1f} / {b['cost_scipy']:.1f} |"
        )
    return "\n".join(lines) + "\n"


def _set_lines(rows: list[dict], metrics: tuple[str, ...]) -> list[str]:
    """Per variant x material kind: each metric's mean on the tuning set / the validation set (gap)."""
    groups: dict[tuple, dict[str, list[dict]]] = {}
    for r in rows:
        groups.setdefault((r["variant"], r.get("kind") or "?"), {"tune": [], "validate": []})[
            r.get("set", "tune")
        ].append(r)
    lines = [
        "| variant | kind | materials tune / validate | " + " | ".join(metrics) + " |",
        "|" + "---|" * (3 + len(metrics)),
    ]
    for (variant, kind), by_set in sorted(groups.items()):
        cols = [tune_validate(*([r.get(m) for r in by_set[s]] for s in ("tune", "validate"))) for m in metrics]
        lines.append(
            f"| {variant} | {kind} | {len(by_set['tune'])} / {len(by_set['validate'])} | " + " | ".join(cols) + " |"
        )
    return lines


def _scans(record: dict) -> list[dict]:
    seen, out = set(), []
    for s in record["speed"]:
        if (s["object"], s["scanner"]) not in seen:
            seen.add((s["object"], s["scanner"]))
            out.append(s)
    return out


def bench_for(**overrides) -> RefineBench:
    """The default bench with the given fields replaced (None leaves a field)."""
    return replace(RefineBench(), **{k: v for k, v in overrides.items() if v is not None})


HELP = "refinement error against time per material, and a scipy baseline"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """``ntp bench refine``'s options."""
    parser.add_argument("--out", type=Path, default=Path("ntp_gallery"), help="the gallery's folder (scans shared)")
    bench_gallery.add_object_arguments(parser)
    bench_gallery.add_scanner_arguments(parser)
    bench_gallery.add_mesh_argument(parser)
    parser.add_argument("--per-material", type=int, default=None, help="sampled texels per material and scan")
    parser.add_argument("--baseline-texels", type=int, default=None, help="texels per scan for the scipy baseline")
    parser.add_argument("--json", type=Path, default=None)
    add_progress_arguments(parser)


def command(args: argparse.Namespace) -> int:
    """``ntp bench refine``: the benchmark with the command line's options; the exit code."""
    bench = bench_for(
        objects=bench_gallery.chosen_objects(args),
        scanners=bench_gallery.chosen_scanners(args),
        per_material=args.per_material,
        baseline_texels=args.baseline_texels,
        gallery=replace(bench_gallery.DEFAULT, mesh=args.mesh) if args.mesh else None,
    )
    run(args.out, bench, json_path=args.json, progress=progress_from_args(args))
    return 0
