import math

import numpy as np
import pytest
import torch
from scipy.optimize import lsq_linear

from ntp_engine.device import Device
from ntp_engine.fit import (FALLBACK_ALPHA, FLAG_NONFINITE, FLAG_ZERO, GeometryFit, bounded_ls2, diffuse_normal,
                            fit_albedo, fit_geometry, lumitexel_log_rmse)
from ntp_engine.fit_baseline import fit_geometry_lbfgsb
from ntp_engine.frame import safe_normalize
from ntp_engine.lumitexel import diffuse_lumitexel, specular_lumitexel
from ntp_engine.synthetic import SyntheticConfig, _random_orthogonal, sample_batch, sample_brdfs


def _lobes(n_tex=256, seed=0, tilt=0.15):
    g = torch.Generator().manual_seed(seed)
    p = sample_brdfs(n_tex, g)
    z = torch.zeros(n_tex, 3)
    z[:, 2] = 1
    n = safe_normalize(z + _random_orthogonal(z, g) * (tilt * torch.randn(n_tex, 1, generator=g)))
    t = _random_orthogonal(n, g)
    rho = p["rho_s"].mean(-1)
    m = specular_lumitexel(n, t, rho[:, None], p["alpha_x"], p["alpha_y"])[..., 0]
    return m, n, t, p["alpha_x"], p["alpha_y"], rho


def _angle(a, b):
    return torch.rad2deg(torch.acos((a * b).sum(-1).clamp(-1, 1)))


def test_exact_lumitexels_are_recovered():
    m, n, t, ax, ay, rho = _lobes()
    f = fit_geometry(m, with_error=True)
    assert (f.flags == 0).all()
    assert _angle(f.normal, n).quantile(0.99) < 0.1
    hi, lo = torch.maximum(ax, ay), torch.minimum(ax, ay)
    assert (f.alpha_x.log() - hi.log()).abs().median() < 1e-3
    assert (f.alpha_y.log() - lo.log()).abs().median() < 1e-3
    assert f.log_rmse.mean() < 1e-3
    aniso = hi > 2 * lo
    t_true = torch.where((ay > ax)[:, None], torch.linalg.cross(n, t, dim=-1), t)
    tan_err = torch.rad2deg(torch.acos((f.tangent[aniso] * t_true[aniso]).sum(-1).abs().clamp(0, 1)))
    assert tan_err.median() < 0.5


def test_canonical_output_under_the_models_symmetries():
    m, n, t, ax, ay, rho = _lobes(32, seed=1)
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
    assert _angle(f.normal, n).max() < 0.5
    assert ((f.alpha_x >= 0.006) & (f.alpha_x <= 0.5)).all()
    assert f.log_rmse.max() < 0.02


def test_grazing_normals_stay_finite_and_close():
    tilt = math.radians(65)
    n = torch.tensor([[math.sin(tilt), 0.0, math.cos(tilt)], [0.0, math.sin(tilt), math.cos(tilt)]])
    t = torch.tensor([[math.cos(tilt), 0.0, -math.sin(tilt)], [1.0, 0.0, 0.0]])
    m = specular_lumitexel(n, t, torch.ones(2, 1), torch.tensor([0.05, 0.2]), torch.tensor([0.05, 0.1]))[..., 0]
    f = fit_geometry(m)
    assert torch.isfinite(f.normal).all() and _angle(f.normal, n).max() < 1.0


def test_zero_saturated_nan_inf_inputs_are_flagged_and_finite():
    m, n, *_ = _lobes(6, seed=2)
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
    assert f.flags[0] & FLAG_ZERO and f.flags[1] & FLAG_NONFINITE and f.flags[2] & FLAG_NONFINITE
    assert float(f.alpha_x[0]) == pytest.approx(FALLBACK_ALPHA) and float(f.rho_s[0]) == 0.0
    assert _angle(f.normal[:3], n[:3]).max() < 1.0  # the fallback normal is the diffuse one
    assert ((f.alpha_x >= 0.006) & (f.alpha_x <= 0.5)).all()


def test_diffuse_normal_is_exact():
    n = safe_normalize(torch.tensor([[0.3, 0.1, 1.0], [0.0, 0.0, 1.0], [-0.5, 0.4, 0.6]]))
    d = diffuse_lumitexel(n, torch.tensor([[0.2], [0.7], [1.0]]))[..., 0]
    nd, rho = diffuse_normal(d)
    assert _angle(nd, n).max() < 1e-2
    torch.testing.assert_close(rho, torch.tensor([0.2, 0.7, 1.0]), rtol=1e-3, atol=0)


def test_bounded_ls2_matches_scipy():
    rng = np.random.default_rng(0)
    for _ in range(40):
        V = rng.integers(2, 12)
        a, b = rng.random(V), rng.random(V) * rng.choice([0.01, 1, 50])
        truth = rng.uniform([-0.5, -3], [1.5, 14])
        y = truth[0] * a + truth[1] * b + 0.05 * rng.standard_normal(V)
        w = rng.uniform(0.2, 1.0, V)
        ref = lsq_linear(np.stack([a, b], 1) * np.sqrt(w)[:, None], y * np.sqrt(w), bounds=([0, 0], [1, 10]),
                         tol=1e-12).x
        u, v = bounded_ls2(*(torch.tensor(x)[None] for x in (a, b, y, w)), 1.0, 10.0)
        cost = lambda p: np.sum(w * (p[0] * a + p[1] * b - y) ** 2)
        assert cost([float(u), float(v)]) <= cost(ref) + 1e-9


def test_albedo_fit_recovers_rgb_from_the_trace():
    dev = Device.load()
    cfg = SyntheticConfig(views_min=24, views_max=24, albedo_jitter=0.0, roughness_jitter=0.0)
    b = sample_batch(dev, 16, torch.Generator().manual_seed(3), cfg, dtype=torch.float64)
    p = b.params
    pattern = torch.as_tensor(dev.pattern)
    pixels = dev.exposure(pattern) * torch.einsum("bvlc,lc->bvc", b.m_phys, dev.effective_pattern(pattern))
    geo = GeometryFit(p["n_local"], p["t_local"], p["alpha_x"], p["alpha_y"], p["rho_s"].mean(-1),
                      torch.zeros(16, dtype=torch.int64), None)
    mask = b.length_mask.clone()
    mask[:, -3:] = False
    pixels[:, -3:] = 1e6  # junk in masked-out entries must not matter
    rd, rs = fit_albedo(dev, None, pixels, b.position, b.normal_geo, b.tangent_geo, mask, geo)
    torch.testing.assert_close(rd, p["rho_d"], atol=1e-6, rtol=1e-6)
    torch.testing.assert_close(rs, p["rho_s"], atol=1e-5, rtol=1e-5)
    assert ((rd >= 0) & (rd <= 1)).all() and ((rs >= 0) & (rs <= 10)).all()


def test_baseline_fits_exact_lumitexels():
    m, n, t, ax, ay, rho = _lobes(2, seed=4)
    f = fit_geometry_lbfgsb(m)
    assert _angle(f.normal, n).max() < 0.5
    fb = fit_geometry(m)
    assert lumitexel_log_rmse(fb, m).mean() <= lumitexel_log_rmse(f, m).mean() + 1e-4


def test_texels_whose_highlight_was_never_seen_are_flagged_with_the_fallback_lobe():
    from ntp_engine.fit import FLAG_NO_HIGHLIGHT, flag_unseen_highlights

    dev = Device.load(Device.load().source.parent / "point_light.toml")
    light = torch.as_tensor(dev.emitter_positions[0])
    x = torch.tensor([[0.0, 0.0, 0.3]], dtype=torch.float64).expand(2, 3)
    # texel 0: geometric normal = the half vector between light and camera (peak seen);
    # texel 1: tilted 35 deg away, a sharp lobe whose mirror direction misses the only light
    h = torch.nn.functional.normalize(torch.nn.functional.normalize(light - x[0], dim=0)
                                      + torch.nn.functional.normalize(-x[0], dim=0), dim=0)
    away = torch.nn.functional.normalize(h + 0.7 * torch.tensor([1.0, 0, 0], dtype=torch.float64), dim=0)
    n_geo = torch.stack([h, away])[:, None]
    t_geo = torch.nn.functional.normalize(torch.linalg.cross(n_geo, torch.tensor([0, 1.0, 0], dtype=torch.float64)
                                                             .expand_as(n_geo), dim=-1), dim=-1)
    z = torch.tensor([[0.0, 0, 1], [0.0, 0, 1]])
    geo = GeometryFit(z, torch.tensor([[1.0, 0, 0], [1.0, 0, 0]]), torch.tensor([0.02, 0.02]),
                      torch.tensor([0.02, 0.02]), torch.ones(2), torch.zeros(2, dtype=torch.int64), None)
    beta = flag_unseen_highlights(dev, x[:, None], n_geo, t_geo, torch.ones(2, 1, dtype=torch.bool), geo)
    assert float(beta[0]) == pytest.approx(1.0) and float(beta[1]) < 1e-3
    assert geo.flags.tolist() == [0, FLAG_NO_HIGHLIGHT]
    assert geo.alpha_x.tolist() == pytest.approx([0.02, 0.3]) and torch.isfinite(geo.normal).all()


def test_one_pass_highlight_check_and_albedo_equal_the_two_steps():
    import copy

    from ntp_engine.fit import fit_albedo, flag_unseen_highlights, highlights_and_albedo

    dev = Device.load()
    cfg = SyntheticConfig(views_min=12, views_max=12)
    b = sample_batch(dev, 24, torch.Generator().manual_seed(11), cfg, dtype=torch.float64)
    p = b.params
    pattern = torch.as_tensor(dev.pattern)
    pixels = dev.exposure(pattern) * torch.einsum("bvlc,lc->bvc", b.m_phys, dev.effective_pattern(pattern))
    g = GeometryFit(p["n_local"], p["t_local"], p["alpha_x"].clone(), p["alpha_y"].clone(), p["rho_s"].mean(-1),
                    torch.zeros(24, dtype=torch.int64), None)
    g.alpha_x[:8], g.alpha_y[:8] = 0.006, 0.006  # lobes too sharp for the views to have seen: fall back
    mask = b.length_mask.clone()
    mask[:, -2:] = False
    two = copy.deepcopy(g)
    beta2 = flag_unseen_highlights(dev, b.position, b.normal_geo, b.tangent_geo, mask, two)
    rd2, rs2 = fit_albedo(dev, None, pixels, b.position, b.normal_geo, b.tangent_geo, mask, two)
    beta1, rd1, rs1 = highlights_and_albedo(dev, pixels, b.position, b.normal_geo, b.tangent_geo, mask, g)
    assert (two.flags != 0).any() and (two.flags == 0).any()  # both paths exercised
    torch.testing.assert_close(beta1, beta2)
    assert torch.equal(g.flags, two.flags) and torch.equal(g.alpha_x, two.alpha_x)
    torch.testing.assert_close(rd1, rd2)
    torch.testing.assert_close(rs1, rs2)


def test_rho_s_prior_settles_an_ill_conditioned_split():
    from ntp_engine.fit import _albedo_ls

    # two views whose diffuse and specular bases are nearly proportional: 1% noise is enough to
    # send the split anywhere; the prior (the network's lobe, worth one view) settles it
    f64 = dict(dtype=torch.float64)
    bd = torch.ones(1, 2, 3, **f64)
    bs = torch.tensor([[[1.0] * 3, [1.02] * 3]], **f64)
    y = 0.5 * bd + 0.1 * bs + torch.tensor([[[0.01] * 3, [-0.01] * 3]], **f64)  # truth 0.5, 0.1
    mask = torch.ones(1, 2, dtype=torch.bool)
    prior = torch.tensor([0.1], **f64)
    rd0, rs0 = _albedo_ls(bd, bs, y, mask, prior, 0.0)
    rd1, rs1 = _albedo_ls(bd, bs, y, mask, prior, 1.0)
    assert (rs0 - 0.1).abs().max() > 0.09  # the unregularised split is off by ~100%
    assert (rs1 - 0.1).abs().max() < 0.01 and (rd1 - 0.5).abs().max() < 0.01
    # in a trace of 16 well-conditioned views, a prior 5x off moves rho_s by a fraction of its error
    bd16 = torch.ones(1, 16, 3, **f64)
    bs16 = torch.linspace(0.0, 3.0, 16, **f64)[None, :, None].expand(1, 16, 3)
    rd2, rs2 = _albedo_ls(bd16, bs16, 0.5 * bd16 + 0.1 * bs16, torch.ones(1, 16, dtype=torch.bool),
                          torch.tensor([0.5], **f64), 1.0)
    assert (rs2 - 0.1).abs().max() < 0.2 * (0.5 - 0.1) and (rd2 - 0.5).abs().max() < 0.1
