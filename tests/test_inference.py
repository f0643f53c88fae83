import numpy as np
import pytest
import torch

from ntp_engine import models
from ntp_engine.device import Device
from ntp_engine.errors import NtpInputError
from ntp_engine.inference import RaggedTraces, predict, predict_all
from ntp_engine.network import NetworkConfig, TraceNet


def _traces(n=9, seed=0):
    gen = torch.Generator().manual_seed(seed)
    lengths = torch.randint(0, 12, (n,), generator=gen)
    lengths[0] = 0  # an empty trace
    offsets = torch.zeros(n + 1, dtype=torch.int64)
    offsets[1:] = torch.cumsum(lengths, 0)
    entries = torch.rand(int(offsets[-1]), 12, generator=gen)
    return RaggedTraces(entries, offsets)


def test_ragged_prediction_matches_padded_forward_in_any_batching():
    torch.manual_seed(0)
    net = TraceNet(NetworkConfig(preset="small"), Device.load()).eval()
    tr = _traces()
    d_all, s_all = predict_all(net, tr, max_entries=1 << 12)
    d_small, s_small = predict_all(net, tr, max_entries=13)  # many tiny batches
    torch.testing.assert_close(d_all, d_small)
    torch.testing.assert_close(s_all, s_small)
    for k in (1, 4):
        a, b = int(tr.offsets[k]), int(tr.offsets[k + 1])
        raw = tr.entries[a:b][None]
        x = net.entries(raw[..., :3], raw[..., 3:6], raw[..., 6:9], raw[..., 9:])
        with torch.no_grad():
            d, s = net(x, torch.ones(1, b - a, dtype=torch.bool))
        torch.testing.assert_close(d_all[k], d[0].clamp_min(0))
        torch.testing.assert_close(s_all[k], torch.expm1(s[0].clamp_min(0)))
    assert (s_all >= 0).all() and torch.isfinite(d_all).all()
    seen = torch.cat([idx for idx, _, _ in predict(net, tr, max_entries=20)])
    assert sorted(seen.tolist()) == list(range(tr.num_traces))


def test_bad_ragged_input():
    with pytest.raises(ValueError):
        RaggedTraces(torch.zeros(4, 10), torch.tensor([0, 4]))
    with pytest.raises(ValueError):
        RaggedTraces(torch.zeros(4, 12), torch.tensor([0, 3]))


def test_export_and_load_round_trip(tmp_path):
    from ntp_engine.train import TrainConfig, train

    run = tmp_path / "run"
    train(run, NetworkConfig(preset="small"), TrainConfig(steps=2, batch=4, validate_every=2, val_batches=1,
                                                           views_max=8), progress=False)
    models.export(run / "checkpoint.pt", tmp_path / "model", {"val_loss": 1.0})
    net, meta = models.load(tmp_path / "model")
    assert meta["network"]["preset"] == "small" and meta["summary"]["steps"] == 2
    ck = torch.load(run / "checkpoint.pt", weights_only=False)
    torch.testing.assert_close(net.pattern_logits.detach(), ck["model"]["pattern_logits"])
    w = ck["model"]["encoder.0.weight"]
    torch.testing.assert_close(net.encoder[0].weight.detach(), w.half().float())
    pattern = np.loadtxt(tmp_path / "model" / "pattern.csv", delimiter=",")
    assert pattern.shape == (512, 3) and ((pattern > 0) & (pattern < 1)).all()
    with pytest.raises(NtpInputError, match="not a model folder"):
        models.load(tmp_path / "nothing")


def test_pattern_export_to_device_is_quantised(tmp_path):
    src = Device.load()
    dev_file = tmp_path / "dev.toml"
    dev_file.write_text(open(src.source).read())
    pattern = np.random.default_rng(0).random((512, 3))
    models.write_pattern_to_device(pattern, dev_file)
    loaded = Device.load(dev_file).pattern
    np.testing.assert_allclose(loaded, np.round(pattern * 255) / 255, atol=1e-7)
    np.testing.assert_allclose(loaded * 255, np.round(loaded * 255), atol=1e-5)


def test_network_benchmark_reads_shipped_models_and_reports_the_keys(tmp_path):
    import json

    from ntp_engine.bench import network as bench_network

    out = tmp_path / "bn.json"
    bench_network.run(quick=True, json_path=out, batches=2, rate_traces=256)
    r = json.loads(out.read_text())
    by = r["val_loss_by_pattern"]
    assert set(by) == {"optimized", "full_on", "point"}
    assert set(r["val_loss_by_test_views"]) == {"8", "16", "32", "64", "128"}
    assert r["traces_per_s"] > 0 and all(v > 0 for v in by.values())
    for k in ("optimized", "point"):  # paired over the same batches: the mean difference is the difference
        d = r["val_loss_minus_full_on"][k]
        assert d["mean"] == pytest.approx(by[k] - by["full_on"], abs=1e-9) and d["standard_error"] >= 0
    assert all(0 <= v <= 1 for v in r["valid_views_by_pattern"].values())


def test_loaded_model_keeps_its_training_exposure_whatever_the_device(tmp_path):
    import dataclasses

    dev = Device.load()
    brighter = dataclasses.replace(dev, gain=dev.gain * 1.5, max_exposure=1.0)  # e.g. a scan's device.toml
    net, meta = models.load(None, brighter)
    assert float(net.gain) == pytest.approx(meta["device_gain"]) == pytest.approx(dev.gain)
    assert float(net.max_exposure) == pytest.approx(meta["device_max_exposure"]) == pytest.approx(dev.max_exposure)
    assert net.exposure() == pytest.approx(dev.exposure(net.pattern().detach().double().numpy()), rel=1e-5)


def test_padded_subsampling_spreads_over_the_trace():
    entries = torch.arange(20, dtype=torch.float32)[:, None].repeat(1, 12)
    tr = RaggedTraces(entries, torch.tensor([0, 2, 12, 20]))
    full, m = tr.padded(torch.tensor([0, 1, 2]))
    assert m.sum(1).tolist() == [2, 10, 8] and full.shape == (3, 10, 12)
    sub, ms = tr.padded(torch.tensor([0, 1, 2]), max_views=4)
    assert ms.sum(1).tolist() == [2, 4, 4]
    assert sub[1, :, 0].tolist() == [2.0, 5.0, 8.0, 11.0]  # first, evenly spread, last
    assert sub[0, :2, 0].tolist() == [0.0, 1.0] and (sub[0, 2:] == 0).all()


def test_bench_network_trains_the_pattern_comparison_from_shared_halfway_networks():
    """The Fig. 14 protocol without --quick: optimised and full-on continue the same half-way
    full-on network; only the optimised one's pattern moves."""
    from ntp_engine.bench import network as bench_network

    nets = bench_network._comparison_models(False, 2, Device.load())
    assert set(nets) == {"optimized", "full_on", "point"}
    opt, full, point = (nets[k].pattern().detach() for k in ("optimized", "full_on", "point"))
    assert (full > 0.99).all() and (point > 0.99).all(1).sum() == 1
    assert 0.4 < float(opt.mean()) < 0.6 and float(opt.std()) > 0  # started at 0.5 and learned
    shared = [k for k in nets["full_on"].state_dict() if k.startswith("encoder")]
    assert shared and all(nets["optimized"].state_dict()[k].shape == nets["full_on"].state_dict()[k].shape
                          for k in shared)
