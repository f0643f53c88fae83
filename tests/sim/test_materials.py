"""Gallery materials: the paper's ranges, labelled painting, tangent fields, label files."""

import numpy as np
import pytest

from ntp_engine.io.errors import NtpInputError
from ntp_engine.io.images import write_png
from ntp_engine.sim.materials import LIBRARY, Material, load_labels, paint, save_labels, value_noise
from ntp_engine.sim.shapes import SHAPES


def test_library_spans_the_papers_ranges():
    ms = list(LIBRARY.values())
    rho_d = [c for m in ms for c in m.rho_d]
    assert min(rho_d) <= 0.02 and max(rho_d) >= 0.9
    assert any(m.matte for m in ms) and max(max(m.rho_s) for m in ms) == 10.0
    alphas = [a for m in ms for a in m.alpha]
    assert min(alphas) == 0.006 and max(alphas) >= 0.48
    assert max(m.anisotropy for m in ms) >= 80
    kinds = {m.tangents for m in ms}
    assert {"circular", "radial", "direction", "noisy"} <= kinds
    assert {"blocks", "noise", "print"} <= {m.texture for m in ms}


def _paint(materials, labeller, res=64):
    return paint(SHAPES["vase"](), materials, labeller, res)


def test_paint_puts_each_material_where_the_labeller_says():
    mats = [LIBRARY["matte_white"], LIBRARY["metal_brushed_dark"]]
    maps, labels = _paint(mats, lambda tex: (tex.position[:, 2] > 0.05).astype(int))
    assert set(np.unique(labels)) == {0, 1}
    matte, metal = labels == 0, labels == 1
    assert maps.specular_albedo[matte].max() == 0 and np.allclose(maps.specular_albedo[metal], [8, 7, 6])
    assert np.allclose(maps.roughness[metal], [0.48, 0.006])
    assert 0.9 * 0.55 * 0.8 - 1e-9 <= maps.diffuse_albedo[matte].min() and maps.diffuse_albedo[matte].max() <= 0.9
    # unit, orthogonal frames
    np.testing.assert_allclose(np.linalg.norm(maps.tangent, axis=-1), 1, atol=1e-9)
    assert np.abs((maps.tangent * maps.normal).sum(-1)).max() < 1e-6


def test_circular_tangents_run_around_the_vertical_axis():
    maps, labels = _paint([LIBRARY["metal_brushed_dark"]], lambda tex: np.zeros(len(tex), int))
    t = maps.tangent.reshape(-1, 3)
    assert np.median(np.abs(t[:, 2])) < 0.05  # horizontal on the vase's near-vertical walls


def test_alpha_noise_varies_alpha_within_a_factor_of_two():
    maps, _ = _paint([LIBRARY["plastic_rough"]], lambda tex: np.zeros(len(tex), int))
    a = maps.roughness[..., 0]
    assert a.max() / a.min() > 1.3 and a.max() <= 0.35 * 2**0.5 + 1e-9 and a.min() >= 0.35 / 2**0.5 - 1e-9


def test_value_noise_is_smooth_and_in_range():
    p = np.random.default_rng(0).uniform(-0.1, 0.1, (2000, 3))
    v = value_noise(p, 0.01, 1)
    assert v.min() >= 0 and v.max() <= 1 and v.std() > 0.05
    near = value_noise(p + 1e-5, 0.01, 1)
    assert np.abs(near - v).max() < 0.01


def test_labels_round_trip_and_bad_label_files(tmp_path):
    mats = [LIBRARY["matte_white"], Material("x", (0.1, 0.1, 0.1), (1.0, 1.0, 1.0), (0.1, 0.2))]
    labels = np.array([[0, 1], [1, 0]], np.uint8)
    save_labels(tmp_path, labels, mats)
    back, table = load_labels(tmp_path)
    np.testing.assert_array_equal(back, labels)
    assert [m["name"] for m in table] == ["matte_white", "x"] and table[0]["matte"] and table[1]["anisotropy"] == 2
    write_png(tmp_path / "labels.png", np.full((2, 2, 1), 5 / 255))
    with pytest.raises(NtpInputError, match="labels.png.*label 5"):
        load_labels(tmp_path)
    (tmp_path / "materials.json").unlink()
    with pytest.raises(NtpInputError, match="materials.json"):
        load_labels(tmp_path)


def test_kind_classifies_by_the_parameters():
    from ntp_engine.sim.materials import LIBRARY, Material

    assert LIBRARY["matte_white"].kind == "matte" and LIBRARY["metal_brushed_dark"].kind == "aniso_metal"
    assert LIBRARY["metal_rough"].kind == "dark_metal" and LIBRARY["lacquer_mirror"].kind == "lacquer"
    assert Material("p", (0.5, 0.2, 0.1), (1.0, 1.0, 1.0), (0.1, 0.1)).kind == "plastic"
    assert Material("n", (0.5, 0.5, 0.5), (0.3, 0.3, 0.3), (0.4, 0.4)).kind == "near_matte"
