"""The refinement's solver: batched Levenberg-Marquardt over texels (11 unknowns each: a frame
rotation omega, two log alphas, RGB rho_d and rho_s), box bounds by projection with an active set,
the albedos' linear start (``albedo_start``) and the multi-start (``multi_start``).

Convention: parameters as ``refine.model``; costs in half chi-square units, data (Cauchy-robust)
plus priors (``refine.priors``).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from ..fit.albedo import bounded_ls2
from ..physics.brdf import ALPHA_MAX, ALPHA_MIN, RHO_D_MAX, RHO_S_MAX
from .gauss_newton import N_PARAMS, data_cost, normal_equations
from .model import P_LOGA, P_OMEGA, P_RHO_D, P_RHO_S, Round, Trace, fold, residuals, robust_cost
from .priors import Prior, prior_cost, prior_normal_in, tint_scale
from .settings import TUNING, RefineSettings

LOWER = torch.tensor([-math.inf] * 3 + [math.log(ALPHA_MIN)] * 2 + [0.0] * 6)
UPPER = torch.tensor([math.inf] * 3 + [math.log(ALPHA_MAX)] * 2 + [RHO_D_MAX] * 3 + [RHO_S_MAX] * 3)


def cost_at(rnd: Round, q: Tensor, prior: Prior, settings: RefineSettings) -> Tensor:
    """The objective per texel at ``q (N, 11)``: robust data cost plus the priors."""
    frame = fold(rnd.frame0, q[:, P_OMEGA])  # one rotation for the bases and the normal's pull
    d, s = rnd.bases_in(frame, q[:, P_LOGA])
    u = prior_normal_in(frame, prior.n_prior)
    tilt = 0.5 * prior.n_w * (u[:, :2] ** 2).sum(1)
    tr = rnd.tr
    data = data_cost(d, s, q, tr.y, tr.inv_sigma, tr.mask, tr.censored, settings.noise.robust)
    return data + prior_cost(q, prior) + tilt


def levenberg_marquardt(
    rnd: Round,
    p: Tensor,
    prior: Prior,
    free: Tensor,
    iterations: int,
    settings: RefineSettings,
) -> tuple[Tensor, Tensor, Tensor]:
    """Up to ``iterations`` LM steps from ``p (N, 11)`` with the parameters ``free (N, 11)``; a
    texel whose step no longer lowers its cost by ``TUNING.solver.converged`` (relative) is done and drops out.
    Each accepted rotation is folded into ``rnd``'s frame (omega stays 0 between steps). Returns p,
    the cost per texel and the Gauss-Newton Hessian (float64) of its last linearisation."""
    N = p.shape[0]
    lam = torch.full((N,), 1e-3, dtype=torch.float64)
    H = torch.zeros(N, N_PARAMS, N_PARAMS, dtype=torch.float64)
    cost = cost_at(rnd, p, prior, settings)
    p = p.clone()
    live = torch.ones(N, dtype=torch.bool)
    for _ in range(iterations):
        ids = live.nonzero().squeeze(1)
        if len(ids) == 0:
            break
        whole = len(ids) == N
        sub = rnd if whole else rnd.rows(ids)
        q, c_new, h, lam_new = lm_step(sub, p[ids], cost[ids], lam[ids], prior.rows(ids), free[ids], settings)
        done = cost[ids] - c_new <= TUNING.solver.converged * cost[ids].abs()  # no progress left
        p[ids], cost[ids], H[ids], lam[ids] = q, c_new, h, lam_new
        if not whole:
            rnd.frame0 = rnd.frame0.index_copy(0, ids, sub.frame0)
        live[ids[done]] = False
    return p, cost, H


def lm_step(
    rnd: Round,
    p: Tensor,
    cost: Tensor,
    lam: Tensor,
    prior: Prior,
    free: Tensor,
    settings: RefineSettings,
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """One LM linearisation (with up to ``TUNING.solver.max_tries`` damping increases) for all of ``rnd``'s texels:
    returns p (omega folded into ``rnd.frame0``), cost, the Gauss-Newton Hessian and the damping."""
    tr = rnd.tr
    N = p.shape[0]
    lo, hi = LOWER.to(p.dtype), UPPER.to(p.dtype)
    bases = rnd.linearised(p[:, P_LOGA])
    H, g = normal_equations(*bases, p, tr.y, tr.inv_sigma, tr.mask, tr.censored, settings.noise.robust)
    la_w, rs_w = prior.la_w.double()[:, None], prior.rs_w.double()[:, None]
    H[:, [3, 4], [3, 4]] += la_w  # the alpha and rho_s priors
    H[:, [8, 9, 10], [8, 9, 10]] += rs_w
    g[:, P_LOGA] += la_w * (p[:, P_LOGA] - prior.la0).double()
    g[:, P_RHO_S] += rs_w * (p[:, P_RHO_S] - prior.rs0).double()
    # the isotropy tie: 1/2 w (log alpha_x - log alpha_y)^2
    tie_w, spread = prior.tie_w.double(), (p[:, 3] - p[:, 4]).double()
    H[:, 3, 3] += tie_w
    H[:, 4, 4] += tie_w
    H[:, 3, 4] -= tie_w
    H[:, 4, 3] -= tie_w
    g[:, 3] += tie_w * spread
    g[:, 4] -= tie_w * spread
    # the tint pull: 1/2 w s |rho_s - mean|^2, its relative scale s held at this linearisation (the
    # cost, which accepts a step, has it exact)
    rs = p[:, P_RHO_S].double()
    tint_w = prior.tint_w * tint_scale(rs)[:, None, None]
    H[:, 8:11, 8:11] += tint_w * (torch.eye(3, dtype=torch.float64) - 1.0 / 3.0)
    g[:, P_RHO_S] += tint_w[..., 0] * (rs - rs.mean(1, keepdim=True))
    # the normal prior: residuals u_x, u_y / sigma of the prior's normal u in the shading frame,
    # d u / d omega_k = u x e_k
    u = prior_normal_in(rnd.frame0, prior.n_prior).double()  # at omega = 0
    zero = torch.zeros_like(u[:, 0])
    sn = prior.n_w**-0.5
    ju = torch.stack([torch.stack([zero, -u[:, 2], u[:, 1]], 1), torch.stack([u[:, 2], zero, -u[:, 0]], 1)], 1) / sn
    H[:, :3, :3] += ju.transpose(1, 2) @ ju
    g[:, :3] += (ju.transpose(1, 2) @ (u[:, :2, None] / sn))[..., 0]
    # active set: a parameter at a bound whose gradient points out stays there this iteration
    at_lo = (p <= lo + 1e-7) & (g > 0)
    at_hi = (p >= hi - 1e-7) & (g < 0)
    mf = (free & ~at_lo & ~at_hi).double()
    Hm = H * mf[:, :, None] * mf[:, None, :]
    gm = g * mf
    diag = Hm.diagonal(dim1=1, dim2=2)
    p, cost, lam = p.clone(), cost.clone(), lam.clone()
    ids = torch.arange(N)  # the texels still waiting for an accepted step
    for _try in range(TUNING.solver.max_tries):  # a rejected step is retried with more damping (same linearisation)
        # only those are evaluated again: a retry on every texel made half of the model's evaluations
        sub, sub_prior = (rnd, prior) if len(ids) == N else (rnd.rows(ids), prior.rows(ids))
        dg = diag[ids]
        A = Hm[ids] + torch.diag_embed(lam[ids, None] * (dg + 1e-3 * dg.mean(1, keepdim=True)) + (1 - mf[ids]))
        step = -torch.linalg.solve(A, gm[ids, :, None])[..., 0]
        q = torch.minimum(torch.maximum(p[ids] + step.to(p.dtype), lo), hi)
        new = cost_at(sub, q, sub_prior, settings)
        better = torch.isfinite(new) & (new < cost[ids])
        k = ids[better]
        p[k], cost[k] = q[better], new[better]
        lam[ids] = torch.where(better, (lam[ids] * 0.3).clamp_min(1e-7), lam[ids] * 10)
        ids = ids[~better]
        if len(ids) == 0:
            break
    rnd.rebase(p[:, P_OMEGA])
    p[:, P_OMEGA] = 0.0  # p is this step's own copy (taken before the tries)
    return p, cost, H, lam


def albedo_start(
    rnd: Round, p: Tensor, specular: bool, keep_rho_s: bool = False, bases: tuple[Tensor, Tensor] | None = None
) -> Tensor:
    """p with rho_d (and rho_s unless ``keep_rho_s``) replaced by the bounded weighted least squares
    for the round's geometry (``bases``: the round's at p, where the caller has them); ``specular``
    False: rho_s = 0. A clipped entry counts, as in the data cost, where the answer predicts it
    darker than its lower bound: up to ``TUNING.solver.clipped_rounds`` solves, each adding (at its bound) the
    clipped entries the last one fell below. Left out, a texel whose every entry is clipped (the
    vase's white print in 2-4 entries) got rho_d 0, and a lobe took its light (docs/history/accuracy.md)."""
    tr = rnd.tr
    d, s = rnd.bases(p[:, P_OMEGA], p[:, P_LOGA]) if bases is None else bases
    w = (tr.inv_sigma**2 * tr.mask).double()
    y = tr.y
    if not specular:
        s = torch.zeros_like(s)
    elif keep_rho_s:  # the lobe is given: only rho_d is solved, against what the lobe leaves
        y, s = y - p[:, None, P_RHO_S] * s, torch.zeros_like(s)
    rho_s_max = RHO_S_MAX if specular and not keep_rho_s else 0.0
    counted = tr.mask & ~tr.censored
    for _ in range(TUNING.solver.clipped_rounds):
        q = with_albedos(p, d, s, y, w * counted, rho_s_max, keep_rho_s)
        pred = q[:, None, P_RHO_D] * d + q[:, None, P_RHO_S] * s  # s: 0 where rho_s is given or none
        now = counted | (tr.censored & (pred < y))  # once below its bound, counted at it (no cycling)
        if torch.equal(now, counted):
            break
        counted = now
    return q


def with_albedos(
    p: Tensor, d: Tensor, s: Tensor, y: Tensor, w: Tensor, rho_s_max: float, keep_rho_s: bool = False
) -> Tensor:
    """p with rho_d (and rho_s unless ``keep_rho_s``) the bounded least squares of ``y`` ≈ rho_d
    ``d`` + rho_s ``s`` channel by channel, weights ``w`` (all ``(N, V, 3)``; float64 inside)."""
    rd, rs = bounded_ls2(
        d.double().transpose(1, 2),
        s.double().transpose(1, 2),
        y.double().transpose(1, 2),
        w.double().transpose(1, 2),
        RHO_D_MAX,
        rho_s_max,
    )
    p = p.clone()
    p[:, P_RHO_D] = rd.to(p.dtype)
    if not keep_rho_s:
        p[:, P_RHO_S] = rs.to(p.dtype)
    return p


def solve(
    tr: Trace,
    frame: Tensor,
    p: Tensor,
    specular: bool,
    settings: RefineSettings,
    prior: Prior | None = None,
    weak: Prior | None = None,
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """All rounds for one group of texels (all with a lobe, or all diffuse-only); returns frame,
    p, cost and the last Gauss-Newton Hessian. ``prior``: the weak pulls (``weak``, else to the
    start) unless given (a basis material's lobe: then no multi-start, and the first round keeps the
    prior's rho_s)."""
    N = p.shape[0]
    free = torch.ones(N, N_PARAMS, dtype=torch.bool)
    if not specular:
        free[:, 2] = False  # omega_z turns only the tangent
        free[:, P_LOGA] = False
        free[:, P_RHO_S] = False
        p = p.clone()
        p[:, P_RHO_S] = 0.0
    given = prior is not None
    if prior is None:
        prior = weak if weak is not None else Prior.weak(frame, p, settings)
    H = torch.zeros(N, N_PARAMS, N_PARAMS, dtype=torch.float64)
    cost = torch.zeros(N, dtype=p.dtype)
    first = 0
    if settings.starts and specular and not given and settings.rounds > 0:  # the multi-start is round one
        frame, p = multi_start(tr, frame, p, prior, free, settings)
        first = 1
    for k in range(first, settings.rounds):
        rnd = Round(tr, frame, p[:, P_LOGA], specular, rho_s=p[:, P_RHO_S])
        if k == 0:
            p = albedo_start(rnd, p, specular, keep_rho_s=given)
        p, cost, H = levenberg_marquardt(rnd, p, prior, free, settings.iterations, settings)
        frame = rnd.frame0
    return frame, p, cost, H


def multi_start(
    tr: Trace, frame: Tensor, p: Tensor, prior: Prior, free: Tensor, settings: RefineSettings
) -> tuple[Tensor, Tensor]:
    """Starts where the lobe is ambiguous: as given, the tangent turned 90 deg (the other axis
    carries alpha_x; not where the start's lobe is isotropic, ``TUNING.solver.isotropic_start`` — turned, it is
    the same model, so the same answer), the lobe 4x sharper; one round of LM each, the cheapest kept
    per texel. The three share F0's normal, so its diffuse basis."""
    N = p.shape[0]
    sharp = p.clone()
    sharp[:, P_LOGA] = (sharp[:, P_LOGA] + math.log(TUNING.solver.sharp_start)).clamp(
        math.log(ALPHA_MIN), math.log(ALPHA_MAX)
    )
    la = p[:, P_LOGA]
    turned = ((la[:, 0] - la[:, 1]).abs() >= math.log(TUNING.solver.isotropic_start)).nonzero().squeeze(1)
    quarter = torch.zeros(len(turned), 3, dtype=p.dtype)
    quarter[:, 2] = math.pi / 2
    best_cost = torch.full((N,), math.inf, dtype=p.dtype)
    best_frame, best_p = frame.clone(), p.clone()
    every = torch.arange(N)
    diffuse: Tensor | None = None  # the first start's, for all N
    for at, f0, q0 in ((every, frame, p), (turned, fold(frame[turned], quarter), p[turned]), (every, frame, sharp)):
        if len(at) == 0:
            continue
        whole = len(at) == N
        sub, sub_prior, sub_free = (tr, prior, free) if whole else (tr.rows(at), prior.rows(at), free[at])
        rnd = Round(sub, f0, q0[:, P_LOGA], True, None if diffuse is None else diffuse[at], q0[:, P_RHO_S])
        diffuse = rnd.diffuse if diffuse is None else diffuse
        q, cost, _ = levenberg_marquardt(
            rnd, albedo_start(rnd, q0, True), sub_prior, sub_free, settings.iterations, settings
        )
        better = cost < best_cost[at]
        k = at[better]
        best_cost[k], best_frame[k], best_p[k] = cost[better], rnd.frame0[better], q[better]
    return best_frame, best_p


def robust_albedos(
    tr: Trace, bases: tuple[Tensor, Tensor], p: Tensor, settings: RefineSettings
) -> tuple[Tensor, Tensor]:
    """rho_d and rho_s of ``p (N, 11)`` re-solved under the robust cost for fixed geometry (pixel
    ``bases``), and that cost ``(N,)``: ``TUNING.solver.albedo_iterations`` of iteratively reweighted bounded least
    squares (Cauchy weights; a clipped entry counts only while the prediction is below it), each
    kept where it lowers the cost. Why: the plain least squares leave out the clipped entries,
    which for a bright lobe are its highlights — the vase's 1:80 brushed metal pooled to a width
    0.5 x 0.15 with them left out, 0.5 x 0.018 with them held (``lobe_costs``)."""
    d, s = bases
    c = settings.noise.robust
    r, active = residuals(tr, d, s, p)
    cost = robust_cost(r, c)
    for _ in range(TUNING.solver.albedo_iterations):
        q = with_albedos(p, d, s, tr.y, tr.inv_sigma**2 * active / (1.0 + (r / c) ** 2), RHO_S_MAX)
        r_q, active_q = residuals(tr, d, s, q)
        new = robust_cost(r_q, c)
        better = new < cost
        p = torch.where(better[:, None], q, p)
        cost = torch.where(better, new, cost)
        r = torch.where(better[:, None, None], r_q, r)
        active = torch.where(better[:, None, None], active_q, active)
    return p, cost
