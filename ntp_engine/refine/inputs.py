"""What the refinement reads for a set of texels (``refine_inputs``): each trace's entries (spread
evenly, clear ones first), its start from the network's fit, its shadows, the support's light and
the pixel footprints; the albedo blend near albedo edges (``with_albedo_blend``); the refinement's
per-texel flags and how an answer is stored into the result's per-texel arrays (``store_refined``).

Convention: per-trace arrays as ``pipeline.fit_traces`` (the texel's geometric frame); trace i is
texel i of the atlas.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import numpy as np
import torch

from ..fit.flags import TexelFlag
from ..fit.texel_fit import TexelFit
from ..io.progress import QUIET, Progress
from ..io.texels import Texels
from ..learn.ragged import RaggedTraces, spans, spread_rows
from ..physics.emitter_blocks import shadow_groups
from ..physics.frame import frame_from_normal_tangent
from ..physics.shadows import grazing, shadowed
from ..scanner.scanner import Scanner
from .footprint import Footprint, albedo_blend, sample_points, slope_spread
from .model import Observations, Start
from .policy import Refined
from .settings import TUNING
from .support_light import SupportScene, SupportView

# the bits the refinement sets (a texel refined again loses its previous ones)
REFINE_FLAGS = (
    TexelFlag.SPECULAR_UNCONSTRAINED
    | TexelFlag.TANGENT_UNCONSTRAINED
    | TexelFlag.FROM_MATERIAL
    | TexelFlag.MARGINAL
    | TexelFlag.WIDTH_FROM_MATERIAL
)


class RefineInputs(NamedTuple):
    """What the refinement reads for n texels (``refine_inputs``): their traces (``obs``, the
    problem every entry point of ``refine.policy`` takes), where each starts, which seek a lobe."""

    obs: Observations
    start: Start
    specular: torch.Tensor  # (n,) texels that seek a lobe
    marginal: torch.Tensor  # (n,) texels that read shadowed or grazing entries (``TUNING.inputs.min_clear_entries``)

    def rows(self, idx: torch.Tensor) -> RefineInputs:
        """The same for the texels ``idx`` (rows) only."""
        return RefineInputs(self.obs.rows(idx), self.start.rows(idx), self.specular[idx], self.marginal[idx])


def refine_inputs(
    scanner: Scanner,
    traces: RaggedTraces,
    idx: torch.Tensor,
    fit: TexelFit,
    support: SupportScene | None = None,
    texels: Texels | None = None,
) -> RefineInputs:
    """What ``refine.policy.refine`` takes for the texels ``idx`` of ``traces`` (linear pixels as
    captured: the camera model is the scanner's): their entries (``TUNING.inputs.refine_views`` spread over each
    trace), the start from ``fit``, which texels seek a lobe (those the highlight check did not
    flag). Marginal entries — the mesh shadows them (``traces.shadowed``) or sees them at grazing
    angles (``traces.grazing``) — are read only by texels with fewer than ``TUNING.inputs.min_clear_entries``
    others (``marginal``): their model is coarser (half emitter blocks hidden or not, no light the
    mesh reflects into its own shadows; a grazing pixel spans a strip of surface) — on the knot
    reading shadowed entries everywhere cost the Cycles scan's normals 0.3-0.7 deg, on the gallery
    grazing ones its relit SSIM (docs/history/accuracy.md). With ``support`` (and ``texels``, the atlas of
    the traces), the support's light on them; with ``texels``, the normals each entry's pixel sample
    spans where the surface turns (``refine.footprint``)."""
    rows, mask, marginal = _chosen_rows(scanner, traces, idx)
    i = idx.numpy()
    specular = torch.as_tensor(fit.flags[i] & TexelFlag.NO_HIGHLIGHT == 0)
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
    return RefineInputs(Observations(scanner, entries, mask, shadow, view, footprint), start, specular, marginal)


def _chosen_rows(scanner: Scanner, traces: RaggedTraces, idx: torch.Tensor) -> tuple[torch.Tensor, ...]:
    """The table rows ``(n, V)`` of the entries the refinement reads of the traces ``idx``
    (``refine_inputs``), their mask, and which texels read a marginal one ``(n,)``."""
    groups = shadow_groups(scanner)
    rows, mask = traces.padded_rows(idx)  # every entry of each trace
    marginal_entry = mask & (shadowed(groups, traces.shadow_at(rows, mask)) | grazing(traces.entries_at(rows, mask)))
    clear = mask & ~marginal_entry
    few = clear.sum(1) < TUNING.inputs.min_clear_entries
    rows, mask = spread_rows(rows, torch.where(few[:, None], mask, clear), TUNING.inputs.refine_views)
    read_marginal = (marginal_entry.gather(1, (rows - traces.offsets[idx][:, None]).clamp_min(0)) & mask).any(1)
    return rows, mask, few & read_marginal


def read_traces(scanner: Scanner, traces: RaggedTraces, progress: Progress = QUIET) -> RaggedTraces:
    """The entries the refinement reads of every trace (``refine_inputs``' choice: at most
    ``TUNING.inputs.refine_views``, spread evenly, clear ones first) as a table of their own, every
    column carried; ``refine_inputs`` on it reads the same entries. Chosen once, in blocks of
    ~``TUNING.inputs.blend_entries`` entries: every later pass reads ~``refine_views`` entries a
    texel, not the whole trace (~400 at 1,000 photos)."""
    parts: list[torch.Tensor] = []
    lengths = torch.zeros(traces.num_traces, dtype=torch.int64)
    # over the traces with entries alone, ~blend_entries at a time: a table of a sample (most traces
    # empty, ``RaggedTraces.only``) would otherwise pad every trace of a block to its longest
    seen = (traces.lengths > 0).nonzero().squeeze(1)
    counted = np.zeros(len(seen) + 1, np.int64)
    counted[1:] = np.cumsum(traces.lengths[seen].numpy())
    with progress.counter("entries read", len(seen), "texel") as bar:
        for start, stop in spans(counted, TUNING.inputs.blend_entries):
            rows, mask, _ = _chosen_rows(scanner, traces, seen[start:stop])
            parts.append(rows[mask])  # trace by trace, in trace order
            lengths[seen[start:stop]] = mask.sum(1)
            bar.update(stop - start)
    return traces.taking(torch.cat(parts) if parts else torch.zeros(0, dtype=torch.int64), lengths)


def with_albedo_blend(
    scanner: Scanner, traces: RaggedTraces, rho_d: np.ndarray, texels: Texels, progress: Progress = QUIET
) -> RaggedTraces:
    """``traces`` (trace i = texel i of ``texels``, which need ``uv_per_metre``) with each entry's
    ``albedo_blend``: how much of its neighbours' albedo its pixel sample may blend in
    (``refine.footprint.albedo_blend``), read from the map of ``rho_d (N, 3)``; texels no trace reached
    take the nearest observed one's. In blocks of ~``TUNING.inputs.blend_entries`` entries."""
    assert texels.uv_per_metre is not None
    albedo = texels.image(rho_d, known=(traces.lengths > 0).numpy())
    uv = texels.uv
    out = torch.zeros(len(traces.entries), 3, dtype=torch.float32)
    with progress.counter("albedo blend", traces.num_traces, "texel") as bar:
        for start, stop in spans(traces.offsets.numpy(), TUNING.inputs.blend_entries):
            b = traces.block(start, stop)
            texel = torch.repeat_interleave(torch.arange(start, stop), b.lengths).numpy()
            entries = b.entries[:, None, :]
            delta, weight = sample_points(scanner, entries, torch.ones(len(entries), 1, dtype=torch.bool))
            blend = albedo_blend(delta, weight, uv[texel], texels.uv_per_metre[texel], albedo)
            a = int(traces.offsets[start])
            out[a : a + len(entries)] = blend[:, 0].to(torch.float32)
            bar.update(stop - start)
    return dataclasses.replace(traces, albedo_blend=out)


def turned_tangents(t_loc: np.ndarray, n_loc: np.ndarray, turn: np.ndarray) -> np.ndarray:
    """Tangents ``t_loc (M, 3)`` turned by ``turn (M,)`` radians about their normals ``n_loc (M, 3)``
    (right-handed, as ``physics.frame.turned_about_normal``)."""
    return np.cos(turn)[:, None] * t_loc + np.sin(turn)[:, None] * np.cross(n_loc, t_loc)


def store_refined(fit: TexelFit, idx: torch.Tensor, r: Refined, marginal: torch.Tensor) -> None:
    """The answers ``r`` of the texels ``idx`` written into ``fit``'s per-texel arrays, their flags
    replacing the refinement's own (``REFINE_FLAGS``), ``TexelFlag.MARGINAL`` where ``marginal``."""
    assert fit.std is not None and fit.highlight is not None  # refine_fit adds them before any pass
    i = idx.numpy()
    fit.n_loc[i], fit.t_loc[i] = r.frame[:, 2].numpy(), r.frame[:, 0].numpy()
    fit.alpha[i] = r.log_alpha.exp().numpy()
    fit.rho_d[i], fit.rho_s[i] = r.rho_d.numpy(), r.rho_s.numpy()
    fit.flags[i] = (fit.flags[i] & ~int(REFINE_FLAGS)) | r.flags.numpy() | marginal.numpy() * TexelFlag.MARGINAL
    fit.std[i] = r.std.numpy()
    fit.highlight[i] = r.highlight.numpy()
