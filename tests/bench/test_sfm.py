import json

import pytest

from ntp_engine.bench import sfm


@pytest.mark.slow  # measured over 5 s on 2 cores
def test_the_mappers_run_on_one_scan_and_are_timed_against_the_incremental_one(tmp_path):
    record = sfm.run(tmp_path / "b", photos=(60,), mappers=("incremental", "hierarchical"))
    rows = record["runs"]
    assert [r["mapper"] for r in rows] == ["incremental", "hierarchical"] and all(r["photos"] == 60 for r in rows)
    for r in rows:
        assert "failed" not in r, r
        assert r["seconds"] > 0 and r["registered"] >= 30 and r["centre_mm"] <= r["centre_max_mm"]
        assert r["centre_mm"] < 10.0  # SfM's own error at 153 x 128 px, after the best similarity
    table = (tmp_path / "b" / "sfm.md").read_text()
    assert "| 60 | incremental |" in table and "| 1.00 |" in table
    assert json.loads((tmp_path / "b" / "sfm.json").read_text())["runs"] == rows
    assert (tmp_path / "b" / "scans" / "dome-60" / "scan.toml").is_file()  # kept for the next run


def test_a_failed_mapper_is_a_row_of_the_table():
    rows = [
        {
            "photos": 60,
            "mapper": "incremental",
            "seconds": 2.0,
            "registered": 40,
            "centre_mm": 1.0,
            "centre_max_mm": 3.0,
            "rotation_deg": 0.2,
        },
        {"photos": 60, "mapper": "global", "seconds": 3.0, "failed": "only 2 photos registered (need 3)"},
    ]
    table = sfm._table(rows)
    assert "| 60 | global | FAILED: only 2 photos registered (need 3) | 3 | 1.50 |" in table
    assert "| 60 | incremental | 40 | 2 | 1.00 | 1.00 / 3.00 | 0.200 |" in table
