"""Image files through OpenImageIO: float EXR maps and 8-bit PNG previews, written atomically.

Arrays are ``(H, W)`` or ``(H, W, C)`` numpy, row 0 at the top. EXR holds linear float32; PNG
holds 8-bit values of ``clip(x, 0, 1) * 255`` (no colour transform: callers choose the encoding).
"""

from __future__ import annotations

import contextlib
import os
import sys
import threading
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import OpenImageIO as oiio

from .atomic import atomic_path
from .errors import NtpInputError
from .input_file import regular_file

# values (width x height x channels) ntp decodes from one file: a 16384^2 RGBA map (the largest
# texture GPUs take), 50x a 2448x2048 RGBA photo; a header declaring more is refused unread
MAX_PIXELS = 1 << 30


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


_QUIET_LOCK = threading.Lock()
_quiet: dict[str, int] = {"depth": 0, "saved": -1}


@contextlib.contextmanager
def _quiet_stderr() -> Iterator[None]:
    """Silence C libraries writing to file descriptor 2 (libpng prints its errors there; ours are
    raised as one line instead). Photos are decoded on several threads: the first to enter
    redirects the process's descriptor, the last to leave restores it."""
    with _QUIET_LOCK:
        if _quiet["depth"] == 0:
            sys.stderr.flush()
            _quiet["saved"] = os.dup(2)
            devnull = os.open(os.devnull, os.O_WRONLY)
            os.dup2(devnull, 2)
            os.close(devnull)
        _quiet["depth"] += 1
    try:
        yield
    finally:
        with _QUIET_LOCK:
            _quiet["depth"] -= 1
            if _quiet["depth"] == 0:
                os.dup2(_quiet["saved"], 2)
                os.close(_quiet["saved"])


@dataclass(frozen=True)
class Decoded:
    """An image as decoded: float32 ``(H, W, C)`` pixels (integer formats scaled to [0, 1]; an 8-bit
    file's uint8 codes where ``decode`` was asked for them), the file's own pixel format (``"uint8"``,
    ``"uint16"``, ``"half"``, ``"float"``, ...) and the alpha channel's index (-1: none). Alpha is
    *not* multiplied in: the colour channels are the file's."""

    pixels: np.ndarray
    format: str
    alpha_channel: int


def decode(
    path: str | Path, size: tuple[int, int] | None = None, max_pixels: int = MAX_PIXELS, eight_bit: bool = False
) -> Decoded:
    """Decode any image OpenImageIO knows. Only a regular file is opened (``io.input_file``); its
    header is checked before any pixel is decoded: ``size`` (width, height) where given, at most
    ``max_pixels`` values otherwise. Strict: a file the decoder reports any problem with raises
    ``NtpInputError`` (a truncated JPEG would otherwise decode, its missing rows grey).
    ``eight_bit``: an 8-bit file's pixels come back as its uint8 codes (a quarter of the float's
    memory, no conversion); other files as float32 all the same."""
    path = Path(path)
    regular_file(path)
    config = oiio.ImageSpec()
    config.attribute("oiio:UnassociatedAlpha", 1)  # PNG stores colour unmultiplied: keep it so
    with _quiet_stderr():
        inp = oiio.ImageInput.open(str(path), config)
        if inp is None:
            raise NtpInputError(path, f"cannot read image ({oiio.geterror().strip() or 'unknown format'})")
        try:
            spec = inp.spec()
            w, h, c = spec.width, spec.height, spec.nchannels
            if size is not None and (w, h) != size:
                raise NtpInputError(path, f"{w}x{h} image, expected {size[0]}x{size[1]}")
            if w * h * c > max_pixels:
                raise NtpInputError(path, f"declares {w}x{h}x{c} values, more than the {max_pixels:.3g} ntp reads")
            as_codes = eight_bit and str(spec.format) == "uint8"
            pixels = inp.read_image(oiio.UINT8 if as_codes else oiio.FLOAT)
            problem = inp.geterror().strip().splitlines() if pixels is None or inp.has_error else None
        finally:
            inp.close()
    if problem is not None:
        raise NtpInputError(path, f"truncated or corrupt image ({problem[0] if problem else 'decode failed'})")
    pixels = np.asarray(pixels, dtype=np.uint8 if as_codes else np.float32)
    return Decoded(pixels if pixels.ndim == 3 else pixels[..., None], str(spec.format), spec.alpha_channel)


def read_image(path: str | Path, size: tuple[int, int] | None = None) -> np.ndarray:
    """``decode(path, size).pixels``: float32 ``(H, W, C)``; 8-bit files come back in [0, 1]."""
    return decode(path, size).pixels
