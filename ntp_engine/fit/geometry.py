"""Fitting lumitexels to anisotropic GGX (paper §7), batched over texels.

Geometry (``fit_geometry``): from grayscale specular lumitexels ``(N, 6144)`` in the lumitexel
frame to the shading normal n, tangent t, alpha_x >= alpha_y and a grayscale rho_s.

The key fact: GGX's D(h) = 1 / (pi ax ay (h^T M h)^2) with M = n n^T + t t^T/ax^2 + b b^T/ay^2.
A lumitexel value is m_l = rho_s D(h_l) Phi_l with Phi_l = F G1(wi) G1(wo) / (4 cos_o r_l^2),
a slowly varying factor. So y_l = (m_l / Phi_l)^(-1/2) = h_l^T A h_l is *linear* in the symmetric
matrix A = sqrt(pi ax ay / rho_s) M: a weighted linear least-squares problem with 6 unknowns per
texel, solved in one batched 6x6 system. Eigen-decomposing A gives n (smallest eigenvalue), t, the
alphas (eigenvalue ratios) and rho_s (scale). Phi depends on the fit, so the solve is repeated a
few times with Phi from the previous estimate (exact for noise-free lumitexels). The weights make
the linear problem approximate least squares in log(1 + x), the network's and the metric's space,
and are re-weighted (IRLS) so that noise far from the lobe counts with its small log residual; after
the first solve, each texel's K lights are those where the fitted lobe is brightest (lights the
model leaves dark add only a constant to the objective). A final Levenberg-Marquardt in A-space
minimises the log(1 + x) residual itself (analytic Jacobian g_l f_l with Phi frozen within a step;
a step is kept only where the true residual falls). Each texel runs these on its own, in one compiled
loop (``fit.lobe_loop``), and stops when its own steps stop paying.

Canonical output (the model's symmetries): alpha_x >= alpha_y (else (t, ax, ay) -> (b, ay, ax)),
and t's component along the lumitexel x (then y) axis is >= 0 (t -> -t is the same BRDF).

Flags (``fit.flags.TexelFlag``): non-finite input, an all-zero lumitexel, no usable lobe: such texels get the
fallback (``FALLBACK_ALPHA`` isotropic, normal from the diffuse lumitexel or +z, rho_s 0) — never
NaN. The highlight check (``highlights``) and the albedo (``albedo``) follow the geometry.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from ..io.thread_pools import numba_threads_as_torch
from ..physics.brdf import fresnel_schlick
from ..physics.frame import any_tangent, cross, frame_from_normal_tangent, safe_normalize
from ..physics.lumitexel import DIFFUSE_RES, SPECULAR_RES, specular_lumitexel, texel_positions
from .flags import TexelFlag
from .lobe_loop import BOUNDS, fit_lobes

FALLBACK_ALPHA = 0.3  # isotropic roughness for texels without a usable specular lobe


@dataclass
class GeometryFit:
    """The fitted lobe of N texels in their lumitexel frames (canonical: alpha_x >= alpha_y)."""

    normal: Tensor  # (N, 3) shading normal in the lumitexel frame
    tangent: Tensor  # (N, 3) shading tangent, alpha_x along it
    alpha_x: Tensor  # (N,) >= alpha_y
    alpha_y: Tensor  # (N,)
    rho_s: Tensor  # (N,) grayscale specular scale of the lumitexel
    flags: Tensor  # (N,) int: ``TexelFlag`` bits, 0 = good fit
    log_rmse: Tensor | None  # (N,) log(1 + x) RMSE fitted vs input over all lights (if asked for)

    def rows(self, sel: slice | Tensor) -> GeometryFit:
        """The fit of the texels ``sel`` only."""
        return GeometryFit(
            self.normal[sel],
            self.tangent[sel],
            self.alpha_x[sel],
            self.alpha_y[sel],
            self.rho_s[sel],
            self.flags[sel],
            None if self.log_rmse is None else self.log_rmse[sel],
        )


@functools.lru_cache(maxsize=4)
def light_table(res: int, device: str, dtype: torch.dtype) -> dict[str, Tensor]:
    """Per light of a ``res`` specular lumitexel (wo = +z): unit wi, r^2, half vector h, the six
    quadratic features of h (A's entries) and Schlick's Fresnel, on ``device`` in ``dtype``."""
    p = texel_positions(res, torch.float64)
    r2 = (p * p).sum(-1)
    wi = p / r2.sqrt()[:, None]
    h = safe_normalize(wi + torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64))
    hx, hy, hz = h.unbind(-1)
    feats = torch.stack([hx * hx, hy * hy, hz * hz, 2 * hx * hy, 2 * hx * hz, 2 * hy * hz], -1)
    fres = fresnel_schlick(hz)  # wo = +z: wi.h = h.z for every light
    out = {"wi": wi, "r2": r2, "h": h, "feats": feats, "fresnel": fres}
    return {k: v.to(device=device, dtype=dtype) for k, v in out.items()}


def canonical_lobe(n: Tensor, t: Tensor, ax: Tensor, ay: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """alpha_x >= alpha_y; t orthogonal to n with a non-negative x (then y) component."""
    b = cross(n, t)
    swap = ay > ax
    t = torch.where(swap[:, None], b, t)
    ax, ay = torch.where(swap, ay, ax), torch.where(swap, ax, ay)
    t = safe_normalize(t - (t * n).sum(-1, keepdim=True) * n, fallback=any_tangent(n))
    key = torch.where(t[:, 0].abs() > 1e-6, t[:, 0], t[:, 1])
    t = torch.where((key < 0)[:, None], -t, t)
    return n, t, ax, ay


def _log_lumitexel(n, t, ax, ay, rho, res=SPECULAR_RES) -> Tensor:
    one = torch.ones_like(rho)[:, None]
    return torch.log1p(specular_lumitexel(n, t, rho[:, None] * one, ax, ay, res)[..., 0])


def diffuse_normal(diffuse: Tensor) -> tuple[Tensor, Tensor]:
    """Normal and grayscale rho_d from diffuse lumitexels ``(N, 384)``: pi r^2 m_l = rho_d (n.wi_l)
    for lit lights, a linear LS for rho_d n. Returns (n (N, 3), rho_d (N,))."""
    p = texel_positions(DIFFUSE_RES, diffuse.dtype, diffuse.device)
    r2 = (p * p).sum(-1)
    wi = p / r2.sqrt()[:, None]
    y = math.pi * r2 * diffuse
    w = (diffuse > 1e-3 * diffuse.amax(-1, keepdim=True).clamp_min(1e-30)).to(diffuse.dtype)
    ata = (wi[None] * w[..., None]).transpose(1, 2) @ wi  # (N, 3, 3)
    atb = ((wi[None] * w[..., None]) * y[..., None]).sum(1)
    ata = ata + 1e-6 * torch.eye(3, dtype=diffuse.dtype, device=diffuse.device)
    v = torch.linalg.solve(ata, atb[..., None])[..., 0]
    rho = v.norm(dim=-1)
    z = torch.zeros_like(v)
    z[:, 2] = 1.0
    return safe_normalize(v, fallback=z), rho


def fit_geometry(
    specular: Tensor,
    diffuse: Tensor | None = None,
    iterations: int = 3,
    top_k: int = 384,
    gn_steps: int = 10,
    with_error: bool = False,
) -> GeometryFit:
    """Fit n, t, alpha_x, alpha_y (and a grayscale rho_s) to specular lumitexels ``(N, 6144)``
    (read as float32, on the CPU; NaN/inf and negative values allowed: flagged or clipped).

    ``diffuse (N, 384)`` provides the fallback normal for texels without a usable lobe. Each texel
    is fitted on its own in float64 (``fit.lobe_loop``); results in float32. ``with_error`` also
    renders the fitted lumitexels to report the log(1 + x) RMSE (costs about as much as the fit)."""
    N = specular.shape[0]
    tab = {k: v.numpy() for k, v in light_table(SPECULAR_RES, "cpu", torch.float64).items()}
    out = np.zeros((N, 12))
    with numba_threads_as_torch():  # the IRLS and the LM per texel
        fit_lobes(
            specular.detach().float().contiguous().numpy(),  # one compiled specialisation
            tab["wi"],
            tab["r2"],
            tab["fresnel"],
            tab["feats"],
            iterations,
            min(top_k, specular.shape[1]),
            gn_steps,
            BOUNDS,
            out,
        )
    o = torch.from_numpy(out).float()
    n, t, ax, ay, rho, ok = o[:, 0:3], o[:, 3:6], o[:, 6], o[:, 7], o[:, 8], o[:, 9] > 0
    finite, peak = o[:, 10] > 0, o[:, 11]
    n, t, ax, ay = canonical_lobe(n, t, ax, ay)
    flags = (~finite).long() * TexelFlag.NONFINITE
    flags |= ((peak <= 1e-8) & finite).long() * TexelFlag.ZERO
    flags |= ((~ok) & (flags == 0)).long() * TexelFlag.NO_LOBE
    bad = flags != 0
    if bad.any():
        if diffuse is not None:
            nd, _ = diffuse_normal(torch.where(torch.isfinite(diffuse), diffuse, torch.zeros_like(diffuse)).float())
        else:
            nd = torch.zeros(N, 3)
            nd[:, 2] = 1.0
        n = torch.where(bad[:, None], nd, n)
        x_axis = torch.tensor([1.0, 0.0, 0.0]).expand_as(nd)
        t = torch.where(bad[:, None], frame_from_normal_tangent(nd, x_axis)[:, 0], t)
        fa = torch.full_like(ax, FALLBACK_ALPHA)
        ax, ay = torch.where(bad, fa, ax), torch.where(bad, fa, ay)
        rho = torch.where(bad, torch.zeros_like(rho), rho)
        n, t, ax, ay = canonical_lobe(n, t, ax, ay)
    fit = GeometryFit(n, t, ax, ay, rho, flags, None)
    if with_error:
        fit.log_rmse = lumitexel_log_rmse(fit, specular)
    return fit


def lumitexel_log_rmse(fit: GeometryFit, specular: Tensor, chunk: int = 1024) -> Tensor:
    """Per texel log(1 + x) RMSE between the fitted and the given lumitexels ``(N, 6144)``."""
    out = []
    for i in range(0, len(specular), chunk):
        s = slice(i, i + chunk)
        m = specular[s].float()
        m = torch.where(torch.isfinite(m), m, torch.zeros_like(m)).clamp_min(0)
        pred = _log_lumitexel(fit.normal[s], fit.tangent[s], fit.alpha_x[s], fit.alpha_y[s], fit.rho_s[s])
        out.append((pred - torch.log1p(m)).pow(2).mean(-1).sqrt())
    return torch.cat(out) if out else torch.zeros(0)
