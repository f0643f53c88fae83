"""The normals and albedos an entry's pixel sample spans (``refine.footprint``)."""

import math

import numpy as np
import pytest
import torch

from ntp_engine.refine.footprint import albedo_blend, sample_points, slope_spread, widening
from ntp_engine.refine.settings import TUNING
from ntp_engine.scanner import camera
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
    assert (spread[..., 0, 0] + spread[..., 1, 1]).max().item() <= TUNING.footprint.spread_max * (1 + 1e-9)
    assert slope_spread(DEV, entries, torch.tensor([[False, False]]), S).abs().max().item() == 0


def test_the_lobe_is_widened_along_the_axis_the_normals_spread():
    spread = torch.zeros(1, 1, 2, 2, dtype=torch.float64)
    spread[..., 0, 0] = 0.004  # along t^ only
    frame = torch.eye(3, dtype=torch.float64)[None]
    turned = torch.tensor([[[0.0, 1, 0], [-1, 0, 0], [0, 0, 1]]], dtype=torch.float64)  # shading t along b^
    assert widening(spread, frame)[0, 0].tolist() == pytest.approx([TUNING.footprint.spread_widening * 0.004, 0.0])
    assert widening(spread, turned)[0, 0].tolist() == pytest.approx([0.0, TUNING.footprint.spread_widening * 0.004])
    # round-off on a flat face is no spread (float32 subnormals would slow every lobe sum)
    assert widening(torch.full((1, 1, 2, 2), 1e-30), frame.float()).abs().max().item() == 0


def test_the_sample_points_are_where_the_four_pixels_see_the_tangent_plane():
    """Each tap's point (texel point + delta along t^, b^) projects onto its pixel's centre (to the
    linearised projection's second order), in ``io.maps.bilinear_corners``' order, with the
    bilinear weights; padding and a surface seen edge-on have no taps."""
    n = torch.tensor([0.3, -0.2, -0.93], dtype=torch.float64)
    n = n / n.norm()
    t = torch.tensor([1.0, 0.4, 0.0], dtype=torch.float64)
    t = t - (t @ n) * n
    t = t / t.norm()
    b = torch.linalg.cross(n, t)
    entries = torch.cat(
        [_entry([0.0123, -0.0071, 0.31], n.tolist(), t.tolist()), _entry([0, 0, 0.3], [1.0, 0, 0], [0, 1.0, 0])], 1
    )
    delta, weight = sample_points(DEV, entries, torch.tensor([[True, True]]))
    px = camera.project(DEV, entries[0, 0, 3:6])
    base = torch.floor(px)
    fc, fr = (px - base).tolist()
    expect_w = [(1 - fc) * (1 - fr), fc * (1 - fr), (1 - fc) * fr, fc * fr]
    np.testing.assert_allclose(weight[0, 0].numpy(), expect_w, atol=1e-12)
    for a, (dr, dc) in enumerate([(0, 0), (0, 1), (1, 0), (1, 1)]):
        x = entries[0, 0, 3:6] + delta[0, 0, a, 0] * t + delta[0, 0, a, 1] * b
        seen = camera.project(DEV, x)
        np.testing.assert_allclose(
            seen.numpy(), (base + torch.tensor([dc, dr], dtype=torch.float64)).numpy(), atol=0.01
        )
    assert weight[0, 1].abs().max().item() == 0 and delta[0, 1].abs().max().item() == 0  # edge-on
    delta, weight = sample_points(DEV, entries, torch.tensor([[False, False]]))
    assert weight.abs().max().item() == 0


def test_the_albedo_blend_is_how_far_the_taps_reach_across_an_edge():
    """On a map with one albedo edge (0.4 | 0.8): taps that reach across it blend sqrt(sum w d^2),
    each difference less ``TUNING.footprint.blend_noise``; taps along the edge, a uniform map, a map varying by less
    than ``TUNING.footprint.blend_noise`` and unweighted taps blend nothing."""
    H = W = 8
    albedo = np.full((H, W, 3), 0.4)
    albedo[:, 4:] = 0.8  # columns 4.. brighter
    uv = np.array([[(3 + 0.5) / W, 1 - (2 + 0.5) / H]] * 2)  # texel row 2, column 3: next to the edge
    per_metre = np.tile(np.eye(2)[None] * 1000.0 / W, (2, 1, 1))  # 1 mm = one texel, u along t, v along b
    delta = torch.zeros(2, 1, 4, 2, dtype=torch.float64)
    delta[0, 0, :, 0] = torch.tensor([-0.5e-3, 0.5e-3, -0.5e-3, 0.5e-3])  # half a texel left and right
    delta[1, 0, :, 1] = torch.tensor([-0.5e-3, -0.5e-3, 0.5e-3, 0.5e-3])  # along v only: along the edge
    weight = torch.full((2, 1, 4), 0.25, dtype=torch.float64)
    out = albedo_blend(delta, weight, uv, per_metre, albedo)
    # right-hand taps at column 3.5 read 0.6 (0.2 brighter), the left ones 0.4
    expect = math.sqrt(0.5 * (0.2 - TUNING.footprint.blend_noise) ** 2)
    np.testing.assert_allclose(out[0, 0].numpy(), [expect] * 3, atol=1e-12)
    np.testing.assert_allclose(out[1, 0].numpy(), [0.0] * 3, atol=1e-12)
    faint = np.full((H, W, 3), 0.4)
    faint[:, 4:] = 0.4 + TUNING.footprint.blend_noise
    for flat in (np.full((H, W, 3), 0.4), faint):
        assert albedo_blend(delta, weight, uv, per_metre, flat).abs().max().item() < 1e-12
    assert albedo_blend(delta, 0 * weight, uv, per_metre, albedo).abs().max().item() == 0
