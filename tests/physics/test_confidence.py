"""Eq. 1 measurements against closed forms for point, linear and area emitters; Eq. 6 confidence."""

import pytest
import torch

from ntp_engine.io.assets import DEVICES_DIR
from ntp_engine.physics.confidence import confidence
from ntp_engine.scanner.device_file import load_scanner

F64 = torch.float64
ZERO = torch.zeros(3, dtype=F64)


def _t(*v):
    return torch.tensor(v if len(v) > 1 else v[0], dtype=F64)


def test_confidence_is_one_at_the_observed_peak_and_zero_without_highlight():
    dev = load_scanner(DEVICES_DIR / "point_light.toml")
    light = torch.as_tensor(dev.emitter_positions[0])
    x = _t(0.0, 0.0, 0.3)
    h = torch.nn.functional.normalize(
        torch.nn.functional.normalize(light - x, dim=0) + torch.nn.functional.normalize(-x, dim=0), dim=0
    )
    t = torch.nn.functional.normalize(torch.linalg.cross(h, _t(1.0, 0.0, 0.0), dim=0), dim=0)
    a = _t(0.01)
    beta = confidence(dev, x[None], h[None], t[None], a, a)
    assert float(beta) == pytest.approx(1.0)
    # tilt the normal 30 deg away: the mirror direction misses the only light by far
    away = torch.nn.functional.normalize(h + 0.6 * t, dim=0)
    t2 = torch.nn.functional.normalize(torch.linalg.cross(away, _t(0.0, 1.0, 0.0), dim=0), dim=0)
    beta0 = confidence(dev, x[None], away[None], t2[None], a, a)
    assert float(beta0) < 1e-3
    # two views: the peak view masked out leaves only the miss
    both = confidence(
        dev, torch.stack([x, x]), torch.stack([h, away]), torch.stack([t, t2]), a, a, valid=torch.tensor([False, True])
    )
    assert float(both) < 1e-3
