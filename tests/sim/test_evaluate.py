import shutil

import numpy as np
import pytest

from ntp_engine.io.assets import DEMO_DIR
from ntp_engine.io.errors import NtpInputError
from ntp_engine.io.images import write_exr
from ntp_engine.io.maps import SVBRDFMaps
from ntp_engine.sim.evaluate import compare_images, material_errors, pose_error, relit_ssim
from ntp_engine.sim.gallery import build_asset
from ntp_engine.sim.materials import load_labels


def test_identical_renders_score_one_and_differences_lower_it():
    rng = np.random.default_rng(0)
    a = rng.random((24, 32, 3))
    mask = np.zeros((24, 32), bool)
    mask[4:20, 4:28] = True
    same = compare_images(a, a.copy(), mask)
    assert same["ssim"] == pytest.approx(1.0) and same["psnr_db"] > 100
    assert compare_images(a, 0.5 * a, mask)["ssim"] < 0.95


def test_pose_error_in_metres_and_degrees():
    eye = np.eye(4)
    moved = np.eye(4)
    moved[:3, 3] = [0.003, 0.0, 0.004]  # camera centre 5 mm away
    c, s = np.cos(np.radians(2)), np.sin(np.radians(2))
    turned = np.eye(4)
    turned[:2, :2] = [[c, -s], [s, c]]
    err = pose_error({"a": moved, "b": turned, "x": eye}, {"a": eye, "b": eye})
    assert err["centre_max_m"] == pytest.approx(0.005) and err["rotation_max_deg"] == pytest.approx(2.0)
    assert pose_error({"x": eye}, {"a": eye}) == {}


def test_the_truth_relit_against_itself_is_perfect(tmp_path):
    result = tmp_path / "result"
    shutil.copytree(DEMO_DIR / "ground_truth", result)
    shutil.copy(DEMO_DIR / "mesh.obj", result / "mesh.obj")
    r = relit_ssim(result, DEMO_DIR / "mesh.obj", DEMO_DIR / "ground_truth", lights=1, scale=0.05, save_dir=tmp_path)
    assert r["relit_ssim"] == pytest.approx(1.0) and (tmp_path / "relit_0.png").is_file()


def _result_from_truth(tmp_path, name="vase", res=32, observed=None):
    asset = build_asset(name, tmp_path / "asset", res)
    result = tmp_path / "result"
    shutil.copytree(asset / "ground_truth", result)
    conf = np.ones((res, res, 3))
    if observed is not None:
        conf[..., 1] = observed
    write_exr(result / "confidence.exr", conf)
    return result, asset / "ground_truth"


def test_material_errors_of_the_truth_are_zero(tmp_path):
    result, truth = _result_from_truth(tmp_path)
    rows = material_errors(result, truth)
    assert [r["material"] for r in rows] == ["matte_print", "plastic_glossy", "metal_brushed_dark", "lacquer_mirror"]
    for r in rows:
        assert r["coverage"] == 1 and r["normal_deg"] < 0.5 and r["rho_d_rmse"] < 0.05
        assert r["rho_d_ratio"] == pytest.approx(1, abs=0.05)
    matte, _, metal, mirror = rows
    assert matte["spurious_lobe"] == 0 and np.isnan(matte["log_alpha"]) and np.isnan(matte["tangent_deg"])
    assert metal["tangent_deg"] < 1 and metal["log_alpha"] < 0.05 and metal["log_rho_s"] < 0.05
    assert np.isnan(mirror["tangent_deg"])  # isotropic: no tangent to score


def test_material_errors_see_each_kind_of_error(tmp_path):
    half = np.zeros((32, 32))
    half[:, :16] = 1  # only the left half observed
    result, truth = _result_from_truth(tmp_path, observed=half)
    labels, _ = load_labels(truth)
    maps = SVBRDFMaps.load(result)
    maps.specular_albedo[labels == 0] = 0.5  # a lobe on matte
    maps.tangent = np.cross(maps.normal, maps.tangent)  # every tangent turned 90 deg
    maps.roughness = maps.roughness * np.e  # alphas e x too large
    maps.diffuse_albedo = maps.diffuse_albedo * 2
    maps.save(result)
    matte, _, metal, _ = material_errors(result, truth)
    assert matte["spurious_lobe"] == 1 and 0.4 < matte["coverage"] < 0.6
    assert matte["rho_d_ratio"] == pytest.approx(2, rel=0.05)
    assert metal["tangent_deg"] == pytest.approx(90, abs=1) and metal["log_alpha"] == pytest.approx(1, abs=0.05)


def test_material_errors_need_labels(tmp_path):
    result, truth = _result_from_truth(tmp_path)
    (truth / "labels.png").unlink()
    with pytest.raises(NtpInputError, match="labels.png"):
        material_errors(result, truth)
