"""The refinement of a whole result (``refine_fit``): the noise model calibrated on a sample, every
observed texel refined against its photos in batches (``refine.policy``), the albedo-edge pass, the
basis-material pass (``refine.material_pass``), the fused normal field and the albedo map near
edges — each step from the previous one's answers.

Convention: per-trace arrays as ``pipeline.fit_traces`` (the texel's geometric frame: n_loc, t_loc
(N, 3), alpha (N, 2), flags (N,), rho_d, rho_s (N, 3)); trace i is texel i of the atlas.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import torch

from ..fit.flags import TexelFlag
from ..fit.texel_fit import TexelFit
from ..io.allocator import freed_memory_kept
from ..io.progress import QUIET, Progress
from ..io.texels import Texels
from ..learn.ragged import RaggedTraces
from ..scanner.scanner import Scanner
from .albedo_map import sharpened_albedos, tap_texels
from .footprint import sample_points
from .inputs import read_traces, refine_inputs, store_refined, with_albedo_blend
from .material_pass import material_pass
from .model import Start, predicted_light
from .normal_field import fused_normals
from .policy import calibrated, refine
from .settings import TUNING, RefineSettings
from .support_light import SupportScene, face_albedo

# the progress stages (``io.progress``) a refinement reports, in their order: ``bench.scale`` tells
# the refine stage's memory from the other stages' by them
PROGRESS_STAGES = (
    "entries read",
    "refine",
    "albedo blend",
    "albedo edges",
    "materials",
    "material widths",
    "material lobes",
    "tangent turns",
    "albedo map",
    "albedo solve",
)


def refine_fit(
    scanner: Scanner,
    traces: RaggedTraces,
    fit: TexelFit,
    settings: RefineSettings | None = None,
    progress: Progress = QUIET,
    texels: Texels | None = None,
    support: SupportScene | None = None,
) -> TexelFit:
    """``fit_traces``'s result refined by analysis-by-synthesis (``refine.policy``) against every entry
    of every observed trace (``traces``: linear pixels as captured), dark and clipped ones included;
    with ``texels`` and ``settings.albedo_blend``, the texels whose pixels may blend a neighbour's
    albedo (``with_albedo_blend``, from the first pass's albedos) refined again from their start
    with that blend as noise (a lobe sought only where the first pass kept one), and every later
    step reading it so;
    adds ``std (N, 4)``, the 1-sigma uncertainties of normal (deg), tangent (deg), log alpha,
    log rho_s (NaN where no trace reached), and ``noise_scale`` (the noise model's calibration
    factor, from a first pass over a sample).
    Texels the network never saw (all entries out of range) start from the fallback lobe.

    With ``settings.materials`` (``refine.materials``), a second pass: basis materials from the texels
    whose own traces kept a lobe, every observed texel assigned one or the matte class
    (``material (N,)``: -1 matte, -2 unobserved; the table as ``material_*`` arrays), and the
    texels without a lobe of their own that belong to a lobe material refined toward its lobe, from
    the tangent turn its trace liked best (``refine.policy.material_costs``) — with ``texels`` (the
    atlas the traces were assembled for, trace i = texel i), weighing most the turn its neighbours
    of the material point along (``refine.tangent_field``). With ``support`` (and ``texels``), Eq. 1
    gains the light the support reflects onto the object (``refine.support_light``). Last, the albedos
    of the edge pass's texels that may blend ``TUNING.albedo_map.min_blend`` or more of a neighbour's are solved
    jointly from their entries' pixel samples (``sharpen_albedos``, ``settings.albedo_map``). Its batches'
    arrays reuse the memory the previous ones freed (``io.allocator``)."""
    with freed_memory_kept():
        return _refine_fit(scanner, traces, fit, settings, progress, texels, support)


def _refine_fit(
    scanner: Scanner,
    traces: RaggedTraces,
    fit: TexelFit,
    settings: RefineSettings | None,
    progress: Progress,
    texels: Texels | None,
    support: SupportScene | None,
) -> TexelFit:
    fit = fit.copy()
    traces = read_traces(scanner, traces, progress)  # every pass reads these entries alone, not whole traces
    todo = (traces.lengths > 0).nonzero().squeeze(1)
    settings = settings or RefineSettings()
    support = _lit_by_itself(support, texels, fit, todo)  # from the network's albedos
    if len(todo):  # the noise model, calibrated on a seeded sample of the texels
        gen = torch.Generator().manual_seed(0)
        sample = todo[torch.randperm(len(todo), generator=gen)[: TUNING.inputs.calibration_texels]].sort().values
        inp = refine_inputs(scanner, traces, sample, fit, support, texels)
        settings = calibrated(inp.obs, inp.start, inp.specular, settings)
        fit.noise_scale = settings.noise.relative / RefineSettings().noise.relative
        fit.normal_prior_at_mesh = settings.normal_prior_at_mesh
    fit.std = np.full((traces.num_traces, 4), np.nan)
    fit.highlight = np.zeros(traces.num_traces, np.float32)
    start = fit.copy()  # where every texel's own refinement starts
    _refine_texels(scanner, traces, fit, start, todo, settings, progress, texels, support, "refine")
    support = _lit_by_itself(support, texels, fit, todo)  # the object's light from the refined albedos
    sharpened = None
    if settings.albedo_blend and texels is not None and texels.uv_per_metre is not None:
        # the albedos just refined say where the edges are; the texels whose pixels may blend a
        # neighbour's are refined again with that blend as noise
        traces = with_albedo_blend(scanner, traces, fit.rho_d, texels, progress)
        assert traces.albedo_blend is not None
        per_trace = np.zeros(traces.num_traces, np.float32)  # each trace's largest blend
        texel = np.repeat(np.arange(traces.num_traces), traces.lengths.numpy())
        np.maximum.at(per_trace, texel, traces.albedo_blend.amax(1).numpy())
        edges = todo[torch.as_tensor(per_trace[todo.numpy()] > 0)]
        sharpened = todo[
            torch.as_tensor(per_trace[todo.numpy()] > TUNING.albedo_map.min_blend)
        ]  # the albedo map's texels
        # from the first pass's answers, TUNING.inputs.edge_rounds and no multi-start: the blend only reweighs
        # some entries. The weak pulls still centre on the start: centred on the first pass's
        # normal, which the blended entries had tipped, they held the matte normals there. A texel
        # that kept no lobe seeks none: noise on some of its entries shows no lobe that all did not
        if settings.edge_pass:
            warm = fit.copy()
            warm.flags[(fit.flags & TexelFlag.SPECULAR_UNCONSTRAINED) != 0] |= TexelFlag.NO_HIGHLIGHT
            again = dataclasses.replace(settings, rounds=TUNING.inputs.edge_rounds, starts=False)
            _refine_texels(scanner, traces, fit, warm, edges, again, progress, texels, support, "albedo edges", start)
    if settings.materials:
        material_pass(scanner, traces, fit, todo, settings, progress, texels, support)
    if settings.normal_field and texels is not None:
        fuse_normals(fit, texels, todo.numpy())
    if settings.albedo_map and sharpened is not None and texels is not None:
        sharpen_albedos(scanner, traces, fit, sharpened, settings, texels, support, progress)
    return fit


def _lit_by_itself(
    support: SupportScene | None, texels: Texels | None, fit: TexelFit, todo: torch.Tensor
) -> SupportScene | None:
    """``support`` with the object's light on itself (``refine.support_light``) from ``fit``'s albedos
    of the observed texels ``todo`` (trace i = texel i of ``texels``), where it has the mesh's face
    normals; else ``support`` as it is."""
    if support is None or support.face_normal is None or texels is None:
        return support
    known = np.zeros(len(texels), bool)
    known[todo.numpy()] = True
    albedo = face_albedo(len(support.face_normal), texels.face, fit.rho_d, known)
    return dataclasses.replace(support, face_albedo=albedo)


def sharpen_albedos(
    scanner: Scanner,
    traces: RaggedTraces,
    fit: TexelFit,
    idx: torch.Tensor,
    settings: RefineSettings,
    texels: Texels,
    support: SupportScene | None = None,
    progress: Progress = QUIET,
) -> None:
    """The albedos of the texels ``idx`` (those whose pixels may blend ``TUNING.albedo_map.min_blend`` of a
    neighbour's) solved
    jointly from their entries' pixel samples at ``fit``'s answers (``refine.albedo_map``): each entry
    (those ``refine_inputs`` reads) as its diffuse light times the albedos its taps land in, its
    lobe's light taken out. ``texels`` need ``uv_per_metre``; updates ``fit.rho_d`` in place."""
    assert texels.uv_per_metre is not None
    index = np.full(texels.shape, -1, np.int64)
    index[texels.row, texels.col] = np.arange(len(texels))
    uv = texels.uv
    parts: list[tuple[np.ndarray, ...]] = []
    bar = progress.counter("albedo map", len(idx), "texel")
    for batch in idx.split(TUNING.inputs.refine_batch):
        inp = refine_inputs(scanner, traces, batch, fit, support, texels)
        diffuse, lobe, inv_sigma = predicted_light(inp.obs, inp.start, settings)
        delta, weight = sample_points(scanner, inp.obs.entries, inp.obs.mask)
        i = batch.numpy()
        taps, w = tap_texels(delta.numpy(), weight.numpy(), uv[i], texels.uv_per_metre[i], index)
        live = inp.obs.mask.numpy()
        target = inp.obs.entries[..., :3].to(lobe.dtype) - lobe
        parts.append(tuple(a[live] for a in (diffuse.numpy(), target.numpy(), inv_sigma.numpy(), taps, w)))
        bar.update(len(batch))
    bar.close()
    if parts:
        d, y, s, t, w = (np.concatenate(col) for col in zip(*parts, strict=True))
        fit.rho_d = sharpened_albedos(d, y, s, t, w, fit.rho_d, idx.numpy(), progress).astype(fit.rho_d.dtype)


def fuse_normals(fit: TexelFit, texels: Texels, i_obs: np.ndarray) -> None:
    """The observed texels' ``i_obs`` normals each fused with its neighbours' of the same material
    label (``fit.material`` where the material pass ran; else all one group) as far as the
    normal field is smooth (``refine.normal_field.fused_normals``), their tangents kept orthogonal and
    ``std``'s normal column the fused one. A texel with no finite normal std keeps its normal.
    Updates ``fit`` in place (trace i = texel i of ``texels``)."""
    frame = texels.frame[i_obs]
    refined = np.einsum("tji,tj->ti", frame, fit.n_loc[i_obs])
    assert fit.std is not None  # refine_fit adds it before any pass
    std = np.radians(fit.std[i_obs, 0])
    label = fit.material[i_obs] if fit.material is not None else np.zeros(len(i_obs), np.int64)
    position, normal = texels.position[i_obs], texels.normal[i_obs]
    for m in np.unique(label):
        source = np.nonzero((label == m) & np.isfinite(std))[0]
        n_obj, n_std = fused_normals(position, normal, refined, std, source)
        k = i_obs[source]
        n_loc = np.einsum("tij,tj->ti", frame[source], n_obj)
        t = fit.t_loc[k]
        t = t - (t * n_loc).sum(1, keepdims=True) * n_loc
        fit.n_loc[k], fit.t_loc[k] = n_loc, t / np.linalg.norm(t, axis=1, keepdims=True)
        fit.std[k, 0] = np.degrees(n_std)


def _refine_texels(
    scanner: Scanner,
    traces: RaggedTraces,
    fit: TexelFit,
    start: TexelFit,
    todo: torch.Tensor,
    settings: RefineSettings,
    progress: Progress,
    texels: Texels | None,
    support: SupportScene | None,
    name: str,
    centre: TexelFit | None = None,
) -> None:
    """The texels ``todo`` refined from ``start`` into ``fit``, the weak pulls centred on ``centre``
    (default: the start)."""
    bar = progress.counter(name, len(todo), "texel")
    for idx in todo.split(TUNING.inputs.refine_batch):
        inp = refine_inputs(scanner, traces, idx, start, support, texels)
        pulls = None if centre is None else Start.from_fit(centre, idx.numpy())
        r = refine(inp.obs, inp.start, inp.specular, settings, pulls)
        store_refined(fit, idx, r, inp.marginal)
        bar.update(len(idx))
    bar.close()
