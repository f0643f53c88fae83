"""Ray casting with Embree (embreex): primary hits and occlusion, batched over numpy arrays.

Convention: rays in the scene's frame (world/object space, metres); directions need not be unit
for intersection (``t`` is then in units of the direction's length). Geometry ids are the order in
which meshes were added.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from embreex import rtcore_scene as rtcs
from embreex.mesh_construction import TriangleMesh


@dataclass
class Hits:
    """The first hit of each ray (``geom`` -1 where a ray hits nothing)."""

    geom: np.ndarray  # (R,) int: geometry id, -1 for a miss
    prim: np.ndarray  # (R,) int: triangle index within that geometry
    u: np.ndarray  # (R,) barycentric weight of vertex 1
    v: np.ndarray  # (R,) barycentric weight of vertex 2
    t: np.ndarray  # (R,) ray parameter of the hit


class RayCaster:
    """An Embree scene of one or more triangle sets, queried in batches of rays."""

    def __init__(self, triangle_sets: list[np.ndarray]):
        """``triangle_sets``: one ``(F, 3, 3)`` array of triangle corners per geometry."""
        self.scene = rtcs.EmbreeScene()
        self._meshes = [TriangleMesh(self.scene, np.ascontiguousarray(t, dtype=np.float32)) for t in triangle_sets]

    def intersect(self, origins: np.ndarray, directions: np.ndarray) -> Hits:
        """The first hit of each ray ``origins, directions (R, 3)``."""
        o = np.ascontiguousarray(origins, dtype=np.float32)
        d = np.ascontiguousarray(directions, dtype=np.float32)
        r = self.scene.run(o, d, output=1)
        return Hits(
            r["geomID"].astype(np.int64),
            r["primID"].astype(np.int64),
            r["u"].astype(np.float64),
            r["v"].astype(np.float64),
            r["tfar"].astype(np.float64),
        )

    def occluded(self, origins: np.ndarray, directions: np.ndarray, distances: np.ndarray) -> np.ndarray:
        """Boolean ``(R,)``: something lies on the ray before ``distances`` (unit directions)."""
        o = np.ascontiguousarray(origins, dtype=np.float32)
        d = np.ascontiguousarray(directions, dtype=np.float32)
        dist = np.ascontiguousarray(distances, dtype=np.float32)
        return self.scene.run(o, d, dists=dist, query="OCCLUDED") != -1
