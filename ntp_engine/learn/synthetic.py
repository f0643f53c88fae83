"""Synthetic training traces (paper §6.5), generated on the fly, seeded, batched on CPU or CUDA.

Convention: a synthetic point has a fixed *geometric* frame (n^, t^) per view, sampled in camera
space (n^ faces the camera with wo.n^ > 0.3, t^ random orthogonal: a random scanner pose), and a
fixed *shading* frame (n, t) expressed in the geometric frame: n is n^ = +z perturbed by a random
orthogonal vector of length ~ N(0, 0.15) (Eq. 4's imprecise geometric normal), t random
orthogonal to n. The same local shading frame is used in every view (a rigid object), so the true
camera-space frame of view j is n_j = F^_j^T n, t_j = F^_j^T t. The views' geometric frames are
i.i.d., or — for ``sweep_fraction`` of the traces — one pose per trace turned by small correlated
rotations (``sweep_frames``), as a hand-held sweep sees a point. The labels are the grayscale
(channel-mean rho) lumitexels in the geometric frame, which is also the network's output frame.

What stays *outside* this module, because it depends on the (learned) pattern: the measurement
B = pattern . m_phys, its noise, 8-bit quantisation and the [32, 224] validity test. The batch
carries the physical lumitexels in factorised form (m_phys(l, c) = A_l rho_d,c / pi + S_l rho_s,c,
``physics.measurement.emitter_terms``; ``TraceBatch.m_phys`` rebuilds the full tensor) and the per-view
highlight ratios for beta.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

from ..physics.brdf import ALPHA_MAX, ALPHA_MIN, RHO_D_MAX, RHO_S_MAX
from ..physics.confidence import view_highlight_ratio
from ..physics.frame import any_tangent, rotation_from_vector, safe_normalize
from ..physics.lumitexel import render_lumitexels
from ..physics.measurement import emitter_terms
from ..scanner.scanner import Scanner


@dataclass
class SyntheticConfig:
    """How synthetic traces are drawn (trace lengths, frames, jitter, sweeps)."""

    views_min: int = 16  # trace length is uniform in [views_min, views_max]
    views_max: int = 64
    normal_sigma: float = 0.15  # geometric-normal perturbation (Eq. 4)
    albedo_jitter: float = 0.10  # per-view multiplicative N(1, sigma) on each rho channel
    roughness_jitter: float = 0.15  # per-view multiplicative N(1, sigma) on alphas
    min_cos_view: float = 0.3  # wo . n^ > 0.3, the pipeline's grazing test
    rho_s_max: float = RHO_S_MAX
    # a hand-held sweep sees a point from correlated directions (DESIGN: docs/network.md): this
    # fraction of traces rotates one scanner pose per trace by a random rotation per view whose
    # rotation vector is N(0, sigma^2 I), sigma log-uniform in sweep_sigma (radians)
    sweep_fraction: float = 0.5
    sweep_sigma: tuple[float, float] = (0.05, 0.6)


@dataclass
class TraceBatch:
    """A batch of B synthetic points with V (padded) views each."""

    terms_diffuse: Tensor  # (B, V, L) A_l of the factorised Eq. 1 (measurement.emitter_terms)
    terms_specular: Tensor  # (B, V, L) S_l
    rho_d_view: Tensor  # (B, V, 3) the per-view (jittered) albedos
    rho_s_view: Tensor  # (B, V, 3)
    position: Tensor  # (B, V, 3) camera space, m
    normal_geo: Tensor  # (B, V, 3) n^ in camera space
    tangent_geo: Tensor  # (B, V, 3) t^ in camera space
    length_mask: Tensor  # (B, V) bool: the view is part of the trace
    highlight_ratio: Tensor  # (B, V) Eq. 6 per-view ratio (grayscale rho_s)
    label_diffuse: Tensor  # (B, 384) grayscale diffuse lumitexel in the geometric frame
    label_specular: Tensor  # (B, 6144) grayscale specular lumitexel in the geometric frame
    params: dict[str, Tensor]  # rho_d (B,3), rho_s (B,3), alpha_x, alpha_y (B,), n_local, t_local (B,3)

    @property
    def m_phys(self) -> Tensor:
        """Physical lumitexels ``(B, V, L, 3)`` (unit drive, camera channels), built on demand."""
        return (
            self.terms_diffuse[..., None] * self.rho_d_view[:, :, None, :] / math.pi
            + self.terms_specular[..., None] * self.rho_s_view[:, :, None, :]
        )

    def to(self, device) -> TraceBatch:
        """The batch on torch ``device``."""

        tensors = {k: v.to(device) for k, v in vars(self).items() if isinstance(v, Tensor)}
        return TraceBatch(**tensors, params={k: v.to(device) for k, v in self.params.items()})


def _random_orthogonal(n: Tensor, gen: torch.Generator) -> Tensor:
    """Uniformly random unit vectors orthogonal to unit ``n (..., 3)``."""
    t0 = any_tangent(n)
    b0 = torch.linalg.cross(n, t0, dim=-1)
    phi = 2 * math.pi * torch.rand(n.shape[:-1], generator=gen, dtype=n.dtype, device=n.device)
    return torch.cos(phi)[..., None] * t0 + torch.sin(phi)[..., None] * b0


def _log_uniform(shape, lo, hi, gen, dtype, device) -> Tensor:
    u = torch.rand(shape, generator=gen, dtype=dtype, device=device)
    return torch.exp(math.log(lo) + (math.log(hi) - math.log(lo)) * u)


def sample_brdfs(
    batch: int, gen: torch.Generator, dtype=torch.float32, device=None, rho_s_max: float = RHO_S_MAX
) -> dict[str, Tensor]:
    """rho_d ~ U[0,1]^3, rho_s ~ U[0, rho_s_max]^3, alphas log-uniform in [0.006, 0.5]."""
    kw = dict(generator=gen, dtype=dtype, device=device)
    return {
        "rho_d": RHO_D_MAX * torch.rand(batch, 3, **kw),
        "rho_s": rho_s_max * torch.rand(batch, 3, **kw),
        "alpha_x": _log_uniform((batch,), ALPHA_MIN, ALPHA_MAX, gen, dtype, device),
        "alpha_y": _log_uniform((batch,), ALPHA_MIN, ALPHA_MAX, gen, dtype, device),
    }


def sample_positions(scanner: Scanner, shape, gen, dtype, device) -> Tensor:
    """Uniform points ``shape + (3,)`` in the scanner's valid box (camera space)."""
    u = torch.rand(*shape, 3, generator=gen, dtype=dtype, device=device) - 0.5
    size = torch.as_tensor(scanner.valid_size, dtype=dtype, device=device)
    axes = torch.as_tensor(scanner.valid_axes, dtype=dtype, device=device)
    centre = torch.as_tensor(scanner.valid_center, dtype=dtype, device=device)
    return centre + (u * size) @ axes


def sample_visible_normals(x: Tensor, min_cos: float, gen: torch.Generator) -> Tensor:
    """Unit normals uniform in solid angle over {n : n . wo > min_cos}, wo = -x/|x| (towards camera)."""
    wo = safe_normalize(-x)
    u = torch.rand(x.shape[:-1], generator=gen, dtype=x.dtype, device=x.device)
    cos = min_cos + (1 - min_cos) * u  # uniform in cos = uniform in solid angle
    sin = torch.sqrt((1 - cos * cos).clamp_min(0))
    side = _random_orthogonal(wo, gen)
    return cos[..., None] * wo + sin[..., None] * side


def sweep_frames(n_geo: Tensor, t_geo: Tensor, sigma: Tensor, gen: torch.Generator) -> tuple[Tensor, Tensor]:
    """Geometric frames of a hand-held sweep: view 0's frame ``n_geo, t_geo (B, V, 3)`` rotated per
    view by a rotation vector ~ N(0, sigma^2 I), ``sigma (B,)`` radians (camera space). Normal and
    tangent turn together (the scanner's roll is correlated too). Views may leave the visible cone:
    the caller masks them as the pipeline's grazing test would."""
    B, V, _ = n_geo.shape
    r = sigma[:, None, None] * torch.randn(B, V, 3, generator=gen, dtype=n_geo.dtype, device=n_geo.device)
    rot = rotation_from_vector(r)
    return (rot @ n_geo[:, :1, :, None])[..., 0], (rot @ t_geo[:, :1, :, None])[..., 0]


def sample_batch(
    scanner: Scanner,
    batch: int,
    gen: torch.Generator,
    cfg: SyntheticConfig | None = None,
    dtype=torch.float32,
    device=None,
    views: int | None = None,
) -> TraceBatch:
    """One batch of synthetic traces. ``views`` fixes every trace's length (else random per trace)."""
    cfg = cfg or SyntheticConfig()
    kw = dict(generator=gen, dtype=dtype, device=device)
    V = views or cfg.views_max
    p = sample_brdfs(batch, gen, dtype, device, cfg.rho_s_max)

    # shading frame in the geometric (lumitexel) frame, shared by all views
    z = torch.zeros(batch, 3, dtype=dtype, device=device)
    z[:, 2] = 1.0
    offset = _random_orthogonal(z, gen) * (cfg.normal_sigma * torch.randn(batch, 1, **kw))
    n_local = safe_normalize(z + offset)
    t_local = _random_orthogonal(n_local, gen)
    p["n_local"], p["t_local"] = n_local, t_local

    # per view: position, geometric frame (a random scanner pose), true frame
    x = sample_positions(scanner, (batch, V), gen, dtype, device)
    n_geo = sample_visible_normals(x, cfg.min_cos_view, gen)
    t_geo = _random_orthogonal(n_geo, gen)
    seen = torch.ones(batch, V, dtype=torch.bool, device=device)
    if cfg.sweep_fraction > 0:
        sweep = torch.rand(batch, generator=gen, dtype=dtype, device=device) < cfg.sweep_fraction
        sigma = _log_uniform((batch,), *cfg.sweep_sigma, gen, dtype, device)
        n_sw, t_sw = sweep_frames(n_geo, t_geo, sigma, gen)
        n_geo = torch.where(sweep[:, None, None], n_sw, n_geo)
        t_geo = torch.where(sweep[:, None, None], t_sw, t_geo)
        seen = (safe_normalize(-x) * n_geo).sum(-1) > cfg.min_cos_view
    b_geo = torch.linalg.cross(n_geo, t_geo, dim=-1)
    geo = torch.stack([t_geo, b_geo, n_geo], dim=-2)  # (B, V, 3, 3) rows
    n_cam = (geo * n_local[:, None, :, None]).sum(-2)
    t_cam = (geo * t_local[:, None, :, None]).sum(-2)

    # per-view material jitter (calibration and model error), clamped to the model's ranges
    def jit(s, shape):
        return 1 + s * torch.randn(*shape, **kw)

    rho_d = (p["rho_d"][:, None] * jit(cfg.albedo_jitter, (batch, V, 3))).clamp(0, RHO_D_MAX)
    rho_s = (p["rho_s"][:, None] * jit(cfg.albedo_jitter, (batch, V, 3))).clamp(0, cfg.rho_s_max)
    ax = (p["alpha_x"][:, None] * jit(cfg.roughness_jitter, (batch, V))).clamp(ALPHA_MIN, ALPHA_MAX)
    ay = (p["alpha_y"][:, None] * jit(cfg.roughness_jitter, (batch, V))).clamp(ALPHA_MIN, ALPHA_MAX)
    a_l, s_l = emitter_terms(scanner, x, n_cam, t_cam, ax, ay)
    ratio = view_highlight_ratio(scanner, x, n_cam, t_cam, p["alpha_x"], p["alpha_y"], p["rho_s"].mean(-1))

    if views is None:
        lengths = torch.randint(cfg.views_min, cfg.views_max + 1, (batch,), generator=gen, device=device)
    else:
        lengths = torch.full((batch,), V, device=device)
    mask = (torch.arange(V, device=device)[None, :] < lengths[:, None]) & seen

    d, s = render_lumitexels(
        n_local,
        t_local,
        p["rho_d"].mean(-1, keepdim=True),
        p["rho_s"].mean(-1, keepdim=True),
        p["alpha_x"],
        p["alpha_y"],
    )
    return TraceBatch(
        terms_diffuse=a_l,
        terms_specular=s_l,
        rho_d_view=rho_d,
        rho_s_view=rho_s,
        position=x,
        normal_geo=n_geo,
        tangent_geo=t_geo,
        length_mask=mask,
        highlight_ratio=ratio,
        label_diffuse=d[..., 0],
        label_specular=s[..., 0],
        params=p,
    )
