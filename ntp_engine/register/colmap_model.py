"""An existing COLMAP model as the scan's camera solution, in place of running SfM (pycolmap reads it).

Convention: a COLMAP model folder (e.g. ``sparse/0``) holds ``cameras``, ``images`` and ``points3D``
as ``.bin`` or ``.txt``. Its ``cam_from_world`` is camera-from-world in OpenCV camera axes (x right,
y down, z forward) — ntp's own convention — in COLMAP's arbitrary world frame and scale, so the
model is aligned to the mesh exactly as ntp's own SfM is (``align.align_to_mesh``). Images are
matched to photos by file name. Cameras must have the photos' size; their intrinsics are COLMAP's
business (ntp projects with the device file's), so a focal length more than ``TUNING.sfm.focal_tolerance`` off
the device's is warned about, not refused.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..io.errors import NtpInputError
from ..io.progress import warn
from ..scanner.scanner import Scanner
from .settings import TUNING
from .sfm import SfmResult

MODEL_FILES = ("cameras", "images", "points3D")


def model_files(folder: Path) -> list[Path]:
    """The model's three files (binary preferred, else text); ``NtpInputError`` if neither is complete."""
    for ext in (".bin", ".txt"):
        files = [folder / f"{name}{ext}" for name in MODEL_FILES]
        if all(f.is_file() for f in files):
            return files
    raise NtpInputError(folder, "not a COLMAP model folder (needs cameras, images and points3D as .bin or .txt)")


def read_colmap_model(folder: Path, scanner: Scanner, names: list[str]) -> SfmResult:
    """Poses (camera-from-world, the model's frame) of the photos ``names`` the model registered, its
    3D points, and the photos it does not hold. One-line errors name the folder or file."""
    import pycolmap

    files = model_files(folder)
    rec = pycolmap.Reconstruction()
    try:
        rec.read(str(folder))
    except Exception as err:  # noqa: BLE001 - pycolmap raises its own types for damaged files
        raise NtpInputError(folder, f"cannot read the COLMAP model ({' '.join(str(err).split())[:200]})") from None
    for cam in rec.cameras.values():
        if (cam.width, cam.height) != (scanner.width, scanner.height):
            raise NtpInputError(
                files[0],
                f"camera {cam.camera_id} is {cam.width}x{cam.height}, the photos are {scanner.width}x{scanner.height}",
            )
        focal = float(np.mean([cam.focal_length_x, cam.focal_length_y]))
        device = float(np.mean([scanner.K[0, 0], scanner.K[1, 1]]))
        if abs(focal / device - 1) > TUNING.sfm.focal_tolerance:
            warn(f"{files[0]}: camera {cam.camera_id}'s focal length {focal:.1f} px is not the device's {device:.1f}")
    wanted, poses = set(names), {}
    for image in rec.images.values():
        if image.name in wanted and image.has_pose:
            m = np.eye(4)
            m[:3, :4] = image.cam_from_world().matrix()
            poses[image.name] = m
    if len(poses) < TUNING.sfm.min_registered:
        raise NtpInputError(
            files[1],
            f"only {len(poses)} of its images are this scan's photos (need {TUNING.sfm.min_registered}; "
            "matched by file name)",
        )
    points = np.array([p.xyz for p in rec.points3D.values()]) if rec.num_points3D() else np.zeros((0, 3))
    return SfmResult(poses, points, sorted(wanted - set(poses)))
