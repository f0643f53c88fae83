"""Image files through OpenImageIO: float EXR maps and 8-bit PNG previews, written atomically.

Arrays are ``(H, W)`` or ``(H, W, C)`` numpy, row 0 at the top. EXR holds linear float32; PNG
holds 8-bit values of ``clip(x, 0, 1) * 255`` (no colour transform: callers choose the encoding).
"""

from __future__ import annotations

import contextlib
import os
import sys
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import OpenImageIO as oiio

from .atomic import atomic_path
from .errors import NtpInputError


def _write(path: Path, pixels: np.ndarray, fmt) -> None:
    if pixels.ndim == 2:
        pixels = pixels[..., None]
    h, w, c = pixels.shape
    with atomic_path(path) as tmp:
        out = oiio.ImageOutput.create(str(tmp))
        if out is None:
            raise NtpInputError(path, f"OpenImageIO cannot write this format ({oiio.geterror()})")
        spec = oiio.ImageSpec(w, h, c, fmt)
        spec.attribute("DateTime", "")  # no write time: the same pixels give the same bytes (content-keyed caches)
        if path.suffix.lower() == ".exr":
            spec.attribute("compression", "zip")
        if not out.open(str(tmp), spec) or not out.write_image(np.ascontiguousarray(pixels)):
            err = out.geterror()
            out.close()
            raise NtpInputError(path, f"cannot write image ({err})")
        out.close()


def write_exr(path: str | Path, pixels: np.ndarray) -> None:
    """Write linear float data as a float32 EXR (zip compressed)."""
    _write(Path(path), np.asarray(pixels, dtype=np.float32), oiio.FLOAT)


def write_png(path: str | Path, pixels: np.ndarray) -> None:
    """Write values in [0, 1] (clipped) as an 8-bit PNG."""
    q = np.round(np.clip(np.nan_to_num(np.asarray(pixels, dtype=np.float64)), 0, 1) * 255).astype(np.uint8)
    _write(Path(path), q, oiio.UINT8)


@contextlib.contextmanager
def _quiet_stderr() -> Iterator[None]:
    """Silence C libraries writing to file descriptor 2 (libpng prints its errors there; ours are
    raised as one line instead)."""
    sys.stderr.flush()
    saved = os.dup(2)
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, 2)
        yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)
        os.close(devnull)


def read_image(path: str | Path) -> np.ndarray:
    """Read any image OpenImageIO knows as float32 ``(H, W, C)``; 8-bit files come back in [0, 1].
    Strict: a file the decoder reports any problem with raises ``NtpInputError`` (a truncated JPEG
    would otherwise decode, its missing rows grey)."""
    path = Path(path)
    with _quiet_stderr():
        inp = oiio.ImageInput.open(str(path))
        if inp is None:
            raise NtpInputError(path, f"cannot read image ({oiio.geterror().strip() or 'unknown format'})")
        try:
            pixels = inp.read_image(oiio.FLOAT)
            problem = inp.geterror().strip().splitlines() if pixels is None or inp.has_error else None
        finally:
            inp.close()
    if problem is not None:
        raise NtpInputError(path, f"truncated or corrupt image ({problem[0] if problem else 'decode failed'})")
    pixels = np.asarray(pixels, dtype=np.float32)
    return pixels if pixels.ndim == 3 else pixels[..., None]
