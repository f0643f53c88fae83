"""RGB albedo per texel (paper §7): rho_d in [0, 1] and rho_s in [0, 10] per channel by bounded
linear least squares against the trace's own measurements, with the fitted geometry, the pattern and
the scanner (2 unknowns per channel; the box-constrained optimum is found among the KKT
candidates). Eq. 1 is evaluated in the dtype of the pixels (float32 is plenty), the least squares in
float64.

Convention: ``pixels (N, V, 3)`` are linear pixel values (``scanner.exposure(pattern) * B``);
``position, normal_geo, tangent_geo (N, V, 3)`` each view's camera-space x, n^, t^; ``mask (N, V)``
the entries in the trace.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from ..physics.brdf import RHO_D_MAX, RHO_S_MAX
from ..physics.confidence import confidence_from_ratios, highlight_ratio
from ..physics.measurement import emitter_terms
from ..physics.pattern_sums import pattern_sums
from ..scanner.scanner import Scanner
from .geometry import FALLBACK_ALPHA, GeometryFit
from .highlights import fall_back_where_unseen, frame_in_views, parked_positions


def _albedo_bases(scanner: Scanner, pattern: Tensor, a_l: Tensor, s_l: Tensor) -> tuple[Tensor, Tensor]:
    """Pixel values of a unit diffuse and a unit specular surface under ``pattern`` (auto-exposed),
    from the factorised Eq. 1 terms ``(..., L)``: ``(..., 3)`` each."""
    p_eff, exposure = scanner.effective_pattern(pattern), scanner.exposure(pattern)
    return exposure * (a_l @ p_eff) / math.pi, exposure * (s_l @ p_eff)


def bounded_ls2(a: Tensor, b: Tensor, y: Tensor, w: Tensor, hi_a: float, hi_b: float) -> tuple[Tensor, Tensor]:
    """argmin over 0 <= u <= hi_a, 0 <= v <= hi_b of sum_j w_j (u a_j + v b_j - y_j)^2, batched over
    leading dims (the last dim is j). Exact: the minimum over the KKT candidates (interior, four
    edges with the other variable optimal and clamped, four corners)."""
    saa, sbb, sab = (w * a * a).sum(-1), (w * b * b).sum(-1), (w * a * b).sum(-1)
    say, sby = (w * a * y).sum(-1), (w * b * y).sum(-1)
    det = saa * sbb - sab * sab
    tiny = 1e-30
    cands = []
    ok_det = det.abs() > 1e-12 * (saa * sbb).clamp_min(tiny)
    cands.append(
        (
            (sbb * say - sab * sby) / torch.where(ok_det, det, torch.ones_like(det)),
            (saa * sby - sab * say) / torch.where(ok_det, det, torch.ones_like(det)),
        )
    )
    for v_fixed in (0.0, hi_b):
        u = ((say - v_fixed * sab) / saa.clamp_min(tiny)).clamp(0, hi_a)
        cands.append((u, torch.full_like(u, v_fixed)))
    for u_fixed in (0.0, hi_a):
        v = ((sby - u_fixed * sab) / sbb.clamp_min(tiny)).clamp(0, hi_b)
        cands.append((torch.full_like(v, u_fixed), v))
    best_u, best_v, best_cost = cands[0][0], cands[0][1], torch.full_like(saa, float("inf"))
    for k, (u, v) in enumerate(cands):
        feasible = (u >= 0) & (u <= hi_a) & (v >= 0) & (v <= hi_b) & torch.isfinite(u) & torch.isfinite(v)
        if k == 0:
            feasible = feasible & ok_det
        u = torch.where(feasible, u, torch.zeros_like(u))
        v = torch.where(feasible, v, torch.zeros_like(v))
        cost = (w * (u[..., None] * a + v[..., None] * b - y) ** 2).sum(-1)
        cost = torch.where(feasible, cost, torch.full_like(cost, float("inf")))
        better = cost < best_cost if k else torch.ones_like(cost, dtype=torch.bool)
        best_u, best_v = torch.where(better, u, best_u), torch.where(better, v, best_v)
        best_cost = torch.where(better, cost, best_cost)
    return best_u, best_v


def _albedo_ls(
    basis_d: Tensor, basis_s: Tensor, pixels: Tensor, mask: Tensor, rho_s_prior: Tensor | None, prior_weight: float
) -> tuple[Tensor, Tensor]:
    """The bounded 2-variable least squares per texel and channel, in float64; bases and pixels
    ``(N, V, 3)``. With ``prior_weight`` w > 0, one pseudo-observation per channel asks rho_s to be
    ``rho_s_prior (N,)`` (the lobe fitted to the network's lumitexel) with the weight of w views of
    typical specular signal: diffuse-dominant texels seen in few views no longer trade diffuse for a
    broad, bright lobe."""
    N, V = mask.shape
    w = mask[..., None].expand(N, V, 3).to(torch.float64)
    y = torch.where(mask[..., None], pixels, torch.zeros_like(pixels)).to(torch.float64)
    a, b = basis_d.double(), basis_s.double()
    if prior_weight > 0 and rho_s_prior is not None:
        scale = ((b.abs() * w).sum(1) / w.sum(1).clamp_min(1)).clamp_min(1e-12)  # (N, 3)
        a = torch.cat([a, torch.zeros_like(scale)[:, None]], 1)
        b = torch.cat([b, scale[:, None]], 1)
        y = torch.cat([y, (scale * rho_s_prior.double()[:, None])[:, None]], 1)
        w = torch.cat([w, torch.full_like(scale, float(prior_weight))[:, None]], 1)
    rd, rs = bounded_ls2(
        a.transpose(1, 2), b.transpose(1, 2), y.transpose(1, 2), w.transpose(1, 2), RHO_D_MAX, RHO_S_MAX
    )
    return rd, rs


def fit_albedo(
    scanner: Scanner,
    pattern: Tensor | None,
    pixels: Tensor,
    position: Tensor,
    normal_geo: Tensor,
    tangent_geo: Tensor,
    mask: Tensor,
    geometry: GeometryFit,
    visibility: Tensor | None = None,
    prior_weight: float = 0.0,
) -> tuple[Tensor, Tensor]:
    """RGB rho_d ``(N, 3)`` in [0, 1] and rho_s ``(N, 3)`` in [0, 10] from a trace's own linear pixel
    values ``pixels (N, V, 3)`` (``scanner.exposure(pattern) * B``) with the fitted geometry.
    Eq. 1 is evaluated in the dtype of ``pixels`` (float32 is plenty), the least squares in float64.

    ``position, normal_geo, tangent_geo (N, V, 3)``: each view's camera-space x, n^, t^;
    ``mask (N, V)``: entries in the trace. Unmasked entries are ignored (their values may be junk)."""
    dtype = pixels.dtype
    n_cam, t_cam = frame_in_views(geometry, normal_geo, tangent_geo)
    N, V = mask.shape
    ax = geometry.alpha_x.to(dtype)[:, None].expand(N, V)
    ay = geometry.alpha_y.to(dtype)[:, None].expand(N, V)
    p = torch.as_tensor(scanner.pattern, dtype=dtype) if pattern is None else pattern.to(dtype)
    # one pass gives both bases: a unit diffuse and a unit specular surface under the pattern
    a_l, s_l = emitter_terms(scanner, parked_positions(position, mask), n_cam, t_cam, ax, ay, visibility)
    basis_d, basis_s = _albedo_bases(scanner, p, a_l, s_l)
    rd, rs = _albedo_ls(basis_d, basis_s, pixels, mask, geometry.rho_s, prior_weight)
    return rd.to(dtype), rs.to(dtype)


def highlights_and_albedo(
    scanner: Scanner,
    pixels: Tensor,
    position: Tensor,
    normal_geo: Tensor,
    tangent_geo: Tensor,
    mask: Tensor,
    geometry: GeometryFit,
    prior_weight: float = 0.0,
) -> tuple[Tensor, Tensor, Tensor]:
    """``flag_unseen_highlights`` then ``fit_albedo`` (the scanner's pattern, no visibility) in one pass:
    every entry's sums over the emitters (``physics.pattern_sums``: the fused loop) serve both
    Eq. 6 and Eq. 1; only texels that fall back to the default lobe get their lobe summed again.
    Same arguments and results as the two (``geometry`` updated in place); returns
    (beta ``(N,)``, rho_d, rho_s ``(N, 3)``)."""
    dtype = pixels.dtype
    N, V = mask.shape
    n_cam, t_cam = (v.reshape(-1, 3) for v in frame_in_views(geometry, normal_geo, tangent_geo))
    x, valid = position.reshape(-1, 3), mask.reshape(-1)

    def per_entry(a):
        return a.double()[:, None].expand(N, V).reshape(-1)

    ax, ay = per_entry(geometry.alpha_x), per_entry(geometry.alpha_y)
    sums = pattern_sums(scanner, x, n_cam, t_cam, ax, ay, valid)
    rho_s = per_entry(geometry.rho_s)
    ratio = highlight_ratio((rho_s * sums.lobe_max)[:, None], rho_s * sums.lobe_peak).reshape(N, V)

    beta = confidence_from_ratios(ratio, mask)
    unseen = fall_back_where_unseen(geometry, beta)
    specular = sums.specular
    redo = unseen[:, None].expand(N, V).reshape(-1) & valid
    if redo.any():
        f = torch.full((int(redo.sum()),), FALLBACK_ALPHA, dtype=torch.float64)
        specular = specular.clone()
        specular[redo] = pattern_sums(scanner, x[redo], n_cam[redo], t_cam[redo], f, f, valid[redo]).specular
    exposure = scanner.exposure(torch.as_tensor(scanner.pattern))
    basis_d = (exposure / math.pi * sums.diffuse).reshape(N, V, 3)
    basis_s = (exposure * specular).reshape(N, V, 3)
    rd, rs = _albedo_ls(basis_d, basis_s, pixels, mask, geometry.rho_s, prior_weight)
    return beta.to(dtype), rd.to(dtype), rs.to(dtype)
