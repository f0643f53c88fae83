"""Where a texel's anisotropic material points, from its neighbours (``fit.refine.material_costs``'s
prior over tangent turns).

A texel whose trace does not show its lobe cannot tell where an anisotropic lobe points; its
neighbours of the same material whose own traces fixed their lobes can — tangent fields are smooth
over a surface (brushing, weaving, machining). Uniform over the turns, the material's lobe pays
~ln 4 for not knowing where it points, and the texel goes to a weakly anisotropic material instead
(docs/accuracy.md, "Isotropic unless shown").

Convention: texels ``(N,)`` with object-space positions (m) and geometric frames (unit ``normal``,
``tangent``; the bitangent n x t); lobe axes ``t_loc (N, 3)`` in each texel's geometric frame (rows
t, b, n: ``fit.refine``'s frames). Angles in radians about the texel's normal from its ``t_loc``,
right-handed (``physics.frame.turned_about_normal``); axial (mod pi): a lobe's axis has no sign.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

NEIGHBOURS = 16  # nearest sources averaged per texel
REACH = 10.0  # a source's weight falls as a Gaussian of this many texel spacings (median nearest-texel distance)
DOUBT = 0.25  # added to the sources' weights (a source in the texel's plane weighs 1): one source is not many


def texel_spacing(position: np.ndarray) -> float:
    """The median distance (m) from each of ``position (N, 3)`` to its nearest other (0 for one)."""
    return float(np.median(cKDTree(position).query(position, k=2)[0][:, 1])) if len(position) > 1 else 0.0


def _object_axes(t_loc: np.ndarray, normal: np.ndarray, tangent: np.ndarray) -> np.ndarray:
    """Local axes ``(N, 3)`` (geometric frame) in object space."""
    bitangent = np.cross(normal, tangent)
    return t_loc[:, :1] * tangent + t_loc[:, 1:2] * bitangent + t_loc[:, 2:3] * normal


def neighbour_turns(
    position: np.ndarray,
    normal: np.ndarray,
    tangent: np.ndarray,
    t_loc: np.ndarray,
    source: np.ndarray,
    target: np.ndarray,
    spacing: float | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """For the texels ``target (M,)`` (indices): the turn ``(M,)`` from their own ``t_loc`` to the
    axis their ``NEIGHBOURS`` nearest ``source (S,)`` texels point along (each projected into the
    target's tangent plane and weighed by that projection's squared length and a Gaussian of its
    distance, sigma ``REACH`` texel spacings; axial mean), and how much to trust it ``(M,)``: the
    resultant of the doubled angles, weighed so, over the projections' weights plus ``DOUBT`` — 1
    for near sources along one axis, toward 0 for far or disagreeing ones (0 and turn 0: none).
    ``spacing``: ``texel_spacing(position)``, computed here unless given."""
    M = len(target)
    turn, agree = np.zeros(M), np.zeros(M)
    if M == 0 or len(source) == 0:
        return turn, agree
    spacing = texel_spacing(position) if spacing is None else spacing
    axes = _object_axes(t_loc[source], normal[source], tangent[source])
    dist, near = cKDTree(position[source]).query(position[target], k=min(NEIGHBOURS, len(source)))
    dist, near = dist.reshape(M, -1), near.reshape(M, -1)  # no distance bound: all finite
    fall = np.exp(-0.5 * (dist / (REACH * max(spacing, 1e-9))) ** 2)
    a = axes[near]  # (M, k, 3)
    n_t, t_t = normal[target][:, None], tangent[target][:, None]
    b_t = np.cross(n_t, t_t)
    x, y = (a * t_t).sum(-1), (a * b_t).sum(-1)  # in the target's geometric frame
    psi = np.arctan2(y, x)
    own = t_loc[target]
    psi0 = np.arctan2(own[:, 1], own[:, 0])[:, None]
    size = x * x + y * y  # an axis nearly along the target's normal says little
    w = size * fall
    c, s = (w * np.cos(2 * (psi - psi0))).sum(1), (w * np.sin(2 * (psi - psi0))).sum(1)
    count = size.sum(1)
    has = count > 1e-12
    turn[has] = 0.5 * np.arctan2(s[has], c[has])
    agree[has] = np.hypot(c[has], s[has]) / (count[has] + DOUBT)
    return turn, agree
