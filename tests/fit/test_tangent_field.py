"""Where a texel's neighbours of the same material say its lobe points (fit.tangent_field)."""

import math

import numpy as np

from ntp_engine.fit.tangent_field import neighbour_turns


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
    assert agree[d > 0.04].max() < 0.2  # 2 sigma (REACH 10 x 2 mm) away
