"""``ntp demo``: the main job end to end on the bundled demo asset.

Virtual-scans ``assets/demo`` (``DIR/scan/``, with ``ground_truth/``), reconstructs it with the
shipped model through the whole pipeline, SfM included (``DIR/result/``), and prints the errors
against the ground truth (``evaluate``): relit SSIM, normal median angle, diffuse RMSE, texel
coverage, camera pose error. Everything goes to ``DIR/demo.json``; the relit comparisons (truth
left, reconstruction right) to ``DIR/relit/``; with bpy installed, the add-on's batch export writes
``DIR/asset.blend``, ``DIR/asset.glb`` and a Cycles ``DIR/preview.png``. Re-running resumes: the scan is kept when its
settings match, and the pipeline's stages are cached. The reconstruction includes the
analysis-by-synthesis refinement (``ntp reconstruct --refine``; ``refine=False`` leaves it out): on
the defaults ~40% of the run's time on 2 cores (5-8 minutes, by the machine), and what meets the demo's quality goals
(docs/accuracy.md).
"""

from __future__ import annotations

import json
import subprocess
import time
from pathlib import Path
from typing import Any

from ..io.atomic import write_text_atomic
from ..io.blender_process import blender_command, has_bpy
from ..io.errors import NtpInputError
from ..io.output_folder import claim
from ..io.progress import QUIET, Progress
from ..pipeline.result_page import write_page
from ..pipeline.stages import MIN_RESOLUTION, reconstruct, register_photos
from ..scanner.scan_folder import load_poses, load_scan
from .evaluate import map_errors, pose_error, relit_ssim
from .virtual_scan import ScanConfig, scan_folder_is_current, virtual_scan

DEMO_VIEWS, DEMO_SCALE, DEMO_RESOLUTION = 60, 0.25, 256  # `ntp demo`'s defaults: under 5 minutes on 2 cores, refined

GOALS = {
    "relit_ssim": (">=", 0.97),
    "normal_median_deg": ("<=", 3.0),
    "diffuse_rmse": ("<=", 0.02),
    "coverage": (">=", 0.90),
    "seconds": ("<=", 300.0),
}


def _blender_export(result: Path, out: Path) -> dict:
    """The .blend, .glb and a Cycles preview via the add-on's headless batch, in its own process
    (the engine never imports bpy); skipped when bpy is not installed."""
    if not has_bpy():
        return {"skipped": "bpy not installed"}
    files = {"blend": out / "asset.blend", "gltf": out / "asset.glb", "preview": out / "preview.png"}
    r = subprocess.run(
        blender_command(
            "batch",
            str(result),
            "--blend",
            str(files["blend"]),
            "--gltf",
            str(files["gltf"]),
            "--preview",
            str(files["preview"]),
        ),
        capture_output=True,
        text=True,
    )
    if r.returncode != 0:
        return {"error": (r.stderr.strip().splitlines() or ["the Blender export failed"])[-1]}
    return {k: str(v) for k, v in files.items()}


def run(
    out: Path,
    views: int = DEMO_VIEWS,
    scale: float = DEMO_SCALE,
    resolution: int = DEMO_RESOLUTION,
    seed: int = 0,
    known_poses: bool = False,
    model: str | None = None,
    progress: Progress = QUIET,
    blend: bool = True,
    refine: bool = True,
) -> dict:
    """Virtual scan, reconstruction, errors and export into ``out`` (see the module docstring);
    returns the summary (also ``out/demo.json``) and prints it."""
    if views < 3 or not 0 < scale <= 1 or resolution < MIN_RESOLUTION:
        raise NtpInputError(None, f"need --views >= 3, 0 < --scale <= 1, --resolution >= {MIN_RESOLUTION}")
    out = Path(out)
    with claim(out, "demo"):
        t_all = time.perf_counter()
        scan_dir, result_dir = out / "scan", out / "result"
        cfg = ScanConfig(views=views, scale=scale, seed=seed)
        capture = scan_dir / "ground_truth" / "capture.json"
        t0 = time.perf_counter()
        wanted = json.loads(json.dumps(cfg.__dict__))
        current = capture.is_file() and json.loads(capture.read_text())["config"] == wanted
        if not (current and scan_folder_is_current(scan_dir)):
            virtual_scan(scan_dir, cfg=cfg, progress=progress)
        t_scan = time.perf_counter() - t0

        truth = load_poses(scan_dir / "ground_truth" / "poses.json")
        scan = load_scan(scan_dir, scan_dir / "ground_truth" / "poses.json" if known_poses else None)
        t0 = time.perf_counter()
        rep = reconstruct(scan, result_dir, resolution=resolution, model=model, progress=progress, refine=refine)
        t_rec = time.perf_counter() - t0
        poses, _, _ = register_photos(scan, result_dir)  # the poses the run used (cached)

        t0 = time.perf_counter()
        gt = scan_dir / "ground_truth"
        relit = relit_ssim(result_dir, scan_dir / "mesh.obj", gt, save_dir=out / "relit")
        errors = {**map_errors(result_dir, gt), **relit}
        t_eval = time.perf_counter() - t0

        t0 = time.perf_counter()
        blender = _blender_export(result_dir, out) if blend else {"skipped": "--no-blend"}
        t_blend = time.perf_counter() - t0
        page = write_page(result_dir, Path(blender["gltf"]) if "gltf" in blender else None)
        metrics = {
            "relit_ssim": errors["relit_ssim"],
            "normal_median_deg": errors["normal_median_deg"],
            "diffuse_rmse": errors["diffuse_rmse"],
            "coverage": rep.texels.coverage if rep.texels else 0.0,
            "seconds": time.perf_counter() - t_all,
        }
        summary: dict[str, Any] = {
            "config": {
                "views": views,
                "scale": scale,
                "resolution": resolution,
                "seed": seed,
                "poses": "ground truth" if known_poses else "structure from motion",
                "refine": refine,
            },
            "metrics": metrics,
            "errors": errors,
            "pose_error": pose_error(poses, truth),
            "alignment": (rep.registration or {}).get("alignment"),
            "seconds": {
                "virtual_scan": round(t_scan, 2),
                "reconstruct": round(t_rec, 2),
                "evaluate": round(t_eval, 2),
                "blender": round(t_blend, 2),
                "stages": rep.stages,
            },
            "blender": blender,
            "page": str(page),
        }
        write_text_atomic(out / "demo.json", json.dumps(summary, indent=2))

        print(f"\nntp demo: {views} photos at {scale:g} scale, {resolution}^2 maps -> {result_dir}")
        for k, (op, goal) in GOALS.items():
            v = metrics[k]
            ok = v >= goal if op == ">=" else v <= goal
            print(f"  {k:18s} {v:10.4f}   goal {op} {goal:<6g} {'met' if ok else 'MISSED'}")
        pe = summary["pose_error"]
        if pe:
            print(
                f"  pose error: centre median {pe['centre_median_m'] * 1e3:.2f} mm, "
                f"rotation median {pe['rotation_median_deg']:.3f} deg"
            )
        print(f"  wrote {out / 'demo.json'}, relit comparisons in {out / 'relit'}")
        if "blend" in blender:
            print(f"  Blender: {blender['blend']}, {blender['gltf']}, {blender['preview']}")
        else:
            print(f"  Blender: {blender.get('skipped') or blender.get('error')}")
        print(f"  result page: {page} (ntp view {result_dir} opens it)")
        return summary
