"""Where a texel's neighbours of the same material say its lobe points (refine.tangent_field)."""

import math

import numpy as np
import pytest

from ntp_engine.refine.settings import TUNING
from ntp_engine.refine.surface_fields import texel_spacing
from ntp_engine.refine.tangent_field import field_variation, fused_turns, neighbour_turns


def _plane(n: int = 20, spacing: float = 0.002):
    """A flat n x n grid of texels (object space, m): normal +z, geometric tangent +x."""
    g = np.stack(np.meshgrid(np.arange(n), np.arange(n), indexing="ij"), -1).reshape(-1, 2) * spacing
    position = np.concatenate([g, np.zeros((len(g), 1))], 1)
    normal = np.tile([0.0, 0.0, 1.0], (len(g), 1))
    tangent = np.tile([1.0, 0.0, 0.0], (len(g), 1))
    return position, normal, tangent


def _axis(deg: float) -> np.ndarray:
    return np.array([math.cos(math.radians(deg)), math.sin(math.radians(deg)), 0.0])


def test_the_turn_is_where_the_neighbours_point_relative_to_the_texels_own_tangent():
    position, normal, tangent = _plane()
    N = len(position)
    t_loc = np.tile(_axis(0.0), (N, 1))
    source = np.arange(0, N, 2)
    t_loc[source] = _axis(30.0)
    t_loc[source[::2]] = _axis(210.0)  # an axis has no sign
    target = np.arange(1, N, 2)
    turn, agree = neighbour_turns(position, normal, tangent, t_loc, source, target)
    np.testing.assert_allclose(turn, math.radians(30.0), atol=1e-9)
    assert (agree > 0.9).all() and (agree < 1.0).all()
    # a target whose geometric frame is turned 90 deg (its local x is object y): 30 - 90 = -60 deg
    tangent[target] = [0.0, 1.0, 0.0]
    turn, _ = neighbour_turns(position, normal, tangent, t_loc, source, target)
    np.testing.assert_allclose(turn, math.radians(-60.0), atol=1e-9)
    # its own start tangent counts too: t_loc at 50 deg in that frame, 30 - 90 - 50 = -110 = 70 (mod 180)
    t_loc[target] = _axis(50.0)
    turn, _ = neighbour_turns(position, normal, tangent, t_loc, source, target)
    np.testing.assert_allclose(turn, math.radians(70.0), atol=1e-9)


def test_no_far_or_disagreeing_neighbours_give_no_confidence():
    position, normal, tangent = _plane()
    N = len(position)
    t_loc = np.tile(_axis(0.0), (N, 1))
    target = np.arange(1, N, 2)
    turn, agree = neighbour_turns(position, normal, tangent, t_loc, np.zeros(0, int), target)
    assert (turn == 0).all() and (agree == 0).all()
    # half the sources along x, half along y, interleaved: no axis
    source = np.arange(0, N, 2)
    t_loc[source[1::2]] = _axis(90.0)
    _, agree = neighbour_turns(position, normal, tangent, t_loc, source, target)
    assert np.median(agree) < 0.3
    # one corner of agreeing sources: far targets trust them less than near ones
    t_loc = np.tile(_axis(20.0), (N, 1))
    corner = np.nonzero((position[:, 0] < 0.005) & (position[:, 1] < 0.005))[0]
    rest = np.setdiff1d(np.arange(N), corner)
    _, agree = neighbour_turns(position, normal, tangent, t_loc, corner, rest)
    d = np.linalg.norm(position[rest], axis=1)
    assert agree[d < 0.01].min() > agree[d > 0.03].max()
    assert agree[d > 0.04].max() < 0.2  # 2 sigma (tangent_reach 10 x 2 mm) away


def test_a_target_with_no_source_where_the_weight_is_above_double_precision_has_none():
    # a strip 200 spacings long, sources at one end (the reach is 10 spacings): targets within ~85
    # spacings have neighbours, and their turn and trust are those of the k nearest wherever they
    # lie (as an unbounded search gives them); beyond, turn 0 and trust 0 exactly
    spacing = 0.001
    x = np.arange(200) * spacing
    position = np.stack([x, np.zeros(200), np.zeros(200)], 1)
    normal, tangent = np.tile([0.0, 0.0, 1.0], (200, 1)), np.tile([1.0, 0.0, 0.0], (200, 1))
    t_loc = np.tile(_axis(0.0), (200, 1))
    source = np.arange(10)
    t_loc[source] = _axis(40.0)
    t_loc[source[::3]] = _axis(44.0)
    target = np.arange(10, 200)
    turn, agree = neighbour_turns(position, normal, tangent, t_loc, source, target, spacing)
    gap = (target - 9) * spacing / (TUNING.fields.tangent_reach * spacing)  # to the nearest source, in sigmas
    has = np.exp(-0.5 * gap**2) >= np.finfo(np.float64).eps
    assert has.sum() > 50 and (~has).sum() > 50
    assert (turn[~has] == 0).all() and (agree[~has] == 0).all()
    # the same sums over the k nearest, by brute force
    d = np.abs(x[target][:, None] - x[source][None])
    k = min(TUNING.fields.tangent_neighbours, len(source))
    near = np.argsort(d, 1, kind="stable")[:, :k]
    psi = np.radians(np.where(source[near] % 3 == 0, 44.0, 40.0))
    w = np.exp(-0.5 * (np.take_along_axis(d, near, 1) / (TUNING.fields.tangent_reach * spacing)) ** 2)
    c, s = (w * np.cos(2 * psi)).sum(1), (w * np.sin(2 * psi)).sum(1)
    np.testing.assert_allclose(turn[has], 0.5 * np.arctan2(s, c)[has], rtol=1e-9)
    np.testing.assert_allclose(agree[has], (np.hypot(c, s) / (k + TUNING.fields.tangent_doubt))[has], rtol=1e-9)


def _turned(t_loc: np.ndarray, turn: np.ndarray) -> np.ndarray:
    """Axis angles (deg) of ``t_loc`` turned by ``turn`` (rad) in the plane's frame."""
    return np.degrees(np.arctan2(t_loc[:, 1], t_loc[:, 0]) + turn)


def test_an_unconstrained_tangent_takes_its_neighbours_and_a_known_one_keeps_its_own():
    position, normal, tangent = _plane()
    N = len(position)
    t_loc = np.tile(_axis(30.0), (N, 1))
    std = np.full(N, math.radians(2.0))
    free, fixed = 105, 294  # two texels far apart
    t_loc[free], std[free] = _axis(-45.0), np.inf  # a guess: its trace did not say
    t_loc[fixed], std[fixed] = _axis(0.0), TUNING.fields.tangent_min_std  # its trace fixed it
    source = np.setdiff1d(np.arange(N), [free])
    turn, fused = fused_turns(position, normal, tangent, t_loc, std, source, np.array([free, fixed]))
    angle = _turned(t_loc[[free, fixed]], turn)
    assert angle[0] == pytest.approx(30.0, abs=1e-6) and fused[0] < math.radians(1.0)
    assert angle[1] == pytest.approx(0.0, abs=1e-9)  # 30 deg from 24 neighbours at 2 deg: the field turns there
    assert fused[1] == TUNING.fields.tangent_min_std  # and its std stays its own
    # one that its neighbours agree with within the errors is averaged with them
    t_loc[fixed] = _axis(29.5)
    turn, fused = fused_turns(position, normal, tangent, t_loc, std, source, np.array([fixed]))
    assert 29.6 < _turned(t_loc[[fixed]], turn)[0] < 30.0 and fused[0] < TUNING.fields.tangent_min_std
    # no sources: nothing moves
    turn, fused = fused_turns(position, normal, tangent, t_loc, std, np.zeros(0, int), np.array([free, fixed]))
    assert (turn == 0).all() and fused[0] == np.inf and fused[1] == TUNING.fields.tangent_min_std


def test_noise_between_neighbours_is_averaged_where_the_field_is_smooth():
    position, normal, tangent = _plane(30)
    N = len(position)
    rng = np.random.default_rng(0)
    truth = 20.0 + 10.0 * position[:, 0] / position[:, 0].max()  # turns slowly across the plane
    noisy = truth + rng.normal(0.0, 4.0, N)
    t_loc = np.stack([np.cos(np.radians(noisy)), np.sin(np.radians(noisy)), np.zeros(N)], 1)
    std = np.full(N, math.radians(4.0))
    every = np.arange(N)
    turn, fused = fused_turns(position, normal, tangent, t_loc, std, every, every)
    before, after = np.abs(noisy - truth), np.abs(_turned(t_loc, turn) - truth)
    assert np.median(after) < 0.4 * np.median(before)  # ~20 neighbours: ~1/4.5 of the noise
    assert (fused <= math.radians(4.0)).all() and np.median(fused) < math.radians(1.0)
    # where the neighbours disagree (a field turning fast), a texel keeps more of its own
    wild = truth + rng.uniform(-90.0, 90.0, N)
    t_wild = np.stack([np.cos(np.radians(wild)), np.sin(np.radians(wild)), np.zeros(N)], 1)
    turn_wild, _ = fused_turns(position, normal, tangent, t_wild, std, every, every)
    assert np.median(np.abs(turn_wild)) < np.median(np.abs(turn)) * 2 + 1e-3 or np.median(np.abs(turn_wild)) < 0.5


def test_the_field_variation_is_how_far_axes_turn_with_distance_beyond_their_errors():
    position, normal, tangent = _plane(30)
    N = len(position)
    rng = np.random.default_rng(1)
    every = np.arange(N)
    std = np.full(N, math.radians(3.0))
    noisy = 20.0 + rng.normal(0.0, 3.0, N)  # one direction, measured to 3 deg
    t_loc = np.stack([np.cos(np.radians(noisy)), np.sin(np.radians(noisy)), np.zeros(N)], 1)
    dist, gamma = field_variation(position, normal, tangent, t_loc, std, every)
    assert dist[0] == pytest.approx(texel_spacing(position)) and (np.diff(dist) > 0).all()
    assert np.sqrt(2 * gamma.max()) < math.radians(1.5)  # the errors explain the spread
    # a field turning 2 deg per texel along x: the variation grows with distance
    turning = noisy + 2.0 * position[:, 0] / texel_spacing(position)
    t_turn = np.stack([np.cos(np.radians(turning)), np.sin(np.radians(turning)), np.zeros(N)], 1)
    _, gamma_turn = field_variation(position, normal, tangent, t_turn, std, every)
    assert (np.diff(gamma_turn) >= 0).all() and gamma_turn[4] > 4 * gamma_turn[1] > 0
    assert np.degrees(np.sqrt(2 * gamma_turn[3])) == pytest.approx(2.0 * 8 / math.sqrt(2), rel=0.5)  # 8 spacings
    # and the fusion weighs far neighbours less there: an unconstrained texel takes its nearest's
    free = 15 * 30 + 15
    std_free = std.copy()
    std_free[free] = np.inf
    turn, _ = fused_turns(position, normal, tangent, t_turn, std_free, np.setdiff1d(every, [free]), np.array([free]))
    truth = 20.0 + 2.0 * position[free, 0] / texel_spacing(position)
    assert abs(_turned(t_turn[[free]], turn)[0] - truth) < 2.0
