"""Headless export for pipelines (bpy as a module):

    python -m ntp_addon.batch RESULT_DIR --blend OUT.blend --gltf OUT.glb --preview OUT.png

Imports the result's mesh with its maps, builds both materials (the default variant on the
object, the other kept in the file), saves the .blend, exports glTF binary with the Principled
material (KHR_materials_anisotropy, KHR_materials_specular) and renders a Cycles preview with the
key-light rig. The .blend holds the result's map files (packed; ``--no-pack`` links them) and its
datablocks are named after the result folder. Each output is written to a temporary name and
renamed. Exit code 2 and one line on stderr for bad input.
"""

from __future__ import annotations

import argparse
import signal
import sys
from pathlib import Path

import bpy  # noqa: F401  (before torch, which the engine imports)

from ntp_engine.io.arguments import int_in
from ntp_engine.io.atomic import atomic_path
from ntp_engine.io.errors import NtpInputError, error_line
from ntp_engine.io.output_folder import check_not_inside
from ntp_engine.io.signals import Terminated, terminate_as_interrupt
from ntp_engine.pipeline.stages import MAX_RESOLUTION, MIN_RESOLUTION

from . import material
from . import scene as bscene
from .gltf import export_glb


def export(
    result: Path,
    blend: Path | None = None,
    gltf: Path | None = None,
    preview: Path | None = None,
    variant: str = material.DEFAULT_VARIANT,
    samples: int = 64,
    size: tuple[int, int] = (640, 512),
    turntable: int = 0,
    pack: bool = True,
    texture_size: int | None = None,
) -> dict:
    """Import the result, build both materials and write the requested .blend, .glb and preview
    (each atomically); with ``pack`` the .blend holds the map files too (self-contained);
    ``texture_size`` scales the .glb's textures (the .blend keeps the maps' own size)."""
    bpy.ops.wm.read_factory_settings(use_empty=True)
    ri_check = material.read_result(result)  # validate before creating anything
    del ri_check
    obj = material.import_result_mesh(result)
    principled, accurate = material.build_materials(result, obj, variant)
    if pack:
        material.pack_file_images((principled, accurate))
    rig = bscene.relight_rig(obj, *size, samples=samples, turntable_frames=turntable)
    written = {}
    if gltf is not None:
        export_glb(obj, principled, gltf, texture_size)
        written["gltf"] = str(gltf)
    if preview is not None:
        with atomic_path(preview) as tmp:
            bscene.render_still(rig["scene"], tmp)
        written["preview"] = str(preview)
    if blend is not None:
        bscene.open_on(rig["scene"])  # the file opens on a scene that renders: Cycles, camera, lights
        with atomic_path(blend) as tmp:
            try:
                bpy.ops.wm.save_as_mainfile(filepath=str(tmp), copy=True, compress=True)
            finally:
                Path(str(tmp) + "1").unlink(missing_ok=True)  # Blender's backup of the file it replaced
        written["blend"] = str(blend)
    return {"object": obj.name, "materials": [principled.name, accurate.name], "variant": variant, **written}


def main(argv: list[str] | None = None) -> int:
    """Command line of the batch export; returns the exit code (2 for bad input)."""
    p = argparse.ArgumentParser(prog="python -m ntp_addon.batch", description=__doc__.split("\n\n")[0])
    p.add_argument("result", type=Path, help="result folder of ntp reconstruct / ntp demo")
    p.add_argument("--blend", type=Path, default=None)
    p.add_argument("--gltf", type=Path, default=None, help=".glb to write")
    p.add_argument("--preview", type=Path, default=None, help="PNG of a Cycles render with the key-light rig")
    p.add_argument("--variant", choices=["accurate", "principled"], default=material.DEFAULT_VARIANT)
    p.add_argument("--samples", type=int, default=64)
    p.add_argument("--turntable", type=int, default=0, help="frames of a 360-degree turntable (0: none)")
    p.add_argument("--no-pack", action="store_true", help="link the map files instead of packing them into the .blend")
    p.add_argument(
        "--gltf-texture-size",
        type=int_in(MIN_RESOLUTION, MAX_RESOLUTION, "the largest texture GPUs and Blender take"),
        default=None,
        help="pixels a side of the .glb's textures (default: the maps' own)",
    )
    a = p.parse_args(argv)
    try:
        for target in (a.blend, a.gltf, a.preview):
            if target is not None:  # the result's files are the export's input: never written over
                check_not_inside(target, (a.result,))
        with terminate_as_interrupt():
            info = export(
                a.result,
                a.blend,
                a.gltf,
                a.preview,
                a.variant,
                a.samples,
                turntable=a.turntable,
                pack=not a.no_pack,
                texture_size=a.gltf_texture_size,
            )
    except (NtpInputError, OSError) as err:
        print(f"ntp_addon.batch: error: {error_line(err)}", file=sys.stderr)
        return 2
    except Terminated:
        print("ntp_addon.batch: terminated — nothing half-written was left", file=sys.stderr)
        return 128 + signal.SIGTERM
    except KeyboardInterrupt:
        print("ntp_addon.batch: interrupted — nothing half-written was left", file=sys.stderr)
        return 130
    for k in ("blend", "gltf", "preview"):
        if k in info:
            print(f"wrote {info[k]}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
