"""The scan folder format (docs/design.md), read and written here: ``scan.toml`` naming the mesh, the
photos folder, the device file and, optionally, a poses file (camera-from-world 4x4 per photo name;
SfM is skipped with it) or a COLMAP model folder (``colmap = "sparse/0"``: SfM is skipped, the
model is aligned to the mesh), a marker board's layout (``board = "board.json"``, written by ``ntp
board``: the object stands on the printed board, which registers the photos; a poses file or a
COLMAP model still wins) and ``support_plane = false`` when the object does not stand on a flat
support at the mesh's lowest z (default true: SfM alignment uses the support, and the entries of
photos whose LEDs the support shadows are kept out of the network's range with those LEDs masked),
and ``support_light = false`` when the photos hold no light
the support (or the object itself) reflects onto the object (a renderer of Eq. 1's direct light
alone: the refinement then leaves it out; default: as ``support_plane``).

Every problem is a one-line ``NtpInputError`` naming the file; photos that cannot be read are not
errors but are left out by photo selection, each named on stderr. A mesh whose size is implausible
for the scanner (``check_mesh_size``: a mesh in millimetres reads 1000x too large) is refused. The
pipeline never writes into a scan folder; a virtual scanner creates one with ``write_scan_toml``.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..io.atomic import write_text_atomic
from ..io.errors import NtpInputError
from ..io.images import decode
from ..io.input_file import MAX_BYTES, regular_file
from ..io.mesh import Mesh
from ..io.progress import warn
from ..io.toml_file import check_keys, read_toml
from .board import Board, read_board
from .device_file import load_scanner
from .scanner import Scanner

# scan.toml's keys
SCAN_KEYS = (
    "mesh",
    "photos",
    "device",
    "poses",
    "colmap",
    "board",
    "support_plane",
    "support_light",
    "mesh_accuracy_mm",
)
PHOTO_SUFFIXES = (".png", ".jpg", ".jpeg")
# pixel formats a photo may hold: the camera's 8-bit codes, or them in a 16-bit file
PHOTO_FORMATS = ("uint8", "uint16")
# a plausible object is this many times the valid volume's largest edge across (1.5 mm to 3 m for
# the paper's 15 cm volume); outside it the mesh is almost surely in another unit than metres
MESH_SIZE_RANGE = (0.01, 20.0)
_UNITS = (("millimetres", 1e-3), ("centimetres", 1e-2), ("inches", 0.0254), ("kilometres", 1e3))


@dataclass
class Scan:
    """A scan folder as read: paths, the scanner that took it, its photos and optional poses."""

    folder: Path
    mesh_path: Path
    photos_dir: Path
    scanner: Scanner
    photo_paths: list[Path]
    poses: dict[str, np.ndarray] | None = None
    colmap: Path | None = None  # a COLMAP model folder to use instead of running SfM
    support_plane: bool = True  # the object stands on a flat support at the mesh's lowest z
    support_light: bool = True  # the photos hold the light the support (and the object) reflect onto it
    board: Board | None = None  # the marker board the object stands on (registration uses it)
    board_path: Path | None = None
    # the mesh's stated accuracy (1 sigma of its surface's error, metres: a shape scanner's spec), or None
    mesh_accuracy_m: float | None = None

    @property
    def input_folders(self) -> tuple[Path, ...]:
        """The folders this scan reads from (ntp never writes into them)."""
        return (self.folder,) if self.colmap is None else (self.folder, self.colmap)


def _required_path(folder: Path, table: dict, key: str, toml: Path) -> Path:
    path = _path(folder, table, key, toml)
    if path is None:
        raise NtpInputError(toml, f"key '{key}' missing")
    return path


def _path(folder: Path, table: dict, key: str, toml: Path) -> Path | None:
    """``key``'s path, relative to the scan folder, which must exist; None when the key is absent."""
    value = table.get(key)
    if value is None:
        return None
    if not isinstance(value, str) or not value:
        raise NtpInputError(toml, f"key '{key}': expected a path string, got {value!r}")
    p = (folder / value).resolve()
    if not p.exists():
        raise NtpInputError(toml, f"key '{key}': {value} does not exist")
    return p


def load_poses(path: Path) -> dict[str, np.ndarray]:
    """``{"photo name": 4x4 camera-from-world}``; each must be a finite rigid transform."""
    regular_file(path, MAX_BYTES["poses"])
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as err:  # unreadable, not UTF-8, not JSON
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


def load_scan(
    folder: str | Path,
    poses_file: str | Path | None = None,
    device_file: str | Path | None = None,
    colmap: str | Path | None = None,
) -> Scan:
    """Read ``folder/scan.toml`` and what it names. ``poses_file`` overrides its poses file,
    ``device_file`` the device file it names (e.g. a recalibration), ``colmap`` its COLMAP model."""
    folder = Path(folder)
    toml = folder / "scan.toml"
    table = read_toml(toml, "no scan.toml in the scan folder")
    check_keys(table, SCAN_KEYS, toml)
    mesh = _required_path(folder, table, "mesh", toml)
    photos = _required_path(folder, table, "photos", toml)
    if not photos.is_dir():
        raise NtpInputError(toml, f"key 'photos': {table['photos']} is not a folder")
    scanner = load_scanner(device_file or _required_path(folder, table, "device", toml))
    pose_path = Path(poses_file) if poses_file else _path(folder, table, "poses", toml)
    model = Path(colmap) if colmap else _path(folder, table, "colmap", toml)
    if pose_path and model:
        raise NtpInputError(model, "give either a poses file or a COLMAP model, not both")
    if model and not model.is_dir():
        raise NtpInputError(model, "a COLMAP model is a folder (cameras, images, points3D)")
    paths = _photo_paths(photos)
    support = table.get("support_plane", True)
    if not isinstance(support, bool):
        raise NtpInputError(toml, f"key 'support_plane': expected true or false, got {support!r}")
    light = table.get("support_light", support)
    if not isinstance(light, bool):
        raise NtpInputError(toml, f"key 'support_light': expected true or false, got {light!r}")
    if light and not support:
        raise NtpInputError(toml, "key 'support_light': true needs a support (support_plane = false)")
    poses = load_poses(pose_path) if pose_path else None
    board_path = _path(folder, table, "board", toml)
    board = read_board(board_path) if board_path else None
    if board is not None and not support:
        raise NtpInputError(toml, "key 'board': the object stands on the board, so it needs a support (support_plane)")
    accuracy = table.get("mesh_accuracy_mm")
    if accuracy is not None and (
        isinstance(accuracy, bool) or not isinstance(accuracy, int | float) or not 0 < accuracy < 100
    ):
        raise NtpInputError(
            toml, f"key 'mesh_accuracy_mm': expected the mesh's accuracy in millimetres (0 to 100), got {accuracy!r}"
        )
    return Scan(
        folder,
        mesh,
        photos,
        scanner,
        paths,
        poses,
        model,
        support_plane=support,
        support_light=light,
        board=board,
        board_path=board_path,
        mesh_accuracy_m=None if accuracy is None else 1e-3 * float(accuracy),
    )


def _photo_paths(photos: Path) -> list[Path]:
    """The photos folder's PNG/JPEG files, sorted by name; any other (not hidden) entry is named on
    stderr as skipped, so a photo in another format is not lost without a word. Entries that are
    not regular files stay in the list: photo selection names them as unreadable."""
    paths = []
    for p in sorted(photos.iterdir()):
        if p.suffix.lower() in PHOTO_SUFFIXES:
            paths.append(p)
        elif not p.name.startswith("."):
            warn(f"{p}: not a PNG/JPEG photo — skipped")
    if not paths:
        raise NtpInputError(photos, "no PNG/JPEG photos")
    return paths


def check_mesh_size(mesh: Mesh, scanner: Scanner, path: Path) -> None:
    """``NtpInputError`` naming the mesh file and the likely unit if the mesh's largest extent is
    implausible for ``scanner``'s valid volume (``MESH_SIZE_RANGE``)."""
    extent = float((mesh.vertices.max(0) - mesh.vertices.min(0)).max())
    edge = float(np.max(scanner.valid_size))
    if MESH_SIZE_RANGE[0] * edge <= extent <= MESH_SIZE_RANGE[1] * edge:
        return
    # the unit that makes the object the typical size, half the valid volume's edge
    unit = min(_UNITS, key=lambda u: abs(np.log(max(extent * u[1], 1e-30) / (0.5 * edge))))[0]
    raise NtpInputError(
        path,
        f"the mesh is {_length(extent)} across — is it in {unit}? (ntp reads meshes in metres; the "
        f"scanner's valid volume is {_length(edge)})",
    )


def _length(metres: float) -> str:
    """A length for a person: ``90 m``, ``4.2 cm``, ``0.09 mm``."""
    for unit, size in (("km", 1e3), ("m", 1.0), ("cm", 1e-2), ("mm", 1e-3)):
        if metres >= size or unit == "mm":
            return f"{metres / size:.3g} {unit}"
    raise AssertionError


def read_codes(path: Path, scanner: Scanner) -> np.ndarray:
    """The photo's 8-bit codes, uint8 ``(H, W, 3)``; ``NtpInputError`` naming the photo if it is
    unreadable, truncated or corrupt, not the scanner camera's size (checked before decoding), not
    RGB, not of integer pixels (the camera's codes are 8-bit; a 16-bit file is read as its 8-bit
    codes, rounded), or has pixels that are not opaque (the camera writes no alpha; a photo
    composited or cut out by another program no longer holds what the camera measured)."""
    img = decode(path, size=(scanner.width, scanner.height), eight_bit=True)
    channels = img.pixels.shape[2] - (img.alpha_channel >= 0)
    if channels < 3:
        kind = "grayscale" if channels == 1 else f"{channels}-channel"
        raise NtpInputError(path, f"a {kind} photo; the camera takes RGB")
    if img.format not in PHOTO_FORMATS:
        raise NtpInputError(
            path, f"holds {img.format} pixels (an HDR/EXR image under this name?); the camera's photos are 8-bit"
        )
    opaque = 255 if img.pixels.dtype == np.uint8 else 1.0
    if img.alpha_channel >= 0:
        clear = int((img.pixels[..., img.alpha_channel] < opaque).sum())
        if clear:
            raise NtpInputError(path, f"{clear} pixels are not opaque (alpha < 1); the camera's photos have no alpha")
    if img.pixels.dtype == np.uint8:
        return np.ascontiguousarray(img.pixels[..., :3])
    return np.round(img.pixels[..., :3] * 255.0).astype(np.uint8)


def read_photo(path: Path, scanner: Scanner) -> np.ndarray:
    """``read_codes`` as float32 ``(H, W, 3)`` (the codes 0-255, what the models read)."""
    return read_codes(path, scanner).astype(np.float32)


def write_scan_toml(
    folder: Path,
    mesh: str = "mesh.obj",
    photos: str = "photos",
    device: str = "device.toml",
    comments: tuple[str, ...] = (),
    support_light: bool = True,
    board: str | None = None,
    mesh_accuracy_mm: float | None = None,
) -> None:
    """Write ``folder/scan.toml`` naming the mesh, the photos folder and the device file (atomic),
    the marker board's layout file where there is one, the mesh's accuracy where it is known, and
    ``support_light = false`` where asked;
    ``comments`` become ``#`` lines around them, the first before, the rest after."""
    lines = [f"# {c}" for c in comments[:1]] + [f'mesh = "{mesh}"', f'photos = "{photos}"', f'device = "{device}"']
    if board is not None:
        lines.append(f'board = "{board}"  # the marker board the object stands on (ntp board)')
    if mesh_accuracy_mm is not None:
        lines.append(f"mesh_accuracy_mm = {mesh_accuracy_mm:.3g}  # the mesh's surface error, 1 sigma")
    if not support_light:
        lines.append("support_light = false  # the photos hold no light reflected by the support")
    lines += [f"# {c}" for c in comments[1:]] + [""]
    write_text_atomic(folder / "scan.toml", "\n".join(lines))
