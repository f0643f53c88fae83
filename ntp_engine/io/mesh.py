"""Triangle meshes with UVs: loading (OBJ/PLY via trimesh), smooth normals, OBJ writing.

Convention: metres; UV origin at the bottom-left of the texture (Blender/OpenGL), so texture row 0
(the top of an image file) is v = 1. Vertices are split where UVs are (one UV per vertex).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .atomic import atomic_path
from .errors import NtpInputError
from .input_file import MAX_BYTES, regular_file


@dataclass
class Mesh:
    """A triangle mesh in metres, with optional per-vertex UVs and unit vertex normals."""

    vertices: np.ndarray  # (V, 3) float64, m
    faces: np.ndarray  # (F, 3) int64
    uv: np.ndarray | None  # (V, 2) or None
    normals: np.ndarray  # (V, 3) unit, area-weighted smooth normals unless the file had them

    @property
    def triangles(self) -> np.ndarray:
        """Corner positions ``(F, 3, 3)``."""
        return self.vertices[self.faces]

    def face_normals(self) -> np.ndarray:
        """Unit face normals ``(F, 3)`` (right-handed winding)."""
        tri = self.triangles
        n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
        return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-30)

    def area(self) -> float:
        """Surface area, m^2."""
        tri = self.triangles
        return float(0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1).sum())


def welded(vertices: np.ndarray) -> np.ndarray:
    """Each vertex's index ``(V,)`` among the vertices merged by position (to 1 nm): the copies a
    UV seam splits share one."""
    return np.unique(np.round(vertices, 9), axis=0, return_inverse=True)[1].reshape(-1)


def smooth_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted vertex normals; vertices split at UV seams are merged by position first
    (``welded``), so a seam does not show in the shading."""
    tri = vertices[faces]
    fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])  # length = 2 * area
    key = welded(vertices)
    acc = np.zeros((key.max() + 1, 3))
    for k in range(3):
        np.add.at(acc, key[faces[:, k]], fn)
    n = acc[key]
    return n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-30)


def load_mesh(path: str | Path) -> Mesh:
    """Read an OBJ or PLY (metres). Raises NtpInputError naming the file on any problem."""
    import trimesh

    path = Path(path)
    regular_file(path, MAX_BYTES["mesh"], "mesh file not found")
    try:
        with warnings.catch_warnings():  # numpy's parse warnings: the checks below say what is wrong, once
            warnings.simplefilter("ignore")
            m = trimesh.load(path, force="mesh", process=False)
        if not isinstance(m, trimesh.Trimesh):
            raise NtpInputError(path, "no triangles in mesh")
        vertices = np.asarray(m.vertices, dtype=np.float64)
        faces = np.asarray(m.faces, dtype=np.int64)
    except NtpInputError:
        raise
    except Exception as err:  # noqa: BLE001 - trimesh raises many types for bad files
        raise NtpInputError(path, f"cannot read mesh ({type(err).__name__}: {err})") from None
    if faces.ndim != 2 or len(faces) == 0:
        raise NtpInputError(path, "no triangles in mesh")
    if vertices.ndim != 2 or vertices.shape[1] != 3 or faces.shape[1] != 3:
        raise NtpInputError(path, f"not a triangle mesh (vertices {vertices.shape}, faces {faces.shape})")
    if faces.min() < 0 or faces.max() >= len(vertices):
        raise NtpInputError(path, f"a face names a vertex the mesh does not have (of {len(vertices)})")
    _check_finite(path, vertices, "vertex position (v)")
    uv = None
    vis = getattr(m, "visual", None)
    if vis is not None and getattr(vis, "uv", None) is not None and len(vis.uv) == len(vertices):
        uv = np.asarray(vis.uv, dtype=np.float64)
        if uv.ndim != 2 or uv.shape[1] != 2:
            raise NtpInputError(path, f"texture coordinates (vt) are not pairs (shape {uv.shape})")
        _check_finite(path, uv, "texture coordinate (vt)")
    return Mesh(vertices, faces, uv, smooth_normals(vertices, faces))


def _check_finite(path: Path, values: np.ndarray, what: str) -> None:
    """``NtpInputError`` quoting the first row of ``values`` with a NaN or infinity."""
    bad = np.flatnonzero(~np.isfinite(values).all(1))
    if len(bad):
        row = " ".join(f"{x:g}" for x in values[bad[0]])
        raise NtpInputError(path, f"a {what} is not finite ({row}; at {len(bad)} of {len(values)} vertices)")


def save_obj(path: str | Path, mesh: Mesh, digits: int = 7) -> None:
    """Write positions (``digits`` significant digits), UVs (if any) and normals; faces as v/vt/vn
    (atomic)."""
    lines = ["# ntp mesh (metres)"]
    lines += [f"v {x:.{digits}g} {y:.{digits}g} {z:.{digits}g}" for x, y, z in mesh.vertices]
    if mesh.uv is not None:
        lines += [f"vt {u:.7g} {v:.7g}" for u, v in mesh.uv]
    lines += [f"vn {x:.6g} {y:.6g} {z:.6g}" for x, y, z in mesh.normals]
    f = mesh.faces + 1
    if mesh.uv is not None:
        lines += [f"f {a}/{a}/{a} {b}/{b}/{b} {c}/{c}/{c}" for a, b, c in f]
    else:
        lines += [f"f {a}//{a} {b}//{b} {c}//{c}" for a, b, c in f]
    with atomic_path(path) as tmp:
        tmp.write_text("\n".join(lines) + "\n")
