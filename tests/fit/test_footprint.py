"""The normals an entry's pixel sample spans (``fit.footprint``)."""

import math

import pytest
import torch

from ntp_engine.fit.footprint import SPREAD_MAX, SPREAD_WIDENING, slope_spread, widening
from ntp_engine.scanner.device_file import load_scanner

DEV = load_scanner()


def _entry(x, n, t):
    e = torch.zeros(1, 1, 12, dtype=torch.float64)
    e[0, 0, 3:6], e[0, 0, 6:9], e[0, 0, 9:12] = torch.tensor(x), torch.tensor(n), torch.tensor(t)
    return e


def test_a_sphere_seen_head_on_spreads_the_normal_by_a_pixel_step_over_the_radius():
    """Half-way between pixel centres (f = 0.5: variance 1/4 px^2 per axis), on a sphere of radius r
    at distance d facing the camera: slope variance (d / (f_x r))^2 / 4 along each axis."""
    d, r = 0.3, 0.009
    K = torch.as_tensor(DEV.K)
    # the point that projects half-way between pixel centres in both axes
    u, v = math.floor(float(K[0, 2])) + 0.5, math.floor(float(K[1, 2])) + 0.5
    x = [(u - float(K[0, 2])) * d / float(K[0, 0]), (v - float(K[1, 2])) * d / float(K[1, 1]), d]
    entries = _entry(x, [0.0, 0.0, -1.0], [1.0, 0.0, 0.0])
    S = torch.eye(2, dtype=torch.float64)[None] / r
    spread = slope_spread(DEV, entries, torch.ones(1, 1, dtype=torch.bool), S)[0, 0]
    expect = 0.25 * (d / (float(K[0, 0]) * r)) ** 2
    assert spread[0, 0].item() == pytest.approx(expect, rel=0.02)
    assert spread[1, 1].item() == pytest.approx(0.25 * (d / (float(K[1, 1]) * r)) ** 2, rel=0.02)
    assert abs(spread[0, 1].item()) < 1e-3 * expect
    # on a pixel centre the four samples are one: no spread; a flat surface, none either
    x0 = [
        (math.floor(float(K[0, 2])) - float(K[0, 2])) * d / float(K[0, 0]),
        (math.floor(float(K[1, 2])) - float(K[1, 2])) * d / float(K[1, 1]),
        d,
    ]
    on_centre = slope_spread(DEV, _entry(x0, [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]), torch.ones(1, 1, dtype=torch.bool), S)
    assert on_centre.abs().max().item() < 1e-6 * expect
    assert slope_spread(DEV, entries, torch.ones(1, 1, dtype=torch.bool), 0 * S).abs().max().item() == 0


def test_padding_and_grazing_entries_are_bounded_and_finite():
    S = torch.eye(2, dtype=torch.float64)[None] * 1000.0  # a 1 mm radius: more than the cap
    entries = torch.cat(
        [_entry([0.001, 0.002, 0.3], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]), _entry([0, 0, 0.3], [1.0, 0, 0], [0, 1.0, 0])],
        1,
    )
    mask = torch.tensor([[True, True]])
    spread = slope_spread(DEV, entries, mask, S)
    assert torch.isfinite(spread).all()
    assert (spread[..., 0, 0] + spread[..., 1, 1]).max().item() <= SPREAD_MAX * (1 + 1e-9)
    assert slope_spread(DEV, entries, torch.tensor([[False, False]]), S).abs().max().item() == 0


def test_the_lobe_is_widened_along_the_axis_the_normals_spread():
    spread = torch.zeros(1, 1, 2, 2, dtype=torch.float64)
    spread[..., 0, 0] = 0.004  # along t^ only
    frame = torch.eye(3, dtype=torch.float64)[None]
    turned = torch.tensor([[[0.0, 1, 0], [-1, 0, 0], [0, 0, 1]]], dtype=torch.float64)  # shading t along b^
    assert widening(spread, frame)[0, 0].tolist() == pytest.approx([SPREAD_WIDENING * 0.004, 0.0])
    assert widening(spread, turned)[0, 0].tolist() == pytest.approx([0.0, SPREAD_WIDENING * 0.004])
    # round-off on a flat face is no spread (float32 subnormals would slow every lobe sum)
    assert widening(torch.full((1, 1, 2, 2), 1e-30), frame.float()).abs().max().item() == 0
