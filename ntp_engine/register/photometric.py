"""A registration refined and judged against the photos: photometric consistency of the mesh's
surface under the scanner's own moving light.

Convention: the mesh frame is metres; ``camera_from_mesh`` poses are rigid 4x4 (OpenCV axes). A
surface point p (normal n) seen unoccluded by photo j has a linear pixel m_jp (RGB) that Eq. 1's
diffuse term predicts as rho_p * D_jp, with D_jp = sum_l A_l(x, n) P_eff[l] / pi in camera j's space
(the LED array moves with the camera, so D changes from photo to photo). Under the right
registration r_jp = log m_jp - log D_jp is the same for every photo (log rho_p) but where a highlight
adds to it; under a wrong one p samples other surface points, or the support, shaded for another
normal. What Eq. 1 leaves out — light bounced off the support and the object itself, a photo's
exposure error — varies smoothly over the object and from photo to photo: each photo gets a shading
field linear in the surface position (per channel), eliminated like each point's albedo
(``eliminate_nuisances``). The cost is a Cauchy loss of what remains, averaged; it is smooth in the
pose because photos are sampled bilinearly after a Gaussian blur (coarse to fine).

``refine`` moves a similarity correction G (rotation about the object's centre, shift, scale) that
acts on every camera at once — the SfM model's own relative poses are kept, so the photos of the
whole sweep vote on the 7 degrees of freedom SfM cannot know (4 on a support, whose plane already
fixed tilt and height: G turns about the vertical and scales about the object's foot; 5 where the
photos are sharp enough to set the height too, ``frees_height``) — then scores the result:
``agreement`` is the fraction of observations within ``TUNING.photometric.agree_log`` of their point's albedo (and
their photo's field).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from scipy.ndimage import distance_transform_edt

from ..io.mesh import Mesh
from ..io.raycast import RayCaster
from ..physics.frame import any_tangent
from ..physics.shadows import MIN_COS_VIEW, SupportShadow
from ..scanner import camera
from .align import surface_samples
from .photo_stack import WORK, PhotoStack, diffuse_shading, edge_mask, eliminate_nuisances, shading_lights
from .settings import TUNING


@dataclass
class PhotometricFit:
    """How the photos agree with a registration: the mean robust cost, the fraction of observations
    within ``TUNING.photometric.agree_log`` of their point's albedo and photo's field, and how many
    observations and points entered."""

    cost: float
    agreement: float
    observations: int
    points: int

    def to_json(self) -> dict:
        """The fit as JSON values."""
        return {
            "cost": self.cost,
            "agreement": self.agreement,
            "observations": self.observations,
            "points": self.points,
        }


@dataclass
class Correction:
    """G(x) = c0 + e^lambda R_omega (x - c0) + tau on mesh-frame points (metres), c0 the pivot (the
    object's centre, or its foot on the support): applied after an alignment it moves every camera
    together."""

    omega: np.ndarray  # (3,) rotation vector, radians
    tau: np.ndarray  # (3,) metres
    log_scale: float
    centre: np.ndarray  # (3,) c0 (the pivot), metres

    def camera_from_mesh(self, pose: np.ndarray) -> np.ndarray:
        """A camera's corrected metric pose (4x4): x_cam = R_j R_w^T (x - c0 - tau) + e^l (R_j c0 + t_j)."""
        Rw = rotation_matrix(self.omega)
        R, t = pose[:3, :3], pose[:3, 3]
        out = np.eye(4)
        out[:3, :3] = R @ Rw.T
        out[:3, 3] = -out[:3, :3] @ (self.centre + self.tau) + np.exp(self.log_scale) * (R @ self.centre + t)
        return out


def _bounded(params: np.ndarray) -> np.ndarray:
    """Correction parameters (omega, tau / size, lambda) within the bounds above."""
    out = params.copy()
    out[3:6] = np.clip(out[3:6], -TUNING.photometric.max_shift, TUNING.photometric.max_shift)
    out[6] = np.clip(out[6], -TUNING.photometric.max_log_scale, TUNING.photometric.max_log_scale)
    return out


def object_distance(poses: np.ndarray, point: np.ndarray) -> float:
    """Median distance (metres) from the cameras ``poses (V, 4, 4)`` (camera-from-mesh) to ``point (3,)``."""
    return float(np.median(np.linalg.norm(poses[:, :3, :3] @ point + poses[:, :3, 3], axis=1)))


def rotation_matrix(omega: np.ndarray) -> np.ndarray:
    """The 3x3 rotation of the rotation vector ``omega (3,)`` (Rodrigues; radians)."""
    theta = float(np.linalg.norm(omega))
    if theta < 1e-15:
        return np.eye(3)
    k = omega / theta
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(theta) * K + (1 - np.cos(theta)) * K @ K


def _rotation_t(omega: torch.Tensor) -> torch.Tensor:
    """Rodrigues' formula, differentiable at 0 (the first-order form below 1e-8 rad)."""
    theta2 = (omega * omega).sum()
    zero = torch.zeros((), dtype=omega.dtype)
    K = torch.stack(
        [
            torch.stack([zero, -omega[2], omega[1]]),
            torch.stack([omega[2], zero, -omega[0]]),
            torch.stack([-omega[1], omega[0], zero]),
        ]
    )
    theta = torch.sqrt(theta2.clamp_min(1e-16))
    a = torch.where(theta2 > 1e-16, torch.sin(theta) / theta, 1 - theta2 / 6)
    b = torch.where(theta2 > 1e-16, (1 - torch.cos(theta)) / theta2.clamp_min(1e-16), 0.5 - theta2 / 24)
    return torch.eye(3, dtype=omega.dtype) + a * K + b * K @ K


@dataclass
class _Samples:
    """A pose's photo samples, kept for its Jacobian: the correction ``params (7,)``, the mesh
    samples in every camera ``x (V, N, 3)`` (float64), their pixels ``px (V, N, 2)`` and the blurred
    photos there ``m (V, N, 3)`` (linear, floored at 1e-6)."""

    params: np.ndarray
    x: np.ndarray
    px: torch.Tensor
    m: torch.Tensor


class PhotometricRegistration:
    """The photometric cost of a registration and its refinement (see the module docstring).

    ``poses``: camera-from-mesh (metric) of the photos in ``photos``, as the alignment gives them."""

    def __init__(
        self,
        mesh: Mesh,
        photos: PhotoStack,
        support_z: float | None,
        points: int = TUNING.photometric.surface_points,
        seed: int = 0,
        edge_stride: int = 1,
        free_height: bool = False,
        free_scale: bool = True,
    ):
        """``edge_stride``: the mesh's image (for the edge distances) is cast every this many pixels;
        ``free_height``: on a support, the height moves too (see ``frees_height``); without
        ``free_scale`` the poses are metric already (a marker board's) and the scale stays."""
        self.photos, self.scanner = photos, photos.scanner
        self.edge_stride = edge_stride
        # the pixels whose rays find the mesh's edges (``_observations``), cast every ``edge_stride``
        self.edge_grid = camera.pixel_rays(self.scanner)[::edge_stride, ::edge_stride]
        self.groups = shading_lights(self.scanner)
        self.points, self.normals = surface_samples(mesh, points, seed=seed, normals=True)
        self.caster = RayCaster([mesh.triangles])
        lo, hi = mesh.vertices.min(0), mesh.vertices.max(0)
        self.centre, self.size = (lo + hi) / 2, float(np.linalg.norm(hi - lo))
        self.shadow = SupportShadow(self.scanner, support_z) if support_z is not None else None
        # on a support the plane (hundreds of SfM points) fixed tilt and height: the correction keeps
        # the tilt, turning about the vertical and scaling about the object's foot on the plane, so free
        # are azimuth, the in-plane shift and scale, and the height where the photos are sharp enough
        # to set it (``frees_height``: SfM's support points lie 0.5-0.8 px low)
        self.pivot = self.centre.copy()
        if support_z is not None:
            self.pivot[2] = support_z
        self.free = np.array([support_z is None] * 2 + [True] * 3 + [support_z is None or free_height, free_scale])
        # each photo's shading field's basis: 1 and the point's position (see ``_eliminated``)
        rel = (self.points - self.centre) / self.size
        self.field = torch.as_tensor(np.concatenate([np.ones((len(rel), 1)), rel], 1), dtype=WORK)

    def _observations(self, poses: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Which (photo, point) pairs see each other ``(V, N)`` and each
        point's distance in pixels to the nearest silhouette or depth edge of the mesh in that photo
        ``(V, N)`` — a blurred photo mixes the two sides of an edge, so points nearer than the blur
        would pull the registration (toward a smaller projection)."""
        V, N = len(poses), len(self.points)
        seen = np.zeros((V, N), bool)
        edge_px = np.zeros((V, N))
        s, k, grid = self.scanner, self.edge_stride, self.edge_grid
        rays = grid.reshape(-1, 3)
        for j, pose in enumerate(poses):
            if self.shadow is not None and self.shadow(pose):
                continue
            R, t = pose[:3, :3], pose[:3, 3]
            x, n = self.points @ R.T + t, self.normals @ R.T
            ok = x[:, 2] > 1e-6
            px = camera.project(s, torch.as_tensor(x)).numpy()
            margin = 3.0
            ok &= (px[:, 0] > margin) & (px[:, 1] > margin) & (px[:, 0] < s.width - 1 - margin)
            ok &= px[:, 1] < s.height - 1 - margin
            ok &= (-(x * n).sum(1) / np.linalg.norm(x, axis=1)) > MIN_COS_VIEW
            idx = np.nonzero(ok)[0]
            origin = self.points[idx] + 1e-4 * self.size * self.normals[idx]
            to_cam = -R.T @ t - origin
            dist = np.linalg.norm(to_cam, axis=1)
            occluded = self.caster.occluded(origin, to_cam / dist[:, None], dist)
            idx = idx[~occluded]
            seen[j, idx] = True
            hits = self.caster.intersect(np.broadcast_to(-R.T @ t, rays.shape), rays @ R)
            edge = edge_mask((hits.geom >= 0).reshape(grid.shape[:2]), hits.t.reshape(grid.shape[:2]))
            far = distance_transform_edt(~edge) * k
            col, row = np.round(px[idx, 0] / k).astype(int), np.round(px[idx, 1] / k).astype(int)
            edge_px[j, idx] = far[row.clip(0, grid.shape[0] - 1), col.clip(0, grid.shape[1] - 1)]
        return seen, edge_px

    def _held(self, poses: np.ndarray, params: np.ndarray, sigma: float, jacobian: bool = True) -> np.ndarray:
        """The observations a round holds, taken at ``params``, and the round's shading."""
        seen = self._seen(poses, params, sigma)
        self._hold_shading(poses, params, seen, jacobian)
        return seen

    def _seen(self, poses: np.ndarray, params: np.ndarray, sigma: float) -> np.ndarray:
        """The usable observations ``(V, N)`` at ``params`` (``_observations``, ``_usable``)."""
        current = self._correction(params).camera_from_mesh
        return self._usable(poses, params, sigma, *self._observations(np.stack([current(p) for p in poses])))

    def _fit_at(self, poses: np.ndarray, params: np.ndarray, sigma: float, seen: np.ndarray) -> PhotometricFit:
        """The fit (``_cost``'s) of the observations ``seen`` at ``params``."""
        r, ok, _ = self._residuals(poses, params, sigma, seen)
        return self._cost(r, ok)[2]

    def _usable(self, poses, params, sigma, seen, edge_px) -> np.ndarray:
        """The observations a level uses: seen, clear of the mesh's edges by the blur, and on pixels
        neither clipped nor in the noise."""
        px = self._pixels(poses, params)
        usable = (self._sample(self.photos.usable, px)[..., 0] > 0.999).numpy()
        return seen & usable & (edge_px > TUNING.photometric.edge_clearance * sigma + 1)

    def _camera(self, poses: np.ndarray, params: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The mesh samples and their normals in every camera ``(V, N, 3)`` under the correction
        ``params`` (omega, tau / size, lambda): x_cam = R_j R_w^T (x - c0 - tau) + e^lambda (R_j c0 + t_j)."""
        R = poses[:, :3, :3]
        return self._camera_points(poses, params), (self.normals @ rotation_matrix(params[:3])) @ R.transpose(0, 2, 1)

    def _camera_points(self, poses: np.ndarray, params: np.ndarray, points: np.ndarray | None = None) -> np.ndarray:
        """``_camera``'s points alone ``(V, N, 3)`` (``points (N, 3)``: others than the samples)."""
        Rw = rotation_matrix(params[:3])
        at = self.points if points is None else points
        local = (at - self.pivot - params[3:6] * self.size) @ Rw  # R_w^T (x - c0 - tau), rows
        R, t = poses[:, :3, :3], poses[:, :3, 3]
        return local @ R.transpose(0, 2, 1) + (np.exp(params[6]) * (R @ self.pivot + t))[:, None, :]

    def _pixels(self, poses: np.ndarray, params: np.ndarray) -> torch.Tensor:
        """Pixel coordinates ``(V, N, 2)`` of the mesh samples under the correction ``params``."""
        return camera.project(self.scanner, torch.as_tensor(self._camera_points(poses, params), dtype=WORK))

    def _pixel_jacobian(
        self, poses: np.ndarray, params: np.ndarray, x: np.ndarray, points: np.ndarray | None = None
    ) -> torch.Tensor:
        """d pixel / d params ``(V, N, 2, 7)`` at the camera-space samples ``x`` (``_camera``'s at
        ``params``): the chain rule through ``_camera`` (the rotation's own derivative by central
        differences of the ``(N, 3)`` local points, exact to ~1e-10)."""
        Rw = rotation_matrix(params[:3])
        base = (self.points if points is None else points) - self.pivot - params[3:6] * self.size
        d_local = np.zeros((len(base), 3, 3))  # d (R_w^T (x - c0 - tau)) / d omega_k
        for k in range(3):
            e = np.zeros(3)
            e[k] = 1e-5
            d_local[..., k] = (base @ rotation_matrix(params[:3] + e) - base @ rotation_matrix(params[:3] - e)) / 2e-5
        R, t = poses[:, :3, :3], poses[:, :3, 3]
        V, N = len(poses), len(base)
        R_t = torch.as_tensor(R, dtype=WORK)
        d_x = torch.cat(
            [
                torch.einsum("vab,nbk->vnak", R_t, torch.as_tensor(d_local, dtype=WORK)),
                torch.as_tensor(-self.size * R @ Rw.T, dtype=WORK)[:, None].expand(V, N, 3, 3),
                torch.as_tensor(np.exp(params[6]) * (R @ self.pivot + t), dtype=WORK)[:, None, :, None].expand(
                    V, N, 3, 1
                ),
            ],
            -1,
        )  # (V, N, 3, 7)
        return camera.project_jacobian(self.scanner, torch.as_tensor(x, dtype=WORK)) @ d_x

    def _log_shading_at(self, poses: np.ndarray, params: np.ndarray, seen: np.ndarray) -> np.ndarray:
        """log D ``(V, N, 3)`` of the seen pairs at ``params`` (0 elsewhere)."""
        x, n = self._camera(poses, params)
        out = np.zeros((*seen.shape, 3))
        d = diffuse_shading(self.scanner, x[seen], n[seen], self.groups)
        out[seen] = np.log(np.maximum(d, 1e-6 * max(float(d.max(initial=0.0)), 1e-12)))
        return out

    def _hold_shading(self, poses: np.ndarray, params: np.ndarray, seen: np.ndarray, jacobian: bool = True) -> None:
        """log D at ``params`` and its forward differences in the 7 parameters, for a round: shading
        held at one pose would pull the fit back toward it, so it follows the pose to first order."""
        base = self._log_shading_at(poses, params, seen)
        J = np.zeros((*base.shape, 7))
        for k in np.nonzero(self.free)[0] if jacobian else []:
            e = np.zeros(7)
            e[k] = 1e-3
            J[..., k] = (self._log_shading_at(poses, params + e, seen) - base) / 1e-3
        self._shade = (params.copy(), torch.as_tensor(base, dtype=WORK), torch.as_tensor(J, dtype=WORK))

    def _log_shading(self, params: np.ndarray) -> tuple[torch.Tensor, torch.Tensor]:
        """log D at ``params`` from the round's linear model, and its Jacobian ``(V, N, 3, 7)``."""
        p0, base, J = self._shade
        return base + J @ torch.as_tensor(params - p0, dtype=WORK), J

    def _sample(self, images: torch.Tensor, px: torch.Tensor) -> torch.Tensor:
        """Bilinear samples ``(V, N, C)`` of ``images (V, C, h, w)`` at ``px (V, N, 2)``."""
        s = self.scanner
        grid = torch.stack([2 * px[..., 0] / (s.width - 1) - 1, 2 * px[..., 1] / (s.height - 1) - 1], -1)
        grid = torch.nan_to_num(grid, nan=-2.0)[:, None]
        return F.grid_sample(images, grid.to(images.dtype), align_corners=True)[:, :, 0].permute(0, 2, 1)

    def _residuals(
        self, poses: np.ndarray, params: np.ndarray, sigma: float, seen: np.ndarray
    ) -> tuple[torch.Tensor, torch.Tensor, _Samples]:
        """Log residuals r ``(V, N, 3)`` at ``params``, the usable mask ``(V, N)`` (``seen``: fixed
        while the pose moves, a mask that changed would make the cost jump) and the samples
        ``_jacobian`` differentiates."""
        x = self._camera_points(poses, params)
        px = camera.project(self.scanner, torch.as_tensor(x, dtype=WORK))
        m = self._sample(self.photos.blurred(sigma), px).clamp_min(1e-6)
        log_d, _ = self._log_shading(params)
        return torch.log(m) - log_d, torch.as_tensor(seen), _Samples(params, x, px, m)

    def _jacobian(
        self, poses: np.ndarray, at: _Samples, sigma: float, ok: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """The Jacobian ``(V, N, 3, 7)`` of ``_residuals``' log residuals at ``at`` in the parameters,
        and the mask ``ok`` less where it is not finite: image gradients of the blurred photos times
        the pixels' derivatives, less the round's shading's."""
        g = self._sample(self.photos.gradients(sigma), at.px).reshape(*at.m.shape[:2], 3, 2)  # d m / d (col, row)
        J_px = torch.nan_to_num(self._pixel_jacobian(poses, at.params, at.x))  # (V, N, 2, 7)
        J = (g / at.m[..., None]) @ J_px - self._shade[2]  # (V, N, 3, 7)
        return J, ok & torch.isfinite(J).all(-1).all(-1)

    def _cost(self, r: torch.Tensor, ok: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, PhotometricFit]:
        """Residuals about each point's albedo and each photo's shading field ``(V, N, 3)`` (0 where
        unused), the mask of points seen often enough, and the fit."""
        # a log residual that is not finite (a point the model shades black at this pose) is no
        # observation: left in, it would make every weight and field NaN
        ok = ok & torch.isfinite(r).all(-1)
        enough = ok.sum(0) >= TUNING.photometric.min_views
        ok = ok & enough[None, :]
        centre = torch.nanmedian(torch.where(ok[..., None], r, torch.nan), dim=0).values
        e = torch.where(ok[..., None], r - centre[None], 0.0)
        for _ in range(3):  # from the median to the Cauchy M-estimate (IRLS): the cost's own minimiser
            w = ok[..., None] / (1 + (e / TUNING.photometric.cauchy_log) ** 2)
            e = torch.where(ok[..., None], eliminate_nuisances(self.field, w, r[..., None])[..., 0], 0.0)
        count = int(ok.sum())
        # nothing seen fits nothing: a pose that lost every observation never wins
        cost = (
            float(torch.log1p((e / TUNING.photometric.cauchy_log) ** 2).sum(dtype=torch.float64)) / count
            if count
            else float("inf")
        )
        agree = (e.abs().amax(-1) < TUNING.photometric.agree_log) & ok
        return e, ok, PhotometricFit(cost, float(agree.sum()) / max(count, 1), count, int(enough.sum()))

    def evaluate(self, poses: np.ndarray, sigma: float = TUNING.photometric.blur_levels_px[-1]) -> PhotometricFit:
        """The cost and agreement of ``poses (V, 4, 4)`` as they are."""
        seen = self._usable(np.asarray(poses), np.zeros(7), sigma, *self._observations(poses))
        self._hold_shading(np.asarray(poses), np.zeros(7), seen)
        return self._fit_at(np.asarray(poses), np.zeros(7), sigma, seen)

    def refine(
        self,
        poses: np.ndarray,
        levels: tuple[float, ...] = TUNING.photometric.blur_levels_px,
        iterations: int = 15,
        max_rounds: int = TUNING.photometric.max_rounds,
    ) -> tuple[Correction, PhotometricFit]:
        """The correction G that minimises the cost — Levenberg-Marquardt on iteratively reweighted
        (Cauchy) least squares, each point's log albedo eliminated as its weighted mean — coarse to
        fine (``levels``: blur sigmas in pixels); and the fit at the finest level.
        ``poses (V, 4, 4)`` camera-from-mesh before G."""
        poses = np.asarray(poses)
        params = np.zeros(7)
        fit = PhotometricFit(float("inf"), 0.0, 0, 0)
        rounds = [(sigma, k) for sigma in levels for k in range(max_rounds)]
        settled, previous = False, np.zeros(7)
        for sigma, k in rounds:
            if k == 0:
                settled, previous = False, np.zeros(7)
            if settled:
                continue
            start = params.copy()
            seen = self._held(poses, params, sigma)
            # the azimuth first (coarsest level): nearly round objects make it the shallow direction
            if sigma == TUNING.photometric.blur_levels_px[0] and k == 0:
                params = self._azimuth_search(poses, params, sigma, seen)
            params, fit = self._descend(poses, params, sigma, seen, iterations)
            # visibility, edges and shading were held for this round: again until the pose stops moving
            step = params - start
            settled = bool(
                np.abs(step[[0, 1, 2, 6]]).max() < TUNING.photometric.settled_rad
                and np.abs(step[3:6]).max() * self.size < TUNING.photometric.settled_m
            )
            # the robust cost anchors each round near its start, so rounds walk a shallow valley in
            # shrinking steps along one direction: jump to the walk's limit when the photos agree
            cos = float(step @ previous) / max(float(np.linalg.norm(step) * np.linalg.norm(previous)), 1e-30)
            ratio = float(np.linalg.norm(step) / max(float(np.linalg.norm(previous)), 1e-30))
            if not settled and cos > 0.9 and ratio < 0.95:
                jump = _bounded(params + step * min(ratio / (1 - ratio), 10.0))
                seen_j = self._held(poses, jump, sigma)
                here, there = (self._fit_at(poses, q, sigma, seen_j) for q in (params, jump))
                if there.cost < here.cost:
                    params, fit = jump, there
            previous = step
        return self._correction(params), fit

    def _descend(self, poses, params, sigma, seen, iterations) -> tuple[np.ndarray, PhotometricFit]:
        """Levenberg-Marquardt steps on the IRLS-weighted least squares with the observations held."""
        damping = 1e-3
        r, ok, at = self._residuals(poses, params, sigma, seen)
        J, ok = self._jacobian(poses, at, sigma, ok)
        e, used, fit = self._cost(r, ok)
        for _ in range(iterations):
            w = used[..., None] / (1 + (e / TUNING.photometric.cauchy_log) ** 2)  # IRLS weights (V, N, 3)
            # the nuisances (each point's albedo, each photo's field) eliminated from both
            both = eliminate_nuisances(self.field, w, torch.cat([J, r[..., None]], -1))
            Jc, ec = both[..., :7], both[..., 7]
            wJ = (w[..., None] * Jc).reshape(-1, 7)
            A = (wJ.T @ Jc.reshape(-1, 7)).double()  # 7 x 7 sums in float32, solved in float64
            b = (wJ.T @ ec.reshape(-1)).double()

            def trial(q: np.ndarray, best: float = fit.cost) -> tuple | None:
                r2, ok2, at2 = self._residuals(poses, q, sigma, seen)
                e2, used2, fit2 = self._cost(r2, ok2)
                return (r2, ok2, at2, e2, used2, fit2) if fit2.cost < best else None

            step, damping, taken = self._damped_step(A, b, params, damping, trial)
            if step is None:
                break
            if taken is not None:  # the step taken: its samples give the next Jacobian
                r, ok2, at2, e, used, fit = taken
                params = at2.params
                J, _ = self._jacobian(poses, at2, sigma, ok2)
            if taken is None or np.abs(step).max() < 1e-7:
                break
        return params, fit

    def _damped_step(
        self, A: torch.Tensor, b: torch.Tensor, params: np.ndarray, damping: float, trial: Callable[[np.ndarray], Any]
    ) -> tuple[np.ndarray | None, float, Any]:
        """One Levenberg-Marquardt step of ``params`` on the normal equations ``A (7, 7) d = -b``
        (float64), the damping raised until ``trial(params + d)`` returns what it accepted (not None).
        Returns the last step tried (None: no free direction the photos see), the next damping and
        the accepted trial's result (None: no step improved)."""
        # a direction the photos do not see (the azimuth of an untextured body of revolution) has
        # a ~zero diagonal: it does not move (solving for it would be singular or wild)
        diag = torch.diag(A).numpy()
        seen_dir = self.free & (diag > 1e-6 * max(float(diag[self.free].max()), 1e-30))
        if not seen_dir.any():
            return None, damping, None
        sd = torch.as_tensor(seen_dir)
        Af = A[sd][:, sd]
        step = np.zeros(7)
        while damping < 1e6:
            step = np.zeros(7)
            step[seen_dir] = -torch.linalg.solve(Af + damping * torch.diag(torch.diag(Af)), b[sd]).numpy()
            step = _bounded(params + step) - params
            taken = trial(params + step)
            if taken is not None:
                return step, max(damping / 10, 1e-7), taken
            damping *= 10
        return step, damping, None

    def _azimuth_search(self, poses, params, sigma, seen) -> np.ndarray:
        """``params`` turned about the vertical through the object's centre to the best of
        ``TUNING.photometric.azimuth_grid_deg`` (visibility held)."""
        best, best_cost = params, float("inf")
        for a in np.radians(TUNING.photometric.azimuth_grid_deg):
            trial = params.copy()
            trial[2] += a
            cost = self._fit_at(poses, trial, sigma, seen).cost
            if cost < best_cost:
                best, best_cost = trial, cost
        return best

    def azimuth_profile(self, poses: np.ndarray, sigma: float, step_deg: float) -> tuple[np.ndarray, np.ndarray]:
        """The cost of ``poses (V, 4, 4)`` turned about the vertical through the object's centre, every
        ``step_deg`` over the whole circle: turns (degrees in [-180, 180)) and costs (inf where too few
        observations). Observations and shading are taken afresh at every turn."""
        turns = np.arange(-180.0, 180.0, step_deg)
        costs = np.full(len(turns), np.inf)
        for i, turn in enumerate(turns):
            params = np.zeros(7)
            params[2] = np.radians(turn)
            seen = self._held(poses, params, sigma, jacobian=False)
            fit = self._fit_at(poses, params, sigma, seen)
            if fit.points >= TUNING.photometric.min_views:
                costs[i] = fit.cost
        return turns, costs

    def sharpness(self, poses: np.ndarray, sigma: float) -> float:
        """Mean relative rise of the cost when ``poses`` move ``TUNING.photometric.sharpness_shift_px`` (at the object's
        distance) either way along each mesh axis, observations held."""
        seen = self._seen(poses, np.zeros(7), sigma)
        self._hold_shading(poses, np.zeros(7), seen)
        return self._rise(poses, lambda params: self._fit_at(poses, params, sigma, seen).cost)

    def texture_sharpness(self, poses: np.ndarray, sigma: float) -> float:
        """``sharpness`` measured by the texture alone: the mean relative rise of ``texture_cost``
        when ``poses`` move ``TUNING.photometric.sharpness_shift_px`` either way along each mesh axis
        (observations held). Free of the shading model, so of the mesh's normals: a scanner's mesh
        (normals ~11 deg off) leaves it as sharp as the photographed one (docs/pipeline.md)."""
        seen = self._seen(poses, np.zeros(7), sigma)
        return self._rise(poses, lambda params: self.texture_cost(poses, params, sigma, seen))

    def _rise(self, poses: np.ndarray, cost: Callable[[np.ndarray], float]) -> float:
        """Mean relative rise of ``cost`` (of the correction's parameters) when ``poses`` move
        ``TUNING.photometric.sharpness_shift_px`` (at the object's distance) either way along each mesh axis;
        NaN where the cost at ``poses`` is not finite (nothing seen there to measure the rise against)."""
        distance = object_distance(poses, self.centre)
        shift = TUNING.photometric.sharpness_shift_px * distance / self.scanner.fx / self.size
        base = cost(np.zeros(7))
        if not np.isfinite(base):
            return float("nan")
        moved = [cost(np.eye(7)[3 + axis] * sign * shift) for axis in range(3) for sign in (-1, 1)]
        return float(np.mean(moved) / max(base, 1e-12) - 1)

    def texture_cost(self, poses: np.ndarray, params: np.ndarray, sigma: float, seen: np.ndarray) -> float:
        """The photos' disagreement about the surface's texture under the correction ``params``: each
        point ``seen (V, N)`` sampled with a small patch around it on its tangent plane
        (``patch_samples``), each photo's mean over a patch taken out (the shading, exposure and
        bounced light — all that Eq. 1's diffuse term and the shading fields model — are one gain over
        a patch a pixel wide), then each sample's mean over the photos (the texture); the Cauchy cost
        of what remains, averaged over the samples. inf where nothing is seen."""
        e, ok, _ = self._texture_residuals(poses, params, sigma, seen, jacobian=False)
        count = int(ok.sum()) * e.shape[2]
        cost = torch.log1p((e / TUNING.photometric.cauchy_log) ** 2).sum(dtype=torch.float64)
        return float(cost) / count if count else float("inf")

    def _texture_residuals(
        self, poses: np.ndarray, params: np.ndarray, sigma: float, seen: np.ndarray, jacobian: bool = True
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor | None]:
        """``texture_cost``'s residuals ``(V, N, S, 3)`` (0 where unused), the points' use ``(V, N)``
        and, with ``jacobian``, the residuals' derivative in the 7 parameters ``(V, N, S, 3, 7)``
        (the same centring applied to the log photos' derivatives: it is linear)."""
        V, N = seen.shape
        pts = self.patch_samples(object_distance(poses, self.centre) / self.scanner.fx)
        S = pts.shape[1]
        flat = pts.reshape(-1, 3)
        x = self._camera_points(poses, params, flat)
        px = camera.project(self.scanner, torch.as_tensor(x, dtype=WORK))
        m = self._sample(self.photos.blurred(sigma), px).clamp_min(1e-6)
        ok = torch.as_tensor(seen)
        ok = ok & (ok.sum(0) >= TUNING.photometric.min_views)[None]
        values = torch.log(m)[..., None]
        if jacobian:
            g = self._sample(self.photos.gradients(sigma), px).reshape(V, N * S, 3, 2)
            J_px = torch.nan_to_num(self._pixel_jacobian(poses, params, x, flat))
            values = torch.cat([values, (g / m[..., None]) @ J_px], -1)
        values = values.reshape(V, N, S, 3, -1)
        values = values - values.mean(2, keepdim=True)  # each photo's gain over a patch
        values = torch.where(ok[..., None, None, None], values, 0.0)
        texture = values.sum(0) / ok.sum(0).clamp_min(1)[:, None, None, None]  # each sample's, over the photos
        values = torch.where(ok[..., None, None, None], values - texture[None], 0.0)
        return values[..., 0], ok, values[..., 1:] if jacobian else None

    def refine_texture(
        self, poses: np.ndarray, levels: tuple[float, ...], iterations: int = 15
    ) -> tuple[Correction, float]:
        """The correction G that minimises ``texture_cost`` — Levenberg-Marquardt on the iteratively
        reweighted (Cauchy) least squares, observations held per level — coarse to fine (``levels``:
        blur sigmas in pixels); and the cost at the finest level. ``poses (V, 4, 4)``: camera-from-mesh
        before G."""
        poses = np.asarray(poses)
        params, cost = np.zeros(7), float("inf")
        for sigma in levels:
            seen = self._seen(poses, params, sigma)  # the texture reads no shading
            params, cost = self._descend_texture(poses, params, sigma, seen, iterations)
        return self._correction(params), cost

    def _descend_texture(self, poses, params, sigma, seen, iterations) -> tuple[np.ndarray, float]:
        """``_descend`` on ``texture_cost``: its parameters and cost after the steps."""
        damping = 1e-3
        e, ok, J = self._texture_residuals(poses, params, sigma, seen)
        cost = self.texture_cost(poses, params, sigma, seen)
        for _ in range(iterations):
            assert J is not None
            w = (ok[..., None, None] / (1 + (e / TUNING.photometric.cauchy_log) ** 2)).double()
            Jd = J.double()
            A = torch.einsum("vnsc,vnsck,vnscl->kl", w, Jd, Jd)
            b = torch.einsum("vnsc,vnsck,vnsc->k", w, Jd, e.double())

            def trial(q: np.ndarray, best: float = cost) -> float | None:
                at_q = self.texture_cost(poses, q, sigma, seen)
                return at_q if at_q < best else None

            step, damping, taken = self._damped_step(A, b, params, damping, trial)
            if step is None:
                break
            if taken is not None:
                params, cost = params + step, taken
                e, ok, J = self._texture_residuals(poses, params, sigma, seen)
            if taken is None or np.abs(step).max() < 1e-7:
                break
        return params, cost

    def patch_samples(self, pixel_m: float) -> np.ndarray:
        """Each surface point and ``TUNING.photometric.patch_offsets`` around it on its tangent plane,
        ``TUNING.photometric.patch_radius_px`` pixels of ``pixel_m`` metres apart: ``(N, S, 3)`` metres,
        mesh frame (the mesh's own normal lays the patch out: a normal 11 deg off moves a sample 2%
        of the radius)."""
        t1 = any_tangent(torch.as_tensor(self.normals)).numpy()
        t2 = np.cross(self.normals, t1)
        offsets = np.asarray(TUNING.photometric.patch_offsets, float) * TUNING.photometric.patch_radius_px * pixel_m
        return self.points[:, None] + offsets[None, :, :1] * t1[:, None] + offsets[None, :, 1:] * t2[:, None]

    def _correction(self, params: np.ndarray) -> Correction:
        return Correction(params[:3].copy(), params[3:6] * self.size, float(params[6]), self.pivot.copy())


def frees_height(pixel_m: float) -> bool:
    """Whether photos whose working-size pixel spans ``pixel_m`` metres at the object move the height
    of a registration on a support. SfM's support points, and so the plane the alignment puts the
    object's foot on, lie 0.5-0.8 px low (docs/pipeline.md); photos this sharp set the height and
    the scale about the foot together, coarser ones leave them on a valley whose floor the cost's
    model errors tilt (the gallery dome at 1.05 mm a pixel: 0.4 mm low from the true poses)."""
    return pixel_m <= TUNING.photometric.height_pixel_m


def edge_stride(photos: PhotoStack) -> int:
    """Every how many pixels the mesh's image is cast for the edge distances of ``photos``: an edge
    located to a pixel of a ~320-wide grid is enough to keep points ~2 px clear of it."""
    return max(1, round(photos.scanner.width / TUNING.photometric.edge_grid_width))
