from lobes import angle_deg, exact_lobes

from ntp_engine.fit.baseline import fit_geometry_lbfgsb
from ntp_engine.fit.geometry import fit_geometry, lumitexel_log_rmse


def test_baseline_fits_exact_lumitexels():
    m, n, t, ax, ay, rho = exact_lobes(2, seed=4)
    f = fit_geometry_lbfgsb(m)
    assert angle_deg(f.normal, n).max() < 0.5
    fb = fit_geometry(m)
    assert lumitexel_log_rmse(fb, m).mean() <= lumitexel_log_rmse(f, m).mean() + 1e-4
