"""Anisotropic GGX BRDF of the paper's appendix (as in the authors' released code).

Convention: directions are unit vectors in the local shading frame (x = t, y = b, z = n), both
pointing away from the surface. f = rho_d/pi + rho_s * D F G / (4 (wi.n)(wo.n)), zero when either
direction is at or below the horizon. D is the anisotropic GGX distribution, G = G1(wi) G1(wo)
the separable Smith term, F Schlick's approximation with F0 = 0.04 (IOR 1.5).

Numerics: G / (4 cos_i cos_o) is evaluated in the cancelled form 1 / ((cos_i + L_i)(cos_o + L_o)),
L_v = |(ax vx, ay vy, vz)|, whose denominator is >= ax*ay > 0, so neither value nor gradient
divides by a vanishing cosine. Masked-out branches are kept finite so that ``torch.where`` never
passes NaN gradients. Values and gradients are finite in float32 for alphas in [0.006, 0.5] and
any unit directions, including z = 0 and below the horizon (``ntp bench stability``).
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from .frame import safe_normalize

F0_DIELECTRIC = 0.04  # Schlick F0 of IOR 1.5: ((1.5 - 1) / (1.5 + 1))^2
ALPHA_MIN, ALPHA_MAX = 0.006, 0.5
RHO_D_MAX, RHO_S_MAX = 1.0, 10.0
_TINY = 1e-20


def ggx_ndf(h: Tensor, alpha_x: Tensor, alpha_y: Tensor) -> Tensor:
    """GGX normal distribution D(h) = 1 / (pi ax ay |(hx/ax, hy/ay, hz)|^4), ``(...)``.

    ``h (..., 3)`` unit half vector in the local frame; per steradian of h; integrates to 1
    against (h.n) over the hemisphere. Not masked: callers zero h_z <= 0.
    """
    q = (h[..., 0] / alpha_x) ** 2 + (h[..., 1] / alpha_y) ** 2 + h[..., 2] ** 2
    return 1.0 / (math.pi * alpha_x * alpha_y * q * q)


def smith_lambda_norm(v: Tensor, alpha_x: Tensor, alpha_y: Tensor) -> Tensor:
    """|(ax vx, ay vy, vz)| for ``v (..., 3)``; the building block of G1, ``(...)``."""
    sq = (alpha_x * v[..., 0]) ** 2 + (alpha_y * v[..., 1]) ** 2 + v[..., 2] ** 2
    return torch.sqrt(sq.clamp_min(_TINY))


def smith_g1(v: Tensor, alpha_x: Tensor, alpha_y: Tensor) -> Tensor:
    """Separable Smith masking G1(v) = 2 vz / (vz + |(ax vx, ay vy, vz)|), 0 for vz <= 0."""
    vz = v[..., 2].clamp_min(0.0)
    return 2.0 * vz / (vz + smith_lambda_norm(v, alpha_x, alpha_y))


def fresnel_schlick(cos_theta: Tensor, f0: float | Tensor = F0_DIELECTRIC, f90: float | Tensor = 1.0) -> Tensor:
    """Schlick's Fresnel F0 + (F90 - F0)(1 - cos)^5 (F90 = 1: the BRDF's); ``cos_theta`` is clamped
    to [0, 1]."""
    m = 1.0 - cos_theta.clamp(0.0, 1.0)
    m2 = m * m
    return f0 + (f90 - f0) * (m2 * m2 * m)


def bounded_f90(rho_s: Tensor) -> Tensor:
    """F90 = min(1, 1 / rho_s): Schlick's F with it keeps rho_s F <= 1, so the lobe reflects at most
    all the light at grazing w_i.h, where the BRDF's F90 = 1 makes a rho_s = 10 lobe reflect 10x
    the light. The two differ only where w_i.h < 0.9 for rho_s > 1 (by < 2.5e-4 of F0 above):
    never for the scanner's own light, whose emitters sit beside the camera, only for light
    bounced onto the object (``refine.support_light``; the Cycles scanner renders it so)."""
    return 1.0 / rho_s.clamp_min(1.0)


def half_vector(wi: Tensor, wo: Tensor) -> Tensor:
    """Unit half vector of wi and wo ``(..., 3)``; +z where wi = -wo (only below the horizon)."""
    return safe_normalize(wi + wo)


def ggx_specular(
    wi: Tensor, wo: Tensor, alpha_x: Tensor, alpha_y: Tensor, f0: float | Tensor = F0_DIELECTRIC
) -> Tensor:
    """Specular lobe D F G / (4 cos_i cos_o) for rho_s = 1, ``(...)``; 0 below either horizon.

    ``f0 = 1`` gives F = 1 (no Fresnel), e.g. to compare with renderers whose GGX has none.
    """
    iz, oz = wi[..., 2], wo[..., 2]
    h = half_vector(wi, wo)
    d = ggx_ndf(h, alpha_x, alpha_y)
    f = fresnel_schlick((wi * h).sum(-1), f0)
    denom = (iz.clamp_min(0.0) + smith_lambda_norm(wi, alpha_x, alpha_y)) * (
        oz.clamp_min(0.0) + smith_lambda_norm(wo, alpha_x, alpha_y)
    )
    value = d * f / denom  # finite everywhere, so masking by a product is NaN-free
    return value * ((iz > 0) & (oz > 0)).to(value.dtype)


def ggx(
    wi: Tensor,
    wo: Tensor,
    rho_d: Tensor,
    rho_s: Tensor,
    alpha_x: Tensor,
    alpha_y: Tensor,
    f0: float | Tensor = F0_DIELECTRIC,
) -> Tensor:
    """Full BRDF f (1/sr). wi, wo ``(..., 3)``; rho_d, rho_s ``(..., C)``; alphas ``(...)``.

    Returns ``(..., C)`` (broadcast of all inputs); zero where wi_z <= 0 or wo_z <= 0.
    """
    spec = ggx_specular(wi, wo, alpha_x, alpha_y, f0)
    above = ((wi[..., 2] > 0) & (wo[..., 2] > 0)).unsqueeze(-1).to(spec.dtype)
    return (rho_d / math.pi) * above + rho_s * spec.unsqueeze(-1)
