"""The refinement's solver: the albedos' linear start recovers known albedos at the true geometry,
and Levenberg-Marquardt lowers every texel's cost from a wrong lobe width and recovers it."""

import math

import torch
from refine.test_policy import DEV, _traces

from ntp_engine.refine.gauss_newton import N_PARAMS
from ntp_engine.refine.model import P_LOGA, P_RHO_D, P_RHO_S, Round, Start, Trace, parameters
from ntp_engine.refine.priors import Prior
from ntp_engine.refine.settings import RefineSettings, SensorNoise
from ntp_engine.refine.solver import albedo_start, levenberg_marquardt


def _true_round(n: int, seed: int, rho_d, rho_s, alpha, alpha_factor: float = 1.0):
    entries, mask, p = _traces(n, seed, rho_d, rho_s, alpha, noise=0.0)
    alphas = torch.stack([p["alpha_x"], p["alpha_y"]], 1) * alpha_factor
    start = Start(p["n_local"], p["t_local"], alphas, torch.zeros(n, 3), torch.zeros(n, 3))
    tr = Trace(DEV, entries, mask, SensorNoise(), None)
    frame, q = parameters(start, tr.y.dtype)  # the trace's precision, as the refinement's own calls
    return tr, frame, q, p


def test_the_albedo_start_recovers_the_albedos_at_the_true_geometry():
    tr, frame, q, p = _true_round(12, 31, (0.5, 0.3, 0.2), (1.0, 0.8, 0.6), (0.2, 0.2))
    rnd = Round(tr, frame, q[:, P_LOGA], True)
    out = albedo_start(rnd, q, True)
    assert (out[:, P_RHO_D] - p["rho_d"]).abs().max() < 0.03
    rel = (out[:, P_RHO_S] - p["rho_s"]).abs() / p["rho_s"]
    assert (rel.amax(1) < 0.15).sum() >= 3, rel
    diffuse_only = albedo_start(rnd, q, False)
    assert (diffuse_only[:, P_RHO_S] == 0).all()


def test_levenberg_marquardt_lowers_each_cost_and_finds_the_lobes_width():
    tr, frame, q, p = _true_round(12, 32, (0.3, 0.3, 0.3), (2.0, 2.0, 2.0), (0.15, 0.15), alpha_factor=2.0)
    settings = RefineSettings()
    rnd = Round(tr, frame, q[:, P_LOGA], True)
    q0 = albedo_start(rnd, q, True)
    prior = Prior.weak(frame, q0, settings)
    free = torch.ones(len(q0), N_PARAMS, dtype=torch.bool)
    _, cost0, _ = levenberg_marquardt(rnd, q0, prior, free, 0, settings)
    q1, cost1, _ = levenberg_marquardt(Round(tr, frame, q0[:, P_LOGA], True), q0, prior, free, 20, settings)
    assert (cost1 <= cost0 + 1e-9).all() and (cost1 < 0.5 * cost0).float().mean() > 0.5
    got = q1[:, P_LOGA].exp()
    assert ((got / 0.15).log().abs().median(0).values < 0.5 * math.log(2.0)).all()  # started log 2 off
