"""The `ntp` command line as a user runs it (a real subprocess)."""
import json
import subprocess
import sys

import numpy as np

from ntp_engine.images import read_image


def ntp(*args, cwd=None):
    return subprocess.run([sys.executable, "-m", "ntp_engine.cli", *args], capture_output=True, text=True, cwd=cwd)


def test_help_lists_commands():
    out = ntp("--help")
    assert out.returncode == 0
    for cmd in ("demo", "device", "bench"):
        assert cmd in out.stdout


def test_demo_writes_lumitexels_and_measurement(tmp_path):
    out = ntp("demo", "--out", str(tmp_path / "demo"))
    assert out.returncode == 0, out.stderr
    assert "ntp-led-32x16" in out.stdout
    d = tmp_path / "demo"
    diffuse, specular, leds = (read_image(d / f) for f in ("lumitexel_diffuse.png", "lumitexel_specular.png",
                                                          "measurement_per_led.png"))
    assert diffuse.shape == (3 * 8 * 16, 4 * 8 * 16, 3) and specular.shape == (3 * 32 * 4, 4 * 32 * 4, 3)
    assert leds.shape == (16 * 16, 32 * 16, 3)
    assert specular.max() == 1.0 and leds.max() == 1.0 and np.isfinite(leds).all()
    summary = json.loads((d / "demo.json").read_text())
    assert len(summary["measurement_B"]) == 3 and all(b > 0 for b in summary["measurement_B"])
    assert 0.0 <= summary["highlight_confidence_beta"] <= 1.0
    assert not list(d.glob(".*"))  # no temporary files left behind


def test_bad_device_is_one_line_error_exit_2(tmp_path):
    bad = tmp_path / "broken.toml"
    bad.write_text('name = "x"\n[camera]\nwidth = "wide"\n')
    out = ntp("device", str(bad))
    assert out.returncode == 2
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1 and "broken.toml" in lines[0] and "camera.width" in lines[0]
    out = ntp("demo", "--out", str(tmp_path / "d"), "--device", str(tmp_path / "missing.toml"))
    assert out.returncode == 2 and "missing.toml" in out.stderr and "Traceback" not in out.stderr


def test_device_list_and_small_stability_run(tmp_path):
    out = ntp("device", "--list")
    assert out.returncode == 0 and "area_light.toml" in out.stdout
    js = tmp_path / "stab.json"
    out = ntp("bench", "stability", "--samples", "40000", "--json", str(js))
    assert out.returncode == 0, out.stderr
    r = json.loads(js.read_text())
    assert r["samples"] == 40000 and r["nonfinite"] == 0 and r["total"]["max_rel_err"] < 1e-4
    assert all(case["samples"] > 0 for case in r["cases"].values())
    js = tmp_path / "phys.json"
    out = ntp("bench", "physics", "--json", str(js))
    assert out.returncode == 0, out.stderr
    r = json.loads(js.read_text())
    assert all(r[dt][k] > 0 for dt in ("float32", "float64") for k in ("brdf_evals_per_s", "lumitexels_per_s"))
