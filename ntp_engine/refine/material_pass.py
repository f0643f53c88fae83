"""The refinement's second pass (docs/refinement.md, "Basis materials"): basis materials from the
texels whose own traces kept a lobe, every observed texel labelled with one or the matte class,
the lobe widths pooled over each material's members (``pooled_widths``), the texels without a lobe
of their own refined toward their material's (``material_pass``), and the anisotropic tangents
fused with their neighbours' where the photos do not object.

Convention: per-trace arrays as ``pipeline.fit_traces`` (the texel's geometric frame); angles in
radians about the texel's normal.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import torch

from ..fit.flags import TexelFlag
from ..fit.texel_fit import TexelFit
from ..io.progress import QUIET, Progress
from ..io.texels import Texels
from ..learn.ragged import RaggedTraces
from ..physics.brdf import ALPHA_MAX, ALPHA_MIN
from ..scanner.scanner import Scanner
from .inputs import refine_inputs, store_refined, turned_tangents
from .materials import (
    BasisMaterials,
    WidthField,
    candidates,
    class_shares,
    colour_costs,
    colour_held,
    estimated_matte_share,
    judged_colour_costs,
    label_neighbours,
    lobe_clusters,
    local_shares,
    pooled_scale,
    second_wins,
    width_field,
)
from .model import Start, Trace
from .policy import lobe_costs, material_costs, refine_toward, turn_costs
from .priors import LobePrior
from .settings import ANISOTROPY_PARAMS, TUNING, RefineSettings
from .support_light import SupportScene
from .surface_fields import texel_spacing
from .tangent_field import field_variation, fused_turns, neighbour_turns

TANGENT_PARAMS = 1  # of ANISOTROPY_PARAMS, the tangent's: each member's own (pooled_widths, materials.second_wins)


def neighbour_turn_costs(
    texels: Texels | None,
    fit: TexelFit,
    i_obs: np.ndarray,
    label: np.ndarray,
    own: np.ndarray,
    rest: np.ndarray,
    K: int,
    spacing: float,
) -> tuple[np.ndarray, np.ndarray] | None:
    """Per texel of ``rest`` (rows of ``i_obs``) and lobe material: the turn its neighbours of that
    material with an anisotropic lobe of their own point along, and how well they agree ``(R, K)``
    each (``refine.tangent_field``; ``spacing``: the texels' ``texel_spacing``); None without ``texels``."""
    if texels is None:
        return None
    turn, agree = np.zeros((len(rest), K)), np.zeros((len(rest), K))
    constrained = own & (fit.flags[i_obs] & TexelFlag.TANGENT_UNCONSTRAINED == 0)
    for m in range(K):
        source = i_obs[constrained & (label == m)]
        turn[:, m], agree[:, m] = neighbour_turns(
            texels.position, texels.normal, texels.tangent, fit.t_loc, source, i_obs[rest], spacing
        )
    return turn, agree


def pooled_widths(
    scanner: Scanner,
    traces: RaggedTraces,
    fit: TexelFit,
    clear: np.ndarray,
    members: np.ndarray,
    basis: BasisMaterials,
    settings: RefineSettings,
    texels: Texels | None,
    support: SupportScene | None,
) -> BasisMaterials:
    """``basis`` with each material's lobe width (alphas) and rho_s from its members' traces
    together instead of the median of their own answers: one trace often cannot tell a broad lobe
    from a narrower one over a brighter diffuse, or a sharp one seen through an LED or two from a
    broader dimmer one, and its own solve lands by its start (the gallery's box alpha 0.5 metal
    came back 0.25 with rho_d x2.3, its glossy plastics and lacquers 1.5-4x too broad). Each of
    ``TUNING.materials.pool_texels`` sampled members (``clear`` texels, ``members`` their material; seeded per
    material) judges candidate widths with its own frame and its albedos re-solved
    (``refine.lobe_costs``); their clipped votes (``materials.pooled_votes``) decide. Candidates:
    an isotropic lobe scaled over ``TUNING.materials.pool_scales`` about the members' geometric-mean width and, where
    the members' median lobe is anisotropic, its smaller alpha scaled (the larger at the median),
    then its larger (the smaller at its pooled value). The anisotropic lobe is kept only where its
    votes beat the isotropic one's by ``ANISOTROPY_PARAMS`` — its ratio once, each member's own
    tangent (``TANGENT_PARAMS``) in that member's vote (``materials.second_wins``): a sharp
    isotropic lobe seen through an LED or two measures one axis, and each member's own solve leaves
    the other by its start (the gallery's vase alpha 0.02 plastic: |log alpha| 0.10 per axis, 0.02
    so) and turns its tangent with it. rho_s: the members'
    median at the chosen width. With ``texels``, an isotropic material's width may vary over the
    object: its members' profile over the scales, where they lie, makes a field where it predicts
    them better (``materials.width_field``; the result's ``width``, ``BasisMaterials.alpha_at``)."""
    alpha, rho_s, lobe_rho_d = basis.alpha.copy(), basis.rho_s.copy(), basis.lobe_rho_d.copy()
    fields: list[WidthField | None] = []
    S = len(TUNING.materials.pool_scales)
    for k in range(len(basis)):
        ids = clear[members == k]
        ids = np.sort(np.random.default_rng(k).choice(ids, min(TUNING.materials.pool_texels, len(ids)), replace=False))
        inp = refine_inputs(scanner, traces, torch.as_tensor(ids), fit, support, texels)
        tr = inp.obs.trace(settings.noise)  # once for every candidate set below
        a = alpha[k]
        mean = np.sqrt(a[0] * a[1]) * np.ones(2)  # the isotropic lobe of the members' mean width
        iso = mean * TUNING.materials.pool_scales[:, None]
        if a[0] < TUNING.policy.isotropic_ratio * a[1]:
            c, _, _ = member_lobe_costs(tr, inp.start, iso, settings)
            profile = c.numpy()  # the isotropic lobe's
            widths = [mean * pooled_scale(profile, TUNING.materials.pool_scales)]
        else:
            # the isotropic profile and the smaller alpha's in one call, then the larger alpha's
            minor = a * np.stack([np.ones(S), TUNING.materials.pool_scales], 1)
            c, _, _ = member_lobe_costs(tr, inp.start, np.concatenate([iso, minor]), settings)
            aniso = np.clip(
                a * np.array([1.0, pooled_scale(c[:, S:].numpy(), TUNING.materials.pool_scales)]), ALPHA_MIN, ALPHA_MAX
            )
            profile = c[:, :S].numpy()
            widths = [mean * pooled_scale(profile, TUNING.materials.pool_scales)]
            c, _, _ = member_lobe_costs(
                tr, inp.start, aniso * np.stack([TUNING.materials.pool_scales, np.ones(S)], 1), settings
            )
            widths.append(aniso * np.array([pooled_scale(c.numpy(), TUNING.materials.pool_scales), 1.0]))
        cand = -np.sort(-np.clip(widths, ALPHA_MIN, ALPHA_MAX), 1)  # alpha_x >= alpha_y
        c, rd, rs = member_lobe_costs(tr, inp.start, cand, settings)
        j = 0  # the isotropic lobe, unless the anisotropic one wins the vote
        if len(cand) == 2:
            # it pays only where it is anisotropic (its larger alpha may have pooled to the range's
            # end with the smaller: the knot's 0.5 metal): for the ratio once, and for each member's
            # own tangent in that member's vote (the gallery box's mirror lacquer, alpha
            # 0.006: its members' own lobes 0.028 x 0.006, elongated along one diagonal of their
            # texels; with the tangents unpaid their votes pooled it 0.0098 x 0.006, 43 against 149)
            anisotropic = cand[1, 0] >= TUNING.policy.isotropic_ratio * cand[1, 1]
            paid = (ANISOTROPY_PARAMS - TANGENT_PARAMS, TANGENT_PARAMS) if anisotropic else (0, 0)
            j = int(second_wins(c.numpy(), *paid))
        alpha[k], rho_s[k] = cand[j], rs[:, j].median(0).values.numpy()
        lobe_rho_d[k] = rd[:, j].median(0).values.numpy()
        # an isotropic lobe's width may vary over the object (the members' profile says where)
        fields.append(
            width_field(profile, texels.position[ids], mean, TUNING.materials.pool_scales)
            if j == 0 and texels is not None
            else None
        )
    return dataclasses.replace(basis, alpha=alpha, rho_s=rho_s, lobe_rho_d=lobe_rho_d, width=tuple(fields))


def member_lobe_costs(
    tr: Trace, start: Start, widths: np.ndarray, settings: RefineSettings
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``refine.lobe_costs`` of the texels of ``tr`` (built under ``settings.noise``) from ``start``
    under ``widths``: ``(W, 2)`` for all of them or ``(N, W, 2)`` each its own."""
    w = torch.as_tensor(widths)
    w = w.expand(tr.N, -1, -1) if w.dim() == 2 else w
    return lobe_costs(tr, start, w, settings)


def _widths_from_materials(
    scanner: Scanner,
    traces: RaggedTraces,
    fit: TexelFit,
    idx: np.ndarray,
    basis: BasisMaterials,
    settings: RefineSettings,
    texels: Texels | None,
    support: SupportScene | None,
    turn: np.ndarray | None = None,
    progress: Progress = QUIET,
) -> None:
    """Texels ``idx`` with a lobe of their own in a lobe material (``fit.material``) take its
    width where their trace explains it within ``TUNING.materials.width_params`` of their own (both with the
    texel's frame and albedos re-solved, ``refine.lobe_costs``): alphas the material's, rho_d and
    rho_s re-solved, flagged ``TexelFlag.WIDTH_FROM_MATERIAL``. ``turn (len(idx),)`` (radians, NaN:
    none): where the material's lobe is also tried turned so about the normal — an isotropic lobe
    of its own has no tangent to offer an anisotropic material's lobe (its neighbours' is the guess,
    ``neighbour_turn_costs``); the better of the two is kept, and its tangent with it. Updates ``fit``
    in place."""
    turn = np.full(len(idx), np.nan) if turn is None else turn
    bar = progress.counter("material widths", len(idx), "texel")
    for rows in _batches(np.arange(len(idx))):
        k = idx[rows]
        inp = refine_inputs(scanner, traces, torch.as_tensor(k), fit, support, texels)
        tr = inp.obs.trace(settings.noise)  # once: the turned subset reads its rows
        position = None if texels is None else texels.position[k]
        assert fit.material is not None  # material_pass labels every texel first
        alphas = np.stack([fit.alpha[k], basis.alpha_at(fit.material[k], position)], 1)  # (n, 2 candidates, 2)
        c, rd, rs = member_lobe_costs(tr, inp.start, alphas, settings)
        turned = np.nonzero(np.isfinite(turn[rows]))[0]
        angle = np.zeros(len(k))
        if len(turned):  # the material's lobe at the turned tangents
            sub = torch.as_tensor(turned)
            start = inp.start.rows(sub)
            a = torch.as_tensor(turn[rows][turned], dtype=start.tangent.dtype)[:, None]
            t, n = start.tangent, start.normal
            start = start._replace(tangent=a.cos() * t + a.sin() * torch.cross(n, t, dim=1))
            c_t, rd_t, rs_t = member_lobe_costs(tr.rows(sub), start, alphas[turned, 1:], settings)
            better = (c_t[:, 0] < c[turned, 1]).numpy()
            j = turned[better]
            c[j, 1], rd[j, 1], rs[j, 1] = c_t[better, 0], rd_t[better, 0], rs_t[better, 0]
            angle[j] = turn[rows][j]
        take = (c[:, 1] <= c[:, 0] + TUNING.materials.width_params).numpy()
        t = k[take]
        fit.alpha[t] = alphas[take, 1]
        fit.rho_d[t], fit.rho_s[t] = rd[take, 1].numpy(), rs[take, 1].numpy()
        fit.flags[t] |= TexelFlag.WIDTH_FROM_MATERIAL
        fit.t_loc[t] = turned_tangents(fit.t_loc[t], fit.n_loc[t], angle[take])
        bar.update(len(rows))
    bar.close()


def material_pass(
    scanner: Scanner,
    traces: RaggedTraces,
    fit: TexelFit,
    todo: torch.Tensor,
    settings: RefineSettings,
    progress: Progress,
    texels: Texels | None = None,
    support: SupportScene | None = None,
) -> None:
    """Basis materials from the first pass, assignment, and the texels that take a lobe from theirs
    refined toward it (``refine_fit``); updates ``fit`` in place."""
    N = traces.num_traces
    fit.material = np.full(N, -2, np.int64)
    i_obs = todo.numpy()
    own = np.zeros(N, bool)
    own[i_obs] = fit.flags[i_obs] & TexelFlag.SPECULAR_UNCONSTRAINED == 0
    # the basis from lobes measured on clear entries: a lobe read through the mesh's shadows (or at
    # grazing angles) is coarser — on the knot's Cycles scan those moved the clusters enough to lose
    # the glossy plastic's lobe
    clear = own & (fit.flags & TexelFlag.MARGINAL == 0)
    rows = np.nonzero(clear)[0]
    assert fit.highlight is not None  # refine_fit adds it before any pass
    basis, members = lobe_clusters(fit.rho_d[rows], fit.alpha[rows], fit.rho_s[rows], fit.highlight[rows])
    # the texels with a lobe of their own are labelled by colour (below): a cluster that holds none
    # of them is no material of its own, and its members join no pool
    basis, members = colour_held(basis, members, fit.rho_d[own])
    basis = pooled_widths(scanner, traces, fit, rows, members, basis, settings, texels, support)
    if len(basis) == 0:  # too few texels kept a lobe to make a material of: all matte
        fit.material[i_obs] = -1
        fit.materials = basis.to_arrays()
        return
    # the texels without a lobe of their own: their traces judge no lobe and the lobe materials of
    # their colour and the broad ones, each with its rho_d re-solved; their colours under each weigh in
    # where the traces cannot tell (judged without the lobe, a broad lobe's texels looked matte:
    # the knot's rough metal, docs/history/accuracy.md)
    colour = colour_costs(fit.rho_d[i_obs], basis)
    prior = colour - np.log(class_shares(basis))
    rest = np.nonzero(~own[i_obs])[0]
    costs = np.full((len(i_obs), 1 + len(basis)), np.inf)
    turns = np.zeros((len(i_obs), len(basis)))
    judged_rho_d = np.full((len(i_obs), 1 + len(basis), 3), np.nan)
    alpha, rho_s = torch.as_tensor(basis.alpha), torch.as_tensor(basis.rho_s)
    label = np.full(len(i_obs), -1)
    label[own[i_obs]] = np.argmin(prior[own[i_obs]], 1) - 1  # a texel with its own lobe: by its colour
    spacing = 0.0 if texels is None else texel_spacing(texels.position)  # once for the pass
    field = neighbour_turn_costs(texels, fit, i_obs, label, own[i_obs], rest, len(basis), spacing)
    bar = progress.counter("materials", len(rest), "texel")
    for k in _batches(np.arange(len(rest))):
        inp = refine_inputs(scanner, traces, torch.as_tensor(i_obs[rest[k]]), fit, support, texels)
        maybe = torch.as_tensor(candidates(prior[rest[k]], basis))
        near = None if field is None else (torch.as_tensor(field[0][k]), torch.as_tensor(field[1][k]))
        c, t, rd = material_costs(inp.obs, inp.start, alpha, rho_s, maybe, settings, near)
        costs[rest[k]], turns[rest[k]], judged_rho_d[rest[k]] = c.numpy(), t.numpy(), rd.numpy()
        bar.update(len(k))
    bar.close()
    # the matte share is this object's: the likeliest given every texel's colour and, where judged,
    # its trace (a texel with its own lobe is no matte one) — the prior above only chose candidates
    colour[rest] = judged_colour_costs(judged_rho_d[rest], basis)
    likelihood = colour.copy()
    likelihood[rest] += costs[rest]
    likelihood[own[i_obs], 0] = np.inf
    matte_share = estimated_matte_share(likelihood, basis)
    fit.matte_share = float(matte_share)
    shares = class_shares(basis, matte_share)
    prior = colour - np.log(shares)
    label[rest] = np.argmin(costs[rest] + prior[rest], 1) - 1  # -1: matte
    if texels is not None:  # then by each class's share where the texel lies (materials.local_shares)
        neighbours = label_neighbours(texels.position[i_obs])
        for _ in range(TUNING.materials.label_rounds):
            prior = colour - np.log(local_shares(neighbours, label, shares))
            label[rest] = np.argmin(costs[rest] + prior[rest], 1) - 1
    fit.material[i_obs] = label
    fit.materials = basis.to_arrays()
    fit.width_varies = np.array([f is not None for f in basis.width], bool)
    # own lobes in lobe materials: an isotropic one in an anisotropic material is also tried at the
    # turn its neighbours of the material point along
    with_own = np.nonzero(own[i_obs] & (label >= 0))[0]
    alpha_own, alpha_mat = fit.alpha[i_obs[with_own]], basis.alpha[label[with_own]]
    ask = (alpha_own[:, 0] < TUNING.policy.isotropic_ratio * alpha_own[:, 1]) & (
        alpha_mat[:, 0] >= TUNING.policy.isotropic_ratio * alpha_mat[:, 1]
    )
    turn = np.full(len(with_own), np.nan)
    around = neighbour_turn_costs(texels, fit, i_obs, label, own[i_obs], with_own[ask], len(basis), spacing)
    if around is not None:
        pick = np.arange(ask.sum()), label[with_own[ask]]
        turn[ask] = np.where(around[1][pick] > 0, around[0][pick], np.nan)  # agree 0: no neighbours
    _widths_from_materials(scanner, traces, fit, i_obs[with_own], basis, settings, texels, support, turn, progress)
    # texels without a lobe of their own in a lobe material: toward its lobe
    takes = np.zeros(N, bool)
    takes[i_obs] = (label >= 0) & ~own[i_obs]
    if takes.any():
        _take_material_lobes(
            scanner, traces, fit, takes, turns, i_obs, label, basis, settings, progress, texels, support
        )
    _fuse_tangents(scanner, traces, fit, i_obs, label, settings, spacing, texels, support, progress)


def _take_material_lobes(
    scanner: Scanner,
    traces: RaggedTraces,
    fit: TexelFit,
    takes: np.ndarray,
    turns: np.ndarray,
    i_obs: np.ndarray,
    label: np.ndarray,
    basis: BasisMaterials,
    settings: RefineSettings,
    progress: Progress,
    texels: Texels | None,
    support: SupportScene | None,
) -> None:
    """The texels ``takes (N,)`` (no lobe of their own, in a lobe material) refined toward their
    material's lobe, from the tangent turn their traces liked best (``turns (O, K)``, rows of
    ``i_obs``); updates ``fit``."""
    # their tangents turned to where their material's lobe fits their traces best
    k_takes = np.nonzero(takes[i_obs])[0]
    turn = turns[k_takes, label[k_takes]]
    i_takes = i_obs[k_takes]
    fit.t_loc[i_takes] = turned_tangents(fit.t_loc[i_takes], fit.n_loc[i_takes], turn)
    sel = torch.as_tensor(np.nonzero(takes)[0])
    bar = progress.counter("material lobes", len(sel), "texel")
    for idx in sel.split(TUNING.inputs.refine_batch):
        inp = refine_inputs(scanner, traces, idx, fit, support, texels)
        assert fit.material is not None  # material_pass labels every texel first
        m = fit.material[idx.numpy()]
        position = None if texels is None else texels.position[idx.numpy()]
        pull = LobePrior(
            torch.as_tensor(basis.alpha_at(m, position), dtype=torch.float32),
            torch.as_tensor(basis.rho_s[m], dtype=torch.float32),
            torch.as_tensor(basis.log_alpha_sigma[m], dtype=torch.float32),
            torch.as_tensor(basis.rho_s_sigma[m], dtype=torch.float32),
        )
        r = refine_toward(inp.obs, inp.start, pull, settings)
        store_refined(fit, idx, r, inp.marginal)
        bar.update(len(idx))
    bar.close()


def _fuse_tangents(
    scanner: Scanner,
    traces: RaggedTraces,
    fit: TexelFit,
    i_obs: np.ndarray,
    label: np.ndarray,
    settings: RefineSettings,
    spacing: float,
    texels: Texels | None = None,
    support: SupportScene | None = None,
    progress: Progress = QUIET,
) -> None:
    """Every anisotropic lobe's tangent fused with its neighbours' of the same material that fixed
    theirs (``refine.tangent_field.fused_turns`` over the material's ``field_variation``) — a tangent
    its trace fixed stays, noise between neighbours is averaged — and ``std``'s tangent column the
    fused one. A texel that took its material's lobe (``TexelFlag.FROM_MATERIAL``) counts as knowing its
    tangent to ``TUNING.materials.taken_tangent_std`` (its trace chose among turns; the LM's local std there says
    where the lobe cannot point, not where it points) and is no source; it turns only where its
    photos do not object (``TUNING.materials.turn_objection`` or more under its own lobe, ``refine.policy.turn_costs``)
    and where the field was seen on ``TUNING.materials.min_source_share`` of the material's anisotropic texels or
    more. Needs ``texels`` (where the texels lie; ``spacing`` their ``texel_spacing``); updates
    ``fit`` in place (docs/refinement.md, basis materials step 6)."""
    if texels is None:
        return
    alpha, flags = fit.alpha[i_obs], fit.flags[i_obs]
    anisotropic = (label >= 0) & (alpha[:, 0] >= TUNING.policy.isotropic_ratio * alpha[:, 1])
    taken = flags & TexelFlag.FROM_MATERIAL > 0
    assert fit.std is not None  # refine_fit adds it before any pass
    std = np.where(taken, TUNING.materials.taken_tangent_std, np.radians(np.nan_to_num(fit.std[i_obs, 1], nan=np.inf)))
    constrained = (
        anisotropic & ~taken & (flags & TexelFlag.TANGENT_UNCONSTRAINED == 0) & (std <= TUNING.materials.max_source_std)
    )
    std_all = np.full(len(fit.std), np.inf)
    std_all[i_obs] = std
    turn, fused = np.zeros(len(i_obs)), std.copy()
    geometry = (texels.position, texels.normal, texels.tangent, fit.t_loc, std_all)
    for m in np.unique(label[anisotropic]):
        target = np.nonzero(anisotropic & (label == m))[0]
        source = i_obs[constrained & (label == m)]
        variation = field_variation(*geometry, source, spacing)
        turn[target], fused[target] = fused_turns(*geometry, source, i_obs[target], variation)
        # a field seen on too few of the material's texels is not laid over the rest: their own
        # traces' turns stay (the blob's underside: 20 sources, 64 deg off, for 2,624 taken lobes)
        if len(source) < TUNING.materials.min_source_share * len(target):
            t_taken = target[taken[target]]
            turn[t_taken], fused[t_taken] = 0.0, std[t_taken]
    # a taken lobe turns only where its photos do not object
    ask = np.nonzero(taken & anisotropic & (np.abs(turn) > TUNING.materials.min_turn))[0]
    bar = progress.counter("tangent turns", len(ask), "texel")
    for k in _batches(ask):
        inp = refine_inputs(scanner, traces, torch.as_tensor(i_obs[k]), fit, support, texels)
        turns = torch.stack([torch.zeros(len(k), dtype=torch.float64), torch.as_tensor(turn[k])], 1)
        c = turn_costs(inp.obs, inp.start, turns, settings).numpy()
        objects = c[:, 1] - c[:, 0] >= TUNING.materials.turn_objection
        turn[k[objects]], fused[k[objects]] = 0.0, std[k[objects]]
        bar.update(len(k))
    bar.close()
    fit.t_loc[i_obs] = turned_tangents(fit.t_loc[i_obs], fit.n_loc[i_obs], turn)
    changed = anisotropic & np.isfinite(fused)
    fit.std[i_obs[changed], 1] = np.degrees(fused[changed])


def _batches(rows: np.ndarray) -> list[np.ndarray]:
    """``rows`` in equal batches of at most ``TUNING.inputs.refine_batch``, in order."""
    return np.array_split(rows, -(-len(rows) // TUNING.inputs.refine_batch)) if len(rows) else []
