"""Photos the marker board does not place, placed by structure from motion beside those it does.

SfM runs on the photos without a board pose and, as anchors, their neighbours along the sweep
(``TUNING.board.fallback_reach`` each side: a hand-held sweep's neighbours overlap, the pairing SfM's
sequential matching uses). The anchors' board poses give the similarity from SfM's frame to the
board's (``align.camera_similarity`` on the camera centres); an SfM photo enters the board frame
through it. The photos SfM does not register, or a join whose anchors disagree with their board
poses by more than ``TUNING.board.max_anchor_rms_px`` at the object, stay unregistered, named. The
cost grows with the photos the board missed, not with the scan.

Convention: camera-from-board 4x4 (OpenCV axes, metres), as ``register.board_poses``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..io.errors import NtpInputError
from ..io.progress import QUIET, Progress
from ..scanner.scanner import Scanner
from .align import camera_similarity, moved_pose
from .board_poses import BoardPoses
from .settings import TUNING
from .sfm import structure_from_motion


@dataclass
class Fallback:
    """What SfM added: poses by name (camera-from-board), and the join's diagnostics."""

    poses: dict[str, np.ndarray]
    anchors: int
    anchor_rms_px: float
    unplaced: dict[str, str]  # photo -> why it stays unregistered

    def to_json(self) -> dict:
        """A summary for ``registration.json`` (``board.sfm_fallback``)."""
        return {
            "photos_placed": sorted(self.poses),
            "anchors": self.anchors,
            "anchor_rms_px": self.anchor_rms_px if np.isfinite(self.anchor_rms_px) else None,
            "unplaced": self.unplaced,
        }


def sfm_subset(names: list[str], missing: list[str], reach: int = TUNING.board.fallback_reach) -> list[str]:
    """The photos SfM maps: ``missing`` and their ``reach`` neighbours each side in ``names``' order."""
    order = sorted(names)
    at = {n: i for i, n in enumerate(order)}
    keep = {order[j] for n in missing for j in range(max(at[n] - reach, 0), min(at[n] + reach + 1, len(order)))}
    return sorted(keep)


def fill_from_sfm(
    photos_dir: Path,
    names: list[str],
    board: BoardPoses,
    scanner: Scanner,
    work: Path,
    progress: Progress = QUIET,
) -> Fallback:
    """SfM poses, in the board frame, for the photos of ``names`` the board did not place (see the
    module docstring); ``work`` holds SfM's database."""
    missing = [n for n in sorted(names) if n not in board.poses]
    subset = sfm_subset(names, missing)
    try:
        sfm = structure_from_motion(photos_dir, subset, scanner, work, progress=progress)
    except NtpInputError as err:
        return Fallback({}, 0, float("nan"), {n: f"structure from motion failed: {err}" for n in missing})
    anchors = {n: board.poses[n] for n in sfm.poses if n in board.poses}
    fit = camera_similarity({n: sfm.poses[n] for n in anchors}, anchors)
    if fit is None:
        why = f"{len(anchors)} of its neighbours the board placed are in SfM's model (need 3)"
        return Fallback({}, len(anchors), float("nan"), dict.fromkeys(missing, why))
    working_m = float(np.linalg.norm(scanner.valid_center))
    apart = [
        np.linalg.norm(_centre(moved_pose(sfm.poses[n], *fit)) - _centre(anchors[n])) * scanner.fx / working_m
        for n in anchors
    ]
    rms = float(np.sqrt(np.mean(np.square(apart))))
    if rms > TUNING.board.max_anchor_rms_px:
        why = f"SfM's model disagrees with the board's poses ({rms:.1f} px RMS at the object)"
        return Fallback({}, len(anchors), rms, dict.fromkeys(missing, why))
    placed = {n: moved_pose(sfm.poses[n], *fit) for n in missing if n in sfm.poses}
    unplaced = {n: "not in SfM's model either" for n in missing if n not in placed}
    return Fallback(placed, len(anchors), rms, unplaced)


def _centre(pose: np.ndarray) -> np.ndarray:
    return -pose[:3, :3].T @ pose[:3, 3]
