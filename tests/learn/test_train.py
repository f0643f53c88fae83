import math

import pytest
import torch

from ntp_engine.io.errors import NtpInputError
from ntp_engine.learn.network import NetworkConfig, TraceNet
from ntp_engine.learn.synthetic import SyntheticConfig, sample_batch
from ntp_engine.learn.train import batch_loss
from ntp_engine.scanner.device_file import load_scanner


def _net(**kw):
    torch.manual_seed(0)
    return TraceNet(NetworkConfig(preset="small", **kw), load_scanner())


def test_pattern_learning_rate_is_its_own_parameter_group(tmp_path):
    from ntp_engine.learn.train import TrainConfig, train

    run = tmp_path / "run"
    tc = dict(steps=2, batch=4, validate_every=2, val_batches=1, views_max=8)
    train(run, NetworkConfig(preset="small"), TrainConfig(pattern_lr=0.05, **tc))
    ck = torch.load(run / "checkpoint.pt", weights_only=False)
    assert [g["lr"] for g in ck["optimizer"]["param_groups"]] == [3e-4, 0.05]
    try:  # resuming with another grouping is refused with a clear message
        train(run, NetworkConfig(preset="small"), TrainConfig(**{**tc, "steps": 3}), resume=True)
        raise AssertionError("expected NtpInputError")
    except NtpInputError as err:
        assert "--pattern-lr" in str(err)


def test_resume_matches_optimizer_state_saved_in_another_parameter_order():
    from ntp_engine.learn.train import _match_optimizer_order

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
    from ntp_engine.learn.synthetic import sample_batch
    from ntp_engine.learn.train import TrainConfig, train

    tc = dict(batch=4, validate_every=2, val_batches=1, views_max=8)
    src, dst = tmp_path / "full_on", tmp_path / "learned"
    train(src, NetworkConfig(preset="small", frozen_pattern="full_on"), TrainConfig(steps=2, **tc))
    train(dst, NetworkConfig(preset="small"), TrainConfig(steps=4, pattern_lr=0.05, **tc), init_from=src)
    a, b = (torch.load(r / "checkpoint.pt", weights_only=False) for r in (src, dst))
    assert b["step"] == 4 and b["train"]["seed"] == a["train"]["seed"]
    # the learned pattern started at 0.5 (auto-exposure sees full-on) and moved; the rest came along
    assert 0.4 < torch.sigmoid(b["model"]["pattern_logits"]).mean() < 0.6
    assert not torch.allclose(b["model"]["pattern_logits"], torch.zeros_like(b["model"]["pattern_logits"]))
    # at the start, the two measure a batch identically (no noise): the warm start changes nothing
    dev = load_scanner()
    full, half = (
        TraceNet(NetworkConfig(preset="small", frozen_pattern="full_on"), dev),
        TraceNet(NetworkConfig(preset="small"), dev),
    )
    with torch.no_grad():
        half.pattern_logits.zero_()
    batch = sample_batch(dev, 4, torch.Generator().manual_seed(0), views=6)
    (p1, v1), (p2, v2) = full.measure_batch(batch, noise=False), half.measure_batch(batch, noise=False)
    assert torch.equal(v1, v2) and torch.allclose(p1, p2, atol=1.5 / 255)
    with pytest.raises(NtpInputError, match="different network config"):
        train(tmp_path / "other", NetworkConfig(preset="compact"), TrainConfig(steps=1, **tc), init_from=src)
    with pytest.raises(NtpInputError, match="no checkpoint"):
        train(
            tmp_path / "none", NetworkConfig(preset="small"), TrainConfig(steps=1, **tc), init_from=tmp_path / "missing"
        )


def test_a_learned_pattern_can_start_from_a_given_one(tmp_path):
    from ntp_engine.learn.train import TrainConfig, train
    from ntp_engine.scanner.pattern import named_pattern

    tc = TrainConfig(steps=1, batch=4, validate_every=1, val_batches=1, views_max=8, lr=1e-9, pattern_init="binary")
    train(tmp_path / "run", NetworkConfig(preset="small"), tc)
    p = torch.sigmoid(torch.load(tmp_path / "run" / "checkpoint.pt", weights_only=False)["model"]["pattern_logits"])
    expected = torch.as_tensor(named_pattern("binary", load_scanner()), dtype=p.dtype).clamp(0.1, 0.9)
    torch.testing.assert_close(p, expected, atol=1e-4, rtol=0)  # one step at lr 1e-9 moves nothing
    frozen = TrainConfig(steps=1, batch=4, validate_every=1, val_batches=1, views_max=8, pattern_init="binary")
    train(tmp_path / "frozen", NetworkConfig(preset="small", frozen_pattern="full_on"), frozen)
    q = torch.sigmoid(torch.load(tmp_path / "frozen" / "checkpoint.pt", weights_only=False)["model"]["pattern_logits"])
    assert float(q.min()) > 0.99  # a frozen pattern ignores the start value


def test_tiny_overfit_drives_the_loss_down():
    dev = load_scanner()
    batch = sample_batch(dev, 8, torch.Generator().manual_seed(4), SyntheticConfig(views_min=24, views_max=24))
    net = _net(dropout=0.0)
    opt = torch.optim.Adam(net.parameters(), lr=1e-3)
    losses = []
    for _ in range(150):
        loss, _, _, _ = batch_loss(net, batch, torch.Generator().manual_seed(99), noise=False)
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.item())
    assert losses[-1] < 0.1 * losses[0], (losses[0], losses[-1])


def test_cosine_schedule_falls_from_the_run_start_to_zero_at_the_last_step(tmp_path):
    from ntp_engine.learn.train import TrainConfig, lr_factor, train

    flat = TrainConfig(steps=100)
    assert lr_factor(flat, 0) == lr_factor(flat, 99) == 1.0
    cos = TrainConfig(steps=300, lr_schedule="cosine", schedule_start=100)
    assert lr_factor(cos, 100) == 1.0 and abs(lr_factor(cos, 200) - 0.5) < 1e-12 and lr_factor(cos, 300) < 1e-12
    assert lr_factor(cos, 50) == 1.0 and lr_factor(cos, 400) == 0.0  # clamped outside the run
    run = tmp_path / "run"
    tc = dict(batch=4, validate_every=4, val_batches=1, views_max=8, pattern_lr=0.05, lr_schedule="cosine")
    train(run, NetworkConfig(preset="small"), TrainConfig(steps=2, **tc))
    ck = torch.load(run / "checkpoint.pt", weights_only=False)
    # the last update (step 1 of 2) ran at half of each group's configured rate
    torch.testing.assert_close([g["lr"] for g in ck["optimizer"]["param_groups"]], [1.5e-4, 0.025])
    # resumed, the schedule scales the configured rates, not the last scaled ones the optimiser saved
    train(run, NetworkConfig(preset="small"), TrainConfig(steps=4, **tc), resume=True)
    ck = torch.load(run / "checkpoint.pt", weights_only=False)
    expected = 0.5 * (1 + math.cos(math.pi * 3 / 4))
    torch.testing.assert_close([g["lr"] for g in ck["optimizer"]["param_groups"]], [3e-4 * expected, 0.05 * expected])
    with pytest.raises(ValueError, match="lr_schedule"):
        train(tmp_path / "bad", NetworkConfig(preset="small"), TrainConfig(steps=1, lr_schedule="linear"))


def test_a_model_folder_is_trained_on_with_its_own_pattern_step_and_data(tmp_path):
    import json

    from ntp_engine.learn import models
    from ntp_engine.learn.train import TrainConfig, train

    tc = dict(batch=4, validate_every=2, val_batches=1, views_max=8)
    src = tmp_path / "src"
    train(src, NetworkConfig(preset="small"), TrainConfig(steps=2, pattern_lr=0.5, seed=7, **tc))
    models.export(src / "checkpoint.pt", tmp_path / "model", {"history": "test"})
    dst = tmp_path / "dst"
    start = tmp_path / "model"
    train(dst, NetworkConfig(preset="small"), TrainConfig(steps=3, lr=1e-12, pattern_lr=0.0, **tc), init_from=start)
    a, b = (torch.load(r / "checkpoint.pt", weights_only=False) for r in (src, dst))
    assert b["step"] == 3 and b["train"]["seed"] == 7 and b["train"]["schedule_start"] == 2
    # the learned pattern goes on exactly where the source left it (not rescaled), so the device
    # file written from the source still matches; the float16 weights came along
    assert torch.equal(b["model"]["pattern_logits"], a["model"]["pattern_logits"])
    w = "diffuse_head.0.weight"
    torch.testing.assert_close(b["model"][w], a["model"][w].half().float(), atol=1e-9, rtol=0)
    (tmp_path / "model" / "summary.json").write_text(json.dumps({"history": "no steps"}))
    with pytest.raises(NtpInputError, match="not a model folder"):
        train(tmp_path / "x", NetworkConfig(preset="small"), TrainConfig(steps=3, **tc), init_from=tmp_path / "model")
