"""What other renderers can draw of ntp's anisotropic GGX: facts the add-on's materials, the
``.glb`` and the run's report share (one home).

Convention: alphas are GGX widths ``(N, 2)`` (alpha_x along the tangent map, alpha_y across),
positive; a texel's anisotropy is ``max / min`` of its two alphas.
"""

from __future__ import annotations

import numpy as np

# glTF's dielectric F0 at its default IOR 1.5, ((1.5 - 1) / (1.5 + 1))^2; KHR_materials_specular
# scales it per channel (ntp's export makes it 0.04 rho_s)
GLTF_DIELECTRIC_F0 = 0.04

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


def base_colour_for_fresnel_mix(rho_d: np.ndarray, rho_s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """glTF base colour ``(..., 3)`` in [0, 1] whose diffuse equals ntp's ``rho_d`` under glTF's
    ``fresnel_mix``, and which texels ``(...)`` it clips at 1: the viewer draws the diffuse times
    (1 - F), F = F0 + (F90 - F0)(1 - v.h)^5 >= F0 = 0.04 rho_s, where ntp's diffuse is rho_d / pi
    whole — so base = rho_d / (1 - 0.04 rho_s), exact where v.h ~ 1 (a light beside the camera;
    the (1 - v.h)^5 term is < 0.3% of F90 while the light is within 90 deg of the view)."""
    base = rho_d / np.maximum(1.0 - GLTF_DIELECTRIC_F0 * rho_s, 1e-6)
    clipped = (base > 1.0).any(-1)
    return np.clip(base, 0.0, 1.0), clipped
