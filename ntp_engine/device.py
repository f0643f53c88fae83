"""Scanner calibration: camera, emitters, valid volume and lighting pattern (a TOML file).

Convention: everything is in the camera space of the scanner (OpenCV: x right, y down, z forward;
metres). An emitter ``l`` has a centre ``emitter_positions[l]``, an outward unit normal
``emitter_normals[l]`` and an in-plane unit axis ``emitter_axes[l]`` (along its length for a
linear light, its width for an area light). ``I(l) = 1`` means: seen from afar, the emitter is a
point source of unit on-axis radiant intensity; an extended emitter spreads that uniformly over its
length/area and is integrated by Gauss-Legendre quadrature (``emitter_samples``). The angular
distribution Psi(cos) multiplies the intensity towards a direction at angle theta from the normal
(cosine lobe ``cos^k`` by default, or a measured table).

File format: see ``docs/device-format.md``; the shipped devices live in ``assets/devices/``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import tomli_w
import torch
from torch import Tensor

from .atomic import write_text_atomic
from .errors import NtpInputError
from .tomlio import read_toml

# the repository's assets/ (source checkout), else the copy a wheel build puts inside the package
ASSETS = next((p for p in (Path(__file__).resolve().parent.parent / "assets", Path(__file__).resolve().parent / "assets")
               if p.is_dir()), Path(__file__).resolve().parent.parent / "assets")
DEVICES_DIR = ASSETS / "devices"
DEFAULT_DEVICE = DEVICES_DIR / "ntp_led_32x16.toml"
EMITTER_KINDS = ("point", "linear", "area")
RESPONSES = ("linear", "gamma", "srgb")


class DeviceFileError(NtpInputError):
    """A malformed device calibration file."""


def auto_exposure(mean_drive: float | Tensor, gain: float | Tensor, full_on_drive: float | Tensor,
                  max_exposure: float | Tensor) -> float | Tensor:
    """Linear pixel value per unit of B: ``gain / max(mean_drive, full_on_drive / max_exposure)``.

    Convention: ``mean_drive`` is the mean of ``pattern @ M^T`` over emitters and channels,
    ``full_on_drive`` the same for the full-on pattern (``gain`` is calibrated for it). The camera's
    exposure follows the pattern's mean drive (auto-exposure), so a dimmer pattern is not penalised,
    but only up to ``max_exposure`` times the full-on exposure (a hand-held capture's motion-blur
    limit): a pattern dimmer than ``full_on_drive / max_exposure`` gives darker photos."""
    floor = full_on_drive / max_exposure
    if isinstance(mean_drive, Tensor):
        return gain / torch.maximum(mean_drive, torch.as_tensor(floor, dtype=mean_drive.dtype,
                                                                device=mean_drive.device)).clamp_min(1e-12)
    return gain / max(float(mean_drive), float(floor), 1e-12)


@dataclass
class Device:
    """A scanner. Arrays are float64 numpy; ``torch_arrays`` gives tensors for computation."""

    name: str
    width: int
    height: int
    K: np.ndarray  # (3, 3) pixel intrinsics
    distortion: np.ndarray  # (5,) OpenCV k1 k2 p1 p2 k3
    emitter_kind: str  # point | linear | area
    emitter_positions: np.ndarray  # (L, 3) centres, camera space, m
    emitter_normals: np.ndarray  # (L, 3) unit
    emitter_axes: np.ndarray  # (L, 3) unit, orthogonal to the normal
    emitter_size: np.ndarray  # (2,) extent along axis and along normal x axis, m
    quadrature: tuple[int, int]  # Gauss-Legendre orders along the two emitter axes
    angular_kind: str  # cosine | table
    angular_exponent: float  # for cosine: Psi = cos^k
    angular_table: np.ndarray  # (T, 2) angle in degrees, relative intensity (for table)
    color_matrix: np.ndarray  # (3, 3): camera channel c sees sum_k M[c, k] * LED channel k
    pattern: np.ndarray  # (L, 3) per-emitter RGB drive in [0, 1]
    valid_center: np.ndarray  # (3,) camera space
    valid_size: np.ndarray  # (3,) box edge lengths along valid_axes rows
    valid_axes: np.ndarray  # (3, 3) rows: the box's axes in camera space
    response: str = "linear"  # 8-bit camera response: linear | gamma | srgb
    gamma: float = 2.2
    gain: float = 1.0  # linear pixel value (1 = code 255) per unit of B under the full-on pattern
    max_exposure: float = 4.0  # longest exposure, x the full-on one (hand-held motion-blur limit)
    grid_shape: tuple[int, int] | None = None  # (columns, rows) when emitters form a grid
    description: str = ""
    source: Path | None = field(default=None, compare=False)

    # ---------------------------------------------------------------- derived quantities
    @property
    def num_emitters(self) -> int:
        return int(self.emitter_positions.shape[0])

    @property
    def fx(self) -> float:
        return float(self.K[0, 0])

    def effective_pattern(self, pattern: np.ndarray | Tensor | None = None) -> np.ndarray | Tensor:
        """Per-emitter, per-camera-channel drive ``(L, 3)``: pattern @ color_matrix^T."""
        p = self.pattern if pattern is None else pattern
        if isinstance(p, Tensor):
            return p @ torch.as_tensor(self.color_matrix, dtype=p.dtype, device=p.device).T
        return p @ self.color_matrix.T

    def exposure(self, pattern: np.ndarray | Tensor | None = None) -> float | Tensor:
        """Linear pixel value per unit of B under ``pattern`` (see ``auto_exposure``)."""
        p_eff = self.effective_pattern(pattern)
        return auto_exposure(p_eff.mean(), self.gain, float(self.color_matrix.sum(1).mean()), self.max_exposure)

    def emitter_samples(self, dtype=torch.float32, device=None) -> tuple[Tensor, Tensor]:
        """Quadrature points ``(L, Q, 3)`` on each emitter and weights ``(L, Q)`` summing to 1."""
        L = self.num_emitters
        pos = torch.as_tensor(self.emitter_positions, dtype=torch.float64)
        if self.emitter_kind == "point":
            pts, w = pos[:, None, :], torch.ones(L, 1, dtype=torch.float64)
        else:
            nu, nv = self.quadrature if self.emitter_kind == "area" else (self.quadrature[0], 1)
            xu, wu = np.polynomial.legendre.leggauss(nu)
            if self.emitter_kind == "area":
                xv, wv = np.polynomial.legendre.leggauss(nv)
            else:
                xv, wv = np.zeros(1), np.full(1, 2.0)
            u = torch.as_tensor(self.emitter_axes, dtype=torch.float64)
            n = torch.as_tensor(self.emitter_normals, dtype=torch.float64)
            v = torch.linalg.cross(n, u, dim=-1)
            su, sv = 0.5 * float(self.emitter_size[0]), 0.5 * float(self.emitter_size[1])
            cu = torch.as_tensor(np.repeat(xu, len(xv)) * su)
            cv = torch.as_tensor(np.tile(xv, len(xu)) * sv)
            pts = pos[:, None, :] + cu[None, :, None] * u[:, None, :] + cv[None, :, None] * v[:, None, :]
            w = torch.as_tensor(np.outer(wu, wv).reshape(-1) / 4.0).expand(L, -1)
        return pts.to(dtype=dtype, device=device), w.to(dtype=dtype, device=device).contiguous()

    def psi(self, cos_theta: Tensor) -> Tensor:
        """Angular distribution Psi for the cosine of the angle from the emitter normal; 0 behind."""
        c = cos_theta.clamp(0.0, 1.0)
        if self.angular_kind == "cosine":
            if self.angular_exponent == 1.0:  # the common Lambertian LED: no pow on the hot path
                return c
            return torch.where(cos_theta > 0, c**self.angular_exponent, torch.zeros_like(c))
        table = torch.as_tensor(self.angular_table, dtype=cos_theta.dtype, device=cos_theta.device)
        ang = torch.rad2deg(torch.acos(c))
        a, val = table[:, 0].contiguous(), table[:, 1].contiguous()
        idx = torch.searchsorted(a, ang.reshape(-1).contiguous()).reshape(ang.shape).clamp(1, len(a) - 1)
        a0, a1, v0, v1 = a[idx - 1], a[idx], val[idx - 1], val[idx]
        w = ((ang - a0) / (a1 - a0)).clamp(0.0, 1.0)
        out = v0 + w * (v1 - v0)
        return torch.where((cos_theta > 0) & (ang <= a[-1]), out, torch.zeros_like(out))

    def in_valid_volume(self, points: Tensor) -> Tensor:
        """Boolean ``(...)``: camera-space ``points (..., 3)`` inside the valid box (edges included)."""
        axes = torch.as_tensor(self.valid_axes, dtype=points.dtype, device=points.device)
        c = torch.as_tensor(self.valid_center, dtype=points.dtype, device=points.device)
        half = torch.as_tensor(self.valid_size / 2, dtype=points.dtype, device=points.device)
        local = (points - c) @ axes.T
        return (local.abs() <= half * (1 + 1e-9)).all(-1)

    def encode(self, linear: Tensor) -> Tensor:
        """Linear pixel value (1 = white) to 8-bit code value in [0, 255] (float, not rounded)."""
        x = linear.clamp(0.0, 1.0)
        if self.response == "gamma":
            x = x ** (1.0 / self.gamma)
        elif self.response == "srgb":
            x = torch.where(x <= 0.0031308, 12.92 * x, 1.055 * x.clamp_min(1e-12) ** (1 / 2.4) - 0.055)
        return 255.0 * x

    def decode(self, code: Tensor) -> Tensor:
        """8-bit code value [0, 255] back to a linear pixel value in [0, 1]."""
        x = (code / 255.0).clamp(0.0, 1.0)
        if self.response == "gamma":
            return x**self.gamma
        if self.response == "srgb":
            return torch.where(x <= 0.04045, x / 12.92, ((x + 0.055) / 1.055) ** 2.4)
        return x

    def project(self, points: Tensor) -> Tensor:
        """Camera-space ``points (..., 3)`` to pixel coordinates ``(..., 2)`` with OpenCV
        distortion (pixel centres at integer coordinates). Points with z <= 0 give NaN."""
        K = torch.as_tensor(self.K, dtype=points.dtype, device=points.device)
        k1, k2, p1, p2, k3 = (float(v) for v in self.distortion)
        z = points[..., 2]
        z = torch.where(z > 0, z, torch.full_like(z, float("nan")))
        x, y = points[..., 0] / z, points[..., 1] / z
        r2 = x * x + y * y
        radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
        xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
        yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
        return torch.stack([K[0, 0] * xd + K[0, 1] * yd + K[0, 2], K[1, 1] * yd + K[1, 2]], -1)

    def summary(self) -> str:
        L = self.num_emitters
        grid = f" ({self.grid_shape[0]}x{self.grid_shape[1]} grid)" if self.grid_shape else ""
        span = self.emitter_positions.max(0) - self.emitter_positions.min(0)
        return "\n".join(
            [
                f"device   {self.name}" + (f" — {self.description}" if self.description else ""),
                f"camera   {self.width}x{self.height} px, fx={self.K[0, 0]:.1f} fy={self.K[1, 1]:.1f} "
                f"cx={self.K[0, 2]:.1f} cy={self.K[1, 2]:.1f}, response={self.response}, gain={self.gain:g}",
                f"emitters {L} {self.emitter_kind}{grid}, extent {span[0] * 100:.1f}x{span[1] * 100:.1f}"
                f"x{span[2] * 100:.1f} cm, size {self.emitter_size[0] * 100:.1f}x{self.emitter_size[1] * 100:.1f} cm, "
                f"Psi={self.angular_kind}" + (f"^{self.angular_exponent:g}" if self.angular_kind == "cosine" else ""),
                f"pattern  mean RGB {np.round(self.pattern.mean(0), 3).tolist()}, "
                f"valid volume {np.round(self.valid_size * 100, 1).tolist()} cm at "
                f"{np.round(self.valid_center, 4).tolist()} m",
            ]
        )

    # ---------------------------------------------------------------- file I/O
    @classmethod
    def load(cls, path: str | Path | None = None) -> "Device":
        """Read a calibration TOML (default: the paper's 32x16 LED array)."""
        path = Path(path) if path is not None else DEFAULT_DEVICE
        return _parse(read_toml(path, "no such device file", DeviceFileError), path)

    def save(self, path: str | Path) -> None:
        """Write this device as TOML (explicit emitter lists; atomic)."""
        write_text_atomic(path, tomli_w.dumps(self.to_dict()))

    def to_dict(self) -> dict[str, Any]:
        em: dict[str, Any] = {
            "kind": self.emitter_kind,
            "layout": "list",
            "positions": self.emitter_positions.tolist(),
            "normals": self.emitter_normals.tolist(),
            "axes": self.emitter_axes.tolist(),
            "size": self.emitter_size.tolist(),
            "quadrature": list(self.quadrature),
            "color_matrix": self.color_matrix.tolist(),
            "angular": {"kind": self.angular_kind, "exponent": self.angular_exponent}
            if self.angular_kind == "cosine"
            else {"kind": "table", "angles_deg": self.angular_table[:, 0].tolist(),
                  "values": self.angular_table[:, 1].tolist()},
        }
        if self.grid_shape:
            em["grid_shape"] = list(self.grid_shape)
        cam = {
            "width": self.width, "height": self.height,
            "fx": float(self.K[0, 0]), "fy": float(self.K[1, 1]),
            "cx": float(self.K[0, 2]), "cy": float(self.K[1, 2]),
            "distortion": self.distortion.tolist(),
            "response": self.response, "gamma": self.gamma, "gain": self.gain,
            "max_exposure": self.max_exposure,
        }
        return {
            "name": self.name,
            "description": self.description,
            "camera": cam,
            "emitters": em,
            "valid_volume": {"center": self.valid_center.tolist(), "size": self.valid_size.tolist(),
                             "axes": self.valid_axes.tolist()},
            "pattern": self.pattern.tolist(),
        }


# -------------------------------------------------------------------- parsing helpers
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

    def integer(self, data: dict, key: str, default: int | None = None) -> int:
        value = _dig(data, key)
        if value is None:
            if default is None:
                raise self.fail(key, "missing")
            return default
        if isinstance(value, bool) or not isinstance(value, int) or value <= 0:
            raise self.fail(key, f"expected a positive integer, got {value!r}")
        return value

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
    "camera": {"width", "height", "fx", "fy", "cx", "cy", "distortion", "response", "gamma", "gain",
               "max_exposure"},
    "emitters": {"kind", "layout", "count", "pitch", "center", "axis", "v_axis", "normal", "positions",
                 "normals", "axes", "size", "quadrature", "color_matrix", "angular", "grid_shape"},
    "emitters.angular": {"kind", "exponent", "angles_deg", "values"},
    "valid_volume": {"center", "size", "axes"},
}


def _parse(data: dict, path: Path) -> Device:
    r = _Reader(path)
    for prefix, known in _KNOWN_KEYS.items():
        table = data if not prefix else _dig(data, prefix)
        if isinstance(table, dict):
            for key in table:
                if key not in known:
                    dotted = f"{prefix}.{key}" if prefix else key
                    raise r.fail(dotted, "unknown key")

    name = data.get("name")
    if not isinstance(name, str) or not name:
        raise r.fail("name", "missing or not a string")
    r.table(data, "camera")  # must exist; its keys are read by dotted name below
    width, height = r.integer(data, "camera.width"), r.integer(data, "camera.height")
    fx = r.number(data, "camera.fx", positive=True)
    fy = r.number(data, "camera.fy", default=fx, positive=True)
    K = np.array([[fx, 0, r.number(data, "camera.cx", (width - 1) / 2)], [0, fy, r.number(data, "camera.cy", (height - 1) / 2)],
                  [0, 0, 1.0]])
    distortion = r.array(data, "camera.distortion", (5,), default=np.zeros(5))
    response = r.choice(data, "camera.response", RESPONSES, default="linear")
    gamma = r.number(data, "camera.gamma", 2.2, positive=True)
    gain = r.number(data, "camera.gain", 1.0, positive=True)
    max_exposure = r.number(data, "camera.max_exposure", 4.0, positive=True)
    if max_exposure < 1:
        raise r.fail("camera.max_exposure", "must be >= 1 (times the full-on pattern's exposure)")

    r.table(data, "emitters")  # must exist; its keys are read by dotted name below
    kind = r.choice(data, "emitters.kind", EMITTER_KINDS)
    layout = r.choice(data, "emitters.layout", ("grid", "list"))
    grid_shape = None
    if layout == "grid":
        count = r.array(data, "emitters.count", (2,))
        if (count < 1).any() or (count != np.round(count)).any():
            raise r.fail("emitters.count", "expected two positive integers [columns, rows]")
        cols, rows = int(count[0]), int(count[1])
        pitch = r.array(data, "emitters.pitch", (2,))
        center = r.array(data, "emitters.center", (3,))
        u = r.unit(data, "emitters.axis", (3,))
        v = r.unit(data, "emitters.v_axis", (3,))
        if abs(float(u @ v)) > 1e-6:
            raise r.fail("emitters.v_axis", "must be orthogonal to emitters.axis")
        ci = (np.arange(cols) - (cols - 1) / 2) * pitch[0]
        ri = (np.arange(rows) - (rows - 1) / 2) * pitch[1]
        # row-major: emitter index = row * cols + col
        positions = center + ri[:, None, None] * v + ci[None, :, None] * u
        positions = positions.reshape(-1, 3)
        L = cols * rows
        normal_default = np.cross(u, v)
        normals = np.tile(r.unit(data, "emitters.normal", (3,), default=normal_default), (L, 1))
        axes = np.tile(u, (L, 1))
        grid_shape = (cols, rows)
    else:
        positions = r.array(data, "emitters.positions", (None, 3))
        L = len(positions)
        if L == 0:
            raise r.fail("emitters.positions", "no emitters")
        normals = r.unit(data, "emitters.normals", (L, 3))
        axes = r.unit(data, "emitters.axes", (L, 3))
        gs = _dig(data, "emitters.grid_shape")
        if gs is not None:
            gsa = r.array(data, "emitters.grid_shape", (2,))
            if int(gsa[0]) * int(gsa[1]) != L:
                raise r.fail("emitters.grid_shape", f"columns x rows must equal the {L} emitters")
            grid_shape = (int(gsa[0]), int(gsa[1]))
    if (np.abs((normals * axes).sum(-1)) > 1e-6).any():
        raise r.fail("emitters.axes" if layout == "list" else "emitters.normal", "emitter axis must be orthogonal to its normal")
    size = r.array(data, "emitters.size", (2,), default=np.zeros(2))
    if (size < 0).any():
        raise r.fail("emitters.size", "must be >= 0")
    if kind != "point" and size[0] <= 0 or kind == "area" and size[1] <= 0:
        raise r.fail("emitters.size", f"a {kind} emitter needs a positive size")
    quad = r.array(data, "emitters.quadrature", (2,), default=np.ones(2))
    if (quad < 1).any() or (quad != np.round(quad)).any():
        raise r.fail("emitters.quadrature", "expected two positive integers")
    color_matrix = r.array(data, "emitters.color_matrix", (3, 3), default=np.eye(3))

    ang = r.table(data, "emitters.angular", required=False)
    angular_kind = r.choice(data, "emitters.angular.kind", ("cosine", "table"), default="cosine") if ang else "cosine"
    exponent = r.number(data, "emitters.angular.exponent", 1.0) if ang else 1.0
    if exponent < 0:
        raise r.fail("emitters.angular.exponent", "must be >= 0")
    table = np.zeros((0, 2))
    if angular_kind == "table":
        a = r.array(data, "emitters.angular.angles_deg", (None,))
        vals = r.array(data, "emitters.angular.values", (len(a),))
        if len(a) < 2 or (np.diff(a) <= 0).any() or a[0] < 0 or a[-1] > 90 or (vals < 0).any():
            raise r.fail("emitters.angular", "table needs >= 2 increasing angles in [0, 90] and values >= 0")
        table = np.stack([a, vals], -1)

    r.table(data, "valid_volume")  # must exist; its keys are read by dotted name below
    valid_center = r.array(data, "valid_volume.center", (3,))
    valid_size = r.array(data, "valid_volume.size", (3,))
    if (valid_size <= 0).any():
        raise r.fail("valid_volume.size", "must be > 0")
    valid_axes = r.unit(data, "valid_volume.axes", (3, 3), default=np.eye(3))
    if np.abs(valid_axes @ valid_axes.T - np.eye(3)).max() > 1e-5:
        raise r.fail("valid_volume.axes", "rows must be orthonormal")

    pattern = _parse_pattern(data.get("pattern", "full_on"), L, path, r)
    return Device(
        name=name, description=str(data.get("description", "")), width=width, height=height, K=K,
        distortion=distortion, emitter_kind=kind, emitter_positions=positions, emitter_normals=normals,
        emitter_axes=axes, emitter_size=size, quadrature=(int(quad[0]), int(quad[1])),
        angular_kind=angular_kind, angular_exponent=exponent, angular_table=table,
        color_matrix=color_matrix, pattern=pattern, valid_center=valid_center, valid_size=valid_size,
        valid_axes=valid_axes, response=response, gamma=gamma, gain=gain,
        max_exposure=max_exposure, grid_shape=grid_shape,
        source=path,
    )


def _parse_pattern(value: Any, L: int, path: Path, r: _Reader) -> np.ndarray:
    """``pattern``: "full_on", a path (CSV/NPY, relative to the TOML) or an inline (L, 3) list."""
    if isinstance(value, str):
        if value == "full_on":
            return np.ones((L, 3))
        file = (path.parent / value).resolve()
        try:
            arr = np.load(file) if file.suffix == ".npy" else np.loadtxt(file, delimiter=",", ndmin=2)
        except (OSError, ValueError) as err:
            raise r.fail("pattern", f"cannot read pattern file {value!r} ({err})") from None
        arr = np.asarray(arr, dtype=np.float64)
    else:
        try:
            arr = np.asarray(value, dtype=np.float64)
        except (TypeError, ValueError):
            raise r.fail("pattern", "expected numbers") from None
    if arr.shape != (L, 3):
        raise r.fail("pattern", f"expected {L}x3 RGB values (one per emitter), got shape {arr.shape}")
    if not np.isfinite(arr).all() or (arr < 0).any() or (arr > 1).any():
        raise r.fail("pattern", "values must be in [0, 1]")
    return arr


def list_devices() -> list[Path]:
    """The device files shipped in ``assets/devices``."""
    return sorted(DEVICES_DIR.glob("*.toml"))
