"""Errors of a reconstruction against ground truth (a virtual scan's ``ground_truth/``).

- map errors over the texels some trace reached (``confidence.exr`` G > 0): median angle between
  reconstructed and true normals (degrees), RMSE of the diffuse albedo (linear RGB), coverage;
- relit SSIM: the engine renders the true and the reconstructed asset from novel viewpoints, each
  lit by the point-light device (a novel light: a single point, unlike the LED array of the scan),
  with exact shadows; one display transform for both (the truth's 99th percentile to 1, clip,
  gamma 2.2); SSIM averaged over the object's pixels only (the backdrop would inflate it).

Both assets must share the UV layout (true for scans of a mesh with UVs, whose UVs the pipeline
keeps).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from skimage.metrics import structural_similarity

from ..io.images import read_image, write_png
from ..io.maps import SVBRDFMaps, texel_uv
from ..io.mesh import load_mesh
from ..scanner.camera import resampled
from ..scanner.device_file import shipped_device
from .renderer import Scene
from .virtual_scan import ScanConfig, trajectory

NOVEL_LIGHT_DEVICE = "point_light.toml"  # relit under a single point light, unlike the scan's LED array


def map_errors(result: Path, truth: Path) -> dict:
    """Normal angle (median, p90; degrees), diffuse RMSE and the observed fraction of a result's
    maps against the truth's, over the texels some trace reached."""
    rec = SVBRDFMaps.load(result)
    H, W = rec.normal.shape[:2]
    observed = read_image(result / "confidence.exr")[..., 1].reshape(-1) > 0
    g = SVBRDFMaps.load(truth).sample(texel_uv((H, W)).reshape(-1, 2))
    n = rec.normal.reshape(-1, 3)[observed]
    ang = np.degrees(np.arccos(np.clip((n * g["normal"][observed]).sum(1), -1, 1)))
    d = rec.diffuse_albedo.reshape(-1, 3)[observed] - g["diffuse_albedo"][observed]
    return {
        "normal_median_deg": float(np.median(ang)),
        "normal_p90_deg": float(np.percentile(ang, 90)),
        "diffuse_rmse": float(np.sqrt((d**2).mean())),
        "observed_fraction": float(observed.mean()),
    }


def compare_images(reference: np.ndarray, test: np.ndarray, mask: np.ndarray) -> dict:
    """SSIM and PSNR of two linear renders ``(H, W, 3)`` over ``mask`` pixels, after one display
    transform for both: scaled so the reference's 99th percentile is 1, clipped, gamma 2.2 (no
    saturated plateau hides differences). SSIM is the mean of the SSIM map over the mask."""
    k = 1.0 / max(float(np.percentile(reference[mask], 99)), 1e-12)
    da, db = (np.clip(x * k, 0, 1) ** (1 / 2.2) for x in (reference, test))
    da[~mask], db[~mask] = 0, 0
    _, smap = structural_similarity(da, db, data_range=1.0, channel_axis=-1, full=True)
    mse = float(((da - db)[mask] ** 2).mean())
    return {
        "ssim": float(smap.mean(-1)[mask].mean()),
        "psnr_db": float(10 * np.log10(1.0 / max(mse, 1e-12))),
        "display": (da, db),
    }


def relit_ssim(
    result: Path,
    truth_mesh: Path,
    truth_maps: Path,
    lights: int = 3,
    scale: float = 0.25,
    seed: int = 1000,
    save_dir: Path | None = None,
) -> dict:
    """Mean SSIM over ``lights`` novel views, each lit by the point-light device, of the result
    rendered against the truth (object pixels; see the module docstring). ``save_dir`` gets the
    pairs as PNG (truth left)."""
    point = shipped_device(NOVEL_LIGHT_DEVICE)
    cam = resampled(point, scale)
    true_scene = Scene(load_mesh(truth_mesh), SVBRDFMaps.load(truth_maps), point, clusters=1)
    rec_scene = Scene(load_mesh(result / "mesh.obj"), SVBRDFMaps.load(result), point, clusters=1)
    poses = trajectory(true_scene.center, point, ScanConfig(views=lights, seed=seed), np.random.default_rng(seed))
    scores = []
    for k, pose in enumerate(poses):
        a, ha = true_scene.render_linear(pose, cam, exact_shadows=True)
        b, _ = rec_scene.render_linear(pose, cam, exact_shadows=True)
        obj = (ha["geom"] == 0).reshape(a.shape[:2])
        c = compare_images(a, b, obj)
        scores.append(c["ssim"])
        da, db = c["display"]
        if save_dir is not None:
            write_png(save_dir / f"relit_{k}.png", np.concatenate([da, db], 1))
    return {"relit_ssim": float(np.mean(scores)), "relit_ssim_per_light": scores}


def pose_error(poses: dict[str, np.ndarray], truth: dict[str, np.ndarray]) -> dict:
    """Median / max camera-centre distance (m) and rotation angle (deg) of camera-from-world
    ``poses`` against the true ones, over the photos both have; empty if none."""
    dt, dr = [], []
    for n, m in poses.items():
        if n not in truth:
            continue
        g = truth[n]
        dt.append(np.linalg.norm(m[:3, :3].T @ m[:3, 3] - g[:3, :3].T @ g[:3, 3]))
        dr.append(np.degrees(np.arccos(np.clip((np.trace(m[:3, :3] @ g[:3, :3].T) - 1) / 2, -1, 1))))
    if not dt:
        return {}
    return {
        "centre_median_m": float(np.median(dt)),
        "centre_max_m": float(np.max(dt)),
        "rotation_median_deg": float(np.median(dr)),
        "rotation_max_deg": float(np.max(dr)),
    }
