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
from typing import NamedTuple

import numba
import numpy as np
import torch
from torch import Tensor

from ..io.jit import compiled
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
    visibility: np.ndarray | None = None,
    peaks: bool = True,
) -> PatternSums:
    """The sums of the module docstring for entries ``x, n, t (M, 3)``, alphas and ``mask (M,)``;
    ``lobe_peak`` as ``specular_peak`` (the same grid of half vectors). ``visibility (M, K)``: the
    V of Eq. 1 per entry and emitter sample (0/1 or a fraction; default all seen) — it weighs both
    sums, not ``lobe_max``, which asks how bright the lobe gets toward a sample, lit or not.
    ``peaks`` False: ``lobe_max`` and ``lobe_peak`` are not computed (zeros; a renderer needs
    only the sums, and the peak's grid is a fifth of the work)."""
    frame = frame_from_normal_tangent(n.double(), t.double()).numpy()
    e = emitter_arrays(scanner)
    M = len(x)
    K = e.points.shape[1]
    if visibility is None:
        vis = np.ones((1, K))
    else:
        vis = np.ascontiguousarray(visibility, dtype=np.float64)
        if vis.shape != (M, K):
            raise ValueError(f"visibility is {vis.shape}, not (entries, emitter samples) = {(M, K)}")
    out = np.zeros((M, 8))
    with numba_threads_as_torch():  # as --threads says
        _pattern_sums_loop(
            np.ascontiguousarray(x.double().numpy()),
            np.ascontiguousarray(frame),
            np.ascontiguousarray(alpha_x.double().numpy()),
            np.ascontiguousarray(alpha_y.double().numpy()),
            np.ascontiguousarray(mask.numpy().astype(np.bool_)),
            e.points,
            e.normals,
            e.drive,
            e.exponent,
            e.table_angles,
            e.table_values,
            PEAK_GRID.numpy(),
            float(f0),
            vis,
            bool(peaks),
            out,
        )
    o = torch.from_numpy(out)
    return PatternSums(o[:, 0:3], o[:, 3:6], o[:, 6], o[:, 7])


class EmitterArrays(NamedTuple):
    """A scanner's K emitter samples as the compiled loops read them: rows of ``(3, K)`` arrays (each
    a contiguous vector), and Psi as ``exponent`` (>= 0: a cosine power; -1: the table)."""

    points: np.ndarray  # (3, K) camera space, m
    normals: np.ndarray  # (3, K) their emitters' unit normals
    weights: np.ndarray  # (K,) quadrature weights
    drive: np.ndarray  # (3, K) effective drive per camera channel times the weight
    exponent: float
    table_angles: np.ndarray  # (T,) degrees (the table's; unused for a power)
    table_values: np.ndarray  # (T,)


def emitter_arrays(scanner: Scanner) -> EmitterArrays:
    """``scanner``'s emitter samples as ``EmitterArrays`` (float64)."""
    pts, wq = scanner.emitter_samples(torch.float64)
    L, Q = wq.shape
    w = wq.reshape(-1).numpy()
    drive = np.repeat(scanner.effective_pattern(), Q, axis=0) * w[:, None]
    normals = np.repeat(np.asarray(scanner.emitter_normals, np.float64), Q, axis=0)
    if scanner.angular_kind == "cosine":
        exponent, table = float(scanner.angular_exponent), np.zeros((2, 2))
    else:
        exponent, table = -1.0, np.asarray(scanner.angular_table, np.float64)
    return EmitterArrays(
        np.ascontiguousarray(pts.reshape(L * Q, 3).numpy().T),
        np.ascontiguousarray(normals.T),
        np.ascontiguousarray(w),
        np.ascontiguousarray(drive.T),
        exponent,
        np.ascontiguousarray(table[:, 0]),
        np.ascontiguousarray(table[:, 1]),
    )


@compiled(inline="always")
def _psi_of_cosine(c, exponent, tab_a, tab_v):  # pragma: no cover - compiled
    """``Scanner.psi`` for one cosine ``c`` already clamped to [0, 1] (``EmitterArrays``' Psi):
    0 behind the emitter (c = 0) for every kind, also a power's 0^0 and a table reaching 90 deg."""
    if c <= 0.0:
        return 0.0
    if exponent >= 0.0:
        return c if exponent == 1.0 else c**exponent
    ang = math.degrees(math.acos(c))  # tabulated Psi(angle in degrees), linear between, 0 past the last
    if ang > tab_a[-1]:
        return 0.0
    j = min(max(int(np.searchsorted(tab_a, ang)), 1), len(tab_a) - 1)
    w = min(max((ang - tab_a[j - 1]) / (tab_a[j] - tab_a[j - 1]), 0.0), 1.0)
    return tab_v[j - 1] + w * (tab_v[j] - tab_v[j - 1])


# ---------------------------------------------------------------- the compiled loop (numba; cached on disk)
# Written for LLVM to vectorise the loops over the K emitter samples (AVX: 4-8 samples at once):
# no branch in their bodies (a sample below the horizon is multiplied by 0, not skipped), samples
# as structure-of-arrays, and the two reductions that do not vectorise in one pass — the lobe's
# maximum and Psi from a table or a power — done over per-entry buffers after it. 2-3x the speed
# of the branchy loop it replaced (docs/performance.md, "Emitter sums").
@compiled(inline="always", fastmath=True)
def _lobe_above(ix, iy, iz, ox, oy, oz, ax2, ay2, iax2, iay2, scale, f0):  # pragma: no cover - compiled
    """brdf.ggx_specular for unit local wi, wo with wo_z > 0, 0 where wi_z <= 0; ``scale`` is
    1 / (pi ax ay (wo_z + |(ax ox, ay oy, oz)|)), the wo side of the G1 product."""
    hx, hy, hz = ix + ox, iy + oy, iz + oz
    h2 = hx * hx + hy * hy + hz * hz
    hq = h2 / (hx * hx * iax2 + hy * hy * iay2 + hz * hz)  # 1 / the unit h's quadratic form
    m = 1.0 - min(0.5 * math.sqrt(h2), 1.0)  # 1 - wi . h^, as |wi + wo| / 2 for unit wi, wo
    f = f0 + (1.0 - f0) * (m * m) * (m * m) * m
    li = math.sqrt(max(ax2 * ix * ix + ay2 * iy * iy + iz * iz, 1e-20))
    up = 1.0 if iz > 0.0 else 0.0
    return up * hq * hq * scale * f / (max(iz, 0.0) + li)


@compiled(parallel=True, fastmath=True)
def _pattern_sums_loop(
    x, frame, alpha_x, alpha_y, mask, pts, normals, drive, exponent, tab_a, tab_v, grid, f0, vis, peaks, out
):  # pragma: no cover
    """Fills ``out (M, 8)``: diffuse sums (3), specular sums (3), lobe max, lobe peak (see the caller).
    ``pts, normals, drive`` are ``(3, K)``: one row per coordinate or channel; ``vis (M, K)`` or
    ``(1, K)`` (one row for every entry)."""
    M, K, G = x.shape[0], pts.shape[1], grid.shape[0]
    px, py, pz = pts[0], pts[1], pts[2]
    qx, qy, qz = normals[0], normals[1], normals[2]
    w0, w1, w2 = drive[0], drive[1], drive[2]
    for m in numba.prange(M):
        if not mask[m]:
            continue
        x0, x1, x2 = x[m, 0], x[m, 1], x[m, 2]
        t0, t1, t2 = frame[m, 0, 0], frame[m, 0, 1], frame[m, 0, 2]  # rows t, b, n: camera -> local
        b0, b1, b2 = frame[m, 1, 0], frame[m, 1, 1], frame[m, 1, 2]
        n0, n1, n2 = frame[m, 2, 0], frame[m, 2, 1], frame[m, 2, 2]
        r = math.sqrt(x0 * x0 + x1 * x1 + x2 * x2)
        ox = -(t0 * x0 + t1 * x1 + t2 * x2) / r
        oy = -(b0 * x0 + b1 * x1 + b2 * x2) / r
        oz = -(n0 * x0 + n1 * x1 + n2 * x2) / r
        if oz <= 0.0:  # seen from below: no light reaches the camera, no lobe
            continue
        ax, ay = alpha_x[m], alpha_y[m]
        ax2, ay2 = ax * ax, ay * ay
        iax2, iay2 = 1.0 / ax2, 1.0 / ay2
        scale = 1.0 / (math.pi * ax * ay * (oz + math.sqrt(max(ax2 * ox * ox + ay2 * oy * oy + oz * oz, 1e-20))))
        buf = np.empty((3, K))
        geo, lobe, psi = buf[0], buf[1], buf[2]  # per sample: V cos_i / r^2 (0 below), lobe, Psi
        seen = vis[m] if vis.shape[0] > 1 else vis[0]
        for k in range(K):
            dx, dy, dz = px[k] - x0, py[k] - x1, pz[k] - x2
            r2 = max(dx * dx + dy * dy + dz * dz, 1e-12)
            inv = 1.0 / math.sqrt(r2)
            ix = (t0 * dx + t1 * dy + t2 * dz) * inv
            iy = (b0 * dx + b1 * dy + b2 * dz) * inv
            iz = (n0 * dx + n1 * dy + n2 * dz) * inv
            lobe[k] = _lobe_above(ix, iy, iz, ox, oy, oz, ax2, ay2, iax2, iay2, scale, f0)
            geo[k] = max(iz, 0.0) / r2 * seen[k]
            psi[k] = min(max(-(dx * qx[k] + dy * qy[k] + dz * qz[k]) * inv, 0.0), 1.0)  # cos at the emitter
        if exponent != 1.0:  # Psi other than the cosine itself: not vectorised, over the buffer
            for k in range(K):
                psi[k] = _psi_of_cosine(psi[k], exponent, tab_a, tab_v)
        d0 = d1 = d2 = s0 = s1 = s2 = 0.0
        for k in range(K):
            a = geo[k] * psi[k]
            d0 += a * w0[k]
            d1 += a * w1[k]
            d2 += a * w2[k]
            a *= lobe[k]
            s0 += a * w0[k]
            s1 += a * w1[k]
            s2 += a * w2[k]
        out[m, 0], out[m, 1], out[m, 2] = d0, d1, d2
        out[m, 3], out[m, 4], out[m, 5] = s0, s1, s2
        if not peaks:
            continue
        top = 0.0  # Eq. 6 asks how bright the lobe gets toward a sample, lit or not
        for k in range(K):
            top = max(top, lobe[k])
        # the lobe's peak: confidence.specular_peak's grid of half vectors (ax u, ay v, 1)
        peak = 0.0
        for gu in range(G):
            for gv in range(G):
                hx, hy = ax * grid[gu], ay * grid[gv]
                hn = 1.0 / math.sqrt(hx * hx + hy * hy + 1.0)
                hx, hy, hz = hx * hn, hy * hn, hn
                dot = 2.0 * (ox * hx + oy * hy + oz * hz)
                ix, iy, iz = dot * hx - ox, dot * hy - oy, dot * hz - oz  # wo mirrored about h
                peak = max(peak, _lobe_above(ix, iy, iz, ox, oy, oz, ax2, ay2, iax2, iay2, scale, f0))
        out[m, 6], out[m, 7] = top, peak
