import pytest
import torch

from ntp_engine.learn.network import NetworkConfig, TraceNet, lumitexel_loss
from ntp_engine.learn.synthetic import SyntheticConfig, sample_batch
from ntp_engine.learn.train import batch_loss
from ntp_engine.physics.confidence import confidence_from_ratios
from ntp_engine.scanner.device_file import load_scanner


def _net(**kw):
    torch.manual_seed(0)
    return TraceNet(NetworkConfig(preset="small", **kw), load_scanner())


def test_masked_pooling_ignores_order_and_padding():
    net = _net().eval()
    gen = torch.Generator().manual_seed(0)
    x = torch.randn(3, 10, 12, generator=gen)
    mask = torch.ones(3, 10, dtype=torch.bool)
    d0, s0 = net(x, mask)
    perm = torch.randperm(10, generator=gen)
    d1, s1 = net(x[:, perm], mask)
    torch.testing.assert_close(d0, d1)
    torch.testing.assert_close(s0, s1)
    # padding with huge garbage that would win an unmasked max
    pad = torch.full((3, 6, 12), 1e6)
    d2, s2 = net(torch.cat([x, pad], 1), torch.cat([mask, torch.zeros(3, 6, dtype=torch.bool)], 1))
    torch.testing.assert_close(d0, d2)
    torch.testing.assert_close(s0, s2)
    # an empty trace pools to zeros (finite output, no -inf)
    d3, s3 = net(x[:1], torch.zeros(1, 10, dtype=torch.bool))
    assert torch.isfinite(d3).all() and torch.isfinite(s3).all()


def test_gradients_reach_the_pattern_unless_frozen():
    dev = load_scanner()
    batch = sample_batch(dev, 8, torch.Generator().manual_seed(1), SyntheticConfig(views_max=16))
    net = _net()
    loss, _, _, valid = batch_loss(net, batch, torch.Generator().manual_seed(2))
    loss.backward()
    g = net.pattern_logits.grad
    assert valid.any() and torch.isfinite(g).all() and g.abs().sum() > 0
    frozen = _net(frozen_pattern="full_on")
    assert not frozen.pattern_logits.requires_grad
    assert torch.allclose(frozen.pattern(), torch.ones(512, 3), atol=1e-5)
    point = _net(frozen_pattern="point").pattern()
    assert int((point > 0.5).any(1).sum()) == 1


def test_measure_quantises_and_applies_the_validity_range():
    net = _net(frozen_pattern="full_on")
    m = torch.zeros(1, 4, 512, 3)
    # one view per case: too dark, fine, fine, saturated
    levels = torch.tensor([10.0, 100.0, 200.0, 250.0]) / 255 / float(net.gain) / 512
    m[0] = levels[:, None, None]
    pixel, valid = net.measure(m, torch.ones(1, 4, dtype=torch.bool), noise=False)
    assert valid.tolist() == [[False, True, True, False]]
    codes = pixel * 255
    torch.testing.assert_close(codes, codes.round(), atol=1e-3, rtol=0)


def test_a_pattern_dimmer_than_the_exposure_limit_gives_darker_pixels():
    full_net, point_net = _net(frozen_pattern="full_on"), _net(frozen_pattern="point")
    # one LED of 512 is exposed only max_exposure (4) times longer than full-on
    assert point_net.exposure() == pytest.approx(4 * full_net.exposure(), rel=1e-4)
    m = torch.full((1, 1, 512, 3), 200 / 255 / float(full_net.gain) / 512)  # code 200 under full-on
    ones = torch.ones(1, 1, dtype=torch.bool)
    (full, ok_full), (point, ok_point) = (n.measure(m, ones, noise=False) for n in (full_net, point_net))
    assert torch.allclose(full * 255, torch.full_like(full, 200.0), atol=0.5) and ok_full.all()
    assert float((point * 255).max()) <= 2.0 and not ok_point.any()  # 128x darker: no valid view


def test_traces_left_without_a_valid_view_still_count_in_the_loss():
    dev = load_scanner()
    batch = sample_batch(dev, 16, torch.Generator().manual_seed(3), SyntheticConfig(views_min=4, views_max=8))
    net = _net(frozen_pattern="point").eval()
    _, ld, _, valid = batch_loss(net, batch, torch.Generator().manual_seed(4))
    empty = ~valid.any(1)
    assert empty.any()
    with torch.no_grad():  # an empty trace is answered from the pooled zeros (the prior) and scored
        prior_d, _ = net(torch.zeros(1, 1, 12), torch.zeros(1, 1, dtype=torch.bool))
    err_empty = ((prior_d - batch.label_diffuse[empty]) ** 2).sum(-1).sum()
    assert float(ld.detach()) * len(valid) >= float(err_empty) - 1e-3


def test_confidence_respects_valid_views():
    ratio = torch.tensor([[0.9, 0.1], [0.0, 0.0]])
    assert confidence_from_ratios(ratio).tolist() == [1.0, 0.0]
    assert torch.allclose(
        confidence_from_ratios(ratio, torch.tensor([[False, True], [True, True]])), torch.tensor([0.2, 0.0])
    )


def test_loss_is_eq5():
    pd, ps = torch.zeros(2, 384), torch.zeros(2, 6144)
    ld, ls = torch.ones(2, 384), torch.full((2, 6144), torch.e - 1)
    total, d, s = lumitexel_loss(pd, ps, ld, ls, torch.tensor([1.0, 0.0]))
    assert float(d) == 384 and abs(float(s) - 6144 / 2) < 1e-2 and abs(float(total) - (384 + 0.01 * 3072)) < 1e-3


def test_factorised_batch_measures_like_the_full_physical_lumitexel():
    from ntp_engine.physics.frame import frame_from_normal_tangent
    from ntp_engine.physics.measurement import physical_lumitexel

    dev = load_scanner()
    b = sample_batch(
        dev, 4, torch.Generator().manual_seed(6), SyntheticConfig(views_min=5, views_max=5, roughness_jitter=0.0)
    )
    net = _net()
    p1, v1 = net.measure_batch(b, noise=False)
    p2, v2 = net.measure(b.m_phys, b.length_mask, noise=False)
    torch.testing.assert_close(p1, p2)
    assert torch.equal(v1, v2)
    # the stored terms are Eq. 1 for the true per-view frames
    geo = frame_from_normal_tangent(b.normal_geo, b.tangent_geo)
    n_cam = (geo * b.params["n_local"][:, None, :, None]).sum(-2)
    t_cam = (geo * b.params["t_local"][:, None, :, None]).sum(-2)
    ax = b.params["alpha_x"][:, None].expand(4, 5)
    ay = b.params["alpha_y"][:, None].expand(4, 5)
    ref = physical_lumitexel(dev, b.position, n_cam, t_cam, b.rho_d_view, b.rho_s_view, ax, ay)
    torch.testing.assert_close(b.m_phys, ref, rtol=2e-4, atol=1e-6)


def test_chunked_linear_is_linear_and_the_same_bits_with_any_thread_count():
    from ntp_engine.learn.network import ChunkedLinear

    torch.manual_seed(0)
    layer = ChunkedLinear(1024, 128)  # the compressed specular head's shape, which BLAS splits by threads
    plain = torch.nn.Linear(1024, 128)
    plain.load_state_dict(layer.state_dict())
    x = torch.randn(2048, 1024)
    threads = torch.get_num_threads()
    try:
        with torch.no_grad():
            torch.set_num_threads(1)
            one = layer(x)
            torch.set_num_threads(2)
            two = layer(x)
            torch.testing.assert_close(two, plain(x), rtol=1e-5, atol=1e-5)
    finally:
        torch.set_num_threads(threads)
    assert torch.equal(one, two)
    assert layer(x[:3, None]).shape == (3, 1, 128)  # any leading shape
