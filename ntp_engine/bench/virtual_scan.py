"""``ntp bench virtual-scan``: seconds per photo of the demo asset at scale 0.25 and 1.0, the
renderer's per-pixel Eq. 1 compiled against the torch terms it replaced (same photos, one run), and the
error of clustered shadows against exact per-emitter shadow rays (on the demo dome with an
occluding wall beside it, so there are shadows to get wrong)."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from ..io.mesh import Mesh, smooth_normals
from ..scanner.camera import resampled
from ..scanner.device_file import load_scanner
from ..sim.renderer import Scene
from ..sim.virtual_scan import ScanConfig, load_asset, take_photo, trajectory
from . import dump_json, print_table


def _with_wall(mesh: Mesh) -> Mesh:
    """The mesh plus a 12 cm x 10 cm vertical wall 1 cm beside it (its UVs unused, set to 0)."""
    x0 = mesh.vertices[:, 0].max() + 0.01
    wall = np.array([[x0, -0.06, 0.0], [x0, 0.06, 0.0], [x0, 0.06, 0.10], [x0, -0.06, 0.10]])
    v = np.concatenate([mesh.vertices, wall])
    k = len(mesh.vertices)
    f = np.concatenate([mesh.faces, [[k, k + 1, k + 2], [k, k + 2, k + 3]]])
    uv = np.concatenate([mesh.uv, np.zeros((4, 2))])
    return Mesh(v, f, uv, smooth_normals(v, f))


def _lit_errors(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Per pixel of the reference ``b (..., 3)`` brighter than 0.02 in some channel: the largest
    channel's |a - b| relative to b's brightest channel."""
    bright = b.max(-1) > 0.02
    return np.abs(a - b)[bright].max(-1) / b[bright].max(-1)


def _shading(scene: Scene, poses: list[np.ndarray], cam) -> dict:
    """The same linear renders with Eq. 1 summed by the compiled loop and by the torch factorised
    terms (``Scene.shading``), alternating photo by photo: seconds each and their largest relative
    difference on lit pixels (float32 torch against float64)."""
    seconds = {"compiled": 0.0, "tensor": 0.0}
    worst = 0.0
    for pose in poses:
        images = {}
        for shading in seconds:
            scene.shading = shading
            t0 = time.perf_counter()
            images[shading], _ = scene.render_linear(pose, cam)
            seconds[shading] += time.perf_counter() - t0
        worst = max(worst, float(_lit_errors(images["compiled"], images["tensor"]).max(initial=0.0)))
    scene.shading = "compiled"
    n = max(len(poses), 1)
    out = {
        "seconds_per_photo_compiled_sums": seconds["compiled"] / n,
        "seconds_per_photo_tensor_sums": seconds["tensor"] / n,
        "shading_speedup": seconds["tensor"] / max(seconds["compiled"], 1e-9),
        "shading_rel_diff_max": worst,
    }
    print(
        f"Eq. 1 per pixel, compiled sums vs torch terms ({cam.width}x{cam.height}, {n} photos, alternating): "
        f"{out['seconds_per_photo_compiled_sums']:.2f} vs {out['seconds_per_photo_tensor_sums']:.2f} s / photo "
        f"({out['shading_speedup']:.2f}x), largest relative difference {worst:.1e}"
    )
    return out


def run(photos: int = 3, json_path=None, scales: tuple[float, ...] = (0.25, 1.0), shadow_scale: float = 0.25) -> dict:
    """Seconds per photo at each of ``scales`` (the first with ``photos`` photos, later ones half as
    many) and the shadow clusters' error at ``shadow_scale``; printed and returned."""
    mesh, maps, _, _ = load_asset(None, None, None)
    scanner = load_scanner()
    cfg = ScanConfig(views=24)
    rng = np.random.default_rng(0)
    scene = Scene(mesh, maps, scanner, cfg.clusters, cfg.exposure)
    poses = trajectory(scene.center, scanner, cfg, rng)
    result, rows = {}, []
    for k, scale in enumerate(scales):
        n = photos if k == 0 else max(1, photos // 2)
        cam = resampled(scanner, scale)
        cfg.scale = scale
        take_photo(scene, poses[0], cam, cfg, rng)  # warm-up
        t0 = time.perf_counter()
        for i in range(n):
            take_photo(scene, poses[1 + i], cam, cfg, rng)
        sec = (time.perf_counter() - t0) / n
        result[f"seconds_per_photo_scale_{scale:g}"] = sec
        rows.append((f"{scale:g}", f"{cam.width}x{cam.height}", f"{sec:.2f}", f"{sec * 120 / 60:.1f}"))
    print_table(rows, ("scale", "pixels", "s / photo", "min / 120 photos"))
    result.update(_shading(scene, poses[1 : 1 + photos], resampled(scanner, scales[0])))

    # shadow error: clusters vs exact, on object pixels of a few views of the dome beside a wall
    walled = Scene(_with_wall(mesh), maps, scanner, cfg.clusters, cfg.exposure)
    cam = resampled(scanner, shadow_scale)
    errs, t_c, t_e = [], 0.0, 0.0
    for i in (2, 9, 16):
        lin, info = walled.render_linear(poses[i], cam)
        obj = np.nonzero(info["geom"].reshape(-1) == 0)[0]
        sub = obj[np.linspace(0, len(obj) - 1, min(1500, len(obj))).astype(int)]
        t0 = time.perf_counter()
        a, _ = walled.render_linear(poses[i], cam, pixel_subset=sub)
        t_c += time.perf_counter() - t0
        t0 = time.perf_counter()
        b, _ = walled.render_linear(poses[i], cam, pixel_subset=sub, exact_shadows=True)
        t_e += time.perf_counter() - t0
        errs.append(_lit_errors(a, b))
    e = np.concatenate(errs) if errs else np.zeros(1)
    result.update(
        {
            "shadow_clusters": cfg.clusters,
            "shadow_rel_err_median": float(np.median(e)),
            "shadow_rel_err_p99": float(np.percentile(e, 99)),
            "shadow_rel_err_max": float(e.max()),
            "shadow_pixels": int(e.size),
            "shadow_cost_ratio_exact_over_clusters": t_e / max(t_c, 1e-9),
        }
    )
    print(
        f"shadows, {cfg.clusters} clusters vs exact per-LED rays ({e.size} object pixels, dome beside a wall): "
        f"relative error median {np.median(e):.2e}, p99 {np.percentile(e, 99):.2e}, max {e.max():.2e}; "
        f"exact costs {t_e / max(t_c, 1e-9):.1f}x"
    )
    dump_json(json_path, result)
    return result


HELP = "seconds per photo (scale 0.25, 1.0) and shadow-cluster error"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """``ntp bench virtual-scan``'s options."""
    parser.add_argument("--photos", type=int, default=3)
    parser.add_argument("--json", type=Path, default=None)


def command(args: argparse.Namespace) -> int:
    """``ntp bench virtual-scan``: the benchmark with the command line's options; the exit code."""
    run(photos=args.photos, json_path=args.json)
    return 0
