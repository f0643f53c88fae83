"""The diffuse albedo map near its edges solved jointly from every entry's pixel sample.

A texel's own refinement (``refine.policy``) explains each entry's pixel with the texel's albedo, but
the pixel is a bilinear sample of four pixels that each see the surface at their own point, up to a
pixel (~a texel) away (``refine.footprint.sample_points``): near an albedo edge every entry blends its
neighbours' albedo in, and the texel's answer comes out as the truth blurred by about half a texel
(the demo's map fitted the truth blurred by a Gaussian of 0.55 texel best: 0.0116 against 0.0199,
docs/history/accuracy.md). Here the albedos of the texels near edges are solved together, each entry
predicted as its diffuse light times the weighted albedos of the texels its four taps land in.

Convention: a texel's albedo is the mean over its square of the map (a tap counts for the texel it
lands in, not a bilinear blend of four): a map coarser than the surface's detail (the gallery's 128²
of 256² textures) is then its detail's average; a sharper reading (bilinear taps) raised the
gallery's ρd RMSE on three of its five objects (box +24%, knot +8%, vase +1%). Residuals in the
entries' sensor sigmas, Cauchy (``TUNING.albedo_map.robust``) by iterative reweighting; a pull of
``TUNING.albedo_map.prior_weight``
times the median texel's data weight toward the texel's own answer sets how far an edge sharpens
(a step between two albedos is the system's least determined mode) and keeps a texel the taps
barely see where it was. Texels not solved are held at their values; a tap that leaves the atlas
(a seam) counts for the entry's own texel.
"""

from __future__ import annotations

import numpy as np
from scipy.sparse import csr_matrix, diags
from scipy.sparse.linalg import cg

from ..io.maps import uv_to_pixel
from ..io.progress import QUIET, Progress
from ..physics.brdf import RHO_D_MAX
from .footprint import tap_uv
from .settings import TUNING


def tap_texels(
    delta: np.ndarray, weight: np.ndarray, uv: np.ndarray, uv_per_metre: np.ndarray, texel_index: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The texel each tap of N texels' entries lands in ``(N, V, 4)`` (index into the atlas's texels)
    and its weight ``(N, V, 4)``.

    ``delta (N, V, 4, 2)``, ``weight (N, V, 4)``: the taps as ``refine.footprint.sample_points`` gives
    them (metres along the texel's (t^, b^)); ``uv (N, 2)``, ``uv_per_metre (N, 2, 2)``: the texels'
    (``io.texels``); ``texel_index (H, W)``: each map pixel's texel, -1 where none. A tap
    lands at ``refine.footprint.tap_uv``, in the texel whose square holds it; one that leaves the
    atlas counts for its own texel (``own``), as does every tap of an entry none of whose taps is
    weighed (padding, edge-on: weight 1 on the first)."""
    N, V = weight.shape[:2]
    H, W = texel_index.shape
    r, c = uv_to_pixel(tap_uv(delta, uv, uv_per_metre).reshape(-1, 2), (H, W))
    row, col = np.rint(r).astype(np.int64), np.rint(c).astype(np.int64)
    inside = (row >= 0) & (row < H) & (col >= 0) & (col < W)
    hit = np.where(inside, texel_index[row.clip(0, H - 1), col.clip(0, W - 1)], -1).reshape(N, V, 4)
    r0, c0 = uv_to_pixel(uv, (H, W))
    own = texel_index[np.rint(r0).astype(np.int64), np.rint(c0).astype(np.int64)]
    taps = np.where(hit >= 0, hit, own[:, None, None])
    w = weight.copy()
    none = w.sum(-1) <= 0
    w[none] = np.array([1.0, 0.0, 0.0, 0.0])
    return taps, w


def sharpened_albedos(
    diffuse: np.ndarray,
    target: np.ndarray,
    inv_sigma: np.ndarray,
    taps: np.ndarray,
    tap_weight: np.ndarray,
    albedo: np.ndarray,
    solved: np.ndarray,
    progress: Progress = QUIET,
) -> np.ndarray:
    """``albedo (T, 3)`` with the texels ``solved (U,)`` solved jointly from M entries (module
    docstring): ``diffuse (M, 3)`` each entry's unit-albedo diffuse light, ``target (M, 3)`` its
    pixel less its lobe's light (linear), ``inv_sigma (M, 3)`` its sensor 1/sigma (0: not used —
    masked or clipped), ``taps (M, 4)`` the texels its taps land in and ``tap_weight (M, 4)``
    their weights (``tap_texels``). Entries that reach no solved texel are left out. In [0,
    RHO_D_MAX]; float64. Reports each channel's solves (``TUNING.albedo_map.rounds`` each) as the
    progress stage "albedo solve"."""
    out = albedo.astype(np.float64).copy()
    T, U = len(albedo), len(solved)
    if U == 0:
        return out
    column = np.full(T, -1, np.int64)
    column[solved] = np.arange(U)
    col = column[taps]  # (M, 4): -1 for a held texel
    reaches = ((col >= 0) & (tap_weight > 0)).any(1)
    bar = progress.counter("albedo solve", albedo.shape[1] * TUNING.albedo_map.rounds, "solve")
    for ch in range(albedo.shape[1]):
        use = reaches & (inv_sigma[:, ch] > 0)
        d, w, c = diffuse[use, ch], tap_weight[use], col[use]
        held = np.where(c < 0, w * out[taps[use], ch], 0.0).sum(1)  # the held texels' share of each pixel
        y = target[use, ch] - d * held
        free = c >= 0
        a = (w * d[:, None])[free]
        rows = np.broadcast_to(np.arange(len(d))[:, None], c.shape)[free]
        A = csr_matrix((a, (rows, c[free])), shape=(len(d), U))
        x0 = out[solved, ch]
        x = x0.copy()
        s2 = inv_sigma[use, ch] ** 2
        for k in range(TUNING.albedo_map.rounds):
            wt = s2 if k == 0 else s2 / (1.0 + ((A @ x - y) * inv_sigma[use, ch] / TUNING.albedo_map.robust) ** 2)
            Aw = A.multiply(wt[:, None]).tocsr()
            M = (A.T @ Aw).tocsr()
            data = M.diagonal()
            prior = TUNING.albedo_map.prior_weight * float(np.median(data[data > 0])) if (data > 0).any() else 1.0
            M = M + diags(np.full(U, prior))
            x, _ = cg(
                M,
                Aw.T @ y + prior * x0,
                x0=x,
                M=diags(1.0 / M.diagonal()),
                rtol=TUNING.albedo_map.cg_tolerance,
                maxiter=500,
            )
            bar.update()
        out[solved, ch] = np.clip(x, 0.0, RHO_D_MAX)
    bar.close()
    return out
