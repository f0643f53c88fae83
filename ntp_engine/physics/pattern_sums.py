"""Eq. 1 summed over every emitter under the pattern, per measurement, in one fused pass.

The fit needs, for every entry of a trace (a point seen in one view), what a unit diffuse and a unit
specular surface with the fitted lobe would show the camera under the scanner's pattern, and how
bright the lobe gets toward any emitter and at its peak (Eq. 6). Evaluated tensor by tensor this
builds a dozen ``(M, K)`` temporaries per entry and emitter sample and is memory-bound; here one
compiled loop (numba, parallel over entries) walks the K samples once per entry, keeping nothing but
the sums. ``measurement.terms_from_lobe``/``specular_lobe`` and ``confidence.specular_peak`` are the
reference the tests hold it to.

Convention: as ``measurement`` — camera space (OpenCV, metres), the camera at the origin,
``x, n, t (M, 3)`` each entry's point and *shading* frame (t is orthogonalised against n), alphas
``(M,)``; emitter samples and Psi from the scanner. Accumulated in float64. Entries outside
``mask`` get zeros (their values are never read).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numba
import numpy as np
import torch
from torch import Tensor

from ..io.thread_pools import numba_threads_as_torch
from ..scanner.scanner import Scanner
from .brdf import F0_DIELECTRIC
from .confidence import PEAK_GRID
from .frame import frame_from_normal_tangent


@dataclass
class PatternSums:
    """Per entry ``(M,)`` / ``(M, 3)``, float64."""

    diffuse: Tensor  # (M, 3) sum_k drive_k,c A_k: pixel / exposure of rho_d = pi (see fit.albedo)
    specular: Tensor  # (M, 3) sum_k drive_k,c S_k: pixel / exposure of rho_s = 1
    lobe_max: Tensor  # (M,) max_k of the rho_s = 1 lobe toward emitter sample k
    lobe_peak: Tensor  # (M,) its maximum over all directions (confidence.specular_peak)


def pattern_sums(
    scanner: Scanner,
    x: Tensor,
    n: Tensor,
    t: Tensor,
    alpha_x: Tensor,
    alpha_y: Tensor,
    mask: Tensor,
    f0: float = F0_DIELECTRIC,
) -> PatternSums:
    """The sums of the module docstring for entries ``x, n, t (M, 3)``, alphas and ``mask (M,)``;
    ``lobe_peak`` as ``specular_peak`` (the same grid of half vectors)."""
    frame = frame_from_normal_tangent(n.double(), t.double()).numpy()
    geo = _emitters(scanner)
    M = len(x)
    out = np.zeros((M, 8))
    with numba_threads_as_torch():  # as --threads says
        _pattern_sums_loop(
            np.ascontiguousarray(x.double().numpy()),
            np.ascontiguousarray(frame),
            np.ascontiguousarray(alpha_x.double().numpy()),
            np.ascontiguousarray(alpha_y.double().numpy()),
            np.ascontiguousarray(mask.numpy().astype(np.bool_)),
            *geo,
            PEAK_GRID.numpy(),
            float(f0),
            out,
        )
    o = torch.from_numpy(out)
    return PatternSums(o[:, 0:3], o[:, 3:6], o[:, 6], o[:, 7])


def _emitters(scanner: Scanner) -> tuple[np.ndarray, np.ndarray, np.ndarray, float, np.ndarray, np.ndarray]:
    """Samples ``(K, 3)``, their emitters' normals ``(K, 3)``, drive per camera channel times the
    quadrature weight ``(K, 3)``, and Psi as (exponent, table angles in degrees, table values):
    exponent >= 0 for a cosine power, -1 for the table."""
    pts, wq = scanner.emitter_samples(torch.float64)
    L, Q = wq.shape
    drive = np.repeat(scanner.effective_pattern(), Q, axis=0) * wq.reshape(-1, 1).numpy()
    normals = np.repeat(np.asarray(scanner.emitter_normals, np.float64), Q, axis=0)
    if scanner.angular_kind == "cosine":
        exponent, table = float(scanner.angular_exponent), np.zeros((2, 2))
    else:
        exponent, table = -1.0, np.asarray(scanner.angular_table, np.float64)
    return (
        np.ascontiguousarray(pts.reshape(L * Q, 3).numpy()),
        np.ascontiguousarray(normals),
        np.ascontiguousarray(drive),
        exponent,
        np.ascontiguousarray(table[:, 0]),
        np.ascontiguousarray(table[:, 1]),
    )


# ---------------------------------------------------------------- the compiled loop (numba; cached on disk)
@numba.njit(inline="always", fastmath=True, cache=True)
def _lobe(ix, iy, iz, ox, oy, oz, ax, ay, lo, f0):  # pragma: no cover - compiled
    """brdf.ggx_specular for unit local wi, wo; ``lo`` = wo_z+ + |(ax ox, ay oy, oz)|."""
    if iz <= 0.0 or oz <= 0.0:
        return 0.0
    hx, hy, hz = ix + ox, iy + oy, iz + oz
    h2 = hx * hx + hy * hy + hz * hz
    q = (hx / ax) ** 2 + (hy / ay) ** 2 + hz * hz  # |h|^2 times the unit h's quadratic form
    d = (h2 / q) ** 2 / (math.pi * ax * ay)
    c = min(max(0.5 * math.sqrt(h2), 0.0), 1.0)  # wi . h^ = |wi + wo| / 2 for unit wi, wo
    m = 1.0 - c
    f = f0 + (1.0 - f0) * (m * m) * (m * m) * m
    li = math.sqrt(max((ax * ix) ** 2 + (ay * iy) ** 2 + iz * iz, 1e-20))
    return d * f / ((iz + li) * lo)


@numba.njit(parallel=True, fastmath=True, cache=True)
def _pattern_sums_loop(
    x, frame, alpha_x, alpha_y, mask, pts, normals, drive, exponent, tab_a, tab_v, grid, f0, out
):  # pragma: no cover
    """Fills ``out (M, 8)``: diffuse sums (3), specular sums (3), lobe max, lobe peak (see the caller)."""
    M, K, G = x.shape[0], pts.shape[0], grid.shape[0]
    for m in numba.prange(M):
        if not mask[m]:
            continue
        x0, x1, x2 = x[m, 0], x[m, 1], x[m, 2]
        ax, ay = alpha_x[m], alpha_y[m]
        # wo = -x / |x| in the local frame (rows t, b, n)
        r = math.sqrt(x0 * x0 + x1 * x1 + x2 * x2)
        ox = -(frame[m, 0, 0] * x0 + frame[m, 0, 1] * x1 + frame[m, 0, 2] * x2) / r
        oy = -(frame[m, 1, 0] * x0 + frame[m, 1, 1] * x1 + frame[m, 1, 2] * x2) / r
        oz = -(frame[m, 2, 0] * x0 + frame[m, 2, 1] * x1 + frame[m, 2, 2] * x2) / r
        lo = max(oz, 0.0) + math.sqrt(max((ax * ox) ** 2 + (ay * oy) ** 2 + oz * oz, 1e-20))
        d0 = d1 = d2 = s0 = s1 = s2 = 0.0
        top = 0.0
        for k in range(K):
            dx, dy, dz = pts[k, 0] - x0, pts[k, 1] - x1, pts[k, 2] - x2
            r2 = max(dx * dx + dy * dy + dz * dz, 1e-12)
            inv = 1.0 / math.sqrt(r2)
            iz = (frame[m, 2, 0] * dx + frame[m, 2, 1] * dy + frame[m, 2, 2] * dz) * inv
            if iz <= 0.0 or oz <= 0.0:
                continue  # below the horizon: no light reaches, no lobe
            ix = (frame[m, 0, 0] * dx + frame[m, 0, 1] * dy + frame[m, 0, 2] * dz) * inv
            iy = (frame[m, 1, 0] * dx + frame[m, 1, 1] * dy + frame[m, 1, 2] * dz) * inv
            s = _lobe(ix, iy, iz, ox, oy, oz, ax, ay, lo, f0)
            top = max(top, s)  # Eq. 6 asks how bright the lobe gets toward a sample, lit or not
            cos_l = -(dx * normals[k, 0] + dy * normals[k, 1] + dz * normals[k, 2]) * inv
            if cos_l <= 0.0:
                continue  # behind the emitter: Psi = 0
            c = min(cos_l, 1.0)
            if exponent == 1.0:
                psi = c
            elif exponent >= 0.0:
                psi = c**exponent
            else:  # tabulated Psi(angle in degrees), linear between entries, 0 past the last
                ang = math.degrees(math.acos(c))
                if ang > tab_a[-1]:
                    continue
                j = min(max(int(np.searchsorted(tab_a, ang)), 1), len(tab_a) - 1)
                w = min(max((ang - tab_a[j - 1]) / (tab_a[j] - tab_a[j - 1]), 0.0), 1.0)
                psi = tab_v[j - 1] + w * (tab_v[j] - tab_v[j - 1])
            a = psi / r2 * iz
            d0 += a * drive[k, 0]
            d1 += a * drive[k, 1]
            d2 += a * drive[k, 2]
            s0 += a * s * drive[k, 0]
            s1 += a * s * drive[k, 1]
            s2 += a * s * drive[k, 2]
        # the lobe's peak: confidence.specular_peak's grid of half vectors (ax u, ay v, 1)
        peak = 0.0
        if oz > 0.0:
            for gu in range(G):
                for gv in range(G):
                    hx, hy = ax * grid[gu], ay * grid[gv]
                    hn = 1.0 / math.sqrt(hx * hx + hy * hy + 1.0)
                    hx, hy, hz = hx * hn, hy * hn, hn
                    dot = 2.0 * (ox * hx + oy * hy + oz * hz)
                    peak = max(peak, _lobe(dot * hx - ox, dot * hy - oy, dot * hz - oz, ox, oy, oz, ax, ay, lo, f0))
        out[m, 0], out[m, 1], out[m, 2] = d0, d1, d2
        out[m, 3], out[m, 4], out[m, 5] = s0, s1, s2
        out[m, 6], out[m, 7] = top, peak
