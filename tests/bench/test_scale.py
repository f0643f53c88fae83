import json

import pytest

from ntp_engine.bench import scale
from ntp_engine.cli import main
from ntp_engine.io.errors import NtpInputError


def test_one_small_cell_times_and_measures_every_stage_by_each_path(tmp_path):
    out = tmp_path / "b"
    argv = ["bench", "scale", "--out", str(out), "--photos", "6", "--resolutions", "16", "--scale", "0.1"]
    assert main([*argv, "--paths", "fast", "refine", "--json", str(tmp_path / "s.json")]) == 0
    fast, refined = json.loads((tmp_path / "s.json").read_text())["cells"]
    assert (fast["path"], refined["path"]) == ("fast", "refine")
    for cell in (fast, refined):
        assert cell["photos"] == 6 and cell["resolution"] == 16 and cell["entries"] > 0
        assert set(cell["seconds"]) == set(scale.STAGES) and all(v >= 0 for v in cell["seconds"].values())
        # the child's own memory is seen (torch alone is > 100 MB) and the high-water mark bounds it
        assert 0.1 < max(cell["peak_anon_gb"].values()) <= cell["high_water_gb"]
        assert 0 < cell["material_texels_per_s"] and 0 <= cell["relit_ssim"] <= 1 and cell["diffuse_rmse"] >= 0
    assert fast["seconds"]["refine"] == 0 < refined["seconds"]["refine"]
    assert fast["material_texels_per_s"] == fast["fit_texels_per_s"] > refined["material_texels_per_s"]
    assert (out / "results" / "p6_r16_refine" / "report.json").is_file()
    assert (out / "bench_scale.png").is_file()  # the plot goes into the bench's folder, not the cwd


def test_an_unknown_path_is_refused(tmp_path):
    with pytest.raises(NtpInputError, match="paths from fast, distil, refine"):
        scale.run(tmp_path / "b", (6,), (16,), paths=("slow",))
    assert not (tmp_path / "b").exists()


def test_the_running_stage_is_read_from_the_progress_lines(tmp_path):
    log = tmp_path / "p.jsonl"
    assert scale._stage(log) == "select"

    def line(stage, done, total):
        with open(log, "a") as f:
            f.write(json.dumps({"stage": stage, "done": done, "total": total}) + "\n")

    for args, now in [
        (("blur check", 3, 10), "select"),
        (("blur check", 10, 10), "atlas"),
        (("atlas", 0, 1), "atlas"),
        (("atlas", 1, 1), "traces"),
        (("visibility", 1, 10), "traces"),
        (("traces", 10, 10), "traces"),
        (("trace table", 4, 16), "traces"),
        (("trace table", 16, 16), "fit"),
        (("network + fit", 5, 90), "fit"),
        (("network + fit", 90, 90), "maps"),
        (("refine", 10, 90), "refine"),
        (("refine", 90, 90), "refine"),
        (("materials", 3, 9), "refine"),
        (("material widths", 2, 9), "refine"),
        (("tangent turns", 9, 9), "refine"),
        (("distil", 800, 800), "refine"),
    ]:
        line(*args)
        assert scale._stage(log) == now, args
