import torch

from ntp_engine.learn.synthetic import SyntheticConfig, sample_batch, sweep_frames
from ntp_engine.physics.lumitexel import render_lumitexels
from ntp_engine.scanner.device_file import load_scanner


def _batch(seed=0, **kw):
    return sample_batch(load_scanner(), 16, torch.Generator().manual_seed(seed), **kw)


def test_batch_shapes_ranges_and_geometry():
    dev = load_scanner()
    b = _batch(cfg=SyntheticConfig(views_min=4, views_max=12, sweep_fraction=0.0))
    assert b.m_phys.shape == (16, 12, 512, 3) and b.label_specular.shape == (16, 6144)
    assert b.label_diffuse.shape == (16, 384) and b.highlight_ratio.shape == (16, 12)
    lengths = b.length_mask.sum(1)
    assert (lengths >= 4).all() and (lengths <= 12).all()
    assert dev.in_valid_volume(b.position).all()
    wo = torch.nn.functional.normalize(-b.position, dim=-1)
    assert ((wo * b.normal_geo).sum(-1) > 0.3 - 1e-6).all()
    assert (b.normal_geo * b.tangent_geo).sum(-1).abs().max() < 1e-5
    p = b.params
    assert ((p["alpha_x"] >= 0.006) & (p["alpha_x"] <= 0.5)).all() and (p["rho_s"] <= 10).all()
    assert (b.m_phys >= 0).all() and torch.isfinite(b.m_phys).all()
    # the shading normal is n^ perturbed by ~0.15: mostly within 30 deg, never flipped
    assert (p["n_local"][:, 2] > 0.5).all()


def test_labels_are_grayscale_lumitexels_of_the_shading_frame():
    b = _batch(seed=3)
    p = b.params
    d, s = render_lumitexels(
        p["n_local"],
        p["t_local"],
        p["rho_d"].mean(-1, keepdim=True),
        p["rho_s"].mean(-1, keepdim=True),
        p["alpha_x"],
        p["alpha_y"],
    )
    torch.testing.assert_close(b.label_diffuse, d[..., 0])
    torch.testing.assert_close(b.label_specular, s[..., 0])


def test_seeded_and_reproducible():
    a, b, c = _batch(5), _batch(5), _batch(6)
    torch.testing.assert_close(a.m_phys, b.m_phys)
    assert not torch.allclose(a.params["rho_d"], c.params["rho_d"])
    fixed = _batch(1, views=7, cfg=SyntheticConfig(sweep_fraction=0.0))
    assert fixed.length_mask.all() and fixed.m_phys.shape[1] == 7


def _view_spread(b) -> torch.Tensor:
    """Per trace: mean resultant length of the kept views' directions in the geometric frame
    (1 = every view from the same direction)."""
    wo = torch.nn.functional.normalize(-b.position, dim=-1)
    bit = torch.linalg.cross(b.normal_geo, b.tangent_geo, dim=-1)
    local = torch.stack([(wo * b.tangent_geo).sum(-1), (wo * bit).sum(-1), (wo * b.normal_geo).sum(-1)], -1)
    m = b.length_mask[..., None]
    return (local * m).sum(1).norm(dim=-1) / b.length_mask.sum(1).clamp_min(1)


def test_sweep_views_are_correlated_and_grazing_views_masked():
    dev = load_scanner()
    gen = lambda: torch.Generator().manual_seed(2)
    iid = sample_batch(dev, 256, gen(), SyntheticConfig(sweep_fraction=0.0), views=24)
    sweep = sample_batch(dev, 256, gen(), SyntheticConfig(sweep_fraction=1.0, sweep_sigma=(0.1, 0.1)), views=24)
    assert _view_spread(sweep).median() > 0.95 > 0.75 > _view_spread(iid).median()
    wo = torch.nn.functional.normalize(-sweep.position, dim=-1)
    cos = (wo * sweep.normal_geo).sum(-1)
    assert (cos[sweep.length_mask] > 0.3).all() and not sweep.length_mask[cos <= 0.3].any()
    assert (sweep.normal_geo * sweep.tangent_geo).sum(-1).abs().max() < 1e-5
    assert torch.isfinite(sweep.m_phys).all() and (sweep.length_mask.sum(1) > 0).float().mean() > 0.95


def test_sweep_frames_rotate_view_zero_by_sigma():
    g = torch.Generator().manual_seed(0)
    n = torch.nn.functional.normalize(torch.randn(64, 1, 3, generator=g), dim=-1).expand(64, 50, 3)
    t = torch.nn.functional.normalize(torch.linalg.cross(n, torch.randn(64, 50, 3, generator=g), dim=-1), dim=-1)
    t = t[:, :1].expand(64, 50, 3)
    for sigma in (0.0, 0.05, 0.3):
        n2, t2 = sweep_frames(n, t, torch.full((64,), sigma), g)
        angle = torch.acos((n2 * n).sum(-1).clamp(-1, 1))
        # a normal tilts by the two rotation components orthogonal to it: Rayleigh, mean sigma sqrt(pi/2)
        assert abs(float(angle.mean()) - sigma * (torch.pi / 2) ** 0.5) < 0.1 * sigma + 1e-3  # acos near 1 in float32
        torch.testing.assert_close((n2 * t2).sum(-1), torch.zeros(64, 50), atol=1e-5, rtol=0)
