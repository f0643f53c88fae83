"""The marker board as a backdrop: where a photo shows the board's print, the object is not there.

Every photo's pose on the board is known (``register.board_poses``) and so is the print
(``Board.albedo``): each pixel whose ray meets the paper is predicted as the print times a smooth
gain (the scanner's light falls off smoothly over a flat sheet), and where the photo shows that
prediction the board is *seen* (``board_seen``). A placement of the mesh that puts surface points in
front of seen print is wrong by how deep into it they project (``penetration``, pixels): a test of
the mesh's outline that reads no normal and no texture of the object, so a scanned mesh's normal
errors (which defeat the shading's check) do not touch it, and its 0.1-0.3 mm of position error is
a fraction of a pixel at the benches' sizes.

``Silhouettes`` sweeps the mesh's azimuth on the board over the whole circle, each start's azimuth
and shift on the plane refined by Levenberg-Marquardt on the penetrations, refines the distinct
minima with the contour generator's points held to the outline from inside too, compares the best
placement with its rivals per photo (a paired test whose unit is a photo) and measures its spread
by a block jackknife over surface regions.

Convention: camera_from_board poses rigid 4x4 (OpenCV axes); the board frame in metres, z out of the
paper; ``Alignment`` maps the board frame to the mesh frame (scale 1); turns in radians about the
board's normal through the mesh's centre unless said; pixels of the photo stack's working size.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
import torch
import torch.nn.functional as F
from scipy.cluster.vq import kmeans2

from ..io.mesh import Mesh
from ..scanner import camera
from ..scanner.board import Board
from ..scanner.scanner import Scanner
from .align import Alignment, azimuth_apart, surface_samples, yaw_deg
from .photo_stack import PhotoStack
from .settings import TUNING


def board_hits(scanner: Scanner, camera_from_board: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Where each pixel's ray meets the board's plane: board-frame ``xy (H, W, 2)`` (metres) and
    ``ahead (H, W)``, False where the plane lies behind the camera or the ray runs parallel to it."""
    rays = camera.pixel_rays(scanner).reshape(-1, 3)
    R, t = camera_from_board[:3, :3], camera_from_board[:3, 3]
    centre = -R.T @ t
    d = rays @ R  # board-frame directions
    with np.errstate(divide="ignore", invalid="ignore"):
        s = -centre[2] / d[:, 2]
    ahead = np.isfinite(s) & (s > 0)
    xy = centre[:2] + np.where(ahead, s, 0.0)[:, None] * d[:, :2]
    return xy.reshape(scanner.height, scanner.width, 2), ahead.reshape(scanner.height, scanner.width)


def _gain_basis(xy: np.ndarray) -> np.ndarray:
    """A quadratic in board coordinates ``(..., 6)`` (centimetres: a well-scaled basis)."""
    x, y = 100.0 * xy[..., 0], 100.0 * xy[..., 1]
    return np.stack([np.ones_like(x), x, y, x * x, x * y, y * y], -1)


def board_seen(
    linear: np.ndarray, usable: np.ndarray, scanner: Scanner, camera_from_board: np.ndarray, board: Board
) -> tuple[np.ndarray, np.ndarray]:
    """``(H, W)`` True where the photo ``linear (H, W, 3)`` shows the board's print (``usable (H, W)``:
    pixels neither clipped nor dark). The print predicted as its albedo times a gain whose log is a
    quadratic over the board, fitted robustly (Tukey) to the paper's white pixels (the object, its
    shadow and its reflections are the outliers); a pixel is the print where every channel lies within
    ``TUNING.silhouette.seen_sigmas`` robust sigmas of the prediction (relative, with a floor of the
    ink's share of the light), and one-pixel gaps between seen pixels (the print's edges, resampled)
    are closed. And ``(H, W)`` where the ray meets usable paper (the print seen or hidden)."""
    import cv2

    xy, ahead = board_hits(scanner, camera_from_board)
    albedo, paper = board.albedo(xy.reshape(-1, 2), TUNING.silhouette.print_texel_mm)
    albedo = albedo.reshape(ahead.shape)
    paper = paper.reshape(ahead.shape) & ahead & usable
    white = paper & (albedo > 0.5 * albedo.max(initial=0.0))
    if white.sum() < TUNING.silhouette.min_paper_px:
        return np.zeros_like(paper), paper
    lum = linear.mean(-1)
    A = _gain_basis(xy[white])
    r = np.log(np.maximum(lum[white], 1e-6) / albedo[white])
    w = np.ones_like(r)
    k = TUNING.triangulation.tukey  # Tukey's biweight constant: one home for it
    for _ in range(TUNING.silhouette.gain_rounds):
        coef = np.linalg.lstsq(A * w[:, None], r * w, rcond=None)[0]
        e = r - A @ coef
        sigma = max(1.4826 * float(np.median(np.abs(e[w > 0] - np.median(e[w > 0])))), 1e-3)
        u = e / (k * sigma)
        w = np.where(np.abs(u) < 1.0, 1.0 - u * u, 0.0)
    gain = np.exp(np.clip(_gain_basis(xy) @ coef, -30.0, 30.0))
    predicted = gain * albedo
    floor = TUNING.silhouette.ink_floor * gain
    relative = (np.abs(linear - predicted[..., None]) / (predicted + floor)[..., None]).max(-1)
    # the fit's own robust spread (log units ~ relative ones for small residuals) sets the bar
    seen = paper & (relative < TUNING.silhouette.seen_sigmas * sigma)
    seen = cv2.morphologyEx(seen.astype(np.uint8), cv2.MORPH_CLOSE, np.ones((3, 3), np.uint8)).astype(bool)
    return seen & paper, paper


def penetration(seen: np.ndarray) -> np.ndarray:
    """``(H, W)`` float32: how many pixels into seen print each pixel lies (0 where the print is not
    seen): the depth a surface point projected there stands in front of board the photo shows."""
    import cv2

    return cv2.distanceTransform(seen.astype(np.uint8), cv2.DIST_L2, 5).astype(np.float32)


def turned(alignment: Alignment, turn: float, shift: np.ndarray, pivot: np.ndarray) -> Alignment:
    """``alignment`` followed by a turn of ``turn`` radians about the vertical through the mesh-frame
    ``pivot (3,)`` and a shift ``(2,)`` (metres) along the board: x_mesh' = Rz (x_mesh - p) + p + s."""
    c, s = np.cos(turn), np.sin(turn)
    Rz = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    t = Rz @ (alignment.translation - pivot) + pivot + np.array([shift[0], shift[1], 0.0])
    return replace(alignment, rotation=Rz @ alignment.rotation, translation=t)


@dataclass
class SilhouettePlacement:
    """The silhouettes' answer: ``alignment`` (board -> mesh), its per-photo cost ``costs (V,)``, the
    share of its points deeper than ``TUNING.silhouette.fit_px`` into seen print (``outside``), its
    rivals as (turn from the answer in degrees, paired significance: how many standard errors worse
    they fit, over photos; mean cost) best first, the photos that saw the print, and its spread."""

    alignment: Alignment
    costs: np.ndarray
    outside: float
    rivals: list[tuple[float, float, float]]
    photos: int
    turn_sigma: float  # the block jackknife's 1 sigma (``Silhouettes.spread``): radians
    shift_sigma: np.ndarray  # (2,) metres along the board

    def to_json(self) -> dict:
        """A summary for ``registration.json``."""
        return {
            "cost": float(self.costs.mean()),
            "points_outside": self.outside,
            "photos": self.photos,
            "rivals": [{"azimuth_change_deg": t, "significance": z, "cost": c} for t, z, c in self.rivals],
            "azimuth_sigma_deg": float(np.degrees(self.turn_sigma)),
            "shift_sigma_mm": (1e3 * self.shift_sigma).tolist(),
        }


class Silhouettes:
    """The photos' board-seen fields and the mesh's surface samples, to score placements by.

    ``photos``: the working-size stack; ``camera_from_board (V, 4, 4)``; ``mesh`` in its own frame."""

    def __init__(self, photos: PhotoStack, camera_from_board: np.ndarray, board: Board, mesh: Mesh, seed: int = 0):
        import cv2

        self.scanner = photos.scanner
        depth, inside = [], []
        for v in range(len(camera_from_board)):
            linear = photos.linear[v].permute(1, 2, 0).numpy()
            usable = photos.usable[v, 0].numpy() > 0
            seen, paper = board_seen(linear, usable, self.scanner, camera_from_board[v], board)
            depth.append(penetration(seen))
            # before paper the print is hidden at: how far from seen print (or the paper's end) each lies
            hidden = (paper & ~seen).astype(np.uint8)
            inside.append(cv2.distanceTransform(hidden, cv2.DIST_L2, 5).astype(np.float32))
        self.fields = torch.as_tensor(np.stack([np.stack(depth), np.stack(inside)], 1))  # (V, 2, H, W)
        self.seen = (self.fields[:, 0] > 0).flatten(1).any(1).numpy()  # photos that see any print
        self.poses = torch.as_tensor(camera_from_board, dtype=torch.float64)
        self.centres = -(self.poses[:, :3, :3].transpose(1, 2) @ self.poses[:, :3, 3:])[..., 0]  # (V, 3) board frame
        self.points = surface_samples(mesh, TUNING.silhouette.points, seed=seed)  # mesh frame: the sweep's
        # the answer's, with normals: the points on each photo's contour generator must meet the backdrop
        self.fine_points, self.fine_normals = surface_samples(mesh, TUNING.silhouette.fine_points, seed + 1, True)
        lo, hi = mesh.vertices.min(0), mesh.vertices.max(0)
        self.pivot = 0.5 * (lo + hi)

    def residuals(
        self, alignment: Alignment, cap: float, points: np.ndarray | None = None, normals: np.ndarray | None = None
    ) -> torch.Tensor:
        """``(V, N)`` each surface point's penetration into seen print under ``alignment``, softly
        capped at ``cap`` pixels (cap tanh(d / cap): a wrong start still has a slope to follow); 0
        outside a photo. With ``normals (N, 3)``, ``(V, 2N)``: then also each point on a photo's
        contour generator (``TUNING.silhouette.rim_cos``) by how far inside the object's image it
        projects from the nearest seen print — the outline held from both sides."""
        p = self.points if points is None else points
        board_pts = torch.as_tensor((p - alignment.translation) @ alignment.rotation)  # R^T (x - t), scale 1
        cam = board_pts @ self.poses[:, :3, :3].transpose(1, 2) + self.poses[:, None, :3, 3]
        px = camera.project(self.scanner, cam)
        h, w = self.fields.shape[-2:]
        grid = torch.stack([2 * px[..., 0] / (w - 1) - 1, 2 * px[..., 1] / (h - 1) - 1], -1).float()
        grid = torch.nan_to_num(grid, nan=2.0)  # behind a camera: outside
        fields = self.fields if normals is not None else self.fields[:, :1]  # the contour's field only with normals
        d = F.grid_sample(fields, grid[:, :, None], mode="bilinear", padding_mode="zeros", align_corners=True)
        d = (cap * torch.tanh(d[..., 0].double() / cap)).nan_to_num(0.0)  # (V, 2, N)
        if normals is None:
            return d[:, 0]
        n = torch.as_tensor(normals @ alignment.rotation)  # board frame
        view = self.centres[:, None] - board_pts[None]
        cos = (view * n[None]).sum(-1) / view.norm(dim=-1)
        rim = (cos.abs() < TUNING.silhouette.rim_cos).double()
        return torch.cat([d[:, 0], d[:, 1] * rim], 1)

    def costs(self, alignment: Alignment, cap: float | None = None, fine: bool = False) -> np.ndarray:
        """``(V,)`` each photo's mean squared capped residual (pixels squared): the sweep's points'
        penetrations, or (``fine``) the fine points' penetrations and contour distances."""
        cap = TUNING.silhouette.cap_px if cap is None else cap
        return (self._residuals(alignment, cap, fine) ** 2).mean(1).numpy()

    def _residuals(self, alignment: Alignment, cap: float, fine: bool, keep: np.ndarray | None = None) -> torch.Tensor:
        """The sweep's points' penetrations, or (``fine``) the fine points' (those ``keep`` selects)
        penetrations and contour distances."""
        if not fine:
            return self.residuals(alignment, cap)
        p, n = self.fine_points, self.fine_normals
        if keep is not None:
            p, n = p[keep], n[keep]
        return self.residuals(alignment, cap, p, n)

    def refine(
        self, alignment: Alignment, cap: float, rounds: int, fine: bool = False, keep: np.ndarray | None = None
    ) -> Alignment:
        """Levenberg-Marquardt on the capped residuals (``_residuals``: ``fine`` adds the contour's,
        ``keep`` selects fine points) over the turn about the vertical and the shift along the board
        (numerical Jacobian: three parameters), from ``alignment``."""
        step = np.array([TUNING.silhouette.jacobian_rad, *(2 * [TUNING.silhouette.jacobian_m])])
        lam, current = 1e-3, alignment
        r0 = self._residuals(current, cap, fine, keep).flatten().numpy()
        for _ in range(rounds):
            J = np.zeros((r0.size, 3))
            for k in range(3):
                dp = np.zeros(3)
                dp[k] = step[k]
                plus = self._residuals(turned(current, dp[0], dp[1:], self.pivot), cap, fine, keep).flatten().numpy()
                minus = self._residuals(turned(current, -dp[0], -dp[1:], self.pivot), cap, fine, keep).flatten().numpy()
                J[:, k] = (plus - minus) / (2 * step[k])
            JtJ, g = J.T @ J, J.T @ r0
            improved = False
            for _ in range(6):
                A = JtJ + lam * np.diag(np.diag(JtJ) + 1e-12)
                delta = -np.linalg.lstsq(A, g, rcond=None)[0]
                trial = turned(current, delta[0], delta[1:], self.pivot)
                r1 = self._residuals(trial, cap, fine, keep).flatten().numpy()
                if r1 @ r1 < r0 @ r0:
                    current, r0, lam, improved = trial, r1, lam / 3, True
                    break
                lam *= 10
            if not improved:
                break
        return current

    def place(self, start: Alignment) -> SilhouettePlacement:
        """The whole-circle sweep: starts every ``TUNING.silhouette.sweep_step_deg`` from ``start``
        (its shift where the cameras aim), each refined under a wide cap, the distinct minima
        refined again under the final cap; the best is the answer and the others its rivals, each
        compared with it photo by photo."""
        s = TUNING.silhouette
        starts = np.radians(np.arange(0.0, 360.0, s.sweep_step_deg))
        found = [self.refine(turned(start, a, np.zeros(2), self.pivot), s.sweep_cap_px, s.sweep_rounds) for a in starts]
        coarse = [float(self.costs(a, s.sweep_cap_px).mean()) for a in found]
        minima: list[Alignment] = []
        for i in np.argsort(coarse):  # distinct minima, best first
            yaw = yaw_deg(found[i])
            if all(azimuth_apart(yaw, yaw_deg(m)) > TUNING.align.ambiguous_deg for m in minima):
                minima.append(found[i])
            if len(minima) == s.rivals + 1:
                break
        refined, costs = [], []
        for m in minima:  # refined, two minima may meet: the better kept
            a = self.refine(m, s.cap_px, s.final_rounds, fine=True)
            refined.append(a)
            costs.append(self.costs(a, fine=True))
        order = np.argsort([c.mean() for c in costs])
        kept: list[int] = []
        for i in order:
            yaw = yaw_deg(refined[i])
            if all(azimuth_apart(yaw, yaw_deg(refined[j])) > TUNING.align.ambiguous_deg for j in kept):
                kept.append(int(i))
        refined, costs = [refined[i] for i in kept], [costs[i] for i in kept]
        answer, used = refined[0], self.seen
        rivals = []
        for a, c in zip(refined[1:], costs[1:], strict=True):
            diff = (c - costs[0])[used]
            se = diff.std(ddof=1) / np.sqrt(diff.size) if diff.size > 1 else 0.0
            z = float(diff.mean() / se) if se > 0 else float(np.sign(diff.mean()) * np.inf)
            turn = (yaw_deg(a) - yaw_deg(answer) + 180.0) % 360.0 - 180.0
            rivals.append((float(turn), z, float(c.mean())))
        rivals.sort(key=lambda r: r[1])
        depth = self.residuals(answer, 1e6, self.fine_points)[torch.as_tensor(used)]  # penetrations alone
        outside = float((depth > s.fit_px).double().mean())
        turn_sigma, shift_sigma = self.spread(answer, s.jackknife_blocks)
        return SilhouettePlacement(answer, costs[0], outside, rivals, int(used.sum()), turn_sigma, shift_sigma)

    def spread(self, answer: Alignment, blocks: int) -> tuple[float, np.ndarray]:
        """The 1-sigma spread of ``answer``'s turn (radians) and shift along the board ``(2,)`` (metres)
        by a block jackknife over the surface: the fine points cut into ``blocks`` regions (k-means on
        their positions), the refinement redone from the answer without each. A scanned mesh's
        deformation is alike over a region and moves every photo's outline there alike: it counts once
        per region, not once per photo."""
        _, label = kmeans2(self.fine_points, blocks, seed=0, minit="++")
        yaw0 = np.radians(yaw_deg(answer))
        runs = []
        for k in range(blocks):
            a = self.refine(answer, TUNING.silhouette.cap_px, TUNING.silhouette.jackknife_rounds, True, label != k)
            turn = (np.radians(yaw_deg(a)) - yaw0 + np.pi) % (2 * np.pi) - np.pi
            base = turned(answer, turn, np.zeros(2), self.pivot)
            runs.append([turn, *(a.translation - base.translation)[:2]])
        r = np.array(runs)
        sigma = np.sqrt((blocks - 1) / blocks * ((r - r.mean(0)) ** 2).sum(0))
        return float(sigma[0]), sigma[1:]
