"""The `ntp` command line as a user runs it (a real subprocess)."""

import base64
import json
import subprocess
import sys

import numpy as np
import pytest

from ntp_engine.io.assets import DEVICES_DIR
from ntp_engine.io.images import read_image
from ntp_engine.pipeline.result_page import VIEWER_BUNDLE
from ntp_engine.scanner.device_file import DEFAULT_DEVICE


def ntp(*args, cwd=None):
    return subprocess.run([sys.executable, "-m", "ntp_engine.cli", *args], capture_output=True, text=True, cwd=cwd)


def test_help_lists_commands():
    out = ntp("--help")
    assert out.returncode == 0
    for cmd in ("demo", "device", "bench"):
        assert cmd in out.stdout


def test_demo_runs_end_to_end_and_reports_errors(tmp_path):
    d = tmp_path / "demo"
    out = ntp(
        "demo", "--out", str(d), "--views", "8", "--scale", "0.1", "--resolution", "24", "--known-poses", "--quiet",
        "--no-refine",
    )  # fmt: skip
    assert out.returncode == 0, out.stderr
    assert "relit_ssim" in out.stdout and "normal_median_deg" in out.stdout
    summary = json.loads((d / "demo.json").read_text())
    m = summary["metrics"]
    assert 0 < m["relit_ssim"] <= 1 and 0 <= m["normal_median_deg"] < 20 and m["coverage"] > 0.5
    assert summary["pose_error"]["centre_max_m"] < 1e-9  # the true poses were used
    assert (d / "result" / "normal.exr").is_file() and (d / "scan" / "ground_truth" / "poses.json").is_file()
    assert summary["blender"]["blend"].endswith("asset.blend") and (d / "asset.glb").is_file()  # bpy is installed
    relit = read_image(d / "relit" / "relit_0.png")
    assert relit.shape[1] > relit.shape[0] and np.isfinite(relit).all()  # truth | reconstruction
    page = d / "result" / "index.html"  # the result page, with the .glb in it (where npm built the viewer)
    assert summary["page"] == str(page) and page.is_file()
    if VIEWER_BUNDLE.is_file():
        glb = page.read_text().split('"glb": "', 1)[1].split('"', 1)[0]
        assert base64.b64decode(glb) == (d / "asset.glb").read_bytes()
    view = ntp("view", str(d / "result"), "--glb", str(d / "asset.glb"), "--no-open")
    assert view.returncode == 0 and view.stdout.strip() == str(page), view.stderr
    bad = ntp("view", str(d), "--no-open")  # the demo folder, not a result
    assert bad.returncode == 2 and len(bad.stderr.strip().splitlines()) == 1 and "not an ntp result" in bad.stderr
    # a second run reuses the scan and every cached stage
    again = ntp(
        "demo",
        "--out",
        str(d),
        "--views",
        "8",
        "--scale",
        "0.1",
        "--resolution",
        "24",
        "--known-poses",
        "--quiet",
        "--no-blend",
        "--no-refine",
    )
    assert again.returncode == 0, again.stderr
    rep = json.loads((d / "result" / "report.json").read_text())
    assert rep["cached_stages"] == ["select", "atlas", "traces", "fit"]
    assert not json.loads((d / "demo.json").read_text())["config"]["refine"]
    assert not (d / "result" / "uncertainty.exr").exists()
    # by default: the same cached stages, then the refinement (its uncertainties, its report)
    refined = ntp(
        "demo", "--out", str(d), "--views", "8", "--scale", "0.1", "--resolution", "24", "--known-poses", "--quiet",
        "--no-blend",
    )  # fmt: skip
    assert refined.returncode == 0, refined.stderr
    rep = json.loads((d / "result" / "report.json").read_text())
    assert rep["cached_stages"] == ["select", "atlas", "traces", "fit"] and "refine" in rep["stages"]
    assert json.loads((d / "demo.json").read_text())["config"]["refine"]
    assert (d / "result" / "uncertainty.exr").is_file() and 0 < rep["refine"]["matte_share"] < 1
    assert [p.name for p in d.rglob(".*")] == [".ntp"] * 3  # no temporary files: the markers of demo, scan, result


@pytest.mark.slow  # measured over 5 s on 2 cores
def test_bad_device_is_one_line_error_exit_2(tmp_path):
    bad = tmp_path / "broken.toml"
    bad.write_text('name = "x"\n[camera]\nwidth = "wide"\n')
    out = ntp("device", str(bad))
    assert out.returncode == 2
    lines = out.stderr.strip().splitlines()
    assert len(lines) == 1 and "broken.toml" in lines[0] and "camera.width" in lines[0]
    out = ntp("device", str(tmp_path / "missing.toml"))
    assert out.returncode == 2 and "missing.toml" in out.stderr and "Traceback" not in out.stderr


def test_device_list_and_bench_through_the_command_line(tmp_path):
    out = ntp("device", "--list")
    assert out.returncode == 0 and "area_light.toml" in out.stdout
    js = tmp_path / "stab.json"
    out = ntp("bench", "stability", "--samples", "8000", "--json", str(js))
    assert out.returncode == 0, out.stderr
    assert json.loads(js.read_text())["samples"] == 8000


def test_progress_file_gets_json_lines_for_each_stage(tmp_path):
    prog = tmp_path / "progress.jsonl"
    out = ntp(
        "virtual-scan",
        "--out",
        str(tmp_path / "scan"),
        "--views",
        "2",
        "--scale",
        "0.05",
        "--quiet",
        "--progress",
        str(prog),
    )
    assert out.returncode == 0, out.stderr
    records = [json.loads(line) for line in prog.read_text().splitlines()]
    assert records[0]["stage"] == "virtual scan" and records[-1]["done"] == records[-1]["total"] == 2
    assert out.stderr == ""  # --quiet: no bars


def test_cycles_scan_and_gallery_refuse_bad_input(tmp_path):
    narrow = tmp_path / "narrow.toml"
    text = DEFAULT_DEVICE.read_text().replace("exponent = 1.0", "exponent = 3.0")
    narrow.write_text(text.replace('pattern = "', f'pattern = "{DEVICES_DIR}/'))
    out = ntp("virtual-scan", "--out", str(tmp_path / "s"), "--renderer", "cycles", "--device", str(narrow))
    lines = out.stderr.strip().splitlines()
    assert out.returncode == 2 and len(lines) == 1 and "narrow.toml" in lines[0] and "Lambertian" in lines[0]
    assert not (tmp_path / "s").exists()
    out = ntp(
        "virtual-scan", "--out", str(tmp_path / "s"), "--renderer", "cycles", "--samples", "8", "--max-samples", "4"
    )
    lines = out.stderr.strip().splitlines()
    assert out.returncode == 2 and len(lines) == 1 and "max-samples" in lines[0] and not (tmp_path / "s").exists()
    out = ntp("bench", "gallery", "--out", str(tmp_path / "g"), "--objects", "teapot")
    assert out.returncode == 2 and "teapot" in out.stderr and not (tmp_path / "g").exists()
