"""The compiled data cost and normal equations equal the torch residuals' Cauchy cost and the torch
Jacobian's J^T W J and J^T W r (float64), censored channels counting only while the prediction is
below the clip, masked ones not at all; a NaN parameter gives a NaN cost."""

import math

import pytest
import torch

from ntp_engine.refine.gauss_newton import N_PARAMS, data_cost, normal_equations


def _case(seed: int, specular: bool, N=7, V=6):
    g = torch.Generator().manual_seed(seed)
    d = torch.float64
    diffuse = torch.randn(N, V, 3, 3, generator=g, dtype=d)
    spec = torch.rand(N, V, 3, generator=g, dtype=d) if specular else torch.zeros(0, V, 3, dtype=d)
    ds = torch.randn(N, V, 5, 3, generator=g, dtype=d) if specular else torch.zeros(0, V, 5, 3, dtype=d)
    p = torch.rand(N, N_PARAMS, generator=g, dtype=d)
    y = torch.rand(N, V, 3, generator=g, dtype=d)
    mask = torch.rand(N, V, 3, generator=g) > 0.2
    censored = (torch.rand(N, V, 3, generator=g) > 0.7) & mask
    inv_sigma = torch.where(mask, 10 + 40 * torch.rand(N, V, 3, generator=g, dtype=d), 0.0)
    return diffuse, spec, ds, p, y, inv_sigma, mask, censored


def _reference(diffuse, spec, ds, p, y, inv_sigma, mask, censored, robust):
    """The torch Jacobian (N, V, 3, 11) of the normalised residuals, and their Cauchy weights."""
    N, V = y.shape[:2]
    ch = torch.arange(3)
    s = spec if len(spec) else torch.zeros_like(y)
    dsp = ds if len(ds) else torch.zeros(N, V, 5, 3, dtype=y.dtype)
    rd, rs = p[:, None, 5:8], p[:, None, 8:11]
    pred = rd * diffuse[..., 2] + rs * s
    r = (pred - y) * inv_sigma
    active = mask & ~(censored & (pred >= y))
    dd = torch.zeros(N, V, 5, 3, dtype=y.dtype)
    dd[:, :, 0], dd[:, :, 1] = -diffuse[..., 1], diffuse[..., 0]  # d n / d omega in the shading frame
    J = torch.zeros(N, V, 3, N_PARAMS, dtype=y.dtype)
    J[..., :5] = (rd[:, :, None] * dd + rs[:, :, None] * dsp).transpose(2, 3)
    J[:, :, ch, 5 + ch] = diffuse[..., 2]
    J[:, :, ch, 8 + ch] = s
    J = (J * (inv_sigma * active)[..., None]).reshape(N, -1, N_PARAMS)
    w = (1 / (1 + (r / robust) ** 2)).reshape(N, -1, 1)
    return J.transpose(1, 2) @ (w * J), (J * w).transpose(1, 2) @ r.reshape(N, -1, 1)


@pytest.mark.parametrize("specular", [True, False])
def test_normal_equations_are_the_jacobians(specular):
    case = _case(3, specular)
    H, g = normal_equations(*case, robust=3.0)
    want_H, want_g = _reference(*case, robust=3.0)
    assert H.dtype == g.dtype == torch.float64 and H.shape == (7, N_PARAMS, N_PARAMS)
    torch.testing.assert_close(H, want_H, rtol=1e-10, atol=1e-10)
    torch.testing.assert_close(g, want_g[..., 0], rtol=1e-10, atol=1e-10)
    assert (H[:, 8:, 8:] != 0).any() == specular  # a diffuse-only model: nothing for rho_s
    # float32 inputs: the same sums to float32 rounding
    H32, g32 = normal_equations(*(x.float() if x.is_floating_point() else x for x in case), robust=3.0)
    torch.testing.assert_close(H32, want_H, rtol=1e-4, atol=1e-3 * float(want_H.abs().max()))
    torch.testing.assert_close(g32, want_g[..., 0], rtol=1e-4, atol=1e-3 * float(want_g.abs().max()))


def test_clipped_channels_above_their_prediction_count_and_masked_ones_do_not():
    diffuse, spec, ds, p, y, inv_sigma, mask, censored = _case(4, True, N=1, V=1)
    mask[:], censored[:], inv_sigma[:] = True, True, 20.0
    y[:] = 10.0  # clipped above every prediction: each is a residual like any other
    H, _ = normal_equations(diffuse, spec, ds, p, y, inv_sigma, mask, censored, 3.0)
    assert (H.diagonal(dim1=1, dim2=2)[:, 5:] > 0).all()
    y[:] = -1.0  # the prediction already above the clip: no residual
    H, g = normal_equations(diffuse, spec, ds, p, y, inv_sigma, mask, censored, 3.0)
    assert not H.any() and not g.any()
    H, g = normal_equations(diffuse, spec, ds, p, y, inv_sigma, torch.zeros_like(mask), censored, 3.0)
    assert not H.any() and not g.any()


@pytest.mark.parametrize("specular", [True, False])
def test_data_cost_is_the_cauchy_cost_of_the_counted_residuals(specular):
    diffuse, spec, ds, p, y, inv_sigma, mask, censored = _case(5, specular)
    s = spec if specular else torch.zeros_like(y)
    d = diffuse[..., 2]
    pred = p[:, None, 5:8] * d + p[:, None, 8:11] * s
    active = mask & ~(censored & (pred >= y))
    r = torch.where(active, (pred - y) * inv_sigma, 0.0)
    want = (0.5 * 9.0 * torch.log1p((r / 3.0) ** 2)).flatten(1).sum(1)
    got = data_cost(d, s, p, y, inv_sigma, mask, censored, 3.0)
    assert got.dtype == torch.float64 and (want > 0).all()
    torch.testing.assert_close(got, want, rtol=1e-12, atol=0.0)
    got32 = data_cost(d.float(), s.float(), p.float(), y.float(), inv_sigma.float(), mask, censored, 3.0)
    assert got32.dtype == torch.float32
    torch.testing.assert_close(got32.double(), want, rtol=1e-5, atol=0.0)
    p[0, 5] = math.nan  # a solve gone non-finite: the LM must see it
    assert torch.isnan(data_cost(d, s, p, y, inv_sigma, mask, censored, 3.0)[0])
