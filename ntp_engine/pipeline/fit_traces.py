"""The fit stage: every trace through the network, then the geometry fit, the highlight check and
the RGB albedo (paper §6-7), in blocks of ``TUNING.fit.fit_block`` texels — the unit of work, run one after
the other in this process or as Ray tasks (``pipeline.task_pool``), with the same result. The refinement
against the photos that may follow is ``refine.passes.refine_fit``.

Convention: the table holds linear pixels as captured; ``fit_blocks`` scales each block's pixels to
the model's exposure (``pixel_scale``) before ``fit_traces``, which undoes it for the physical
albedo. Results are per trace, in the texel's geometric frame (n^, t^ as the lumitexel's z and x):
n_loc, t_loc (N, 3), alpha (N, 2) = (alpha_x, alpha_y), flags (N,), rho_d, rho_s (N, 3). Traces
with no entry keep the defaults (+z, +x, FALLBACK_ALPHA, zeros).
"""

from __future__ import annotations

import time

import numpy as np

from ..fit.albedo import highlights_and_albedo
from ..fit.geometry import fit_geometry
from ..fit.texel_fit import TexelFit
from ..io.progress import QUIET, Progress
from ..learn.inference import predict
from ..learn.network import TraceNet
from ..learn.ragged import RaggedTraces
from ..scanner.scanner import Scanner
from .settings import TUNING
from .task_pool import LocalPool, TaskPool


def fit_blocks(
    net: TraceNet,
    scanner: Scanner,
    traces: RaggedTraces,
    pixel_scale: float,
    pool: TaskPool | None = None,
    progress: Progress = QUIET,
) -> TexelFit:
    """``fit_traces`` over ``traces`` (linear pixels as captured; may be memory-mapped) block by
    block on ``pool`` (default: this process); each block's pixels are scaled by ``pixel_scale`` on
    its own copy. The same arrays as ``fit_traces`` on the whole table, bit for bit whichever pool."""
    N = traces.num_traces
    starts = range(0, N, TUNING.fit.fit_block)
    blocks = (_own_block(traces, a, min(a + TUNING.fit.fit_block, N)) for a in starts)
    observed = int((traces.lengths > 0).sum())
    bar = progress.counter("network + fit", observed, "texel")
    out: dict[str, np.ndarray] = {}
    for b, part in (pool or LocalPool()).map(_fit_block, blocks, shared=(net, scanner, pixel_scale)):
        arrays = part.arrays()
        if not out:
            out = {k: np.zeros((N, *v.shape[1:]), v.dtype) for k, v in arrays.items()}
        a = starts[b]
        for k, v in arrays.items():
            out[k][a : a + len(v)] = v
        bar.update(int((traces.lengths[a : a + TUNING.fit.fit_block] > 0).sum()))
    bar.close()
    # no trace at all: the empty arrays
    return TexelFit.from_arrays(out) if out else fit_traces(net, scanner, traces, pixel_scale)


def _own_block(traces: RaggedTraces, start: int, stop: int) -> RaggedTraces:
    """Traces ``start:stop`` with their in-range entries only (all ``fit_traces`` reads) as a
    contiguous copy: pickled for a Ray task, a view would carry the whole table's storage along, and
    the fit scales the copy's pixels in place. One copy, not a copy and then the in-range one."""
    b = traces.block(start, stop)
    return RaggedTraces(b.entries.clone(), b.offsets.clone()) if b.in_range is None else b.in_range_only()


def _fit_block(block: RaggedTraces, net: TraceNet, scanner: Scanner, pixel_scale: float) -> TexelFit:
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
) -> TexelFit:
    """Network + geometry fit + RGB albedo per trace (the refinement's start, ``refine_fit``).
    ``pixel_scale`` is the factor the traces' linear pixels were scaled by to the model's exposure
    (undone for the physical albedo LS). Reads the in-range entries only. Returns per-trace arrays in
    the texel's geometric frame: n_loc, t_loc (N, 3), alpha (N, 2), flags (N,), rho_d, rho_s (N, 3).
    ``seconds``, if given, receives the wall time of each part: network, geometry, albedo
    (``ntp bench fit`` reports them)."""
    clock = {"network": 0.0, "geometry": 0.0, "albedo": 0.0}
    traces = traces.in_range_only()
    N = traces.num_traces
    out = TexelFit.defaults(N)  # what a trace with no entry keeps
    observed = int((traces.lengths > 0).sum())
    bar = progress.counter("network + fit", observed, "texel")
    t0 = time.perf_counter()
    for idx, d, s in predict(net, traces, max_entries=batch * 32, max_views=TUNING.fit.network_views):
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
        out.n_loc[i], out.t_loc[i] = g.normal.numpy(), g.tangent.numpy()
        out.alpha[i, 0], out.alpha[i, 1], out.flags[i] = g.alpha_x.numpy(), g.alpha_y.numpy(), g.flags.numpy()
        for a in range(0, len(idx), 256):  # (n, V, L) Eq. 1 terms: keep them cache-sized
            sub = slice(a, a + 256)
            ent, mask = traces.padded(idx[sub], max_views=TUNING.fit.albedo_views)
            gs = g.rows(sub)
            _, rd, rs = highlights_and_albedo(
                scanner,
                ent[..., :3] / pixel_scale,
                ent[..., 3:6],
                ent[..., 6:9],
                ent[..., 9:12],
                mask,
                gs,
                prior_weight=TUNING.fit.rho_s_prior_weight,
            )
            out.rho_d[i[sub]], out.rho_s[i[sub]] = rd.numpy(), rs.numpy()
            out.alpha[i[sub], 0], out.alpha[i[sub], 1] = gs.alpha_x.numpy(), gs.alpha_y.numpy()
            out.flags[i[sub]] = gs.flags.numpy()
        bar.update(len(idx))
        t0 = time.perf_counter()
        clock["albedo"] += t0 - t2
    bar.close()
    if seconds is not None:
        seconds.update(clock)
    return out
