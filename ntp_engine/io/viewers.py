"""What other renderers can draw of ntp's anisotropic GGX: facts the add-on's materials and the
run's report share (one home).

Convention: alphas are GGX widths ``(N, 2)`` (alpha_x along the tangent map, alpha_y across),
positive; a texel's anisotropy is ``max / min`` of its two alphas.
"""

from __future__ import annotations

import numpy as np

# Cycles' Principled BSDF (4.x/5.x, svm_closure.h): alpha_x = r^2 / s, alpha_y = r^2 s with
# s = sqrt(1 - 0.9 Anisotropic), Anisotropic in [0, 1] — at most 1 / (1 - 0.9) = 10:1
CYCLES_PRINCIPLED_MAX_ANISOTROPY = 10.0


def beyond_principled(alpha: np.ndarray) -> np.ndarray:
    """Which texels of ``alpha (N, 2)`` are more anisotropic than Cycles' Principled BSDF draws
    (``(N,)`` bool): it clamps them to 10:1 — the accurate material's Glossy BSDF reaches 10^4."""
    hi, lo = alpha.max(1), alpha.min(1)
    return hi > CYCLES_PRINCIPLED_MAX_ANISOTROPY * lo
