"""The fit stage: every trace through the network, then the geometry fit, the highlight check and
the RGB albedo (paper §6-7), in blocks of ``FIT_BLOCK`` texels — the unit of work, run one after
the other in this process or as Ray tasks (``pipeline.task_pool``), with the same result — and the
optional refinement against the photos (``refine_fit``).

Convention: the table holds linear pixels as captured; ``fit_blocks`` scales each block's pixels to
the model's exposure (``pixel_scale``) before ``fit_traces``, which undoes it for the physical
albedo. Results are per trace, in the texel's geometric frame (n^, t^ as the lumitexel's z and x):
n_loc, t_loc (N, 3), alpha (N, 2) = (alpha_x, alpha_y), flags (N,), rho_d, rho_s (N, 3). Traces
with no entry keep the defaults (+z, +x, FALLBACK_ALPHA, zeros).
"""

from __future__ import annotations

import dataclasses
import time
from typing import NamedTuple

import numpy as np
import torch

from ..fit.albedo import highlights_and_albedo
from ..fit.albedo_map import MIN_BLEND, sharpened_albedos, tap_texels
from ..fit.emitter_blocks import shadow_groups
from ..fit.footprint import Footprint, albedo_blend, sample_points, slope_spread
from ..fit.geometry import FALLBACK_ALPHA, FLAG_NO_HIGHLIGHT, fit_geometry
from ..fit.materials import (
    LABEL_ROUNDS,
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
from ..fit.normal_field import fused_normals
from ..fit.refine import (
    ANISOTROPY_PARAMS,
    FLAG_FROM_MATERIAL,
    FLAG_SPECULAR_UNCONSTRAINED,
    FLAG_TANGENT_UNCONSTRAINED,
    ISOTROPIC_RATIO,
    LobePrior,
    Refined,
    RefineSettings,
    Start,
    calibrated,
    lobe_costs,
    material_costs,
    predicted_light,
    refine,
    refine_toward,
    turn_costs,
)
from ..fit.support_light import SupportScene, SupportView, face_albedo
from ..fit.surface_fields import texel_spacing
from ..fit.tangent_field import field_variation, fused_turns, neighbour_turns
from ..io.allocator import freed_memory_kept
from ..io.progress import QUIET, Progress
from ..learn.inference import predict
from ..learn.network import TraceNet
from ..learn.ragged import RaggedTraces, spans, spread_rows
from ..physics.brdf import ALPHA_MAX, ALPHA_MIN
from ..physics.frame import frame_from_normal_tangent
from ..scanner.scanner import Scanner
from .task_pool import LocalPool, TaskPool
from .texels import Texels
from .traces import grazing, shadowed

# entries per trace the network reads, spread evenly over the trace: the length it was trained on,
# and its validation loss is lowest there (2.08 at 64 views vs 2.15 at 128; docs/network.md); a
# 1000-photo scan's ~323-entry traces cost the network 5x less
NETWORK_VIEWS = 64
ALBEDO_VIEWS = 16  # entries per texel for the beta check and the albedo LS (Eq. 1 per entry and emitter)
RHO_S_PRIOR_WEIGHT = 1.0  # the network's rho_s counts as one view in the albedo LS (fit._albedo_ls)
REFINE_VIEWS = 24  # entries per texel the refinement reads (spread evenly over the trace)
# a texel with this many clear entries (neither shadowed by its mesh nor grazing) refines on those
# alone; with fewer it reads its marginal ones too (``refine_inputs``)
MIN_CLEAR_ENTRIES = 1
CALIBRATION_TEXELS = 512  # texels refined first to calibrate the noise and the normal's pull (fit.refine.calibrated)
BLEND_ENTRIES = 1 << 18  # entries per block of with_albedo_blend (its float64 temporaries ~100 MB)
# rounds of the albedo-edge pass (from the first pass's answers); 1 lost the engine box's mirror
# lacquer lobe (|log alpha| 0.002 -> 1.29) — docs/refinement.md, "Speed"
EDGE_ROUNDS = 2
REFINE_BATCH = 512  # texels per refinement batch: (batch, views, emitters) tensors stay ~100 MB
FLAG_MARGINAL = 128  # refined on entries the mesh shadows or sees at grazing angles (too few others)
MAX_SOURCE_STD = np.radians(20.0)  # a tangent known worse than this tells its neighbours nothing (_fuse_tangents)
TAKEN_TANGENT_STD = np.radians(20.0)  # a taken lobe's tangent: the turn its trace liked best, to about this
MIN_SOURCE_SHARE = 0.02  # a material's texels that must have fixed their own tangents for the others to take theirs
TURN_OBJECTION = 2.0  # a taken lobe's photos object to its neighbours' tangent at this much more cost (half chi^2)
MIN_TURN = np.radians(0.5)  # a turn below this is not worth asking the photos about
FLAG_WIDTH_FROM_MATERIAL = 256  # a lobe of its own, its width its material's: the trace could not tell them apart
REFINE_FLAGS = FLAG_SPECULAR_UNCONSTRAINED | FLAG_TANGENT_UNCONSTRAINED | FLAG_FROM_MATERIAL
REFINE_FLAGS |= FLAG_MARGINAL | FLAG_WIDTH_FROM_MATERIAL
# a material's lobe width from its members' traces together (``pooled_widths``): this many sampled
# members (with 256, five member samples of the knot's glossy plastic under Cycles pooled to alpha
# 0.006-0.0205; with 1024, all of its members, 0.0119 every time), the width scaled over this grid
# (per axis of an anisotropic lobe)
POOL_TEXELS = 1024
POOL_SCALES = 2.0 ** np.linspace(-2.0, 2.0, 9)
# a texel with its own lobe takes its material's width where that costs its trace at most this more
# than its own (AIC's 1 per parameter for the 2 alphas it would add; half chi-square units)
WIDTH_PARAMS = 2.0
TANGENT_PARAMS = 1  # of ANISOTROPY_PARAMS, the tangent's: each member's own (pooled_widths, materials.second_wins)
# texels per unit of work of the fit stage (a Ray task with --ray): a few seconds of work and ~10 MB
# of traces at 60 photos; only one block's traces are in memory at a time (the table is on disk)
FIT_BLOCK = 4096


def fit_blocks(
    net: TraceNet,
    scanner: Scanner,
    traces: RaggedTraces,
    pixel_scale: float,
    pool: TaskPool | None = None,
    progress: Progress = QUIET,
) -> dict[str, np.ndarray]:
    """``fit_traces`` over ``traces`` (linear pixels as captured; may be memory-mapped) block by
    block on ``pool`` (default: this process); each block's pixels are scaled by ``pixel_scale`` on
    its own copy. The same arrays as ``fit_traces`` on the whole table, bit for bit whichever pool."""
    N = traces.num_traces
    starts = range(0, N, FIT_BLOCK)
    blocks = (_own_block(traces, a, min(a + FIT_BLOCK, N)) for a in starts)
    observed = int((traces.lengths > 0).sum())
    bar = progress.counter("network + fit", observed, "texel")
    out: dict[str, np.ndarray] = {}
    for b, part in (pool or LocalPool()).map(_fit_block, blocks, shared=(net, scanner, pixel_scale)):
        if not out:
            out = {k: np.zeros((N, *v.shape[1:]), v.dtype) for k, v in part.items()}
        a = starts[b]
        for k, v in part.items():
            out[k][a : a + len(v)] = v
        bar.update(int((traces.lengths[a : a + FIT_BLOCK] > 0).sum()))
    bar.close()
    return out or fit_traces(net, scanner, traces, pixel_scale)  # no trace at all: the empty arrays


def _own_block(traces: RaggedTraces, start: int, stop: int) -> RaggedTraces:
    """Traces ``start:stop`` with their in-range entries only (all ``fit_traces`` reads) as a
    contiguous copy: pickled for a Ray task, a view would carry the whole table's storage along, and
    the fit scales the copy's pixels in place. One copy, not a copy and then the in-range one."""
    b = traces.block(start, stop)
    return RaggedTraces(b.entries.clone(), b.offsets.clone()) if b.in_range is None else b.in_range_only()


def _fit_block(block: RaggedTraces, net: TraceNet, scanner: Scanner, pixel_scale: float) -> dict[str, np.ndarray]:
    """One block (a Ray task's body; ``block`` is its own): pixels scaled to the model's exposure,
    then ``fit_traces``."""
    block.entries[:, :3] *= pixel_scale
    return fit_traces(net, scanner, block, pixel_scale)


def fit_traces(
    net: TraceNet,
    scanner: Scanner,
    traces: RaggedTraces,
    pixel_scale: float,
    batch: int = 4096,
    progress: Progress = QUIET,
    seconds: dict[str, float] | None = None,
) -> dict[str, np.ndarray]:
    """Network + geometry fit + RGB albedo per trace (the refinement's start, ``refine_fit``).
    ``pixel_scale`` is the factor the traces' linear pixels were scaled by to the model's exposure
    (undone for the physical albedo LS). Reads the in-range entries only. Returns per-trace arrays in
    the texel's geometric frame: n_loc, t_loc (N, 3), alpha (N, 2), flags (N,), rho_d, rho_s (N, 3).
    ``seconds``, if given, receives the wall time of each part: network, geometry, albedo
    (``ntp bench fit`` reports them)."""
    clock = {"network": 0.0, "geometry": 0.0, "albedo": 0.0}
    traces = traces.in_range_only()
    N = traces.num_traces
    n_loc, t_loc = np.zeros((N, 3)), np.zeros((N, 3))
    n_loc[:, 2], t_loc[:, 0] = 1.0, 1.0
    ax, ay, flags = np.full(N, FALLBACK_ALPHA), np.full(N, FALLBACK_ALPHA), np.zeros(N, np.int64)
    rho_d, rho_s = np.zeros((N, 3)), np.zeros((N, 3))
    observed = int((traces.lengths > 0).sum())
    bar = progress.counter("network + fit", observed, "texel")
    t0 = time.perf_counter()
    for idx, d, s in predict(net, traces, max_entries=batch * 32, max_views=NETWORK_VIEWS):
        t1 = time.perf_counter()
        clock["network"] += t1 - t0
        keep = traces.lengths[idx] > 0
        idx, d, s = idx[keep], d[keep], s[keep]
        if len(idx) == 0:
            t0 = time.perf_counter()
            continue
        g = fit_geometry(s, d)
        t2 = time.perf_counter()
        clock["geometry"] += t2 - t1
        i = idx.numpy()
        n_loc[i], t_loc[i] = g.normal.numpy(), g.tangent.numpy()
        ax[i], ay[i], flags[i] = g.alpha_x.numpy(), g.alpha_y.numpy(), g.flags.numpy()
        for a in range(0, len(idx), 256):  # (n, V, L) Eq. 1 terms: keep them cache-sized
            sub = slice(a, a + 256)
            ent, mask = traces.padded(idx[sub], max_views=ALBEDO_VIEWS)
            gs = g.rows(sub)
            _, rd, rs = highlights_and_albedo(
                scanner,
                ent[..., :3] / pixel_scale,
                ent[..., 3:6],
                ent[..., 6:9],
                ent[..., 9:12],
                mask,
                gs,
                prior_weight=RHO_S_PRIOR_WEIGHT,
            )
            rho_d[i[sub]], rho_s[i[sub]] = rd.numpy(), rs.numpy()
            ax[i[sub]], ay[i[sub]], flags[i[sub]] = gs.alpha_x.numpy(), gs.alpha_y.numpy(), gs.flags.numpy()
        bar.update(len(idx))
        t0 = time.perf_counter()
        clock["albedo"] += t0 - t2
    bar.close()
    if seconds is not None:
        seconds.update(clock)
    return {
        "n_loc": n_loc,
        "t_loc": t_loc,
        "alpha": np.stack([ax, ay], 1),
        "flags": flags,
        "rho_d": rho_d,
        "rho_s": rho_s,
    }


class RefineInputs(NamedTuple):
    """What ``fit.refine`` takes for n texels (``refine_inputs``)."""

    entries: torch.Tensor  # (n, V, 12) linear pixels as captured
    mask: torch.Tensor  # (n, V)
    start: Start
    specular: torch.Tensor  # (n,) texels that seek a lobe
    shadow: torch.Tensor  # (n, V) int64 emitter groups the mesh hides from each entry
    marginal: torch.Tensor  # (n,) texels that read shadowed or grazing entries (``MIN_CLEAR_ENTRIES``)
    support: SupportView | None  # the support's light on them (``fit.support_light``), or None
    footprint: Footprint | None  # what each entry's pixel sample spans (``fit.footprint``)

    def rows(self, idx: torch.Tensor) -> RefineInputs:
        """The same for the texels ``idx`` (rows) only."""
        view = self.support
        return RefineInputs(
            self.entries[idx],
            self.mask[idx],
            Start(*(v[idx] for v in self.start)),
            self.specular[idx],
            self.shadow[idx],
            self.marginal[idx],
            None if view is None else view.rows(idx),
            None if self.footprint is None else self.footprint.rows(idx),
        )


def refine_inputs(
    scanner: Scanner,
    traces: RaggedTraces,
    idx: torch.Tensor,
    fit: dict[str, np.ndarray],
    support: SupportScene | None = None,
    texels: Texels | None = None,
) -> RefineInputs:
    """What ``fit.refine.refine`` takes for the texels ``idx`` of ``traces`` (linear pixels as
    captured: the camera model is the scanner's): their entries (``REFINE_VIEWS`` spread over each
    trace), the start from ``fit``, which texels seek a lobe (those the highlight check did not
    flag). Marginal entries — the mesh shadows them (``traces.shadowed``) or sees them at grazing
    angles (``traces.grazing``) — are read only by texels with fewer than ``MIN_CLEAR_ENTRIES``
    others (``marginal``): their model is coarser (half emitter blocks hidden or not, no light the
    mesh reflects into its own shadows; a grazing pixel spans a strip of surface) — on the knot
    reading shadowed entries everywhere cost the Cycles scan's normals 0.3-0.7 deg, on the gallery
    grazing ones its relit SSIM (docs/accuracy.md). With ``support`` (and ``texels``, the atlas of
    the traces), the support's light on them; with ``texels``, the normals each entry's pixel sample
    spans where the surface turns (``fit.footprint``)."""
    groups = shadow_groups(scanner)
    rows, mask = traces.padded_rows(idx)  # every entry of each trace
    marginal_entry = mask & (shadowed(groups, traces.shadow_at(rows, mask)) | grazing(traces.entries_at(rows, mask)))
    clear = mask & ~marginal_entry
    few = clear.sum(1) < MIN_CLEAR_ENTRIES
    marginal = few & marginal_entry.any(1)
    rows, mask = spread_rows(rows, torch.where(few[:, None], mask, clear), REFINE_VIEWS)
    i = idx.numpy()
    specular = torch.as_tensor(fit["flags"][i] & FLAG_NO_HIGHLIGHT == 0)
    start = Start.from_fit(fit, i)
    view = None
    if support is not None:
        if texels is None:
            raise ValueError("the support's light needs the texels the traces were assembled for")
        frame = frame_from_normal_tangent(torch.as_tensor(texels.normal[i]), torch.as_tensor(texels.tangent[i]))
        exposed = None if support.exposed is None else torch.as_tensor(support.exposed[i])
        view = SupportView(support, torch.as_tensor(texels.position[i]), frame, exposed)
    entries, shadow = traces.entries_at(rows, mask), traces.shadow_at(rows, mask)
    spread = None
    if texels is not None and texels.shape_operator is not None:
        spread = slope_spread(scanner, entries, mask, torch.as_tensor(texels.shape_operator[i]))
    blend = traces.albedo_blend_at(rows, mask)
    footprint = None if spread is None and blend is None else Footprint(spread, blend)
    return RefineInputs(entries, mask, start, specular, shadow, marginal, view, footprint)


def with_albedo_blend(scanner: Scanner, traces: RaggedTraces, rho_d: np.ndarray, texels: Texels) -> RaggedTraces:
    """``traces`` (trace i = texel i of ``texels``, which need ``uv_per_metre``) with each entry's
    ``albedo_blend``: how much of its neighbours' albedo its pixel sample may blend in
    (``fit.footprint.albedo_blend``), read from the map of ``rho_d (N, 3)``; texels no trace reached
    take the nearest observed one's. In blocks of ~``BLEND_ENTRIES`` entries."""
    assert texels.uv_per_metre is not None
    albedo = texels.image(rho_d, known=(traces.lengths > 0).numpy())
    uv = texels.uv
    out = torch.zeros(len(traces.entries), 3, dtype=torch.float32)
    for start, stop in spans(traces.offsets.numpy(), BLEND_ENTRIES):
        b = traces.block(start, stop)
        texel = torch.repeat_interleave(torch.arange(start, stop), b.lengths).numpy()
        entries = b.entries[:, None, :]
        delta, weight = sample_points(scanner, entries, torch.ones(len(entries), 1, dtype=torch.bool))
        blend = albedo_blend(delta, weight, uv[texel], texels.uv_per_metre[texel], albedo)
        a = int(traces.offsets[start])
        out[a : a + len(entries)] = blend[:, 0].to(torch.float32)
    return dataclasses.replace(traces, albedo_blend=out)


def refine_fit(
    scanner: Scanner,
    traces: RaggedTraces,
    fit: dict[str, np.ndarray],
    settings: RefineSettings | None = None,
    progress: Progress = QUIET,
    texels: Texels | None = None,
    support: SupportScene | None = None,
) -> dict[str, np.ndarray]:
    """``fit_traces``'s result refined by analysis-by-synthesis (``fit.refine``) against every entry
    of every observed trace (``traces``: linear pixels as captured), dark and clipped ones included;
    with ``texels`` and ``settings.albedo_blend``, the texels whose pixels may blend a neighbour's
    albedo (``with_albedo_blend``, from the first pass's albedos) refined again from their start
    with that blend as noise (a lobe sought only where the first pass kept one), and every later
    step reading it so;
    adds ``std (N, 4)``, the 1-sigma uncertainties of normal (deg), tangent (deg), log alpha,
    log rho_s (NaN where no trace reached), and ``noise_scale`` (the noise model's calibration
    factor, from a first pass over a sample).
    Texels the network never saw (all entries out of range) start from the fallback lobe.

    With ``settings.materials`` (``fit.materials``), a second pass: basis materials from the texels
    whose own traces kept a lobe, every observed texel assigned one or the matte class
    (``material (N,)``: -1 matte, -2 unobserved; the table as ``material_*`` arrays), and the
    texels without a lobe of their own that belong to a lobe material refined toward its lobe, from
    the tangent turn its trace liked best (``fit.refine.material_costs``) — with ``texels`` (the
    atlas the traces were assembled for, trace i = texel i), weighing most the turn its neighbours
    of the material point along (``fit.tangent_field``). With ``support`` (and ``texels``), Eq. 1
    gains the light the support reflects onto the object (``fit.support_light``). Last, the albedos
    of the edge pass's texels that may blend ``MIN_BLEND`` or more of a neighbour's are solved
    jointly from their entries' pixel samples (``sharpen_albedos``, ``settings.albedo_map``). Its batches'
    arrays reuse the memory the previous ones freed (``io.allocator``)."""
    with freed_memory_kept():
        return _refine_fit(scanner, traces, fit, settings, progress, texels, support)


def _refine_fit(
    scanner: Scanner,
    traces: RaggedTraces,
    fit: dict[str, np.ndarray],
    settings: RefineSettings | None,
    progress: Progress,
    texels: Texels | None,
    support: SupportScene | None,
) -> dict[str, np.ndarray]:
    fit = {k: v.copy() for k, v in fit.items()}
    todo = (traces.lengths > 0).nonzero().squeeze(1)
    settings = settings or RefineSettings()
    support = _lit_by_itself(support, texels, fit, todo)  # from the network's albedos
    if len(todo):  # the noise model, calibrated on a seeded sample of the texels
        gen = torch.Generator().manual_seed(0)
        sample = todo[torch.randperm(len(todo), generator=gen)[:CALIBRATION_TEXELS]].sort().values
        inp = refine_inputs(scanner, traces, sample, fit, support, texels)
        settings = calibrated(
            scanner, inp.entries, inp.mask, inp.start, inp.specular, settings, inp.shadow, inp.support, inp.footprint
        )
        fit["noise_scale"] = np.array(settings.noise.relative / RefineSettings().noise.relative)
        fit["normal_prior_at_mesh"] = np.array(settings.normal_prior_at_mesh)
    fit["std"] = np.full((traces.num_traces, 4), np.nan)
    fit["highlight"] = np.zeros(traces.num_traces, np.float32)
    start = {k: v.copy() for k, v in fit.items()}  # where every texel's own refinement starts
    _refine_texels(scanner, traces, fit, start, todo, settings, progress, texels, support, "refine")
    support = _lit_by_itself(support, texels, fit, todo)  # the object's light from the refined albedos
    sharpened = None
    if settings.albedo_blend and texels is not None and texels.uv_per_metre is not None:
        # the albedos just refined say where the edges are; the texels whose pixels may blend a
        # neighbour's are refined again with that blend as noise
        traces = with_albedo_blend(scanner, traces, fit["rho_d"], texels)
        assert traces.albedo_blend is not None
        per_trace = np.zeros(traces.num_traces, np.float32)  # each trace's largest blend
        texel = np.repeat(np.arange(traces.num_traces), traces.lengths.numpy())
        np.maximum.at(per_trace, texel, traces.albedo_blend.amax(1).numpy())
        edges = todo[torch.as_tensor(per_trace[todo.numpy()] > 0)]
        sharpened = todo[torch.as_tensor(per_trace[todo.numpy()] > MIN_BLEND)]  # the albedo map's texels
        # from the first pass's answers, EDGE_ROUNDS and no multi-start: the blend only reweighs
        # some entries. The weak pulls still centre on the start: centred on the first pass's
        # normal, which the blended entries had tipped, they held the matte normals there. A texel
        # that kept no lobe seeks none: noise on some of its entries shows no lobe that all did not
        warm = {k: v.copy() for k, v in fit.items()}
        warm["flags"][(fit["flags"] & FLAG_SPECULAR_UNCONSTRAINED) != 0] |= FLAG_NO_HIGHLIGHT
        again = dataclasses.replace(settings, rounds=EDGE_ROUNDS, starts=False)
        _refine_texels(scanner, traces, fit, warm, edges, again, progress, texels, support, "albedo edges", start)
    if settings.materials:
        _material_pass(scanner, traces, fit, todo, settings, progress, texels, support)
    if settings.normal_field and texels is not None:
        fuse_normals(fit, texels, todo.numpy())
    if settings.albedo_map and sharpened is not None and texels is not None:
        sharpen_albedos(scanner, traces, fit, sharpened, settings, texels, support, progress)
    return fit


def _lit_by_itself(
    support: SupportScene | None, texels: Texels | None, fit: dict[str, np.ndarray], todo: torch.Tensor
) -> SupportScene | None:
    """``support`` with the object's light on itself (``fit.support_light``) from ``fit``'s albedos
    of the observed texels ``todo`` (trace i = texel i of ``texels``), where it has the mesh's face
    normals; else ``support`` as it is."""
    if support is None or support.face_normal is None or texels is None:
        return support
    known = np.zeros(len(texels), bool)
    known[todo.numpy()] = True
    albedo = face_albedo(len(support.face_normal), texels.face, fit["rho_d"], known)
    return dataclasses.replace(support, face_albedo=albedo)


def sharpen_albedos(
    scanner: Scanner,
    traces: RaggedTraces,
    fit: dict[str, np.ndarray],
    idx: torch.Tensor,
    settings: RefineSettings,
    texels: Texels,
    support: SupportScene | None = None,
    progress: Progress = QUIET,
) -> None:
    """The albedos of the texels ``idx`` (those whose pixels may blend ``MIN_BLEND`` of a neighbour's) solved
    jointly from their entries' pixel samples at ``fit``'s answers (``fit.albedo_map``): each entry
    (those ``refine_inputs`` reads) as its diffuse light times the albedos its taps land in, its
    lobe's light taken out. ``texels`` need ``uv_per_metre``; updates ``fit["rho_d"]`` in place."""
    assert texels.uv_per_metre is not None
    index = np.full(texels.shape, -1, np.int64)
    index[texels.row, texels.col] = np.arange(len(texels))
    uv = texels.uv
    parts: list[tuple[np.ndarray, ...]] = []
    bar = progress.counter("albedo map", len(idx), "texel")
    for batch in idx.split(REFINE_BATCH):
        inp = refine_inputs(scanner, traces, batch, fit, support, texels)
        diffuse, lobe, inv_sigma = predicted_light(
            scanner, inp.entries, inp.mask, inp.start, settings, inp.shadow, inp.support, inp.footprint
        )
        delta, weight = sample_points(scanner, inp.entries, inp.mask)
        i = batch.numpy()
        taps, w = tap_texels(delta.numpy(), weight.numpy(), uv[i], texels.uv_per_metre[i], index)
        live = inp.mask.numpy()
        target = inp.entries[..., :3].to(lobe.dtype) - lobe
        parts.append(tuple(a[live] for a in (diffuse.numpy(), target.numpy(), inv_sigma.numpy(), taps, w)))
        bar.update(len(batch))
    bar.close()
    if parts:
        d, y, s, t, w = (np.concatenate(col) for col in zip(*parts, strict=True))
        fit["rho_d"] = sharpened_albedos(d, y, s, t, w, fit["rho_d"], idx.numpy()).astype(fit["rho_d"].dtype)


def fuse_normals(fit: dict[str, np.ndarray], texels: Texels, i_obs: np.ndarray) -> None:
    """The observed texels' ``i_obs`` normals each fused with its neighbours' of the same material
    label (``fit["material"]`` where the material pass ran; else all one group) as far as the
    normal field is smooth (``fit.normal_field.fused_normals``), their tangents kept orthogonal and
    ``std``'s normal column the fused one. A texel with no finite normal std keeps its normal.
    Updates ``fit`` in place (trace i = texel i of ``texels``)."""
    frame = texels.frame[i_obs]
    refined = np.einsum("tji,tj->ti", frame, fit["n_loc"][i_obs])
    std = np.radians(fit["std"][i_obs, 0])
    label = fit["material"][i_obs] if "material" in fit else np.zeros(len(i_obs), np.int64)
    position, normal = texels.position[i_obs], texels.normal[i_obs]
    for m in np.unique(label):
        source = np.nonzero((label == m) & np.isfinite(std))[0]
        n_obj, n_std = fused_normals(position, normal, refined, std, source)
        k = i_obs[source]
        n_loc = np.einsum("tij,tj->ti", frame[source], n_obj)
        t = fit["t_loc"][k]
        t = t - (t * n_loc).sum(1, keepdims=True) * n_loc
        fit["n_loc"][k], fit["t_loc"][k] = n_loc, t / np.linalg.norm(t, axis=1, keepdims=True)
        fit["std"][k, 0] = np.degrees(n_std)


def _refine_texels(
    scanner: Scanner,
    traces: RaggedTraces,
    fit: dict[str, np.ndarray],
    start: dict[str, np.ndarray],
    todo: torch.Tensor,
    settings: RefineSettings,
    progress: Progress,
    texels: Texels | None,
    support: SupportScene | None,
    name: str,
    centre: dict[str, np.ndarray] | None = None,
) -> None:
    """The texels ``todo`` refined from ``start`` into ``fit``, the weak pulls centred on ``centre``
    (default: the start)."""
    bar = progress.counter(name, len(todo), "texel")
    for idx in todo.split(REFINE_BATCH):
        inp = refine_inputs(scanner, traces, idx, start, support, texels)
        pulls = None if centre is None else Start.from_fit(centre, idx.numpy())
        r = refine(
            scanner,
            inp.entries,
            inp.mask,
            inp.start,
            inp.specular,
            settings,
            inp.shadow,
            inp.support,
            inp.footprint,
            pulls,
        )
        _store(fit, idx, r, inp.marginal)
        bar.update(len(idx))
    bar.close()


def _neighbour_turns(
    texels: Texels | None,
    fit: dict[str, np.ndarray],
    i_obs: np.ndarray,
    label: np.ndarray,
    own: np.ndarray,
    rest: np.ndarray,
    K: int,
    spacing: float,
) -> tuple[np.ndarray, np.ndarray] | None:
    """Per texel of ``rest`` (rows of ``i_obs``) and lobe material: the turn its neighbours of that
    material with an anisotropic lobe of their own point along, and how well they agree ``(R, K)``
    each (``fit.tangent_field``; ``spacing``: the texels' ``texel_spacing``); None without ``texels``."""
    if texels is None:
        return None
    turn, agree = np.zeros((len(rest), K)), np.zeros((len(rest), K))
    constrained = own & (fit["flags"][i_obs] & FLAG_TANGENT_UNCONSTRAINED == 0)
    for m in range(K):
        source = i_obs[constrained & (label == m)]
        turn[:, m], agree[:, m] = neighbour_turns(
            texels.position, texels.normal, texels.tangent, fit["t_loc"], source, i_obs[rest], spacing
        )
    return turn, agree


def pooled_widths(
    scanner: Scanner,
    traces: RaggedTraces,
    fit: dict[str, np.ndarray],
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
    ``POOL_TEXELS`` sampled members (``clear`` texels, ``members`` their material; seeded per
    material) judges candidate widths with its own frame and its albedos re-solved
    (``refine.lobe_costs``); their clipped votes (``materials.pooled_votes``) decide. Candidates:
    an isotropic lobe scaled over ``POOL_SCALES`` about the members' geometric-mean width and, where
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
    S = len(POOL_SCALES)
    for k in range(len(basis)):
        ids = clear[members == k]
        ids = np.sort(np.random.default_rng(k).choice(ids, min(POOL_TEXELS, len(ids)), replace=False))
        inp = refine_inputs(scanner, traces, torch.as_tensor(ids), fit, support, texels)
        a = alpha[k]
        mean = np.sqrt(a[0] * a[1]) * np.ones(2)  # the isotropic lobe of the members' mean width
        iso = mean * POOL_SCALES[:, None]
        if a[0] < ISOTROPIC_RATIO * a[1]:
            c, _, _ = _lobe_costs(scanner, inp, iso, settings)
            profile = c.numpy()  # the isotropic lobe's
            widths = [mean * pooled_scale(profile, POOL_SCALES)]
        else:
            # the isotropic profile and the smaller alpha's in one call, then the larger alpha's
            minor = a * np.stack([np.ones(S), POOL_SCALES], 1)
            c, _, _ = _lobe_costs(scanner, inp, np.concatenate([iso, minor]), settings)
            aniso = np.clip(a * np.array([1.0, pooled_scale(c[:, S:].numpy(), POOL_SCALES)]), ALPHA_MIN, ALPHA_MAX)
            profile = c[:, :S].numpy()
            widths = [mean * pooled_scale(profile, POOL_SCALES)]
            c, _, _ = _lobe_costs(scanner, inp, aniso * np.stack([POOL_SCALES, np.ones(S)], 1), settings)
            widths.append(aniso * np.array([pooled_scale(c.numpy(), POOL_SCALES), 1.0]))
        cand = -np.sort(-np.clip(widths, ALPHA_MIN, ALPHA_MAX), 1)  # alpha_x >= alpha_y
        c, rd, rs = _lobe_costs(scanner, inp, cand, settings)
        j = 0  # the isotropic lobe, unless the anisotropic one wins the vote
        if len(cand) == 2:
            # it pays only where it is anisotropic (its larger alpha may have pooled to the range's
            # end with the smaller: the knot's 0.5 metal): for the ratio once, and for each member's
            # own tangent in that member's vote (the gallery box's mirror lacquer, alpha
            # 0.006: its members' own lobes 0.028 x 0.006, elongated along one diagonal of their
            # texels; with the tangents unpaid their votes pooled it 0.0098 x 0.006, 43 against 149)
            anisotropic = cand[1, 0] >= ISOTROPIC_RATIO * cand[1, 1]
            paid = (ANISOTROPY_PARAMS - TANGENT_PARAMS, TANGENT_PARAMS) if anisotropic else (0, 0)
            j = int(second_wins(c.numpy(), *paid))
        alpha[k], rho_s[k] = cand[j], rs[:, j].median(0).values.numpy()
        lobe_rho_d[k] = rd[:, j].median(0).values.numpy()
        # an isotropic lobe's width may vary over the object (the members' profile says where)
        fields.append(
            width_field(profile, texels.position[ids], mean, POOL_SCALES) if j == 0 and texels is not None else None
        )
    return dataclasses.replace(basis, alpha=alpha, rho_s=rho_s, lobe_rho_d=lobe_rho_d, width=tuple(fields))


def _lobe_costs(
    scanner: Scanner, inp: RefineInputs, widths: np.ndarray, settings: RefineSettings
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``refine.lobe_costs`` of ``inp``'s texels under ``widths``: ``(W, 2)`` for all of them or
    ``(N, W, 2)`` each its own."""
    w = torch.as_tensor(widths)
    w = w.expand(len(inp.mask), -1, -1) if w.dim() == 2 else w
    return lobe_costs(scanner, inp.entries, inp.mask, inp.start, w, settings, inp.shadow, inp.support, inp.footprint)


def _widths_from_materials(
    scanner: Scanner,
    traces: RaggedTraces,
    fit: dict[str, np.ndarray],
    idx: np.ndarray,
    basis: BasisMaterials,
    settings: RefineSettings,
    texels: Texels | None,
    support: SupportScene | None,
    turn: np.ndarray | None = None,
) -> None:
    """Texels ``idx`` with a lobe of their own in a lobe material (``fit["material"]``) take its
    width where their trace explains it within ``WIDTH_PARAMS`` of their own (both with the
    texel's frame and albedos re-solved, ``refine.lobe_costs``): alphas the material's, rho_d and
    rho_s re-solved, flagged ``FLAG_WIDTH_FROM_MATERIAL``. ``turn (len(idx),)`` (radians, NaN:
    none): where the material's lobe is also tried turned so about the normal — an isotropic lobe
    of its own has no tangent to offer an anisotropic material's lobe (its neighbours' is the guess,
    ``_neighbour_turns``); the better of the two is kept, and its tangent with it. Updates ``fit``
    in place."""
    turn = np.full(len(idx), np.nan) if turn is None else turn
    for rows in np.array_split(np.arange(len(idx)), -(-len(idx) // REFINE_BATCH)) if len(idx) else []:
        k = idx[rows]
        inp = refine_inputs(scanner, traces, torch.as_tensor(k), fit, support, texels)
        position = None if texels is None else texels.position[k]
        alphas = np.stack([fit["alpha"][k], basis.alpha_at(fit["material"][k], position)], 1)  # (n, 2 candidates, 2)
        c, rd, rs = _lobe_costs(scanner, inp, alphas, settings)
        turned = np.nonzero(np.isfinite(turn[rows]))[0]
        angle = np.zeros(len(k))
        if len(turned):  # the material's lobe at the turned tangents
            sub = inp.rows(torch.as_tensor(turned))
            a = torch.as_tensor(turn[rows][turned], dtype=sub.start.tangent.dtype)[:, None]
            t, n = sub.start.tangent, sub.start.normal
            sub = sub._replace(start=sub.start._replace(tangent=a.cos() * t + a.sin() * torch.cross(n, t, dim=1)))
            c_t, rd_t, rs_t = _lobe_costs(scanner, sub, alphas[turned, 1:], settings)
            better = (c_t[:, 0] < c[turned, 1]).numpy()
            j = turned[better]
            c[j, 1], rd[j, 1], rs[j, 1] = c_t[better, 0], rd_t[better, 0], rs_t[better, 0]
            angle[j] = turn[rows][j]
        take = (c[:, 1] <= c[:, 0] + WIDTH_PARAMS).numpy()
        t = k[take]
        fit["alpha"][t] = alphas[take, 1]
        fit["rho_d"][t], fit["rho_s"][t] = rd[take, 1].numpy(), rs[take, 1].numpy()
        fit["flags"][t] |= FLAG_WIDTH_FROM_MATERIAL
        fit["t_loc"][t] = _turned(fit["t_loc"][t], fit["n_loc"][t], angle[take])


def _turned(t_loc: np.ndarray, n_loc: np.ndarray, turn: np.ndarray) -> np.ndarray:
    """Tangents ``t_loc (M, 3)`` turned by ``turn (M,)`` radians about their normals ``n_loc (M, 3)``
    (right-handed, as ``physics.frame.turned_about_normal``)."""
    return np.cos(turn)[:, None] * t_loc + np.sin(turn)[:, None] * np.cross(n_loc, t_loc)


def _store(fit: dict[str, np.ndarray], idx: torch.Tensor, r: Refined, marginal: torch.Tensor) -> None:
    i = idx.numpy()
    fit["n_loc"][i], fit["t_loc"][i] = r.frame[:, 2].numpy(), r.frame[:, 0].numpy()
    fit["alpha"][i] = r.log_alpha.exp().numpy()
    fit["rho_d"][i], fit["rho_s"][i] = r.rho_d.numpy(), r.rho_s.numpy()
    fit["flags"][i] = (fit["flags"][i] & ~REFINE_FLAGS) | r.flags.numpy() | marginal.numpy() * FLAG_MARGINAL
    fit["std"][i] = r.std.numpy()
    fit["highlight"][i] = r.highlight.numpy()


def _material_pass(
    scanner: Scanner,
    traces: RaggedTraces,
    fit: dict[str, np.ndarray],
    todo: torch.Tensor,
    settings: RefineSettings,
    progress: Progress,
    texels: Texels | None = None,
    support: SupportScene | None = None,
) -> None:
    """Basis materials from the first pass, assignment, and the texels that take a lobe from theirs
    refined toward it (``refine_fit``); updates ``fit`` in place."""
    N = traces.num_traces
    fit["material"] = np.full(N, -2, np.int64)
    i_obs = todo.numpy()
    own = np.zeros(N, bool)
    own[i_obs] = fit["flags"][i_obs] & FLAG_SPECULAR_UNCONSTRAINED == 0
    # the basis from lobes measured on clear entries: a lobe read through the mesh's shadows (or at
    # grazing angles) is coarser — on the knot's Cycles scan those moved the clusters enough to lose
    # the glossy plastic's lobe
    clear = own & (fit["flags"] & FLAG_MARGINAL == 0)
    rows = np.nonzero(clear)[0]
    basis, members = lobe_clusters(fit["rho_d"][rows], fit["alpha"][rows], fit["rho_s"][rows], fit["highlight"][rows])
    # the texels with a lobe of their own are labelled by colour (below): a cluster that holds none
    # of them is no material of its own, and its members join no pool
    basis, members = colour_held(basis, members, fit["rho_d"][own])
    basis = pooled_widths(scanner, traces, fit, rows, members, basis, settings, texels, support)
    if len(basis) == 0:  # too few texels kept a lobe to make a material of: all matte
        fit["material"][i_obs] = -1
        fit.update(basis.to_arrays())
        return
    # the texels without a lobe of their own: their traces judge no lobe and the lobe materials of
    # their colour and the broad ones, each with its rho_d re-solved; their colours under each weigh in
    # where the traces cannot tell (judged without the lobe, a broad lobe's texels looked matte:
    # the knot's rough metal, docs/accuracy.md)
    colour = colour_costs(fit["rho_d"][i_obs], basis)
    prior = colour - np.log(class_shares(basis))
    rest = np.nonzero(~own[i_obs])[0]
    costs = np.full((len(i_obs), 1 + len(basis)), np.inf)
    turns = np.zeros((len(i_obs), len(basis)))
    judged_rho_d = np.full((len(i_obs), 1 + len(basis), 3), np.nan)
    alpha, rho_s = torch.as_tensor(basis.alpha), torch.as_tensor(basis.rho_s)
    label = np.full(len(i_obs), -1)
    label[own[i_obs]] = np.argmin(prior[own[i_obs]], 1) - 1  # a texel with its own lobe: by its colour
    spacing = 0.0 if texels is None else texel_spacing(texels.position)  # once for the pass
    field = _neighbour_turns(texels, fit, i_obs, label, own[i_obs], rest, len(basis), spacing)
    bar = progress.counter("materials", len(rest), "texel")
    for k in np.array_split(np.arange(len(rest)), -(-len(rest) // REFINE_BATCH)) if len(rest) else []:
        inp = refine_inputs(scanner, traces, torch.as_tensor(i_obs[rest[k]]), fit, support, texels)
        maybe = torch.as_tensor(candidates(prior[rest[k]], basis))
        near = None if field is None else (torch.as_tensor(field[0][k]), torch.as_tensor(field[1][k]))
        c, t, rd = material_costs(
            scanner,
            inp.entries,
            inp.mask,
            inp.start,
            alpha,
            rho_s,
            maybe,
            settings,
            inp.shadow,
            near,
            inp.support,
            inp.footprint,
        )
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
    fit["material_matte_share"] = np.array(matte_share)
    shares = class_shares(basis, matte_share)
    prior = colour - np.log(shares)
    label[rest] = np.argmin(costs[rest] + prior[rest], 1) - 1  # -1: matte
    if texels is not None:  # then by each class's share where the texel lies (materials.local_shares)
        neighbours = label_neighbours(texels.position[i_obs])
        for _ in range(LABEL_ROUNDS):
            prior = colour - np.log(local_shares(neighbours, label, shares))
            label[rest] = np.argmin(costs[rest] + prior[rest], 1) - 1
    fit["material"][i_obs] = label
    fit.update(basis.to_arrays())
    fit["material_width_varies"] = np.array([f is not None for f in basis.width], bool)
    # own lobes in lobe materials: an isotropic one in an anisotropic material is also tried at the
    # turn its neighbours of the material point along
    with_own = np.nonzero(own[i_obs] & (label >= 0))[0]
    alpha_own, alpha_mat = fit["alpha"][i_obs[with_own]], basis.alpha[label[with_own]]
    ask = (alpha_own[:, 0] < ISOTROPIC_RATIO * alpha_own[:, 1]) & (alpha_mat[:, 0] >= ISOTROPIC_RATIO * alpha_mat[:, 1])
    turn = np.full(len(with_own), np.nan)
    around = _neighbour_turns(texels, fit, i_obs, label, own[i_obs], with_own[ask], len(basis), spacing)
    if around is not None:
        pick = np.arange(ask.sum()), label[with_own[ask]]
        turn[ask] = np.where(around[1][pick] > 0, around[0][pick], np.nan)  # agree 0: no neighbours
    _widths_from_materials(scanner, traces, fit, i_obs[with_own], basis, settings, texels, support, turn)
    # texels without a lobe of their own in a lobe material: toward its lobe
    takes = np.zeros(N, bool)
    takes[i_obs] = (label >= 0) & ~own[i_obs]
    if takes.any():
        _take_material_lobes(
            scanner, traces, fit, takes, turns, i_obs, label, basis, settings, progress, texels, support
        )
    _fuse_tangents(scanner, traces, fit, i_obs, label, settings, spacing, texels, support)


def _take_material_lobes(
    scanner: Scanner,
    traces: RaggedTraces,
    fit: dict[str, np.ndarray],
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
    fit["t_loc"][i_takes] = _turned(fit["t_loc"][i_takes], fit["n_loc"][i_takes], turn)
    sel = torch.as_tensor(np.nonzero(takes)[0])
    bar = progress.counter("material lobes", len(sel), "texel")
    for idx in sel.split(REFINE_BATCH):
        inp = refine_inputs(scanner, traces, idx, fit, support, texels)
        m = fit["material"][idx.numpy()]
        position = None if texels is None else texels.position[idx.numpy()]
        pull = LobePrior(
            torch.as_tensor(basis.alpha_at(m, position), dtype=torch.float32),
            torch.as_tensor(basis.rho_s[m], dtype=torch.float32),
            torch.as_tensor(basis.log_alpha_sigma[m], dtype=torch.float32),
            torch.as_tensor(basis.rho_s_sigma[m], dtype=torch.float32),
        )
        r = refine_toward(
            scanner, inp.entries, inp.mask, inp.start, pull, settings, inp.shadow, inp.support, inp.footprint
        )
        _store(fit, idx, r, inp.marginal)
        bar.update(len(idx))
    bar.close()


def _fuse_tangents(
    scanner: Scanner,
    traces: RaggedTraces,
    fit: dict[str, np.ndarray],
    i_obs: np.ndarray,
    label: np.ndarray,
    settings: RefineSettings,
    spacing: float,
    texels: Texels | None = None,
    support: SupportScene | None = None,
) -> None:
    """Every anisotropic lobe's tangent fused with its neighbours' of the same material that fixed
    theirs (``fit.tangent_field.fused_turns`` over the material's ``field_variation``) — a tangent
    its trace fixed stays, noise between neighbours is averaged — and ``std``'s tangent column the
    fused one. A texel that took its material's lobe (``FLAG_FROM_MATERIAL``) counts as knowing its
    tangent to ``TAKEN_TANGENT_STD`` (its trace chose among turns; the LM's local std there says
    where the lobe cannot point, not where it points) and is no source; it turns only where its
    photos do not object (``TURN_OBJECTION`` or more under its own lobe, ``fit.refine.turn_costs``)
    and where the field was seen on ``MIN_SOURCE_SHARE`` of the material's anisotropic texels or
    more. Needs ``texels`` (where the texels lie; ``spacing`` their ``texel_spacing``); updates
    ``fit`` in place (docs/refinement.md, basis materials step 6)."""
    if texels is None:
        return
    alpha, flags = fit["alpha"][i_obs], fit["flags"][i_obs]
    anisotropic = (label >= 0) & (alpha[:, 0] >= ISOTROPIC_RATIO * alpha[:, 1])
    taken = flags & FLAG_FROM_MATERIAL > 0
    std = np.where(taken, TAKEN_TANGENT_STD, np.radians(np.nan_to_num(fit["std"][i_obs, 1], nan=np.inf)))
    constrained = anisotropic & ~taken & (flags & FLAG_TANGENT_UNCONSTRAINED == 0) & (std <= MAX_SOURCE_STD)
    std_all = np.full(len(fit["std"]), np.inf)
    std_all[i_obs] = std
    turn, fused = np.zeros(len(i_obs)), std.copy()
    geometry = (texels.position, texels.normal, texels.tangent, fit["t_loc"], std_all)
    for m in np.unique(label[anisotropic]):
        target = np.nonzero(anisotropic & (label == m))[0]
        source = i_obs[constrained & (label == m)]
        variation = field_variation(*geometry, source, spacing)
        turn[target], fused[target] = fused_turns(*geometry, source, i_obs[target], variation)
        # a field seen on too few of the material's texels is not laid over the rest: their own
        # traces' turns stay (the blob's underside: 20 sources, 64 deg off, for 2,624 taken lobes)
        if len(source) < MIN_SOURCE_SHARE * len(target):
            t_taken = target[taken[target]]
            turn[t_taken], fused[t_taken] = 0.0, std[t_taken]
    # a taken lobe turns only where its photos do not object
    ask = np.nonzero(taken & anisotropic & (np.abs(turn) > MIN_TURN))[0]
    for k in np.array_split(ask, -(-len(ask) // REFINE_BATCH)) if len(ask) else []:
        inp = refine_inputs(scanner, traces, torch.as_tensor(i_obs[k]), fit, support, texels)
        turns = torch.stack([torch.zeros(len(k), dtype=torch.float64), torch.as_tensor(turn[k])], 1)
        c = turn_costs(
            scanner, inp.entries, inp.mask, inp.start, turns, settings, inp.shadow, inp.support, inp.footprint
        ).numpy()
        objects = c[:, 1] - c[:, 0] >= TURN_OBJECTION
        turn[k[objects]], fused[k[objects]] = 0.0, std[k[objects]]
    fit["t_loc"][i_obs] = _turned(fit["t_loc"][i_obs], fit["n_loc"][i_obs], turn)
    changed = anisotropic & np.isfinite(fused)
    fit["std"][i_obs[changed], 1] = np.degrees(fused[changed])
