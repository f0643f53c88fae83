"""The sRGB transfer function (IEC 61966-2-1), for numpy arrays and torch tensors alike.

Convention: values in [0, 1] (callers clip); linear is scene-referred reflectance or pixel value,
encoded is what an 8-bit sRGB file stores divided by 255.
"""

from __future__ import annotations

from typing import TypeVar

import numpy as np
from torch import Tensor

A = TypeVar("A", np.ndarray, Tensor)


def srgb_encode(linear: A) -> A:
    """Linear ``(...)`` to sRGB-encoded values ``(...)``."""
    small = linear <= 0.0031308
    return small * (12.92 * linear) + ~small * (1.055 * linear.clip(1e-12) ** (1 / 2.4) - 0.055)


def srgb_decode(encoded: A) -> A:
    """sRGB-encoded ``(...)`` to linear values ``(...)`` (``srgb_encode``'s inverse)."""
    small = encoded <= 0.04045
    return small * (encoded / 12.92) + ~small * ((encoded.clip(0.04045) + 0.055) / 1.055) ** 2.4
