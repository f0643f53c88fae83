import torch

from ntp_engine.fit.baseline import fit_geometry_lbfgsb
from ntp_engine.fit.geometry import fit_geometry, lumitexel_log_rmse
from ntp_engine.learn.synthetic import _random_orthogonal, sample_brdfs
from ntp_engine.physics.frame import safe_normalize
from ntp_engine.physics.lumitexel import specular_lumitexel


def _lobes(n_tex=256, seed=0, tilt=0.15):
    g = torch.Generator().manual_seed(seed)
    p = sample_brdfs(n_tex, g)
    z = torch.zeros(n_tex, 3)
    z[:, 2] = 1
    n = safe_normalize(z + _random_orthogonal(z, g) * (tilt * torch.randn(n_tex, 1, generator=g)))
    t = _random_orthogonal(n, g)
    rho = p["rho_s"].mean(-1)
    m = specular_lumitexel(n, t, rho[:, None], p["alpha_x"], p["alpha_y"])[..., 0]
    return m, n, t, p["alpha_x"], p["alpha_y"], rho


def _angle(a, b):
    return torch.rad2deg(torch.acos((a * b).sum(-1).clamp(-1, 1)))


def test_baseline_fits_exact_lumitexels():
    m, n, t, ax, ay, rho = _lobes(2, seed=4)
    f = fit_geometry_lbfgsb(m)
    assert _angle(f.normal, n).max() < 0.5
    fb = fit_geometry(m)
    assert lumitexel_log_rmse(fb, m).mean() <= lumitexel_log_rmse(f, m).mean() + 1e-4
