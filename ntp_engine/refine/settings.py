"""The refinement's settings: ``RefineSettings`` (how hard one run works, with the camera's noise
model ``SensorNoise``) and ``RefineTuning`` (the stage's tuned constants, one section per part of
the refinement), every value declared with its provenance (``io.tuned``; the table of them all is
``docs/tuning.md``, generated from here).

The values every measurement so far was made on are the gallery's five objects at 40 photos: the
tuning set. A value of kind *unmeasured* is a modelling choice that no measurement backs yet.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch
from torch import Tensor

from ..io.tuned import budget, derived, measured, unmeasured
from ..scanner.camera import VALID_CODE

# facts of the model, not tunable
CENSOR_CODE = VALID_CODE[1]  # above this an 8-bit code may be (or border) a clipped pixel: a lower bound
ANISOTROPY_PARAMS = 2  # what anisotropy adds to an isotropic lobe: the alpha ratio and the tangent turn
LOBE_PARAMS = 6  # what a texel's own lobe adds to its diffuse-only model: tangent turn, 2 alphas, RGB rho_s

GALLERY = "the gallery (5 objects, 40 photos, true poses): ntp bench gallery --poses true --refine"
ENGINE_GALLERY = "the gallery's engine scans (40 photos, true poses): ntp bench gallery --scanners engine --refine"
CYCLES_GALLERY = "the gallery's Cycles scans (40 photos, true poses): ntp bench gallery --scanners cycles --refine"


@dataclass(frozen=True)
class ModelTuning:
    """The forward model (``refine.model``): which emitters it sums exactly, the noise it adds."""

    expanded_blocks: int = unmeasured(
        4, "emitter blocks per entry summed sample by sample (the rest as coarse emitters): the blocks under the lobe"
    )
    select_widen: float = unmeasured(3.0, "emitters are chosen under the round's alphas times this ...")
    select_floor: float = unmeasured(0.03, "... and at least this alpha: a lobe sharpens between rounds")
    bounce_noise: float = measured(
        0.6,
        "the light bounced onto an entry (support, object) as the model sums it is right to ~30% per entry (the "
        "box's Cycles scan at the truth: rms 0.19-0.34 of it): noise of this many times the pixel's bounced "
        "share. 0.3 / 0.6 / 1.0: 0.6 the normals' best, 1.0 lost the box's rough metal's lobe",
        on="the Cycles box and knot (docs/refinement.md): " + CYCLES_GALLERY,
    )
    noise_scale: tuple[float, float] = measured(
        (1.0, 10.0),
        "bounds of the noise model's calibration factor (``policy.calibrated``): it inflates the model, never "
        "tightens it — tighter than 1 let the data tip normals against the priors",
        on=GALLERY + " (docs/refinement.md)",
    )
    min_specular_share: float = unmeasured(0.05, "a lobe below this share of every entry's pixel was not observed")


@dataclass(frozen=True)
class SolverTuning:
    """The per-texel Levenberg-Marquardt solve (``refine.solver``, ``refine.priors``)."""

    max_tries: int = budget(3, "damping increases per LM iteration before the texel waits for the next iteration")
    converged: float = budget(1e-4, "a texel whose LM step lowers its cost by less than this (relative) is done")
    sharp_start: float = unmeasured(0.25, "the multi-start's sharper lobe: the start's alphas times this")
    isotropic_start: float = measured(
        1.001,
        "a start lobe's alphas within this ratio: turned 90 deg it is the same lobe (the multi-start skips that "
        "start); 1.25 cost the Cycles vase's dark brushed metal 7.9 -> 9.1 deg of tangent",
        on="the Cycles vase: " + CYCLES_GALLERY,
    )
    albedo_iterations: int = budget(3, "reweighted least squares of the albedos under the robust cost (lobe_costs)")
    clipped_rounds: int = budget(3, "solves of the albedo start, each adding the clipped entries it predicted")
    tint_floor: float = measured(
        0.5,
        "the tint pull is relative to the lobe's mean rho_s, floored here. At 0.05 it was so stiff near rho_s 0, "
        "where a lobe's solve starts, that LM stalled and dropped 2 of 48 synthetic lobes; at 0.5 none",
        on="48 synthetic lobes: tests/refine/test_policy.py::test_anisotropic_lobe_recovered_from_a_perturbed_start",
    )
    isotropic_tie: float = derived(1e4, "weight 1 / sigma^2 of the pull of log alpha_x to log alpha_y: sigma 0.01")


@dataclass(frozen=True)
class PolicyTuning:
    """Which model a texel keeps (``refine.policy``): a lobe, anisotropy, where the normal's pull centres."""

    lobe_evidence: float = unmeasured(
        4.0,
        "a lobe must lower the robust cost (half chi-square units) by at least this, or by BIC's penalty for "
        "LOBE_PARAMS (0.5 x 6 x ln n, which equals it at n ~ 4 entries) where that is larger",
    )
    isotropic_ratio: float = unmeasured(
        1.25, "alpha_x / alpha_y below this: the tangent is not constrained by the lobe"
    )
    anisotropy_test: float = unmeasured(
        4.0,
        "a lobe solved less anisotropic than this is solved again isotropic, and keeps its anisotropy only where "
        "the trace pays for it (``_prefer_isotropic``)",
    )
    isotropic_rounds: int = measured(
        1,
        "rounds of that isotropic solve, from the solved lobe: 3 rounds moved the gallery cells' |log alpha| by "
        "<= 0.04 more and cost 3x (the vase's refine stage +31%)",
        on=GALLERY,
    )
    at_bound: float = derived(
        1e-4,
        "a lobe's log alpha or rho_s within this of its range's bound is on it (flag AT_BOUND): the solver "
        "projects onto the box exactly, and its float32 copy of a bound rounds by ~1e-7",
    )
    tangent_turns: int = budget(4, "tangents an anisotropic material's lobe is tried at (material_costs): 45 deg apart")
    normal_fixed_deg: float = unmeasured(
        1.0, "a texel whose normal's 1-sigma is below this (deg) has it from its photos, not the prior (calibrated)"
    )
    normal_fixed_texels: int = unmeasured(16, "... and this many such texels decide where the normal's pull centres")


@dataclass(frozen=True)
class InputTuning:
    """What the refinement reads per texel and how it batches (``refine.inputs``, ``refine.passes``)."""

    refine_views: int = measured(
        24,
        "entries per texel the refinement reads (spread evenly over the trace); 16 instead: vase mirror lacquer "
        "|log alpha| 1.79 -> 2.47, dome gold tangent 1.03 -> 1.44 deg, |log rho_s| median 1.37 -> 1.56",
        on='docs/refinement.md, "Tried the same night": ntp bench refine --scanners engine (gallery, 40 photos)',
    )
    min_clear_entries: int = derived(
        1,
        "a texel with this many clear entries (neither shadowed by its mesh nor grazing) refines on those alone; "
        "with none it reads its marginal ones too: any clear entry is better evidence than a marginal one",
    )
    blend_entries: int = budget(1 << 18, "entries per block of with_albedo_blend (its float64 temporaries ~100 MB)")
    refine_batch: int = budget(
        1024,
        "texels per refinement batch: (batch, views, emitters) tensors ~200 MB; each batch's torch and Python "
        "overhead is paid per call, so larger batches refine faster until the arrays leave the caches (the knot, "
        "360 photos, 128^2: 512 texels 20.5-21.0 s, 1024 18.2-19.3 s, 2048 18.8 s at 1.5 GB peak, 128 27.6-30.2 s)",
    )
    calibration_texels: int = budget(
        512, "texels refined first to calibrate the noise and the normal's pull (policy.calibrated): one batch"
    )
    edge_rounds: int = measured(
        2,
        "rounds of the albedo-edge pass (from the first pass's answers); 1 lost the engine box's mirror lacquer "
        "lobe (|log alpha| 0.002 -> 1.29)",
        on='the engine box (docs/refinement.md, "Speed"): ' + ENGINE_GALLERY,
    )


@dataclass(frozen=True)
class MaterialTuning:
    """Basis materials (``refine.materials``, ``refine.material_pass``): their clusters, the mixture that
    assigns texels to them, the pooled lobe widths and the tangents a material's texels share."""

    max_materials: int = unmeasured(6, "k-means clusters at most")
    restarts: int = derived(
        16, "k-means runs per k, the tightest kept: one run's local optimum flips with rounding-level changes"
    )
    separation: float = derived(2.0, "feature units between the centres of two materials (one unit each side)")
    min_members: int = unmeasured(16, "texels a material needs ...")
    min_share: float = unmeasured(0.02, "... and this share of its kind's texels")
    colour_scale: float = unmeasured(0.25, "feature scale of log rho_d: one unit is a difference worth a material")
    log_alpha_scale: float = unmeasured(0.5, "feature scale of log alpha")
    log_rho_s_scale: float = unmeasured(0.5, "feature scale of log rho_s")
    colour_floor: float = unmeasured(0.02, "added to rho_d before logs: dark albedos differ by their noise, not ratio")
    min_colour_sigma: float = unmeasured(
        0.1, "a material's colour spread (log rho_d) at least: its members are a sample"
    )
    min_log_alpha_sigma: float = unmeasured(0.25, "its log alpha spread at least: the prior lets a texel's data speak")
    min_rho_s_sigma: float = unmeasured(0.25, "its rho_s spread at least (relative)")
    matte_share: float = derived(
        0.5, "the broad matte class's share before the object's is estimated (EM's start): neither class favoured"
    )
    matte_colour_sigma: float = derived(
        1.0, "the broad matte class's colour spread (log rho_d): any colour, e-fold either way"
    )
    matte_share_range: tuple[float, float] = unmeasured(
        (0.05, 0.95), "the estimated matte share stays inside: neither class is ruled out"
    )
    share_em_iterations: int = budget(500, "at most; a texel that cannot tell follows the prior, so EM creeps")
    share_em_tolerance: float = derived(1e-5, "EM stops when the share moves less: far below any share that matters")
    min_highlight: float = unmeasured(0.4, "a lobe that made this share of some pixel or more showed itself")
    dielectric_rho_s: float = derived(
        1.5, "rho_s of a dielectric's lobe at most (Schlick F0 <= 0.06, IOR <= ~1.65): such a lobe shows faintly"
    )
    candidate_margin: float = unmeasured(
        math.log(1000.0), "lobe materials this much less likely by colour than the best are not judged by the trace"
    )
    broad_alpha: float = unmeasured(
        0.2, "a lobe whose smaller alpha is this or more spreads its light like a diffuse term: judged for every texel"
    )
    field_units: float = measured(
        4.0,
        "what a width field pays per neighbourhood of local_members (half chi^2): at 2 the vase's lacquer and the "
        "knot's plastic took fields and lost |log alpha|; the dome's lacquer gained 44 and 52 on its clusters",
        on="docs/refinement.md (basis materials' width fields): " + ENGINE_GALLERY,
    )
    local_members: int = unmeasured(32, "a varying material's width at a point: the votes of this many members")
    label_neighbours: int = unmeasured(16, "nearest texels whose classes set a texel's local shares (local_shares)")
    share_pseudo: float = unmeasured(4.0, "the object's shares count as this many neighbours more")
    label_rounds: int = budget(2, "relabellings of the texels a trace judged, each by the last one's local shares")
    pool_clip: float = unmeasured(
        2.0, "a texel's vote on its material's lobe width: its cost above its best, clipped here (pooled_scale)"
    )
    pool_texels: int = measured(
        1024,
        "a material's lobe width from this many sampled members' traces together (with 256, five member samples "
        "of the knot's glossy plastic pooled to alpha 0.006-0.0205; with 1024, all of its members, 0.0119 each time)",
        on="the Cycles knot: " + CYCLES_GALLERY,
    )
    pool_scales: np.ndarray = budget(
        2.0 ** np.linspace(-2.0, 2.0, 9), "the pooled width scaled over this grid: 4x either way, in sqrt(2) steps"
    )
    width_params: float = derived(
        2.0,
        "a texel with its own lobe takes its material's width where that costs its trace at most this more than "
        "its own: AIC's 1 per parameter for the 2 alphas it would add (half chi-square units)",
    )
    max_source_std: float = unmeasured(
        np.radians(20.0), "a tangent known worse than this tells its neighbours nothing (_fuse_tangents)"
    )
    taken_tangent_std: float = unmeasured(
        np.radians(20.0), "a taken lobe's tangent: its trace's best turn, to about this"
    )
    min_source_share: float = unmeasured(
        0.02, "a material's texels that must have fixed their own tangents for the others to take theirs"
    )
    turn_objection: float = unmeasured(
        2.0, "a taken lobe's photos object to its neighbours' tangent at this much more cost (half chi^2)"
    )
    min_turn: float = budget(np.radians(0.5), "a turn below this is not worth asking the photos about")


@dataclass(frozen=True)
class FootprintTuning:
    """What one entry's pixel spans on the surface (``refine.footprint``)."""

    blend_noise: float = unmeasured(0.05, "albedo differences in the estimate below this are its noise, not an edge")
    spread_max: float = derived(
        0.05,
        "slope variance at most (~13 deg std): a grazing entry's pixel spans a long strip, which the second-order "
        "picture does not describe",
    )
    negligible: float = derived(1e-12, "slope variance of a 1e-6 rad spread: none")
    spread_widening: float = measured(
        0.5,
        "alpha^2 grows by this times the slope variance. 2 is a Gaussian spread's exact widening of a Beckmann "
        "lobe, but four point samples are not a Gaussian spread: 2 over-corrected (the box's brushed sides took a "
        "sharp isotropic cluster), 1 still did on the knot (|log alpha| 0.12 -> 0.39, relit SSIM -0.005); 0.5 kept "
        "every |log alpha| cell but three (each <= 0.03) and every relit SSIM within 0.002",
        on="docs/history/accuracy.md: " + ENGINE_GALLERY,
    )


@dataclass(frozen=True)
class SupportTuning:
    """The light bounced from the support and the object (``refine.support_light``)."""

    specular_samples: int = measured(
        32,
        "per entry, from the round's lobe (widened); 16: Cycles box rough metal |log a| 1.02 (32: 0.26)",
        on="the Cycles box: " + CYCLES_GALLERY,
    )
    diffuse_samples: int = measured(
        32,
        "per entry, cosine-distributed about the normal (16: -25% on a face seen edge-on)",
        on="the Cycles box: " + CYCLES_GALLERY,
    )
    sample_widen: float = unmeasured(1.5, "the sampled lobe: the round's alphas times this ...")
    sample_floor: float = unmeasured(0.02, "... and at least this alpha")
    max_reach: float = unmeasured(1.0, "m: support points farther from the texel carry no light")
    ray_offset: float = derived(1e-4, "m: rays start this far off the surfaces they leave (float32 at metres: 1e-7)")
    cell: float = unmeasured(0.004, "m: the support's albedo map's cells")
    reach_radii: float = unmeasured(3.0, "the map spans this many object radii around the object's footprint")
    code_range: tuple[float, float] = derived(
        (2.0, 250.0), "support pixels read with every channel's 8-bit code inside (not black, not clipped)"
    )


@dataclass(frozen=True)
class AlbedoMapTuning:
    """The albedos near edges solved jointly from the entries' pixel samples (``refine.albedo_map``)."""

    prior_weight: float = measured(
        0.2,
        "the pull to the texel's own answer, per median texel's data weight: 0.05 / 0.2 / 0.5 gave the demo rho_d "
        "RMSE 0.0165 / 0.0173 / 0.0182 (0.0199 without), the Cycles gallery's cells a net loss / even / a small gain",
        on="the demo (ntp demo) and " + CYCLES_GALLERY,
    )
    min_blend: float = measured(
        0.02,
        "texels some entry of which may blend this much of a neighbour's albedo are solved: 25% fewer of the demo's "
        "texels than any blend, 2.6 of its 10 s, the same rho_d RMSE on the demo and within 0.0006 on the gallery",
        on="the demo (ntp demo) and " + ENGINE_GALLERY,
    )
    robust: float = unmeasured(2.0, "Cauchy scale of the residuals, in sensor sigmas")
    rounds: int = budget(3, "a least-squares solve, then reweighted solves")
    cg_tolerance: float = derived(1e-6, "relative residual of the normal equations: below float32's 1e-7 x size")


@dataclass(frozen=True)
class FieldTuning:
    """Normals and tangents fused with their neighbours' (``refine.normal_field``, ``refine.tangent_field``)
    and the semivariogram that says how smooth a field is (``refine.surface_fields``)."""

    normal_neighbours: int = unmeasured(24, "nearest texels of the group a normal is fused with")
    normal_range: float = unmeasured(
        1.0, "a neighbour whose offset differs by s sigmas (both errors) weighs exp(-s^2 / 2 range^2) more or less"
    )
    normal_gate: float = derived(3.0, "sigmas of disagreement beyond which a texel keeps its own normal (99.7%)")
    normal_min_std: float = derived(math.radians(0.1), "a floor under the LM's normal std (its weights stay finite)")
    tangent_neighbours: int = unmeasured(16, "nearest sources averaged per texel")
    tangent_reach: float = unmeasured(
        10.0, "a source's weight falls as a Gaussian of this many texel spacings (median nearest-texel distance)"
    )
    tangent_doubt: float = unmeasured(
        0.25, "added to the sources' weights (a source in the texel's plane weighs 1): one source is not many"
    )
    tangent_fuse_neighbours: int = unmeasured(24, "fused_turns: a texel's own tangent with its nearest neighbours'")
    tangent_gate: float = derived(
        3.0, "sigmas of disagreement beyond which a tangent and its neighbours' are not fused"
    )
    tangent_min_std: float = measured(
        math.radians(0.5),
        "no trace fixes a tangent better: a floor under the LM's std (0.3 deg ones erred 0.4)",
        on=GALLERY,
    )
    variation_bins: int = derived(12, "the semivariogram's distances: 1, 2, 4, ... 2048 texel spacings (a 2048^2 map)")
    variation_pairs: int = budget(8, "pairs per texel: its nearest others, and as many random ones")
    min_pairs: int = unmeasured(16, "pairs a distance bin needs (else it takes the nearer bin's value)")


@dataclass(frozen=True)
class RefineTuning:
    """The refinement's tuned constants, one section per part (fixed per release; ``docs/tuning.md``)."""

    model: ModelTuning = field(default_factory=ModelTuning)
    solver: SolverTuning = field(default_factory=SolverTuning)
    policy: PolicyTuning = field(default_factory=PolicyTuning)
    inputs: InputTuning = field(default_factory=InputTuning)
    materials: MaterialTuning = field(default_factory=MaterialTuning)
    footprint: FootprintTuning = field(default_factory=FootprintTuning)
    support: SupportTuning = field(default_factory=SupportTuning)
    albedo_map: AlbedoMapTuning = field(default_factory=AlbedoMapTuning)
    fields: FieldTuning = field(default_factory=FieldTuning)


TUNING = RefineTuning()


@dataclass(frozen=True)
class SensorNoise:
    """Per-entry noise of a linear pixel y: sigma^2 = (read_code / 255)^2 + (relative * y)^2 (an
    absolute floor for dark values — 8-bit quantisation, read noise — plus shot/renderer noise that
    grows with the signal); residuals beyond ``robust`` sigmas count less (Cauchy)."""

    read_code: float = derived(1.0, "one 8-bit code: quantisation (0.29 code rms) and read noise together")
    relative: float = unmeasured(
        0.03, "shot and renderer noise, relative to the pixel (policy.calibrated scales it up)"
    )
    robust: float = derived(3.0, "residuals beyond 3 sigma (0.3% of Gaussian noise) count less")

    def sigma(self, y: Tensor) -> Tensor:
        """sigma ``(...)`` of linear pixels ``y (...)``."""
        return torch.sqrt((self.read_code / 255.0) ** 2 + (self.relative * y) ** 2)


@dataclass(frozen=True)
class RefineSettings:
    """How hard the refinement works (``ntp bench refine`` measures the ladder)."""

    rounds: int = budget(3, "model re-linearisations: the emitter blocks reselected, the multi-start the first")
    iterations: int = budget(3, "LM iterations per round")
    starts: bool = budget(True, "multi-start in the first round: tangent turned 90 deg, a 4x sharper lobe")
    noise: SensorNoise = field(default_factory=SensorNoise)
    log_alpha_prior_sigma: float = derived(3.0, "a weak pull to the start's alphas: e^3 = 20x either way at 1 sigma")
    normal_prior_deg: float = unmeasured(
        3.0,
        "a weak pull to the start's normal, or the mesh's (normal_prior_at_mesh): a lobe seen in few views cannot "
        "tip it far",
    )
    normal_prior_at_mesh: bool = derived(
        False, "the pull centres on the mesh's normal, not the start's (policy.calibrated decides per scan)"
    )
    rho_s_tint_sigma: float = measured(
        0.3,
        "a pull of rho_s's channels to their mean, sigma relative to it: a lobe is grey unless its photos say "
        "otherwise. A white highlight on a red diffuse clips first in red: the dome's white lacquer came out "
        "4.7 / 1.6 / 1.6 on half its texels without; 0.15 held it greyer but cost three Cycles |log alpha| cells",
        on='docs/history/accuracy.md, "A lobe is grey...": ' + GALLERY,
    )
    materials: bool = measured(
        True,
        "basis materials for texels whose own trace does not show their lobe (refine.materials)",
        on='docs/history/accuracy.md, "With basis materials": ' + GALLERY,
    )
    albedo_blend: bool = measured(
        True,
        "the neighbours' albedo each entry's pixel may blend in, as noise on its diffuse light (refine.footprint)",
        on='docs/history/accuracy.md, "Albedo edges: what a pixel blends": ' + GALLERY,
    )
    edge_pass: bool = budget(
        True,
        "with albedo_blend: the texels whose pixels may blend a neighbour's albedo refined again with that blend "
        "as noise (TUNING.inputs.edge_rounds); without, the blend only picks the albedo map's texels",
    )
    albedo_map: bool = measured(
        True,
        "the albedos near edges solved jointly from the entries' pixel samples (refine.albedo_map; needs the "
        "texels, so refine.passes.refine_fit does it)",
        on='docs/history/accuracy.md, "The albedo map near edges, solved jointly": ' + GALLERY,
    )
    normal_field: bool = measured(
        True,
        "each normal fused with its neighbours' as far as the normal field is smooth (refine.normal_field; "
        "refine.passes.refine_fit does it)",
        on='docs/history/accuracy.md, "The normal field, fused": ' + GALLERY,
    )
