"""Cycles against the engine: the same maps, camera and point light, rendered by both.

The engine side is ``virtual_scan.Scene`` with an isotropic point emitter of unit intensity (identity
colour matrix, full drive, exact shadows), scaled by P / (4 pi) to a Blender point light of power P.
Both images are compared on the object's pixels only, after the same display transform (scaled so
the engine's 99th percentile is 1, clipped, gamma 2.2): SSIM (mean of the SSIM map over the object)
and PSNR.
"""

from __future__ import annotations

import dataclasses
import math
import time
from pathlib import Path

import bpy
import numpy as np

from ntp_engine.io.images import write_png
from ntp_engine.io.maps import SVBRDFMaps
from ntp_engine.io.mesh import load_mesh
from ntp_engine.scanner.camera import resampled
from ntp_engine.scanner.device_file import shipped_device
from ntp_engine.scanner.scanner import Scanner
from ntp_engine.sim.evaluate import NOVEL_LIGHT_DEVICE, compare_images
from ntp_engine.sim.renderer import Scene
from ntp_engine.sim.virtual_scan import ScanConfig, trajectory

from . import material
from . import scene as bscene

POWER_W = 10.0


def point_device(scale: float) -> Scanner:
    """The shipped point-light device with its camera at ``scale``."""
    return resampled(shipped_device(NOVEL_LIGHT_DEVICE), scale)


def novel_views(result: Path, count: int, seed: int = 2024, scale: float = 0.25) -> list[tuple[np.ndarray, np.ndarray]]:
    """(camera-from-world pose, light position in world) pairs: viewpoints of a hand-held sweep,
    each lit by a point light 8 cm right of and 4 cm above the camera (not the scan's LED array)."""
    cam = point_device(scale)
    mesh = load_mesh(result / "mesh.obj")
    centre = 0.5 * (mesh.vertices.min(0) + mesh.vertices.max(0))
    poses = trajectory(centre, cam, ScanConfig(views=count, seed=seed), np.random.default_rng(seed))
    out = []
    for p in poses:
        light_cam = np.array([0.08, -0.04, 0.0])
        out.append((p, p[:3, :3].T @ (light_cam - p[:3, 3])))
    return out


def engine_render(
    result: Path, pose: np.ndarray, light_world: np.ndarray, cam: Scanner
) -> tuple[np.ndarray, np.ndarray]:
    """Linear radiance ``(H, W, 3)`` under a Blender point light of POWER_W, and the object mask."""
    dev = dataclasses.replace(
        cam,
        emitter_positions=(pose[:3, :3] @ light_world + pose[:3, 3])[None],
        emitter_normals=np.array([[0.0, 0.0, 1.0]]),
        emitter_axes=np.array([[1.0, 0.0, 0.0]]),
        angular_exponent=0.0,
        color_matrix=np.eye(3),
        pattern=np.ones((1, 3)),
    )
    sc = Scene(load_mesh(result / "mesh.obj"), SVBRDFMaps.load(result), dev, clusters=1)
    img, hit = sc.render_linear(pose, cam, exact_shadows=True)
    return img / sc.exposure * POWER_W / (4 * math.pi), (hit["geom"] == 0).reshape(img.shape[:2])


def cycles_render(
    obj: bpy.types.Object,
    mat: bpy.types.Material,
    pose: np.ndarray,
    light_world: np.ndarray,
    cam: Scanner,
    out: Path,
    samples: int,
) -> tuple[np.ndarray, float]:
    """Render the result in Cycles with ``mat`` from ``pose`` under a point light; (image, seconds)."""
    scene = bpy.context.scene
    bscene.setup_cycles(scene, cam.width, cam.height, samples)
    obj.data.materials[0] = mat
    camera = bscene.camera_object("ntp compare camera", cam, pose)
    light = bscene.point_light("ntp compare light", light_world, POWER_W)
    scene.camera = camera
    t0 = time.perf_counter()
    try:
        img = bscene.render_exr(scene, out)
    finally:
        bpy.data.objects.remove(camera, do_unlink=True)
        bpy.data.objects.remove(light, do_unlink=True)
    return img, time.perf_counter() - t0


def run(
    result: str | Path,
    views: int = 3,
    scale: float = 0.25,
    samples: int = 64,
    work: Path | None = None,
    save_png: bool = False,
    require_report: bool = True,
) -> dict:
    """Render the result with both materials in Cycles and with the engine from ``views`` novel
    views/lights; SSIM/PSNR per variant and seconds per Cycles render. ``require_report=False``
    for a folder of maps that is not a pipeline result (true maps)."""
    import tempfile

    result = Path(result)
    bpy.ops.wm.read_factory_settings(use_empty=True)
    obj = material.import_result_mesh(result)
    principled, accurate = material.build_materials(result, obj, require_report=require_report)
    cam = point_device(scale)
    rows = {"principled": [], "accurate": []}
    seconds = {"principled": [], "accurate": []}
    with tempfile.TemporaryDirectory() as tmp:
        work = work or Path(tmp)
        for k, (pose, light) in enumerate(novel_views(result, views, scale=scale)):
            ref, mask = engine_render(result, pose, light, cam)
            for name, mat in (("principled", principled), ("accurate", accurate)):
                img, sec = cycles_render(obj, mat, pose, light, cam, work / f"{name}_{k}.exr", samples)
                c = compare_images(ref, img, mask)
                if save_png:
                    write_png(work / f"{name}_{k}.png", np.concatenate(c["display"], 1))
                rows[name].append({"ssim": c["ssim"], "psnr_db": c["psnr_db"]})
                seconds[name].append(sec)
    return {
        v: {
            "ssim": float(np.mean([r["ssim"] for r in rows[v]])),
            "psnr_db": float(np.mean([r["psnr_db"] for r in rows[v]])),
            "per_view": rows[v],
            "seconds_per_render": float(np.mean(seconds[v])),
        }
        for v in rows
    }
