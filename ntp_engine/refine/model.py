"""The refinement's forward model: one texel's entries predicted through Eq. 1 and the camera.
Model of one entry j (a view of the texel) and camera channel c, in linear pixel units (1 = code 255):
    y_jc = exposure * sum_k P[k, c] w_jk (wi_jk . n)+ (rho_d,c / pi + rho_s,c lobe(wi_jk, wo_j; t, ax, ay))
over the emitter samples k (``measurement``'s factorised Eq. 1, falloff w = w_q Psi / r^2). The
camera is the sensor model ``SensorNoise``: an entry channel whose 8-bit code is above ``CENSOR_CODE``
may be clipped (or bilinearly mixed with a clipped pixel) and only says "at least this bright" (censored);
dark entries keep their information with an absolute noise floor instead of being dropped. On a
curved surface an entry's pixel sample spans several normals and sees the lobe widened, and near an
albedo edge it may blend the neighbours' albedo, which counts as noise on its diffuse light
(``refine.footprint``).

Convention: the parameters live in the texel's geometric (lumitexel) frame (z = n^, x = t^), like
``fit_traces``'s results: ``frame (N, 3, 3)`` rows (t, b, n); ``log_alpha (N, 2)`` natural logs of
(alpha_x, alpha_y); ``rho_d, rho_s (N, 3)``. Entries are the trace layout (``learn.ragged``) with
pixels as captured (not scaled to a model's exposure).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor

from ..fit.highlights import parked_positions
from ..fit.texel_fit import TexelFit
from ..physics.brdf import ALPHA_MAX, ALPHA_MIN, RHO_D_MAX, RHO_S_MAX
from ..physics.emitter_blocks import EmitterBlocks, emitter_blocks, shadow_groups
from ..physics.frame import (
    frame_from_normal_tangent,
    rotation_from_vector,
)
from ..scanner.scanner import Scanner
from .footprint import Footprint, widening
from .gauss_newton import N_PARAMS
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
from .settings import CENSOR_CODE, TUNING, RefineSettings, SensorNoise
from .support_light import (
    Sources,
    SupportEmitters,
    SupportView,
    support_diffuse_basis,
    support_specular_emitters,
)

# by BIC's 0.5 LOBE_PARAMS ln(residuals): a short trace fits any 6 more parameters to its noise

P_OMEGA, P_LOGA, P_RHO_D, P_RHO_S = slice(0, 3), slice(3, 5), slice(5, 8), slice(8, 11)


class Start(NamedTuple):
    """Where N texels' refinement starts (geometric frame): the network's fit, or any guess."""

    normal: Tensor  # (N, 3)
    tangent: Tensor  # (N, 3)
    alpha: Tensor  # (N, 2) alpha_x, alpha_y
    rho_d: Tensor  # (N, 3)
    rho_s: Tensor  # (N, 3)

    @classmethod
    def from_fit(cls, fit: TexelFit, idx: np.ndarray) -> Start:
        """The texels ``idx`` of a ``pipeline.fit_traces`` result (float32)."""

        def col(values: np.ndarray) -> Tensor:
            return torch.as_tensor(values[idx], dtype=torch.float32)

        return cls(col(fit.n_loc), col(fit.t_loc), col(fit.alpha), col(fit.rho_d), col(fit.rho_s))

    def rows(self, idx: Tensor) -> Start:
        """The same for the texels ``idx`` only."""
        return Start(*(v[idx] for v in self))


# the trace's per-sample arrays: shared between a chunk and its subsets (``Trace.rows``)
SAMPLE_ARRAYS = ("wo", "wi", "falloff", "wi_c", "falloff_c")


class Observations(NamedTuple):
    """N texels' traces as every refinement entry point reads them — built once per batch
    (``refine.inputs.refine_inputs``) and handed to ``refine``, ``refine_toward``,
    ``material_costs``, ``turn_costs``, ``lobe_costs``, ``calibrated`` and ``predicted_light``.
    ``entries (N, V, 12)``: the trace layout (``learn.ragged``) with pixels as captured, ``mask
    (N, V)`` the real ones; ``shadow (N, V)`` int64: the emitter groups the mesh hides from each
    entry (None: none); ``support``: the light the support reflects onto them
    (``refine.support_light``; None: not modelled); ``footprint``: what each entry's pixel sample
    spans (``refine.footprint``; None: a flat surface, no albedo blend)."""

    scanner: Scanner
    entries: Tensor
    mask: Tensor
    shadow: Tensor | None = None
    support: SupportView | None = None
    footprint: Footprint | None = None

    def trace(self, noise: SensorNoise) -> Trace:
        """The forward model's view of these traces under the sensor model ``noise``."""
        return Trace(
            self.scanner,
            self.entries,
            self.mask,
            noise,
            emitter_blocks(self.scanner),
            self.shadow,
            self.support,
            self.footprint,
        )

    def rows(self, idx: Tensor) -> Observations:
        """The same for the texels ``idx`` only."""
        return Observations(
            self.scanner,
            self.entries[idx],
            self.mask[idx],
            None if self.shadow is None else self.shadow[idx],
            None if self.support is None else self.support.rows(idx),
            None if self.footprint is None else self.footprint.rows(idx),
        )


class Trace:
    """One chunk of traces, ready for the model: every entry's directions to each emitter sample
    (and, with ``blocks``, to each block's coarse emitter) and falloff in the texel's geometric
    frame — none depends on the parameters (a shading frame only rotates them). Sample index K is
    padding: it emits nothing. Those per-sample arrays (``SAMPLE_ARRAYS``) are shared by a subset of
    the texels (``rows``), which reads its rows ``srow`` of them instead of copying them. ``shadow
    (N, V)``: the emitter groups the
    mesh hides from each entry (``learn.ragged``), whose falloff is 0. ``footprint``: what each
    entry's pixel sample spans (``refine.footprint``): the slope spread, which widens the lobe it sees,
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
        # the slope spread each entry's pixel sample covers (``refine.footprint``): None on a flat or
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
        if support is not None:  # the support's light (``refine.support_light``): what each round needs
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
        ``refine.footprint``) as noise on its diffuse light, added in quadrature to the sensor's: its
        diffuse basis at the geometric normal (a refined normal a degree or two off moves it by its
        cosine) times the blend. The censoring stays the pixel's as captured."""
        basis = self.diffuse_z[..., 2]  # (N, V, 3 channels)
        if self.support is not None:
            basis = basis + self.support_diffuse[..., 2]
        self._add_noise(albedo_blend.to(self.y.dtype) * basis.to(self.y.dtype))

    def _bounce_noise(self) -> None:
        """The bounced light's uncertainty (``TUNING.model.bounce_noise``) as noise on each entry, added in
        quadrature to the sensor's: the pixel times its share of bounced light — of the diffuse
        light at the geometric normal, per channel; fixed by the data and the geometry alone, so
        every start and round of a texel is judged on the same scale. Censoring stays the pixel's."""
        direct, bounced = self.diffuse_z[..., 2], self.support_diffuse[..., 2]  # (N, V, 3 channels)
        share = bounced / (direct + bounced).clamp_min(1e-30)
        self._add_noise(TUNING.model.bounce_noise * share.to(self.y.dtype) * self.y)

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

    def light_rows(self, idx: Tensor) -> Trace:
        """The texels ``idx`` with only what the residuals need (no per-emitter arrays)."""
        out = object.__new__(Trace)
        for k in ("y", "inv_sigma", "censored", "mask"):
            setattr(out, k, getattr(self, k)[idx])
        out.N, out.V, out.blocks = len(idx), self.V, self.blocks
        return out

    def rows(self, idx: Tensor) -> Trace:
        """The same chunk for the texels ``idx`` only: per-texel arrays copied, the per-sample ones
        shared (``srow``: the subset's rows of them)."""
        out = object.__new__(Trace)
        for k, v in vars(self).items():
            per_texel = isinstance(v, Tensor) and k not in ("drive", "drive_c") and k not in SAMPLE_ARRAYS
            setattr(out, k, v[idx] if per_texel else v)
        out.N = len(idx)
        return out


class Round:
    """The model of one round: frame F0 fixed; per entry, the emitter blocks brightest under a
    broadened lobe are summed sample by sample, the others as their coarse emitters."""

    def __init__(
        self,
        tr: Trace,
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
        # what each entry's sample adds to the round's alpha_x^2, alpha_y^2 (``refine.footprint``)
        if tr.spread is not None:
            self.widening = widening(tr.spread, frame0)
        if tr.blocks is None:  # a small device: every sample exactly
            self.emitters = pack_emitters(tr.wi[tr.srow], tr.falloff[tr.srow], tr.drive)
        else:
            seen = log_alpha.exp()
            if self.widening is not None:  # the widest lobe any entry sees
                seen = torch.sqrt(seen**2 + self.widening.amax(1))
            wide = (TUNING.model.select_widen * seen).clamp(TUNING.model.select_floor, ALPHA_MAX)
            score = lobe_weights(frame0, tr.wi_c, tr.wo, tr.falloff_c, wide, tr.srow)  # (N, V, C)
            top = score.topk(TUNING.model.expanded_blocks, -1, sorted=False).indices
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

    def rows(self, idx: Tensor) -> Round:
        """The same round for the texels ``idx`` only (the LM drops texels that have converged); the
        per-entry emitters are not copied: the subset reads its rows ``row``."""
        out = object.__new__(Round)
        vars(out).update(vars(self))
        out.tr, out.row = self.tr.light_rows(idx), self.row[idx]
        out.frame0, out.diffuse = self.frame0[idx], self.diffuse[idx]
        out.widening = None if self.widening is None else self.widening[idx]
        return out

    def rebase(self, omega: Tensor) -> None:
        """Fold the rotation ``omega (N, 3)`` into the round's frame (linearise about it next)."""
        self.frame0 = fold(self.frame0, omega)

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
        return self.bases_in(fold(self.frame0, omega), log_alpha)

    def bases_in(self, frame: Tensor, log_alpha: Tensor) -> tuple[Tensor, Tensor]:
        """``bases`` in the shading frame ``frame (N, 3, 3)`` (the round's start turned)."""
        diffuse = (self.diffuse * frame[:, None, None, 2, :]).sum(-1)
        if not self.specular:
            return diffuse, torch.zeros_like(diffuse)
        alpha = log_alpha.exp()
        spec = specular_basis(frame, self.emitters, self.wo, alpha, self.row, self.widening)
        return diffuse, spec


def residuals(tr: Trace, diffuse: Tensor, spec: Tensor, p: Tensor) -> tuple[Tensor, Tensor]:
    """Normalised residuals ``(N, V, 3)`` and which of them count (censored entries only when the
    prediction falls below the measured lower bound)."""
    pred = p[:, None, P_RHO_D] * diffuse + p[:, None, P_RHO_S] * spec
    r = (pred - tr.y) * tr.inv_sigma
    active = tr.mask & ~(tr.censored & (pred >= tr.y))
    return torch.where(active, r, torch.zeros_like(r)), active


def robust_cost(r: Tensor, c: float) -> Tensor:
    """Cauchy cost per texel from residuals ``(N, V, 3)``."""
    return (0.5 * c * c * torch.log1p((r / c) ** 2)).flatten(1).sum(1)


def fold(frame: Tensor, omega: Tensor) -> Tensor:
    """The frame turned by ``omega`` (shading-frame rotation vector): rows of R^T F."""
    return rotation_from_vector(omega).transpose(-1, -2) @ frame


def parameters(start: Start, dtype: torch.dtype) -> tuple[Tensor, Tensor]:
    """``start`` as the solver's frame ``(N, 3, 3)`` and parameters ``p (N, 11)`` (omega 0), in range."""
    frame = frame_from_normal_tangent(start.normal.to(dtype), start.tangent.to(dtype))
    p = torch.zeros(len(frame), N_PARAMS, dtype=dtype)
    p[:, P_LOGA] = start.alpha.to(dtype).clamp(ALPHA_MIN, ALPHA_MAX).log()
    p[:, P_RHO_D] = start.rho_d.to(dtype).clamp(0, RHO_D_MAX)
    p[:, P_RHO_S] = start.rho_s.to(dtype).clamp(0, RHO_S_MAX)
    return frame, p


def predicted_light(
    obs: Observations, answer: Start, settings: RefineSettings | None = None
) -> tuple[Tensor, Tensor, Tensor]:
    """Eq. 1 at N texels' ``answer`` (taken as it is), as ``refine`` models their entries: each
    entry's unit-albedo diffuse light, its lobe's light (the answer's rho_s times the specular basis)
    and its sensor 1/sigma (``settings.noise``; 0 where masked or clipped), each ``(N, V, 3)``.
    ``obs.footprint``'s slope spread widens the lobe; its albedo blend is left out (the sensor's noise only)."""
    settings = settings or RefineSettings()
    footprint = obs.footprint
    tr = obs._replace(footprint=None if footprint is None else Footprint(footprint.spread, None)).trace(settings.noise)
    frame, p = parameters(answer, tr.y.dtype)
    diffuse, spec = predict(tr, frame, p)
    inv_sigma = torch.where(tr.censored, torch.zeros_like(tr.inv_sigma), tr.inv_sigma)
    return diffuse, p[:, None, P_RHO_S] * spec, inv_sigma


def predict(tr: Trace, frame: Tensor, p: Tensor) -> tuple[Tensor, Tensor]:
    """Unit-albedo diffuse and specular bases ``(N, V, 3)`` of the answer ``frame``, ``p`` (omega 0)."""
    rnd = Round(tr, frame, p[:, P_LOGA], True, rho_s=p[:, P_RHO_S])
    return rnd.bases(torch.zeros_like(p[:, P_OMEGA]), p[:, P_LOGA])


def highlight_share(tr: Trace, frame: Tensor, p: Tensor) -> Tensor:
    """The largest share ``(N,)`` of an entry's pixel that the fitted lobe makes (``TUNING.model.min_specular_share``
    or more: some entry shows it)."""
    d, s = predict(tr, frame, p)
    pred_s = (p[:, None, P_RHO_S] * s).sum(-1)
    pred = (p[:, None, P_RHO_D] * d).sum(-1) + pred_s
    share = torch.where(tr.mask[..., 0], pred_s / pred.clamp_min(1e-12), torch.zeros_like(pred))
    return share.amax(1)
