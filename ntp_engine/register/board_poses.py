"""Camera poses from the marker board (``scanner.board``): each photo's ChArUco corners found to
sub-pixel (OpenCV's ``CharucoDetector``), then its pose by PnP against the board's known layout
with the device's intrinsics (IPPE's two planar solutions, the better refined by Levenberg-Marquardt).

Convention: camera-from-board 4x4 (OpenCV axes, metres; the board frame of ``scanner.board``);
pixels at integer centres, as the device file. The board's layout is exact (printed), so each
photo's pose is its own maximum-likelihood estimate: a bundle adjustment over all photos would move
none of them.

A corner the object half hides can pull the sub-pixel search onto its outline (pixels off): each
photo's corners are judged by their own residuals — the one furthest out is dropped while it lies
beyond ``TUNING.board.outlier_z`` robust sigmas (1.4826 x the median absolute residual, at least
``TUNING.board.noise_floor_px``) and more than ``TUNING.board.min_corners`` remain — and the pose
solved again without it. A photo with fewer corners is named as not seeing the board. OpenCV's
corners are moved by ``TUNING.board.corner_offset_px`` into the device file's pixel convention.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..io.mesh import Mesh
from ..io.progress import QUIET, Progress
from ..io.threads import worker_threads
from ..scanner.board import Board
from ..scanner.scanner import Scanner
from .align import Alignment, convergence_point
from .settings import TUNING


@dataclass
class BoardView:
    """One photo's view of the board: corners found, their ids ``(N,)`` and pixels ``(N, 2)``, the
    pose (None: not found or rejected) and its residuals' sum of squares (pixels^2)."""

    name: str
    ids: np.ndarray
    pixels: np.ndarray
    pose: np.ndarray | None = None
    sum_sq_px: float = float("nan")
    rejected: str | None = None  # why the pose was not kept
    dropped: int = 0  # corners left out as outliers

    @property
    def rms_px(self) -> float:
        """Reprojection RMS of the corners (pixels, per coordinate)."""
        return float(np.sqrt(self.sum_sq_px / max(2 * len(self.ids), 1)))


@dataclass
class BoardPoses:
    """The photos the board placed: camera-from-board by name; those it did not, by name."""

    poses: dict[str, np.ndarray]
    unregistered: list[str]
    views: list[BoardView]
    sfm: dict | None = None  # what structure from motion added (``board_fallback.Fallback.to_json``)

    def to_json(self) -> dict:
        """A summary for ``registration.json``."""
        kept = [v for v in self.views if v.pose is not None]
        return {
            "photos_with_pose": len(kept),
            "photos_without": {v.name: v.rejected for v in self.views if v.pose is None},
            "corners_median": float(np.median([len(v.ids) for v in kept])) if kept else 0.0,
            "rms_px_median": float(np.median([v.rms_px for v in kept])) if kept else None,
            "corners_dropped": int(sum(v.dropped for v in kept)),
            "sfm_fallback": self.sfm,
        }


def detect_corners(gray: np.ndarray, board: Board) -> tuple[np.ndarray, np.ndarray]:
    """The board's inner corners seen in an 8-bit grey photo ``(H, W)``: ids ``(N,)`` and
    sub-pixel positions ``(N, 2)`` (integer pixel centres). Markers a foreign or different board
    shows are not this board's: they yield no corner."""
    import cv2

    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = cv2.aruco.CORNER_REFINE_SUBPIX
    detector = cv2.aruco.CharucoDetector(board.opencv(), cv2.aruco.CharucoParameters(), params)
    corners, ids, _, _ = detector.detectBoard(gray)
    if ids is None or len(ids) == 0:
        return np.zeros(0, dtype=int), np.zeros((0, 2))
    return ids.ravel().astype(int), corners.reshape(-1, 2).astype(np.float64) - TUNING.board.corner_offset_px


def solve_pose(
    ids: np.ndarray, pixels: np.ndarray, board: Board, scanner: Scanner
) -> tuple[np.ndarray, np.ndarray] | None:
    """Camera-from-board 4x4 from corners (``detect_corners``) and each corner's reprojection
    residual ``(N, 2)`` (pixels); None with fewer than ``TUNING.board.min_corners``, corners all on
    one line, or the board behind the camera."""
    import cv2

    if len(ids) < TUNING.board.min_corners:
        return None
    obj = board.corner_points()[ids]
    centred = obj[:, :2] - obj[:, :2].mean(0)
    if np.linalg.svd(centred, compute_uv=False)[-1] < 1e-3 * board.square_mm * 1e-3 * np.sqrt(len(ids)):
        return None  # collinear: the pose turns freely about the line
    K, dist = scanner.K.astype(np.float64), np.asarray(scanner.distortion, dtype=np.float64)
    img = pixels.reshape(-1, 1, 2)
    n, rvecs, tvecs, errors = cv2.solvePnPGeneric(obj, img, K, dist, flags=cv2.SOLVEPNP_IPPE)
    if n == 0:
        return None
    best = int(np.argmin(np.asarray(errors).ravel()))
    rvec, tvec = cv2.solvePnPRefineLM(obj, img, K, dist, rvecs[best].copy(), tvecs[best].copy())
    if tvec.ravel()[2] <= 0:
        return None  # the board behind the camera: a mirror solution
    projected, _ = cv2.projectPoints(obj, rvec, tvec, K, dist)
    pose = np.eye(4)
    pose[:3, :3] = cv2.Rodrigues(rvec)[0]
    pose[:3, 3] = tvec.ravel()
    return pose, projected.reshape(-1, 2) - pixels


def robust_pose(name: str, ids: np.ndarray, pixels: np.ndarray, board: Board, scanner: Scanner) -> BoardView:
    """The photo's pose with its outlying corners dropped one at a time (see the module docstring)."""
    v = BoardView(name, ids, pixels)
    keep = np.ones(len(ids), dtype=bool)
    while (solved := solve_pose(ids[keep], pixels[keep], board, scanner)) is not None:
        v.pose, residual = solved
        v.sum_sq_px = float((residual**2).sum())
        r = np.abs(residual).max(1)
        sigma = max(1.4826 * float(np.median(np.abs(residual))), TUNING.board.noise_floor_px)
        worst = int(np.argmax(r))
        if r[worst] <= TUNING.board.outlier_z * sigma or keep.sum() <= TUNING.board.min_corners:
            v.ids, v.pixels, v.dropped = ids[keep], pixels[keep], int((~keep).sum())
            return v
        keep[np.flatnonzero(keep)[worst]] = False
    v.pose = None
    v.rejected = f"board not seen ({len(ids)} corners, need {TUNING.board.min_corners} not on one line)"
    return v


def board_poses(
    photos_dir: Path, names: list[str], board: Board, scanner: Scanner, progress: Progress = QUIET
) -> BoardPoses:
    """The board's pose in each photo of ``names`` (see the module docstring); photos read in
    parallel (``io.threads.worker_threads``). The pipeline finds the corners as it selects the
    photos (``pipeline.photo_selection``) and calls ``poses_from_corners``."""

    def corners(name: str) -> tuple[np.ndarray, np.ndarray]:
        import cv2

        gray = cv2.imread(str(photos_dir / name), cv2.IMREAD_GRAYSCALE)
        if gray is None:
            return np.zeros(0, dtype=int), np.zeros((0, 2))
        return detect_corners(gray, board)

    with ThreadPoolExecutor(worker_threads()) as pool:
        found = list(progress.track(pool.map(corners, names), "marker board", total=len(names), unit="photo"))
    return poses_from_corners(dict(zip(names, found, strict=True)), board, scanner)


def poses_from_corners(corners: dict[str, tuple[np.ndarray, np.ndarray]], board: Board, scanner: Scanner) -> BoardPoses:
    """The board's pose in each photo from its corners (ids, pixels) by name (``robust_pose``)."""
    views = [robust_pose(name, ids, px, board, scanner) for name, (ids, px) in corners.items()]
    poses = {v.name: v.pose for v in views if v.pose is not None}
    return BoardPoses(poses, [v.name for v in views if v.pose is None], views)


def first_placement(mesh: Mesh, camera_from_board: list[np.ndarray]) -> Alignment:
    """The mesh put on the board before the photos refine it: its foot on the board's plane, its
    centre where the cameras' optical axes pass closest (a hand-held scan aims at the object), turned
    as the board (the check sweeps every azimuth). Board frame -> mesh frame, scale 1 (metric)."""
    aim = convergence_point(camera_from_board)
    lo, hi = mesh.vertices.min(0), mesh.vertices.max(0)
    centre = 0.5 * (lo + hi)
    translation = np.array([centre[0] - aim[0], centre[1] - aim[1], lo[2]])
    return Alignment(1.0, np.eye(3), translation, float("nan"), 0, 0, 0)
