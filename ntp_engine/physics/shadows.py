"""Which entries of a trace the paper's Eq. 1, as the network learnt it, describes: those whose
emitters all reach the point (no support, no part of the mesh, hides more than
``MAX_SHADOWED_DRIVE`` of the pattern's drive) and that see their point at a steep enough angle
(``MIN_COS_VIEW``). Trace assembly flags the others, the registration's photometric check skips
them, the refinement reads them where a texel has nothing better.

Convention: entries are ``learn.ragged.RaggedTraces`` rows (camera space, x the point, n^ its
normal); poses are camera-from-world 4x4; the support is the plane z = ``support_z`` of the world
(the mesh's frame, z up, metres).
"""

from __future__ import annotations

import numpy as np
from torch import Tensor

from ..scanner.scanner import Scanner
from .emitter_blocks import ShadowGroups, sample_drive

MAX_SHADOWED_DRIVE = 0.05  # fraction of the pattern's drive the support, or the mesh, may block from a used entry
MIN_COS_VIEW = 0.3  # wo . n^ above this: an entry the network reads


class SupportShadow:
    """Whether the support (the plane z = ``support_z`` under the object) blocks emitters carrying
    more than ``MAX_SHADOWED_DRIVE`` of the pattern's drive in a photo — for every point of the
    object at once, which Eq. 1 as the network learnt it does not model — and which emitter groups
    it blocks (``mask``): an emitter below the plane is hidden from every point above it."""

    def __init__(self, scanner: Scanner, support_z: float):
        self.points, self.drive = sample_drive(scanner)
        self.support_z = support_z

    def __call__(self, camera_from_world: np.ndarray) -> bool:
        """True when the support shadows the photo taken from ``camera_from_world`` (4x4)."""
        R, t = camera_from_world[:3, :3], camera_from_world[:3, 3]
        below = ((self.points - t) @ R)[..., 2] < self.support_z  # emitter samples in world: R^T (p - t)
        return bool(self.drive[below].sum() > MAX_SHADOWED_DRIVE)

    def mask(self, camera_from_world: np.ndarray, groups: ShadowGroups) -> int:
        """The int64 shadow mask (bit g: ``groups``' group g) of the groups whose centres lie below
        the support in the photo taken from ``camera_from_world`` — hidden or not as their centres,
        as ``EmitterShadow``'s; needs ``groups.fits``."""
        R, t = camera_from_world[:3, :3], camera_from_world[:3, 3]
        below = np.nonzero(((groups.points - t) @ R)[:, 2] < self.support_z)[0]
        return int(np.bitwise_or.reduce(np.left_shift(1, below.astype(np.int64)), initial=0))


def grazing(entries: Tensor) -> Tensor:
    """``(...)`` True where entries ``(..., 12)`` see their point at ``wo . n^ <= MIN_COS_VIEW``
    (camera space: wo = -x / |x|): kept for the refinement, too grazing for the network."""
    x, n = entries[..., 3:6], entries[..., 6:9]
    return -(x * n).sum(-1) <= MIN_COS_VIEW * x.norm(dim=-1)


def shadowed(groups: ShadowGroups, shadow: Tensor) -> Tensor:
    """``(...)`` True where the emitter groups ``shadow (...)`` hides carry more than
    ``MAX_SHADOWED_DRIVE`` of the pattern's drive: too much for the network, which assumes every
    emitter above the horizon reaches the point."""
    return groups.share(shadow) > MAX_SHADOWED_DRIVE
