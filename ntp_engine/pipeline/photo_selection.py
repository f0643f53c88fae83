"""Photo selection: drop unreadable photos and blurry ones (paper §7 cites Crete et al. 2007).

The blur metric is scikit-image's ``measure.blur_effect`` (Crete et al.'s no-reference
perceptual blur, 0 = sharp, 1 = fully blurred) on the photo's grey level. One scan's photos share
their content, so a photo is blurry relative to the scan: its score exceeds the scan's median by
more than ``margin`` (0.08 by default; a 1-pixel Gaussian blur adds ~0.14 on virtual scans).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..io.errors import NtpInputError
from ..io.progress import QUIET, Progress, warn
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

    def to_json(self) -> dict:
        """A JSON-able dict (``from_json`` reads it back)."""
        return {"kept": self.kept, "blurry": self.blurry, "unreadable": self.unreadable, "scores": self.scores}

    @classmethod
    def from_json(cls, d: dict) -> Selection:
        """The selection ``to_json`` wrote."""
        return cls(d["kept"], d["blurry"], d["unreadable"], d["scores"])


def blur_score(codes: np.ndarray) -> float:
    """Crete et al. blur of an ``(H, W, 3)`` 8-bit photo (grey = channel mean)."""
    from skimage.measure import blur_effect

    return float(blur_effect(codes.mean(-1) / 255.0))


def select_photos(
    paths: list[Path], scanner: Scanner, margin: float = TUNING.select.blur_margin, progress: Progress = QUIET
) -> Selection:
    """Keep the readable photos of the camera's size whose blur is at most the median + ``margin``;
    each photo left out as unreadable (truncated, corrupt, wrong size) is named on stderr."""
    scores, unreadable = {}, []
    for p in progress.track(paths, "blur check", unit="photo"):
        try:
            img = read_photo(p, scanner)
        except NtpInputError as err:
            warn(f"{err} — skipped")
            unreadable.append(p.name)
            continue
        scores[p.name] = blur_score(img)
    if not scores:
        return Selection([], {}, unreadable, {})
    limit = float(np.median(list(scores.values()))) + margin
    blurry = {n: round(s, 4) for n, s in scores.items() if s > limit}
    kept = [n for n in scores if n not in blurry]
    return Selection(kept, blurry, unreadable, {n: round(s, 4) for n, s in scores.items()})
