"""The fit stage: every trace through the network, then the geometry fit, the highlight check and
the RGB albedo (paper §6-7), in bounded batches.

Convention: traces hold linear pixels scaled to the model's exposure (``pixel_scale``; undone for
the physical albedo). Results are per trace, in the texel's geometric frame (n^, t^ as the
lumitexel's z and x): n_loc, t_loc (N, 3), alpha (N, 2) = (alpha_x, alpha_y), flags (N,), rho_d,
rho_s (N, 3). Traces with no entry keep the defaults (+z, +x, FALLBACK_ALPHA, zeros).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import torch

from ..fit.albedo import highlights_and_albedo
from ..fit.geometry import FALLBACK_ALPHA, FLAG_NO_HIGHLIGHT, fit_geometry
from ..fit.refine import RefineSettings, Start, calibrated_noise, refine
from ..io.progress import QUIET, Progress
from ..learn.inference import predict
from ..learn.network import TraceNet
from ..learn.ragged import RaggedTraces
from ..scanner.scanner import Scanner

ALBEDO_VIEWS = 16  # entries per texel for the beta check and the albedo LS (Eq. 1 per entry and emitter)
RHO_S_PRIOR_WEIGHT = 1.0  # the network's rho_s counts as one view in the albedo LS (fit._albedo_ls)
REFINE_VIEWS = 24  # entries per texel the refinement reads (spread evenly over the trace)
CALIBRATION_TEXELS = 512  # texels refined first to calibrate the noise model (fit.refine.calibrated_noise)
REFINE_BATCH = 512  # texels per refinement batch: (batch, views, emitters) tensors stay ~100 MB


def fit_traces(
    net: TraceNet,
    scanner: Scanner,
    traces: RaggedTraces,
    pixel_scale: float,
    batch: int = 4096,
    progress: Progress = QUIET,
) -> dict[str, np.ndarray]:
    """Network + geometry fit + RGB albedo per trace (the refinement's start, ``refine_fit``).
    ``pixel_scale`` is the factor the traces' linear pixels were scaled by to the model's exposure
    (undone for the physical albedo LS). Reads the in-range entries only. Returns per-trace arrays in
    the texel's geometric frame: n_loc, t_loc (N, 3), alpha (N, 2), flags (N,), rho_d, rho_s (N, 3)."""
    traces = traces.in_range_only()
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


def refine_inputs(
    traces: RaggedTraces, idx: torch.Tensor, pixel_scale: float, fit: dict[str, np.ndarray]
) -> tuple[torch.Tensor, torch.Tensor, Start, torch.Tensor]:
    """What ``fit.refine.refine`` takes for the texels ``idx``: their entries (``REFINE_VIEWS``
    spread over each trace, pixels as captured: the camera model is the scanner's), the mask, the
    start from ``fit`` and which texels seek a lobe (those the highlight check did not flag)."""
    ent, mask = traces.padded(idx, max_views=REFINE_VIEWS)
    ent[..., :3] /= pixel_scale
    i = idx.numpy()
    return ent, mask, Start.from_fit(fit, i), torch.as_tensor(fit["flags"][i] & FLAG_NO_HIGHLIGHT == 0)


def refine_fit(
    scanner: Scanner,
    traces: RaggedTraces,
    pixel_scale: float,
    fit: dict[str, np.ndarray],
    settings: RefineSettings | None = None,
    progress: Progress = QUIET,
) -> dict[str, np.ndarray]:
    """``fit_traces``'s result refined by analysis-by-synthesis (``fit.refine``) against every entry
    of every observed trace, dark and clipped ones included; adds ``std (N, 4)``, the 1-sigma
    uncertainties of normal (deg), tangent (deg), log alpha, log rho_s (NaN where no trace reached),
    and ``noise_scale`` (the noise model's calibration factor, from a first pass over a sample).
    Texels the network never saw (all entries out of range) start from the fallback lobe."""
    fit = {k: v.copy() for k, v in fit.items()}
    todo = (traces.lengths > 0).nonzero().squeeze(1)
    settings = settings or RefineSettings()
    if len(todo):  # the noise model, calibrated on a seeded sample of the texels
        gen = torch.Generator().manual_seed(0)
        sample = todo[torch.randperm(len(todo), generator=gen)[:CALIBRATION_TEXELS]].sort().values
        noise = calibrated_noise(scanner, *refine_inputs(traces, sample, pixel_scale, fit), settings)
        settings = dataclasses.replace(settings, noise=noise)
        fit["noise_scale"] = np.array(noise.relative / RefineSettings().noise.relative)
    std = np.full((traces.num_traces, 4), np.nan)
    bar = progress.counter("refine", len(todo), "texel")
    for a in range(0, len(todo), REFINE_BATCH):
        idx = todo[a : a + REFINE_BATCH]
        i = idx.numpy()
        r = refine(scanner, *refine_inputs(traces, idx, pixel_scale, fit), settings)
        fit["n_loc"][i], fit["t_loc"][i] = r.frame[:, 2].numpy(), r.frame[:, 0].numpy()
        fit["alpha"][i] = r.log_alpha.exp().numpy()
        fit["rho_d"][i], fit["rho_s"][i] = r.rho_d.numpy(), r.rho_s.numpy()
        fit["flags"][i] |= r.flags.numpy()
        std[i] = r.std.numpy()
        bar.update(len(idx))
    bar.close()
    fit["std"] = std
    return fit
