"""The device file: a scanner's calibration as TOML (``docs/device-format.md``; shipped ones in
``assets/devices/``). Reading validates every key and gives one-line errors naming the file and the
dotted key; writing is atomic and explicit (emitters as lists, the pattern inline).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import tomli_w

from ..io.assets import DEVICES_DIR
from ..io.atomic import write_text_atomic
from ..io.errors import NtpInputError
from ..io.toml_file import read_toml, unknown_key
from .pattern import checked_pattern, read_pattern_file, write_pattern_file
from .scanner import Scanner

DEFAULT_DEVICE = DEVICES_DIR / "ntp_led_32x16.toml"  # the paper's 32x16 LED array
EMITTER_KINDS = ("point", "linear", "area")
RESPONSES = ("linear", "gamma", "srgb")
# bounds of the file's counts, far beyond any real device, so a typo cannot allocate without limit:
MAX_SIDE = 65536  # camera pixels per side (the paper's camera: 2448x2048)
MAX_EMITTERS = 65536  # 128x the paper's 512 LEDs
MAX_QUADRATURE = 4096  # samples per emitter (quadrature columns x rows; the shipped devices use <= 16)
MAX_COUNT = 1 << 31  # any other count


class DeviceFileError(NtpInputError):
    """A malformed device calibration file."""


def load_scanner(path: str | Path | None = None) -> Scanner:
    """Read a device file (default: the paper's 32x16 LED array)."""
    path = Path(path) if path is not None else DEFAULT_DEVICE
    return _parse(read_toml(path, "no such device file", DeviceFileError), path)


def save_scanner(scanner: Scanner, path: str | Path) -> None:
    """Write ``scanner`` as a device file (explicit emitter lists, pattern inline; atomic)."""
    write_text_atomic(path, tomli_w.dumps(scanner_to_dict(scanner)))


def list_devices() -> list[Path]:
    """The device files shipped in ``assets/devices``."""
    return sorted(DEVICES_DIR.glob("*.toml"))


def shipped_device(file_name: str) -> Scanner:
    """A shipped device by file name, e.g. ``point_light.toml``."""
    path = DEVICES_DIR / file_name
    if not path.is_file():
        raise NtpInputError(path, "no such shipped device; see `ntp device --list`")
    return load_scanner(path)


def scanner_to_dict(scanner: Scanner) -> dict[str, Any]:
    """The device file's table for ``scanner`` (what ``save_scanner`` writes)."""
    s = scanner
    em: dict[str, Any] = {
        "kind": s.emitter_kind,
        "layout": "list",
        "positions": s.emitter_positions.tolist(),
        "normals": s.emitter_normals.tolist(),
        "axes": s.emitter_axes.tolist(),
        "size": s.emitter_size.tolist(),
        "quadrature": list(s.quadrature),
        "color_matrix": s.color_matrix.tolist(),
        "angular": {"kind": s.angular_kind, "exponent": s.angular_exponent}
        if s.angular_kind == "cosine"
        else {"kind": "table", "angles_deg": s.angular_table[:, 0].tolist(), "values": s.angular_table[:, 1].tolist()},
    }
    if s.grid_shape:
        em["grid_shape"] = list(s.grid_shape)
    cam = {
        "width": s.width,
        "height": s.height,
        "fx": float(s.K[0, 0]),
        "fy": float(s.K[1, 1]),
        "cx": float(s.K[0, 2]),
        "cy": float(s.K[1, 2]),
        "distortion": s.distortion.tolist(),
        "response": s.response,
        "gamma": s.gamma,
        "gain": s.gain,
        "max_exposure": s.max_exposure,
    }
    return {
        "name": s.name,
        "description": s.description,
        "camera": cam,
        "emitters": em,
        "valid_volume": {
            "center": s.valid_center.tolist(),
            "size": s.valid_size.tolist(),
            "axes": s.valid_axes.tolist(),
        },
        "pattern": s.pattern.tolist(),
    }


def write_pattern(device_file: Path, pattern: np.ndarray) -> Path:
    """Store ``pattern`` (8-bit quantised) as ``<device>_pattern.csv`` beside ``device_file`` and make
    the file's ``pattern`` key name it. A file that already names that CSV is left untouched (its
    comments kept); otherwise the key is rewritten through the parsed table. Returns the CSV's path."""
    csv_path = device_file.with_name(device_file.stem + "_pattern.csv")
    table = read_toml(device_file, "no such device file", DeviceFileError)
    # the file must be valid, apart from the pattern being replaced, before anything is written
    emitters = _parse({**table, "pattern": "full_on"}, device_file).num_emitters
    checked_pattern(np.asarray(pattern, dtype=np.float64), emitters, csv_path)
    write_pattern_file(csv_path, pattern)
    if table.get("pattern") != csv_path.name:
        table["pattern"] = csv_path.name
        write_text_atomic(device_file, tomli_w.dumps(table))
    load_scanner(device_file)  # must still parse
    return csv_path


class _Reader:
    """Typed access to nested TOML tables; every error names the file and the dotted key."""

    def __init__(self, path: Path):
        self.path = path

    def fail(self, key: str, problem: str) -> DeviceFileError:
        return DeviceFileError(self.path, f"key '{key}': {problem}")

    def table(self, data: dict, key: str, required: bool = True) -> dict:
        value = _dig(data, key)
        if value is None and not required:
            return {}
        if not isinstance(value, dict):
            raise self.fail(key, "missing table" if value is None else "must be a table")
        return value

    def number(self, data: dict, key: str, default: float | None = None, positive=False) -> float:
        value = _dig(data, key)
        if value is None:
            if default is None:
                raise self.fail(key, "missing")
            return float(default)
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise self.fail(key, f"expected a number, got {value!r}")
        if positive and value <= 0:
            raise self.fail(key, f"must be > 0, got {value!r}")
        return float(value)

    def integer(self, data: dict, key: str, default: int | None = None, maximum: int = MAX_COUNT) -> int:
        value = _dig(data, key)
        if value is None:
            if default is None:
                raise self.fail(key, "missing")
            return default
        if isinstance(value, bool) or not isinstance(value, int) or value <= 0:
            raise self.fail(key, f"expected a positive integer, got {value!r}")
        if value > maximum:
            raise self.fail(key, f"{value} is more than {maximum}")
        return value

    def counts(self, data: dict, key: str, maximum: int) -> tuple[int, int]:
        """Two positive integers (e.g. ``[columns, rows]``) whose product is at most ``maximum``."""
        arr = self.array(data, key, (2,))
        if (arr < 1).any() or (arr != np.round(arr)).any():
            raise self.fail(key, "expected two positive integers")
        if arr[0] * arr[1] > maximum:
            raise self.fail(key, f"{arr[0]:g} x {arr[1]:g} is more than {maximum}")
        return int(arr[0]), int(arr[1])

    def choice(self, data: dict, key: str, options: tuple[str, ...], default: str | None = None) -> str:
        value = _dig(data, key)
        if value is None:
            if default is None:
                raise self.fail(key, "missing")
            return default
        if value not in options:
            raise self.fail(key, f"expected one of {', '.join(options)}, got {value!r}")
        return value

    def array(self, data: dict, key: str, shape: tuple[int | None, ...], default=None) -> np.ndarray:
        value = _dig(data, key)
        if value is None:
            if default is None:
                raise self.fail(key, "missing")
            return np.asarray(default, dtype=np.float64)
        try:
            arr = np.asarray(value, dtype=np.float64)
        except (TypeError, ValueError):
            raise self.fail(key, "expected numbers") from None
        if arr.ndim != len(shape) or any(s is not None and s != a for s, a in zip(shape, arr.shape)):
            want = "x".join("N" if s is None else str(s) for s in shape)
            raise self.fail(key, f"expected shape {want}, got {'x'.join(map(str, arr.shape)) or 'scalar'}")
        if not np.isfinite(arr).all():
            raise self.fail(key, "contains non-finite values")
        return arr

    def unit(self, data: dict, key: str, shape, default=None) -> np.ndarray:
        arr = self.array(data, key, shape, default)
        norm = np.linalg.norm(arr, axis=-1, keepdims=True)
        if (norm < 1e-9).any():
            raise self.fail(key, "zero-length direction")
        return arr / norm


def _dig(data: dict, dotted: str):
    node: Any = data
    for part in dotted.split("."):
        if not isinstance(node, dict) or part not in node:
            return None
        node = node[part]
    return node


_KNOWN_KEYS = {
    "": {"name", "description", "camera", "emitters", "valid_volume", "pattern"},
    "camera": {"width", "height", "fx", "fy", "cx", "cy", "distortion", "response", "gamma", "gain", "max_exposure"},
    "emitters": {
        "kind",
        "layout",
        "count",
        "pitch",
        "center",
        "axis",
        "v_axis",
        "normal",
        "positions",
        "normals",
        "axes",
        "size",
        "quadrature",
        "color_matrix",
        "angular",
        "grid_shape",
    },
    "emitters.angular": {"kind", "exponent", "angles_deg", "values"},
    "valid_volume": {"center", "size", "axes"},
}


def _parse(data: dict, path: Path) -> Scanner:
    r = _Reader(path)
    _check_known_keys(data, r)
    name = data.get("name")
    if not isinstance(name, str) or not name:
        raise r.fail("name", "missing or not a string")
    camera = _parse_camera(data, r)
    emitters = _parse_emitters(data, r)
    L = len(emitters["emitter_positions"])
    return Scanner(
        name=name,
        description=str(data.get("description", "")),
        **camera,
        **emitters,
        **_parse_valid_volume(data, r),
        pattern=_parse_pattern(data.get("pattern", "full_on"), L, path, r),
        source=path,
    )


def _check_known_keys(data: dict, r: _Reader) -> None:
    for prefix, known in _KNOWN_KEYS.items():
        table = data if not prefix else _dig(data, prefix)
        if isinstance(table, dict):
            for key in table:
                if key not in known:
                    raise r.fail(f"{prefix}.{key}" if prefix else key, unknown_key(key, known))


def _parse_camera(data: dict, r: _Reader) -> dict[str, Any]:
    r.table(data, "camera")  # must exist; its keys are read by dotted name below
    width, height = (
        r.integer(data, "camera.width", maximum=MAX_SIDE),
        r.integer(data, "camera.height", maximum=MAX_SIDE),
    )
    fx = r.number(data, "camera.fx", positive=True)
    fy = r.number(data, "camera.fy", default=fx, positive=True)
    cx, cy = r.number(data, "camera.cx", (width - 1) / 2), r.number(data, "camera.cy", (height - 1) / 2)
    max_exposure = r.number(data, "camera.max_exposure", 4.0, positive=True)
    if max_exposure < 1:
        raise r.fail("camera.max_exposure", "must be >= 1 (times the full-on pattern's exposure)")
    return {
        "width": width,
        "height": height,
        "K": np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1.0]]),
        "distortion": r.array(data, "camera.distortion", (5,), default=np.zeros(5)),
        "response": r.choice(data, "camera.response", RESPONSES, default="linear"),
        "gamma": r.number(data, "camera.gamma", 2.2, positive=True),
        "gain": r.number(data, "camera.gain", 1.0, positive=True),
        "max_exposure": max_exposure,
    }


def _emitter_grid(data: dict, r: _Reader) -> tuple[np.ndarray, np.ndarray, np.ndarray, tuple[int, int]]:
    """Positions, normals, axes of a regular grid (row-major: index = row * columns + column)."""
    cols, rows = r.counts(data, "emitters.count", MAX_EMITTERS)
    pitch = r.array(data, "emitters.pitch", (2,))
    center = r.array(data, "emitters.center", (3,))
    u = r.unit(data, "emitters.axis", (3,))
    v = r.unit(data, "emitters.v_axis", (3,))
    if abs(float(u @ v)) > 1e-6:
        raise r.fail("emitters.v_axis", "must be orthogonal to emitters.axis")
    ci = (np.arange(cols) - (cols - 1) / 2) * pitch[0]
    ri = (np.arange(rows) - (rows - 1) / 2) * pitch[1]
    positions = (center + ri[:, None, None] * v + ci[None, :, None] * u).reshape(-1, 3)
    L = cols * rows
    normals = np.tile(r.unit(data, "emitters.normal", (3,), default=np.cross(u, v)), (L, 1))
    return positions, normals, np.tile(u, (L, 1)), (cols, rows)


def _emitter_list(data: dict, r: _Reader) -> tuple[np.ndarray, np.ndarray, np.ndarray, tuple[int, int] | None]:
    """Positions, normals, axes listed one per emitter (and an optional grid shape)."""
    positions = r.array(data, "emitters.positions", (None, 3))
    L = len(positions)
    if not 0 < L <= MAX_EMITTERS:
        raise r.fail("emitters.positions", f"{L} emitters: need 1 to {MAX_EMITTERS}")
    normals = r.unit(data, "emitters.normals", (L, 3))
    axes = r.unit(data, "emitters.axes", (L, 3))
    grid_shape = None
    if _dig(data, "emitters.grid_shape") is not None:
        grid_shape = r.counts(data, "emitters.grid_shape", MAX_EMITTERS)
        if grid_shape[0] * grid_shape[1] != L:
            raise r.fail("emitters.grid_shape", f"columns x rows must equal the {L} emitters")
    return positions, normals, axes, grid_shape


def _parse_emitters(data: dict, r: _Reader) -> dict[str, Any]:
    r.table(data, "emitters")  # must exist; its keys are read by dotted name below
    kind = r.choice(data, "emitters.kind", EMITTER_KINDS)
    layout = r.choice(data, "emitters.layout", ("grid", "list"))
    positions, normals, axes, grid_shape = (_emitter_grid if layout == "grid" else _emitter_list)(data, r)
    if (np.abs((normals * axes).sum(-1)) > 1e-6).any():
        raise r.fail(
            "emitters.axes" if layout == "list" else "emitters.normal", "emitter axis must be orthogonal to its normal"
        )
    size = r.array(data, "emitters.size", (2,), default=np.zeros(2))
    if (size < 0).any():
        raise r.fail("emitters.size", "must be >= 0")
    if kind != "point" and size[0] <= 0 or kind == "area" and size[1] <= 0:
        raise r.fail("emitters.size", f"a {kind} emitter needs a positive size")
    quad = (1, 1)
    if _dig(data, "emitters.quadrature") is not None:
        quad = r.counts(data, "emitters.quadrature", MAX_QUADRATURE)
    return {
        "emitter_kind": kind,
        "emitter_positions": positions,
        "emitter_normals": normals,
        "emitter_axes": axes,
        "emitter_size": size,
        "quadrature": quad,
        "grid_shape": grid_shape,
        "color_matrix": r.array(data, "emitters.color_matrix", (3, 3), default=np.eye(3)),
        **_parse_angular(data, r),
    }


def _parse_angular(data: dict, r: _Reader) -> dict[str, Any]:
    ang = r.table(data, "emitters.angular", required=False)
    kind = r.choice(data, "emitters.angular.kind", ("cosine", "table"), default="cosine") if ang else "cosine"
    exponent = r.number(data, "emitters.angular.exponent", 1.0) if ang else 1.0
    if exponent < 0:
        raise r.fail("emitters.angular.exponent", "must be >= 0")
    table = np.zeros((0, 2))
    if kind == "table":
        a = r.array(data, "emitters.angular.angles_deg", (None,))
        vals = r.array(data, "emitters.angular.values", (len(a),))
        if len(a) < 2 or (np.diff(a) <= 0).any() or a[0] < 0 or a[-1] > 90 or (vals < 0).any():
            raise r.fail("emitters.angular", "table needs >= 2 increasing angles in [0, 90] and values >= 0")
        table = np.stack([a, vals], -1)
    return {"angular_kind": kind, "angular_exponent": exponent, "angular_table": table}


def _parse_valid_volume(data: dict, r: _Reader) -> dict[str, Any]:
    r.table(data, "valid_volume")  # must exist; its keys are read by dotted name below
    valid_size = r.array(data, "valid_volume.size", (3,))
    if (valid_size <= 0).any():
        raise r.fail("valid_volume.size", "must be > 0")
    valid_axes = r.unit(data, "valid_volume.axes", (3, 3), default=np.eye(3))
    if np.abs(valid_axes @ valid_axes.T - np.eye(3)).max() > 1e-5:
        raise r.fail("valid_volume.axes", "rows must be orthonormal")
    return {
        "valid_center": r.array(data, "valid_volume.center", (3,)),
        "valid_size": valid_size,
        "valid_axes": valid_axes,
    }


def _parse_pattern(value: Any, L: int, path: Path, r: _Reader) -> np.ndarray:
    """``pattern``: "full_on", a path (CSV/NPY, relative to the TOML) or an inline (L, 3) list."""
    if isinstance(value, str) and value == "full_on":
        return np.ones((L, 3))
    try:
        if isinstance(value, str):
            return read_pattern_file((path.parent / value).resolve(), L)
        try:
            arr = np.asarray(value, dtype=np.float64)
        except (TypeError, ValueError):
            raise r.fail("pattern", "expected numbers") from None
        return checked_pattern(arr, L, path)
    except DeviceFileError:
        raise
    except NtpInputError as err:  # the pattern file's problem, reported as this key's
        where = f"pattern file {value!r}: " if isinstance(value, str) else ""
        raise r.fail("pattern", where + err.problem) from None
