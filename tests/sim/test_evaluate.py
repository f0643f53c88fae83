import shutil

import numpy as np
import pytest

from ntp_engine.io.assets import DEMO_DIR
from ntp_engine.sim.evaluate import compare_images, pose_error, relit_ssim


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
