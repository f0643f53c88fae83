"""Photo selection: drop unreadable photos and blurry ones (paper §7 cites Crete et al. 2007).

The blur metric is Crete et al.'s no-reference perceptual blur (0 = sharp, 1 = fully blurred) on
the photo's grey level, as scikit-image's ``measure.blur_effect`` computes it (the same score to
1e-5, ``tests/pipeline/test_photo_selection.py``) in one compiled pass an axis over the photo's
8-bit codes (0.09 s at the device's 5 MP on one core; OpenCV's float32 filters took 0.21 s,
scikit-image 0.62 s), and photos are scored on every core at once (``io.threads.worker_threads``).

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
from ..io.jit import compiled
from ..io.progress import QUIET, Progress, warn
from ..io.threads import worker_threads
from ..register.board_poses import detect_corners
from ..scanner.board import Board
from ..scanner.scan_folder import read_codes
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
    as scikit-image). One compiled pass an axis, the GIL released (photos are scored in threads)."""
    sums = _crete_sums(np.ascontiguousarray(codes), BLUR_WINDOW // 2)
    return max(abs(total - kept) / max(total, 1e-30) for total, kept in sums)


@compiled(nogil=True)
def _reflect(i: int, n: int) -> int:
    """OpenCV's BORDER_REFLECT (fedcba|abcdef) of index ``i`` into ``[0, n)``."""
    while i < 0 or i >= n:
        i = -i - 1 if i < 0 else 2 * n - i - 1
    return i


@compiled(nogil=True, fastmath=True)
def _crete_sums(codes: np.ndarray, half: int) -> np.ndarray:
    """Per axis (y, then x) of the grey image of ``codes (H, W, 3)``: the inner pixels' summed Sobel
    gradient along it and the part of it a box blur of ``2 half + 1`` along it does not remove
    ``(2, 2)``: float32 terms, as OpenCV's float32 filters, summed in float32 along a row (fastmath
    lets the compiler vectorise those sums) and in float64 over the rows."""
    h, w = codes.shape[0], codes.shape[1]
    grey = np.empty((h, w), np.float32)
    scale = np.float32(1.0 / (3.0 * 255.0))
    for i in range(h):
        for j in range(w):
            grey[i, j] = (np.float32(codes[i, j, 0]) + np.float32(codes[i, j, 1]) + np.float32(codes[i, j, 2])) * scale
    inv = 1.0 / (2 * half + 1)
    zero, two = np.float32(0.0), np.float32(2.0)
    out = np.zeros((2, 2))
    # along y: running column sums of the box, row by row
    blurred = np.empty((h, w), np.float32)
    acc = np.zeros(w)
    for k in range(-half, half + 1):
        row = grey[_reflect(k, h)]
        for j in range(w):
            acc[j] += row[j]
    for i in range(h):
        above, below = grey[_reflect(i + half + 1, h)], grey[_reflect(i - half, h)]
        for j in range(w):
            blurred[i, j] = acc[j] * inv
            acc[j] += above[j] - below[j]
    total, kept = np.float64(0.0), np.float64(0.0)
    for i in range(2, h - 1):
        g0, g2, b0, b2 = grey[i - 1], grey[i + 1], blurred[i - 1], blurred[i + 1]
        row_total, row_kept = zero, zero
        for j in range(2, w - 1):
            sharp = abs(g2[j - 1] + two * g2[j] + g2[j + 1] - g0[j - 1] - two * g0[j] - g0[j + 1])
            soft = abs(b2[j - 1] + two * b2[j] + b2[j + 1] - b0[j - 1] - two * b0[j] - b0[j + 1])
            row_total += sharp
            row_kept += max(sharp - soft, zero)
        total += row_total
        kept += row_kept
    out[0] = total, kept
    # along x: a running sum along each row (the y pass on the transposed image would be one loop
    # for both, but the transposed copy made the score ~17% slower, measured)
    for i in range(h):
        run = 0.0
        for k in range(-half, half + 1):
            run += grey[i, _reflect(k, w)]
        row = grey[i]
        for j in range(w):
            blurred[i, j] = run * inv
            ahead, behind = j + half + 1, j - half
            run += row[ahead if ahead < w else _reflect(ahead, w)] - row[behind if behind >= 0 else _reflect(behind, w)]
    total, kept = np.float64(0.0), np.float64(0.0)
    for i in range(2, h - 1):
        g0, g1, g2, b0, b1, b2 = grey[i - 1], grey[i], grey[i + 1], blurred[i - 1], blurred[i], blurred[i + 1]
        row_total, row_kept = zero, zero
        for j in range(2, w - 1):
            sharp = abs(g0[j + 1] + two * g1[j + 1] + g2[j + 1] - g0[j - 1] - two * g1[j - 1] - g2[j - 1])
            soft = abs(b0[j + 1] + two * b1[j + 1] + b2[j + 1] - b0[j - 1] - two * b1[j - 1] - b2[j - 1])
            row_total += sharp
            row_kept += max(sharp - soft, zero)
        total += row_total
        kept += row_kept
    out[1] = total, kept
    return out


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
            codes = read_codes(p, scanner)
        except NtpInputError as err:
            return err
        if board is None:
            return blur_score(codes), None
        import cv2

        grey = cv2.cvtColor(codes, cv2.COLOR_RGB2GRAY)
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
