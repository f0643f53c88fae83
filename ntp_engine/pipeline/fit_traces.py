"""The fit stage: every trace through the network, then the geometry fit, the highlight check and
the RGB albedo (paper §6-7), in bounded batches.

Convention: traces hold linear pixels scaled to the model's exposure (``pixel_scale``; undone for
the physical albedo). Results are per trace, in the texel's geometric frame (n^, t^ as the
lumitexel's z and x): n_loc, t_loc (N, 3), alpha (N, 2) = (alpha_x, alpha_y), flags (N,), rho_d,
rho_s (N, 3). Traces with no entry keep the defaults (+z, +x, FALLBACK_ALPHA, zeros).
"""

from __future__ import annotations

import numpy as np

from ..fit.albedo import highlights_and_albedo
from ..fit.geometry import FALLBACK_ALPHA, fit_geometry
from ..io.progress import QUIET, Progress
from ..learn.inference import predict
from ..learn.network import TraceNet
from ..learn.ragged import RaggedTraces
from ..scanner.scanner import Scanner

ALBEDO_VIEWS = 16  # entries per texel for the beta check and the albedo LS (Eq. 1 per entry and emitter)
RHO_S_PRIOR_WEIGHT = 1.0  # the network's rho_s counts as one view in the albedo LS (fit._albedo_ls)


def fit_traces(
    net: TraceNet,
    scanner: Scanner,
    traces: RaggedTraces,
    pixel_scale: float,
    batch: int = 4096,
    progress: Progress = QUIET,
) -> dict[str, np.ndarray]:
    """Network + geometry fit + RGB albedo per trace. ``pixel_scale`` is the factor the traces' linear
    pixels were scaled by to the model's exposure (undone for the physical albedo LS). Returns per-trace arrays in the
    texel's geometric frame: n_loc, t_loc (N, 3), alpha (N, 2), flags (N,), rho_d, rho_s (N, 3)."""
    N = traces.num_traces
    n_loc, t_loc = np.zeros((N, 3)), np.zeros((N, 3))
    n_loc[:, 2], t_loc[:, 0] = 1.0, 1.0
    ax, ay, flags = np.full(N, FALLBACK_ALPHA), np.full(N, FALLBACK_ALPHA), np.zeros(N, np.int64)
    rho_d, rho_s = np.zeros((N, 3)), np.zeros((N, 3))
    observed = int((traces.lengths > 0).sum())
    bar = progress.counter("network + fit", observed, "texel")
    for idx, d, s in predict(net, traces, max_entries=batch * 32):
        keep = traces.lengths[idx] > 0
        idx, d, s = idx[keep], d[keep], s[keep]
        if len(idx) == 0:
            continue
        g = fit_geometry(s, d)
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
    bar.close()
    return {
        "n_loc": n_loc,
        "t_loc": t_loc,
        "alpha": np.stack([ax, ay], 1),
        "flags": flags,
        "rho_d": rho_d,
        "rho_s": rho_s,
    }
