"""The GGX BRDF against independent facts: normalisation, reciprocity, energy, closed forms."""

import functools
import math

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.special import roots_legendre

from ntp_engine.physics.brdf import (
    ALPHA_MAX,
    ALPHA_MIN,
    F0_DIELECTRIC,
    bounded_f90,
    fresnel_schlick,
    ggx,
    ggx_ndf,
    ggx_specular,
    smith_g1,
)
from ntp_engine.physics.frame import reflect

F64 = torch.float64


@functools.lru_cache(maxsize=4)
def _gauss_legendre(n: int):
    return roots_legendre(n)


def _half_vector_quadrature(c: float, n_u: int = 1200, n_phi: int = 4096):
    """Half vectors over the hemisphere with solid-angle weights, dense near the pole.

    tan(theta) = c u / (1 - u), u in [0, 1) by Gauss-Legendre; phi uniform (periodic)."""
    u, wu = _gauss_legendre(n_u)
    u, wu = 0.5 * (u + 1), 0.5 * wu
    s = c * u / (1 - u)
    theta = np.arctan(s)
    dtheta = c / (1 - u) ** 2 / (1 + s * s)
    phi = (np.arange(n_phi) + 0.5) * 2 * np.pi / n_phi
    th, ph = np.meshgrid(theta, phi, indexing="ij")
    w = (wu * dtheta * np.sin(theta))[:, None] * np.full(n_phi, 2 * np.pi / n_phi)[None, :]
    h = np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)], -1)
    return torch.tensor(h.reshape(-1, 3)), torch.tensor(w.reshape(-1))


@pytest.mark.parametrize("ax,ay", [(0.006, 0.006), (0.05, 0.05), (0.5, 0.5), (0.006, 0.05), (0.5, 0.1), (0.006, 0.5)])
def test_ndf_integrates_to_one(ax, ay):
    h, w = _half_vector_quadrature(min(ax, ay))
    d = ggx_ndf(h, torch.tensor(ax, dtype=F64), torch.tensor(ay, dtype=F64))
    assert float((d * h[:, 2] * w).sum()) == pytest.approx(1.0, abs=2e-3)


def _random_dirs(n, gen, upper=True):
    v = torch.nn.functional.normalize(torch.randn(n, 3, generator=gen, dtype=F64), dim=-1)
    if upper:
        v[:, 2] = v[:, 2].abs()
    return v


def test_reciprocity():
    gen = torch.Generator().manual_seed(1)
    wi, wo = _random_dirs(10000, gen), _random_dirs(10000, gen)
    a = torch.exp(torch.empty(2, 10000, dtype=F64).uniform_(math.log(ALPHA_MIN), math.log(ALPHA_MAX), generator=gen))
    rd, rs = torch.rand(2, 10000, 3, generator=gen, dtype=F64)
    f1 = ggx(wi, wo, rd, 10 * rs, a[0], a[1])
    f2 = ggx(wo, wi, rd, 10 * rs, a[0], a[1])
    torch.testing.assert_close(f1, f2, rtol=1e-12, atol=0)


def _specular_albedo(wo, ax, ay, f0):
    """int f_spec cos_i d(wi), integrated over half vectors: d(wi) = 4 (wo.h) d(h)."""
    h, w = _half_vector_quadrature(min(ax, ay), n_u=800, n_phi=2048)
    wo_b = wo.expand_as(h)
    wi = reflect(wo_b, h)
    f = ggx_specular(wi, wo_b, torch.tensor(ax, dtype=F64), torch.tensor(ay, dtype=F64), f0)
    jac = 4 * (wo_b * h).sum(-1).clamp_min(0)
    return float((f * wi[:, 2].clamp_min(0) * jac * w).sum())


@pytest.mark.parametrize("theta_o", [0.0, 40.0, 75.0, 88.0])
@pytest.mark.parametrize("ax,ay", [(0.006, 0.006), (0.1, 0.3), (0.5, 0.5)])
def test_specular_directional_albedo_at_most_one(theta_o, ax, ay):
    t = math.radians(theta_o)
    wo = torch.tensor([math.sin(t), 0.0, math.cos(t)], dtype=F64)
    no_fresnel = _specular_albedo(wo, ax, ay, f0=1.0)
    assert no_fresnel <= 1.0 + 2e-3
    assert _specular_albedo(wo, ax, ay, F0_DIELECTRIC) <= no_fresnel
    if theta_o == 0.0 and ax < 0.05:
        # a smooth microfacet surface seen head-on loses almost nothing to shadowing/masking
        assert no_fresnel > 0.99


def test_closed_form_at_normal_incidence():
    n = torch.tensor([0.0, 0.0, 1.0], dtype=F64)
    ax, ay = torch.tensor(0.2, dtype=F64), torch.tensor(0.05, dtype=F64)
    f = ggx(n, n, torch.tensor([0.3], dtype=F64), torch.tensor([2.0], dtype=F64), ax, ay)
    # D(n) = 1/(pi ax ay), F = F0, G = 1, 4 cos cos = 4
    expect = 0.3 / math.pi + 2.0 * 0.04 / (math.pi * 0.2 * 0.05) / 4
    assert float(f) == pytest.approx(expect, rel=1e-12)


def test_components_closed_form():
    v = torch.tensor([math.sin(0.7), 0.0, math.cos(0.7)], dtype=F64)
    a = torch.tensor(0.3, dtype=F64)
    # isotropic Smith G1 = 2 / (1 + sqrt(1 + a^2 tan^2))
    assert float(smith_g1(v, a, a)) == pytest.approx(2 / (1 + math.sqrt(1 + 0.09 * math.tan(0.7) ** 2)))
    assert float(fresnel_schlick(torch.tensor(0.5, dtype=F64))) == pytest.approx(0.04 + 0.96 * 0.5**5)
    assert float(smith_g1(torch.tensor([1.0, 0, 0], dtype=F64), a, a)) == 0.0


def test_the_bounded_fresnel_never_reflects_more_than_all_the_light():
    """rho_s F with F90 = bounded_f90(rho_s) is at most 1 at every w_i.h, is the BRDF's F for rho_s
    <= 1, and differs from it by < 2.5e-4 of F0 where the scanner's own light arrives (w_i.h >= 0.9)."""
    c = torch.linspace(0, 1, 101, dtype=F64)[:, None]
    rho_s = torch.tensor([0.0, 0.08, 0.5, 1.0, 2.0, 5.0, 10.0], dtype=F64)
    bounded = fresnel_schlick(c, 0.04, bounded_f90(rho_s))
    assert float((rho_s * bounded).max()) <= 1 + 1e-12
    assert float((rho_s * fresnel_schlick(c)).max()) == pytest.approx(10.0)  # the BRDF's: 10x
    low = rho_s <= 1
    torch.testing.assert_close(bounded[:, low], fresnel_schlick(c).expand(-1, int(low.sum())), rtol=0, atol=0)
    near = c[:, 0] >= 0.9
    assert float((fresnel_schlick(c[near]) - bounded[near]).abs().max()) < 2.5e-4 * 0.04


def test_anisotropy_orientation():
    """alpha_x > alpha_y: the lobe reaches further along the tangent (x) than the bitangent."""
    ax, ay = torch.tensor(0.3, dtype=F64), torch.tensor(0.03, dtype=F64)
    wo = torch.tensor([0.0, 0.0, 1.0], dtype=F64)
    tilt = math.radians(10)
    along_t = torch.tensor([math.sin(tilt), 0, math.cos(tilt)], dtype=F64)
    along_b = torch.tensor([0, math.sin(tilt), math.cos(tilt)], dtype=F64)
    assert float(ggx_specular(along_t, wo, ax, ay)) > 50 * float(ggx_specular(along_b, wo, ax, ay))


def test_zero_below_horizon_and_broadcasting():
    wi = torch.tensor([[0.0, 0.6, -0.8], [0.6, 0.0, 0.8], [1.0, 0.0, 0.0]], dtype=F64)
    wo = torch.tensor([0.0, 0.0, 1.0], dtype=F64)
    f = ggx(
        wi,
        wo,
        torch.ones(3, dtype=F64),
        torch.ones(3, dtype=F64),
        torch.tensor(0.1, dtype=F64),
        torch.tensor(0.1, dtype=F64),
    )
    assert f.shape == (3, 3)
    assert (f[0] == 0).all() and (f[2] == 0).all() and (f[1] > 0).all()


def _dir(z: float, phi: float) -> list[float]:
    r = math.sqrt(max(0.0, 1 - z * z))
    return [r * math.cos(phi), r * math.sin(phi), z]


z_values = st.one_of(st.sampled_from([0.0, -0.0, 1.0, -1.0, 1e-7, -1e-7, 1e-30]), st.floats(-1, 1))
alphas = st.one_of(st.sampled_from([ALPHA_MIN, ALPHA_MAX]), st.floats(ALPHA_MIN, ALPHA_MAX))


@settings(max_examples=400, deadline=None)
@given(
    zi=z_values,
    pi_=st.floats(0, 2 * math.pi),
    zo=z_values,
    po=st.floats(0, 2 * math.pi),
    ax=alphas,
    ay=alphas,
    mirror=st.booleans(),
    rho_s=st.floats(0, 10),
)
def test_float32_values_and_gradients_finite(zi, pi_, zo, po, ax, ay, mirror, rho_s):
    wo = torch.tensor(_dir(zo, po), dtype=torch.float32)
    wi = torch.tensor(_dir(zi, pi_), dtype=torch.float32)
    if mirror:  # the exact highlight peak, or wi = -wo when wo lies in the tangent plane
        wi = reflect(wo, torch.tensor([0.0, 0.0, 1.0]))
    leaves = [
        wi.requires_grad_(),
        wo.requires_grad_(),
        torch.tensor([0.5, 0.2, 1.0], requires_grad=True),
        torch.tensor([rho_s] * 3, dtype=torch.float32, requires_grad=True),
        torch.tensor(ax, dtype=torch.float32, requires_grad=True),
        torch.tensor(ay, dtype=torch.float32, requires_grad=True),
    ]
    f = ggx(*leaves)
    assert torch.isfinite(f).all() and (f >= 0).all()
    f.sum().backward()
    for leaf in leaves:
        assert torch.isfinite(leaf.grad).all()
