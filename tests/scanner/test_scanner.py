import numpy as np
import pytest
import torch

from ntp_engine.io.assets import DEVICES_DIR
from ntp_engine.scanner.device_file import load_scanner
from ntp_engine.scanner.scanner import auto_exposure


def test_auto_exposure_follows_the_pattern_up_to_the_limit():
    dev = load_scanner()
    full = dev.exposure(np.ones((512, 3)))
    assert full == pytest.approx(dev.gain)
    assert dev.exposure(np.full((512, 3), 0.5)) == pytest.approx(2 * full)  # within the limit: compensated
    point = np.zeros((512, 3))
    point[0] = 1.0
    assert dev.exposure(point) == pytest.approx(dev.max_exposure * full)  # capped: 512x dimmer than full-on
    t = dev.exposure(torch.full((512, 3), 0.01, dtype=torch.float64))
    assert isinstance(t, torch.Tensor) and float(t) == pytest.approx(4 * full)
    assert auto_exposure(0.0, 1.0, 1.0, 2.0) == pytest.approx(2.0)  # a black pattern: the limit, finite


def test_cosine_psi_is_zero_behind_the_emitter():
    d = load_scanner()
    c = torch.tensor([1.0, 0.5, 0.0, -0.5], dtype=torch.float64)
    np.testing.assert_allclose(d.psi(c).numpy(), [1.0, 0.5, 0.0, 0.0])


def test_quadrature_weights_sum_to_one_and_points_lie_on_the_emitter():
    for name in ("area_light.toml", "linear_light.toml", "ntp_led_32x16.toml"):
        d = load_scanner(DEVICES_DIR / name)
        pts, w = d.emitter_samples(torch.float64)
        np.testing.assert_allclose(w.sum(-1).numpy(), 1.0, atol=1e-12)
        offset = pts.numpy() - d.emitter_positions[:, None, :]
        np.testing.assert_allclose((offset * d.emitter_normals[:, None, :]).sum(-1), 0.0, atol=1e-12)  # in-plane


def test_valid_volume_includes_its_edges_only():
    d = load_scanner()
    half = d.valid_size / 2 @ d.valid_axes
    inside = torch.as_tensor(np.stack([d.valid_center, d.valid_center + half, d.valid_center + 1.01 * half]))
    assert d.in_valid_volume(inside).tolist() == [True, True, False]
