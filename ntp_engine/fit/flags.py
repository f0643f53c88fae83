"""The per-texel flags of a result (``fit.flags``, ``confidence.exr``'s count of flagged texels):
one bit each, defined here once, set by the fit (``fit.geometry``, ``fit.highlights``) and the
refinement (``refine``). Stored as int32 in the fit's arrays and int in torch tensors; a texel with
no bit set was fitted from its own trace without reservation.
"""

from __future__ import annotations

from enum import IntFlag


class TexelFlag(IntFlag):
    """What a texel's parameters do not rest on (bit values are part of the cached fit arrays)."""

    NONFINITE = 1  # NaN/Inf in the lumitexel (treated as 0)
    ZERO = 2  # no signal in the lumitexel
    NO_LOBE = 4  # no specular lobe could be fitted: FALLBACK_ALPHA and rho_s 0
    NO_HIGHLIGHT = 8  # no view saw the fitted lobe's highlight (paper Eq. 6's beta below BETA_MIN)
    SPECULAR_UNCONSTRAINED = 16  # the refinement kept no lobe of the texel's own: its photos do not show one
    TANGENT_UNCONSTRAINED = (
        32  # the lobe is isotropic to within RefineTuning.policy.isotropic_ratio: the tangent is arbitrary
    )
    FROM_MATERIAL = 64  # the lobe is its basis material's: the texel's photos miss it
    MARGINAL = 128  # refined on entries the mesh shadows or sees at grazing angles (too few others)
    WIDTH_FROM_MATERIAL = 256  # a lobe of its own, its width its material's: the trace could not tell them apart
    AT_BOUND = 512  # a kept lobe's alpha or rho_s settled on its range's bound: the photos bound it from one side
