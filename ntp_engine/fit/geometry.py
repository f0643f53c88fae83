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
a step is kept only where the true residual falls).

Canonical output (the model's symmetries): alpha_x >= alpha_y (else (t, ax, ay) -> (b, ay, ax)),
and t's component along the lumitexel x (then y) axis is >= 0 (t -> -t is the same BRDF).

Flags (``FLAG_*``): non-finite input, an all-zero lumitexel, no usable lobe: such texels get the
fallback (``FALLBACK_ALPHA`` isotropic, normal from the diffuse lumitexel or +z, rho_s 0) — never
NaN. The highlight check (``highlights``) and the albedo (``albedo``) follow the geometry.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import torch
from torch import Tensor

from ..physics.brdf import ALPHA_MAX, ALPHA_MIN, RHO_S_MAX, fresnel_schlick, smith_g1
from ..physics.frame import any_tangent, cross, frame_from_normal_tangent, safe_normalize
from ..physics.lumitexel import DIFFUSE_RES, SPECULAR_RES, specular_lumitexel, texel_positions

FALLBACK_ALPHA = 0.3  # isotropic roughness for texels without a usable specular lobe
FLAG_NONFINITE, FLAG_ZERO, FLAG_NO_LOBE, FLAG_NO_HIGHLIGHT = 1, 2, 4, 8


@dataclass
class GeometryFit:
    """The fitted lobe of N texels in their lumitexel frames (canonical: alpha_x >= alpha_y)."""

    normal: Tensor  # (N, 3) shading normal in the lumitexel frame
    tangent: Tensor  # (N, 3) shading tangent, alpha_x along it
    alpha_x: Tensor  # (N,) >= alpha_y
    alpha_y: Tensor  # (N,)
    rho_s: Tensor  # (N,) grayscale specular scale of the lumitexel
    flags: Tensor  # (N,) int: FLAG_* bits, 0 = good fit
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


def _phi(wi: Tensor, r2: Tensor, fres: Tensor, n: Tensor, t: Tensor, ax: Tensor, ay: Tensor) -> Tensor:
    """F G1(wi) G1(wo) / (4 cos_o r^2) for lights ``(N, K)`` under the frames ``(N, 3)``."""
    frame = frame_from_normal_tangent(n, t)  # (N, 3, 3) rows t, b, n
    wi_l = wi @ frame.transpose(1, 2)  # to_local as one batched product (N, K, 3)
    wo_l = frame[:, :, 2]  # wo = +z in the lumitexel frame
    g = smith_g1(wi_l, ax[:, None], ay[:, None]) * smith_g1(wo_l, ax, ay)[:, None]
    cos_o = wo_l[:, 2].clamp_min(1e-4)[:, None]
    phi = fres * g / (4 * cos_o * r2)
    return torch.where(wi_l[..., 2] > 0, phi, torch.zeros_like(phi))


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


def _solve_lobe(y: Tensor, w: Tensor, feats: Tensor) -> tuple[Tensor, ...]:
    """Weighted LS for A (y ~ f^T a) and its GGX reading: n, t, ax, ay, rho_s, ok, a (N, 6)."""
    fw = (feats * w[..., None]).transpose(1, 2)  # (N, 6, K)
    ata = fw @ feats  # (N, 6, 6)
    atb = (fw @ y[..., None])[..., 0]  # (N, 6)
    scale = ata.diagonal(dim1=1, dim2=2).mean(-1).clamp_min(1e-30)
    ata = ata + 1e-9 * scale[:, None, None] * torch.eye(6, dtype=y.dtype, device=y.device)
    a = torch.linalg.solve(ata, atb[..., None])[..., 0]
    return _solve_lobe_from_a(a)


def _solve_lobe_from_a(a: Tensor) -> tuple[Tensor, ...]:
    """Read n, t, ax, ay, rho_s (alphas clamped to their bounds), ok, a from A's 6 entries."""
    A = torch.stack(
        [
            torch.stack([a[:, 0], a[:, 3], a[:, 4]], -1),
            torch.stack([a[:, 3], a[:, 1], a[:, 5]], -1),
            torch.stack([a[:, 4], a[:, 5], a[:, 2]], -1),
        ],
        -2,
    )
    evals, evecs = torch.linalg.eigh(A)  # ascending
    lam0 = evals[:, 0]
    ok = torch.isfinite(evals).all(-1) & (lam0 > 0)
    lam0c = lam0.clamp_min(1e-30)
    n = evecs[:, :, 0]
    n = torch.where((n[:, 2:3] < 0), -n, n)
    t = evecs[:, :, 1]
    ax = (lam0c / evals[:, 1].clamp_min(1e-30)).sqrt().clamp(ALPHA_MIN, ALPHA_MAX)
    ay = (lam0c / evals[:, 2].clamp_min(1e-30)).sqrt().clamp(ALPHA_MIN, ALPHA_MAX)
    rho = math.pi * ax * ay / (lam0c * lam0c)
    return n, t, ax, ay, rho, ok, a


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
    chunk: int = 1024,
    with_error: bool = False,
) -> GeometryFit:
    """Fit n, t, alpha_x, alpha_y (and a grayscale rho_s) to specular lumitexels ``(N, 6144)``.

    ``diffuse (N, 384)`` provides the fallback normal for texels without a usable lobe.
    Works in float32 (input is cast); processes ``chunk`` texels at a time. ``with_error`` also
    renders the fitted lumitexels to report the log(1 + x) RMSE (costs about as much as the fit)."""
    outs = [
        _fit_chunk(
            specular[i : i + chunk].float(),
            None if diffuse is None else diffuse[i : i + chunk].float(),
            iterations,
            top_k,
            gn_steps,
        )
        for i in range(0, len(specular), chunk)
    ]
    if not outs:
        e = torch.zeros(0)
        return GeometryFit(torch.zeros(0, 3), torch.zeros(0, 3), e, e, e, torch.zeros(0, dtype=torch.int64), e)
    fields = [f for f in GeometryFit.__dataclass_fields__ if f != "log_rmse"]
    fit = GeometryFit(**{f: torch.cat([getattr(o, f) for o in outs]) for f in fields}, log_rmse=None)
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


def _fit_chunk(m: Tensor, diffuse: Tensor | None, iterations: int, top_k: int, gn_steps: int) -> GeometryFit:
    N = m.shape[0]
    dev = m.device
    tab = light_table(SPECULAR_RES, str(dev), torch.float32)
    flags = torch.zeros(N, dtype=torch.int64, device=dev)
    finite = torch.isfinite(m).all(-1)
    flags |= (~finite).long() * FLAG_NONFINITE
    m = torch.nan_to_num(m, nan=0.0, posinf=0.0, neginf=0.0).clamp_min_(0)
    peak = m.amax(-1)
    flags |= ((peak <= 1e-8) & finite).long() * FLAG_ZERO

    # first pass: the K most significant lights of the data (by m / Phi0, Phi0 with n = z, G = 1);
    # later passes: the K lights where the fitted lobe is largest (smallest h^T A h) - lights the
    # model leaves dark add only a constant to the log(1 + x) objective
    phi0 = tab["fresnel"] / (4 * tab["r2"])
    k = min(top_k, m.shape[1])
    idx = (m / phi0).topk(k, dim=-1).indices  # (N, K)

    n = torch.zeros(N, 3, device=dev)
    n[:, 2] = 1.0
    t = torch.zeros(N, 3, device=dev)
    t[:, 0] = 1.0
    ax = torch.full((N,), 0.1, device=dev)
    ay = ax.clone()
    ok = torch.zeros(N, dtype=torch.bool, device=dev)
    rho = torch.ones(N, device=dev)
    a_cur = None
    for it in range(iterations):
        if it < 2:  # the lights change once, after the first solve
            mk = m.gather(1, idx)
            wi, r2, fres, feats = tab["wi"][idx], tab["r2"][idx], tab["fresnel"][idx], tab["feats"][idx]
            feats64 = feats.double()
        phi = phi0[idx] if a_cur is None else _phi(wi, r2, fres, n, t, ax, ay)
        valid = (mk > 1e-6 * peak[:, None]) & (phi > 0)
        y = torch.where(valid, mk / phi.clamp_min(1e-30), torch.ones_like(mk)).rsqrt()
        # d log1p(m) = -2 m / (1 + m) dy / y: weights that turn the solve into log1p-space LS ...
        w = (2 * mk / ((1 + mk) * y)) ** 2
        if a_cur is not None:
            # ... and, away from the current fit, weights that make the weighted y residual equal
            # the true log1p residual (IRLS): far noise has a huge y residual but a small log one
            y_model = (feats64 @ a_cur[..., None])[..., 0].float()
            m_model = phi / y_model.clamp_min(1e-12) ** 2
            r_log = torch.log1p(m_model.clamp_max(1e30)) - torch.log1p(mk)
            dy = y_model - y
            far = (dy.abs() > 1e-3 * y) & (y_model > 0)
            w = torch.where(far, (r_log / torch.where(far, dy, torch.ones_like(dy))) ** 2, w)
        w = torch.where(valid, w, torch.zeros_like(w))
        n_new, t_new, ax_new, ay_new, rho_new, ok_new, a_new = _solve_lobe(y.double(), w.double(), feats64)
        n_new, t_new, ax_new, ay_new, rho_new = (v.float() for v in (n_new, t_new, ax_new, ay_new, rho_new))
        take = ok_new & (n_new[:, 2] > 0.05)
        n = torch.where(take[:, None], n_new, n)
        t = torch.where(take[:, None], t_new, t)
        ax, ay, rho = torch.where(take, ax_new, ax), torch.where(take, ay_new, ay), torch.where(take, rho_new, rho)
        a_cur = a_new if a_cur is None else torch.where(take[:, None], a_new, a_cur)
        ok = ok | take
        if it == 0 and iterations > 1:  # one re-selection suffices: the lobe moves little after
            y_all = a_cur.float() @ tab["feats"].T  # (N, 6144): small where the lobe is bright
            y_all.masked_fill_(~(y_all > 0), float("inf"))
            model_idx = y_all.topk(k, dim=-1, largest=False).indices
            idx = torch.where(ok[:, None], model_idx, idx)
    rho = rho.clamp(1e-12, RHO_S_MAX * 10)
    if gn_steps > 0:
        n, t, ax, ay, rho = _gauss_newton(m, idx, n, t, ax, ay, rho, ok & finite, gn_steps)
    n, t, ax, ay = canonical_lobe(n, t, ax, ay)

    flags |= ((~ok) & (flags == 0)).long() * FLAG_NO_LOBE
    bad = flags != 0
    if bad.any():
        if diffuse is not None:
            nd, _ = diffuse_normal(torch.where(torch.isfinite(diffuse), diffuse, torch.zeros_like(diffuse)))
        else:
            nd = torch.zeros(N, 3, device=dev)
            nd[:, 2] = 1.0
        n = torch.where(bad[:, None], nd, n)
        t = torch.where(
            bad[:, None],
            frame_from_normal_tangent(nd, torch.tensor([1.0, 0.0, 0.0], device=dev).expand_as(nd))[:, 0],
            t,
        )
        fa = torch.full_like(ax, FALLBACK_ALPHA)
        ax, ay = torch.where(bad, fa, ax), torch.where(bad, fa, ay)
        rho = torch.where(bad, torch.zeros_like(rho), rho)
        n, t, ax, ay = canonical_lobe(n, t, ax, ay)
    return GeometryFit(n, t, ax, ay, rho, flags, None)


# --------------------------------------------------------------------- Gauss-Newton in A-space
def _lobe_to_a(n: Tensor, t: Tensor, ax: Tensor, ay: Tensor, rho: Tensor) -> Tensor:
    """The 6 entries (a00, a11, a22, a01, a02, a12) of A = sqrt(pi ax ay / rho) M(n, t, ax, ay)."""
    b = cross(n, t)
    M = (
        n[:, :, None] * n[:, None, :]
        + t[:, :, None] * t[:, None, :] / (ax * ax)[:, None, None]
        + b[:, :, None] * b[:, None, :] / (ay * ay)[:, None, None]
    )
    A = (math.pi * ax * ay / rho.clamp_min(1e-30)).sqrt()[:, None, None] * M
    return torch.stack([A[:, 0, 0], A[:, 1, 1], A[:, 2, 2], A[:, 0, 1], A[:, 0, 2], A[:, 1, 2]], -1)


def _log_residual(a: Tensor, feats: Tensor, phi: Tensor, log_mk: Tensor, valid: Tensor):
    """log1p(model) - log1p(m) over K lights with the model m = Phi / (f.a)^2; also d r / d y."""
    y = (feats @ a[:, :, None])[..., 0]
    good = valid & (y > 0)
    ys = torch.where(good, y, torch.ones_like(y))
    mm = torch.where(good, phi / (ys * ys), torch.zeros_like(y))
    r = torch.where(valid, torch.log1p(mm) - log_mk, torch.zeros_like(y))
    g = torch.where(good, -2 * mm / ((1 + mm) * ys), torch.zeros_like(y))
    return r, g


def _gauss_newton(m, idx, n, t, ax, ay, rho, active, steps):
    """Levenberg-Marquardt on the log1p residual over each texel's K lights, parameterised by A
    (analytic Jacobian g_l f_l with Phi frozen within a step, re-evaluated after it); a step is
    kept only where the true residual (new Phi, alphas clamped to their bounds) decreases.
    float64 throughout (measured: faster here than float32 Phi with casts)."""
    tab = light_table(SPECULAR_RES, str(m.device), torch.float64)
    wi, r2, fres, feats = tab["wi"][idx], tab["r2"][idx], tab["fresnel"][idx], tab["feats"][idx]
    mk = m.gather(1, idx).double()
    log_mk = torch.log1p(mk)
    valid = mk >= 0
    n, t, ax, ay, rho = (v.double() for v in (n, t, ax, ay, rho))
    a = _lobe_to_a(n, t, ax, ay, rho)
    phi = _phi(wi, r2, fres, n, t, ax, ay)
    r, g = _log_residual(a, feats, phi, log_mk, valid)
    cost = (r * r).sum(-1)
    lam = torch.full_like(cost, 1e-3)
    eye = torch.eye(6, dtype=torch.float64, device=m.device)
    for _ in range(steps):
        J = g[..., None] * feats
        jtj = J.transpose(1, 2) @ J
        H = jtj + lam[:, None, None] * (torch.diag_embed(jtj.diagonal(dim1=1, dim2=2)) + 1e-12 * eye)
        step = torch.linalg.solve(H, -(J.transpose(1, 2) @ r[..., None]))[..., 0]
        n2, t2, ax2, ay2, rho2, ok2, _ = _solve_lobe_from_a(a + step)
        a2 = _lobe_to_a(n2, t2, ax2, ay2, rho2)
        phi2 = _phi(wi, r2, fres, n2, t2, ax2, ay2)
        r_new, g_new = _log_residual(a2, feats, phi2, log_mk, valid)
        cost_new = (r_new * r_new).sum(-1)
        better = active & ok2 & (n2[:, 2] > 0.05) & torch.isfinite(cost_new) & (cost_new < cost)
        moving = better & (cost - cost_new > 1e-3 * cost)  # still improving by more than 0.1%
        sel = better[:, None]
        n, t, a = torch.where(sel, n2, n), torch.where(sel, t2, t), torch.where(sel, a2, a)
        ax, ay, rho = torch.where(better, ax2, ax), torch.where(better, ay2, ay), torch.where(better, rho2, rho)
        r, g, cost = torch.where(sel, r_new, r), torch.where(sel, g_new, g), torch.where(better, cost_new, cost)
        lam = torch.where(better, lam * 0.2, lam * 10).clamp(1e-9, 1e6)
        if float(moving.float().mean()) < 0.005:  # (nearly) every texel has converged
            break
    return n.float(), t.float(), ax.float(), ay.float(), rho.float()
