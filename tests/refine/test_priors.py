"""The refinement's priors: zero at their centres, growing away from them, the tint pull relative to
the lobe's brightness, the normal's pull at the start or at the mesh."""

import dataclasses

import torch

from ntp_engine.refine.model import P_LOGA, P_RHO_S
from ntp_engine.refine.priors import Prior, normal_prior, prior_cost, tint_scale
from ntp_engine.refine.settings import TUNING, RefineSettings


def _prior(n: int, **weights) -> Prior:
    z = torch.zeros(n, dtype=torch.float64)
    base = dict(
        n_prior=torch.zeros(n, 3, dtype=torch.float64),
        n_w=0.0,
        la0=torch.full((n, 2), -2.0, dtype=torch.float64),
        la_w=z,
        rs0=torch.full((n, 3), 0.5, dtype=torch.float64),
        rs_w=z,
        tie_w=z,
        tint_w=0.0,
    )
    base.update(weights)
    return Prior(**base)


def test_each_pull_is_zero_at_its_centre_and_half_chi_square_away_from_it():
    p = torch.zeros(2, 11, dtype=torch.float64)
    p[:, P_LOGA] = -2.0
    p[:, P_RHO_S] = 0.5
    one = torch.ones(2, dtype=torch.float64)
    prior = _prior(2, la_w=one * 4.0, rs_w=one * 2.0, tie_w=one, tint_w=1.0)
    assert (prior_cost(p, prior) == 0).all()
    q = p.clone()
    q[0, 3] += 0.5  # log alpha_x off by 0.5: 0.5 * 4 * 0.25 from the alpha pull, 0.5 * 1 * 0.25 from the tie
    q[1, 8] += 0.3  # rho_s red off by 0.3: the rho_s pull and the tint pull
    c = prior_cost(q, prior)
    assert abs(c[0].item() - (0.5 + 0.125)) < 1e-12
    spread = ((q[1, 8:] - q[1, 8:].mean()) ** 2).sum()
    expected = 0.5 * 2.0 * 0.09 + 0.5 * tint_scale(q[1:, 8:])[0] * spread
    assert abs(c[1].item() - expected.item()) < 1e-12


def test_the_tint_pull_is_relative_to_the_lobes_brightness_above_its_floor():
    rs = torch.tensor([[0.0, 0.0, 0.0], [4.0, 4.0, 4.0], [8.0, 8.0, 8.0]], dtype=torch.float64)
    s = tint_scale(rs)
    assert abs(s[0].item() - 1 / TUNING.solver.tint_floor**2) < 1e-12
    assert 3.9 < (s[1] / s[2]).item() < 4.0  # ~ 1 / mean^2 well above the floor


def test_the_normals_pull_centres_on_the_start_or_on_the_mesh():
    frame = torch.eye(3, dtype=torch.float64).roll(1, 0).expand(2, 3, 3).clone()  # n = +x
    at_start = normal_prior(frame, dataclasses.replace(RefineSettings(), normal_prior_at_mesh=False))
    at_mesh = normal_prior(frame, dataclasses.replace(RefineSettings(), normal_prior_at_mesh=True))
    assert (at_start == frame[:, 2]).all()
    assert (at_mesh == torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)).all()
