"""Statistics of a field over a surface's texels (tangent axes, normal offsets): how far apart the
texels lie, and how much the field varies with distance beyond the texels' own errors — what
``refine.tangent_field`` and ``refine.normal_field`` fuse neighbours by (docs/refinement.md).

Convention: texels at object-space ``position (N, 3)`` (m); a field compared pair by pair as a
squared difference (rad^2) against the pair's noise (the sum of the two texels' 1-sigma errors
squared); distances in bins doubling from one texel spacing.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree
from scipy.special import gammaincinv

from .settings import TUNING


def texel_spacing(position: np.ndarray) -> float:
    """The median distance (m) from each of ``position (N, 3)`` to its nearest other (0 for one)."""
    return float(np.median(cKDTree(position).query(position, k=2)[0][:, 1])) if len(position) > 1 else 0.0


def field_pairs(position: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pairs of ``position (S, 3)``'s texels to measure a field's variation on: each with its
    ``TUNING.fields.variation_pairs`` nearest others and as many seeded random ones (far pairs too), never a
    texel with itself: rows ``i, j (P,)`` and their distances ``(P,)`` (m). None for one texel."""
    S = len(position)
    k = min(TUNING.fields.variation_pairs + 1, S)
    _, near = cKDTree(position).query(position, k=k)
    near = near.reshape(S, -1)
    rng = np.random.default_rng(0)
    i = np.repeat(np.arange(S), 2 * (k - 1))
    j = np.concatenate([near[:, 1:], rng.integers(0, S, (S, k - 1))], 1).reshape(-1)
    keep = i != j
    i, j = i[keep], j[keep]
    return i, j, np.linalg.norm(position[i] - position[j], axis=1)


def semivariogram(
    distance: np.ndarray, squared_difference: np.ndarray, noise: np.ndarray, spacing: float, dof: int
) -> tuple[np.ndarray, np.ndarray]:
    """How far a field varies with distance beyond its texels' errors: distances ``(B,)`` (m;
    ``TUNING.fields.variation_bins``, doubling from ``spacing``) and the semivariogram there ``(B,)`` — half the
    mean squared difference of two texels' values less their ``noise`` — from pairs at
    ``distance (P,)`` with ``squared_difference (P,)`` and ``noise (P,)`` (the expected squared
    difference of two equal values). Robust: from the medians, the squared difference of a
    ``dof``-component Gaussian error having median ``chi2(dof).median() / dof`` of its mean.
    Non-decreasing with distance, 0 where a bin has fewer than ``TUNING.fields.min_pairs`` pairs from the start."""
    bins = max(spacing, 1e-9) * 2.0 ** np.arange(TUNING.fields.variation_bins)
    gamma = np.zeros(TUNING.fields.variation_bins)
    if len(distance) == 0:
        return bins, gamma
    ratio = 2.0 * float(gammaincinv(dof / 2.0, 0.5)) / dof  # chi2(dof)'s median, as scipy.stats computes it
    b = np.clip(
        np.round(np.log2(np.maximum(distance / max(spacing, 1e-9), 1.0))).astype(int),
        0,
        TUNING.fields.variation_bins - 1,
    )
    for n in range(TUNING.fields.variation_bins):
        sel = b == n
        if sel.sum() >= TUNING.fields.min_pairs:
            gamma[n] = max(0.0, float(np.median(squared_difference[sel])) / ratio - float(np.median(noise[sel]))) / 2
        elif n:
            gamma[n] = gamma[n - 1]
    return bins, np.maximum.accumulate(gamma)


def fused_with_neighbours(
    own_var: np.ndarray, w: np.ndarray, spread: np.ndarray, distance2: np.ndarray, gate: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A texel's own value (variance ``own_var (M,)``, inf: unknown) and its neighbours' weighted
    mean (weights ``w (M, k)``, 1 / their variances as predictors; the neighbours' ``spread (M,)``
    about their mean) combined by inverse variance: the mean counts as one measurement whose
    variance is its standard error, at least the spread over the effective number of neighbours
    and at least 1 / their total weight. Where the two lie more than ``gate`` sigmas apart together
    (``distance2 (M,)``: their squared difference) or no neighbour weighs, the texel keeps its own
    (the field changes there). Returns the mean's share in the fused value ``(M,)``, the fused
    variance ``(M,)`` and where it fused ``(M,)``."""
    total = w.sum(1)
    effective = total**2 / np.maximum((w * w).sum(1), 1e-300)
    mean_var = np.maximum(spread / np.maximum(effective, 1.0), 1.0 / np.maximum(total, 1e-300))
    fuse = (total > 0) & ~(distance2 > gate**2 * (own_var + mean_var))
    share = np.where(fuse, 1.0 / (1.0 + mean_var / own_var), 0.0)  # 1 where the own is unknown (inf)
    fused_var = np.where(fuse, 1.0 / (1.0 / own_var + 1.0 / mean_var), own_var)
    return share, fused_var, fuse
