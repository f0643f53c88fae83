import numpy as np
import torch
from scipy.optimize import lsq_linear

from ntp_engine.fit.albedo import _albedo_ls, bounded_ls2, fit_albedo, highlights_and_albedo
from ntp_engine.fit.geometry import GeometryFit
from ntp_engine.fit.highlights import flag_unseen_highlights
from ntp_engine.learn.synthetic import SyntheticConfig, sample_batch
from ntp_engine.scanner.device_file import load_scanner


def test_bounded_ls2_matches_scipy():
    rng = np.random.default_rng(0)
    for _ in range(40):
        V = rng.integers(2, 12)
        a, b = rng.random(V), rng.random(V) * rng.choice([0.01, 1, 50])
        truth = rng.uniform([-0.5, -3], [1.5, 14])
        y = truth[0] * a + truth[1] * b + 0.05 * rng.standard_normal(V)
        w = rng.uniform(0.2, 1.0, V)
        ref = lsq_linear(
            np.stack([a, b], 1) * np.sqrt(w)[:, None], y * np.sqrt(w), bounds=([0, 0], [1, 10]), tol=1e-12
        ).x
        u, v = bounded_ls2(*(torch.tensor(x)[None] for x in (a, b, y, w)), 1.0, 10.0)
        cost = lambda p: np.sum(w * (p[0] * a + p[1] * b - y) ** 2)
        assert cost([float(u), float(v)]) <= cost(ref) + 1e-9


def test_bounded_ls2_batches_broadcast_and_an_empty_or_nan_problem_gives_zero():
    rng = np.random.default_rng(1)
    a, b = torch.tensor(rng.random((4, 3, 6))), torch.tensor(rng.random((4, 3, 6)))
    y = 0.4 * a + 2.0 * b
    u, v = bounded_ls2(a, b, y, torch.ones(6, dtype=torch.float64), 1.0, 10.0)  # w broadcast
    assert u.shape == v.shape == (4, 3) and u.dtype == torch.float64
    assert torch.allclose(u, torch.full_like(u, 0.4)) and torch.allclose(v, torch.full_like(v, 2.0))
    w = torch.ones(4, 3, 6, dtype=torch.float64)
    w[0] = 0.0  # no data
    y = y.clone()
    y[1, 0, 2] = float("nan")
    u, v = bounded_ls2(a.float(), b.float(), y.float(), w.float(), 1.0, 10.0)
    assert u.dtype == torch.float32
    assert (u[0] == 0).all() and (v[0] == 0).all() and u[1, 0] == 0 and v[1, 0] == 0
    assert torch.isfinite(u).all() and torch.allclose(u[2:], torch.full_like(u[2:], 0.4))


def test_albedo_fit_recovers_rgb_from_the_trace():
    dev = load_scanner()
    cfg = SyntheticConfig(views_min=24, views_max=24, albedo_jitter=0.0, roughness_jitter=0.0)
    b = sample_batch(dev, 16, torch.Generator().manual_seed(3), cfg, dtype=torch.float64)
    p = b.params
    pattern = torch.as_tensor(dev.pattern)
    pixels = dev.exposure(pattern) * torch.einsum("bvlc,lc->bvc", b.m_phys, dev.effective_pattern(pattern))
    geo = GeometryFit(
        p["n_local"],
        p["t_local"],
        p["alpha_x"],
        p["alpha_y"],
        p["rho_s"].mean(-1),
        torch.zeros(16, dtype=torch.int64),
        None,
    )
    mask = b.length_mask.clone()
    mask[:, -3:] = False
    pixels[:, -3:] = 1e6  # junk in masked-out entries must not matter
    rd, rs = fit_albedo(dev, None, pixels, b.position, b.normal_geo, b.tangent_geo, mask, geo)
    torch.testing.assert_close(rd, p["rho_d"], atol=1e-6, rtol=1e-6)
    torch.testing.assert_close(rs, p["rho_s"], atol=1e-5, rtol=1e-5)
    assert ((rd >= 0) & (rd <= 1)).all() and ((rs >= 0) & (rs <= 10)).all()


def test_one_pass_highlight_check_and_albedo_equal_the_two_steps():
    import copy

    dev = load_scanner()
    cfg = SyntheticConfig(views_min=12, views_max=12)
    b = sample_batch(dev, 24, torch.Generator().manual_seed(11), cfg, dtype=torch.float64)
    p = b.params
    pattern = torch.as_tensor(dev.pattern)
    pixels = dev.exposure(pattern) * torch.einsum("bvlc,lc->bvc", b.m_phys, dev.effective_pattern(pattern))
    g = GeometryFit(
        p["n_local"],
        p["t_local"],
        p["alpha_x"].clone(),
        p["alpha_y"].clone(),
        p["rho_s"].mean(-1),
        torch.zeros(24, dtype=torch.int64),
        None,
    )
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
    rd2, rs2 = _albedo_ls(
        bd16, bs16, 0.5 * bd16 + 0.1 * bs16, torch.ones(1, 16, dtype=torch.bool), torch.tensor([0.5], **f64), 1.0
    )
    assert (rs2 - 0.1).abs().max() < 0.2 * (0.5 - 0.1) and (rd2 - 0.5).abs().max() < 0.1
