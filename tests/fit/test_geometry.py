import math

import pytest
import torch
from lobes import angle_deg, exact_lobes

from ntp_engine.fit.flags import TexelFlag
from ntp_engine.fit.geometry import FALLBACK_ALPHA, diffuse_normal, fit_geometry
from ntp_engine.physics.frame import safe_normalize
from ntp_engine.physics.lumitexel import diffuse_lumitexel, specular_lumitexel


def test_exact_lumitexels_are_recovered():
    m, n, t, ax, ay, rho = exact_lobes()
    f = fit_geometry(m, with_error=True)
    assert (f.flags == 0).all()
    assert angle_deg(f.normal, n).quantile(0.99) < 0.1
    hi, lo = torch.maximum(ax, ay), torch.minimum(ax, ay)
    assert (f.alpha_x.log() - hi.log()).abs().median() < 1e-3
    assert (f.alpha_y.log() - lo.log()).abs().median() < 1e-3
    assert f.log_rmse.mean() < 1e-3
    aniso = hi > 2 * lo
    t_true = torch.where((ay > ax)[:, None], torch.linalg.cross(n, t, dim=-1), t)
    tan_err = torch.rad2deg(torch.acos((f.tangent[aniso] * t_true[aniso]).sum(-1).abs().clamp(0, 1)))
    assert tan_err.median() < 0.5


def test_canonical_output_under_the_models_symmetries():
    m, n, t, ax, ay, rho = exact_lobes(32, seed=1)
    b = torch.linalg.cross(n, t, dim=-1)
    m2 = specular_lumitexel(n, b, rho[:, None], ay, ax)[..., 0]  # the same BRDF, other labelling
    f1, f2 = fit_geometry(m), fit_geometry(m2)
    assert (f1.alpha_x >= f1.alpha_y).all()
    assert (f1.normal * f1.tangent).sum(-1).abs().max() < 1e-4
    torch.testing.assert_close(f1.alpha_x, f2.alpha_x, rtol=2e-3, atol=0)
    torch.testing.assert_close(f1.tangent, f2.tangent, atol=5e-3, rtol=0)
    key = torch.where(f1.tangent[:, 0].abs() > 1e-6, f1.tangent[:, 0], f1.tangent[:, 1])
    assert (key >= 0).all()


@pytest.mark.parametrize("alpha", [0.006, 0.5])
def test_alphas_at_the_bounds(alpha):
    n = safe_normalize(torch.tensor([[0.1, -0.05, 1.0]] * 4))
    t = safe_normalize(torch.linalg.cross(n, torch.tensor([[0.0, 1.0, 0.0]] * 4), dim=-1))
    a = torch.full((4,), alpha)
    m = specular_lumitexel(n, t, torch.full((4, 1), 2.0), a, a)[..., 0]
    f = fit_geometry(m, with_error=True)
    assert torch.isfinite(f.normal).all() and (f.flags == 0).all()
    assert angle_deg(f.normal, n).max() < 0.5
    assert ((f.alpha_x >= 0.006) & (f.alpha_x <= 0.5)).all()
    assert f.log_rmse.max() < 0.02


def test_grazing_normals_stay_finite_and_close():
    tilt = math.radians(65)
    n = torch.tensor([[math.sin(tilt), 0.0, math.cos(tilt)], [0.0, math.sin(tilt), math.cos(tilt)]])
    t = torch.tensor([[math.cos(tilt), 0.0, -math.sin(tilt)], [1.0, 0.0, 0.0]])
    m = specular_lumitexel(n, t, torch.ones(2, 1), torch.tensor([0.05, 0.2]), torch.tensor([0.05, 0.1]))[..., 0]
    f = fit_geometry(m)
    assert torch.isfinite(f.normal).all() and angle_deg(f.normal, n).max() < 1.0


def test_zero_saturated_nan_inf_inputs_are_flagged_and_finite():
    m, n, *_ = exact_lobes(6, seed=2)
    m = m.clone()
    m[0] = 0.0
    m[1, 100] = float("nan")
    m[2, 7] = float("inf")
    m[3] = 1e4  # saturated everywhere
    m[4] = m[4].clamp_max(0.05 * float(m[4].max()))  # a clipped lobe
    d = diffuse_lumitexel(n, torch.full((6, 1), 0.5))[..., 0]
    f = fit_geometry(m, diffuse=d)
    for field in ("normal", "tangent", "alpha_x", "alpha_y", "rho_s"):
        assert torch.isfinite(getattr(f, field)).all(), field
    assert f.flags[0] & TexelFlag.ZERO and f.flags[1] & TexelFlag.NONFINITE and f.flags[2] & TexelFlag.NONFINITE
    assert float(f.alpha_x[0]) == pytest.approx(FALLBACK_ALPHA) and float(f.rho_s[0]) == 0.0
    assert angle_deg(f.normal[:3], n[:3]).max() < 1.0  # the fallback normal is the diffuse one
    assert ((f.alpha_x >= 0.006) & (f.alpha_x <= 0.5)).all()


def test_diffuse_normal_is_exact():
    n = safe_normalize(torch.tensor([[0.3, 0.1, 1.0], [0.0, 0.0, 1.0], [-0.5, 0.4, 0.6]]))
    d = diffuse_lumitexel(n, torch.tensor([[0.2], [0.7], [1.0]]))[..., 0]
    nd, rho = diffuse_normal(d)
    assert angle_deg(nd, n).max() < 1e-2
    torch.testing.assert_close(rho, torch.tensor([0.2, 0.7, 1.0]), rtol=1e-3, atol=0)
