import pytest

from ntp_engine.bench import gallery, registration
from ntp_engine.io.progress import QUIET


@pytest.mark.slow  # measured over 5 s on 2 cores
def test_registration_runs_per_seed_and_reuses_the_kept_sfm_model(tmp_path):
    settings = gallery.settings_for(True, objects=("dome",), scanners=("engine",), views=24)
    first = registration.run(tmp_path / "g", settings, seeds=(0,))
    (row,) = first["runs"]
    assert row["object"] == "dome" and row["seed"] == 0 and "failed" not in row, row
    assert row["seconds_sfm"] > 0 and row["registered"] >= 12 and row["centre_mm"] >= 0
    assert (tmp_path / "g" / "sfm" / "dome-engine-s0" / "cameras.bin").is_file()
    assert row["sharpness"] == row["sharpness"] and row["accepted"] in (True, False) and row["seconds_photometric"] > 0
    assert row["accepted"] == (row["refusal"] is None)
    assert row["kind"] in ("accepted", "unconfirmed", "ambiguous") and row["diagnosis"]
    assert len(row["candidate_rotation_deg"]) >= 1
    assert row["symmetry_mm"] is None or row["symmetry_mm"] > 0.3  # the dome has no symmetry
    assert row["equivalent_turns"] == [] and row["symmetry"] is None and row["truth_turn_deg"] == 0.0
    # the second cue and the statistics a right registration of this scan scores
    assert row["texture_centre_mm"] >= 0 and row["texture_rotation_deg"] >= 0 and row["cues_apart_mm"] >= 0
    assert row["truth_sharpness"] > 0 and row["truth_texture_sharpness"] > 0 and row["texture_sharpness"] > -1
    table = (tmp_path / "g" / "registration.md").read_text()
    assert table.count("\n") == 5 and "wrong accepted:" in table and "right refused:" in table
    # a rerun reads the kept model back instead of running SfM again (the registration after it is
    # the same code as above: not run twice here)
    again, seconds = registration._sfm(
        tmp_path / "g" / "scans" / "dome-engine", tmp_path / "g" / "sfm" / "dome-engine-s0", 0, QUIET
    )
    assert seconds == 0.0 and len(again.poses) == row["registered"] and len(again.points) > 100


def test_diagnosis_names_wrong_acceptances_and_where_the_truth_was():
    base = {"right": False, "chosen": 0, "rival": 1, "candidate_rotation_deg": [30.0, 2.0], "rotation_deg": 29.0}
    assert registration._diagnosis({**base, "kind": "accepted"}) == "WRONG ACCEPTED"
    assert registration._diagnosis({**base, "kind": "accepted", "right": True}) == "right"
    assert registration._diagnosis({**base, "kind": "unconfirmed", "right": True}) == "RIGHT REFUSED (unconfirmed)"
    assert "truth at rival (2.0 deg)" in registration._diagnosis({**base, "kind": "ambiguous"})
    assert registration._diagnosis({**base, "kind": "ambiguous", "candidate_rotation_deg": [9.0, 8.0]}).endswith(
        "neither"
    )


def test_the_symmetry_cell_counts_equivalent_placements():
    row = {"symmetry_mm": 0.01, "symmetry_turn_deg": -180.0}
    assert registration._symmetry_cell({**row, "equivalent_turns": [-180.0]}) == "-180 / 0.01 (2 placements)"
    assert registration._symmetry_cell({**row, "equivalent_turns": None}) == "every turn"
    assert registration._symmetry_cell({"symmetry_mm": None, "equivalent_turns": []}) == "-"


def test_the_outcome_is_summed_per_set_when_both_ran():
    def row(obj, which, right, accepted):
        return {"object": obj, "set": which, "right": right, "accepted": accepted}

    rows = [row("vase", "tune", True, True), row("star-1001", "validate", True, False)]
    assert "right refused: 1" in registration._summary(rows, "")
    assert registration._summary(rows[:1], "tune: ").startswith("tune: 1 registrations: right and accepted 1")
    assert "**wrong accepted: 0; right refused: 1**" in registration._summary(rows[1:], "validate: ")
