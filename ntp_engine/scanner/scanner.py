"""The scanner record and its radiometry: emitters, their angular distribution, the lighting
pattern through the colour matrix, auto-exposure and the valid volume.

Convention: everything is in the camera space of the scanner (OpenCV: x right, y down, z forward;
metres). An emitter ``l`` has a centre ``emitter_positions[l]``, an outward unit normal
``emitter_normals[l]`` and an in-plane unit axis ``emitter_axes[l]`` (along its length for a
linear light, its width for an area light). ``I(l) = 1`` means: seen from afar, the emitter is a
point source of unit on-axis radiant intensity; an extended emitter spreads that uniformly over its
length/area and is integrated by Gauss-Legendre quadrature (``emitter_samples``). The angular
distribution Psi(cos) multiplies the intensity towards a direction at angle theta from the normal
(cosine lobe ``cos^k`` by default, or a measured table).

The camera model (projection, distortion, 8-bit response) is ``camera``; the file format
``device_file`` (``docs/device-format.md``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import overload

import numpy as np
import torch
from torch import Tensor


@overload
def auto_exposure(
    mean_drive: Tensor, gain: float | Tensor, full_on_drive: float | Tensor, max_exposure: float | Tensor
) -> Tensor: ...
@overload
def auto_exposure(mean_drive: float, gain: float, full_on_drive: float, max_exposure: float) -> float: ...
def auto_exposure(
    mean_drive: float | Tensor, gain: float | Tensor, full_on_drive: float | Tensor, max_exposure: float | Tensor
) -> float | Tensor:
    """Linear pixel value per unit of B: ``gain / max(mean_drive, full_on_drive / max_exposure)``.

    Convention: ``mean_drive`` is the mean of ``pattern @ M^T`` over emitters and channels,
    ``full_on_drive`` the same for the full-on pattern (``gain`` is calibrated for it). The camera's
    exposure follows the pattern's mean drive (auto-exposure), so a dimmer pattern is not penalised,
    but only up to ``max_exposure`` times the full-on exposure (a hand-held capture's motion-blur
    limit): a pattern dimmer than ``full_on_drive / max_exposure`` gives darker photos."""
    floor = full_on_drive / max_exposure
    if isinstance(mean_drive, Tensor):
        return gain / torch.maximum(
            mean_drive, torch.as_tensor(floor, dtype=mean_drive.dtype, device=mean_drive.device)
        ).clamp_min(1e-12)
    return float(gain) / max(float(mean_drive), float(floor), 1e-12)


@dataclass
class Scanner:
    """A scanner: camera, emitters, valid volume and lighting pattern, with its radiometry.

    Arrays are float64 numpy in the scanner's camera space (see the module docstring); methods that
    compute take and return torch tensors. Read and written by ``device_file``."""

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
        """L, the number of emitters."""
        return int(self.emitter_positions.shape[0])

    @property
    def fx(self) -> float:
        """Focal length along x, pixels."""
        return float(self.K[0, 0])

    @overload
    def effective_pattern(self, pattern: Tensor) -> Tensor: ...
    @overload
    def effective_pattern(self, pattern: np.ndarray | None = None) -> np.ndarray: ...
    def effective_pattern(self, pattern: np.ndarray | Tensor | None = None) -> np.ndarray | Tensor:
        """Per-emitter, per-camera-channel drive ``(L, 3)``: pattern @ color_matrix^T."""
        p = self.pattern if pattern is None else pattern
        if isinstance(p, Tensor):
            return p @ torch.as_tensor(self.color_matrix, dtype=p.dtype, device=p.device).T
        return p @ self.color_matrix.T

    @overload
    def exposure(self, pattern: Tensor) -> Tensor: ...
    @overload
    def exposure(self, pattern: np.ndarray | None = None) -> float: ...
    def exposure(self, pattern: np.ndarray | Tensor | None = None) -> float | Tensor:
        """Linear pixel value per unit of B under ``pattern`` (see ``auto_exposure``)."""
        full_on = float(self.color_matrix.sum(1).mean())
        if isinstance(pattern, Tensor):
            return auto_exposure(self.effective_pattern(pattern).mean(), self.gain, full_on, self.max_exposure)
        return auto_exposure(float(self.effective_pattern(pattern).mean()), self.gain, full_on, self.max_exposure)

    def emitter_samples(
        self, dtype: torch.dtype = torch.float32, device: torch.device | str | None = None
    ) -> tuple[Tensor, Tensor]:
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

    def summary(self) -> str:
        """Four lines for a person: camera, emitters, pattern and valid volume."""
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
