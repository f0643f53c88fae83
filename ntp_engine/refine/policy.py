"""Analysis-by-synthesis refinement (``refine``, ``refine_toward``): per texel, the anisotropic GGX
parameters that best explain the trace's own pixels through Eq. 1 and the camera model
(``refine.model``), starting from the network's fit — and the policy around the solver
(``refine.solver``): which model a texel's photos support (a lobe or none, isotropic or not), what a
basis material's lobe costs a texel (``material_costs``, ``lobe_costs``), the noise model's
calibration (``calibrated``) and the uncertainties of the answer. Design and measurements:
docs/refinement.md.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from typing import NamedTuple

import torch
from torch import Tensor

from ..fit.flags import TexelFlag
from ..physics.brdf import ALPHA_MAX, ALPHA_MIN, RHO_D_MAX, RHO_S_MAX
from ..physics.frame import frame_from_normal_tangent, turned_about_normal
from .gauss_newton import N_PARAMS, data_cost
from .model import (
    P_LOGA,
    P_OMEGA,
    P_RHO_D,
    P_RHO_S,
    Observations,
    Round,
    Start,
    Trace,
    highlight_share,
    parameters,
    predict,
    residuals,
)
from .priors import LobePrior, Prior, normal_prior
from .settings import ANISOTROPY_PARAMS, LOBE_PARAMS, TUNING, RefineSettings, SensorNoise
from .solver import albedo_start, robust_albedos, solve


@dataclass
class Refined:
    """Refined parameters of N texels (geometric frame) and how well their traces constrain them."""

    frame: Tensor  # (N, 3, 3) rows t, b, n
    log_alpha: Tensor  # (N, 2) alpha_x >= alpha_y
    rho_d: Tensor  # (N, 3)
    rho_s: Tensor  # (N, 3)
    flags: Tensor  # (N,) TexelFlag.SPECULAR_UNCONSTRAINED | TexelFlag.TANGENT_UNCONSTRAINED
    std: Tensor  # (N, 4) 1-sigma: normal (deg), tangent (deg), log alpha_x, log rho_s (mean channel)
    cost: Tensor  # (N,) objective at the answer (robust data cost plus the priors)
    highlight: Tensor  # (N,) the largest share of an entry's pixel the texel's kept lobe makes (0: none)


def refine(
    obs: Observations,
    start: Start,
    specular: Tensor,
    settings: RefineSettings | None = None,
    centre: Start | None = None,
) -> Refined:
    """Refine N texels from ``start``, the weak pulls centred on ``centre`` (default: the start).
    ``entries (N, V, 12)`` as captured with ``mask (N, V)`` and
    ``shadow (N, V)`` (the emitter groups the mesh hides from each entry: ``learn.ragged``);
    ``specular (N,)``: texels whose lobe is solved. A texel without one, or whose solved lobe no
    entry shows (below ``TUNING.model.min_specular_share`` of every pixel), gets a diffuse-only solve from its
    start and rho_s = 0, its lobe flagged unconstrained. ``footprint``: what each entry's pixel sample
    spans (``refine.footprint``; None: a flat surface, no albedo blend) — the normals, which widen the
    lobe it sees, and the neighbours' albedo it may blend in. Never NaN: a failed solve keeps the start."""
    settings = settings or RefineSettings()
    tr = obs.trace(settings.noise)
    return _refine(tr, start, specular, settings, centre)


def _refine(
    tr: Trace, start: Start, specular: Tensor, settings: RefineSettings, centre: Start | None = None
) -> Refined:
    """``refine`` on traces already prepared with ``settings.noise``."""
    dtype = tr.y.dtype
    N = tr.N
    frame, p = parameters(start, dtype)
    weak = Prior.weak(*(parameters(centre, dtype) if centre is not None else (frame, p)), settings)
    # every texel's diffuse-only answer (cheap: no lobe), then the lobe where one is sought; the lobe
    # stays where an entry shows it and it lowers the cost by more than ``lobe_evidence``
    out_frame, out_p, cost, H = solve(tr, frame, p, False, settings, weak=weak)
    highlight = torch.zeros(N, dtype=dtype)
    evidence = lobe_evidence(tr.mask.sum((1, 2)))
    idx = (specular & _lobe_can_pass(cost, evidence)).nonzero().squeeze(1)
    if len(idx):
        sub = tr if len(idx) == N else tr.rows(idx)  # idx sorted: all texels or a subset
        f, q, c, h = solve(sub, frame[idx], p[idx], True, settings, weak=weak.rows(idx))
        peak = highlight_share(sub, f, q)
        keep = (peak >= TUNING.model.min_specular_share) & (c < cost[idx] - evidence[idx])
        diffuse_cost = cost[idx[keep]]
        highlight[idx] = torch.where(keep, peak, torch.zeros_like(peak))
        k = idx[keep]
        out_frame[k], out_p[k], cost[k], H[k] = f[keep], q[keep], c[keep], h[keep]
        sel, f, q, c, h, peak = _prefer_isotropic(tr, k, out_frame[k], out_p[k], cost[k], weak.rows(k), settings)
        ok = c < diffuse_cost[sel] - evidence[k[sel]]  # the isotropic lobe still passes the lobe test
        j = k[sel[ok]]
        out_frame[j], out_p[j], cost[j], H[j], highlight[j] = f[ok], q[ok], c[ok], h[ok], peak[ok]
    # never NaN: a texel whose solve went non-finite keeps its start
    bad = ~(torch.isfinite(out_p).all(1) & torch.isfinite(out_frame).flatten(1).all(1) & torch.isfinite(cost))
    out_p[bad], out_frame[bad] = p[bad], frame[bad]
    return _finish(out_frame, out_p, H, cost, highlight)


def _prefer_isotropic(
    tr: Trace, idx: Tensor, frame: Tensor, p: Tensor, cost: Tensor, prior: Prior, settings: RefineSettings
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor]:
    """Isotropic unless the trace shows otherwise: of the N solved lobes of ``tr``'s texels ``idx``
    (``frame``, ``p``, ``cost``, solved under ``prior``), those less anisotropic than
    ``TUNING.policy.anisotropy_test`` are solved again from the same answer with their alphas tied (at their
    geometric mean), under the same pulls. The anisotropic answer stays only where it lowers the
    cost by more than AIC's penalty for the ``ANISOTROPY_PARAMS`` it adds (1 per parameter in half
    chi-square units; BIC's, 4.3 at 72 residuals, made a third of a 2.5:1 lobe isotropic in the
    tests' synthetic traces, AIC a tenth). Why: a trace of a sharp isotropic lobe sees it through
    one or two LEDs in a few entries, so one axis is measured and the other drifts toward the
    start's (the gallery's alpha 0.02 plastic came back 0.03 x 0.06). Returns which of the N texels
    ``sel`` take the isotropic answer, and its frame, p, cost, Hessian and highlight ``(len(sel),
    ...)``."""
    la = p[:, P_LOGA]
    test = ((la[:, 0] - la[:, 1]).abs() < math.log(TUNING.policy.anisotropy_test)).nonzero().squeeze(1)
    if len(test) == 0:
        none = torch.zeros(0, dtype=torch.long)
        return none, frame[:0], p[:0], cost[:0], torch.zeros(0, N_PARAMS, N_PARAMS, dtype=torch.float64), p[:0, 0]
    sub = tr.rows(idx[test])
    start = p[test].clone()
    start[:, P_LOGA] = start[:, P_LOGA].mean(1, keepdim=True)
    pulls = prior.rows(test).tied(torch.ones(len(test), dtype=torch.bool))
    f, q, c, h = solve(
        sub, frame[test], start, True, dataclasses.replace(settings, rounds=TUNING.policy.isotropic_rounds), pulls
    )
    peak = highlight_share(sub, f, q)
    take = torch.isfinite(c) & (peak >= TUNING.model.min_specular_share) & (c <= cost[test] + ANISOTROPY_PARAMS)
    return test[take], f[take], q[take], c[take], h[take], peak[take]


def _lobe_can_pass(diffuse_cost: Tensor, evidence: Tensor) -> Tensor:
    """Texels ``(N,)`` whose own lobe could pass the evidence test: the full solve's cost (robust
    data cost plus priors) is never below 0, so a lobe is kept only where the diffuse-only cost
    exceeds the evidence — elsewhere its solve would be thrown away (on the gallery's engine scans
    22–72% of the texels, the demo 30%), and is skipped: the same answers."""
    return diffuse_cost > evidence


def lobe_evidence(residuals: Tensor) -> Tensor:
    """How much a texel's own lobe must lower its robust cost to be kept, for its number of
    ``residuals (N,)``: ``TUNING.policy.lobe_evidence`` or BIC's penalty for ``LOBE_PARAMS``, the larger."""
    return (0.5 * LOBE_PARAMS * residuals.clamp_min(1).to(torch.float32).log()).clamp_min(TUNING.policy.lobe_evidence)


class MaterialCosts(NamedTuple):
    """``material_costs``' answer: per texel and model (no lobe, then each material)."""

    cost: Tensor  # (N, 1 + K) robust data cost; inf: not judged
    turn: Tensor  # (N, K) the best turn of each material's tangent (radians)
    rho_d: Tensor  # (N, 1 + K, 3) the rho_d re-solved under each model; NaN: not judged


def material_costs(
    obs: Observations,
    start: Start,
    alpha: Tensor,
    rho_s: Tensor,
    candidates: Tensor | None = None,
    settings: RefineSettings | None = None,
    turn_prior: tuple[Tensor, Tensor] | None = None,
) -> MaterialCosts:
    """How well K basis materials' lobes (``alpha (K, 2)``, ``rho_s (K, 3)``) explain N traces:
    the robust data cost ``(N, 1 + K)`` of each texel's trace under no lobe (column 0) and under each
    material's lobe where ``candidates (N, K)`` (default all; elsewhere inf), with the texel's own
    normal and its rho_d re-solved (bounded least squares; ``(N, 1 + K, 3)``, NaN where not judged),
    and the turn ``(N, K)`` (radians, about the normal from ``start``'s tangent) that fits best (its
    rho_d the one at that turn). An anisotropic lobe at the texel's start tangent is a guess (a UV
    direction), so it is tried at ``TUNING.policy.tangent_turns`` turns over 180 deg and its cost is the negative
    log of their mean likelihood (uniform over turns; the cheapest alone would let a lobe hide in
    the noise by choosing where to point). ``turn_prior`` = (turn, agree)
    ``(N, K)``: where the texel's neighbours say material k points (``refine.tangent_field``) — that
    turn is tried too and weighs ``agree`` in the mean, the others ``(1 - agree) / TUNING.policy.tangent_turns``
    (agree 0: uniform; the turns stay anchored at the start tangent, a UV direction, which is the
    better guess where neighbours disagree). Columns are comparable: each model has the same free
    rho_d."""
    settings = settings or RefineSettings()
    tr_all = obs.trace(settings.noise)
    dtype = tr_all.y.dtype
    N, K = tr_all.N, alpha.shape[0]
    frame_all = frame_from_normal_tangent(start.normal.to(dtype), start.tangent.to(dtype))
    cost = torch.full((N, 1 + K), math.inf, dtype=dtype)
    rho_d = torch.full((N, 1 + K, 3), math.nan, dtype=dtype)
    turn = torch.zeros(N, K, dtype=dtype)
    candidates = torch.ones(N, K, dtype=torch.bool) if candidates is None else candidates

    def judged(tr: Trace, f: Tensor, m: int, diffuse: Tensor | None) -> tuple[Tensor, Tensor, Tensor]:
        """The cost under material m (0: no lobe), the round's diffuse basis and the rho_d."""
        a, r = (alpha[m - 1], rho_s[m - 1]) if m else (alpha.new_ones(2), rho_s.new_zeros(3))
        return _given_lobe_cost(tr, f, a.expand(tr.N, 2), r.expand(tr.N, 3), m > 0, diffuse, settings)

    # every model shares the texel's normal, so its diffuse basis
    cost[:, 0], diffuse, rho_d[:, 0] = judged(tr_all, frame_all, 0, None)
    for m in range(1, K + 1):
        idx = candidates[:, m - 1].nonzero().squeeze(1)
        if len(idx) == 0:
            continue
        tr, frame, d = tr_all.rows(idx), frame_all[idx], diffuse[idx]
        anisotropic = bool(alpha[m - 1, 0] >= TUNING.policy.isotropic_ratio * alpha[m - 1, 1])
        n = TUNING.policy.tangent_turns if anisotropic else 1
        angles = (torch.arange(n, dtype=dtype) * math.pi / TUNING.policy.tangent_turns).expand(len(idx), n)
        weight = torch.full((len(idx), n), 1.0 / n, dtype=dtype)
        if anisotropic and turn_prior is not None:  # the neighbours' turn as one more, weighing agree
            agree = turn_prior[1][idx, m - 1].to(dtype).clamp(0, 1)[:, None]
            angles = torch.cat([angles, turn_prior[0][idx, m - 1].to(dtype)[:, None]], 1)
            weight = torch.cat([weight * (1 - agree), agree], 1)
        each = [judged(tr, turned_about_normal(frame, a), m, d) for a in angles.unbind(1)]
        c = torch.stack([e[0] for e in each], 1)
        score = torch.log(weight) - c  # log of each turn's share of the likelihood (a weight of 0: none)
        best = score.argmax(1)
        cost[idx, m] = -torch.logsumexp(score, 1)
        turn[idx, m - 1] = angles.gather(1, best[:, None])[:, 0]
        rho_d[idx, m] = torch.stack([e[2] for e in each], 1)[torch.arange(len(idx)), best]
    return MaterialCosts(cost, turn, rho_d)


def _given_lobe_cost(
    tr: Trace,
    frame: Tensor,
    alpha: Tensor,
    rho_s: Tensor,
    specular: bool,
    diffuse: Tensor | None,
    settings: RefineSettings,
) -> tuple[Tensor, Tensor, Tensor]:
    """The robust data cost ``(N,)`` of traces under the lobes ``alpha (N, 2)``, ``rho_s (N, 3)``
    (``specular`` False: none) in ``frame``, rho_d re-solved (bounded least squares; inf where not
    finite), the round's diffuse basis (``diffuse``: one of the same normal, reused) and that rho_d
    ``(N, 3)``."""
    dtype = tr.y.dtype
    p = torch.zeros(tr.N, N_PARAMS, dtype=dtype)
    if specular:
        p[:, P_LOGA] = alpha.to(dtype).clamp(ALPHA_MIN, ALPHA_MAX).log()
        p[:, P_RHO_S] = rho_s.to(dtype).clamp(0, RHO_S_MAX)
    rnd = Round(tr, frame, p[:, P_LOGA], specular, diffuse, p[:, P_RHO_S])
    bases = rnd.bases(p[:, P_OMEGA], p[:, P_LOGA])
    p = albedo_start(rnd, p, specular, keep_rho_s=True, bases=bases)
    c = data_cost(*bases, p, tr.y, tr.inv_sigma, tr.mask, tr.censored, settings.noise.robust)
    return torch.nan_to_num(c, nan=math.inf), rnd.diffuse, p[:, P_RHO_D]


def turn_costs(obs: Observations, start: Start, turns: Tensor, settings: RefineSettings | None = None) -> Tensor:
    """The robust data cost ``(N, T)`` of N traces under each texel's own lobe (``start``'s normal,
    alphas and rho_s) with its tangent turned by ``turns (N, T)`` (radians about the normal, as
    ``material_costs``' turns), rho_d re-solved: how much its photos object to each direction."""
    settings = settings or RefineSettings()
    tr = obs.trace(settings.noise)
    dtype = tr.y.dtype
    frame = frame_from_normal_tangent(start.normal.to(dtype), start.tangent.to(dtype))
    costs, diffuse = [], None
    for a in turns.to(dtype).unbind(1):
        c, diffuse, _ = _given_lobe_cost(
            tr, turned_about_normal(frame, a), start.alpha, start.rho_s, True, diffuse, settings
        )
        costs.append(c)
    return torch.stack(costs, 1)


def lobe_costs(
    obs: Observations | Trace, start: Start, alphas: Tensor, settings: RefineSettings | None = None
) -> tuple[Tensor, Tensor, Tensor]:
    """How well S candidate lobe widths explain N traces: the robust data cost ``(N, S)`` of each
    texel's trace under ``alphas (N, S, 2)`` (alpha_x along ``start``'s tangent; clamped to the
    range) with the texel's own frame and its rho_d and rho_s re-solved under that cost
    (``robust_albedos``), and those ``rho_d, rho_s (N, S, 3)``. Summed over a material's texels
    it is the profile of their cost over the material's lobe width, which one trace alone may not
    tell from a broader diffuse (``refine.materials.pooled_scale``). ``obs`` may be their ``Trace``
    already built under ``settings.noise`` (or its ``rows``), for callers that ask it several times."""
    settings = settings or RefineSettings()
    tr = obs if isinstance(obs, Trace) else obs.trace(settings.noise)
    dtype = tr.y.dtype
    frame = frame_from_normal_tangent(start.normal.to(dtype), start.tangent.to(dtype))
    N, S = alphas.shape[:2]
    cost = torch.empty(N, S, dtype=dtype)
    rho_d, rho_s = torch.empty(N, S, 3, dtype=dtype), torch.empty(N, S, 3, dtype=dtype)
    diffuse: Tensor | None = None  # one normal, one diffuse basis for every width
    for k in range(S):
        p = torch.zeros(N, N_PARAMS, dtype=dtype)
        p[:, P_LOGA] = alphas[:, k].to(dtype).clamp(ALPHA_MIN, ALPHA_MAX).log()
        rnd = Round(tr, frame, p[:, P_LOGA], True, diffuse, start.rho_s.to(dtype))  # its Fresnel: start's rho_s
        diffuse = rnd.diffuse
        bases = rnd.bases(p[:, P_OMEGA], p[:, P_LOGA])
        p, c = robust_albedos(tr, bases, albedo_start(rnd, p, True, bases=bases), settings)
        cost[:, k] = torch.nan_to_num(c, nan=math.inf)
        rho_d[:, k], rho_s[:, k] = p[:, P_RHO_D], p[:, P_RHO_S]
    return cost, rho_d, rho_s


def refine_toward(obs: Observations, start: Start, prior: LobePrior, settings: RefineSettings | None = None) -> Refined:
    """Refine N texels that take their lobe from a basis material: from ``start`` (the material's
    lobe with the texel's own frame, rho_d), with alphas and rho_s pulled to ``prior`` by its
    spreads; no multi-start. The lobe is kept whether or not an entry shows it (flags:
    ``TexelFlag.FROM_MATERIAL``, and ``TexelFlag.SPECULAR_UNCONSTRAINED`` where none does: its parameters are
    then the material's; its uncertainty the prior's). Never NaN: a failed solve keeps the start."""
    settings = settings or RefineSettings()
    tr = obs.trace(settings.noise)
    dtype = tr.y.dtype
    N = tr.N
    frame = frame_from_normal_tangent(start.normal.to(dtype), start.tangent.to(dtype))
    p = torch.zeros(N, N_PARAMS, dtype=dtype)
    p[:, P_LOGA] = prior.alpha.to(dtype).clamp(ALPHA_MIN, ALPHA_MAX).log()
    p[:, P_RHO_D] = start.rho_d.to(dtype).clamp(0, RHO_D_MAX)
    p[:, P_RHO_S] = prior.rho_s.to(dtype).clamp(0, RHO_S_MAX)
    pulls = Prior(
        normal_prior(frame, settings),
        math.radians(settings.normal_prior_deg) ** -2,
        p[:, P_LOGA].clone(),
        prior.log_alpha_sigma.to(dtype).clamp_min(1e-3) ** -2,
        p[:, P_RHO_S].clone(),
        prior.rho_s_sigma.to(dtype).clamp_min(1e-3) ** -2,
        torch.zeros(N, dtype=dtype),
        settings.rho_s_tint_sigma**-2,
    ).tied(p[:, 3] - p[:, 4] < math.log(TUNING.policy.isotropic_ratio))  # an isotropic material's lobe stays isotropic
    f, q, cost, H = solve(tr, frame, p, True, settings, pulls)
    bad = ~(torch.isfinite(q).all(1) & torch.isfinite(f).flatten(1).all(1) & torch.isfinite(cost))
    q[bad], f[bad] = p[bad], frame[bad]
    return _finish(f, q, H, cost, highlight_share(tr, f, q), from_material=torch.ones(N, dtype=torch.bool))


def calibrated(obs: Observations, start: Start, specular: Tensor, settings: RefineSettings) -> RefineSettings:
    """``settings`` calibrated on a refinement of these sample traces. The noise model is scaled
    (within ``TUNING.model.noise_scale``) so that the answer's residuals have unit robust scale — 1.4826 x the
    median |normalised residual| over its entries is 1 when the model is right (Monte Carlo renders
    and unmodelled effects give more): data from a noisier source then weigh against the priors as
    much as they deserve; a quieter source keeps the model as it is (``TUNING.model.noise_scale``'s floor of 1).
    And the normal's weak pull centres on the mesh's normal where the sample's texels whose own
    photos fix their normals (1-sigma below ``TUNING.policy.normal_fixed_deg``, at least
    ``TUNING.policy.normal_fixed_texels``
    of them) lie nearer it than to their start's in the median — the start (the network's answer)
    reads the same photos, and where it errs a pull to it keeps the error on the texels the photos
    say little about (docs/refinement.md)."""
    tr = obs.trace(settings.noise)
    r = _refine(tr, start, specular, settings)
    p = torch.cat([torch.zeros_like(r.rho_d), r.log_alpha, r.rho_d, r.rho_s], 1)
    res, active = residuals(tr, *predict(tr, r.frame, p), p)
    vals = res[active].abs()
    k = float(1.4826 * vals.median()) if len(vals) else 1.0
    k = min(max(k, TUNING.model.noise_scale[0]), TUNING.model.noise_scale[1])
    noise = SensorNoise(settings.noise.read_code * k, settings.noise.relative * k, settings.noise.robust)
    fixed = r.std[:, 0] < TUNING.policy.normal_fixed_deg
    at_mesh = settings.normal_prior_at_mesh
    if int(fixed.sum()) >= TUNING.policy.normal_fixed_texels:
        n = r.frame[fixed, 2]
        from_mesh = torch.acos(n[:, 2].clamp(-1, 1)).median()
        n0 = torch.nn.functional.normalize(start.normal[fixed].to(n.dtype), dim=1)
        from_start = torch.acos((n * n0).sum(1).clamp(-1, 1)).median()
        at_mesh = bool(from_mesh < from_start)
    return dataclasses.replace(settings, noise=noise, normal_prior_at_mesh=at_mesh)


def _finish(
    frame: Tensor, p: Tensor, H: Tensor, cost: Tensor, highlight: Tensor, from_material: Tensor | None = None
) -> Refined:
    """Canonical lobe (alpha_x >= alpha_y), the flags and the 1-sigma uncertainties. A lobe is
    written where seen (its ``highlight`` is ``TUNING.model.min_specular_share`` of some entry's pixel or more)
    or given ``from_material``; else rho_s = 0."""
    seen = highlight >= TUNING.model.min_specular_share
    from_material = torch.zeros_like(seen) if from_material is None else from_material
    kept = seen | from_material
    la = p[:, P_LOGA]
    swap = la[:, 1] > la[:, 0]
    t, b, n = frame[:, 0], frame[:, 1], frame[:, 2]
    frame = torch.stack([torch.where(swap[:, None], b, t), torch.where(swap[:, None], -t, b), n], 1)
    la = torch.where(swap[:, None], la.flip(1), la)
    # uncertainty: diag of the inverse Gauss-Newton Hessian (unit-sigma residuals, priors included)
    Hd = H + 1e-12 * torch.eye(N_PARAMS, dtype=H.dtype)
    cov = torch.linalg.pinv(Hd).diagonal(dim1=1, dim2=2).clamp_min(0).sqrt().to(p.dtype)
    normal_std = torch.rad2deg(torch.sqrt(cov[:, 0] ** 2 + cov[:, 1] ** 2))
    rho_s_mean = p[:, P_RHO_S].mean(1).clamp_min(1e-3)
    std = torch.stack(
        [normal_std, torch.rad2deg(cov[:, 2]), cov[:, 3:5].amax(1), cov[:, P_RHO_S].mean(1) / rho_s_mean], 1
    )
    std = torch.where(kept[:, None], std, std.masked_fill(torch.tensor([False, True, True, True]), math.inf))
    # a parameter on its bound: the Gauss-Newton sigma describes a minimum the range cut off, so it
    # is written as undetermined and the texel flagged (the photos bound it from one side only)
    tol = TUNING.policy.at_bound
    alpha_bound = kept & ((la[:, 0] >= math.log(ALPHA_MAX) - tol) | (la[:, 1] <= math.log(ALPHA_MIN) + tol))
    rho_s_bound = kept & (p[:, P_RHO_S] >= RHO_S_MAX - tol).any(1)
    std[:, 2] = torch.where(alpha_bound, math.inf, std[:, 2])
    std[:, 3] = torch.where(rho_s_bound, math.inf, std[:, 3])
    flags = (~seen).long() * TexelFlag.SPECULAR_UNCONSTRAINED | from_material.long() * TexelFlag.FROM_MATERIAL
    flags = flags | (alpha_bound | rho_s_bound).long() * TexelFlag.AT_BOUND
    iso = (la[:, 0] - la[:, 1]) < math.log(TUNING.policy.isotropic_ratio)
    flags = flags | ((~seen | iso).long() * TexelFlag.TANGENT_UNCONSTRAINED)
    rho_s = torch.where(kept[:, None], p[:, P_RHO_S], torch.zeros_like(p[:, P_RHO_S]))
    return Refined(frame, la, p[:, P_RHO_D], rho_s, flags, std, cost, highlight)
