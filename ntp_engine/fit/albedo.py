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

import numba
import numpy as np
import torch
from torch import Tensor

from ..io.jit import compiled
from ..io.thread_pools import numba_threads_as_torch
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
    leading dims (the last dim is j; the four broadcast together); ``(...)`` each, in ``a``'s dtype.
    Exact: the minimum over the KKT candidates (interior, four edges with the other variable optimal
    and clamped), summed in float64 in one compiled pass per problem (the torch form's ~50 small
    operations a call cost ~10% of the refinement). A problem with no finite candidate gets (0, 0)."""
    a, b, y, w = torch.broadcast_tensors(a, b, y, w)
    shape, J = a.shape[:-1], a.shape[-1]
    rows = [np.ascontiguousarray(t.detach().to(torch.float64).numpy()).reshape(-1, J) for t in (a, b, y, w)]
    u, v = np.zeros(len(rows[0])), np.zeros(len(rows[0]))
    with numba_threads_as_torch():
        _bounded_ls2_loop(*rows, float(hi_a), float(hi_b), u, v)
    return torch.from_numpy(u).reshape(shape).to(a.dtype), torch.from_numpy(v).reshape(shape).to(a.dtype)


@compiled(parallel=True)
def _bounded_ls2_loop(a, b, y, w, hi_a, hi_b, out_u, out_v):  # pragma: no cover
    """Fills ``out_u``, ``out_v (M,)`` (see ``bounded_ls2``) for the rows of ``a, b, y, w (M, J)``."""
    M, J = a.shape
    tiny = 1e-30
    cu, cv = np.empty((M, 5)), np.empty((M, 5))
    for m in numba.prange(M):
        saa = sbb = sab = say = sby = 0.0
        for j in range(J):
            wa, wb = w[m, j] * a[m, j], w[m, j] * b[m, j]
            saa += wa * a[m, j]
            sbb += wb * b[m, j]
            sab += wa * b[m, j]
            say += wa * y[m, j]
            sby += wb * y[m, j]
        det = saa * sbb - sab * sab
        ok_det = abs(det) > 1e-12 * (saa * sbb if saa * sbb > tiny else tiny)
        sa, sb = (saa if saa > tiny else tiny), (sbb if sbb > tiny else tiny)
        # the interior, then v = 0, v = hi_b, u = 0, u = hi_a each with the other optimal and clamped
        inv = 1.0 / det if ok_det else math.nan  # NaN: not a candidate
        cu[m, 0], cv[m, 0] = (sbb * say - sab * sby) * inv, (saa * sby - sab * say) * inv
        cu[m, 1], cv[m, 1] = min(max(say / sa, 0.0), hi_a), 0.0
        cu[m, 2], cv[m, 2] = min(max((say - hi_b * sab) / sa, 0.0), hi_a), hi_b
        cu[m, 3], cv[m, 3] = 0.0, min(max(sby / sb, 0.0), hi_b)
        cu[m, 4], cv[m, 4] = hi_a, min(max((sby - hi_a * sab) / sb, 0.0), hi_b)
        best, bu, bv = math.inf, 0.0, 0.0
        for k in range(5):
            u, v = cu[m, k], cv[m, k]
            if not (0.0 <= u <= hi_a and 0.0 <= v <= hi_b):
                continue  # NaN fails the bounds too
            cost = 0.0
            for j in range(J):
                r = u * a[m, j] + v * b[m, j] - y[m, j]
                cost += w[m, j] * r * r
            if cost < best:
                best, bu, bv = cost, u, v
        out_u[m], out_v[m] = bu, bv


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
