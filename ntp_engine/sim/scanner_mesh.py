"""The mesh a shape scanner delivers: what ntp is given in place of the true shape (paper, Fig. 11).

A structured-light scanner's mesh misses what is finer than its resolution, is noisy at a fraction
of a millimetre and is triangulated its own way. ``scanner_mesh`` makes one from the true mesh:

1. another triangulation: the same surface on a coarser grid, where the caller has it (``coarse``;
   generated objects re-sample their parametric surface at 60% of the grid), else the true mesh's;
2. details smoothed away: ``iterations`` of Taubin smoothing (lambda 0.5, mu -0.53: shrinks no
   volume) over the mesh's vertices welded by position (UV seams do not tear);
3. noise along the normals: a smooth field of about 3 mm cells plus a per-vertex part, ``noise_m``
   standard deviation (0.1-0.5 mm: a hand-held scanner's), seeded.

UVs are kept: the maps ntp makes for the scanner's mesh and the truth's share their (u, v), so
errors are measured texel by texel against the truth. Convention: metres; the result's mesh stands
where the true one does (noise and smoothing have zero mean).
"""

from __future__ import annotations

import numpy as np

from ..io.mesh import Mesh, smooth_normals, welded
from .materials import value_noise

NOISE_M = 3e-4  # the default noise: between 0.1 and 0.5 mm
SMOOTHING = 4  # Taubin iterations: removes relief of a few texels, keeps the shape
_LAMBDA, _MU = 0.5, -0.53  # Taubin's pass band (mu < -lambda: no shrinking)
NOISE_CELL_M = 3e-3  # the smooth part's cell: a scanner's errors are correlated over millimetres


def taubin(mesh: Mesh, iterations: int) -> np.ndarray:
    """Vertex positions ``(V, 3)`` after ``iterations`` Taubin passes (each a lambda and a mu step
    towards the neighbours' mean) over the mesh welded by position; open rims stay put."""
    key = welded(mesh.vertices)
    n = int(key.max()) + 1
    pos = np.zeros((n, 3))
    pos[key] = mesh.vertices
    f = key[mesh.faces]
    all_edges = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    all_edges = all_edges[all_edges[:, 0] != all_edges[:, 1]]
    edges, uses = np.unique(all_edges, axis=0, return_counts=True)
    # an open rim (a scan's base on the support) stays where it is: smoothing would lift it
    rim = np.zeros(n, bool)
    rim[edges[uses == 1].ravel()] = True
    degree = np.bincount(edges.ravel(), minlength=n).astype(np.float64)[:, None]
    moves = (~rim & (degree[:, 0] > 0))[:, None]
    for _ in range(iterations):
        for step in (_LAMBDA, _MU):
            acc = np.zeros_like(pos)
            np.add.at(acc, edges[:, 0], pos[edges[:, 1]])
            np.add.at(acc, edges[:, 1], pos[edges[:, 0]])
            mean = acc / np.maximum(degree, 1)
            pos = pos + np.where(moves, step * (mean - pos), 0.0)
    return pos[key]


def scanner_mesh(
    mesh: Mesh, seed: int, noise_m: float = NOISE_M, iterations: int = SMOOTHING, coarse: Mesh | None = None
) -> Mesh:
    """The mesh a scanner would deliver for the true ``mesh`` (module docstring); ``coarse``: the
    same surface triangulated otherwise, with the same UV parametrisation."""
    base = coarse if coarse is not None else mesh
    smooth = Mesh(taubin(base, iterations), base.faces, base.uv, base.normals)
    normals = smooth_normals(smooth.vertices, smooth.faces)
    key = welded(smooth.vertices)  # one displacement per welded vertex: seams stay closed
    first = np.unique(key, return_index=True)[1]
    p = smooth.vertices[first]
    rng = np.random.default_rng([11, seed])
    salt = int(rng.integers(0, 1 << 20))
    smooth_part = value_noise(p, NOISE_CELL_M, salt)
    field = (smooth_part - smooth_part.mean()) / max(float(smooth_part.std()), 1e-12)  # unit variance
    shift = noise_m * (np.sqrt(0.8) * field + np.sqrt(0.2) * rng.standard_normal(len(p)))
    shift -= shift.mean()
    v = smooth.vertices + shift[key][:, None] * normals
    return Mesh(v, smooth.faces, smooth.uv, smooth_normals(v, smooth.faces))
