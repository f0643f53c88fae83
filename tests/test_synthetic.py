import torch

from ntp_engine.device import Device
from ntp_engine.lumitexel import render_lumitexels
from ntp_engine.synthetic import SyntheticConfig, sample_batch


def _batch(seed=0, **kw):
    return sample_batch(Device.load(), 16, torch.Generator().manual_seed(seed), **kw)


def test_batch_shapes_ranges_and_geometry():
    dev = Device.load()
    b = _batch(cfg=SyntheticConfig(views_min=4, views_max=12))
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
    d, s = render_lumitexels(p["n_local"], p["t_local"], p["rho_d"].mean(-1, keepdim=True),
                             p["rho_s"].mean(-1, keepdim=True), p["alpha_x"], p["alpha_y"])
    torch.testing.assert_close(b.label_diffuse, d[..., 0])
    torch.testing.assert_close(b.label_specular, s[..., 0])


def test_seeded_and_reproducible():
    a, b, c = _batch(5), _batch(5), _batch(6)
    torch.testing.assert_close(a.m_phys, b.m_phys)
    assert not torch.allclose(a.params["rho_d"], c.params["rho_d"])
    fixed = _batch(1, views=7)
    assert fixed.length_mask.all() and fixed.m_phys.shape[1] == 7
