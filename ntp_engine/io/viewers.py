"""What other renderers can draw of ntp's anisotropic GGX: facts the add-on's materials, the
``.glb`` and the run's report share (one home).

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


def khronos_inputs(alpha_hi: np.ndarray, alpha_lo: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """glTF ``roughness`` and ``KHR_materials_anisotropy`` strength that give GGX widths
    ``alpha_hi`` along the anisotropy direction and ``alpha_lo`` across it (``khronos_alphas``'
    inverse): roughness = sqrt(alpha_lo), strength = sqrt((alpha_hi - alpha_lo) / (1 - alpha_lo)).
    Every ratio is reachable while alpha_hi <= 1 (ntp's alphas are <= 0.5)."""
    lo = np.clip(alpha_lo, 0.0, 1.0)
    hi = np.clip(np.maximum(alpha_hi, lo), 0.0, 1.0)
    return np.sqrt(lo), np.sqrt(np.clip((hi - lo) / np.maximum(1.0 - lo, 1e-12), 0.0, 1.0))


def khronos_alphas(roughness: np.ndarray, strength: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(alpha_t, alpha_b) a viewer conforming to ``KHR_materials_anisotropy`` draws: alpha = r^2,
    alpha_t = mix(alpha, 1, strength^2) along the anisotropy direction, alpha_b = alpha."""
    alpha = roughness**2
    return alpha + (1.0 - alpha) * strength**2, alpha
