"""The gallery's shapes: meshes with UVs, made by code, each chosen for what it breaks.

Convention: object space = world space, metres, z up; every shape stands on the backdrop (lowest
point at z = 0) and fits the scanner's 15 cm valid volume. Parametric shapes are grids of quads
(two triangles each) over (u, v) in [0, 1]^2 whose UVs are (u, v); the box gets an xatlas atlas.

- ``dome``: the demo object (``demo_asset.dome_mesh``): round, nothing faces down.
- ``vase``: a surface of revolution with a 2% elliptic belly: nearly rotationally symmetric, so
  the azimuth of the SfM cloud against the mesh is (nearly) ambiguous.
- ``blob``: an organic star-shaped body resting on its lowest point, with lobes, dents and an
  underside facing down (self-shadowing, concavities, overhangs).
- ``box``: a cuboid with flat faces and sharp edges (faces subdivided so vertex-normal blending
  only bends the outer ring of each face), turned 25 deg about z.
- ``knot``: a (2, 3) torus knot tube: thin, holed, self-occluding.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from ..io.mesh import Mesh, smooth_normals
from ..io.texels import uv_atlas
from .demo_asset import dome_mesh

SurfaceFn = Callable[[np.ndarray, np.ndarray], np.ndarray]  # (u, v) grids -> points (..., 3)


def grid_mesh(surface: SurfaceFn, n_u: int, n_v: int) -> Mesh:
    """A mesh of ``n_u`` x ``n_v`` quads over (u, v) in [0, 1]^2 with UVs (u, v); vertices on the
    u = 0 / u = 1 seam are duplicated (their normals still agree: ``smooth_normals`` merges them)."""
    u = np.linspace(0, 1, n_u + 1)
    v = np.linspace(0, 1, n_v + 1)
    vv, uu = np.meshgrid(v, u, indexing="ij")
    p = surface(uu, vv).reshape(-1, 3)
    idx = np.arange((n_v + 1) * (n_u + 1)).reshape(n_v + 1, n_u + 1)
    a, b, c, d = idx[:-1, :-1], idx[:-1, 1:], idx[1:, 1:], idx[1:, :-1]
    faces = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)])
    return Mesh(p, faces, np.stack([uu, vv], -1).reshape(-1, 2), smooth_normals(p, faces))


def _on_ground(mesh: Mesh) -> Mesh:
    """The mesh moved so its lowest point is at z = 0 (and centred in x, y)."""
    lo, hi = mesh.vertices.min(0), mesh.vertices.max(0)
    shift = np.array([-(lo[0] + hi[0]) / 2, -(lo[1] + hi[1]) / 2, -lo[2]])
    return Mesh(mesh.vertices + shift, mesh.faces, mesh.uv, mesh.normals)


def vase_mesh(n_u: int = 128, n_v: int = 64) -> Mesh:
    """Height 11 cm: base 3 cm radius, belly 4.6 cm, neck 1.7 cm, lip 2.3 cm, closed by a rounded
    stopper (radius -> 0 at the top, v = 1); u = azimuth / 2 pi, v along the profile."""
    z_k = np.array([0.0, 0.035, 0.075, 0.092, 0.100, 0.106, 0.110])
    r_k = np.array([0.030, 0.046, 0.017, 0.023, 0.020, 0.012, 0.0])

    def surface(u, v):
        phi = 2 * math.pi * u
        z = np.interp(v, np.linspace(0, 1, len(z_k)), z_k)
        r = np.interp(z, z_k, r_k) * (1 + 0.02 * np.cos(2 * phi))
        return np.stack([r * np.cos(phi), r * np.sin(phi), z], -1)

    return grid_mesh(surface, n_u, n_v)


def blob_mesh(n_u: int = 128, n_v: int = 64) -> Mesh:
    """An organic body, radius 4.5 cm x (1 + lobes - dents) about its centre; u = azimuth / 2 pi,
    v = polar angle / pi from the bottom."""

    def surface(u, v):
        phi, theta = 2 * math.pi * u, math.pi * v  # theta = 0 at the bottom
        k = (
            1
            + 0.22 * np.sin(theta) ** 2 * np.cos(3 * phi + 0.4)
            + 0.15 * np.cos(theta) * np.sin(2 * phi)
            - 0.18 * np.exp(-((phi - 4.0) ** 2 + (theta - 1.9) ** 2) / 0.12)  # a dent
            + 0.12 * np.exp(-((phi - 1.3) ** 2 + (theta - 1.2) ** 2) / 0.08)  # a knob
        )
        r = 0.045 * k
        d = np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), -np.cos(theta)], -1)
        return r[..., None] * d * np.array([1.0, 0.8, 0.85])

    return _on_ground(grid_mesh(surface, n_u, n_v))


def box_mesh(size: tuple[float, float, float] = (0.09, 0.065, 0.05), n: int = 12, turn_deg: float = 25.0) -> Mesh:
    """A cuboid of ``size`` (m) standing on its base, each visible face an n x n grid (the base is
    left out: it lies on the backdrop), turned ``turn_deg`` about z; xatlas UVs."""
    h = np.array(size) / 2
    faces_3d = [  # (origin corner, edge a, edge b) with a x b pointing outwards
        (np.array([-1, -1, 1]), np.array([2, 0, 0]), np.array([0, 2, 0])),  # top
        (np.array([-1, -1, -1]), np.array([2, 0, 0]), np.array([0, 0, 2])),  # -y
        (np.array([1, 1, -1]), np.array([-2, 0, 0]), np.array([0, 0, 2])),  # +y
        (np.array([1, -1, -1]), np.array([0, 2, 0]), np.array([0, 0, 2])),  # +x
        (np.array([-1, 1, -1]), np.array([0, -2, 0]), np.array([0, 0, 2])),  # -x
    ]
    verts: list[np.ndarray] = []
    tris: list[np.ndarray] = []
    s = np.linspace(0, 1, n + 1)
    ss, tt = np.meshgrid(s, s, indexing="ij")
    idx = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    a, b, c, d = idx[:-1, :-1], idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]
    quad = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)])
    for o, ea, eb in faces_3d:
        p = (o[None] + ss.reshape(-1, 1) * ea + tt.reshape(-1, 1) * eb) * h
        tris.append(quad + sum(x.shape[0] for x in verts))
        verts.append(p)
    v = np.concatenate(verts)
    turn = math.radians(turn_deg)
    rot = np.array([[math.cos(turn), -math.sin(turn), 0], [math.sin(turn), math.cos(turn), 0], [0, 0, 1]])
    v = v @ rot.T + np.array([0, 0, h[2]])
    f = np.concatenate(tris)
    return uv_atlas(Mesh(v, f, None, smooth_normals(v, f)), 256)


def knot_mesh(n_u: int = 384, n_v: int = 24, tube: float = 0.009) -> Mesh:
    """A (2, 3) torus knot (ring radius 3.4 cm, winding radius 1.5 cm) swept by a tube of radius
    ``tube``; u along the knot, v around the tube (parallel-transport-free frame: the tube's
    normal plane spanned by the curve's principal normal and binormal)."""
    R, r = 0.034, 0.015

    def curve(s):
        return np.stack(
            [(R + r * np.cos(3 * s)) * np.cos(2 * s), (R + r * np.cos(3 * s)) * np.sin(2 * s), r * np.sin(3 * s)], -1
        )

    def surface(u, v):
        s, a = 2 * math.pi * u, -2 * math.pi * v  # -v: the normal P_u x P_v points outwards
        eps = 1e-4
        c = curve(s)
        t = curve(s + eps) - curve(s - eps)
        t /= np.linalg.norm(t, axis=-1, keepdims=True)
        k = curve(s + eps) - 2 * c + curve(s - eps)
        nrm = k - (k * t).sum(-1, keepdims=True) * t
        nrm /= np.linalg.norm(nrm, axis=-1, keepdims=True)
        bi = np.cross(t, nrm)
        return c + tube * (np.cos(a)[..., None] * nrm + np.sin(a)[..., None] * bi)

    return _on_ground(grid_mesh(surface, n_u, n_v))


SHAPES: dict[str, Callable[[], Mesh]] = {
    "dome": dome_mesh,
    "vase": vase_mesh,
    "blob": blob_mesh,
    "box": box_mesh,
    "knot": knot_mesh,
}
