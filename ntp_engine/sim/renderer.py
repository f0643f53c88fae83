"""The renderer behind the virtual scanner and the relit evaluation: an object (mesh + SVBRDF maps)
standing on a textured backdrop, photographed by a scanner (paper Eq. 1 per pixel).

World frame = the mesh's frame (metres, z up); the object stands on a backdrop at z = 0 (random grey
blocks at two scales, like AR markers, so structure-from-motion finds features), and optionally on
a printed marker board (``scanner.board``) lying on it.

Image formation per pixel: Embree primary ray; on the object, the maps sampled at the hit's UV
(bilinear) give rho_d, rho_s, alphas and the object-space shading frame; B from every emitter with
Psi, 1/r^2, the colour matrix and per-emitter shadowing, summed in the fit's fused loop
(``physics.pattern_sums``, float64). Shadows are traced to *emitter clusters*
(k-means over the emitters' quadrature points, 64 by default) and shared by a cluster's emitters:
exact per-LED shadow rays cost ~50 M rays per photo; ``ntp bench virtual-scan`` measures the error
this makes. The backdrop is diffuse, lit by the clusters without shadows. Images are linear pixel
values after auto-exposure (``Scanner.exposure``); the virtual scanner adds the sensor.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from ..io.maps import SVBRDFMaps
from ..io.mesh import Mesh
from ..io.raycast import RayCaster
from ..physics.measurement import measurement_rgb
from ..physics.pattern_sums import pattern_sums
from ..scanner import camera
from ..scanner.board import Board
from ..scanner.scanner import Scanner

BACKDROP_Z = -1e-4
BACKDROP_HALF = 0.4


def marker_albedo(xy: np.ndarray) -> np.ndarray:
    """Grey albedo of the backdrop at world (x, y): random blocks of 1.5 cm and 0.5 cm cells."""

    def cell_hash(ix, iy, salt):
        h = (ix * 73856093) ^ (iy * 19349663) ^ salt
        h = (h ^ (h >> 13)) * 1274126177
        return ((h ^ (h >> 16)) & 0xFFFF) / 65535.0

    big = cell_hash(np.floor(xy[:, 0] / 0.015).astype(np.int64), np.floor(xy[:, 1] / 0.015).astype(np.int64), 17)
    small = cell_hash(np.floor(xy[:, 0] / 0.005).astype(np.int64), np.floor(xy[:, 1] / 0.005).astype(np.int64), 91)
    return 0.12 + 0.45 * big + 0.3 * small


def backdrop_triangles() -> np.ndarray:
    """The backdrop square ``(2, 3, 3)``: two triangles at z = BACKDROP_Z, BACKDROP_HALF m each way."""
    h, z = BACKDROP_HALF, BACKDROP_Z
    quad = np.array([[-h, -h, z], [h, -h, z], [h, h, z], [-h, h, z]])
    return quad[[[0, 1, 2], [0, 2, 3]]]


def emitter_clusters(scanner: Scanner, k: int) -> tuple[np.ndarray, np.ndarray]:
    """k-means over the emitters' quadrature points (camera space): centres ``(C, 3)`` and the
    cluster of every point ``(L, Q)``. Deterministic (initialised on a spread subset)."""
    pts, _ = scanner.emitter_samples(torch.float64)
    flat = pts.reshape(-1, 3).numpy()
    k = min(k, len(flat))
    centres = flat[np.linspace(0, len(flat) - 1, k).round().astype(int)].copy()
    for _ in range(20):
        assign = np.argmin(((flat[:, None] - centres[None]) ** 2).sum(-1), axis=1)
        for c in range(k):
            if (assign == c).any():
                centres[c] = flat[assign == c].mean(0)
    assign = np.argmin(((flat[:, None] - centres[None]) ** 2).sum(-1), axis=1)
    return centres, assign.reshape(pts.shape[:2])


class Scene:
    """The object (mesh + maps) on the backdrop, ready to render with one scanner's emitters."""

    def __init__(
        self,
        mesh: Mesh,
        maps: SVBRDFMaps,
        scanner: Scanner,
        clusters: int = 64,
        exposure: float = 1.0,
        board: tuple[Board, np.ndarray] | None = None,
    ):
        """``board``: a marker board and its world-from-board 4x4 (on the backdrop, z = 0)."""
        if mesh.uv is None:
            raise ValueError("mesh has no UVs")
        self.mesh, self.maps, self.scanner, self.uv = mesh, maps, scanner, mesh.uv
        self.caster = RayCaster([mesh.triangles, backdrop_triangles()])
        self.cluster_centres, self.cluster_of = emitter_clusters(scanner, clusters)
        # how Eq. 1 is summed per pixel: "compiled" (physics.pattern_sums, float64) or "tensor"
        # (physics.measurement_rgb in float32 torch: what ``ntp bench virtual-scan`` times it against)
        self.shading = "compiled"
        # per cluster: summed effective drive (quadrature-weighted) and mean emitter normal
        pts, w = scanner.emitter_samples(torch.float64)
        self.emitter_points = pts.numpy()  # (L, Q, 3) camera space, for exact shadows
        p_eff = scanner.effective_pattern(scanner.pattern)  # (L, 3)
        C = len(self.cluster_centres)
        drive = np.zeros((C, 3))
        np.add.at(drive, self.cluster_of.reshape(-1), (w.numpy()[..., None] * p_eff[:, None, :]).reshape(-1, 3))
        self.cluster_drive = drive
        normal = scanner.emitter_normals.mean(0)
        self.cluster_normal = normal / np.linalg.norm(normal)
        self.exposure = exposure * float(scanner.exposure(scanner.pattern))
        lo, hi = mesh.vertices.min(0), mesh.vertices.max(0)
        self.center = 0.5 * (lo + hi)
        self.board = board

    def render_linear(
        self,
        pose: np.ndarray,
        cam: Scanner,
        chunk: int = 2048,
        exact_shadows: bool = False,
        pixel_subset: np.ndarray | None = None,
        shadows: bool = True,
    ) -> tuple[np.ndarray, dict]:
        """Linear pixel values ``(H, W, 3)`` (exposure applied, before noise and quantisation) and
        per-pixel hit info. ``exact_shadows`` traces one shadow ray per emitter sample; without
        ``shadows`` every emitter lights every point it faces (the BRDF alone, as a viewer without
        shadow maps draws it)."""
        R, tr = pose[:3, :3], pose[:3, 3]
        dirs_cam = camera.pixel_rays(cam).reshape(-1, 3)
        if pixel_subset is not None:
            dirs_cam = dirs_cam[pixel_subset]
        origin = -R.T @ tr
        dirs_w = dirs_cam @ R  # R^T d for each row
        hits = self.caster.intersect(np.broadcast_to(origin, dirs_w.shape), dirs_w)
        out = np.zeros((len(dirs_w), 3))
        obj = np.nonzero(hits.geom == 0)[0]
        back = np.nonzero(hits.geom == 1)[0]
        for s in range(0, len(obj), chunk):
            idx = obj[s : s + chunk]
            out[idx] = self._shade_object(hits, idx, origin, dirs_w, R, tr, exact_shadows, shadows)
        if len(back):
            out[back] = self._shade_backdrop(origin + hits.t[back, None] * dirs_w[back], R, tr)
        shape = (cam.height, cam.width, 3) if pixel_subset is None else (len(dirs_w), 3)
        return (self.exposure * out).reshape(shape), {"geom": hits.geom}

    def _shade_object(self, hits, idx, origin, dirs_w, R, tr, exact_shadows, shadows=True) -> np.ndarray:
        faces = self.mesh.faces[hits.prim[idx]]
        u, v = hits.u[idx, None], hits.v[idx, None]
        w = 1 - u - v

        def blend(per_vertex: np.ndarray) -> np.ndarray:  # barycentric interpolation over each hit's face
            return w * per_vertex[faces[:, 0]] + u * per_vertex[faces[:, 1]] + v * per_vertex[faces[:, 2]]

        uv = blend(self.uv)
        n_geo = blend(self.mesh.normals)
        n_geo /= np.linalg.norm(n_geo, axis=1, keepdims=True)
        x_w = origin + hits.t[idx, None] * dirs_w[idx]
        m = self.maps.sample(uv)
        x_c = x_w @ R.T + tr
        if shadows:
            vis = self._visibility(x_w + 2e-5 * n_geo, R, tr, exact_shadows)
        else:
            vis = np.ones((len(idx), *self.emitter_points.shape[:2]))

        n_c, t_c, alpha = m["normal"] @ R.T, m["tangent"] @ R.T, m["roughness"]
        rho_d, rho_s = m["diffuse_albedo"], m["specular_albedo"]
        if self.shading == "tensor":

            def T(a):
                return torch.as_tensor(np.ascontiguousarray(a), dtype=torch.float32)

            x, n, t, rd, rs, ax, ay = map(T, (x_c, n_c, t_c, rho_d, rho_s, alpha[:, 0], alpha[:, 1]))
            return measurement_rgb(self.scanner, x, n, t, rd, rs, ax, ay, None, T(vis)).double().numpy()
        # Eq. 1 as the fit's fused loop sums it: measurement_rgb's factorised terms in float64,
        # each emitter sample weighed by its shadow (``ntp bench virtual-scan`` times it against the torch terms)
        x64, n64, t64, ax64, ay64 = (
            torch.from_numpy(np.ascontiguousarray(a, np.float64)) for a in (x_c, n_c, t_c, *alpha.T)
        )
        seen = torch.ones(len(idx), dtype=torch.bool)
        sums = pattern_sums(
            self.scanner, x64, n64, t64, ax64, ay64, seen, visibility=vis.reshape(len(idx), -1), peaks=False
        )
        return rho_d / math.pi * sums.diffuse.numpy() + rho_s * sums.specular.numpy()

    def _visibility(self, p_w: np.ndarray, R, tr, exact: bool) -> np.ndarray:
        """``(N, L, Q)`` 0/1: emitter sample visible from each point (cluster or exact)."""
        pts = self.emitter_points
        targets = (pts.reshape(-1, 3) if exact else self.cluster_centres) - tr  # camera -> world
        targets_w = targets @ R  # R^T (c - t)
        d = targets_w[None] - p_w[:, None]
        dist = np.linalg.norm(d, axis=-1)
        d /= np.maximum(dist[..., None], 1e-12)
        occ = self.caster.occluded(
            np.repeat(p_w, len(targets_w), 0), d.reshape(-1, 3), dist.reshape(-1) - 1e-4
        ).reshape(len(p_w), -1)
        if exact:
            return (~occ).reshape(len(p_w), *pts.shape[:2]).astype(np.float64)
        return (~occ)[:, self.cluster_of].astype(np.float64)

    def _shade_backdrop(self, x_w: np.ndarray, R, tr, chunk: int = 4096) -> np.ndarray:
        """Diffuse backdrop lit by the emitter clusters (their summed drive), unshadowed; ``chunk``
        points at a time (their (chunk, C) terms stay in cache: 3x faster than all at once)."""
        n_c = torch.as_tensor(R[:, 2], dtype=torch.float32)  # world +z in camera space
        c = torch.as_tensor(self.cluster_centres, dtype=torch.float32)
        nl = torch.as_tensor(self.cluster_normal, dtype=torch.float32)
        drive = torch.as_tensor(self.cluster_drive, dtype=torch.float32)
        out = np.empty((len(x_w), 3))
        for s in range(0, len(x_w), chunk):
            x_c = torch.as_tensor(x_w[s : s + chunk] @ R.T + tr, dtype=torch.float32)
            r2 = ((c * c).sum(-1)[None] - 2 * x_c @ c.T + (x_c * x_c).sum(-1, keepdim=True)).clamp_min(1e-8)
            inv_r = torch.rsqrt(r2)
            cos_p = ((c @ n_c)[None] - (x_c @ n_c)[:, None]) * inv_r
            cos_l = ((x_c @ nl)[:, None] - (c @ nl)[None]) * inv_r
            irr = (cos_p.clamp_min(0) * self.scanner.psi(cos_l) / r2) @ drive
            seen = ((-x_c) @ n_c > 0).to(torch.float32)[:, None]
            out[s : s + chunk] = (irr * seen).double().numpy()
        return self.support_albedo(x_w)[:, None] / math.pi * out

    def support_albedo(self, x_w: np.ndarray) -> np.ndarray:
        """Grey albedo of the backdrop at world points ``(N, 3)``: the board's print where it lies."""
        albedo = marker_albedo(x_w)
        if self.board is not None:
            board, world_from_board = self.board
            xy = (x_w - world_from_board[:3, 3]) @ world_from_board[:3, :3]
            printed, on = board.albedo(xy[:, :2])
            albedo[on] = printed[on]
        return albedo
