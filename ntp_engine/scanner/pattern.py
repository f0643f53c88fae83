"""Lighting patterns: per-emitter RGB drive ``(L, 3)`` in [0, 1].

Files are CSV (one emitter per row, R,G,B) or NPY. The LED driver projects a pattern with 8 bits
per channel, so two patterns that agree to half a step of 1/255 light the object identically
(``patterns_agree``). The named patterns are the paper's comparisons (Fig. 14): ``full_on``,
``point`` (the emitter nearest the array's centre) and ``binary`` (a fixed pseudo-random half on).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..io.atomic import atomic_path
from ..io.errors import NtpInputError
from ..io.input_file import MAX_BYTES, regular_file
from .scanner import Scanner

NAMED_PATTERNS = ("full_on", "point", "binary")
QUANTUM = 1.0 / 255.0  # one step of the LED driver's 8-bit PWM


def read_pattern_file(path: Path, emitters: int) -> np.ndarray:
    """An ``(emitters, 3)`` pattern from a CSV or NPY file; a one-line ``NtpInputError`` naming
    the file when it is unreadable, has the wrong shape or values outside [0, 1]."""
    regular_file(path, MAX_BYTES["pattern"])
    try:
        arr = np.load(path) if path.suffix == ".npy" else np.loadtxt(path, delimiter=",", ndmin=2)
    except (OSError, ValueError) as err:
        raise NtpInputError(path, f"cannot read ({err})") from None
    return checked_pattern(np.asarray(arr, dtype=np.float64), emitters, path)


def checked_pattern(pattern: np.ndarray, emitters: int, source: Path | None) -> np.ndarray:
    """``pattern`` if it is ``(emitters, 3)`` and finite in [0, 1]; else a one-line error naming ``source``."""
    if pattern.shape != (emitters, 3):
        raise NtpInputError(source, f"expected {emitters}x3 RGB values (one per emitter), got shape {pattern.shape}")
    if not np.isfinite(pattern).all() or (pattern < 0).any() or (pattern > 1).any():
        raise NtpInputError(source, "values must be in [0, 1]")
    return pattern


def quantise(pattern: np.ndarray) -> np.ndarray:
    """The pattern as the driver projects it: each value rounded to k / 255."""
    return np.round(np.clip(pattern, 0, 1) * 255) / 255


def write_pattern_file(path: Path, pattern: np.ndarray) -> None:
    """Write the 8-bit-quantised pattern as CSV (atomic)."""
    with atomic_path(path) as tmp:
        np.savetxt(tmp, quantise(pattern), delimiter=",", fmt="%.8f")


def patterns_agree(a: np.ndarray, b: np.ndarray) -> bool:
    """True when ``a`` and ``b (L, 3)`` are the same pattern to the driver's 8-bit quantisation."""
    return a.shape == b.shape and bool(np.abs(a - b).max(initial=0.0) <= 0.5 * QUANTUM + 1e-6)


def named_pattern(kind: str, scanner: Scanner) -> np.ndarray:
    """A fixed ``(L, 3)`` pattern for ``scanner``: ``full_on``, ``point``, ``binary`` or a pattern file."""
    L = scanner.num_emitters
    if kind == "full_on":
        return np.ones((L, 3))
    if kind == "point":
        p = np.zeros((L, 3))
        centre = scanner.emitter_positions.mean(0)
        p[int(np.argmin(np.linalg.norm(scanner.emitter_positions - centre, axis=1)))] = 1.0
        return p
    if kind == "binary":
        return (np.random.default_rng(7).random((L, 3)) < 0.5).astype(np.float64)
    return read_pattern_file(Path(kind), L)
