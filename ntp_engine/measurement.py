"""What the scanner's camera measures of a surface point (paper Eq. 1) and the confidence beta (Eq. 6).

Convention: points, normals and tangents are in the scanner's camera space (OpenCV, metres), the
camera at the origin, so the view direction is wo = -x / |x|. The physical lumitexel of a point is
m_phys(l) = sum_q w_q f(wi, wo) (wi.n)+ Psi_l(-wi . n_l) V / r^2 over the emitter's quadrature
points q (one for a point emitter), with unit drive I(l) = 1. The measurement in camera channel c is
B_c = sum_l P_eff[l, c] m_phys(l, c), with P_eff = pattern @ color_matrix^T: the colour matrix says
how much of each LED channel camera channel c sees. B is linear radiance-like units; the camera's
pixel value is ``device.gain * B`` before the response curve.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import torch
from torch import Tensor

from .brdf import F0_DIELECTRIC, ggx, ggx_specular
from .device import Device
from .frame import frame_from_normal_tangent, reflect, safe_normalize, to_local

Visibility = Tensor | Callable[[Tensor, Tensor], Tensor] | None


def emitter_geometry(device: Device, x: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Directions and falloff from points ``x (..., 3)`` to every emitter quadrature point.

    Returns wi ``(..., L, Q, 3)`` (unit, from the point towards the emitter), the emitted-direction
    weight ``w_q Psi_l / r^2`` ``(..., L, Q)``, the quadrature points ``(L, Q, 3)`` and ``r^2``.
    """
    pts, w = device.emitter_samples(x.dtype, x.device)
    d = pts - x[..., None, None, :]
    r2 = (d * d).sum(-1).clamp_min(1e-12)
    wi = d * torch.rsqrt(r2)[..., None]
    n_l = torch.as_tensor(device.emitter_normals, dtype=x.dtype, device=x.device)[:, None, :]
    psi = device.psi(-(wi * n_l).sum(-1))
    return wi, w * psi / r2, pts, r2


def physical_lumitexel(
    device: Device, x: Tensor, n: Tensor, t: Tensor, rho_d: Tensor, rho_s: Tensor,
    alpha_x: Tensor, alpha_y: Tensor, visibility: Visibility = None, f0: float = F0_DIELECTRIC,
) -> Tensor:
    """m_phys ``(..., L, C)`` of points ``x (..., 3)`` with shading frame n, t ``(..., 3)``.

    ``rho_d, rho_s (..., C)``, alphas ``(...)``. ``visibility`` (the V of Eq. 1): None (all
    visible), a tensor broadcastable to ``(..., L, Q)``, or a callable ``(x, points (L, Q, 3)) ->
    (..., L, Q)`` returning 0/1 (or fractional) visibility of each emitter sample.
    """
    wi, falloff, pts, _ = emitter_geometry(device, x)
    if visibility is not None:
        v = visibility(x, pts) if callable(visibility) else visibility
        falloff = falloff * v
    frame = frame_from_normal_tangent(n, t)
    wo_l = to_local(safe_normalize(-x), frame)
    wi_l = to_local(wi, frame[..., None, None, :, :])
    f = ggx(wi_l, wo_l[..., None, None, :], rho_d[..., None, None, :], rho_s[..., None, None, :],
            alpha_x[..., None, None], alpha_y[..., None, None], f0)  # (..., L, Q, C)
    weight = falloff * wi_l[..., 2].clamp_min(0.0)  # (..., L, Q)
    return (f * weight[..., None]).sum(-2)


def measure(device: Device, m_phys: Tensor, pattern: Tensor | None = None) -> Tensor:
    """B ``(..., C)`` from a physical lumitexel ``(..., L, C)`` under ``pattern (L, 3)`` in [0, 1]
    (default: the device's). C = 3 uses the colour matrix; C = 1 (grayscale) uses its row mean."""
    if pattern is None:
        pattern = torch.as_tensor(device.pattern, dtype=m_phys.dtype, device=m_phys.device)
    p_eff = device.effective_pattern(pattern.to(m_phys.dtype))
    if m_phys.shape[-1] == 1:
        p_eff = p_eff.mean(-1, keepdim=True)
    return (m_phys * p_eff).sum(-2)


# ---------------------------------------------------------------------------- confidence (Eq. 6)
_PEAK_GRID = torch.linspace(-2.5, 2.5, 11, dtype=torch.float64)


def specular_peak(wo: Tensor, alpha_x: Tensor, alpha_y: Tensor, rho_s: Tensor | float = 1.0,
                  f0: float = F0_DIELECTRIC) -> Tensor:
    """max over wi of rho_s * specular lobe(wi; wo) ``(...)``, for local ``wo (..., 3)``.

    Searched over half vectors h ~ (ax u, ay v, 1), |u|, |v| <= 2.5 around the normal (the lobe's
    maximum lies there: D peaks at h = n; F, G only shift it at grazing views). 0 if wo_z <= 0.
    """
    g = _PEAK_GRID.to(dtype=wo.dtype, device=wo.device)
    u, v = torch.meshgrid(g, g, indexing="ij")
    ax, ay = alpha_x[..., None], alpha_y[..., None]
    h = safe_normalize(torch.stack([ax * u.reshape(-1), ay * v.reshape(-1), torch.ones_like(ax * u.reshape(-1))], -1))
    wi = reflect(wo[..., None, :], h)
    spec = ggx_specular(wi, wo[..., None, :], ax, ay, f0)
    return torch.as_tensor(rho_s, dtype=wo.dtype, device=wo.device) * spec.amax(-1)


def highlight_ratio(spec_at_emitters: Tensor, spec_peak: Tensor) -> Tensor:
    """Per-view ratio log(1 + max_l s_jl) / log(1 + s*_j) of Eq. 6, ``(..., V)``.

    ``spec_at_emitters (..., V, L)``: the specular lobe towards each emitter in view j;
    ``spec_peak (..., V)``: its maximum over all directions. Views with no lobe (peak 0) give 0.
    """
    num = torch.log1p(spec_at_emitters.amax(-1))
    den = torch.log1p(spec_peak)
    return torch.where(den > 0, num / den.clamp_min(1e-30), torch.zeros_like(num))


def confidence_from_ratios(ratio: Tensor, valid: Tensor | None = None, eps: float = 0.5) -> Tensor:
    """beta = min(max_j ratio_j / eps, 1) over the views in the trace (``valid (..., V)``)."""
    if valid is not None:
        ratio = torch.where(valid, ratio, torch.zeros_like(ratio))
    return (ratio.amax(-1) / eps).clamp(0.0, 1.0)


def view_highlight_ratio(device: Device, x: Tensor, n: Tensor, t: Tensor, alpha_x: Tensor, alpha_y: Tensor,
                         rho_s: Tensor | float = 1.0) -> Tensor:
    """Eq. 6's per-view ratio for one point seen in V views: x, n, t ``(..., V, 3)`` camera space,
    alphas and grayscale rho_s ``(...)``. Returns ``(..., V)`` in [0, ~1]."""
    lead = x.shape[:-1]  # (..., V)
    flat = lambda a: torch.as_tensor(a, dtype=x.dtype, device=x.device)
    ax, ay = (flat(a)[..., None].expand(lead).reshape(-1) for a in (alpha_x, alpha_y))
    rs = flat(rho_s)
    rs = (rs[..., None] if rs.dim() else rs).expand(lead).reshape(-1)
    geo = local_emitter_geometry(device, x.reshape(-1, 3), n.reshape(-1, 3), t.reshape(-1, 3))
    return ratios_from_lobe(geo, specular_lobe(geo, ax, ay), ax, ay, rs).reshape(lead)


def ratios_from_lobe(geo: "EmitterGeometry", spec: Tensor, alpha_x: Tensor, alpha_y: Tensor, rho_s: Tensor) -> Tensor:
    """Eq. 6's ratio per point ``(M,)`` from its lobe toward every emitter sample ``spec (M, K)``."""
    return highlight_ratio(rho_s[:, None] * spec, specular_peak(geo.wo_l, alpha_x, alpha_y, rho_s))


def confidence(device: Device, x: Tensor, n: Tensor, t: Tensor, alpha_x: Tensor, alpha_y: Tensor,
               rho_s: Tensor | float = 1.0, valid: Tensor | None = None, eps: float = 0.5) -> Tensor:
    """beta of Eq. 6 for one point seen in V views (see ``view_highlight_ratio``); ``valid (..., V)``
    masks views out of the trace. beta is 0 when no view sees any highlight, 1 once a view sees
    >= eps of the peak (in log(1 + x)). Returns ``(...)`` in [0, 1]."""
    return confidence_from_ratios(view_highlight_ratio(device, x, n, t, alpha_x, alpha_y, rho_s), valid, eps)


def _local_emitters(device: Device, x: Tensor, frame: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """For points ``x (N, 3)`` with frames ``(N, 3, 3)``: unit directions to every emitter sample in
    the local frame ``(N, K, 3)`` (K = L * Q), r^2 ``(N, K)``, the emitter-side cosine (-wi).n_l
    ``(N, K)`` and the quadrature weights ``(L, Q)`` — all from matrix products (F P^T - F x)."""
    pts, wq = device.emitter_samples(x.dtype, x.device)  # (L, Q, 3), (L, Q)
    L, Q = wq.shape
    P = pts.reshape(L * Q, 3)
    nl = torch.as_tensor(device.emitter_normals, dtype=x.dtype, device=x.device).repeat_interleave(Q, 0)
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

    def rows(self, idx: Tensor) -> "EmitterGeometry":
        return EmitterGeometry(self.wi_l[idx], self.wo_l[idx], self.falloff[idx], self.shape)


def local_emitter_geometry(device: Device, x: Tensor, n: Tensor, t: Tensor,
                           visibility: Tensor | None = None) -> EmitterGeometry:
    """``x, n, t (M, 3)`` camera space; ``visibility`` broadcastable to ``(M, L, Q)``."""
    frame = frame_from_normal_tangent(n, t)  # (M, 3, 3)
    wi_l, r2, cos_l, wq = _local_emitters(device, x, frame)
    L, Q = wq.shape
    falloff = wq.reshape(-1) * device.psi(cos_l) / r2
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


def emitter_terms(device: Device, x: Tensor, n: Tensor, t: Tensor, alpha_x: Tensor, alpha_y: Tensor,
                  visibility: Tensor | None = None, f0: float = F0_DIELECTRIC) -> tuple[Tensor, Tensor]:
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
        L, Q = device.emitter_samples(x.dtype, x.device)[1].shape
        vis = torch.broadcast_to(visibility, (*lead, L, Q)).reshape(-1, L, Q)
    geo = local_emitter_geometry(device, x.reshape(-1, 3), n.reshape(-1, 3), t.reshape(-1, 3), vis)
    a_l, s_l = terms_from_lobe(geo, specular_lobe(geo, alpha_x, alpha_y, f0))
    return a_l.reshape(*lead, -1), s_l.reshape(*lead, -1)


def measure_terms(device: Device, a_l: Tensor, s_l: Tensor, rho_d: Tensor, rho_s: Tensor,
                  pattern: Tensor | None = None) -> Tensor:
    """B ``(..., 3)`` from the factorised terms ``(..., L)`` and RGB albedos ``(..., 3)``."""
    if pattern is None:
        pattern = torch.as_tensor(device.pattern, dtype=a_l.dtype, device=a_l.device)
    p_eff = device.effective_pattern(pattern.to(a_l.dtype))  # (L, 3)
    return rho_d / torch.pi * (a_l @ p_eff) + rho_s * (s_l @ p_eff)


def measurement_rgb(device: Device, x: Tensor, n: Tensor, t: Tensor, rho_d: Tensor, rho_s: Tensor,
                    alpha_x: Tensor, alpha_y: Tensor, pattern: Tensor | None = None,
                    visibility: Tensor | None = None, f0: float = F0_DIELECTRIC) -> Tensor:
    """B ``(..., 3)``, equal to ``measure(physical_lumitexel(...))``, through the factorised terms
    (``emitter_terms``): for renderers and training data (many points)."""
    a_l, s_l = emitter_terms(device, x, n, t, alpha_x, alpha_y, visibility, f0)
    return measure_terms(device, a_l, s_l, rho_d, rho_s, pattern)
