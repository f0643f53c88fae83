"""Scan folders (DESIGN.md): ``scan.toml`` naming the mesh, the photos folder, the device file and,
optionally, a poses file (camera-from-world 4x4 per photo name; SfM is skipped with it) and
``support_plane = false`` when the object does not stand on a flat support at the mesh's lowest z
(default true: SfM alignment uses the support, and photos whose LEDs the support shadows are
skipped).

Every problem is a one-line ``NtpInputError`` naming the file; photos that cannot be read are not
errors but are listed (``Scan.unreadable``). Nothing in the scan folder is ever written.
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .device import Device
from .errors import NtpInputError
from .tomlio import read_toml

PHOTO_SUFFIXES = (".png", ".jpg", ".jpeg")


@dataclass
class Scan:
    folder: Path
    mesh_path: Path
    photos_dir: Path
    device: Device
    photo_paths: list[Path]
    poses: dict[str, np.ndarray] | None = None
    unreadable: list[str] = field(default_factory=list)
    support_plane: bool = True  # the object stands on a flat support at the mesh's lowest z


def _path(folder: Path, table: dict, key: str, toml: Path, required: bool = True) -> Path | None:
    value = table.get(key)
    if value is None:
        if required:
            raise NtpInputError(toml, f"key '{key}' missing")
        return None
    if not isinstance(value, str) or not value:
        raise NtpInputError(toml, f"key '{key}': expected a path string, got {value!r}")
    p = (folder / value).resolve()
    if not p.exists():
        raise NtpInputError(toml, f"key '{key}': {value} does not exist")
    return p


def load_poses(path: Path) -> dict[str, np.ndarray]:
    """``{"photo name": 4x4 camera-from-world}``; each must be a finite rigid transform."""
    try:
        data = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as err:
        raise NtpInputError(path, f"cannot read poses ({err})") from None
    if not isinstance(data, dict) or not data:
        raise NtpInputError(path, "expected an object mapping photo names to 4x4 matrices")
    poses = {}
    for name, m in data.items():
        try:
            a = np.asarray(m, dtype=np.float64)
        except (TypeError, ValueError):
            raise NtpInputError(path, f"pose of {name!r} is not numeric") from None
        if a.shape != (4, 4) or not np.isfinite(a).all():
            raise NtpInputError(path, f"pose of {name!r} must be a finite 4x4 matrix")
        R = a[:3, :3]
        if np.abs(R @ R.T - np.eye(3)).max() > 1e-4 or np.linalg.det(R) < 0:
            raise NtpInputError(path, f"pose of {name!r} is not a rotation plus translation")
        poses[name] = a
    return poses


def load_scan(folder: str | Path, poses_file: str | Path | None = None) -> Scan:
    folder = Path(folder)
    toml = folder / "scan.toml"
    table = read_toml(toml, "no scan.toml in the scan folder")
    mesh = _path(folder, table, "mesh", toml)
    photos = _path(folder, table, "photos", toml)
    if not photos.is_dir():
        raise NtpInputError(toml, f"key 'photos': {table['photos']} is not a folder")
    device = Device.load(_path(folder, table, "device", toml))
    pose_path = Path(poses_file) if poses_file else _path(folder, table, "poses", toml, required=False)
    paths = sorted(p for p in photos.iterdir() if p.suffix.lower() in PHOTO_SUFFIXES)
    if not paths:
        raise NtpInputError(photos, "no PNG/JPEG photos")
    support = table.get("support_plane", True)
    if not isinstance(support, bool):
        raise NtpInputError(toml, f"key 'support_plane': expected true or false, got {support!r}")
    return Scan(folder, mesh, photos, device, paths, load_poses(pose_path) if pose_path else None,
                support_plane=support)


def read_photo(path: Path, device: Device) -> np.ndarray | None:
    """8-bit codes ``(H, W, 3)`` float, or None if unreadable or not the device camera's size."""
    from .images import read_image

    try:
        img = read_image(path)
    except NtpInputError:
        return None
    if img.shape[:2] != (device.height, device.width) or img.shape[2] < 3:
        return None
    return np.round(img[..., :3] * 255.0)
