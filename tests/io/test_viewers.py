import numpy as np

from ntp_engine.io.viewers import CYCLES_PRINCIPLED_MAX_ANISOTROPY, beyond_principled


def test_beyond_principled_is_past_cycles_ten_to_one():
    s2 = 1 - 0.9  # Cycles' Principled at Anisotropic = 1: alpha_x / alpha_y = 1 / s^2
    assert np.isclose(1 / s2, CYCLES_PRINCIPLED_MAX_ANISOTROPY)
    alpha = np.array([[0.5, 0.006], [0.006, 0.5], [0.3, 0.031], [0.2, 0.2], [0.01, 0.0999]])
    assert beyond_principled(alpha).tolist() == [True, True, False, False, False]


def test_khronos_inputs_give_back_the_alphas_a_conforming_viewer_draws():
    from ntp_engine.io.viewers import khronos_alphas, khronos_inputs

    hi = np.array([0.48, 0.3, 0.2, 0.006, 1.0])
    lo = np.array([0.006, 0.025, 0.2, 0.006, 0.01])  # 1:80, the dome's gold, isotropic twice, at alpha 1
    t, b = khronos_alphas(*khronos_inputs(hi, lo))
    assert np.allclose(t, hi) and np.allclose(b, lo)
    r, s = khronos_inputs(np.array([0.2]), np.array([0.2]))
    assert r == np.sqrt(0.2) and s == 0.0  # isotropic: no strength


def test_base_colour_for_fresnel_mix_gives_rho_d_back_after_the_viewers_one_minus_f():
    from ntp_engine.io.viewers import GLTF_DIELECTRIC_F0, base_colour_for_fresnel_mix

    rho_d = np.array([[0.5, 0.2, 0.1], [0.9, 0.9, 0.9], [0.3, 0.3, 0.3]])
    rho_s = np.array([[1.0, 1.0, 1.0], [5.0, 5.0, 5.0], [0.0, 0.0, 0.0]])
    base, clipped = base_colour_for_fresnel_mix(rho_d, rho_s)
    f0 = GLTF_DIELECTRIC_F0 * rho_s  # glTF's F at v.h = 1 with the exported specular
    assert np.allclose((base * (1 - f0))[[0, 2]], rho_d[[0, 2]])  # no lobe: unchanged
    assert clipped.tolist() == [False, True, False] and base.max() == 1.0  # 0.9 / 0.8 > 1: clipped, said
