"""What the scanner's camera measures of a surface point: paper Eq. 1, in two forms.

Convention: points, normals and tangents are in the scanner's camera space (OpenCV, metres), the
camera at the origin, so the view direction is wo = -x / |x|. The physical lumitexel of a point is
m_phys(l) = sum_q w_q f(wi, wo) (wi.n)+ Psi_l(-wi . n_l) V / r^2 over the emitter's quadrature
points q (one for a point emitter), with unit drive I(l) = 1. The measurement in camera channel c is
B_c = sum_l P_eff[l, c] m_phys(l, c), with P_eff = pattern @ color_matrix^T: the colour matrix says
how much of each LED channel camera channel c sees. B is linear radiance-like units; the camera's
pixel value is ``scanner.exposure(pattern) * B`` before the response curve.

Two forms, one model: the *reference* (``physical_lumitexel`` over ``reference_emitter_geometry``)
broadcasts BRDF tensors over every point, emitter and quadrature sample, as Eq. 1 reads; the
*factorised* form (``emitter_terms``, ``measurement_rgb``, over ``local_emitter_geometry``) gets every
direction from matrix products and splits m_phys into a diffuse and a specular term per emitter — the
one renderers, training and the fitter use. Tests hold the second to the first.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import Tensor

from ..scanner.scanner import Scanner
from .brdf import F0_DIELECTRIC, ggx, ggx_specular
from .frame import frame_from_normal_tangent, safe_normalize, to_local

Visibility = Tensor | Callable[[Tensor, Tensor], Tensor] | None


def reference_emitter_geometry(scanner: Scanner, x: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Directions and falloff from points ``x (..., 3)`` to every emitter quadrature point, by
    broadcasting (the reference form; ``local_emitter_geometry`` is the fast one).

    Returns wi ``(..., L, Q, 3)`` (unit, from the point towards the emitter), the emitted-direction
    weight ``w_q Psi_l / r^2`` ``(..., L, Q)``, the quadrature points ``(L, Q, 3)`` and ``r^2``.
    """
    pts, w = scanner.emitter_samples(x.dtype, x.device)
    d = pts - x[..., None, None, :]
    r2 = (d * d).sum(-1).clamp_min(1e-12)
    wi = d * torch.rsqrt(r2)[..., None]
    n_l = torch.as_tensor(scanner.emitter_normals, dtype=x.dtype, device=x.device)[:, None, :]
    psi = scanner.psi(-(wi * n_l).sum(-1))
    return wi, w * psi / r2, pts, r2


def physical_lumitexel(
    scanner: Scanner,
    x: Tensor,
    n: Tensor,
    t: Tensor,
    rho_d: Tensor,
    rho_s: Tensor,
    alpha_x: Tensor,
    alpha_y: Tensor,
    visibility: Visibility = None,
    f0: float = F0_DIELECTRIC,
) -> Tensor:
    """m_phys ``(..., L, C)`` of points ``x (..., 3)`` with shading frame n, t ``(..., 3)``.

    ``rho_d, rho_s (..., C)``, alphas ``(...)``. ``visibility`` (the V of Eq. 1): None (all
    visible), a tensor broadcastable to ``(..., L, Q)``, or a callable ``(x, points (L, Q, 3)) ->
    (..., L, Q)`` returning 0/1 (or fractional) visibility of each emitter sample.
    """
    wi, falloff, pts, _ = reference_emitter_geometry(scanner, x)
    if visibility is not None:
        v = visibility(x, pts) if callable(visibility) else visibility
        falloff = falloff * v
    frame = frame_from_normal_tangent(n, t)
    wo_l = to_local(safe_normalize(-x), frame)
    wi_l = to_local(wi, frame[..., None, None, :, :])
    f = ggx(
        wi_l,
        wo_l[..., None, None, :],
        rho_d[..., None, None, :],
        rho_s[..., None, None, :],
        alpha_x[..., None, None],
        alpha_y[..., None, None],
        f0,
    )  # (..., L, Q, C)
    weight = falloff * wi_l[..., 2].clamp_min(0.0)  # (..., L, Q)
    return (f * weight[..., None]).sum(-2)


def measure(scanner: Scanner, m_phys: Tensor, pattern: Tensor | None = None) -> Tensor:
    """B ``(..., C)`` from a physical lumitexel ``(..., L, C)`` under ``pattern (L, 3)`` in [0, 1]
    (default: the scanner's). C = 3 uses the colour matrix; C = 1 (grayscale) uses its row mean."""
    if pattern is None:
        pattern = torch.as_tensor(scanner.pattern, dtype=m_phys.dtype, device=m_phys.device)
    p_eff = scanner.effective_pattern(pattern.to(m_phys.dtype))
    if m_phys.shape[-1] == 1:
        p_eff = p_eff.mean(-1, keepdim=True)
    return (m_phys * p_eff).sum(-2)


def _local_emitters(scanner: Scanner, x: Tensor, frame: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """For points ``x (N, 3)`` with frames ``(N, 3, 3)``: unit directions to every emitter sample in
    the local frame ``(N, K, 3)`` (K = L * Q), r^2 ``(N, K)``, the emitter-side cosine (-wi).n_l
    ``(N, K)`` and the quadrature weights ``(L, Q)`` — all from matrix products (F P^T - F x)."""
    pts, wq = scanner.emitter_samples(x.dtype, x.device)  # (L, Q, 3), (L, Q)
    L, Q = wq.shape
    P = pts.reshape(L * Q, 3)
    nl = torch.as_tensor(scanner.emitter_normals, dtype=x.dtype, device=x.device).repeat_interleave(Q, 0)
    d = torch.einsum("nij,kj->nik", frame, P) - (frame @ x[:, :, None])  # (N, 3, K) local offsets
    r2 = (d * d).sum(1).clamp_min(1e-12)
    inv_r = torch.rsqrt(r2)
    wi_l = (d * inv_r[:, None, :]).transpose(1, 2)
    cos_l = ((x @ nl.T) - (P * nl).sum(-1)) * inv_r
    return wi_l, r2, cos_l, wq


@dataclass
class EmitterGeometry:
    """Points ``(M,)`` against every emitter sample (K = L * Q), local frames: what Eq. 1 needs
    besides the lobe. ``falloff`` = w_q Psi V / r^2 ``(M, K)``; ``wi_l (M, K, 3)``; ``wo_l (M, 3)``."""

    wi_l: Tensor
    wo_l: Tensor
    falloff: Tensor
    shape: tuple[int, int]  # (L, Q)

    def rows(self, idx: Tensor) -> EmitterGeometry:
        """The same geometry for the points ``idx`` only."""
        return EmitterGeometry(self.wi_l[idx], self.wo_l[idx], self.falloff[idx], self.shape)


def local_emitter_geometry(
    scanner: Scanner, x: Tensor, n: Tensor, t: Tensor, visibility: Tensor | None = None
) -> EmitterGeometry:
    """``x, n, t (M, 3)`` camera space; ``visibility`` broadcastable to ``(M, L, Q)``."""
    frame = frame_from_normal_tangent(n, t)  # (M, 3, 3)
    wi_l, r2, cos_l, wq = _local_emitters(scanner, x, frame)
    L, Q = wq.shape
    falloff = wq.reshape(-1) * scanner.psi(cos_l) / r2
    if visibility is not None:
        falloff = falloff * torch.broadcast_to(visibility, (len(x), L, Q)).reshape(-1, L * Q).to(x.dtype)
    return EmitterGeometry(wi_l, to_local(safe_normalize(-x), frame), falloff, (L, Q))


def specular_lobe(geo: EmitterGeometry, alpha_x: Tensor, alpha_y: Tensor, f0: float = F0_DIELECTRIC) -> Tensor:
    """The rho_s = 1 lobe toward every emitter sample ``(M, K)``; alphas ``(M,)``."""
    return ggx_specular(geo.wi_l, geo.wo_l[:, None, :], alpha_x[:, None], alpha_y[:, None], f0)


def terms_from_lobe(geo: EmitterGeometry, spec: Tensor) -> tuple[Tensor, Tensor]:
    """A_l and S_l ``(M, L)`` of the factorised Eq. 1 (see ``emitter_terms``)."""
    L, Q = geo.shape
    w = geo.falloff * geo.wi_l[..., 2].clamp_min(0.0) * (geo.wo_l[:, 2:3] > 0).to(geo.falloff.dtype)
    return w.reshape(-1, L, Q).sum(-1), (w * spec).reshape(-1, L, Q).sum(-1)


def emitter_terms(
    scanner: Scanner,
    x: Tensor,
    n: Tensor,
    t: Tensor,
    alpha_x: Tensor,
    alpha_y: Tensor,
    visibility: Tensor | None = None,
    f0: float = F0_DIELECTRIC,
) -> tuple[Tensor, Tensor]:
    """The two per-emitter scalars of the factorised Eq. 1, ``(..., L)`` each, for points
    ``x, n, t (..., 3)`` and alphas ``(...)``: m_phys(l, c) = A_l rho_d,c / pi + S_l rho_s,c with
    A_l = sum_q w_q Psi V (wi.n)+ / r^2 and S_l = the same times the specular lobe (rho_s = 1).
    Every direction comes from matrix products (local emitter offsets F P^T - F x; r^2 and the
    emitter-side cosines likewise), so no (..., L, 3) BRDF tensors are built.
    ``visibility`` broadcastable to ``(..., L, Q)``."""
    lead = x.shape[:-1]
    alpha_x, alpha_y = alpha_x.expand(lead).reshape(-1), alpha_y.expand(lead).reshape(-1)
    vis = None
    if visibility is not None:
        L, Q = scanner.emitter_samples(x.dtype, x.device)[1].shape
        vis = torch.broadcast_to(visibility, (*lead, L, Q)).reshape(-1, L, Q)
    geo = local_emitter_geometry(scanner, x.reshape(-1, 3), n.reshape(-1, 3), t.reshape(-1, 3), vis)
    a_l, s_l = terms_from_lobe(geo, specular_lobe(geo, alpha_x, alpha_y, f0))
    return a_l.reshape(*lead, -1), s_l.reshape(*lead, -1)


def measure_terms(
    scanner: Scanner, a_l: Tensor, s_l: Tensor, rho_d: Tensor, rho_s: Tensor, pattern: Tensor | None = None
) -> Tensor:
    """B ``(..., 3)`` from the factorised terms ``(..., L)`` and RGB albedos ``(..., 3)``."""
    if pattern is None:
        pattern = torch.as_tensor(scanner.pattern, dtype=a_l.dtype, device=a_l.device)
    p_eff = scanner.effective_pattern(pattern.to(a_l.dtype))  # (L, 3)
    return rho_d / torch.pi * (a_l @ p_eff) + rho_s * (s_l @ p_eff)


def measurement_rgb(
    scanner: Scanner,
    x: Tensor,
    n: Tensor,
    t: Tensor,
    rho_d: Tensor,
    rho_s: Tensor,
    alpha_x: Tensor,
    alpha_y: Tensor,
    pattern: Tensor | None = None,
    visibility: Tensor | None = None,
    f0: float = F0_DIELECTRIC,
) -> Tensor:
    """B ``(..., 3)``, equal to ``measure(physical_lumitexel(...))``, through the factorised terms
    (``emitter_terms``): for renderers and training data (many points)."""
    a_l, s_l = emitter_terms(scanner, x, n, t, alpha_x, alpha_y, visibility, f0)
    return measure_terms(scanner, a_l, s_l, rho_d, rho_s, pattern)
