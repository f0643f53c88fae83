"""Local shading frames and world <-> local transforms.

Convention (docs/design.md): the local frame of a surface point has x = tangent t, y = bitangent
b = n x t, z = normal n. A frame is stored as a ``(..., 3, 3)`` matrix whose *rows* are t, b, n,
so ``to_local(v, F) = F @ v`` and ``to_world(v, F) = F^T @ v``. All functions broadcast over
leading dimensions and keep the input dtype/device.
"""

from __future__ import annotations

import torch
from torch import Tensor

_TINY = 1e-20


def safe_normalize(v: Tensor, fallback: Tensor | None = None) -> Tensor:
    """Unit vectors along ``v (..., 3)``; where ``|v|`` is ~0, ``fallback`` (default +z).

    Gradients stay finite at ``v = 0`` (the square norm is clamped before the square root).
    """
    sq = (v * v).sum(-1, keepdim=True)
    out = v * torch.rsqrt(sq.clamp_min(_TINY))
    if fallback is None:
        fallback = torch.tensor([0.0, 0.0, 1.0], dtype=v.dtype, device=v.device)  # broadcast, no full copy
    return torch.where(sq > _TINY, out, fallback)


def cross(a: Tensor, b: Tensor) -> Tensor:
    """a x b over the last axis ``(..., 3)``, broadcasting; component form (torch.linalg.cross has
    no working forward-mode AD for float32 here, which the fitter's Jacobians need)."""
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    return torch.stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], -1)


def any_tangent(n: Tensor) -> Tensor:
    """A unit vector orthogonal to the unit normal ``n (..., 3)``, continuous except at n_z = -1.

    Duff et al. 2017 ("Building an orthonormal basis, revisited"), branch-free; returns ``(..., 3)``.
    """
    x, y, z = n.unbind(-1)
    sign = torch.where(z >= 0, torch.ones_like(z), -torch.ones_like(z))
    a = -1.0 / (sign + z)
    b = x * y * a
    return torch.stack([1.0 + sign * x * x * a, sign * b, -sign * x], -1)


def frame_from_normal_tangent(n: Tensor, t: Tensor) -> Tensor:
    """Orthonormal frame ``(..., 3, 3)`` with rows (t, b, n) from a normal and a rough tangent.

    ``n`` is normalised; ``t`` is Gram-Schmidt orthogonalised against it (it need not be exactly
    orthogonal). Where ``t`` is parallel to ``n`` (or zero) an arbitrary orthogonal tangent is used.
    """
    n = safe_normalize(n)
    t_perp = t - (t * n).sum(-1, keepdim=True) * n
    t = safe_normalize(t_perp, fallback=any_tangent(n))
    b = cross(n, t)
    return torch.stack([t, b, n], dim=-2)


def to_local(v: Tensor, frame: Tensor) -> Tensor:
    """World/camera-space vectors ``(..., 3)`` into the frame ``(..., 3, 3)`` (rows t, b, n)."""
    # component form: no (..., 3, 3) broadcast temporary (a third of the measurement time)
    v0, v1, v2 = v[..., 0], v[..., 1], v[..., 2]
    return torch.stack([v0 * frame[..., i, 0] + v1 * frame[..., i, 1] + v2 * frame[..., i, 2] for i in range(3)], -1)


def to_world(v: Tensor, frame: Tensor) -> Tensor:
    """Local vectors ``(..., 3)`` (x along t, z along n) back to world/camera space."""
    v0, v1, v2 = v[..., 0], v[..., 1], v[..., 2]
    return torch.stack([v0 * frame[..., 0, i] + v1 * frame[..., 1, i] + v2 * frame[..., 2, i] for i in range(3)], -1)


def rotation_from_vector(r: Tensor) -> Tensor:
    """Rotation matrices ``(..., 3, 3)`` from rotation vectors ``r (..., 3)`` (axis * angle, radians;
    Rodrigues). Convention: right-handed, ``R @ v`` rotates column vectors; ``r = 0`` gives identity
    (the series form keeps small angles exact, no division by the angle)."""
    theta2 = (r * r).sum(-1, keepdim=True)[..., None]
    small = theta2 < 1e-8
    safe = torch.where(small, torch.ones_like(theta2), theta2).sqrt()  # no sqrt'(0) in the graph
    a = torch.where(small, 1 - theta2 / 6, torch.sin(safe) / safe)
    b = torch.where(small, 0.5 - theta2 / 24, (1 - torch.cos(safe)) / (safe * safe))
    zero = torch.zeros_like(r[..., 0])
    K = torch.stack(
        [zero, -r[..., 2], r[..., 1], r[..., 2], zero, -r[..., 0], -r[..., 1], r[..., 0], zero], -1
    ).reshape(*r.shape[:-1], 3, 3)
    eye = torch.eye(3, dtype=r.dtype, device=r.device).expand_as(K)
    return eye + a * K + b * (K @ K)


def reflect(v: Tensor, n: Tensor) -> Tensor:
    """Mirror direction of ``v`` about unit ``n`` (both pointing away from the surface)."""
    return 2.0 * (v * n).sum(-1, keepdim=True) * n - v


def turned_about_normal(frame: Tensor, angle: Tensor) -> Tensor:
    """Frames ``(..., 3, 3)`` (rows t, b, n) turned by ``angle (...)`` radians about their normals.

    Convention: right-handed about n: t' = cos t + sin b, b' = cos b - sin t; n unchanged."""
    c, s = angle.cos()[..., None], angle.sin()[..., None]
    t, b = frame[..., 0, :], frame[..., 1, :]
    return torch.stack([c * t + s * b, c * b - s * t, frame[..., 2, :]], -2)
