"""How well a trace saw a point's specular highlight: the confidence beta of paper Eq. 6.

Convention: per view j, the ratio log(1 + max_l s_jl) / log(1 + s*_j) compares the brightest the
specular lobe appears toward any emitter with the lobe's peak over all directions; beta =
min(max_j ratio_j / eps, 1) over the trace's views. Points, frames and the camera as in
``measurement`` (the scanner's camera space, metres). beta is 0 when no view saw the highlight.
"""

from __future__ import annotations

import torch
from torch import Tensor

from ..scanner.scanner import Scanner
from .brdf import F0_DIELECTRIC, ggx_specular
from .frame import reflect, safe_normalize
from .measurement import EmitterGeometry, local_emitter_geometry, specular_lobe

# the peak's search grid: half vectors (ax u, ay v, 1) for u, v on it (specular_peak)
PEAK_GRID = torch.linspace(-2.5, 2.5, 11, dtype=torch.float64)


def specular_peak(
    wo: Tensor, alpha_x: Tensor, alpha_y: Tensor, rho_s: Tensor | float = 1.0, f0: float = F0_DIELECTRIC
) -> Tensor:
    """max over wi of rho_s * specular lobe(wi; wo) ``(...)``, for local ``wo (..., 3)``.

    Searched over half vectors h ~ (ax u, ay v, 1), |u|, |v| <= 2.5 around the normal (the lobe's
    maximum lies there: D peaks at h = n; F, G only shift it at grazing views). 0 if wo_z <= 0.
    """
    g = PEAK_GRID.to(dtype=wo.dtype, device=wo.device)
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


def view_highlight_ratio(
    scanner: Scanner, x: Tensor, n: Tensor, t: Tensor, alpha_x: Tensor, alpha_y: Tensor, rho_s: Tensor | float = 1.0
) -> Tensor:
    """Eq. 6's per-view ratio for one point seen in V views: x, n, t ``(..., V, 3)`` camera space,
    alphas and grayscale rho_s ``(...)``. Returns ``(..., V)`` in [0, ~1]."""
    lead = x.shape[:-1]  # (..., V)

    def flat(a):
        return torch.as_tensor(a, dtype=x.dtype, device=x.device)

    ax, ay = (flat(a)[..., None].expand(lead).reshape(-1) for a in (alpha_x, alpha_y))
    rs = flat(rho_s)
    rs = (rs[..., None] if rs.dim() else rs).expand(lead).reshape(-1)
    geo = local_emitter_geometry(scanner, x.reshape(-1, 3), n.reshape(-1, 3), t.reshape(-1, 3))
    return ratios_from_lobe(geo, specular_lobe(geo, ax, ay), ax, ay, rs).reshape(lead)


def ratios_from_lobe(geo: EmitterGeometry, spec: Tensor, alpha_x: Tensor, alpha_y: Tensor, rho_s: Tensor) -> Tensor:
    """Eq. 6's ratio per point ``(M,)`` from its lobe toward every emitter sample ``spec (M, K)``."""
    return highlight_ratio(rho_s[:, None] * spec, specular_peak(geo.wo_l, alpha_x, alpha_y, rho_s))


def confidence(
    scanner: Scanner,
    x: Tensor,
    n: Tensor,
    t: Tensor,
    alpha_x: Tensor,
    alpha_y: Tensor,
    rho_s: Tensor | float = 1.0,
    valid: Tensor | None = None,
    eps: float = 0.5,
) -> Tensor:
    """beta of Eq. 6 for one point seen in V views (see ``view_highlight_ratio``); ``valid (..., V)``
    masks views out of the trace. beta is 0 when no view sees any highlight, 1 once a view sees
    >= eps of the peak (in log(1 + x)). Returns ``(...)`` in [0, 1]."""
    return confidence_from_ratios(view_highlight_ratio(scanner, x, n, t, alpha_x, alpha_y, rho_s), valid, eps)
