"""Texels of a mesh's UV atlas: the surface point, geometric normal and tangent behind each texel;
and the atlas itself for meshes without UVs (xatlas).

Convention: an H x W map, texel (row, col) centred at uv = ((col + 0.5) / W, 1 - (row + 0.5) / H)
(``io.maps.texel_uv``). A texel belongs to the triangle whose UV triangle contains its centre (ties:
the lower triangle index). Positions and frames are in the mesh's (object) space: the normal is
the barycentric blend of the smooth vertex normals, the tangent the UV-derived direction dP/du of
the triangle made orthogonal to it — a fixed, smooth t^ per texel (Eq. 4 only needs *a* consistent
frame). Texels no triangle covers are left out (seams and gaps are dilated at the end).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import xatlas

from .maps import fill_missing, texel_uv
from .mesh import Mesh, smooth_normals


@dataclass
class Texels:
    """The texels a mesh's UV triangles cover, each with its surface point and geometric frame."""

    shape: tuple[int, int]  # (H, W)
    row: np.ndarray  # (T,) int
    col: np.ndarray  # (T,) int
    face: np.ndarray  # (T,) int
    bary: np.ndarray  # (T, 3)
    position: np.ndarray  # (T, 3) object space, m
    normal: np.ndarray  # (T, 3) unit geometric normal
    tangent: np.ndarray  # (T, 3) unit, orthogonal to normal
    # (T, 2, 2) 1/m: d(n . t^, n . b^) / d(x . t^, x . b^) of the geometric normal n at the texel, in
    # its frame (b^ = n^ x t^): how fast the surface turns (``shape_operators``; ``rasterize``'s
    # ``curvature``)
    shape_operator: np.ndarray | None = None
    # (T, 2, 2) 1/m: d(u, v) / d(x . t^, x . b^) on the texel's triangle — where a step on the surface
    # lands in the map (``uv_per_metre``; ``rasterize``'s ``curvature``)
    uv_per_metre: np.ndarray | None = None

    def __len__(self) -> int:
        """T, the number of covered texels."""
        return len(self.row)

    @property
    def index(self) -> np.ndarray:
        """Flat map index row * W + col ``(T,)``."""
        return self.row * self.shape[1] + self.col

    @property
    def frame(self) -> np.ndarray:
        """Each texel's geometric frame ``(T, 3, 3)``, rows t^, b^ = n^ x t^, n^ (object space): a
        local vector v is ``frame^T v`` in object space (the refinement's ``n_loc``, ``t_loc``)."""
        return np.stack([self.tangent, np.cross(self.normal, self.tangent), self.normal], 1)

    @property
    def uv(self) -> np.ndarray:
        """uv of each texel's centre ``(T, 2)`` (``io.maps.texel_uv``)."""
        return texel_uv(self.shape)[self.row, self.col]

    def image(self, values: np.ndarray, known: np.ndarray | None = None) -> np.ndarray:
        """``values (T, C)`` as an ``(H, W, C)`` map; texels not ``known (T,)`` (default: all are)
        and those no triangle covers take the nearest known texel's (``io.maps.fill_missing``)."""
        seen = np.zeros(self.shape, bool)
        seen[self.row, self.col] = True if known is None else known
        img = np.zeros(self.shape + (values.shape[1],))
        img[self.row, self.col] = values
        return fill_missing(img, seen)


def _uv_tangents(mesh: Mesh, mesh_uv: np.ndarray) -> np.ndarray:
    """Per-face dP/du ``(F, 3)`` (unnormalised; zero for degenerate UV triangles)."""
    p = mesh.vertices[mesh.faces]
    uv = mesh_uv[mesh.faces]
    e1, e2 = p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]
    d1, d2 = uv[:, 1] - uv[:, 0], uv[:, 2] - uv[:, 0]
    det = d1[:, 0] * d2[:, 1] - d2[:, 0] * d1[:, 1]
    safe = np.where(np.abs(det) > 1e-20, det, 1.0)
    t = (e1 * d2[:, 1:2] - e2 * d1[:, 1:2]) / safe[:, None]
    return np.where((np.abs(det) > 1e-20)[:, None], t, 0.0)


def rasterize(mesh: Mesh, shape: tuple[int, int], batch: int = 1 << 22, curvature: bool = False) -> Texels:
    """All texels of an ``shape = (H, W)`` map covered by the mesh's UV triangles; with
    ``curvature``, their shape operators and ``uv_per_metre`` too (a third of the time: only the
    refinement reads them)."""
    if mesh.uv is None:
        raise ValueError("mesh has no UVs")
    h, w = shape
    uv = mesh.uv[mesh.faces]  # (F, 3, 2)
    px = np.stack([uv[..., 0] * w - 0.5, (1.0 - uv[..., 1]) * h - 0.5], -1)  # (col, row) continuous
    lo = np.clip(np.ceil(px.min(1) - 1e-9), 0, [w - 1, h - 1]).astype(np.int64)
    hi = np.clip(np.floor(px.max(1) + 1e-9), 0, [w - 1, h - 1]).astype(np.int64)
    nx, ny = np.maximum(hi[:, 0] - lo[:, 0] + 1, 0), np.maximum(hi[:, 1] - lo[:, 1] + 1, 0)
    counts = nx * ny
    faces_out, cols, rows, barys = [], [], [], []
    order = np.arange(len(counts))
    start = 0
    while start < len(order):  # bounded memory: triangles in groups of ~batch candidates
        cum = np.cumsum(counts[start:])
        stop = start + max(1, int(np.searchsorted(cum, batch, side="right")))
        f = np.repeat(order[start:stop], counts[start:stop])
        if len(f):
            first = np.repeat(np.cumsum(counts[start:stop]) - counts[start:stop], counts[start:stop])
            k = np.arange(len(f)) - first
            c = lo[f, 0] + k % nx[f]
            r = lo[f, 1] + k // nx[f]
            a, b, cc = px[f, 0], px[f, 1], px[f, 2]
            v0, v1 = b - a, cc - a
            p = np.stack([c, r], -1) - a
            den = v0[:, 0] * v1[:, 1] - v1[:, 0] * v0[:, 1]
            ok_den = np.abs(den) > 1e-12
            den = np.where(ok_den, den, 1.0)
            l1 = (p[:, 0] * v1[:, 1] - v1[:, 0] * p[:, 1]) / den
            l2 = (v0[:, 0] * p[:, 1] - p[:, 0] * v0[:, 1]) / den
            l0 = 1 - l1 - l2
            inside = ok_den & (l0 >= -1e-9) & (l1 >= -1e-9) & (l2 >= -1e-9)
            faces_out.append(f[inside])
            cols.append(c[inside])
            rows.append(r[inside])
            barys.append(np.stack([l0, l1, l2], -1)[inside])
        start = stop
    face = np.concatenate(faces_out) if faces_out else np.zeros(0, np.int64)
    col = np.concatenate(cols) if cols else np.zeros(0, np.int64)
    row = np.concatenate(rows) if rows else np.zeros(0, np.int64)
    bary = np.concatenate(barys) if barys else np.zeros((0, 3))
    # one triangle per texel: the lowest face index among those covering it
    key = row * w + col
    order = np.lexsort((face, key))
    keep = order[np.r_[True, key[order][1:] != key[order][:-1]]] if len(order) else order
    face, col, row, bary = face[keep], col[keep], row[keep], np.clip(bary[keep], 0, 1)
    bary /= bary.sum(1, keepdims=True)
    tri = mesh.faces[face]
    pos = np.einsum("tk,tkj->tj", bary, mesh.vertices[tri])
    nrm = np.einsum("tk,tkj->tj", bary, mesh.normals[tri])
    nrm /= np.maximum(np.linalg.norm(nrm, axis=1, keepdims=True), 1e-30)
    tan = _uv_tangents(mesh, mesh.uv)[face]
    tan = tan - (tan * nrm).sum(1, keepdims=True) * nrm
    bad = np.linalg.norm(tan, axis=1) < 1e-12
    if bad.any():  # degenerate UVs: any direction orthogonal to the normal
        ref = np.where(np.abs(nrm[bad, 0:1]) < 0.9, [[1.0, 0, 0]], [[0, 1.0, 0]])
        tan[bad] = ref - (ref * nrm[bad]).sum(1, keepdims=True) * nrm[bad]
    tan /= np.linalg.norm(tan, axis=1, keepdims=True)
    if not curvature:
        return Texels((h, w), row, col, face, bary, pos, nrm, tan)
    shape_op, to_uv = shape_operators(mesh, face, bary, nrm, tan), uv_per_metre(mesh, face, nrm, tan)
    return Texels((h, w), row, col, face, bary, pos, nrm, tan, shape_op, to_uv)


def shape_operators(
    mesh: Mesh, face: np.ndarray, bary: np.ndarray, normal: np.ndarray, tangent: np.ndarray
) -> np.ndarray:
    """The shape operator ``(T, 2, 2)`` (1/m) at points ``bary (T, 3)`` of triangles ``face (T,)``
    with unit geometric ``normal`` and ``tangent (T, 3)``: the derivative of the normal interpolated
    from the vertex normals (then normalised), d(n . t, n . b) / d(x . t, x . b) with b = n x t.
    Convention: 0 on a flat face; I / r on a sphere of radius r; 0 on degenerate triangles."""
    tri = mesh.faces[face]
    p, nv = mesh.vertices[tri], mesh.normals[tri]  # (T, 3 corners, 3)
    basis = np.stack([tangent, np.cross(normal, tangent)], 1)  # (T, 2, 3)
    edges = np.einsum("tij,tkj->tik", basis, p[:, 1:] - p[:, :1])  # (T, 2 axes, 2 edges)
    turns = np.einsum("tij,tkj->tik", basis, nv[:, 1:] - nv[:, :1])
    det = edges[:, 0, 0] * edges[:, 1, 1] - edges[:, 0, 1] * edges[:, 1, 0]
    scale = np.linalg.norm(p[:, 1] - p[:, 0], axis=1) * np.linalg.norm(p[:, 2] - p[:, 0], axis=1)
    ok = np.abs(det) > 1e-9 * np.maximum(scale, 1e-30)
    inv = np.linalg.inv(np.where(ok[:, None, None], edges, np.eye(2)))
    # the normalisation's derivative: the tangential part of d(raw normal) over its length
    length = np.linalg.norm(np.einsum("tk,tkj->tj", bary, nv), axis=1)
    out = turns @ inv / np.maximum(length, 1e-12)[:, None, None]
    return np.where(ok[:, None, None], out, 0.0)


def uv_per_metre(mesh: Mesh, face: np.ndarray, normal: np.ndarray, tangent: np.ndarray) -> np.ndarray:
    """``(T, 2, 2)``: d(u, v) / d(x . t, x . b) (1/m) on triangles ``face (T,)`` at texels with unit
    geometric ``normal`` and ``tangent (T, 3)``, b = n x t — the inverse of the triangle's dP/du,
    dP/dv seen along (t, b). Convention: uv as ``io.maps.texel_uv`` (v up); 0 on triangles
    degenerate in space (one degenerate in UV maps every step onto its line, as its texels do)."""
    if mesh.uv is None:
        raise ValueError("mesh has no UVs")
    p, uv = mesh.vertices[mesh.faces[face]], mesh.uv[mesh.faces[face]]
    basis = np.stack([tangent, np.cross(normal, tangent)], 1)  # (T, 2, 3)
    edges = np.einsum("tij,tkj->tik", basis, p[:, 1:] - p[:, :1])  # (T, 2 axes, 2 edges)
    duv = (uv[:, 1:] - uv[:, :1]).transpose(0, 2, 1)  # (T, 2 uv, 2 edges)
    det = edges[:, 0, 0] * edges[:, 1, 1] - edges[:, 0, 1] * edges[:, 1, 0]
    scale = np.linalg.norm(p[:, 1] - p[:, 0], axis=1) * np.linalg.norm(p[:, 2] - p[:, 0], axis=1)
    ok = np.abs(det) > 1e-9 * np.maximum(scale, 1e-30)
    out = duv @ np.linalg.inv(np.where(ok[:, None, None], edges, np.eye(2)))
    return np.where(ok[:, None, None], out, 0.0)


def uv_atlas(mesh: Mesh, resolution: int) -> Mesh:
    """The mesh with xatlas UVs (vertices split at seams); texel density set from the mesh area so
    the atlas fills a ``resolution``^2 map."""
    atlas = xatlas.Atlas()
    atlas.add_mesh(mesh.vertices.astype(np.float32), mesh.faces.astype(np.uint32))
    pack = xatlas.PackOptions()
    pack.resolution = resolution
    pack.texels_per_unit = 0.8 * resolution / max(np.sqrt(mesh.area()), 1e-9)
    pack.padding = 2
    atlas.generate(pack_options=pack)
    vmap, faces, uv = atlas[0]
    v = mesh.vertices[vmap]
    return Mesh(v, faces.astype(np.int64), uv.astype(np.float64), smooth_normals(v, faces.astype(np.int64)))
