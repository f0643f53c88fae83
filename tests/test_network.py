import pytest
import torch

from ntp_engine.device import Device
from ntp_engine.measurement import confidence_from_ratios
from ntp_engine.network import NetworkConfig, TraceNet, lumitexel_loss
from ntp_engine.synthetic import SyntheticConfig, sample_batch
from ntp_engine.train import batch_loss


def _net(**kw):
    torch.manual_seed(0)
    return TraceNet(NetworkConfig(preset="small", **kw), Device.load())


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
    dev = Device.load()
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
    dev = Device.load()
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
    assert torch.allclose(confidence_from_ratios(ratio, torch.tensor([[False, True], [True, True]])),
                          torch.tensor([0.2, 0.0]))


def test_tiny_overfit_drives_the_loss_down():
    dev = Device.load()
    batch = sample_batch(dev, 8, torch.Generator().manual_seed(4), SyntheticConfig(views_min=24, views_max=24))
    net = _net(dropout=0.0)
    opt = torch.optim.Adam(net.parameters(), lr=1e-3)
    losses = []
    for step in range(150):
        loss, _, _, _ = batch_loss(net, batch, torch.Generator().manual_seed(99), noise=False)
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.item())
    assert losses[-1] < 0.1 * losses[0], (losses[0], losses[-1])


def test_loss_is_eq5():
    pd, ps = torch.zeros(2, 384), torch.zeros(2, 6144)
    ld, ls = torch.ones(2, 384), torch.full((2, 6144), torch.e - 1)
    total, d, s = lumitexel_loss(pd, ps, ld, ls, torch.tensor([1.0, 0.0]))
    assert float(d) == 384 and abs(float(s) - 6144 / 2) < 1e-2 and abs(float(total) - (384 + 0.01 * 3072)) < 1e-3


def test_factorised_batch_measures_like_the_full_physical_lumitexel():
    from ntp_engine.frame import frame_from_normal_tangent
    from ntp_engine.measurement import physical_lumitexel

    dev = Device.load()
    b = sample_batch(dev, 4, torch.Generator().manual_seed(6), SyntheticConfig(views_min=5, views_max=5,
                                                                                  roughness_jitter=0.0))
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


def test_pattern_learning_rate_is_its_own_parameter_group(tmp_path):
    from ntp_engine.train import TrainConfig, train

    run = tmp_path / "run"
    tc = dict(steps=2, batch=4, validate_every=2, val_batches=1, views_max=8)
    train(run, NetworkConfig(preset="small"), TrainConfig(pattern_lr=0.05, **tc), progress=False)
    ck = torch.load(run / "checkpoint.pt", weights_only=False)
    assert [g["lr"] for g in ck["optimizer"]["param_groups"]] == [3e-4, 0.05]
    try:  # resuming with another grouping is refused with a clear message
        train(run, NetworkConfig(preset="small"), TrainConfig(**{**tc, "steps": 3}), resume=True, progress=False)
        raise AssertionError("expected SystemExit")
    except SystemExit as err:
        assert "--pattern-lr" in str(err)


def test_resume_matches_optimizer_state_saved_in_another_parameter_order():
    from ntp_engine.train import _match_optimizer_order

    torch.manual_seed(0)
    a, b = torch.nn.Parameter(torch.randn(4, 3)), torch.nn.Parameter(torch.randn(7))
    c = torch.nn.Parameter(torch.randn(4, 3))
    old = torch.optim.Adam([b, a, c], lr=1e-2)  # the pattern-like (7,) tensor first
    (a.sum() * 2 + b.sum() * 3 + c.sum() * 5).backward()
    old.step()
    new = torch.optim.Adam([a, c, b], lr=1e-2)  # ... and last
    new.load_state_dict(_match_optimizer_order(old.state_dict(), new))
    for p in (a, b, c):
        assert torch.equal(new.state[p]["exp_avg"], old.state[p]["exp_avg"])


def test_warm_start_from_a_frozen_full_on_run_measures_the_same_and_learns(tmp_path):
    from ntp_engine.synthetic import sample_batch
    from ntp_engine.train import TrainConfig, train

    tc = dict(batch=4, validate_every=2, val_batches=1, views_max=8)
    src, dst = tmp_path / "full_on", tmp_path / "learned"
    train(src, NetworkConfig(preset="small", frozen_pattern="full_on"), TrainConfig(steps=2, **tc), progress=False)
    train(dst, NetworkConfig(preset="small"), TrainConfig(steps=4, pattern_lr=0.05, **tc), progress=False,
          init_from=src)
    a, b = (torch.load(r / "checkpoint.pt", weights_only=False) for r in (src, dst))
    assert b["step"] == 4 and b["train"]["seed"] == a["train"]["seed"]
    # the learned pattern started at 0.5 (auto-exposure sees full-on) and moved; the rest came along
    assert 0.4 < torch.sigmoid(b["model"]["pattern_logits"]).mean() < 0.6
    assert not torch.allclose(b["model"]["pattern_logits"], torch.zeros_like(b["model"]["pattern_logits"]))
    # at the start, the two measure a batch identically (no noise): the warm start changes nothing
    dev = Device.load()
    full, half = TraceNet(NetworkConfig(preset="small", frozen_pattern="full_on"), dev), TraceNet(NetworkConfig(preset="small"), dev)
    with torch.no_grad():
        half.pattern_logits.zero_()
    batch = sample_batch(dev, 4, torch.Generator().manual_seed(0), views=6)
    (p1, v1), (p2, v2) = full.measure_batch(batch, noise=False), half.measure_batch(batch, noise=False)
    assert torch.equal(v1, v2) and torch.allclose(p1, p2, atol=1.5 / 255)
    with pytest.raises(SystemExit, match="different network config"):
        train(tmp_path / "other", NetworkConfig(preset="compact"), TrainConfig(steps=1, **tc), progress=False,
              init_from=src)
    with pytest.raises(SystemExit, match="no checkpoint"):
        train(tmp_path / "none", NetworkConfig(preset="small"), TrainConfig(steps=1, **tc), progress=False,
              init_from=tmp_path / "missing")


def test_a_learned_pattern_can_start_from_a_given_one(tmp_path):
    from ntp_engine.network import frozen_pattern
    from ntp_engine.train import TrainConfig, train

    tc = TrainConfig(steps=1, batch=4, validate_every=1, val_batches=1, views_max=8, lr=1e-9, pattern_init="binary")
    train(tmp_path / "run", NetworkConfig(preset="small"), tc, progress=False)
    p = torch.sigmoid(torch.load(tmp_path / "run" / "checkpoint.pt", weights_only=False)["model"]["pattern_logits"])
    expected = torch.as_tensor(frozen_pattern("binary", Device.load()), dtype=p.dtype).clamp(0.1, 0.9)
    torch.testing.assert_close(p, expected, atol=1e-4, rtol=0)  # one step at lr 1e-9 moves nothing
    frozen = TrainConfig(steps=1, batch=4, validate_every=1, val_batches=1, views_max=8, pattern_init="binary")
    train(tmp_path / "frozen", NetworkConfig(preset="small", frozen_pattern="full_on"), frozen, progress=False)
    q = torch.sigmoid(torch.load(tmp_path / "frozen" / "checkpoint.pt", weights_only=False)["model"]["pattern_logits"])
    assert float(q.min()) > 0.99  # a frozen pattern ignores the start value
