import json

from ntp_engine.bench import scale
from ntp_engine.cli import main


def test_one_small_cell_times_and_measures_every_stage(tmp_path):
    out = tmp_path / "b"
    argv = ["bench", "scale", "--out", str(out), "--photos", "6", "--resolutions", "16", "--scale", "0.1"]
    assert main([*argv, "--json", str(tmp_path / "s.json")]) == 0
    (cell,) = json.loads((tmp_path / "s.json").read_text())["cells"]
    assert cell["photos"] == 6 and cell["resolution"] == 16 and cell["entries"] > 0
    assert set(cell["seconds"]) == set(scale.STAGES) and all(v >= 0 for v in cell["seconds"].values())
    # the child's own memory is seen (torch alone is > 100 MB) and the high-water mark bounds it
    assert 0.1 < max(cell["peak_anon_gb"].values()) <= cell["high_water_gb"]
    assert (out / "bench_scale.png").is_file()  # the plot goes into the bench's folder, not the cwd


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
    ]:
        line(*args)
        assert scale._stage(log) == now, args
