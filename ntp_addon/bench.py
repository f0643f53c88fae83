"""``ntp bench blender`` (runs as ``python -m ntp_addon.bench``): Cycles renders of the demo asset
with both materials against the engine's render of the same maps, under 3 novel point lights
(SSIM/PSNR, seconds per render), and seconds per preview render of the relight rig."""

from __future__ import annotations

import argparse
import shutil
import sys
import tempfile
import time
from pathlib import Path

import bpy  # noqa: F401  (before torch)

from ntp_engine.bench import dump_json, print_table
from ntp_engine.io.assets import DEMO_DIR

from . import compare, material
from . import scene as bscene

DEMO = DEMO_DIR


def run(views: int = 3, scale: float = 0.25, samples: int = 64, json_path: Path | None = None) -> dict:
    """Cycles against the engine for both materials and the preview's render time; printed and returned."""
    with tempfile.TemporaryDirectory() as tmp:
        result = Path(tmp) / "demo"
        result.mkdir()
        for f in (DEMO / "ground_truth").glob("*.exr"):
            shutil.copy(f, result / f.name)
        shutil.copy(DEMO / "mesh.obj", result / "mesh.obj")
        r = compare.run(result, views=views, scale=scale, samples=samples, require_report=False)
        bpy.ops.wm.read_factory_settings(use_empty=True)
        obj = material.import_result_mesh(result)
        material.build_materials(result, obj, require_report=False)  # the demo's true maps: no report
        rig = bscene.relight_rig(obj, 640, 512, samples=samples)
        t0 = time.perf_counter()
        bscene.render_still(rig["scene"], Path(tmp) / "preview.png")
        preview_s = time.perf_counter() - t0
    rows = []
    for v in ("accurate", "principled"):
        rows.append(
            (
                v,
                f"{r[v]['ssim']:.4f}",
                f"{r[v]['psnr_db']:.2f}",
                " ".join(f"{x['ssim']:.3f}" for x in r[v]["per_view"]),
                f"{r[v]['seconds_per_render']:.2f}",
            )
        )
    print_table(rows, ("material", "SSIM", "PSNR dB", "SSIM per light", "s / render"))
    print(f"preview render (640x512, {samples} spp, key/fill/rim rig, 4 bounces): {preview_s:.2f} s")
    data = {
        "views": views,
        "scale": scale,
        "samples": samples,
        **{v: r[v] for v in r},
        "preview_seconds": preview_s,
        "default_variant": material.DEFAULT_VARIANT,
    }
    dump_json(json_path, data)
    return data


def main(argv: list[str] | None = None) -> int:
    """Command line of ``ntp bench blender``."""
    p = argparse.ArgumentParser(prog="ntp bench blender")
    p.add_argument("--views", type=int, default=3)
    p.add_argument("--scale", type=float, default=0.25)
    p.add_argument("--samples", type=int, default=64)
    p.add_argument("--json", type=Path, default=None)
    a = p.parse_args(argv)
    run(a.views, a.scale, a.samples, a.json)
    return 0


if __name__ == "__main__":
    sys.exit(main())
