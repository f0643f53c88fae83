"""Each texel's refined normal fused with its neighbours' as far as the normal field is smooth
(used by ``pipeline.fit_traces``; docs/refinement.md "The normal field, fused").

One trace fixes a normal to a degree or so — more where its photos are noisy (a Monte Carlo
render, a dark or grazing view) — and that noise is independent enough between neighbouring
texels that averaging it away is most of what is left to gain on a smooth surface. But a normal
map exists for the detail the mesh lacks (a tile's bevel, an engraving): the neighbours count
only as far as the data say the field is smooth — the field's semivariogram over distance beyond
the texels' own errors (``surface_fields``), and, texel by texel, a neighbour whose offset differs
from the texel's beyond both their errors weighs less (a bilateral range weight), and a texel whose
neighbours disagree with it beyond ``TUNING.fields.normal_gate`` sigmas keeps its own.

Convention: texels ``(N,)`` with object-space ``position (N, 3)`` (m) and unit geometric (mesh)
``normal (N, 3)``; the field fused is each refined normal's offset from its mesh normal, ``n - m``
(object space, nearly in the tangent plane: the mesh's curvature is not smoothed); 1-sigma ``std
(N,)`` radians, the refinement's normal uncertainty (both tilt axes together).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from .settings import TUNING
from .surface_fields import field_pairs, fused_with_neighbours, semivariogram, texel_spacing


def fused_normals(
    position: np.ndarray,
    normal: np.ndarray,
    refined: np.ndarray,
    std: np.ndarray,
    source: np.ndarray,
    spacing: float | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """The ``source (S,)`` texels' refined normals ``refined (N, 3)`` (unit, object space) each
    fused with its ``TUNING.fields.normal_neighbours`` nearest other sources': their offsets from the mesh ``normal``
    averaged with weights 1 / (std_j^2 + 2 gamma(d)) — gamma the sources' semivariogram at the
    distance d (``surface_fields``) — times the range weight (module docstring); that mean counts
    as one measurement whose variance is its standard error (at least its spread over the square
    root of the effective number), combined with the texel's own by inverse variance unless they
    differ by more than ``TUNING.fields.normal_gate`` sigmas together. Returns the fused unit normals ``(S, 3)`` and
    their std ``(S,)`` (radians). ``spacing``: ``texel_spacing`` of the positions, computed here
    unless given."""
    S = len(source)
    own = np.maximum(std[source], TUNING.fields.normal_min_std)
    offset = refined[source] - normal[source]
    if S < 2:
        return refined[source].copy(), own.copy()
    pos = position[source]
    spacing = texel_spacing(pos) if spacing is None else spacing
    i, j, d = field_pairs(pos)
    variation = semivariogram(d, ((offset[i] - offset[j]) ** 2).sum(1), own[i] ** 2 + own[j] ** 2, spacing, 2)
    dist, near = cKDTree(pos).query(pos, k=min(TUNING.fields.normal_neighbours + 1, S))
    field = 2 * np.interp(dist, *variation)  # variance of the field's change from a neighbour
    apart2 = ((offset[near] - offset[:, None]) ** 2).sum(-1) / (own[:, None] ** 2 + own[near] ** 2)
    w = np.exp(-0.5 * apart2 / TUNING.fields.normal_range**2) / (own[near] ** 2 + field)
    w = w * (near != np.arange(S)[:, None])  # a texel is not its own neighbour
    safe = np.maximum(w.sum(1), 1e-300)
    mean = (w[..., None] * offset[near]).sum(1) / safe[:, None]
    spread = (w * ((offset[near] - mean[:, None]) ** 2).sum(-1)).sum(1) / safe
    share, fused_var, _ = fused_with_neighbours(
        own**2, w, spread, ((mean - offset) ** 2).sum(1), TUNING.fields.normal_gate
    )
    fused = normal[source] + offset + share[:, None] * (mean - offset)
    fused /= np.linalg.norm(fused, axis=1, keepdims=True)
    fused_std = np.sqrt(fused_var)
    return fused, fused_std
