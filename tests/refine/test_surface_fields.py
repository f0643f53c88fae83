"""How far apart a surface's texels lie and how a field varies over them (refine.surface_fields)."""

import numpy as np
import pytest

from ntp_engine.refine.settings import TUNING
from ntp_engine.refine.surface_fields import field_pairs, semivariogram, texel_spacing


def _grid(n: int = 40, spacing: float = 0.001) -> np.ndarray:
    g = np.stack(np.meshgrid(np.arange(n), np.arange(n), indexing="ij"), -1).reshape(-1, 2) * spacing
    return np.concatenate([g, np.zeros((len(g), 1))], 1)


def test_pairs_are_near_and_random_others_never_a_texel_with_itself():
    position = _grid()
    assert texel_spacing(position) == pytest.approx(0.001) and texel_spacing(position[:1]) == 0.0
    i, j, d = field_pairs(position)
    assert (i != j).all() and len(i) > len(position) * TUNING.fields.variation_pairs
    np.testing.assert_allclose(d, np.linalg.norm(position[i] - position[j], axis=1))
    assert np.median(d) < 0.01 < d.max()  # near pairs and far ones


@pytest.mark.parametrize("dof", [1, 2])
def test_the_semivariogram_is_what_the_errors_do_not_explain(dof):
    position = _grid()
    rng = np.random.default_rng(dof)
    sigma = 0.01
    i, j, d = field_pairs(position)
    noise = np.full(len(i), 2 * sigma**2)
    values = rng.normal(0.0, sigma / np.sqrt(dof), (len(position), dof))  # total variance sigma^2
    sq = ((values[i] - values[j]) ** 2).sum(1)
    bins, gamma = semivariogram(d, sq, noise, texel_spacing(position), dof)
    assert bins[0] == pytest.approx(0.001) and gamma.max() < 0.1 * sigma**2  # noise only: ~0
    # a ramp of 0.05 per mm along x on top: half the mean squared difference grows with distance
    ramp = values + 50.0 * position[:, :1]
    bins, gamma = semivariogram(d, ((ramp[i] - ramp[j]) ** 2).sum(1), noise, texel_spacing(position), dof)
    assert (np.diff(gamma) >= 0).all() and gamma[3] > 10 * max(gamma[0], sigma**2 / 10)
    assert semivariogram(np.zeros(0), np.zeros(0), np.zeros(0), 0.001, dof)[1].max() == 0.0
