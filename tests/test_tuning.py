"""docs/tuning.md is generated from the code's constants and their comments, and is up to date."""

from pathlib import Path

import tuning_table


def test_the_tuning_table_is_up_to_date():
    assert tuning_table.DOC.read_text(encoding="utf-8") == tuning_table.table(), (
        "docs/tuning.md is out of date: run `python tools/tuning_table.py`"
    )


def test_each_constant_is_read_with_its_reason_and_classified(tmp_path: Path):
    src = tmp_path / "m.py"
    src.write_text(
        "# spread of the noise, 1.4826 x the MAD\n"
        "A = 1.4826\n"
        "B = 4  # 3 -> 4 moved the knot's tangents 9 -> 6 deg\n"
        "C = 1 << 20  # entries per batch: ~100 MB\n"
        "D = 0.3\n"
        "_E = 2  # private: not a tunable\n"
    )
    rows = {r["names"][0]: r for r in tuning_table.constants(src)}
    assert set(rows) == {"A", "B", "C", "D"}
    assert [rows[k]["kind"] for k in "ABCD"] == ["derived", "measured", "budget", "unexplained"]
    assert rows["A"]["reason"] == "spread of the noise, 1.4826 x the MAD" and rows["C"]["value"] == "1 << 20"
