"""Analysis-by-synthesis refinement (issue 17): per texel, the anisotropic GGX parameters that best
explain the trace's own pixels through Eq. 1 and the camera model, starting from the network's fit.

Model of one entry j (a view of the texel) and camera channel c, in linear pixel units (1 = code 255):
    y_jc = exposure * sum_k P[k, c] w_jk (wi_jk . n)+ (rho_d,c / pi + rho_s,c lobe(wi_jk, wo_j; t, ax, ay))
over the emitter samples k (``measurement``'s factorised Eq. 1, falloff w = w_q Psi / r^2). The
camera is the sensor model ``SensorNoise``: an entry channel whose 8-bit code is above ``CENSOR_CODE``
may be clipped (or bilinearly mixed with a clipped pixel) and only says "at least this bright" (censored);
dark entries keep their information with an absolute noise floor instead of being dropped. On a
curved surface an entry's pixel sample spans several normals and sees the lobe widened, and near an
albedo edge it may blend the neighbours' albedo, which counts as noise on its diffuse light
(``fit.footprint``).

Convention: the parameters live in the texel's geometric (lumitexel) frame (z = n^, x = t^), like
``fit_traces``'s results: ``frame (N, 3, 3)`` rows (t, b, n); ``log_alpha (N, 2)`` natural logs of
(alpha_x, alpha_y); ``rho_d, rho_s (N, 3)``. Entries are the trace layout (``learn.ragged``) with
pixels as captured (not scaled to a model's exposure).

The solver: batched Levenberg-Marquardt over texels with 11 unknowns each (a frame rotation omega in
the shading frame — omega_z turns the tangent about n, omega_x,y tilt n — two log alphas, RGB rho_d
and rho_s), Cauchy-robust residuals, box bounds by projection with an active set, analytic
Jacobians (rho enters linearly; the lobe's derivatives are closed form, summed over the emitters in one
compiled loop: ``pixel_bases``).
Speed: the diffuse basis is linear in n (precomputed per entry), and the specular sum runs over the
emitter blocks (``emitter_blocks``) brightest under a broadened lobe sample by sample and over the
other blocks as one coarse emitter each. Design and measurements: docs/refinement.md.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor

from ..physics.brdf import ALPHA_MAX, ALPHA_MIN, RHO_D_MAX, RHO_S_MAX
from ..physics.frame import (
    frame_from_normal_tangent,
    rotation_from_vector,
    turned_about_normal,
)
from ..scanner.camera import VALID_CODE
from ..scanner.scanner import Scanner
from .albedo import bounded_ls2
from .emitter_blocks import EmitterBlocks, emitter_blocks, shadow_groups
from .footprint import Footprint, widening
from .gauss_newton import N_PARAMS, data_cost, normal_equations
from .highlights import parked_positions
from .pixel_bases import (
    diffuse_basis_and_margin,
    diffuse_basis_near,
    emitter_directions,
    lobe_weights,
    pack_emitters,
    selected_emitters,
    specular_basis,
    specular_basis_and_derivatives,
)
from .support_light import (
    Sources,
    SupportEmitters,
    SupportView,
    support_diffuse_basis,
    support_specular_emitters,
)

VERSION = 50  # of the method: part of the pipeline's cache key (bump when results change for the same settings)
CENSOR_CODE = VALID_CODE[1]  # above this an 8-bit code may be (or border) a clipped pixel: a lower bound
EXPANDED_BLOCKS = 4  # emitter blocks per entry summed sample by sample (the rest as coarse emitters)
SELECT_WIDEN, SELECT_FLOOR = 3.0, 0.03  # emitters are chosen under alphas x3 (at least 0.03)
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
# a texel whose normal's 1-sigma is below this (deg) has it from its photos, not the prior
# (``calibrated``: where the normal's pull centres), and this many such texels decide
NORMAL_FIXED_DEG, NORMAL_FIXED_TEXELS = 1.0, 16
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
# by BIC's 0.5 LOBE_PARAMS ln(residuals): a short trace fits any 6 more parameters to its noise

P_OMEGA, P_LOGA, P_RHO_D, P_RHO_S = slice(0, 3), slice(3, 5), slice(5, 8), slice(8, 11)
FLAG_SPECULAR_UNCONSTRAINED, FLAG_TANGENT_UNCONSTRAINED, FLAG_FROM_MATERIAL = 16, 32, 64


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
    # it greyer but cost three Cycles |log alpha| cells; docs/accuracy.md, "A lobe is grey...")
    rho_s_tint_sigma: float = 0.3
    materials: bool = True  # basis materials for texels whose own trace does not show their lobe (fit.materials)
    # the neighbours' albedo each entry's pixel may blend in, as noise on its diffuse light (fit.footprint)
    albedo_blend: bool = True
    # the albedos near edges solved jointly from the entries' pixel samples (fit.albedo_map; needs the texels, so
    # ``pipeline.fit_traces.refine_fit`` does it)
    albedo_map: bool = True
    # each normal fused with its neighbours' as far as the normal field is smooth (fit.normal_field; needs the
    # texels, so ``pipeline.fit_traces.refine_fit`` does it)
    normal_field: bool = True


class Start(NamedTuple):
    """Where N texels' refinement starts (geometric frame): the network's fit, or any guess."""

    normal: Tensor  # (N, 3)
    tangent: Tensor  # (N, 3)
    alpha: Tensor  # (N, 2) alpha_x, alpha_y
    rho_d: Tensor  # (N, 3)
    rho_s: Tensor  # (N, 3)

    @classmethod
    def from_fit(cls, fit: dict[str, np.ndarray], idx: np.ndarray) -> Start:
        """The texels ``idx`` of a ``pipeline.fit_traces`` result (float32)."""

        def col(key: str) -> Tensor:
            return torch.as_tensor(fit[key][idx], dtype=torch.float32)

        return cls(col("n_loc"), col("t_loc"), col("alpha"), col("rho_d"), col("rho_s"))


@dataclass
class Refined:
    """Refined parameters of N texels (geometric frame) and how well their traces constrain them."""

    frame: Tensor  # (N, 3, 3) rows t, b, n
    log_alpha: Tensor  # (N, 2) alpha_x >= alpha_y
    rho_d: Tensor  # (N, 3)
    rho_s: Tensor  # (N, 3)
    flags: Tensor  # (N,) FLAG_SPECULAR_UNCONSTRAINED | FLAG_TANGENT_UNCONSTRAINED
    std: Tensor  # (N, 4) 1-sigma: normal (deg), tangent (deg), log alpha_x, log rho_s (mean channel)
    cost: Tensor  # (N,) objective at the answer (robust data cost plus the priors)
    highlight: Tensor  # (N,) the largest share of an entry's pixel the texel's kept lobe makes (0: none)


class LobePrior(NamedTuple):
    """N texels' basis-material lobes as priors (``refine_toward``): alphas ``(N, 2)``, rho_s ``(N, 3)``
    and their 1-sigma spreads, of log alpha ``(N,)`` and of rho_s ``(N,)`` (linear units)."""

    alpha: Tensor
    rho_s: Tensor
    log_alpha_sigma: Tensor
    rho_s_sigma: Tensor


# the trace's per-sample arrays: shared between a chunk and its subsets (``_Trace.rows``)
SAMPLE_ARRAYS = ("wo", "wi", "falloff", "wi_c", "falloff_c")


class _Trace:
    """One chunk of traces, ready for the model: every entry's directions to each emitter sample
    (and, with ``blocks``, to each block's coarse emitter) and falloff in the texel's geometric
    frame — none depends on the parameters (a shading frame only rotates them). Sample index K is
    padding: it emits nothing. Those per-sample arrays (``SAMPLE_ARRAYS``) are shared by a subset of
    the texels (``rows``), which reads its rows ``srow`` of them instead of copying them. ``shadow
    (N, V)``: the emitter groups the
    mesh hides from each entry (``learn.ragged``), whose falloff is 0. ``footprint``: what each
    entry's pixel sample spans (``fit.footprint``): the slope spread, which widens the lobe it sees,
    and the neighbours' albedo it may blend in, noise on its diffuse light."""

    def __init__(
        self,
        scanner: Scanner,
        entries: Tensor,
        mask: Tensor,
        noise: SensorNoise,
        blocks: EmitterBlocks | None,
        shadow: Tensor | None = None,
        support: SupportView | None = None,
        footprint: Footprint | None = None,
    ):
        N, V, _ = entries.shape
        self.N, self.V, self.blocks = N, V, blocks
        x = parked_positions(entries[..., 3:6], mask).reshape(-1, 3)
        frame = frame_from_normal_tangent(entries[..., 6:9].reshape(-1, 3), entries[..., 9:12].reshape(-1, 3))
        live = mask.reshape(-1)
        exposure = float(scanner.exposure(scanner.pattern))

        def directions(dev: Scanner, padding: bool) -> tuple[Tensor, Tensor, Tensor]:
            """wo (N, V, 3), and per emitter sample wi (N, V, 3, K) and falloff (N, V, K)."""
            wo, wi, falloff = emitter_directions(dev, x, frame, live, padding)
            K = falloff.shape[1]
            return wo.view(N, V, 3), wi.view(N, V, 3, K), falloff.view(N, V, K)

        # sample index K: padding (any direction, no light)
        self.wo, self.wi, self.falloff = directions(scanner, True)
        self.srow = torch.arange(N)  # each texel's row of the per-sample arrays
        Q = scanner.emitter_samples(x.dtype)[1].shape[1]
        p_eff = torch.as_tensor(scanner.effective_pattern(), dtype=x.dtype)
        drive = exposure * p_eff.repeat_interleave(Q, 0)  # per sample (the falloff holds w_q)
        self.drive = torch.cat([drive, torch.zeros(1, 3, dtype=x.dtype)])  # (K + 1, 3)
        if blocks is not None:
            _, self.wi_c, self.falloff_c = directions(blocks.coarse, False)
            self.drive_c = exposure * blocks.coarse_drive.to(x.dtype)
        if shadow is not None and bool((shadow != 0).any()):
            groups = shadow_groups(scanner)
            hidden = groups.hidden(shadow)  # (N, V, P)
            lit = ~hidden.gather(-1, groups.group.expand(N, V, -1))  # per emitter sample (N, V, K)
            lit = torch.cat([lit, torch.ones(N, V, 1, dtype=torch.bool)], -1).to(x.dtype)  # padding
            self.falloff = self.falloff * lit
            if blocks is not None:  # a block's coarse emitter carries the drive of its visible groups
                self.falloff_c = self.falloff_c * groups.block_visibility(shadow, x.dtype)
        # the slope spread each entry's pixel sample covers (``fit.footprint``): None on a flat or
        # unknown surface
        spread = None if footprint is None else footprint.spread
        self.spread = None if spread is None or not bool((spread != 0).any()) else spread.to(x.dtype)
        y = entries[..., :3]
        self.y = torch.where(mask[..., None], y, torch.zeros_like(y))
        code = 255.0 * self.y
        # per channel: the camera clips each channel on its own (``scanner.camera.encode``), so a
        # pixel whose red clips still measures its green and blue exactly
        self.censored = (code > CENSOR_CODE) & mask[..., None]
        self.mask = mask[..., None].expand(N, V, 3)
        self.inv_sigma = torch.where(self.mask, 1.0 / noise.sigma(self.y), torch.zeros_like(self.y))
        self.support = None if support is None else support.scene
        if support is not None:  # the support's light (``fit.support_light``): what each round needs
            self.scanner, self.sources = scanner, Sources.of(scanner, blocks)
            self.live, self.x_cam, self.frame_cam = mask, x.view(N, V, 3), frame.view(N, V, 3, 3)
            self.position, self.frame_world = support.position.double(), support.frame_world.double()
            self.exposed = support.exposed
            self.support_diffuse = support_diffuse_basis(
                support, scanner, self.sources, self.x_cam, self.frame_cam, self.live
            ).to(self.wi.dtype)
        # the diffuse basis at the geometric normal (+z here) and how far a normal may move before an
        # emitter crosses an entry's horizon: a round's basis sums again only the entries that crossed
        self.diffuse_z, self.horizon_margin = diffuse_basis_and_margin(self._up(), self.wi, self.falloff, self.drive)
        if footprint is not None and footprint.albedo_blend is not None:
            self._blend_noise(footprint.albedo_blend)
        if support is not None:
            self._bounce_noise()

    def _up(self) -> Tensor:
        """The geometric normal ``(N, 3)``: +z in the texel's frame."""
        up = torch.zeros(self.N, 3, dtype=self.wi.dtype)
        up[:, 2] = 1
        return up

    def diffuse_basis(self, normal: Tensor) -> Tensor:
        """The diffuse basis ``(N, V, 3, 3)`` (``pixel_bases``) for the normals ``normal (N, 3)``, the
        support's light included."""
        known = (self.diffuse_z, self._up(), self.horizon_margin)
        d = diffuse_basis_near(normal, self.wi, self.falloff, self.drive, *known, rows=self.srow)
        return d if self.support is None else d + self.support_diffuse

    def _blend_noise(self, albedo_blend: Tensor) -> None:
        """The albedo each entry's pixel may blend in of the neighbours' (``albedo_blend (N, V, 3)``,
        ``fit.footprint``) as noise on its diffuse light, added in quadrature to the sensor's: its
        diffuse basis at the geometric normal (a refined normal a degree or two off moves it by its
        cosine) times the blend. The censoring stays the pixel's as captured."""
        basis = self.diffuse_z[..., 2]  # (N, V, 3 channels)
        if self.support is not None:
            basis = basis + self.support_diffuse[..., 2]
        self._add_noise(albedo_blend.to(self.y.dtype) * basis.to(self.y.dtype))

    def _bounce_noise(self) -> None:
        """The bounced light's uncertainty (``BOUNCE_NOISE``) as noise on each entry, added in
        quadrature to the sensor's: the pixel times its share of bounced light — of the diffuse
        light at the geometric normal, per channel; fixed by the data and the geometry alone, so
        every start and round of a texel is judged on the same scale. Censoring stays the pixel's."""
        direct, bounced = self.diffuse_z[..., 2], self.support_diffuse[..., 2]  # (N, V, 3 channels)
        share = bounced / (direct + bounced).clamp_min(1e-30)
        self._add_noise(BOUNCE_NOISE * share.to(self.y.dtype) * self.y)

    def _add_noise(self, extra: Tensor) -> None:
        """``extra (N, V, 3)`` added in quadrature to each entry's sigma."""
        sigma = 1.0 / torch.where(self.mask, self.inv_sigma, torch.ones_like(self.inv_sigma))
        self.inv_sigma = torch.where(self.mask, torch.rsqrt(sigma * sigma + extra * extra), self.inv_sigma)

    def support_specular(self, frame0: Tensor, alpha: Tensor, rho_s: Tensor | None) -> SupportEmitters | None:
        """The support's light as specular emitters for a round's ``frame0 (N, 3, 3)`` and lobe
        ``alpha (N, 2)`` (``rho_s (N, 3)``: its Fresnel bounded), or None without a support."""
        if self.support is None:
            return None
        view = SupportView(self.support, self.position, self.frame_world, self.exposed)
        wo = self.wo[self.srow]
        return support_specular_emitters(
            view, self.scanner, self.sources, self.x_cam, self.frame_cam, self.live, wo, frame0, alpha, rho_s
        )

    def light_rows(self, idx: Tensor) -> _Trace:
        """The texels ``idx`` with only what the residuals need (no per-emitter arrays)."""
        out = object.__new__(_Trace)
        for k in ("y", "inv_sigma", "censored", "mask"):
            setattr(out, k, getattr(self, k)[idx])
        out.N, out.V, out.blocks = len(idx), self.V, self.blocks
        return out

    def rows(self, idx: Tensor) -> _Trace:
        """The same chunk for the texels ``idx`` only: per-texel arrays copied, the per-sample ones
        shared (``srow``: the subset's rows of them)."""
        out = object.__new__(_Trace)
        for k, v in vars(self).items():
            per_texel = isinstance(v, Tensor) and k not in ("drive", "drive_c") and k not in SAMPLE_ARRAYS
            setattr(out, k, v[idx] if per_texel else v)
        out.N = len(idx)
        return out


class _Round:
    """The model of one round: frame F0 fixed; per entry, the emitter blocks brightest under a
    broadened lobe are summed sample by sample, the others as their coarse emitters."""

    def __init__(
        self,
        tr: _Trace,
        frame0: Tensor,
        log_alpha: Tensor,
        specular: bool,
        diffuse: Tensor | None = None,
        rho_s: Tensor | None = None,
    ):
        """``rho_s (N, 3)``: the lobe's at the round's start, for the bounded Fresnel of the light
        bounced onto the texel (``support_light.support_specular_emitters``); None: the BRDF's."""
        self.tr, self.specular, self.frame0 = tr, specular, frame0
        # diffuse basis per channel: linear in the shading normal (emitters above F0's horizon);
        # ``diffuse``: given by a round of the same normal
        self.diffuse = tr.diffuse_basis(frame0[:, 2]) if diffuse is None else diffuse  # (N, V, 3, 3), wi's dtype
        # the round's per-entry emitters are its own (N rows; the LM's subsets read their rows ``row``)
        self.wo, self.row = tr.wo[tr.srow], torch.arange(tr.N)
        self.widening: Tensor | None = None
        if not specular:
            return
        # what each entry's sample adds to the round's alpha_x^2, alpha_y^2 (``fit.footprint``)
        if tr.spread is not None:
            self.widening = widening(tr.spread, frame0)
        if tr.blocks is None:  # a small device: every sample exactly
            self.emitters = pack_emitters(tr.wi[tr.srow], tr.falloff[tr.srow], tr.drive)
        else:
            seen = log_alpha.exp()
            if self.widening is not None:  # the widest lobe any entry sees
                seen = torch.sqrt(seen**2 + self.widening.amax(1))
            wide = (SELECT_WIDEN * seen).clamp(SELECT_FLOOR, ALPHA_MAX)
            score = lobe_weights(frame0, tr.wi_c, tr.wo, tr.falloff_c, wide, tr.srow)  # (N, V, C)
            top = score.topk(EXPANDED_BLOCKS, -1, sorted=False).indices
            self.emitters = selected_emitters(
                top,
                tr.blocks.members,
                (tr.wi, tr.falloff, tr.drive),
                (tr.wi_c, tr.falloff_c, tr.drive_c),
                tr.srow,
            )
        # the support's light: more emitters, drawn for this round's lobe
        support = tr.support_specular(frame0, log_alpha.exp(), rho_s)
        if support is not None:
            packed = pack_emitters(support.wi.transpose(-1, -2), support.weight, support.drive)
            self.emitters = torch.cat([self.emitters, packed], 3)

    def rows(self, idx: Tensor) -> _Round:
        """The same round for the texels ``idx`` only (the LM drops texels that have converged); the
        per-entry emitters are not copied: the subset reads its rows ``row``."""
        out = object.__new__(_Round)
        vars(out).update(vars(self))
        out.tr, out.row = self.tr.light_rows(idx), self.row[idx]
        out.frame0, out.diffuse = self.frame0[idx], self.diffuse[idx]
        out.widening = None if self.widening is None else self.widening[idx]
        return out

    def rebase(self, omega: Tensor) -> None:
        """Fold the rotation ``omega (N, 3)`` into the round's frame (linearise about it next)."""
        self.frame0 = _fold(self.frame0, omega)

    def linearised(self, log_alpha: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """What the LM step's normal equations need at omega = 0 (``gauss_newton``): the diffuse
        basis in the shading frame ``(N, V, 3, 3)`` (its derivatives by omega follow from it), the
        specular basis and its derivatives ``(N, V, 5, 3)`` by (omega, log alpha) (analytic:
        ``pixel_bases.specular_basis_and_derivatives``; empty for a diffuse-only round)."""
        frame = self.frame0
        diffuse = torch.einsum("nij,nvcj->nvci", frame, self.diffuse)
        if not self.specular:  # no specular basis: empty arrays (``gauss_newton``'s convention)
            V = diffuse.shape[1]
            return diffuse, diffuse.new_zeros(0, V, 3), diffuse.new_zeros(0, V, 5, 3)
        alpha = log_alpha.exp()
        spec, ds = specular_basis_and_derivatives(frame, self.emitters, self.wo, alpha, self.row, self.widening)
        return diffuse, spec, ds

    def bases(self, omega: Tensor, log_alpha: Tensor) -> tuple[Tensor, Tensor]:
        """Unit-albedo diffuse and specular pixel bases ``(N, V, 3)`` for the rotation ``omega
        (N, 3)`` (shading frame at the round's start) and ``log_alpha (N, 2)``."""
        return self.bases_in(_fold(self.frame0, omega), log_alpha)

    def bases_in(self, frame: Tensor, log_alpha: Tensor) -> tuple[Tensor, Tensor]:
        """``bases`` in the shading frame ``frame (N, 3, 3)`` (the round's start turned)."""
        diffuse = (self.diffuse * frame[:, None, None, 2, :]).sum(-1)
        if not self.specular:
            return diffuse, torch.zeros_like(diffuse)
        alpha = log_alpha.exp()
        spec = specular_basis(frame, self.emitters, self.wo, alpha, self.row, self.widening)
        return diffuse, spec


_LO = torch.tensor([-math.inf] * 3 + [math.log(ALPHA_MIN)] * 2 + [0.0] * 6)
_HI = torch.tensor([math.inf] * 3 + [math.log(ALPHA_MAX)] * 2 + [RHO_D_MAX] * 3 + [RHO_S_MAX] * 3)


def _residuals(tr: _Trace, diffuse: Tensor, spec: Tensor, p: Tensor) -> tuple[Tensor, Tensor]:
    """Normalised residuals ``(N, V, 3)`` and which of them count (censored entries only when the
    prediction falls below the measured lower bound)."""
    pred = p[:, None, P_RHO_D] * diffuse + p[:, None, P_RHO_S] * spec
    r = (pred - tr.y) * tr.inv_sigma
    active = tr.mask & ~(tr.censored & (pred >= tr.y))
    return torch.where(active, r, torch.zeros_like(r)), active


def _cost(r: Tensor, c: float) -> Tensor:
    """Cauchy cost per texel from residuals ``(N, V, 3)``."""
    return (0.5 * c * c * torch.log1p((r / c) ** 2)).flatten(1).sum(1)


class _Prior(NamedTuple):
    """Gaussian pulls per texel: the normal toward ``n_prior (N, 3)`` (the start's or the mesh's,
    ``_normal_prior``; geometric frame, weight ``n_w = 1 / sigma^2`` in rad^-2), log alphas toward
    ``la0 (N, 2)`` (``la_w (N,)``) and rho_s toward ``rs0 (N, 3)`` (``rs_w (N,)``; 0 = none): the
    start's, or a basis material's. ``tie_w (N,)``: a pull of log alpha_x to log alpha_y
    (``ISOTROPIC_TIE``: an isotropic lobe; 0 = none). ``tint_w``: rho_s's channels to their mean
    (``RefineSettings.rho_s_tint_sigma^-2``, relative to the mean: ``_tint_scale``)."""

    n_prior: Tensor
    n_w: float
    la0: Tensor
    la_w: Tensor
    rs0: Tensor
    rs_w: Tensor
    tie_w: Tensor
    tint_w: float

    def rows(self, idx: Tensor) -> _Prior:
        return _Prior(
            self.n_prior[idx],
            self.n_w,
            self.la0[idx],
            self.la_w[idx],
            self.rs0[idx],
            self.rs_w[idx],
            self.tie_w[idx],
            self.tint_w,
        )

    def tied(self, isotropic: Tensor) -> _Prior:
        """The same pulls with the lobes of the texels ``isotropic (N,)`` (bool) held isotropic."""
        return self._replace(tie_w=torch.where(isotropic, ISOTROPIC_TIE, 0.0).to(self.la_w.dtype))

    @classmethod
    def weak(cls, frame: Tensor, p: Tensor, settings: RefineSettings) -> _Prior:
        """The weak pulls (``RefineSettings``) to the start ``frame``, ``p`` — the normal to the
        mesh's instead with ``settings.normal_prior_at_mesh`` —; none on rho_s."""
        N = p.shape[0]
        return cls(
            _normal_prior(frame, settings),
            math.radians(settings.normal_prior_deg) ** -2,
            p[:, P_LOGA].clone(),
            torch.full((N,), settings.log_alpha_prior_sigma**-2, dtype=p.dtype),
            torch.zeros(N, 3, dtype=p.dtype),
            torch.zeros(N, dtype=p.dtype),
            torch.zeros(N, dtype=p.dtype),
            settings.rho_s_tint_sigma**-2,
        )


def _tint_scale(rho_s: Tensor) -> Tensor:
    """1 / (mean channel^2 + TINT_FLOOR^2) ``(N,)`` of ``rho_s (N, 3)``: the tint pull is relative."""
    return 1.0 / (rho_s.mean(1) ** 2 + TINT_FLOOR**2)


def _prior(p: Tensor, prior: _Prior) -> Tensor:
    """The alpha and rho_s pulls' cost per texel at ``p (N, 11)``."""
    la = 0.5 * prior.la_w * ((p[:, P_LOGA] - prior.la0) ** 2).sum(1)
    la = la + 0.5 * prior.tie_w * (p[:, 3] - p[:, 4]) ** 2
    rs = p[:, P_RHO_S]
    tint = 0.5 * prior.tint_w * _tint_scale(rs) * ((rs - rs.mean(1, keepdim=True)) ** 2).sum(1)
    return la + tint + 0.5 * prior.rs_w * ((rs - prior.rs0) ** 2).sum(1)


def _normal_prior(frame: Tensor, settings: RefineSettings) -> Tensor:
    """Where the normal's weak pull centres ``(N, 3)`` (geometric frame): the normal of the start
    ``frame (N, 3, 3)``, or the mesh's (+z) with ``settings.normal_prior_at_mesh``."""
    if not settings.normal_prior_at_mesh:
        return frame[:, 2].clone()
    out = torch.zeros_like(frame[:, 2])
    out[:, 2] = 1
    return out


def _prior_normal_in(frame: Tensor, n_prior: Tensor) -> Tensor:
    """The prior's normal ``n_prior (N, 3)`` (geometric frame) in the shading frame ``frame (N, 3,
    3)`` (rows t, b, n; a round's start turned by ``_fold``) ``(N, 3)``."""
    return (frame @ n_prior[:, :, None])[..., 0]


def _cost_at(rnd: _Round, q: Tensor, prior: _Prior, settings: RefineSettings) -> Tensor:
    """The objective per texel at ``q (N, 11)``: robust data cost plus the priors."""
    frame = _fold(rnd.frame0, q[:, P_OMEGA])  # one rotation for the bases and the normal's pull
    d, s = rnd.bases_in(frame, q[:, P_LOGA])
    u = _prior_normal_in(frame, prior.n_prior)
    tilt = 0.5 * prior.n_w * (u[:, :2] ** 2).sum(1)
    tr = rnd.tr
    data = data_cost(d, s, q, tr.y, tr.inv_sigma, tr.mask, tr.censored, settings.noise.robust)
    return data + _prior(q, prior) + tilt


def _lm(
    rnd: _Round,
    p: Tensor,
    prior: _Prior,
    free: Tensor,
    iterations: int,
    settings: RefineSettings,
) -> tuple[Tensor, Tensor, Tensor]:
    """Up to ``iterations`` LM steps from ``p (N, 11)`` with the parameters ``free (N, 11)``; a
    texel whose step no longer lowers its cost by ``CONVERGED`` (relative) is done and drops out.
    Each accepted rotation is folded into ``rnd``'s frame (omega stays 0 between steps). Returns p,
    the cost per texel and the Gauss-Newton Hessian (float64) of its last linearisation."""
    N = p.shape[0]
    lam = torch.full((N,), 1e-3, dtype=torch.float64)
    H = torch.zeros(N, N_PARAMS, N_PARAMS, dtype=torch.float64)
    cost = _cost_at(rnd, p, prior, settings)
    p = p.clone()
    live = torch.ones(N, dtype=torch.bool)
    for _ in range(iterations):
        ids = live.nonzero().squeeze(1)
        if len(ids) == 0:
            break
        whole = len(ids) == N
        sub = rnd if whole else rnd.rows(ids)
        q, c_new, h, lam_new = _lm_step(sub, p[ids], cost[ids], lam[ids], prior.rows(ids), free[ids], settings)
        done = cost[ids] - c_new <= CONVERGED * cost[ids].abs()  # no progress left
        p[ids], cost[ids], H[ids], lam[ids] = q, c_new, h, lam_new
        if not whole:
            rnd.frame0 = rnd.frame0.index_copy(0, ids, sub.frame0)
        live[ids[done]] = False
    return p, cost, H


def _lm_step(
    rnd: _Round,
    p: Tensor,
    cost: Tensor,
    lam: Tensor,
    prior: _Prior,
    free: Tensor,
    settings: RefineSettings,
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """One LM linearisation (with up to ``MAX_TRIES`` damping increases) for all of ``rnd``'s texels:
    returns p (omega folded into ``rnd.frame0``), cost, the Gauss-Newton Hessian and the damping."""
    tr = rnd.tr
    N = p.shape[0]
    lo, hi = _LO.to(p.dtype), _HI.to(p.dtype)
    bases = rnd.linearised(p[:, P_LOGA])
    H, g = normal_equations(*bases, p, tr.y, tr.inv_sigma, tr.mask, tr.censored, settings.noise.robust)
    la_w, rs_w = prior.la_w.double()[:, None], prior.rs_w.double()[:, None]
    H[:, [3, 4], [3, 4]] += la_w  # the alpha and rho_s priors
    H[:, [8, 9, 10], [8, 9, 10]] += rs_w
    g[:, P_LOGA] += la_w * (p[:, P_LOGA] - prior.la0).double()
    g[:, P_RHO_S] += rs_w * (p[:, P_RHO_S] - prior.rs0).double()
    # the isotropy tie: 1/2 w (log alpha_x - log alpha_y)^2
    tie_w, spread = prior.tie_w.double(), (p[:, 3] - p[:, 4]).double()
    H[:, 3, 3] += tie_w
    H[:, 4, 4] += tie_w
    H[:, 3, 4] -= tie_w
    H[:, 4, 3] -= tie_w
    g[:, 3] += tie_w * spread
    g[:, 4] -= tie_w * spread
    # the tint pull: 1/2 w s |rho_s - mean|^2, its relative scale s held at this linearisation (the
    # cost, which accepts a step, has it exact)
    rs = p[:, P_RHO_S].double()
    tint_w = prior.tint_w * _tint_scale(rs)[:, None, None]
    H[:, 8:11, 8:11] += tint_w * (torch.eye(3, dtype=torch.float64) - 1.0 / 3.0)
    g[:, P_RHO_S] += tint_w[..., 0] * (rs - rs.mean(1, keepdim=True))
    # the normal prior: residuals u_x, u_y / sigma of the prior's normal u in the shading frame,
    # d u / d omega_k = u x e_k
    u = _prior_normal_in(rnd.frame0, prior.n_prior).double()  # at omega = 0
    zero = torch.zeros_like(u[:, 0])
    sn = prior.n_w**-0.5
    ju = torch.stack([torch.stack([zero, -u[:, 2], u[:, 1]], 1), torch.stack([u[:, 2], zero, -u[:, 0]], 1)], 1) / sn
    H[:, :3, :3] += ju.transpose(1, 2) @ ju
    g[:, :3] += (ju.transpose(1, 2) @ (u[:, :2, None] / sn))[..., 0]
    # active set: a parameter at a bound whose gradient points out stays there this iteration
    at_lo = (p <= lo + 1e-7) & (g > 0)
    at_hi = (p >= hi - 1e-7) & (g < 0)
    mf = (free & ~at_lo & ~at_hi).double()
    Hm = H * mf[:, :, None] * mf[:, None, :]
    gm = g * mf
    diag = Hm.diagonal(dim1=1, dim2=2)
    p, cost, lam = p.clone(), cost.clone(), lam.clone()
    ids = torch.arange(N)  # the texels still waiting for an accepted step
    for _try in range(MAX_TRIES):  # a rejected step is retried with more damping (same linearisation)
        # only those are evaluated again: a retry on every texel made half of the model's evaluations
        sub, sub_prior = (rnd, prior) if len(ids) == N else (rnd.rows(ids), prior.rows(ids))
        dg = diag[ids]
        A = Hm[ids] + torch.diag_embed(lam[ids, None] * (dg + 1e-3 * dg.mean(1, keepdim=True)) + (1 - mf[ids]))
        step = -torch.linalg.solve(A, gm[ids, :, None])[..., 0]
        q = torch.minimum(torch.maximum(p[ids] + step.to(p.dtype), lo), hi)
        new = _cost_at(sub, q, sub_prior, settings)
        better = torch.isfinite(new) & (new < cost[ids])
        k = ids[better]
        p[k], cost[k] = q[better], new[better]
        lam[ids] = torch.where(better, (lam[ids] * 0.3).clamp_min(1e-7), lam[ids] * 10)
        ids = ids[~better]
        if len(ids) == 0:
            break
    rnd.rebase(p[:, P_OMEGA])
    p[:, P_OMEGA] = 0.0  # p is this step's own copy (taken before the tries)
    return p, cost, H, lam


def _fold(frame: Tensor, omega: Tensor) -> Tensor:
    """The frame turned by ``omega`` (shading-frame rotation vector): rows of R^T F."""
    return rotation_from_vector(omega).transpose(-1, -2) @ frame


def _albedo_start(
    rnd: _Round, p: Tensor, specular: bool, keep_rho_s: bool = False, bases: tuple[Tensor, Tensor] | None = None
) -> Tensor:
    """p with rho_d (and rho_s unless ``keep_rho_s``) replaced by the bounded weighted least squares
    for the round's geometry (``bases``: the round's at p, where the caller has them); ``specular``
    False: rho_s = 0. A clipped entry counts, as in the data cost, where the answer predicts it
    darker than its lower bound: up to ``CLIPPED_ROUNDS`` solves, each adding (at its bound) the
    clipped entries the last one fell below. Left out, a texel whose every entry is clipped (the
    vase's white print in 2-4 entries) got rho_d 0, and a lobe took its light (docs/accuracy.md)."""
    tr = rnd.tr
    d, s = rnd.bases(p[:, P_OMEGA], p[:, P_LOGA]) if bases is None else bases
    w = (tr.inv_sigma**2 * tr.mask).double()
    y = tr.y
    if not specular:
        s = torch.zeros_like(s)
    elif keep_rho_s:  # the lobe is given: only rho_d is solved, against what the lobe leaves
        y, s = y - p[:, None, P_RHO_S] * s, torch.zeros_like(s)
    rho_s_max = RHO_S_MAX if specular and not keep_rho_s else 0.0
    counted = tr.mask & ~tr.censored
    for _ in range(CLIPPED_ROUNDS):
        q = _with_albedos(p, d, s, y, w * counted, rho_s_max, keep_rho_s)
        pred = q[:, None, P_RHO_D] * d + q[:, None, P_RHO_S] * s  # s: 0 where rho_s is given or none
        now = counted | (tr.censored & (pred < y))  # once below its bound, counted at it (no cycling)
        if torch.equal(now, counted):
            break
        counted = now
    return q


def _with_albedos(
    p: Tensor, d: Tensor, s: Tensor, y: Tensor, w: Tensor, rho_s_max: float, keep_rho_s: bool = False
) -> Tensor:
    """p with rho_d (and rho_s unless ``keep_rho_s``) the bounded least squares of ``y`` ≈ rho_d
    ``d`` + rho_s ``s`` channel by channel, weights ``w`` (all ``(N, V, 3)``; float64 inside)."""
    rd, rs = bounded_ls2(
        d.double().transpose(1, 2),
        s.double().transpose(1, 2),
        y.double().transpose(1, 2),
        w.double().transpose(1, 2),
        RHO_D_MAX,
        rho_s_max,
    )
    p = p.clone()
    p[:, P_RHO_D] = rd.to(p.dtype)
    if not keep_rho_s:
        p[:, P_RHO_S] = rs.to(p.dtype)
    return p


def _solve(
    tr: _Trace,
    frame: Tensor,
    p: Tensor,
    specular: bool,
    settings: RefineSettings,
    prior: _Prior | None = None,
    weak: _Prior | None = None,
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """All rounds for one group of texels (all with a lobe, or all diffuse-only); returns frame,
    p, cost and the last Gauss-Newton Hessian. ``prior``: the weak pulls (``weak``, else to the
    start) unless given (a basis material's lobe: then no multi-start, and the first round keeps the
    prior's rho_s)."""
    N = p.shape[0]
    free = torch.ones(N, N_PARAMS, dtype=torch.bool)
    if not specular:
        free[:, 2] = False  # omega_z turns only the tangent
        free[:, P_LOGA] = False
        free[:, P_RHO_S] = False
        p = p.clone()
        p[:, P_RHO_S] = 0.0
    given = prior is not None
    if prior is None:
        prior = weak if weak is not None else _Prior.weak(frame, p, settings)
    H = torch.zeros(N, N_PARAMS, N_PARAMS, dtype=torch.float64)
    cost = torch.zeros(N, dtype=p.dtype)
    first = 0
    if settings.starts and specular and not given and settings.rounds > 0:  # the multi-start is round one
        frame, p = _multi_start(tr, frame, p, prior, free, settings)
        first = 1
    for k in range(first, settings.rounds):
        rnd = _Round(tr, frame, p[:, P_LOGA], specular, rho_s=p[:, P_RHO_S])
        if k == 0:
            p = _albedo_start(rnd, p, specular, keep_rho_s=given)
        p, cost, H = _lm(rnd, p, prior, free, settings.iterations, settings)
        frame = rnd.frame0
    return frame, p, cost, H


def _multi_start(
    tr: _Trace, frame: Tensor, p: Tensor, prior: _Prior, free: Tensor, settings: RefineSettings
) -> tuple[Tensor, Tensor]:
    """Starts where the lobe is ambiguous: as given, the tangent turned 90 deg (the other axis
    carries alpha_x; not where the start's lobe is isotropic, ``ISOTROPIC_START`` — turned, it is
    the same model, so the same answer), the lobe 4x sharper; one round of LM each, the cheapest kept
    per texel. The three share F0's normal, so its diffuse basis."""
    N = p.shape[0]
    sharp = p.clone()
    sharp[:, P_LOGA] = (sharp[:, P_LOGA] + math.log(SHARP_START)).clamp(math.log(ALPHA_MIN), math.log(ALPHA_MAX))
    la = p[:, P_LOGA]
    turned = ((la[:, 0] - la[:, 1]).abs() >= math.log(ISOTROPIC_START)).nonzero().squeeze(1)
    quarter = torch.zeros(len(turned), 3, dtype=p.dtype)
    quarter[:, 2] = math.pi / 2
    best_cost = torch.full((N,), math.inf, dtype=p.dtype)
    best_frame, best_p = frame.clone(), p.clone()
    every = torch.arange(N)
    diffuse: Tensor | None = None  # the first start's, for all N
    for at, f0, q0 in ((every, frame, p), (turned, _fold(frame[turned], quarter), p[turned]), (every, frame, sharp)):
        if len(at) == 0:
            continue
        whole = len(at) == N
        sub, sub_prior, sub_free = (tr, prior, free) if whole else (tr.rows(at), prior.rows(at), free[at])
        rnd = _Round(sub, f0, q0[:, P_LOGA], True, None if diffuse is None else diffuse[at], q0[:, P_RHO_S])
        diffuse = rnd.diffuse if diffuse is None else diffuse
        q, cost, _ = _lm(rnd, _albedo_start(rnd, q0, True), sub_prior, sub_free, settings.iterations, settings)
        better = cost < best_cost[at]
        k = at[better]
        best_cost[k], best_frame[k], best_p[k] = cost[better], rnd.frame0[better], q[better]
    return best_frame, best_p


def refine(
    scanner: Scanner,
    entries: Tensor,
    mask: Tensor,
    start: Start,
    specular: Tensor,
    settings: RefineSettings | None = None,
    shadow: Tensor | None = None,
    support: SupportView | None = None,
    footprint: Footprint | None = None,
    centre: Start | None = None,
) -> Refined:
    """Refine N texels from ``start``, the weak pulls centred on ``centre`` (default: the start).
    ``entries (N, V, 12)`` as captured with ``mask (N, V)`` and
    ``shadow (N, V)`` (the emitter groups the mesh hides from each entry: ``learn.ragged``);
    ``specular (N,)``: texels whose lobe is solved. A texel without one, or whose solved lobe no
    entry shows (below ``MIN_SPECULAR_SHARE`` of every pixel), gets a diffuse-only solve from its
    start and rho_s = 0, its lobe flagged unconstrained. ``footprint``: what each entry's pixel sample
    spans (``fit.footprint``; None: a flat surface, no albedo blend) — the normals, which widen the
    lobe it sees, and the neighbours' albedo it may blend in. Never NaN: a failed solve keeps the start."""
    settings = settings or RefineSettings()
    tr = _Trace(scanner, entries, mask, settings.noise, emitter_blocks(scanner), shadow, support, footprint)
    return _refine(tr, start, specular, settings, centre)


def _parameters(start: Start, dtype: torch.dtype) -> tuple[Tensor, Tensor]:
    """``start`` as the solver's frame ``(N, 3, 3)`` and parameters ``p (N, 11)`` (omega 0), in range."""
    frame = frame_from_normal_tangent(start.normal.to(dtype), start.tangent.to(dtype))
    p = torch.zeros(len(frame), N_PARAMS, dtype=dtype)
    p[:, P_LOGA] = start.alpha.to(dtype).clamp(ALPHA_MIN, ALPHA_MAX).log()
    p[:, P_RHO_D] = start.rho_d.to(dtype).clamp(0, RHO_D_MAX)
    p[:, P_RHO_S] = start.rho_s.to(dtype).clamp(0, RHO_S_MAX)
    return frame, p


def _refine(
    tr: _Trace, start: Start, specular: Tensor, settings: RefineSettings, centre: Start | None = None
) -> Refined:
    """``refine`` on traces already prepared with ``settings.noise``."""
    dtype = tr.y.dtype
    N = tr.N
    frame, p = _parameters(start, dtype)
    weak = _Prior.weak(*(_parameters(centre, dtype) if centre is not None else (frame, p)), settings)
    # every texel's diffuse-only answer (cheap: no lobe), then the lobe where one is sought; the lobe
    # stays where an entry shows it and it lowers the cost by more than ``lobe_evidence``
    out_frame, out_p, cost, H = _solve(tr, frame, p, False, settings, weak=weak)
    highlight = torch.zeros(N, dtype=dtype)
    evidence = lobe_evidence(tr.mask.sum((1, 2)))
    idx = (specular & _lobe_can_pass(cost, evidence)).nonzero().squeeze(1)
    if len(idx):
        sub = tr if len(idx) == N else tr.rows(idx)  # idx sorted: all texels or a subset
        f, q, c, h = _solve(sub, frame[idx], p[idx], True, settings, weak=weak.rows(idx))
        peak = _highlight(sub, f, q)
        keep = (peak >= MIN_SPECULAR_SHARE) & (c < cost[idx] - evidence[idx])
        diffuse_cost = cost[idx[keep]]
        highlight[idx] = torch.where(keep, peak, torch.zeros_like(peak))
        k = idx[keep]
        out_frame[k], out_p[k], cost[k], H[k] = f[keep], q[keep], c[keep], h[keep]
        sel, f, q, c, h, peak = _prefer_isotropic(tr, k, out_frame[k], out_p[k], cost[k], weak.rows(k), settings)
        ok = c < diffuse_cost[sel] - evidence[k[sel]]  # the isotropic lobe still passes the lobe test
        j = k[sel[ok]]
        out_frame[j], out_p[j], cost[j], H[j], highlight[j] = f[ok], q[ok], c[ok], h[ok], peak[ok]
    # never NaN: a texel whose solve went non-finite keeps its start
    bad = ~(torch.isfinite(out_p).all(1) & torch.isfinite(out_frame).flatten(1).all(1) & torch.isfinite(cost))
    out_p[bad], out_frame[bad] = p[bad], frame[bad]
    return _finish(out_frame, out_p, H, cost, highlight)


def _prefer_isotropic(
    tr: _Trace, idx: Tensor, frame: Tensor, p: Tensor, cost: Tensor, prior: _Prior, settings: RefineSettings
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor]:
    """Isotropic unless the trace shows otherwise: of the N solved lobes of ``tr``'s texels ``idx``
    (``frame``, ``p``, ``cost``, solved under ``prior``), those less anisotropic than
    ``ANISOTROPY_TEST`` are solved again from the same answer with their alphas tied (at their
    geometric mean), under the same pulls. The anisotropic answer stays only where it lowers the
    cost by more than AIC's penalty for the ``ANISOTROPY_PARAMS`` it adds (1 per parameter in half
    chi-square units; BIC's, 4.3 at 72 residuals, made a third of a 2.5:1 lobe isotropic in the
    tests' synthetic traces, AIC a tenth). Why: a trace of a sharp isotropic lobe sees it through
    one or two LEDs in a few entries, so one axis is measured and the other drifts toward the
    start's (the gallery's alpha 0.02 plastic came back 0.03 x 0.06). Returns which of the N texels
    ``sel`` take the isotropic answer, and its frame, p, cost, Hessian and highlight ``(len(sel),
    ...)``."""
    la = p[:, P_LOGA]
    test = ((la[:, 0] - la[:, 1]).abs() < math.log(ANISOTROPY_TEST)).nonzero().squeeze(1)
    if len(test) == 0:
        none = torch.zeros(0, dtype=torch.long)
        return none, frame[:0], p[:0], cost[:0], torch.zeros(0, N_PARAMS, N_PARAMS, dtype=torch.float64), p[:0, 0]
    sub = tr.rows(idx[test])
    start = p[test].clone()
    start[:, P_LOGA] = start[:, P_LOGA].mean(1, keepdim=True)
    pulls = prior.rows(test).tied(torch.ones(len(test), dtype=torch.bool))
    f, q, c, h = _solve(sub, frame[test], start, True, dataclasses.replace(settings, rounds=ISOTROPIC_ROUNDS), pulls)
    peak = _highlight(sub, f, q)
    take = torch.isfinite(c) & (peak >= MIN_SPECULAR_SHARE) & (c <= cost[test] + ANISOTROPY_PARAMS)
    return test[take], f[take], q[take], c[take], h[take], peak[take]


def _lobe_can_pass(diffuse_cost: Tensor, evidence: Tensor) -> Tensor:
    """Texels ``(N,)`` whose own lobe could pass the evidence test: the full solve's cost (robust
    data cost plus priors) is never below 0, so a lobe is kept only where the diffuse-only cost
    exceeds the evidence — elsewhere its solve would be thrown away (on the gallery's engine scans
    22–72% of the texels, the demo 30%), and is skipped: the same answers."""
    return diffuse_cost > evidence


def lobe_evidence(residuals: Tensor) -> Tensor:
    """How much a texel's own lobe must lower its robust cost to be kept, for its number of
    ``residuals (N,)``: ``LOBE_EVIDENCE`` or BIC's penalty for ``LOBE_PARAMS``, the larger."""
    return (0.5 * LOBE_PARAMS * residuals.clamp_min(1).to(torch.float32).log()).clamp_min(LOBE_EVIDENCE)


class MaterialCosts(NamedTuple):
    """``material_costs``' answer: per texel and model (no lobe, then each material)."""

    cost: Tensor  # (N, 1 + K) robust data cost; inf: not judged
    turn: Tensor  # (N, K) the best turn of each material's tangent (radians)
    rho_d: Tensor  # (N, 1 + K, 3) the rho_d re-solved under each model; NaN: not judged


def material_costs(
    scanner: Scanner,
    entries: Tensor,
    mask: Tensor,
    start: Start,
    alpha: Tensor,
    rho_s: Tensor,
    candidates: Tensor | None = None,
    settings: RefineSettings | None = None,
    shadow: Tensor | None = None,
    turn_prior: tuple[Tensor, Tensor] | None = None,
    support: SupportView | None = None,
    footprint: Footprint | None = None,
) -> MaterialCosts:
    """How well K basis materials' lobes (``alpha (K, 2)``, ``rho_s (K, 3)``) explain N traces:
    the robust data cost ``(N, 1 + K)`` of each texel's trace under no lobe (column 0) and under each
    material's lobe where ``candidates (N, K)`` (default all; elsewhere inf), with the texel's own
    normal and its rho_d re-solved (bounded least squares; ``(N, 1 + K, 3)``, NaN where not judged),
    and the turn ``(N, K)`` (radians, about the normal from ``start``'s tangent) that fits best (its
    rho_d the one at that turn). An anisotropic lobe at the texel's start tangent is a guess (a UV
    direction), so it is tried at ``TANGENT_TURNS`` turns over 180 deg and its cost is the negative
    log of their mean likelihood (uniform over turns; the cheapest alone would let a lobe hide in
    the noise by choosing where to point). ``turn_prior`` = (turn, agree)
    ``(N, K)``: where the texel's neighbours say material k points (``fit.tangent_field``) — that
    turn is tried too and weighs ``agree`` in the mean, the others ``(1 - agree) / TANGENT_TURNS``
    (agree 0: uniform; the turns stay anchored at the start tangent, a UV direction, which is the
    better guess where neighbours disagree). Columns are comparable: each model has the same free
    rho_d."""
    settings = settings or RefineSettings()
    tr_all = _Trace(scanner, entries, mask, settings.noise, emitter_blocks(scanner), shadow, support, footprint)
    dtype = tr_all.y.dtype
    N, K = tr_all.N, alpha.shape[0]
    frame_all = frame_from_normal_tangent(start.normal.to(dtype), start.tangent.to(dtype))
    cost = torch.full((N, 1 + K), math.inf, dtype=dtype)
    rho_d = torch.full((N, 1 + K, 3), math.nan, dtype=dtype)
    turn = torch.zeros(N, K, dtype=dtype)
    candidates = torch.ones(N, K, dtype=torch.bool) if candidates is None else candidates

    def judged(tr: _Trace, f: Tensor, m: int, diffuse: Tensor | None) -> tuple[Tensor, Tensor, Tensor]:
        """The cost under material m (0: no lobe), the round's diffuse basis and the rho_d."""
        a, r = (alpha[m - 1], rho_s[m - 1]) if m else (alpha.new_ones(2), rho_s.new_zeros(3))
        return _given_lobe_cost(tr, f, a.expand(tr.N, 2), r.expand(tr.N, 3), m > 0, diffuse, settings)

    # every model shares the texel's normal, so its diffuse basis
    cost[:, 0], diffuse, rho_d[:, 0] = judged(tr_all, frame_all, 0, None)
    for m in range(1, K + 1):
        idx = candidates[:, m - 1].nonzero().squeeze(1)
        if len(idx) == 0:
            continue
        tr, frame, d = tr_all.rows(idx), frame_all[idx], diffuse[idx]
        anisotropic = bool(alpha[m - 1, 0] >= ISOTROPIC_RATIO * alpha[m - 1, 1])
        n = TANGENT_TURNS if anisotropic else 1
        angles = (torch.arange(n, dtype=dtype) * math.pi / TANGENT_TURNS).expand(len(idx), n)
        weight = torch.full((len(idx), n), 1.0 / n, dtype=dtype)
        if anisotropic and turn_prior is not None:  # the neighbours' turn as one more, weighing agree
            agree = turn_prior[1][idx, m - 1].to(dtype).clamp(0, 1)[:, None]
            angles = torch.cat([angles, turn_prior[0][idx, m - 1].to(dtype)[:, None]], 1)
            weight = torch.cat([weight * (1 - agree), agree], 1)
        each = [judged(tr, turned_about_normal(frame, a), m, d) for a in angles.unbind(1)]
        c = torch.stack([e[0] for e in each], 1)
        score = torch.log(weight) - c  # log of each turn's share of the likelihood (a weight of 0: none)
        best = score.argmax(1)
        cost[idx, m] = -torch.logsumexp(score, 1)
        turn[idx, m - 1] = angles.gather(1, best[:, None])[:, 0]
        rho_d[idx, m] = torch.stack([e[2] for e in each], 1)[torch.arange(len(idx)), best]
    return MaterialCosts(cost, turn, rho_d)


def _given_lobe_cost(
    tr: _Trace,
    frame: Tensor,
    alpha: Tensor,
    rho_s: Tensor,
    specular: bool,
    diffuse: Tensor | None,
    settings: RefineSettings,
) -> tuple[Tensor, Tensor, Tensor]:
    """The robust data cost ``(N,)`` of traces under the lobes ``alpha (N, 2)``, ``rho_s (N, 3)``
    (``specular`` False: none) in ``frame``, rho_d re-solved (bounded least squares; inf where not
    finite), the round's diffuse basis (``diffuse``: one of the same normal, reused) and that rho_d
    ``(N, 3)``."""
    dtype = tr.y.dtype
    p = torch.zeros(tr.N, N_PARAMS, dtype=dtype)
    if specular:
        p[:, P_LOGA] = alpha.to(dtype).clamp(ALPHA_MIN, ALPHA_MAX).log()
        p[:, P_RHO_S] = rho_s.to(dtype).clamp(0, RHO_S_MAX)
    rnd = _Round(tr, frame, p[:, P_LOGA], specular, diffuse, p[:, P_RHO_S])
    bases = rnd.bases(p[:, P_OMEGA], p[:, P_LOGA])
    p = _albedo_start(rnd, p, specular, keep_rho_s=True, bases=bases)
    c = data_cost(*bases, p, tr.y, tr.inv_sigma, tr.mask, tr.censored, settings.noise.robust)
    return torch.nan_to_num(c, nan=math.inf), rnd.diffuse, p[:, P_RHO_D]


def turn_costs(
    scanner: Scanner,
    entries: Tensor,
    mask: Tensor,
    start: Start,
    turns: Tensor,
    settings: RefineSettings | None = None,
    shadow: Tensor | None = None,
    support: SupportView | None = None,
    footprint: Footprint | None = None,
) -> Tensor:
    """The robust data cost ``(N, T)`` of N traces under each texel's own lobe (``start``'s normal,
    alphas and rho_s) with its tangent turned by ``turns (N, T)`` (radians about the normal, as
    ``material_costs``' turns), rho_d re-solved: how much its photos object to each direction."""
    settings = settings or RefineSettings()
    tr = _Trace(scanner, entries, mask, settings.noise, emitter_blocks(scanner), shadow, support, footprint)
    dtype = tr.y.dtype
    frame = frame_from_normal_tangent(start.normal.to(dtype), start.tangent.to(dtype))
    costs, diffuse = [], None
    for a in turns.to(dtype).unbind(1):
        c, diffuse, _ = _given_lobe_cost(
            tr, turned_about_normal(frame, a), start.alpha, start.rho_s, True, diffuse, settings
        )
        costs.append(c)
    return torch.stack(costs, 1)


def lobe_costs(
    scanner: Scanner,
    entries: Tensor,
    mask: Tensor,
    start: Start,
    alphas: Tensor,
    settings: RefineSettings | None = None,
    shadow: Tensor | None = None,
    support: SupportView | None = None,
    footprint: Footprint | None = None,
) -> tuple[Tensor, Tensor, Tensor]:
    """How well S candidate lobe widths explain N traces: the robust data cost ``(N, S)`` of each
    texel's trace under ``alphas (N, S, 2)`` (alpha_x along ``start``'s tangent; clamped to the
    range) with the texel's own frame and its rho_d and rho_s re-solved under that cost
    (``_robust_albedos``), and those ``rho_d, rho_s (N, S, 3)``. Summed over a material's texels
    it is the profile of their cost over the material's lobe width, which one trace alone may not
    tell from a broader diffuse (``fit.materials.pooled_scale``)."""
    settings = settings or RefineSettings()
    tr = _Trace(scanner, entries, mask, settings.noise, emitter_blocks(scanner), shadow, support, footprint)
    dtype = tr.y.dtype
    frame = frame_from_normal_tangent(start.normal.to(dtype), start.tangent.to(dtype))
    N, S = alphas.shape[:2]
    cost = torch.empty(N, S, dtype=dtype)
    rho_d, rho_s = torch.empty(N, S, 3, dtype=dtype), torch.empty(N, S, 3, dtype=dtype)
    diffuse: Tensor | None = None  # one normal, one diffuse basis for every width
    for k in range(S):
        p = torch.zeros(N, N_PARAMS, dtype=dtype)
        p[:, P_LOGA] = alphas[:, k].to(dtype).clamp(ALPHA_MIN, ALPHA_MAX).log()
        rnd = _Round(tr, frame, p[:, P_LOGA], True, diffuse, start.rho_s.to(dtype))  # its Fresnel: start's rho_s
        diffuse = rnd.diffuse
        bases = rnd.bases(p[:, P_OMEGA], p[:, P_LOGA])
        p, c = _robust_albedos(tr, bases, _albedo_start(rnd, p, True, bases=bases), settings)
        cost[:, k] = torch.nan_to_num(c, nan=math.inf)
        rho_d[:, k], rho_s[:, k] = p[:, P_RHO_D], p[:, P_RHO_S]
    return cost, rho_d, rho_s


def _robust_albedos(
    tr: _Trace, bases: tuple[Tensor, Tensor], p: Tensor, settings: RefineSettings
) -> tuple[Tensor, Tensor]:
    """rho_d and rho_s of ``p (N, 11)`` re-solved under the robust cost for fixed geometry (pixel
    ``bases``), and that cost ``(N,)``: ``ALBEDO_ITERATIONS`` of iteratively reweighted bounded least
    squares (Cauchy weights; a clipped entry counts only while the prediction is below it), each
    kept where it lowers the cost. Why: the plain least squares leave out the clipped entries,
    which for a bright lobe are its highlights — the vase's 1:80 brushed metal pooled to a width
    0.5 x 0.15 with them left out, 0.5 x 0.018 with them held (``lobe_costs``)."""
    d, s = bases
    c = settings.noise.robust
    r, active = _residuals(tr, d, s, p)
    cost = _cost(r, c)
    for _ in range(ALBEDO_ITERATIONS):
        q = _with_albedos(p, d, s, tr.y, tr.inv_sigma**2 * active / (1.0 + (r / c) ** 2), RHO_S_MAX)
        r_q, active_q = _residuals(tr, d, s, q)
        new = _cost(r_q, c)
        better = new < cost
        p = torch.where(better[:, None], q, p)
        cost = torch.where(better, new, cost)
        r = torch.where(better[:, None, None], r_q, r)
        active = torch.where(better[:, None, None], active_q, active)
    return p, cost


def refine_toward(
    scanner: Scanner,
    entries: Tensor,
    mask: Tensor,
    start: Start,
    prior: LobePrior,
    settings: RefineSettings | None = None,
    shadow: Tensor | None = None,
    support: SupportView | None = None,
    footprint: Footprint | None = None,
) -> Refined:
    """Refine N texels that take their lobe from a basis material: from ``start`` (the material's
    lobe with the texel's own frame, rho_d), with alphas and rho_s pulled to ``prior`` by its
    spreads; no multi-start. The lobe is kept whether or not an entry shows it (flags:
    ``FLAG_FROM_MATERIAL``, and ``FLAG_SPECULAR_UNCONSTRAINED`` where none does: its parameters are
    then the material's; its uncertainty the prior's). Never NaN: a failed solve keeps the start."""
    settings = settings or RefineSettings()
    tr = _Trace(scanner, entries, mask, settings.noise, emitter_blocks(scanner), shadow, support, footprint)
    dtype = tr.y.dtype
    N = tr.N
    frame = frame_from_normal_tangent(start.normal.to(dtype), start.tangent.to(dtype))
    p = torch.zeros(N, N_PARAMS, dtype=dtype)
    p[:, P_LOGA] = prior.alpha.to(dtype).clamp(ALPHA_MIN, ALPHA_MAX).log()
    p[:, P_RHO_D] = start.rho_d.to(dtype).clamp(0, RHO_D_MAX)
    p[:, P_RHO_S] = prior.rho_s.to(dtype).clamp(0, RHO_S_MAX)
    pulls = _Prior(
        _normal_prior(frame, settings),
        math.radians(settings.normal_prior_deg) ** -2,
        p[:, P_LOGA].clone(),
        prior.log_alpha_sigma.to(dtype).clamp_min(1e-3) ** -2,
        p[:, P_RHO_S].clone(),
        prior.rho_s_sigma.to(dtype).clamp_min(1e-3) ** -2,
        torch.zeros(N, dtype=dtype),
        settings.rho_s_tint_sigma**-2,
    ).tied(p[:, 3] - p[:, 4] < math.log(ISOTROPIC_RATIO))  # an isotropic material's lobe stays isotropic
    f, q, cost, H = _solve(tr, frame, p, True, settings, pulls)
    bad = ~(torch.isfinite(q).all(1) & torch.isfinite(f).flatten(1).all(1) & torch.isfinite(cost))
    q[bad], f[bad] = p[bad], frame[bad]
    return _finish(f, q, H, cost, _highlight(tr, f, q), from_material=torch.ones(N, dtype=torch.bool))


def calibrated(
    scanner: Scanner,
    entries: Tensor,
    mask: Tensor,
    start: Start,
    specular: Tensor,
    settings: RefineSettings,
    shadow: Tensor | None = None,
    support: SupportView | None = None,
    footprint: Footprint | None = None,
) -> RefineSettings:
    """``settings`` calibrated on a refinement of these sample traces. The noise model is scaled
    (within ``NOISE_SCALE``) so that the answer's residuals have unit robust scale — 1.4826 x the
    median |normalised residual| over its entries is 1 when the model is right (Monte Carlo renders
    and unmodelled effects give more): data from a noisier source then weigh against the priors as
    much as they deserve; a quieter source keeps the model as it is (``NOISE_SCALE``'s floor of 1).
    And the normal's weak pull centres on the mesh's normal where the sample's texels whose own
    photos fix their normals (1-sigma below ``NORMAL_FIXED_DEG``, at least ``NORMAL_FIXED_TEXELS``
    of them) lie nearer it than to their start's in the median — the start (the network's answer)
    reads the same photos, and where it errs a pull to it keeps the error on the texels the photos
    say little about (docs/refinement.md)."""
    tr = _Trace(scanner, entries, mask, settings.noise, emitter_blocks(scanner), shadow, support, footprint)
    r = _refine(tr, start, specular, settings)
    p = torch.cat([torch.zeros_like(r.rho_d), r.log_alpha, r.rho_d, r.rho_s], 1)
    res, active = _residuals(tr, *_predict(tr, r.frame, p), p)
    vals = res[active].abs()
    k = float(1.4826 * vals.median()) if len(vals) else 1.0
    k = min(max(k, NOISE_SCALE[0]), NOISE_SCALE[1])
    noise = SensorNoise(settings.noise.read_code * k, settings.noise.relative * k, settings.noise.robust)
    fixed = r.std[:, 0] < NORMAL_FIXED_DEG
    at_mesh = settings.normal_prior_at_mesh
    if int(fixed.sum()) >= NORMAL_FIXED_TEXELS:
        n = r.frame[fixed, 2]
        from_mesh = torch.acos(n[:, 2].clamp(-1, 1)).median()
        n0 = torch.nn.functional.normalize(start.normal[fixed].to(n.dtype), dim=1)
        from_start = torch.acos((n * n0).sum(1).clamp(-1, 1)).median()
        at_mesh = bool(from_mesh < from_start)
    return dataclasses.replace(settings, noise=noise, normal_prior_at_mesh=at_mesh)


def predicted_light(
    scanner: Scanner,
    entries: Tensor,
    mask: Tensor,
    answer: Start,
    settings: RefineSettings | None = None,
    shadow: Tensor | None = None,
    support: SupportView | None = None,
    footprint: Footprint | None = None,
) -> tuple[Tensor, Tensor, Tensor]:
    """Eq. 1 at N texels' ``answer`` (taken as it is), as ``refine`` models their entries: each
    entry's unit-albedo diffuse light, its lobe's light (the answer's rho_s times the specular basis)
    and its sensor 1/sigma (``settings.noise``; 0 where masked or clipped), each ``(N, V, 3)``.
    ``footprint``'s slope spread widens the lobe; its albedo blend is left out (the sensor's noise only)."""
    settings = settings or RefineSettings()
    spread = None if footprint is None else Footprint(footprint.spread, None)
    tr = _Trace(scanner, entries, mask, settings.noise, emitter_blocks(scanner), shadow, support, spread)
    frame, p = _parameters(answer, tr.y.dtype)
    diffuse, spec = _predict(tr, frame, p)
    inv_sigma = torch.where(tr.censored, torch.zeros_like(tr.inv_sigma), tr.inv_sigma)
    return diffuse, p[:, None, P_RHO_S] * spec, inv_sigma


def _predict(tr: _Trace, frame: Tensor, p: Tensor) -> tuple[Tensor, Tensor]:
    """Unit-albedo diffuse and specular bases ``(N, V, 3)`` of the answer ``frame``, ``p`` (omega 0)."""
    rnd = _Round(tr, frame, p[:, P_LOGA], True, rho_s=p[:, P_RHO_S])
    return rnd.bases(torch.zeros_like(p[:, P_OMEGA]), p[:, P_LOGA])


def _highlight(tr: _Trace, frame: Tensor, p: Tensor) -> Tensor:
    """The largest share ``(N,)`` of an entry's pixel that the fitted lobe makes (``MIN_SPECULAR_SHARE``
    or more: some entry shows it)."""
    d, s = _predict(tr, frame, p)
    pred_s = (p[:, None, P_RHO_S] * s).sum(-1)
    pred = (p[:, None, P_RHO_D] * d).sum(-1) + pred_s
    share = torch.where(tr.mask[..., 0], pred_s / pred.clamp_min(1e-12), torch.zeros_like(pred))
    return share.amax(1)


def _finish(
    frame: Tensor, p: Tensor, H: Tensor, cost: Tensor, highlight: Tensor, from_material: Tensor | None = None
) -> Refined:
    """Canonical lobe (alpha_x >= alpha_y), the flags and the 1-sigma uncertainties. A lobe is
    written where seen (its ``highlight`` is ``MIN_SPECULAR_SHARE`` of some entry's pixel or more)
    or given ``from_material``; else rho_s = 0."""
    seen = highlight >= MIN_SPECULAR_SHARE
    from_material = torch.zeros_like(seen) if from_material is None else from_material
    kept = seen | from_material
    la = p[:, P_LOGA]
    swap = la[:, 1] > la[:, 0]
    t, b, n = frame[:, 0], frame[:, 1], frame[:, 2]
    frame = torch.stack([torch.where(swap[:, None], b, t), torch.where(swap[:, None], -t, b), n], 1)
    la = torch.where(swap[:, None], la.flip(1), la)
    # uncertainty: diag of the inverse Gauss-Newton Hessian (unit-sigma residuals, priors included)
    Hd = H + 1e-12 * torch.eye(N_PARAMS, dtype=H.dtype)
    cov = torch.linalg.pinv(Hd).diagonal(dim1=1, dim2=2).clamp_min(0).sqrt().to(p.dtype)
    normal_std = torch.rad2deg(torch.sqrt(cov[:, 0] ** 2 + cov[:, 1] ** 2))
    rho_s_mean = p[:, P_RHO_S].mean(1).clamp_min(1e-3)
    std = torch.stack(
        [normal_std, torch.rad2deg(cov[:, 2]), cov[:, 3:5].amax(1), cov[:, P_RHO_S].mean(1) / rho_s_mean], 1
    )
    std = torch.where(kept[:, None], std, std.masked_fill(torch.tensor([False, True, True, True]), math.inf))
    flags = (~seen).long() * FLAG_SPECULAR_UNCONSTRAINED | from_material.long() * FLAG_FROM_MATERIAL
    iso = (la[:, 0] - la[:, 1]) < math.log(ISOTROPIC_RATIO)
    flags = flags | ((~seen | iso).long() * FLAG_TANGENT_UNCONSTRAINED)
    rho_s = torch.where(kept[:, None], p[:, P_RHO_S], torch.zeros_like(p[:, P_RHO_S]))
    return Refined(frame, la, p[:, P_RHO_D], rho_s, flags, std, cost, highlight)
