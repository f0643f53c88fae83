"""The scan's local frame: world coordinates re-centred, in float64, before any float32 work.

Embree's rays, the texel atlas and the photometric registration hold positions in float32, whose
step is 6e-8 of the value: at 1000 m from the origin that is 0.06 mm — a texel's normal from
neighbouring positions turns by up to 0.67 rad. Work is done in a frame whose origin is the mesh's
bounding-box centre *rounded to the metre* (``ORIGIN_GRID_M``): positions then lie within about a
metre of it, where float32's step is 0.1 um. For a scan near the world's origin (every real
turntable or tabletop scan in metres) the origin is exactly 0 and nothing changes, bit for bit.

Convention: a pose is camera-from-world, 4x4, float64; ``x_world = x_local + origin``, so a pose
``T`` becomes ``T @ translation(origin)`` in the local frame. What a user reads — ``poses.json``,
the result's ``mesh.obj`` — is in the world frame.
"""

from __future__ import annotations

import numpy as np

from ..io.mesh import Mesh

ORIGIN_GRID_M = 1.0  # float32 positions within ~1 m of the origin: steps of 0.1 um


def local_origin(mesh: Mesh) -> np.ndarray:
    """``(3,)`` float64: the mesh's bounding-box centre rounded to ``ORIGIN_GRID_M`` (0 near the origin)."""
    centre = 0.5 * (mesh.vertices.min(0) + mesh.vertices.max(0))
    return np.round(centre / ORIGIN_GRID_M) * ORIGIN_GRID_M + 0.0  # + 0.0: no -0.0


def moved(mesh: Mesh, offset: np.ndarray) -> Mesh:
    """``mesh`` with every vertex moved by ``offset`` (m, float64); the same mesh when it is 0."""
    if not np.any(offset):
        return mesh
    return Mesh(mesh.vertices + offset, mesh.faces, mesh.uv, mesh.normals)


def _translation(offset: np.ndarray) -> np.ndarray:
    t = np.eye(4)
    t[:3, 3] = offset
    return t


def pose_to_local(pose: np.ndarray, origin: np.ndarray) -> np.ndarray:
    """Camera-from-world ``(4, 4)`` -> camera-from-local."""
    return pose if not np.any(origin) else pose @ _translation(origin)


def pose_to_world(pose: np.ndarray, origin: np.ndarray) -> np.ndarray:
    """Camera-from-local ``(4, 4)`` -> camera-from-world (``pose_to_local``'s inverse)."""
    return pose if not np.any(origin) else pose @ _translation(-origin)


def position_digits(origin: np.ndarray) -> int:
    """Significant digits a world position needs in a text file to keep the local frame's 0.1 um
    (7 near the origin: float32's; one more per power of ten the origin is away)."""
    return 7 + int(np.ceil(np.log10(1.0 + float(np.abs(origin).max()))))
