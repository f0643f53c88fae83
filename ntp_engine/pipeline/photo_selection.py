"""Photo selection: drop unreadable photos and blurry ones (paper §7 cites Crete et al. 2007).

The blur metric is Crete et al.'s no-reference perceptual blur (0 = sharp, 1 = fully blurred) on
the photo's grey level, as scikit-image's ``measure.blur_effect`` computes it (the same score to
1e-6, ``tests/pipeline/test_photo_selection.py``) in float32 OpenCV filters: 3x faster at the
device's 5 MP, and photos are scored on every core at once (``io.threads.worker_threads``).

Where the object stands on a marker board, the same read of each photo finds the board's corners
(``register.board_poses.detect_corners``), kept with the selection: a photo is decoded once (a 5 MP
PNG takes as long to decode as the blur score and the corner search together). One scan's photos share
their content, so a photo is blurry relative to the scan: its score exceeds the scan's median by
more than ``margin`` (0.08 by default; a 1-pixel Gaussian blur adds ~0.14 on virtual scans).
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..io.errors import NtpInputError
from ..io.progress import QUIET, Progress, warn
from ..io.threads import worker_threads
from ..register.board_poses import detect_corners
from ..scanner.board import Board
from ..scanner.scan_folder import read_photo
from ..scanner.scanner import Scanner
from .settings import TUNING


@dataclass
class Selection:
    """Which photos a scan keeps: sharp and readable ones, by name; the rest with the reason."""

    kept: list[str]
    blurry: dict[str, float] = field(default_factory=dict)  # name -> blur score
    unreadable: list[str] = field(default_factory=list)
    scores: dict[str, float] = field(default_factory=dict)
    # with a board: each readable photo's corners, (ids (N,), pixels (N, 2)) — ``detect_corners``
    corners: dict[str, tuple[np.ndarray, np.ndarray]] | None = None

    def to_json(self) -> dict:
        """A JSON-able dict (``from_json`` reads it back)."""
        corners = None
        if self.corners is not None:
            corners = {n: [ids.tolist(), px.tolist()] for n, (ids, px) in self.corners.items()}
        return {
            "kept": self.kept,
            "blurry": self.blurry,
            "unreadable": self.unreadable,
            "scores": self.scores,
            "board_corners": corners,
        }

    @classmethod
    def from_json(cls, d: dict) -> Selection:
        """The selection ``to_json`` wrote."""
        corners = d.get("board_corners")
        if corners is not None:
            corners = {
                n: (np.asarray(ids, dtype=int), np.asarray(px, dtype=np.float64).reshape(-1, 2))
                for n, (ids, px) in corners.items()
            }
        return cls(d["kept"], d["blurry"], d["unreadable"], d["scores"], corners)


BLUR_WINDOW = 11  # pixels: Crete et al.'s (and scikit-image's) strong low-pass along each axis


def blur_score(codes: np.ndarray) -> float:
    """Crete et al. blur of an ``(H, W, 3)`` 8-bit photo (grey = channel mean): per image axis, the
    share of the Sobel gradient along it that an 11-pixel box blur along it does not remove is the
    sharpness; the score is 1 minus the smaller one (reflected borders, the outer 2 pixels left out,
    as scikit-image)."""
    import cv2

    grey = cv2.transform(codes.astype(np.float32), np.full((1, 3), 1.0 / (3 * 255.0)))
    h, w = grey.shape
    inner = (slice(2, h - 1), slice(2, w - 1))
    scores = []
    for dx, dy in ((0, 1), (1, 0)):  # along rows (y), then along columns (x)
        box = (BLUR_WINDOW, 1) if dx else (1, BLUR_WINDOW)  # OpenCV sizes are (width, height)
        blurred = cv2.blur(grey, box, borderType=cv2.BORDER_REFLECT)
        sharp = np.abs(cv2.Sobel(grey, cv2.CV_32F, dx, dy, ksize=3, borderType=cv2.BORDER_REFLECT))[inner]
        soft = np.abs(cv2.Sobel(blurred, cv2.CV_32F, dx, dy, ksize=3, borderType=cv2.BORDER_REFLECT))[inner]
        total = float(sharp.sum(dtype=np.float64))
        kept = float(np.maximum(sharp - soft, 0).sum(dtype=np.float64))
        scores.append(abs(total - kept) / max(total, 1e-30))
    return max(scores)


def select_photos(
    paths: list[Path],
    scanner: Scanner,
    margin: float = TUNING.select.blur_margin,
    progress: Progress = QUIET,
    board: Board | None = None,
) -> Selection:
    """Keep the readable photos of the camera's size whose blur is at most the median + ``margin``;
    each photo left out as unreadable (truncated, corrupt, wrong size) is named on stderr. With a
    ``board``, each readable photo's board corners are found in the same read."""
    scores, unreadable, corners = {}, [], {}

    def score(p: Path) -> tuple[float, tuple[np.ndarray, np.ndarray] | None] | NtpInputError:
        try:
            codes = read_photo(p, scanner)
        except NtpInputError as err:
            return err
        if board is None:
            return blur_score(codes), None
        import cv2

        grey = cv2.cvtColor(codes.astype(np.uint8), cv2.COLOR_RGB2GRAY)
        return blur_score(codes), detect_corners(grey, board)

    with ThreadPoolExecutor(worker_threads()) as pool:
        stage = "blur check" if board is None else "blur check, marker board"
        done = progress.track(pool.map(score, paths), stage, len(paths), "photo")
        for p, s in zip(paths, done, strict=True):
            if isinstance(s, NtpInputError):
                warn(f"{s} — skipped")
                unreadable.append(p.name)
                continue
            scores[p.name] = s[0]
            if s[1] is not None:
                corners[p.name] = s[1]
    found = corners if board is not None else None
    if not scores:
        return Selection([], {}, unreadable, {}, found)
    limit = float(np.median(list(scores.values()))) + margin
    blurry = {n: round(s, 4) for n, s in scores.items() if s > limit}
    kept = [n for n in scores if n not in blurry]
    return Selection(kept, blurry, unreadable, {n: round(s, 4) for n, s in scores.items()}, found)
