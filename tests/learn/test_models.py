import numpy as np
import pytest
import torch

from ntp_engine.io.errors import NtpInputError
from ntp_engine.learn import models
from ntp_engine.learn.network import NetworkConfig
from ntp_engine.scanner.device_file import load_scanner, write_pattern


def test_export_and_load_round_trip(tmp_path):
    from ntp_engine.learn.train import TrainConfig, train

    run = tmp_path / "run"
    train(
        run, NetworkConfig(preset="small"), TrainConfig(steps=2, batch=4, validate_every=2, val_batches=1, views_max=8)
    )
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
    src = load_scanner()
    dev_file = tmp_path / "dev.toml"
    dev_file.write_text(open(src.source).read())
    pattern = np.random.default_rng(0).random((512, 3))
    write_pattern(dev_file, pattern)
    loaded = load_scanner(dev_file).pattern
    np.testing.assert_allclose(loaded, np.round(pattern * 255) / 255, atol=1e-7)
    np.testing.assert_allclose(loaded * 255, np.round(loaded * 255), atol=1e-5)


def test_loaded_model_keeps_its_training_exposure_whatever_the_device(tmp_path):
    import dataclasses

    dev = load_scanner()
    brighter = dataclasses.replace(dev, gain=dev.gain * 1.5, max_exposure=1.0)  # e.g. a scan's device.toml
    net, meta = models.load(None, brighter)
    assert float(net.gain) == pytest.approx(meta["device_gain"]) == pytest.approx(dev.gain)
    assert float(net.max_exposure) == pytest.approx(meta["device_max_exposure"]) == pytest.approx(dev.max_exposure)
    assert net.exposure() == pytest.approx(dev.exposure(net.pattern().detach().double().numpy()), rel=1e-5)


def test_a_scanner_lit_by_another_pattern_is_refused_naming_both_files(tmp_path):
    import dataclasses

    src = load_scanner()
    ours = models.pattern_of(None)
    for name, pattern, ok in (("same", ours, True), ("off", ours * 0.5, False)):
        dev_file = tmp_path / f"{name}.toml"
        dev_file.write_text(src.source.read_text())
        write_pattern(dev_file, pattern)  # quantised to 8 bits, as the driver projects it
        if ok:
            models.load(None, load_scanner(dev_file))
            continue
        with pytest.raises(NtpInputError) as err:
            models.load(None, load_scanner(dev_file))
        msg = str(err.value)
        assert "compact/pattern.csv" in msg and "off.toml" in msg and "\n" not in msg
    # the tolerance is half an 8-bit step
    models.load(None, dataclasses.replace(src, pattern=np.clip(ours + 0.45 / 255, 0, 1)))
    with pytest.raises(NtpInputError, match="another lighting pattern"):
        models.load(None, dataclasses.replace(src, pattern=np.clip(ours + 0.6 / 255, 0, 1)))
    net, _ = models.load("compare_point")  # no capture's scanner: the network's own pattern, no check
    assert float(net.pattern().sum()) == pytest.approx(3, abs=0.01)  # one LED on (frozen at 1 - 1e-6)


def test_specular_basis_compresses_the_head_within_its_tolerance(tmp_path):
    from ntp_engine.learn.train import TrainConfig, train

    run = tmp_path / "run"
    train(
        run, NetworkConfig(preset="small"), TrainConfig(steps=2, batch=4, validate_every=2, val_batches=1, views_max=8)
    )
    folder = tmp_path / "model"
    models.export(run / "checkpoint.pt", folder, {})
    assert models.model_files(folder) == [folder / "config.json", folder / "model.pt"]
    found = models.write_specular_basis(folder, traces=256, tolerance=0.02)
    assert 1 <= found["rank"] < 256 and found["worst_fit"] <= 0.02  # fewer directions than the layer's inputs
    assert models.model_files(folder)[-1] == folder / models.SPECULAR_BASIS  # the cache key sees it
    full, meta_full = models.load(folder, exact=True)
    low, meta = models.load(folder)
    assert meta_full["specular_basis"] is None and meta["specular_basis"] == found["rank"]
    scanner = load_scanner()
    from ntp_engine.learn.synthetic import SyntheticConfig, sample_batch

    gen = torch.Generator().manual_seed(5)  # traces the basis never saw
    b = sample_batch(scanner, 64, gen, SyntheticConfig(), views=16)
    with torch.no_grad():
        pixel, valid = full.measure_batch(b, gen, noise=False)
        x = full.entries(pixel, b.position, b.normal_geo, b.tangent_geo)
        d_full, s_full = full(x, valid)
        d_low, s_low = low(x, valid)
    torch.testing.assert_close(d_low, d_full)
    err = float((s_low - s_full).abs().max())
    assert 0 < err < 3 * 0.02, err  # compressed, and close


def test_full_rank_basis_is_the_layer_itself():
    torch.manual_seed(0)
    from ntp_engine.learn.network import TraceNet

    net = TraceNet(NetworkConfig(preset="small"), load_scanner()).eval()
    h = torch.randn(5, 256)
    want = net.specular_head[-1](h)
    w = net.specular_head[-1].weight.detach().double()
    basis = torch.linalg.qr(w)[0]  # spans the layer's whole range: nothing is cut
    net.compress_specular(basis.float(), torch.randn(256))
    torch.testing.assert_close(net.specular_head[-1](h), want, rtol=1e-4, atol=1e-4)


def test_a_damaged_specular_basis_is_refused_naming_the_file(tmp_path):
    import shutil

    folder = tmp_path / "compact"
    shutil.copytree(models.resolve(None), folder)
    (folder / models.SPECULAR_BASIS).write_bytes(b"not torch")
    with pytest.raises(NtpInputError, match="specular_basis.pt: not a specular basis"):
        models.load(folder)
