import json

from ntp_engine.io.progress import QUIET, Progress, read_progress


def test_json_lines_name_the_stage_and_count_to_the_total(tmp_path):
    path = tmp_path / "p.jsonl"
    p = Progress(json_path=path, min_interval_s=0.0)
    assert list(p.track(range(3), "traces", unit="photo")) == [0, 1, 2]
    records, offset = read_progress(path)
    assert [r["done"] for r in records] == [0, 1, 2, 3, 3]
    assert records[-1] == {**records[-1], "stage": "traces", "total": 3, "unit": "photo", "eta_s": 0.0}
    assert offset == path.stat().st_size and read_progress(path, offset) == ([], offset)


def test_throttled_lines_and_partial_lines_wait(tmp_path):
    path = tmp_path / "p.jsonl"
    with Progress(json_path=path, min_interval_s=3600).counter("fit", 1000, "texel") as c:
        for _ in range(1000):
            c.update()
    records, offset = read_progress(path)
    assert [r["done"] for r in records] == [0, 1000]  # start and end only
    with open(path, "a") as fh:
        fh.write(json.dumps({"stage": "x"})[:5])  # a line still being written
    assert read_progress(path, offset) == ([], offset)
    assert read_progress(tmp_path / "none.jsonl") == ([], 0)


def test_quiet_writes_nothing(tmp_path, capsys):
    assert list(QUIET.track([1, 2], "x")) == [1, 2]
    assert capsys.readouterr().err == "" and not list(tmp_path.iterdir())


def test_warn_is_one_line_on_stderr(capsys):
    from ntp_engine.io.progress import warn

    warn("photos/0003.png: truncated\n  — skipped")
    assert capsys.readouterr().err == "ntp: warning: photos/0003.png: truncated — skipped\n"
