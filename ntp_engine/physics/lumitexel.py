"""Lumitexels (paper §6.2): virtual one-light-at-a-time measurements on a cube around a point.

Convention: the lumitexel frame has its origin at the surface point, z along the trace's normal
n^ and x along its tangent t^. The cube is centred there, side 0.725 m; a virtual isotropic point
light of unit intensity sits at each face texel centre; the virtual camera is on +z at 0.3562 m,
so wo = +z. A lumitexel value is f(wi, wo) (n.wi)+ / r^2 with the *shading* normal n and tangent
t expressed in the lumitexel frame (they differ from n^, t^ by the network's frame freedom).

Face order is OpenGL's cube map: +x, -x, +y, -y, +z, -z. Within a face, texels are row-major,
``index = face * N^2 + row * N + col``; the texel centre is ``major * h + sc * u + tc * v`` with
``u = (2 col + 1) / N - 1``, ``v = (2 row + 1) / N - 1`` (times h = side / 2) and the OpenGL
(sc, tc) axes per face: +x: (-z, -y), -x: (+z, -y), +y: (+x, +z), -y: (+x, -z), +z: (+x, -y),
-z: (-x, -y). Diffuse lumitexels use N = 8 (384 lights), specular N = 32 (6144 lights).
"""

from __future__ import annotations

import functools

import torch
from torch import Tensor

from .brdf import F0_DIELECTRIC, ggx_specular
from .frame import frame_from_normal_tangent, to_local

CUBE_SIDE = 0.725  # m
CAMERA_DISTANCE = 0.3562  # m, the virtual camera on +z (wo = +z)
DIFFUSE_RES = 8
SPECULAR_RES = 32
FACES = ("+x", "-x", "+y", "-y", "+z", "-z")
# (major axis, sc axis, tc axis) as signed unit vectors, OpenGL cube-map convention
_FACE_AXES = (
    ((1, 0, 0), (0, 0, -1), (0, -1, 0)),
    ((-1, 0, 0), (0, 0, 1), (0, -1, 0)),
    ((0, 1, 0), (1, 0, 0), (0, 0, 1)),
    ((0, -1, 0), (1, 0, 0), (0, 0, -1)),
    ((0, 0, 1), (1, 0, 0), (0, -1, 0)),
    ((0, 0, -1), (-1, 0, 0), (0, -1, 0)),
)


@functools.lru_cache(maxsize=16)
def _texel_positions_f64(res: int) -> Tensor:
    axes = torch.tensor(_FACE_AXES, dtype=torch.float64)  # (6, 3, 3)
    c = (2.0 * torch.arange(res, dtype=torch.float64) + 1.0) / res - 1.0
    v, u = torch.meshgrid(c, c, indexing="ij")  # row (v) major
    h = CUBE_SIDE / 2
    pos = (
        axes[:, None, None, 0]
        + u[None, :, :, None] * axes[:, None, None, 1]
        + v[None, :, :, None] * axes[:, None, None, 2]
    )
    return (h * pos).reshape(6 * res * res, 3)


def texel_positions(res: int, dtype=torch.float32, device=None) -> Tensor:
    """Virtual light positions ``(6 res^2, 3)`` in the lumitexel frame (m), in lumitexel order."""
    return _texel_positions_f64(res).to(dtype=dtype, device=device)


def _light_dirs(res: int, like: Tensor) -> tuple[Tensor, Tensor]:
    p = texel_positions(res, like.dtype, like.device)
    r2 = (p * p).sum(-1)
    return p * torch.rsqrt(r2)[:, None], r2


def diffuse_lumitexel(n: Tensor, rho_d: Tensor, res: int = DIFFUSE_RES) -> Tensor:
    """Diffuse lumitexel ``(..., 6 res^2, C)``: rho_d/pi (n.wi)+ / r^2, 0 where n.z <= 0.

    ``n (..., 3)`` unit shading normal in the lumitexel frame; ``rho_d (..., C)``.
    """
    wi, r2 = _light_dirs(res, n)
    cos_i = (n[..., None, :] * wi).sum(-1).clamp_min(0.0)  # (..., M)
    seen = (n[..., 2:3] > 0).to(n.dtype)  # wo = +z must be above the shading horizon
    shade = cos_i / r2 * seen / torch.pi
    return shade[..., None] * rho_d[..., None, :]


def specular_lumitexel(
    n: Tensor,
    t: Tensor,
    rho_s: Tensor,
    alpha_x: Tensor,
    alpha_y: Tensor,
    res: int = SPECULAR_RES,
    f0: float = F0_DIELECTRIC,
) -> Tensor:
    """Specular lumitexel ``(..., 6 res^2, C)``: rho_s D F G / (4 cos_i cos_o) (n.wi)+ / r^2.

    ``n, t (..., 3)`` shading normal and tangent in the lumitexel frame (t is orthogonalised);
    ``rho_s (..., C)``; alphas ``(...)``.
    """
    wi, r2 = _light_dirs(res, n)
    frame = frame_from_normal_tangent(n, t)[..., None, :, :]  # (..., 1, 3, 3)
    wi_l = to_local(wi, frame)  # (..., M, 3)
    wo = torch.zeros_like(n)
    wo[..., 2] = 1.0
    wo_l = to_local(wo[..., None, :], frame)
    spec = ggx_specular(wi_l, wo_l, alpha_x[..., None], alpha_y[..., None], f0)
    return (spec * wi_l[..., 2].clamp_min(0.0) / r2)[..., None] * rho_s[..., None, :]


def render_lumitexels(
    n: Tensor,
    t: Tensor,
    rho_d: Tensor,
    rho_s: Tensor,
    alpha_x: Tensor,
    alpha_y: Tensor,
    diffuse_res: int = DIFFUSE_RES,
    specular_res: int = SPECULAR_RES,
) -> tuple[Tensor, Tensor]:
    """Both lumitexels of a batch of BRDFs: ``(..., 6 Nd^2, C)`` and ``(..., 6 Ns^2, C)``."""
    return (
        diffuse_lumitexel(n, rho_d, diffuse_res),
        specular_lumitexel(n, t, rho_s, alpha_x, alpha_y, specular_res),
    )


def unfold_cross(lumitexel: Tensor, res: int) -> Tensor:
    """Lay a lumitexel ``(..., 6 res^2, C)`` out as a horizontal-cross image ``(..., 3 res, 4 res, C)``
    for previews: row 0 holds +y, row 1 holds -x, +z, +x, -z, row 2 holds -y (zeros elsewhere)."""
    *lead, m, c = lumitexel.shape
    if m != 6 * res * res:
        raise ValueError(f"lumitexel has {m} lights, expected 6*{res}^2")
    faces = lumitexel.reshape(*lead, 6, res, res, c)
    out = lumitexel.new_zeros(*lead, 3 * res, 4 * res, c)
    for face, (gr, gc) in {2: (0, 1), 1: (1, 0), 4: (1, 1), 0: (1, 2), 5: (1, 3), 3: (2, 1)}.items():
        out[..., gr * res : (gr + 1) * res, gc * res : (gc + 1) * res, :] = faces[..., face, :, :, :]
    return out
