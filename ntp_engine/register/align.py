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

from dataclasses import dataclass, field

import numpy as np
from scipy.cluster.vq import kmeans2
from scipy.optimize import minimize_scalar
from scipy.spatial import cKDTree

from ..io.mesh import Mesh
from ..io.raycast import RayCaster
from .settings import TUNING


@dataclass
class Alignment:
    """A similarity from the SfM frame to the mesh frame, ``x_mesh = s R x_sfm + t``, and its fit."""

    scale: float
    rotation: np.ndarray  # (3, 3)
    translation: np.ndarray  # (3,)
    residual_m: float  # RMS distance of the inlier object points to the mesh, metres
    object_points: int  # SfM points above the support used by the ICP
    kept_points: int  # of which are inliers (closer to the mesh than 0.6% of its size)
    support_points: int
    # the azimuth search's candidates (one per coarse start, converged): (azimuth deg, score), best
    # first, and how much worse the best alternative more than TUNING.align.ambiguous_deg away scores (relative)
    candidates: list[tuple[float, float]] = field(default_factory=list)
    azimuth_margin: float = float("inf")
    # a metric placement's spread (``align_on_board``): 1 sigma of the azimuth (rad) and shift (m)
    azimuth_sigma: float = float("nan")
    shift_sigma: np.ndarray = field(default_factory=lambda: np.full(3, np.nan))
    # a metric placement's rivals (``align_on_board``): per candidate (``candidates``' order) how
    # significantly worse it fits the points than the answer, by surface regions (``_AzimuthSearch.rival_z``)
    candidate_z: list[float] = field(default_factory=list)

    def apply(self, x: np.ndarray) -> np.ndarray:
        """SfM points ``(..., 3)`` in the mesh frame (metres)."""
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


def camera_similarity(
    poses: dict[str, np.ndarray], target: dict[str, np.ndarray], scale: bool = True
) -> tuple[float, np.ndarray, np.ndarray] | None:
    """The similarity ``x_target = s R x + t`` that best fits the camera centres of ``poses``
    (camera-from-world 4x4, any frame and scale) to those of the same names in ``target`` (Umeyama,
    least squares; ``s`` = 1 without ``scale``); None with fewer than 3 names in common."""
    names = [n for n in poses if n in target]
    if len(names) < 3:
        return None
    a = np.array([-poses[n][:3, :3].T @ poses[n][:3, 3] for n in names])
    b = np.array([-target[n][:3, :3].T @ target[n][:3, 3] for n in names])
    ma, mb = a.mean(0), b.mean(0)
    U, S, Vt = np.linalg.svd((a - ma).T @ (b - mb))
    d = np.array([1.0, 1.0, np.sign(np.linalg.det(Vt.T @ U.T))])
    R = Vt.T @ np.diag(d) @ U.T
    s = float((S * d).sum() / max(float(((a - ma) ** 2).sum()), 1e-300)) if scale else 1.0
    return s, R, mb - s * R @ ma


def moved_pose(pose: np.ndarray, s: float, R: np.ndarray, t: np.ndarray) -> np.ndarray:
    """A camera-from-world pose in the frame ``x' = s R x + t`` (``camera_similarity``), metric there."""
    out = np.eye(4)
    out[:3, :3] = pose[:3, :3] @ R.T
    out[:3, 3] = s * pose[:3, 3] - out[:3, :3] @ t
    return out


def ransac_plane(
    points: np.ndarray, threshold: float, iterations: int = 400, seed: int = 0
) -> tuple[np.ndarray, float, np.ndarray]:
    """Dominant plane ``n·x = d`` (unit n) and its inlier mask; refined by least squares."""
    rng = np.random.default_rng(seed)
    tri = points[rng.integers(0, len(points), (iterations, 3))]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    ok = np.linalg.norm(n, axis=1) > 0
    n = n[ok] / np.linalg.norm(n[ok], axis=1, keepdims=True)
    d = (n * tri[ok, 0]).sum(1)
    counts = np.zeros(len(n), np.int64)
    for a in range(0, len(n), 50):  # (50, P) distances at a time
        counts[a : a + 50] = (np.abs(n[a : a + 50] @ points.T - d[a : a + 50, None]) < threshold).sum(1)
    best = int(np.argmax(counts))
    inl = np.abs(points @ n[best] - d[best]) < threshold
    centre = points[inl].mean(0)
    normal = np.linalg.svd(points[inl] - centre)[2][2]
    return normal, float(normal @ centre), np.abs(points @ normal - normal @ centre) < threshold


def surface_samples(mesh: Mesh, count: int, seed: int = 0, normals: bool = False):
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


@dataclass
class _SupportFrame:
    """Where the object is in the SfM cloud: a rotation making the support plane z = 0 (tilt), the
    SfM point that goes to ``target`` in the mesh frame, and which points are object and support."""

    R_tilt: np.ndarray
    anchor: np.ndarray
    target: np.ndarray
    object_mask: np.ndarray
    support_mask: np.ndarray


def _support_frame(
    points: np.ndarray,
    centres: np.ndarray,
    c: np.ndarray,
    s0: float,
    lo: np.ndarray,
    hi: np.ndarray,
    samples: np.ndarray,
    support_plane: bool,
    plane: tuple[np.ndarray, float] | None = None,
) -> _SupportFrame:
    """The support plane (RANSAC, or ``plane`` (n, d): n . x = d where it is known) fixes tilt and
    height; points above it near the object are the object's, points on it around the object the
    support's. Without a support: points within the object's size of the cameras' convergence point."""
    size = float(np.linalg.norm(hi - lo))
    if not support_plane:
        obj = np.linalg.norm(points - c, axis=1) * s0 < size
        return _SupportFrame(
            np.eye(3), points[obj].mean(0) if obj.any() else c, samples.mean(0), obj, np.zeros(len(points), bool)
        )
    if plane is None:
        n, d, on_plane = ransac_plane(points, threshold=0.004 * size / s0)
    else:
        n, d = plane
        on_plane = np.abs(points @ n - d) * s0 < 0.004 * size
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
    target = np.array([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, float(lo[2])])
    return _SupportFrame(R_tilt, foot, target, obj, support)


class _AzimuthSearch:
    """Scale, azimuth and in-plane shift of the object points ``A`` (support plane as z = 0, SfM
    units) against the mesh samples, scored with the support points ``B`` (see the module docstring)."""

    def __init__(
        self,
        A: np.ndarray,
        B: np.ndarray,
        mesh: Mesh,
        samples: np.ndarray,
        sample_normals: np.ndarray,
        target: np.ndarray,
        size: float,
        keep: float,
        iterations: int,
        metric: bool = False,
    ):
        self.A, self.B, self.target, self.size = A, B, target, size
        self.keep, self.iterations = keep, iterations
        # metric points (a marker board's): the scale stays 1 and the height moves instead
        self.metric = metric
        self.samples, self.sample_normals = samples, sample_normals
        self.tree = cKDTree(self.samples)
        self.tau = TUNING.align.inlier_fraction * size
        self.caster = RayCaster([mesh.triangles])
        self.up = np.tile([0.0, 0.0, 1.0], (len(B), 1))

    def nearest(self, X: np.ndarray, bound: float) -> tuple[np.ndarray, np.ndarray]:
        """Distance to and index of the nearest mesh sample for points ``X (n, 3)``; exact where
        the distance is below ``bound``, else (inf, len(samples))."""
        return self.tree.query(X, distance_upper_bound=bound)

    def place(self, X: np.ndarray, s: float, yaw: float, txy: np.ndarray) -> np.ndarray:
        """Points ``X`` scaled, turned by ``yaw`` about z and shifted by ``txy`` (x, y and, for metric
        points, a height change): mesh frame."""
        c, sn = np.cos(yaw), np.sin(yaw)
        xy = s * X[:, :2] @ np.array([[c, sn], [-sn, c]]) + txy[:2]
        return np.column_stack([xy, s * X[:, 2] + self.target[2] + (txy[2] if len(txy) > 2 else 0.0)])

    def score(self, s: float, yaw: float, txy: np.ndarray) -> tuple[float, np.ndarray]:
        """Truncated quadratic (MSAC) of the object points' distances to the mesh, plus an outlier's
        cost per support point under the object; and those distances (exact below tau, inf beyond)."""
        tau = self.tau
        dist, _ = self.nearest(self.place(self.A, s, yaw, txy), tau)  # only min(dist, tau) is used
        value = float(np.minimum(dist, tau) @ np.minimum(dist, tau))
        if len(self.B):  # support points cannot lie under the object: each one there costs an outlier
            xs = self.place(self.B, s, yaw, txy)
            xs[:, 2] += 0.1 * tau
            value += tau**2 * float(self.caster.occluded(xs, self.up, np.full(len(self.B), 2 * self.size)).sum())
        return value, dist

    def icp(self, s: float, yaw: float, txy: np.ndarray, free_yaw: bool) -> tuple[float, float, np.ndarray]:
        """Trimmed, scale-aware ICP of (s, yaw, txy); the azimuth held unless ``free_yaw``."""
        A, samples = self.A, self.samples
        # distances are needed exactly up to the trimming threshold only; far points are what make a
        # kd-tree query slow (every sample is about as far), so the query stops at twice the last one
        bound = np.inf
        for _ in range(self.iterations):
            X = self.place(A, s, yaw, txy)
            dist, j = self.nearest(X, bound)
            threshold = trim_threshold(dist, self.keep, self.tau)
            if threshold is None:  # the bound cut into the quantile: every distance exact
                dist, j = self.nearest(X, np.inf)
                threshold = trim_threshold(dist, self.keep, self.tau)
            assert threshold is not None
            kept = dist <= threshold
            bound = 2.0 * threshold
            a, q = A[kept], samples[j[kept]]
            yaw_new = yaw
            if free_yaw:  # yaw from the 2D Procrustes of the xy parts
                ac, qc = a[:, :2] - a[:, :2].mean(0), q[:, :2] - q[:, :2].mean(0)
                yaw_new = float(np.arctan2((ac[:, 0] * qc[:, 1] - ac[:, 1] * qc[:, 0]).sum(), (ac * qc).sum()))
            c, sn = np.cos(yaw_new), np.sin(yaw_new)
            rot = a[:, :2] @ np.array([[c, sn], [-sn, c]])
            if self.metric:  # the shift (x, y, height) by the mean offsets
                shift = np.concatenate(
                    [(q[:, :2] - s * rot).mean(0), [(q[:, 2] - s * a[:, 2] - self.target[2]).mean()]]
                )
                moved = abs(yaw_new - yaw) + np.abs(shift - txy).max() / self.size
                yaw, txy = yaw_new, shift
                if moved < 1e-7:
                    break
                continue
            n = len(a)  # (s, tx, ty) by linear least squares over x, y and z
            M = np.zeros((3 * n, 3))
            M[:n, 0], M[:n, 1] = rot[:, 0], 1
            M[n : 2 * n, 0], M[n : 2 * n, 2] = rot[:, 1], 1
            M[2 * n :, 0] = a[:, 2]
            rhs = np.concatenate([q[:, 0], q[:, 1], q[:, 2] - self.target[2]])
            s_new, tx, ty = np.linalg.lstsq(M, rhs, rcond=None)[0]
            moved = abs(s_new / s - 1) + abs(yaw_new - yaw) + np.abs(np.array([tx, ty]) - txy).max() / self.size
            s, yaw, txy = float(s_new), yaw_new, np.array([tx, ty])
            if moved < 1e-9:
                break
        return s, yaw, txy

    def search(self, s0: float) -> tuple[float, float, np.ndarray]:
        """The best-scoring (s, yaw, txy): free ICP from every coarse azimuth, then the azimuth held
        on a fine grid around the winner (point-to-point ICP barely turns a nearly round object; the
        score still tells)."""
        best: tuple[float, float, float, np.ndarray] | None = None
        self.candidates: list[tuple[float, float]] = []
        self.placements: list[tuple[float, np.ndarray]] = []  # each candidate's (yaw, txy)
        start = np.zeros(3 if self.metric else 2)
        start[:2] = self.target[:2]
        for yaw0 in np.radians(TUNING.align.coarse_azimuths_deg):
            s, yaw, txy = self.icp(s0, float(yaw0), start.copy(), True)
            value = self.score(s, yaw, txy)[0]
            self.candidates.append((float(np.degrees(yaw)) % 360.0, value))
            self.placements.append((yaw, txy.copy()))
            best = self._keep_better(best, s, yaw, txy)
        assert best is not None
        # metric points are many (a board's triangulation): the point-to-plane polish turns the azimuth
        for yaw0 in [] if self.metric else best[2] + np.radians(TUNING.align.fine_azimuths_deg):
            best = self._keep_better(best, *self.icp(best[1], float(yaw0), best[3].copy(), False))
        return best[1], best[2], best[3]

    def _keep_better(self, best, s: float, yaw: float, txy: np.ndarray):
        value, _ = self.score(s, yaw, txy)
        return (value, s, yaw, txy) if best is None or value < best[0] else best

    def polish(self, s: float, yaw: float, txy: np.ndarray) -> tuple[float, float, np.ndarray]:
        """Point-to-plane Gauss-Newton on (scale, azimuth, x, y) over the inliers — free of the
        samples' spacing, which biases point-to-point correspondences by a few tenths of a mm."""
        if self.metric:
            return self._polish_metric(s, yaw, txy)
        A = self.A
        for _ in range(self.iterations):
            dist, j = self.nearest(self.place(A, s, yaw, txy), self.tau)
            kept = dist < self.tau
            if kept.sum() < 4:
                break
            a, q, nq = A[kept], self.samples[j[kept]], self.sample_normals[j[kept]]
            c, sn = np.cos(yaw), np.sin(yaw)
            rot = a[:, :2] @ np.array([[c, sn], [-sn, c]])  # R(yaw) a_xy
            drot = a[:, :2] @ np.array([[-sn, c], [-c, -sn]])  # dR/dyaw a_xy
            J = np.column_stack(
                [(nq[:, :2] * rot).sum(1) + nq[:, 2] * a[:, 2], (nq[:, :2] * drot).sum(1), nq[:, 0], nq[:, 1]]
            )
            rhs = (nq * q).sum(1) - nq[:, 2] * self.target[2]
            s_new, w, tx, ty = np.linalg.lstsq(J, rhs, rcond=None)[0]
            yaw_new = yaw + w / s_new
            moved = abs(s_new / s - 1) + abs(yaw_new - yaw)
            s, yaw, txy = float(s_new), float(yaw_new), np.array([tx, ty])
            if moved < 1e-10:
                break
        return s, yaw, txy

    def _polish_metric(
        self, s: float, yaw: float, txy: np.ndarray, points: np.ndarray | None = None
    ) -> tuple[float, float, np.ndarray]:
        """Metric points (``points``, default all of ``A``): Gauss-Newton on (azimuth, x, y, height),
        the scale held, reweighted by Tukey's biweight at ``TUNING.triangulation.tukey`` robust
        sigmas of the signed point-to-plane residuals (1.4826 x their median absolute value): the
        points' own noise and the mesh's set the scale, where a truncation at a fixed distance would
        cut into a noisy mesh's inliers."""
        yaw0, txy0 = yaw, txy.copy()
        every = self.A if points is None else points
        for _ in range(self.iterations):
            a = every
            dist, j = self.nearest(self.place(a, s, yaw, txy), 3 * self.tau)
            near = dist < 3 * self.tau
            if near.sum() < 4:
                break
            a, q, nq = a[near], self.samples[j[near]], self.sample_normals[j[near]]
            r = (nq * (self.place(a, s, yaw, txy) - q)).sum(1)
            sigma = max(1.4826 * float(np.median(np.abs(r))), 1e-6 * self.size)
            w = np.clip(1 - (r / (TUNING.triangulation.tukey * sigma)) ** 2, 0, None) ** 2
            c, sn = np.cos(yaw), np.sin(yaw)
            drot = a[:, :2] @ np.array([[-sn, c], [-c, -sn]])  # dR/dyaw a_xy
            # the azimuth as the turn's arc at the object's size (metres, like the shift); a direction the
            # points do not see (the azimuth of a body of revolution) is held at the start by a pull of a
            # fraction of the best seen one's curvature instead of wandering in the solver's null space
            J = np.column_stack([s * (nq[:, :2] * drot).sum(1) / self.size, nq])
            normal = (J * w[:, None]).T @ J
            pull = TUNING.triangulation.azimuth_pull * float(np.diag(normal).max())
            normal += pull * np.eye(4)
            rhs = -(J * w[:, None]).T @ r
            rhs -= pull * np.concatenate([[(yaw - yaw0) * self.size], txy - txy0])
            step = np.linalg.solve(normal, rhs)
            step[0] /= self.size
            yaw, txy = yaw + float(step[0]), txy + step[1:]
            if abs(step[0]) + np.abs(step[1:]).max() / self.size < 1e-9:
                break
        return s, yaw, txy

    def rival_z(
        self, yaw: float, shift: np.ndarray, rivals: list[tuple[float, np.ndarray]], blocks: int
    ) -> list[float]:
        """How significantly each of the metric placements ``rivals`` ((yaw, shift) each) fits the
        points worse than (``yaw``, ``shift``): the points' truncated squared distances (the score's
        terms) differenced point by point, summed over ``blocks`` regions of the points (k-means), and
        the total over its standard error from the regions' spread (a paired test whose unit is a
        region: a scanned mesh's deformation, alike over millimetres, counts once per region, where
        counting points as independent would make any rival look hundreds of chi-square units
        worse). Where every region's total is the same: ±inf by its sign, nan where it is 0 (the
        same placement); nan for all with fewer than 2 ``blocks`` points."""
        A = self.A
        if len(A) < 2 * blocks:
            return [float("nan")] * len(rivals)
        _, label = kmeans2(A, blocks, seed=0, minit="++")

        def terms(y: float, t: np.ndarray) -> np.ndarray:
            dist, _ = self.nearest(self.place(A, 1.0, y, t), self.tau)
            return np.minimum(dist, self.tau) ** 2

        own = terms(yaw, shift)
        out = []
        for y, t in rivals:
            total = np.bincount(label, weights=terms(y, t) - own, minlength=blocks)
            se = np.sqrt(blocks * total.var(ddof=1))
            out.append(float(total.sum() / se) if se > 0 else float("inf") * np.sign(total.sum()))
        return out

    def jackknife(self, yaw: float, shift: np.ndarray, blocks: int) -> tuple[float, np.ndarray]:
        """The spread (1 sigma) of a metric placement's azimuth (radians) and shift ``(3,)`` (metres) by
        a block jackknife: the inliers cut into ``blocks`` regions (k-means on their positions), the
        polish done again without each. Errors that are alike over a region of the surface — a
        scanned mesh's deformation, a patch of features on one highlight — count once per region,
        not once per point, as the points' own scatter would."""
        dist, _ = self.nearest(self.place(self.A, 1.0, yaw, shift), self.tau)
        inliers = self.A[dist < self.tau]
        if len(inliers) < 2 * blocks:
            return float("inf"), np.full(3, np.inf)
        _, label = kmeans2(inliers, blocks, seed=0, minit="++")
        runs = []
        for k in range(blocks):
            _, y, t = self._polish_metric(1.0, yaw, shift.copy(), inliers[label != k])
            runs.append(np.concatenate([[y], t]))
        runs_a = np.array(runs)
        spread = np.sqrt((blocks - 1) / blocks * ((runs_a - runs_a.mean(0)) ** 2).sum(0))
        return float(spread[0]), spread[1:]


def trim_threshold(dist: np.ndarray, keep: float, tau: float) -> float | None:
    """The trimmed ICP's threshold max(quantile(dist, keep), tau) for distances ``dist (n,)`` that are
    exact below some bound and inf beyond it; None when an infinite one is among the order
    statistics the (linear) quantile reads — positions floor((n - 1) keep) and the one after, which
    numpy reads even at weight 0 (inf x 0 would be NaN)."""
    n = len(dist)
    last = min(int(np.floor((n - 1) * keep)) + 1, n - 1)
    if not np.isfinite(np.partition(dist, last)[last]):
        return None
    return max(float(np.quantile(dist, keep)), tau)


def align_to_mesh(
    points: np.ndarray,
    poses: list[np.ndarray],
    mesh: Mesh,
    working_distance: float,
    support_plane: bool = True,
    keep: float = 0.5,
    iterations: int = 40,
) -> Alignment:
    """Similarity from the SfM frame to the mesh frame. ``points`` (P, 3) SfM cloud, ``poses`` the
    registered cameras (camera-from-SfM), ``working_distance`` metres from camera to object centre.

    Stages: starting scale (cameras at the working distance from where their axes converge) ->
    support frame -> azimuth search -> polish. Raises ValueError when there is nothing to align
    (too few points above the support)."""
    c = convergence_point(poses)
    centres = np.array([-m[:3, :3].T @ m[:3, 3] for m in poses])
    s0 = working_distance / float(np.median(np.linalg.norm(centres - c, axis=1)))
    lo, hi = mesh.vertices.min(0), mesh.vertices.max(0)
    size = float(np.linalg.norm(hi - lo))
    samples, sample_normals = surface_samples(mesh, TUNING.align.surface_samples, normals=True)
    frame = _support_frame(points, centres, c, s0, lo, hi, samples, support_plane)
    P, S = points[frame.object_mask], points[frame.support_mask]
    if len(P) < 6:
        raise ValueError(f"only {len(P)} structure-from-motion points lie on the object (need 6)")
    search = _AzimuthSearch(
        (P - frame.anchor) @ frame.R_tilt.T,
        (S - frame.anchor) @ frame.R_tilt.T,
        mesh,
        samples,
        sample_normals,
        frame.target,
        size,
        keep,
        iterations,
    )
    s, yaw, txy = search.polish(*search.search(s0))
    final, dist = search.score(s, yaw, txy)
    best = _alignment(search, frame, s, yaw, txy, dist)
    best.candidates = sorted(search.candidates, key=lambda c: c[1])
    best.azimuth_margin = _azimuth_margin(best.candidates, yaw, final)
    return best


def _azimuth_margin(candidates: list[tuple[float, float]], yaw: float, score: float) -> float:
    """How much worse (relative to ``score``) the best of the ``candidates`` (azimuth deg, score) more
    than ``TUNING.align.ambiguous_deg`` from ``yaw`` (radians) scores; inf when there is none."""
    away = [v for a, v in candidates if azimuth_apart(a, np.degrees(yaw)) > TUNING.align.ambiguous_deg]
    return float((min(away) - score) / max(score, 1e-30)) if away else float("inf")


def align_on_board(points: np.ndarray, poses: list[np.ndarray], mesh: Mesh, iterations: int = 40) -> Alignment:
    """The mesh placed on points triangulated in a marker board's frame (``register.triangulate``:
    metric, the board the plane z = 0): ``align_to_mesh``'s search with the scale held at 1 and the
    height free (the mesh's lowest vertex need not touch the board: a scanned mesh's foot is noisy,
    and the board has a thickness). ``poses`` camera-from-board. Raises ValueError with fewer than
    6 points on the object."""
    c = convergence_point(poses)
    centres = np.array([-m[:3, :3].T @ m[:3, 3] for m in poses])
    lo, hi = mesh.vertices.min(0), mesh.vertices.max(0)
    size = float(np.linalg.norm(hi - lo))
    samples, sample_normals = surface_samples(mesh, TUNING.align.surface_samples, normals=True)
    frame = _support_frame(points, centres, c, 1.0, lo, hi, samples, True, plane=(np.array([0.0, 0.0, 1.0]), 0.0))
    P, S = points[frame.object_mask], points[frame.support_mask]
    if len(P) < 6:
        raise ValueError(f"only {len(P)} triangulated points lie on the object (need 6)")
    # the search (every start azimuth) on a subset, the polish on every point
    rng = np.random.default_rng(0)
    few = TUNING.triangulation.search_points
    P_all = (P - frame.anchor) @ frame.R_tilt.T
    if len(S) > few:
        S = S[rng.choice(len(S), few, replace=False)]
    coarse = slice(None, None, max(len(samples) // TUNING.triangulation.search_samples, 1))
    B = (S - frame.anchor) @ frame.R_tilt.T

    def searcher(A: np.ndarray, step: slice, rounds: int) -> _AzimuthSearch:
        return _AzimuthSearch(
            A, B, mesh, samples[step], sample_normals[step], frame.target, size, 0.5, rounds, metric=True
        )

    # each start only has to reach its basin: the polish converges the winner
    starts = TUNING.triangulation.search_iterations
    search = searcher(P_all[rng.choice(len(P), few, replace=False)] if len(P) > few else P_all, coarse, starts)
    found = search.search(1.0)
    order = np.argsort([score for _, score in search.candidates], kind="stable")
    candidates, placements = [search.candidates[i] for i in order], [search.placements[i] for i in order]
    search = searcher(P_all, slice(None), iterations)
    s, yaw, shift = search.polish(*found)
    _, dist = search.score(s, yaw, shift)
    best = _alignment(search, frame, s, yaw, shift, dist)
    best.candidates = candidates
    # the margin on the subset's scores, as the candidates were scored
    best.azimuth_margin = _azimuth_margin(best.candidates, yaw, best.candidates[0][1])
    blocks = TUNING.triangulation.jackknife_blocks
    best.azimuth_sigma, best.shift_sigma = search.jackknife(yaw, shift, blocks)
    best.candidate_z = search.rival_z(yaw, shift, placements, blocks)  # on every point, the answer polished
    return best


def turned_distance(mesh: Mesh, centre: np.ndarray, turns_deg: np.ndarray, count: int = 20_000) -> np.ndarray:
    """How far the mesh turned about the vertical through ``centre`` lies from itself ``(K,)``:
    the median point-to-plane distance (metres) of its surface samples, turned by each of
    ``turns_deg``, to the nearest untouched sample. Near 0: the mesh is symmetric under that turn,
    and no photo of the object can tell the two placements apart."""
    pts, normals = surface_samples(mesh, count, seed=1, normals=True)
    tree = cKDTree(pts)
    out = []
    for turn in np.radians(np.asarray(turns_deg, dtype=float)):
        c, s = np.cos(turn), np.sin(turn)
        R = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        q = (pts - centre) @ R.T + centre
        _, near = tree.query(q)
        out.append(float(np.median(np.abs(((q - pts[near]) * normals[near]).sum(1)))))
    return np.array(out)


def symmetry_profile(mesh: Mesh, centre: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``turned_distance`` over the whole circle: turns (degrees, every
    ``TUNING.align.symmetry_step_deg`` from -180) and distances (metres), ``(K,)`` each."""
    turns = np.arange(-180.0, 180.0, TUNING.align.symmetry_step_deg)
    return turns, turned_distance(mesh, centre, turns, count=TUNING.align.symmetry_samples)


def _refined_minimum(mesh: Mesh, centre: np.ndarray, turn: float, dist: float) -> tuple[float, float]:
    """A grid minimum of the profile at ``turn`` (``dist`` m) refined to 0.05 deg; (deg in [-180, 180), m)."""
    step = TUNING.align.symmetry_step_deg
    best = minimize_scalar(
        lambda a: turned_distance(mesh, centre, np.array([a]), count=TUNING.align.symmetry_samples)[0],
        bounds=(turn - step, turn + step),
        method="bounded",
        options={"xatol": 0.05},
    )
    turn, dist = (float(best.x), float(best.fun)) if best.fun < dist else (turn, dist)
    return (turn + 180.0) % 360.0 - 180.0, dist


def _local_minima(turns: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """Which samples of a circular profile are local minima more than ``TUNING.align.ambiguous_deg`` from 0."""
    return (dist <= np.roll(dist, 1)) & (dist <= np.roll(dist, -1)) & (np.abs(turns) > TUNING.align.ambiguous_deg)


def mesh_symmetry(
    mesh: Mesh, centre: np.ndarray, profile: tuple[np.ndarray, np.ndarray] | None = None
) -> tuple[float, float]:
    """The turn about the vertical through ``centre`` (degrees, more than ``TUNING.align.ambiguous_deg`` from 0)
    under which the mesh lies closest to itself, and that distance (metres, ``turned_distance``):
    the lowest local minimum of the distance over the whole circle (``profile``: ``symmetry_profile``'s,
    computed when not given), refined. A box gives (180, ~0), a body of revolution ~0 everywhere, a
    round but asymmetric mesh no local minimum near 0 (its distance only grows from the zero turn):
    then (nan, inf)."""
    turns, d = profile if profile is not None else symmetry_profile(mesh, centre)
    lowest = _local_minima(turns, d)
    if not lowest.any():
        return float("nan"), float("inf")
    i = int(np.argmin(np.where(lowest, d, np.inf)))
    return _refined_minimum(mesh, centre, float(turns[i]), float(d[i]))


def equivalent_turns(
    mesh: Mesh, centre: np.ndarray, tolerance_m: float, profile: tuple[np.ndarray, np.ndarray] | None = None
) -> list[float] | None:
    """The turns about the vertical through ``centre`` (degrees, sorted, 0 left out) that put the mesh
    within ``tolerance_m`` of itself — placements no photo can tell from the chosen one, and that
    give the same asset: the profile's local minima under the tolerance, refined. ``None`` when every
    sampled turn more than ``TUNING.align.ambiguous_deg`` from 0 does (a body of revolution: every
    azimuth is equivalent); ``[]`` for no symmetry — or turns that form no group (``is_turn_group``)."""
    turns, d = profile if profile is not None else symmetry_profile(mesh, centre)
    away = np.abs(turns) > TUNING.align.ambiguous_deg
    if (d[away] <= tolerance_m).all():
        return None
    found = []
    for i in np.nonzero(_local_minima(turns, d) & (d <= tolerance_m))[0]:
        turn, dist = _refined_minimum(mesh, centre, float(turns[i]), float(d[i]))
        if dist <= tolerance_m:
            found.append((dist, turn))
    # a noisy mesh's profile dips more than once about one symmetry: minima within
    # TUNING.align.ambiguous_deg of a closer one are that one (as candidates are)
    out: list[float] = []
    for _, turn in sorted(found):
        if all(azimuth_apart(turn, t) > TUNING.align.ambiguous_deg for t in out):
            out.append(turn)
    return sorted(out) if is_turn_group(out) else []


def is_turn_group(turns_deg: list[float]) -> bool:
    """Whether ``turns_deg`` with 0 is closed under composition — as the symmetries of a shape are
    (a half turn, the quarter turns of a square): t1 + t2 is in the set again, to two grid steps
    (``TUNING.align.symmetry_step_deg``: the turns are refined from that grid). A mesh that is *nearly*
    a body of revolution (a wavy profile) lies within the tolerance of itself under scattered turns
    that form no group: those are no symmetry, and the photos must tell its placements apart."""
    found = [0.0, *turns_deg]
    close = 2 * TUNING.align.symmetry_step_deg
    return all(min(azimuth_apart(a + b, c) for c in found) <= close for a in found for b in found)


def yaw_deg(alignment: Alignment) -> float:
    """The alignment's turn about the vertical (degrees)."""
    return float(np.degrees(np.arctan2(alignment.rotation[1, 0], alignment.rotation[0, 0])))


def azimuth_apart(a_deg: float, b_deg: float) -> float:
    """The angle between two azimuths, degrees in [0, 180]."""
    return abs((a_deg - b_deg + 180.0) % 360.0 - 180.0)


def _alignment(
    search: _AzimuthSearch, frame: _SupportFrame, s: float, yaw: float, txy: np.ndarray, dist: np.ndarray
) -> Alignment:
    """The similarity of the search's (scale, azimuth, shift) and its fit to the mesh, from the
    score's distances ``dist`` there."""
    c, sn = np.cos(yaw), np.sin(yaw)
    R = np.array([[c, -sn, 0], [sn, c, 0], [0, 0, 1]]) @ frame.R_tilt
    height = txy[2] if len(txy) > 2 else 0.0
    t = np.array([txy[0], txy[1], frame.target[2] + height]) - s * R @ frame.anchor
    kept = dist < search.tau
    rms = float(np.sqrt((dist[kept] ** 2).mean())) if kept.any() else float("inf")
    return Alignment(s, R, t, rms, len(search.A), int(kept.sum()), len(search.B))
