"""Where a texel's anisotropic material points, from its neighbours: ``refine.policy.material_costs``'s
prior over tangent turns (``neighbour_turns``), and every anisotropic tangent fused with its
neighbours' as far as the field is smooth (``fused_turns`` over ``field_variation``; used by
``pipeline.fit_traces``, docs/refinement.md "The tangent field, fused").

A texel whose trace does not show its lobe cannot tell where an anisotropic lobe points; its
neighbours of the same material whose own traces fixed their lobes can — tangent fields are smooth
over a surface (brushing, weaving, machining). Uniform over the turns, the material's lobe pays
~ln 4 for not knowing where it points, and the texel goes to a weakly anisotropic material instead
(docs/history/accuracy.md, "Isotropic unless shown"). And a tangent a trace did fix is noisy by a few
degrees, enough to break a sharp anisotropic highlight into sparkles.

Convention: texels ``(N,)`` with object-space positions (m) and geometric frames (unit ``normal``,
``tangent``; the bitangent n x t); lobe axes ``t_loc (N, 3)`` in each texel's geometric frame (rows
t, b, n: ``refine.policy``'s frames). Angles in radians about the texel's normal from its ``t_loc``,
right-handed (``physics.frame.turned_about_normal``); axial (mod pi): a lobe's axis has no sign.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial import cKDTree

from .settings import TUNING
from .surface_fields import field_pairs, fused_with_neighbours, semivariogram, texel_spacing

# the distance, in sigmas, where a Gaussian weight falls below float64's epsilon
_NEGLIGIBLE_SIGMAS = math.sqrt(-2.0 * math.log(np.finfo(np.float64).eps))


def _object_axes(t_loc: np.ndarray, normal: np.ndarray, tangent: np.ndarray) -> np.ndarray:
    """Local axes ``(N, 3)`` (geometric frame) in object space."""
    bitangent = np.cross(normal, tangent)
    return t_loc[:, :1] * tangent + t_loc[:, 1:2] * bitangent + t_loc[:, 2:3] * normal


def _neighbour_axes(
    position: np.ndarray,
    normal: np.ndarray,
    tangent: np.ndarray,
    t_loc: np.ndarray,
    source: np.ndarray,
    target: np.ndarray,
    k: int,
    reach: float = np.inf,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The ``k`` nearest ``source`` texels of each ``target`` that has one within ``reach`` (m): their
    axes' turns from the target's own ``t_loc`` in its tangent plane ``(M, k)`` (radians), the
    squared length of their projections there, their distances (m) and their rows of ``source``
    ``(M, k)`` each. A target with none within reach has none: distances inf, rows ``len(source)``,
    projections 0."""
    M, k = len(target), min(k, len(source))
    axes = _object_axes(t_loc[source], normal[source], tangent[source])
    axes = np.concatenate([axes, np.zeros((1, 3))])  # row len(source): no source
    tree = cKDTree(position[source])
    dist, near = tree.query(position[target], k=k, distance_upper_bound=reach)
    dist, near = dist.reshape(M, -1), near.reshape(M, -1)
    some = np.isinf(dist).any(1) & np.isfinite(dist[:, 0])  # some within reach: all k wherever they lie
    if some.any():
        d, n = tree.query(position[target[some]], k=k)
        dist[some], near[some] = d.reshape(-1, k), n.reshape(-1, k)
    a = axes[near]  # (M, k, 3)
    n_t, t_t = normal[target][:, None], tangent[target][:, None]
    b_t = np.cross(n_t, t_t)
    x, y = (a * t_t).sum(-1), (a * b_t).sum(-1)  # in the target's geometric frame
    own = t_loc[target]
    psi = np.arctan2(y, x) - np.arctan2(own[:, 1], own[:, 0])[:, None]
    return psi, x * x + y * y, dist, near


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
    axis their ``TUNING.fields.tangent_neighbours`` nearest ``source (S,)`` texels point along (each projected into the
    target's tangent plane and weighed by that projection's squared length and a Gaussian of its
    distance, sigma ``TUNING.fields.tangent_reach`` texel spacings; axial mean), and how much to trust it ``(M,)``: the
    resultant of the doubled angles, weighed so, over the projections' weights plus ``TUNING.fields.tangent_doubt`` — 1
    for near sources along one axis, toward 0 for far or disagreeing ones (0 and turn 0: none, or
    none within the distance where the Gaussian falls below float64's epsilon).
    ``spacing``: ``texel_spacing(position)``, computed here unless given."""
    M = len(target)
    turn, agree = np.zeros(M), np.zeros(M)
    if M == 0 or len(source) == 0:
        return turn, agree
    spacing = texel_spacing(position) if spacing is None else spacing
    sigma = TUNING.fields.tangent_reach * max(spacing, 1e-9)
    # a target whose nearest source lies where the Gaussian has fallen below float64's epsilon has
    # no neighbours (its trust would be below it); the bounded search skips the far side of the
    # object — a k-d tree's slow case, and most targets of a material lie far from its sources
    psi, size, dist, _ = _neighbour_axes(
        position, normal, tangent, t_loc, source, target, TUNING.fields.tangent_neighbours, sigma * _NEGLIGIBLE_SIGMAS
    )
    fall = np.exp(-0.5 * (dist / sigma) ** 2)
    w = size * fall  # an axis nearly along the target's normal says little
    c, s = (w * np.cos(2 * psi)).sum(1), (w * np.sin(2 * psi)).sum(1)
    count = size.sum(1)
    has = count > 1e-12
    turn[has] = 0.5 * np.arctan2(s[has], c[has])
    agree[has] = np.hypot(c[has], s[has]) / (count[has] + TUNING.fields.tangent_doubt)
    return turn, agree


def field_variation(
    position: np.ndarray,
    normal: np.ndarray,
    tangent: np.ndarray,
    t_loc: np.ndarray,
    std: np.ndarray,
    source: np.ndarray,
    spacing: float | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """How far one material's tangent field turns with distance, measured on its ``source``
    texels (those whose traces fixed their tangents, 1-sigma ``std (N,)`` radians): distances
    ``(B,)`` (m) and the field's semivariogram there ``(B,)`` (rad^2) — half the mean squared angle
    between two texels' axes beyond what their own errors explain (``surface_fields.semivariogram``
    over the sources' ``field_pairs``; 0 without two sources)."""
    spacing = texel_spacing(position) if spacing is None else spacing
    if len(source) < 2:
        return semivariogram(np.zeros(0), np.zeros(0), np.zeros(0), spacing, 1)
    axes = _object_axes(t_loc[source], normal[source], tangent[source])
    i, j, d = field_pairs(position[source])
    angle = np.arccos(np.clip(np.abs((axes[i] * axes[j]).sum(1)), 0.0, 1.0))  # axial
    noise = (
        np.maximum(std[source[i]], TUNING.fields.tangent_min_std) ** 2
        + np.maximum(std[source[j]], TUNING.fields.tangent_min_std) ** 2
    )
    return semivariogram(d, angle**2, noise, spacing, 1)


def fused_turns(
    position: np.ndarray,
    normal: np.ndarray,
    tangent: np.ndarray,
    t_loc: np.ndarray,
    std: np.ndarray,
    source: np.ndarray,
    target: np.ndarray,
    variation: tuple[np.ndarray, np.ndarray] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Each of ``target (M,)``'s tangent and its neighbours' together: the turn ``(M,)`` (radians,
    from its own ``t_loc``) to the precision-weighted axial mean of its own axis (1-sigma ``std``
    radians ``(N,)``, inf: unconstrained) and its ``TUNING.fields.tangent_fuse_neighbours`` nearest other ``source``
    texels' — each weighed by the squared length of its projection into the target's tangent plane
    over the variance of predicting the target from it: its own std^2 plus twice the field's
    semivariogram at its distance (``variation``: ``field_variation``'s, by default of these
    sources) — and the fused std ``(M,)``. The neighbours' mean counts as one measurement whose
    variance is its standard error (at least their spread over the square root of their effective
    number). So a texel whose own trace fixed its tangent keeps it, one that did not takes its
    neighbours' as far as the field is smooth over the distance to them, and noise between the two
    is averaged. Where the two differ by more than ``TUNING.fields.tangent_gate`` sigmas together the field turns there
    (the texel keeps its own). A target without sources keeps its tangent and std."""
    M = len(target)
    turn, fused = np.zeros(M), std[target].astype(np.float64)  # a copy
    if M == 0 or len(source) == 0:
        return turn, fused
    if variation is None:
        variation = field_variation(position, normal, tangent, t_loc, std, source)
    psi, size, dist, near = _neighbour_axes(
        position, normal, tangent, t_loc, source, target, TUNING.fields.tangent_fuse_neighbours + 1
    )
    field = 2 * np.interp(dist, *variation)  # variance of the field's turn between source and target
    w = size / (np.maximum(std[source], TUNING.fields.tangent_min_std)[near] ** 2 + field)
    w = w * (source[near] != target[:, None])  # a texel is not its own neighbour
    total = w.sum(1)
    c, s = (w * np.cos(2 * psi)).sum(1), (w * np.sin(2 * psi)).sum(1)
    mean = 0.5 * np.arctan2(s, c)  # the neighbours' axis, from the target's own
    resultant = np.clip(np.hypot(c, s) / np.maximum(total, 1e-300), 1e-12, 1.0)
    spread = -0.5 * np.log(resultant)  # variance of the axes (doubled angles' circular variance / 4)
    own_var = np.maximum(std[target], TUNING.fields.tangent_min_std) ** 2
    # a texel that disagrees with its neighbours beyond both their errors sits where the field turns
    # (an edge of brushing): its own trace says so, and it keeps its tangent
    share, fused_var, fuse = fused_with_neighbours(own_var, w, spread, mean**2, TUNING.fields.tangent_gate)
    turn[fuse] = (share * mean)[fuse]
    fused[fuse] = np.sqrt(fused_var)[fuse]
    return turn, fused
