"""The scanner's camera: pinhole projection with OpenCV distortion and its inverse, the 8-bit
response (encode/decode), the validity test of a measured code, poses that look at a point, and
the same camera at another resolution.

Convention: camera space is OpenCV's (x right, y down, z forward; metres); pixel centres sit at
integer coordinates, (0, 0) the centre of the top-left pixel; poses are camera-from-world 4x4.
Linear pixel values are 1 at code 255. Functions take the ``Scanner`` whose camera they use.
"""

from __future__ import annotations

import dataclasses
from typing import overload

import numpy as np
import torch
from torch import Tensor

from ..io.colour import srgb_decode, srgb_encode
from .scanner import Scanner

VALID_CODE = (32.0, 224.0)  # an 8-bit code in this range is neither noise-dominated nor near clipping
UNDISTORT_ITERATIONS = 20


@overload
def code_is_valid(code: Tensor) -> Tensor: ...
@overload
def code_is_valid(code: np.ndarray) -> np.ndarray: ...
def code_is_valid(code: np.ndarray | Tensor) -> np.ndarray | Tensor:
    """Boolean ``(...)``: every channel of the 8-bit codes ``(..., C)`` lies in ``VALID_CODE``
    (the paper's measurement filter). Works on numpy arrays and torch tensors alike."""
    lo, hi = VALID_CODE
    return ((code >= lo) & (code <= hi)).all(-1)


def encode(scanner: Scanner, linear: Tensor) -> Tensor:
    """Linear pixel value (1 = white) to an 8-bit code value in [0, 255] (float, not rounded),
    through the camera's response (linear, gamma or sRGB); values are clipped to [0, 1] first."""
    x = linear.clamp(0.0, 1.0)
    if scanner.response == "gamma":
        x = x ** (1.0 / scanner.gamma)
    elif scanner.response == "srgb":
        x = srgb_encode(x)
    return 255.0 * x


def decode(scanner: Scanner, code: Tensor) -> Tensor:
    """8-bit code value [0, 255] back to a linear pixel value in [0, 1] (``encode``'s inverse)."""
    x = (code / 255.0).clamp(0.0, 1.0)
    if scanner.response == "gamma":
        return x**scanner.gamma
    if scanner.response == "srgb":
        return srgb_decode(x)
    return x


def distort(scanner: Scanner, x: Tensor, y: Tensor) -> tuple[Tensor, Tensor]:
    """OpenCV's distortion (k1 k2 p1 p2 k3) of normalised image coordinates ``x, y (...)``."""
    k1, k2, p1, p2, k3 = (float(v) for v in scanner.distortion)
    r2 = x * x + y * y
    radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    return x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x), y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y


def undistort(scanner: Scanner, xd: np.ndarray, yd: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Normalised coordinates whose ``distort`` is ``xd, yd (...)``: fixed-point inversion of
    OpenCV's model (``UNDISTORT_ITERATIONS`` steps; exact when there is no distortion)."""
    k1, k2, p1, p2, k3 = scanner.distortion
    x, y = xd.copy(), yd.copy()
    if np.any(scanner.distortion):
        for _ in range(UNDISTORT_ITERATIONS):
            r2 = x * x + y * y
            radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
            dx = 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
            dy = p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
            x, y = (xd - dx) / radial, (yd - dy) / radial
    return x, y


def project(scanner: Scanner, points: Tensor) -> Tensor:
    """Camera-space ``points (..., 3)`` to pixel coordinates ``(..., 2)`` (x = column, y = row) with
    distortion. Points with z <= 0 give NaN."""
    K = torch.as_tensor(scanner.K, dtype=points.dtype, device=points.device)
    z = points[..., 2]
    z = torch.where(z > 0, z, torch.full_like(z, float("nan")))
    xd, yd = distort(scanner, points[..., 0] / z, points[..., 1] / z)
    return torch.stack([K[0, 0] * xd + K[0, 1] * yd + K[0, 2], K[1, 1] * yd + K[1, 2]], -1)


def in_image(scanner: Scanner, px: np.ndarray) -> np.ndarray:
    """``(N,)`` True where pixel coordinates ``px (N, 2)`` (``project``'s) lie in the photo, its
    border pixels' centres included; NaN (behind the camera) is outside."""
    return (px[:, 0] >= 0) & (px[:, 1] >= 0) & (px[:, 0] <= scanner.width - 1) & (px[:, 1] <= scanner.height - 1)


def project_jacobian(scanner: Scanner, points: Tensor) -> Tensor:
    """d pixel / d point ``(..., 2, 3)`` of ``project`` at camera-space ``points (..., 3)``
    (distortion included); NaN where z <= 0."""
    k1, k2, p1, p2, k3 = (float(v) for v in scanner.distortion)
    K = scanner.K
    z = points[..., 2]
    z = torch.where(z > 0, z, torch.full_like(z, float("nan")))
    x, y = points[..., 0] / z, points[..., 1] / z
    r2 = x * x + y * y
    radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
    d_radial = k1 + r2 * (2 * k2 + 3 * k3 * r2)  # d radial / d r2
    dxd_dx = radial + 2 * x * x * d_radial + 2 * p1 * y + 6 * p2 * x
    dxd_dy = 2 * x * y * d_radial + 2 * p1 * x + 2 * p2 * y
    dyd_dx = 2 * x * y * d_radial + 2 * p1 * x + 2 * p2 * y
    dyd_dy = radial + 2 * y * y * d_radial + 6 * p1 * y + 2 * p2 * x
    # d (x, y) / d (X, Y, Z): [[1/z, 0, -x/z], [0, 1/z, -y/z]]
    zero = torch.zeros_like(x)
    dn = torch.stack([torch.stack([1 / z, zero, -x / z], -1), torch.stack([zero, 1 / z, -y / z], -1)], -2)
    dd = torch.stack([torch.stack([dxd_dx, dxd_dy], -1), torch.stack([dyd_dx, dyd_dy], -1)], -2)
    kk = torch.as_tensor(K[:2, :2], dtype=points.dtype)  # [[fx, skew], [0, fy]]
    return kk @ dd @ dn


def pixel_directions(scanner: Scanner, cols: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """Unit camera-space ray directions ``(..., 3)`` through pixel coordinates ``cols, rows (...)``
    (``project``'s: x = column, y = row; distortion undone): ``project`` of any point on the ray
    gives them back."""
    K = scanner.K
    yd = (rows - K[1, 2]) / K[1, 1]
    x, y = undistort(scanner, (cols - K[0, 2] - K[0, 1] * yd) / K[0, 0], yd)
    d = np.stack([x, y, np.ones_like(x)], -1)
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


def pixel_rays(scanner: Scanner) -> np.ndarray:
    """Unit camera-space ray directions ``(H, W, 3)`` through every pixel centre (distortion undone)."""
    rows, cols = np.meshgrid(np.arange(scanner.height), np.arange(scanner.width), indexing="ij")
    return pixel_directions(scanner, cols, rows)


def look_at(position: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Camera-from-world 4x4 (OpenCV axes) at ``position`` looking at ``target``, level with world
    z up (the camera's x axis is horizontal). Undefined when looking straight up or down."""
    z = (target - position) / np.linalg.norm(target - position)
    x = np.cross(z, [0.0, 0.0, 1.0])  # right = forward x up
    x /= np.linalg.norm(x)
    R = np.stack([x, np.cross(z, x), z])  # rows: camera axes in world coordinates
    pose = np.eye(4)
    pose[:3, :3], pose[:3, 3] = R, -R @ position
    return pose


def resampled(scanner: Scanner, scale: float) -> Scanner:
    """The same scanner with its camera resampled to ``scale`` of the resolution (pixel centres
    kept at integers: c' = (c + 0.5) s - 0.5)."""
    K = scanner.K.copy()
    K[0, 0] *= scale
    K[1, 1] *= scale
    K[0, 2] = (K[0, 2] + 0.5) * scale - 0.5
    K[1, 2] = (K[1, 2] + 0.5) * scale - 0.5
    return dataclasses.replace(
        scanner, K=K, width=max(1, round(scanner.width * scale)), height=max(1, round(scanner.height * scale))
    )
