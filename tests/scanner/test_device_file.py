import hashlib
from pathlib import Path

import numpy as np
import pytest
import torch

from ntp_engine.scanner.device_file import DEFAULT_DEVICE, DeviceFileError, list_devices, load_scanner, save_scanner


def test_shipped_devices_load():
    names = {p.stem: load_scanner(p) for p in list_devices()}
    assert {"ntp_led_32x16", "point_light", "linear_light", "area_light"} <= set(names)
    kinds = {d.emitter_kind for d in names.values()}
    assert kinds == {"point", "linear", "area"}
    assert load_scanner().name == "ntp-led-32x16"


def test_default_device_is_the_papers_scanner():
    d = load_scanner()
    assert d.num_emitters == 512 and d.grid_shape == (32, 16)
    assert (d.width, d.height) == (2448, 2048) and d.fx == pytest.approx(2345)
    p = d.emitter_positions
    u, v, n = d.emitter_axes[0], np.cross(d.emitter_normals[0], d.emitter_axes[0]), d.emitter_normals[0]
    # row-major order, 1 cm pitch, 31 cm x 15 cm between the outer LED centres
    np.testing.assert_allclose(p[1] - p[0], 0.01 * u, atol=1e-6)
    np.testing.assert_allclose(p[32] - p[0], 0.01 * v, atol=1e-6)
    assert np.linalg.norm(p[31] - p[0]) == pytest.approx(0.31, abs=1e-5)
    assert np.linalg.norm(p[-1] - p[-32]) == pytest.approx(0.31, abs=1e-5)
    assert np.linalg.norm(p[-32] - p[0]) == pytest.approx(0.15, abs=1e-5)
    centre = p.mean(0)
    # valid volume: 15 cm cube centred 30 cm in front of the panel centre
    np.testing.assert_allclose(d.valid_center, centre + 0.30 * n, atol=1e-5)
    np.testing.assert_allclose(d.valid_size, [0.15] * 3)
    # the camera (origin) sits at the middle of the panel's top edge and looks at the volume centre
    np.testing.assert_allclose(centre - 0.08 * v, 0.0, atol=1e-5)
    np.testing.assert_allclose(d.valid_center[:2], 0.0, atol=1e-5)
    inside = d.in_valid_volume(
        torch.tensor(np.stack([d.valid_center, d.valid_center + 0.07 * n, d.valid_center + 0.08 * n]))
    )
    assert inside.tolist() == [True, True, False]


def test_save_load_round_trip_leaves_input_untouched(tmp_path):
    before = hashlib.sha256(DEFAULT_DEVICE.read_bytes()).hexdigest()
    for path in list_devices():
        d = load_scanner(path)
        save_scanner(d, tmp_path / path.name)
        d2 = load_scanner(tmp_path / path.name)
        for key, value in vars(d).items():
            if isinstance(value, np.ndarray):
                np.testing.assert_allclose(getattr(d2, key), value, atol=1e-12, err_msg=key)
            elif key != "source":
                assert getattr(d2, key) == value, key
    assert hashlib.sha256(DEFAULT_DEVICE.read_bytes()).hexdigest() == before


BAD = [
    ("fx = 2345.0", 'fx = "abc"', "camera.fx"),
    ("width = 2448\n", "", "camera.width"),
    ("fy = 2345.0", "fy = 2345.0\nfxx = 1.0", "camera.fxx"),
    ('kind = "point"', 'kind = "laser"', "emitters.kind"),
    ("PATTERN_LINE", "pattern = [[1.0, 1.0, 1.0]]", "pattern"),
    ("PATTERN_LINE", 'pattern = "missing.csv"', "pattern"),
    ("count = [32, 16]", "count = [32, 0]", "emitters.count"),
    ("size = [0.15, 0.15, 0.15]", "size = [0.15, -1.0, 0.15]", "valid_volume.size"),
    ("exponent = 1.0", "exponent = -2.0", "emitters.angular.exponent"),
    ("[valid_volume]", "[valid_volume\n", "not valid TOML"),
    ("gain = 0.000543", "gain = 0.000543\nmax_exposure = 0.5", "camera.max_exposure"),
]


@pytest.mark.parametrize("old,new,needle", BAD)
def test_malformed_device_gives_one_line_error_naming_file_and_key(tmp_path, old, new, needle):
    text = DEFAULT_DEVICE.read_text()
    if old == "PATTERN_LINE":  # whatever pattern the default device ships with
        old = next(line for line in text.splitlines() if line.startswith("pattern ="))
    assert old in text
    bad = tmp_path / "bad_device.toml"
    bad.write_text(text.replace(old, new, 1))
    with pytest.raises(DeviceFileError) as info:
        load_scanner(bad)
    msg = str(info.value)
    assert "\n" not in msg and str(bad) in msg and needle in msg


def test_missing_file_and_out_of_range_pattern(tmp_path):
    with pytest.raises(DeviceFileError, match="no such device file"):
        load_scanner(tmp_path / "nope.toml")
    text = (Path(DEFAULT_DEVICE).parent / "point_light.toml").read_text()
    (tmp_path / "p.toml").write_text(text.replace('pattern = "full_on"', "pattern = [[1.5, 0.0, 0.0]]"))
    with pytest.raises(DeviceFileError, match=r"key 'pattern': values must be in \[0, 1\]"):
        load_scanner(tmp_path / "p.toml")


def test_pattern_file_and_angular_table(tmp_path):
    text = (Path(DEFAULT_DEVICE).parent / "point_light.toml").read_text()
    (tmp_path / "pat.csv").write_text("0.25,0.5,1.0\n")
    text = text.replace('pattern = "full_on"', 'pattern = "pat.csv"')
    text = text.replace(
        'kind = "cosine"\nexponent = 1.0', 'kind = "table"\nangles_deg = [0.0, 60.0, 80.0]\nvalues = [1.0, 0.5, 0.1]'
    )
    (tmp_path / "dev.toml").write_text(text)
    d = load_scanner(tmp_path / "dev.toml")
    np.testing.assert_allclose(d.pattern, [[0.25, 0.5, 1.0]])
    cos = torch.cos(torch.deg2rad(torch.tensor([0.0, 30.0, 60.0, 70.0, 85.0, 120.0], dtype=torch.float64)))
    np.testing.assert_allclose(d.psi(cos).numpy(), [1.0, 0.75, 0.5, 0.3, 0.0, 0.0], atol=1e-9)
