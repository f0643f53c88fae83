"""The per-texel fit record: defaults for unseen texels, a copy that owns its arrays, and a round
trip through the stage cache's .npz with and without the refinement's extras."""

import numpy as np

from ntp_engine.fit.geometry import FALLBACK_ALPHA
from ntp_engine.fit.texel_fit import TexelFit


def test_unseen_texels_get_the_defaults():
    fit = TexelFit.defaults(3)
    assert len(fit) == 3
    np.testing.assert_array_equal(fit.n_loc, [[0, 0, 1]] * 3)
    np.testing.assert_array_equal(fit.t_loc, [[1, 0, 0]] * 3)
    np.testing.assert_array_equal(fit.alpha, FALLBACK_ALPHA)
    assert fit.std is None and fit.material is None and (fit.rho_s == 0).all()


def test_a_copy_owns_its_arrays():
    fit = TexelFit.defaults(2)
    fit.std = np.zeros((2, 4))
    other = fit.copy()
    other.rho_d[0] = 0.5
    other.std[1] = 1.0
    assert (fit.rho_d == 0).all() and (fit.std == 0).all()


def test_the_record_round_trips_through_npz(tmp_path):
    plain = TexelFit.defaults(4)
    plain.save(tmp_path / "fit.npz")
    back = TexelFit.load(tmp_path / "fit.npz")
    assert set(back.arrays()) == {"n_loc", "t_loc", "alpha", "flags", "rho_d", "rho_s"}
    refined = TexelFit.defaults(4)
    refined.std, refined.highlight = np.ones((4, 4)), np.full(4, 0.5)
    refined.noise_scale, refined.normal_prior_at_mesh = 1.7, True
    refined.material = np.array([0, -1, -2, 0])
    refined.materials = {"material_share": np.array([0.5]), "material_alpha": np.array([[0.3, 0.1]])}
    refined.matte_share, refined.width_varies = 0.25, np.array([False])
    refined.save(tmp_path / "refined.npz")
    back = TexelFit.load(tmp_path / "refined.npz")
    assert back.noise_scale == 1.7 and back.normal_prior_at_mesh is True and back.matte_share == 0.25
    assert back.materials is not None and set(back.materials) == {"material_share", "material_alpha"}
    for k, v in refined.arrays().items():
        np.testing.assert_array_equal(back.arrays()[k], v, err_msg=k)
