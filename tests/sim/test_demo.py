import json

import pytest

from ntp_engine.io.errors import NtpInputError
from ntp_engine.sim import demo


def test_bad_settings_are_refused_before_any_work(tmp_path):
    with pytest.raises(NtpInputError, match="--views >= 3"):
        demo.run(tmp_path / "d", views=2)
    assert not (tmp_path / "d").exists()


@pytest.mark.slow  # measured over 5 s on 2 cores
def test_a_tiny_demo_with_true_poses_measures_itself(tmp_path):
    s = demo.run(tmp_path / "d", views=6, scale=0.08, resolution=16, known_poses=True, blend=False)
    assert s["pose_error"]["centre_max_m"] < 1e-9 and 0 < s["metrics"]["relit_ssim"] <= 1
    assert json.loads((tmp_path / "d" / "demo.json").read_text())["config"]["poses"] == "ground truth"
    assert s["blender"] == {"skipped": "--no-blend"}
