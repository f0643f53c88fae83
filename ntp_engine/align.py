"""Similarity alignment of a structure-from-motion reconstruction to the pre-scanned mesh.

Convention: the mesh frame is z up, metres, and (by default) the object stands on a flat support
whose plane is the mesh's lowest z — how a pre-scan on a table or marker mat comes out. SfM poses
are camera-from-world 4x4 in an arbitrary frame and scale; the result maps SfM points to the mesh
frame, ``x_mesh = s R x_sfm + t``.

Method (SfM clouds of a hand-held scan are mostly the support, with only tens of points on the
object): RANSAC plane = the support; the optical axes converge on the object, and the scanner is
held at its working distance (the valid volume's centre), which gives the starting scale. With the
plane fixing tilt and height, a trimmed, scale-aware ICP of the points above the plane against
dense samples of the mesh solves azimuth, scale and the in-plane shift, from 36 start azimuths and
then on a 0.25-degree grid around the best; the winner has the lowest score: a truncated quadratic
(MSAC) of the object points' distances to the mesh plus one outlier's cost per support point that
would lie under the object (the hole the object leaves in the support cloud is its footprint, which
fixes the azimuth where the object's own points are few). A point-to-plane Gauss-Newton polish
ends it.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from .mesh import Mesh
from .raycast import RayCaster


@dataclass
class Alignment:
    scale: float
    rotation: np.ndarray  # (3, 3)
    translation: np.ndarray  # (3,)
    residual_m: float  # RMS distance of the inlier object points to the mesh, metres
    object_points: int  # SfM points above the support used by the ICP
    kept_points: int  # of which are inliers (closer to the mesh than 0.6% of its size)
    support_points: int

    def apply(self, x: np.ndarray) -> np.ndarray:
        return self.scale * x @ self.rotation.T + self.translation

    def camera_from_mesh(self, camera_from_sfm: np.ndarray) -> np.ndarray:
        """(4, 4) pose in the SfM frame -> the same camera's pose in the mesh frame (metres)."""
        R_c, t_c = camera_from_sfm[:3, :3], camera_from_sfm[:3, 3]
        out = np.eye(4)
        out[:3, :3] = R_c @ self.rotation.T
        out[:3, 3] = self.scale * t_c - out[:3, :3] @ self.translation
        return out


def convergence_point(camera_from_world: list[np.ndarray]) -> np.ndarray:
    """Least-squares point closest to every camera's optical axis (+z of the camera)."""
    A, b = np.zeros((3, 3)), np.zeros(3)
    for m in camera_from_world:
        c, d = -m[:3, :3].T @ m[:3, 3], m[2, :3]
        P = np.eye(3) - np.outer(d, d)
        A += P
        b += P @ c
    return np.linalg.lstsq(A, b, rcond=None)[0]  # parallel axes: the least-norm point


def ransac_plane(points: np.ndarray, threshold: float, iterations: int = 400,
                 seed: int = 0) -> tuple[np.ndarray, float, np.ndarray]:
    """Dominant plane ``n·x = d`` (unit n) and its inlier mask; refined by least squares."""
    rng = np.random.default_rng(seed)
    tri = points[rng.integers(0, len(points), (iterations, 3))]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    ok = np.linalg.norm(n, axis=1) > 0
    n = n[ok] / np.linalg.norm(n[ok], axis=1, keepdims=True)
    d = (n * tri[ok, 0]).sum(1)
    counts = np.zeros(len(n), np.int64)
    for a in range(0, len(n), 50):  # (50, P) distances at a time
        counts[a:a + 50] = (np.abs(n[a:a + 50] @ points.T - d[a:a + 50, None]) < threshold).sum(1)
    best = int(np.argmax(counts))
    inl = np.abs(points @ n[best] - d[best]) < threshold
    centre = points[inl].mean(0)
    normal = np.linalg.svd(points[inl] - centre)[2][2]
    return normal, float(normal @ centre), np.abs(points @ normal - normal @ centre) < threshold


def _surface_samples(mesh: Mesh, count: int, seed: int = 0, normals: bool = False):
    """Area-uniform points on the mesh ``(count, 3)`` (and their faces' unit normals)."""
    tri = mesh.triangles
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    area = 0.5 * np.linalg.norm(cross, axis=1)
    rng = np.random.default_rng(seed)
    f = rng.choice(len(tri), count, p=area / area.sum())
    u, v = rng.random(count), rng.random(count)
    flip = u + v > 1
    u[flip], v[flip] = 1 - u[flip], 1 - v[flip]
    pts = tri[f, 0] + u[:, None] * (tri[f, 1] - tri[f, 0]) + v[:, None] * (tri[f, 2] - tri[f, 0])
    if not normals:
        return pts
    return pts, cross[f] / np.maximum(2 * area[f, None], 1e-300)


def align_to_mesh(points: np.ndarray, poses: list[np.ndarray], mesh: Mesh, working_distance: float,
                  support_plane: bool = True, keep: float = 0.5, iterations: int = 40) -> Alignment:
    """Similarity from the SfM frame to the mesh frame. ``points`` (P, 3) SfM cloud, ``poses`` the
    registered cameras (camera-from-SfM), ``working_distance`` metres from camera to object centre.

    Raises ValueError when there is nothing to align (too few points above the support)."""
    c = convergence_point(poses)
    centres = np.array([-m[:3, :3].T @ m[:3, 3] for m in poses])
    L = float(np.median(np.linalg.norm(centres - c, axis=1)))
    s0 = working_distance / L
    lo, hi = mesh.vertices.min(0), mesh.vertices.max(0)
    size = float(np.linalg.norm(hi - lo))
    z_support = float(lo[2])
    samples, sample_normals = _surface_samples(mesh, 200_000, normals=True)
    tree = cKDTree(samples)

    if support_plane:
        n, d, on_plane = ransac_plane(points, threshold=0.004 * size / s0)
        if (centres @ n - d).mean() < 0:
            n, d = -n, -d
        height = points @ n - d
        foot = c - (c @ n - d) * n
        radial = np.linalg.norm((points - foot) - height[:, None] * n, axis=1) * s0
        obj = (height * s0 > 0.01 * size) & (height * s0 < 1.3 * (hi[2] - lo[2])) & (radial < 0.75 * size)
        support = on_plane & (radial < 1.5 * size)
        # rotation taking n to +z, then the foot of the convergence point onto the mesh's centre
        z = np.array([0.0, 0.0, 1.0])
        v, cth = np.cross(n, z), float(n @ z)
        K = np.array([[0, -v[2], v[1]], [v[2], 0, -v[0]], [-v[1], v[0], 0]])
        R_tilt = np.eye(3) + K + K @ K / (1 + cth) if cth > -0.999 else np.diag([1.0, -1.0, -1.0])
        anchor, target = foot, np.array([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, z_support])
    else:
        obj = np.linalg.norm(points - c, axis=1) * s0 < size
        support = np.zeros(len(points), bool)
        R_tilt, anchor, target = np.eye(3), points[obj].mean(0) if obj.any() else c, samples.mean(0)
    P, S = points[obj], points[support]
    if len(P) < 6:
        raise ValueError(f"only {len(P)} structure-from-motion points lie on the object (need 6)")
    A = (P - anchor) @ R_tilt.T  # object points with the support plane as z = 0 (SfM units)
    B = (S - anchor) @ R_tilt.T
    tau = 0.006 * size  # inlier distance (1 mm on a 16 cm object)
    caster = RayCaster([mesh.triangles])
    up = np.tile([0.0, 0.0, 1.0], (len(S), 1))

    def place(X: np.ndarray, s: float, yaw: float, txy: np.ndarray) -> np.ndarray:
        c, sn = np.cos(yaw), np.sin(yaw)
        xy = s * X[:, :2] @ np.array([[c, sn], [-sn, c]]) + txy
        return np.column_stack([xy, s * X[:, 2] + target[2]])

    def score(s: float, yaw: float, txy: np.ndarray) -> tuple[float, np.ndarray]:
        dist, _ = tree.query(place(A, s, yaw, txy))
        value = float(np.minimum(dist, tau) @ np.minimum(dist, tau))  # truncated quadratic (MSAC)
        if len(S):  # support points cannot lie under the object: each one there costs an outlier
            xs = place(B, s, yaw, txy)
            xs[:, 2] += 0.1 * tau
            value += tau ** 2 * float(caster.occluded(xs, up, np.full(len(S), 2 * size)).sum())
        return value, dist

    def icp(s: float, yaw: float, txy: np.ndarray, free_yaw: bool) -> tuple[float, float, np.ndarray]:
        for _ in range(iterations):
            dist, j = tree.query(place(A, s, yaw, txy))
            kept = dist <= max(np.quantile(dist, keep), tau)
            a, q = A[kept], samples[j[kept]]
            yaw_new = yaw
            if free_yaw:  # yaw from the 2D Procrustes of the xy parts
                ac, qc = a[:, :2] - a[:, :2].mean(0), q[:, :2] - q[:, :2].mean(0)
                yaw_new = float(np.arctan2((ac[:, 0] * qc[:, 1] - ac[:, 1] * qc[:, 0]).sum(), (ac * qc).sum()))
            c, sn = np.cos(yaw_new), np.sin(yaw_new)
            rot = a[:, :2] @ np.array([[c, sn], [-sn, c]])
            n = len(a)  # (s, tx, ty) by linear least squares over x, y and z
            M = np.zeros((3 * n, 3))
            M[:n, 0], M[:n, 1] = rot[:, 0], 1
            M[n:2 * n, 0], M[n:2 * n, 2] = rot[:, 1], 1
            M[2 * n:, 0] = a[:, 2]
            rhs = np.concatenate([q[:, 0], q[:, 1], q[:, 2] - target[2]])
            s_new, tx, ty = np.linalg.lstsq(M, rhs, rcond=None)[0]
            moved = abs(s_new / s - 1) + abs(yaw_new - yaw) + np.abs(np.array([tx, ty]) - txy).max() / size
            s, yaw, txy = float(s_new), yaw_new, np.array([tx, ty])
            if moved < 1e-9:
                break
        return s, yaw, txy

    best = None
    # coarse: free ICP from 36 azimuths; fine: the azimuth held on a 0.25-degree grid around the
    # winner (point-to-point ICP barely turns a nearly round object; the score still tells)
    for yaws, free in ((np.radians(np.arange(0, 360, 10)), True), (None, False)):
        if yaws is None:
            yaws = best[2] + np.radians(np.arange(-8, 8.01, 0.25))
        for yaw0 in yaws:
            s, yaw, txy = icp(best[1] if not free else s0, float(yaw0),
                              best[3].copy() if not free else target[:2].copy(), free)
            value, dist = score(s, yaw, txy)
            if best is None or value < best[0]:
                best = (value, s, yaw, txy, dist)
    _, s, yaw, txy, _ = best

    # polish: point-to-plane Gauss-Newton on (scale, azimuth, x, y) over the inliers — free of the
    # samples' spacing, which biases point-to-point correspondences by a few tenths of a millimetre
    for _ in range(iterations):
        xp = place(A, s, yaw, txy)
        dist, j = tree.query(xp)
        kept = dist < tau
        if kept.sum() < 4:
            break
        a, q, nq = A[kept], samples[j[kept]], sample_normals[j[kept]]
        c, sn = np.cos(yaw), np.sin(yaw)
        rot = a[:, :2] @ np.array([[c, sn], [-sn, c]])  # R(yaw) a_xy
        drot = a[:, :2] @ np.array([[-sn, c], [-c, -sn]])  # dR/dyaw a_xy
        J = np.column_stack([(nq[:, :2] * rot).sum(1) + nq[:, 2] * a[:, 2], (nq[:, :2] * drot).sum(1),
                             nq[:, 0], nq[:, 1]])
        rhs = (nq * q).sum(1) - nq[:, 2] * target[2]
        s_new, w, tx, ty = np.linalg.lstsq(J, rhs, rcond=None)[0]
        yaw_new = yaw + w / s_new
        moved = abs(s_new / s - 1) + abs(yaw_new - yaw)
        s, yaw, txy = float(s_new), float(yaw_new), np.array([tx, ty])
        if moved < 1e-10:
            break
    value, dist = score(s, yaw, txy)
    c, sn = np.cos(yaw), np.sin(yaw)
    R = np.array([[c, -sn, 0], [sn, c, 0], [0, 0, 1]]) @ R_tilt
    t = np.array([txy[0], txy[1], target[2]]) - s * R @ anchor
    kept = dist < tau
    rms = float(np.sqrt((dist[kept] ** 2).mean())) if kept.any() else float("inf")
    best = (None, Alignment(s, R, t, rms, len(P), int(kept.sum()), len(S)))
    return best[1]
