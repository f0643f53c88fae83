"""``ntp bench scale``: time and peak memory of every stage of ``ntp reconstruct`` as scans grow —
photos (60 / 300 / 1000) x maps (256² / 1024²) — on virtual scans of the demo asset with their true
poses (SfM at scale is ``ntp bench sfm``'s) — by each reconstruction path asked for (``--paths``:
network + fit, the scan's own network, every texel refined), with the maps' errors against the
truth beside the seconds: run time against error as photos and maps grow.

Each reconstruct runs as users run it, ``ntp reconstruct`` in a child process; its memory is read
from ``/proc`` every ``SAMPLE_S`` (``RssAnon``: the process's own memory; memory-mapped trace files
are the page cache's and are left out) and charged to the stage its progress lines say is running;
the kernel's high-water mark (``VmHWM``, every page the process held at once) is the whole run's
peak. Virtual scans are kept under ``OUT/scans`` and reused; results are recomputed every run.
Writes a table, JSON and a plot (seconds per stage, peak memory per stage).
"""

from __future__ import annotations

import argparse
import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

from ..io.errors import NtpInputError
from ..io.output_folder import claim
from ..pipeline.report import Report
from ..pipeline.settings import PATHS
from ..refine.passes import PROGRESS_STAGES
from ..sim.evaluate import map_errors, relit_ssim
from ..sim.virtual_scan import ScanConfig, true_mesh_path, virtual_scan
from . import dump_json, number, print_table

PHOTOS = (60, 300, 1000)
RESOLUTIONS = (256, 1024)
# a low camera scale: the trace table (texels x the views that see them) and every stage after the
# photos are read do not depend on the photos' pixel count, only the scan's disk size does
CAMERA_SCALE = 0.1
SAMPLE_S = 0.1
# "refine": everything after the network + fit that estimates materials (the distilled path's teacher,
# fine-tuning and polish; the refinement)
STAGES = ("select", "atlas", "traces", "fit", "refine", "maps")
_REFINE_STAGES = ("teacher", "distil", "polish", "refine")
# the refinement's progress stages and the fine-tuning's (pipeline.distil)
_REFINING = (*PROGRESS_STAGES, "distil")
# progress counter -> the stage it runs in, and the stage that follows it when it closes
_RUNNING = {
    "blur check": "select",
    "atlas": "atlas",
    "visibility": "traces",
    "traces": "traces",
    "trace table": "traces",
    "network + fit": "fit",
    **dict.fromkeys(_REFINING, "refine"),
}
_AFTER = {
    "blur check": "atlas",
    "atlas": "traces",
    "visibility": "traces",
    "traces": "traces",
    "trace table": "fit",
    "network + fit": "maps",
    **dict.fromkeys(_REFINING, "refine"),  # the next counter says when it ends
}
MEMORY_GOAL_GB = 12.0  # the scale issue's goal at 1000 photos x 1024²


def run(
    out: Path,
    photos: tuple[int, ...] = PHOTOS,
    resolutions: tuple[int, ...] = RESOLUTIONS,
    camera_scale: float = CAMERA_SCALE,
    threads: int = 0,
    json_path: Path | None = None,
    plot: Path | None = None,
    paths: tuple[str, ...] = ("fast",),
) -> dict:
    """Every (photos, resolution, path) cell: stage seconds, peak memory and the maps' errors; a
    table, JSON, a plot."""
    if not paths or not set(paths) <= set(PATHS):
        raise NtpInputError(None, f"paths from {', '.join(PATHS)}")
    rows: list[dict] = []
    record = {"camera_scale": camera_scale, "threads": threads, "cells": rows}
    with claim(out, "gallery"):
        for n in photos:
            scan = _scan(out / "scans" / f"p{n}", n, camera_scale)
            for res, path in ((r, q) for r in resolutions for q in paths):
                suffix = "" if path == "fast" else f"_{path}"
                result = out / "results" / f"p{n}_r{res}{suffix}"
                shutil.rmtree(result, ignore_errors=True)  # the bench's own folder: time from scratch
                cell = _measure(scan, result, res, threads, path)
                rows.append({"photos": n, "resolution": res, "path": path, **cell})
                _print_row(rows[-1])
                dump_json(json_path, record)  # so far
    _table(rows)
    if plot is not None:
        _plot(rows, plot)
    return record


def _scan(folder: Path, views: int, camera_scale: float) -> Path:
    """The virtual scan with ``views`` photos (made once, reused while its settings match)."""
    capture = folder / "ground_truth" / "capture.json"
    if capture.is_file() and (folder / "scan.toml").is_file():
        cfg = json.loads(capture.read_text()).get("config", {})
        if cfg.get("views") == views and cfg.get("scale") == camera_scale:
            return folder
    t0 = time.perf_counter()
    virtual_scan(folder, cfg=ScanConfig(views=views, scale=camera_scale, seed=0))
    print(f"virtual scan: {views} photos in {time.perf_counter() - t0:.0f} s")
    return folder


def _measure(scan: Path, result: Path, resolution: int, threads: int, path: str = "fast") -> dict:
    """One ``ntp reconstruct`` by ``path`` in a child process, sampled: seconds and peak memory per
    stage; then the maps' errors against the scan's truth (``sim.evaluate``: normal, diffuse RMSE,
    relit SSIM), after the child has finished."""
    result.parent.mkdir(parents=True, exist_ok=True)
    progress = result.parent / f"{result.name}.progress.jsonl"
    progress.unlink(missing_ok=True)
    cmd = [
        sys.executable,
        "-m",
        "ntp_engine.cli",
        "reconstruct",
        str(scan),
        "--out",
        str(result),
        "--resolution",
        str(resolution),
        "--poses",
        str(scan / "ground_truth" / "poses.json"),
        "--threads",
        str(threads),
        "--quiet",
        "--progress",
        str(progress),
        *({"fast": [], "distil": ["--distil"], "refine": ["--refine"]}[path]),
    ]
    peak = dict.fromkeys(STAGES, 0.0)
    high_water = 0.0
    t0 = time.perf_counter()
    child = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    while child.poll() is None:
        status = _status(child.pid)
        if status:
            stage = _stage(progress)
            peak[stage] = max(peak[stage], status.get("RssAnon", 0.0))
            high_water = max(high_water, status.get("VmHWM", 0.0))
        time.sleep(SAMPLE_S)
    wall = time.perf_counter() - t0
    if child.returncode != 0:
        raise RuntimeError(f"ntp reconstruct {scan} failed: {child.stderr.read() if child.stderr else ''}")
    report = Report.from_json(json.loads((result / "report.json").read_text()))
    assert report.texels is not None and report.traces is not None  # a finished reconstruction's
    st = report.stages
    seconds = {
        "select": st["select"],
        "atlas": st["atlas"],
        "traces": st["traces"],
        "fit": st["network_and_fit"],
        "refine": sum(st.get(k, 0.0) for k in _REFINE_STAGES),
        "maps": st["maps"],
    }
    observed = report.texels.observed
    truth = scan / "ground_truth"
    errors = map_errors(result, truth)
    return {
        "texels_observed": observed,
        "entries": report.traces.entries,
        # every row, in range or not: 12 float32 + the in-range flag
        "table_gb": report.traces.table_entries * 49 / 1e9,
        "seconds": seconds,
        "wall_s": round(wall, 1),
        "fit_texels_per_s": round(observed / max(seconds["fit"], 1e-9)),
        # material estimation: the network + fit and what refines after it
        "material_texels_per_s": round(observed / max(seconds["fit"] + seconds["refine"], 1e-9)),
        "normal_median_deg": errors["normal_median_deg"],
        "diffuse_rmse": errors["diffuse_rmse"],
        "relit_ssim": relit_ssim(result, true_mesh_path(scan), truth)["relit_ssim"],
        "peak_anon_gb": {k: round(v / 2**20, 3) for k, v in peak.items()},
        "high_water_gb": round(high_water / 2**20, 3),
    }


def _status(pid: int) -> dict[str, float]:
    """The child's memory figures in kB (``/proc/PID/status``); empty once it has gone."""
    try:
        text = Path(f"/proc/{pid}/status").read_text()
    except OSError:
        return {}
    out = {}
    for line in text.splitlines():
        key, _, value = line.partition(":")
        if key in ("RssAnon", "VmHWM", "VmRSS"):
            out[key] = float(value.split()[0])
    return out


def _stage(progress: Path) -> str:
    """The stage running now, from the last progress line (a closed counter: the stage after it)."""
    try:
        lines = progress.read_text().splitlines()
        last = json.loads(lines[-1]) if lines else None
    except (OSError, ValueError):
        last = None
    if last is None:
        return "select"
    name = last["stage"]
    closed = last["total"] is not None and last["done"] >= last["total"]
    return (_AFTER if closed else _RUNNING).get(name, "select")


def _print_row(r: dict) -> None:
    s = r["seconds"]
    print(
        f"{r['photos']} photos, {r['resolution']}², {r['path']}: {r['wall_s']:.0f} s "
        f"(traces {s['traces']:.0f}, fit {s['fit']:.0f}, refine {s['refine']:.0f}; "
        f"materials {r['material_texels_per_s']} texels/s), relit SSIM {r['relit_ssim']:.3f}, "
        f"peak {r['high_water_gb']:.2f} GB, table {r['table_gb']:.2f} GB",
        flush=True,
    )


def _table(rows: list[dict]) -> None:
    print_table(
        [
            (
                r["photos"],
                f"{r['resolution']}²",
                r["path"],
                f"{r['entries'] / 1e6:.1f} M",
                f"{r['table_gb']:.2f}",
                *(f"{r['seconds'][k]:.1f}" for k in STAGES),
                f"{r['wall_s']:.0f}",
                r["fit_texels_per_s"],
                r["material_texels_per_s"],
                *(number(r.get(k)) for k in ("normal_median_deg", "diffuse_rmse", "relit_ssim")),
                *(f"{r['peak_anon_gb'][k]:.2f}" for k in ("traces", "fit", "refine")),
                f"{r['high_water_gb']:.2f}",
            )
            for r in rows
        ],
        (
            "photos",
            "maps",
            "path",
            "entries",
            "table GB",
            *(f"{k} s" for k in STAGES),
            "wall s",
            "fit texels/s",
            "materials texels/s",
            "normal °",
            "ρd RMSE",
            "relit SSIM",
            "traces GB",
            "fit GB",
            "refine GB",
            "peak GB",
        ),
    )


def _plot(rows: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a, b) = plt.subplots(1, 2, figsize=(12, 4))
    labels = [f"{r['photos']} photos\n{r['resolution']}²\n{r['path']}" for r in rows]
    x = range(len(rows))
    bottom = [0.0] * len(rows)
    for k in STAGES:
        v = [r["seconds"][k] / 60 for r in rows]
        a.bar(x, v, bottom=bottom, label=k)
        bottom = [p + q for p, q in zip(bottom, v)]
    a.set_xticks(list(x), labels, fontsize=8)
    a.set_ylabel("minutes (2 CPU cores)")
    a.set_title("time per stage")
    a.legend(fontsize=8)
    width = 0.8 / len(STAGES)
    for j, k in enumerate(STAGES):
        at = [i + (j - (len(STAGES) - 1) / 2) * width for i in x]  # the stages' bars centred on the cell
        b.bar(at, [r["peak_anon_gb"][k] for r in rows], width, label=k)
    b.plot(list(x), [r["high_water_gb"] for r in rows], "k_", markersize=20, label="whole run (VmHWM)")
    b.axhline(MEMORY_GOAL_GB, color="r", ls="--", lw=1, label=f"goal {MEMORY_GOAL_GB:.0f} GB")
    b.set_xticks(list(x), labels, fontsize=8)
    b.set_ylabel("peak memory (GB)")
    b.set_title("peak memory per stage")
    b.legend(fontsize=7)
    fig.suptitle("ntp bench scale: virtual scans of the demo asset, true poses")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    print(f"wrote {path}")


HELP = "time, peak memory and error per stage: photos x map resolution x path (true poses)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """``ntp bench scale``'s options."""
    parser.add_argument("--out", type=Path, default=Path("ntp_bench_scale"), help="folder for the scans and results")
    parser.add_argument("--photos", type=int, nargs="+", default=list(PHOTOS))
    parser.add_argument("--resolutions", type=int, nargs="+", default=list(RESOLUTIONS))
    parser.add_argument("--scale", type=float, default=CAMERA_SCALE, help="virtual camera resolution scale")
    parser.add_argument("--threads", type=int, default=0, help="CPU threads of each reconstruct (0: every core)")
    parser.add_argument(
        "--paths",
        nargs="+",
        choices=PATHS,
        default=["fast"],
        help="reconstruct each cell by these paths (fast: network + fit; distil: the scan's own network; "
        "refine: every texel refined), each timed and measured against the truth",
    )
    parser.add_argument("--plot", type=Path, default=None, help="PNG: seconds and memory (default OUT/bench_scale.png)")
    parser.add_argument("--json", type=Path, default=None)


def command(args: argparse.Namespace) -> int:
    """``ntp bench scale``: the benchmark with the command line's options; the exit code."""
    run(
        args.out,
        tuple(args.photos),
        tuple(args.resolutions),
        camera_scale=args.scale,
        threads=args.threads,
        json_path=args.json,
        plot=args.plot if args.plot is not None else args.out / "bench_scale.png",
        paths=tuple(args.paths),
    )
    return 0
