"""The refinement's settings (``RefineSettings``, with the camera's noise model ``SensorNoise``) and the
constants of its model, solver and policy, each with where its value comes from (the reasons, with
their measurements, are in docs/refinement.md and docs/tuning.md).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch
from torch import Tensor

from ..scanner.camera import VALID_CODE

CENSOR_CODE = VALID_CODE[1]  # above this an 8-bit code may be (or border) a clipped pixel: a lower bound
EXPANDED_BLOCKS = 4  # emitter blocks per entry summed sample by sample (the rest as coarse emitters)
MAX_TRIES = 3  # damping increases per LM iteration before the texel waits for the next one
# bounds of the noise model's calibration factor (``calibrated``): it inflates the model, never
# tightens it — tighter than 1 let the data tip normals against the priors (gallery, docs/refinement.md)
NOISE_SCALE = (1.0, 10.0)
# the light bounced onto an entry (support, object) as the model sums it is right to ~30% per entry
# (the box's Cycles scan at the truth: rms 0.19-0.34 of it; the model's samples, 16 specular then, the renders'
# Monte Carlo noise, second bounces): noise of this many times the pixel's bounced share (its
# diffuse light's, at the geometric normal) — 0.3 / 0.6 / 1.0 measured on the box and the knot
# (docs/refinement.md): 0.6 the normals' best, 1.0 lost the box's rough metal's lobe
BOUNCE_NOISE = 0.6
CONVERGED = 1e-4  # a texel whose LM step lowers its cost by less than this (relative) is done
SHARP_START = 0.25  # the multi-start's sharper lobe: alphas times this
ALBEDO_ITERATIONS = 3  # reweighted least squares of the albedos under the robust cost (lobe_costs)
CLIPPED_ROUNDS = 3  # solves of the albedo start, each adding the clipped entries it predicted below them
ISOTROPIC_RATIO = 1.25  # alpha_x / alpha_y below this: the tangent is not constrained by the lobe
# a lobe solved less anisotropic than this is solved again isotropic, and keeps its anisotropy only
# where the trace pays for it (``_prefer_isotropic``)
ANISOTROPY_TEST = 4.0
# the tint pull is relative to the lobe's mean rho_s, floored here: below it the pull holds the channels' absolute
# spread. At 0.05 it was so stiff near rho_s 0, where a lobe's solve starts, that LM stalled and dropped
# 2 of 48 synthetic lobes (test_anisotropic_lobe_recovered_from_a_perturbed_start); at 0.5 none
TINT_FLOOR = 0.5
ISOTROPIC_TIE = 1e4  # weight of the pull of log alpha_x to log alpha_y that holds a lobe isotropic (sigma 0.01)
# rounds of that isotropic solve: it starts at the solved lobe (3 rounds moved the gallery cells'
# |log alpha| by <= 0.04 more, and cost 3x; the vase's refine stage +31% with them)
ISOTROPIC_ROUNDS = 1
ANISOTROPY_PARAMS = 2  # what anisotropy adds to an isotropic lobe: the alpha ratio and the tangent turn
# a start lobe's alphas within this ratio: turned 90 deg it is the same lobe (the multi-start skips
# that start); 1.25 cost the Cycles vase's dark brushed metal 7.9 -> 9.1 deg of tangent
ISOTROPIC_START = 1.001
TANGENT_TURNS = 4  # tangents an anisotropic material's lobe is tried at (material_costs): 45 deg apart
MIN_SPECULAR_SHARE = 0.05  # a lobe below this share of some entry's pixel was not observed
LOBE_PARAMS = 6  # what a texel's own lobe adds to its diffuse-only model: tangent turn, 2 alphas, RGB rho_s
LOBE_EVIDENCE = 4.0  # a lobe must lower the robust cost (half chi-square units) by at least this much, and
SELECT_WIDEN, SELECT_FLOOR = 3.0, 0.03  # emitters are chosen under alphas x3 (at least 0.03)


@dataclass(frozen=True)
class SensorNoise:
    """Per-entry noise of a linear pixel y: sigma^2 = (read_code / 255)^2 + (relative * y)^2 (an
    absolute floor for dark values — 8-bit quantisation, read noise — plus shot/renderer noise that
    grows with the signal); residuals beyond ``robust`` sigmas count less (Cauchy)."""

    read_code: float = 1.0
    relative: float = 0.03
    robust: float = 3.0

    def sigma(self, y: Tensor) -> Tensor:
        """sigma ``(...)`` of linear pixels ``y (...)``."""
        return torch.sqrt((self.read_code / 255.0) ** 2 + (self.relative * y) ** 2)


@dataclass(frozen=True)
class RefineSettings:
    """How hard the refinement works (``ntp bench refine`` measures the ladder)."""

    rounds: int = 3  # model re-linearisations: the emitter blocks reselected, the multi-start the first
    iterations: int = 3  # LM iterations per round
    starts: bool = True  # multi-start in the first round: tangent turned 90 deg, a 4x sharper lobe
    noise: SensorNoise = field(default_factory=SensorNoise)
    log_alpha_prior_sigma: float = 3.0  # a weak pull to the start's alphas (natural log units)
    # a weak pull to the start's normal, or the mesh's (``normal_prior_at_mesh``): a lobe seen in few
    # views cannot tip it far
    normal_prior_deg: float = 3.0
    # the pull centres on the mesh's normal, not the start's (``calibrated`` decides per scan)
    normal_prior_at_mesh: bool = False
    # a pull of rho_s's channels to their mean, sigma relative to it: a lobe is grey unless its photos say
    # otherwise. A white highlight on a red diffuse clips first in red, which then bounds red's rho_s
    # only from below: the dome's white lacquer came out 4.7 / 1.6 / 1.6 on half its texels (0.15 held
    # it greyer but cost three Cycles |log alpha| cells; docs/history/accuracy.md, "A lobe is grey...")
    rho_s_tint_sigma: float = 0.3
    materials: bool = True  # basis materials for texels whose own trace does not show their lobe (refine.materials)
    # the neighbours' albedo each entry's pixel may blend in, as noise on its diffuse light (refine.footprint)
    albedo_blend: bool = True
    # the albedos near edges solved jointly from the entries' pixel samples (refine.albedo_map; needs the texels, so
    # ``refine.passes.refine_fit`` does it)
    albedo_map: bool = True
    # each normal fused with its neighbours' as far as the normal field is smooth (refine.normal_field; needs the
    # texels, so ``refine.passes.refine_fit`` does it)
    normal_field: bool = True
