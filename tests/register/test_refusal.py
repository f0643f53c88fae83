"""The registration the photos cannot confirm is refused, scanned and registered as a user does; a
symmetry of the mesh is named, and refuses nothing by itself (a turned placement is the same asset)."""

import json
import subprocess
import sys
from dataclasses import replace

from scans import hemisphere, run_virtual_scan, uniform_maps

from ntp_engine.io.mesh import save_obj
from ntp_engine.register.check import PhotoCheck
from ntp_engine.register.photometric import PhotometricFit
from ntp_engine.register.refusal import named_rival, refusal, refusal_kind, symmetry_note


def _ntp(*args) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "ntp_engine.cli", *map(str, args)], capture_output=True, text=True)


def test_an_unconfirmed_registration_is_refused_with_its_diagnostics_and_forced_on_request(tmp_path):
    asset = tmp_path / "asset"
    asset.mkdir()
    save_obj(asset / "mesh.obj", hemisphere())
    uniform_maps([0.6, 0.5, 0.4], [0.3, 0.3, 0.3], 0.3, 0.3).save(asset / "maps")
    scan = tmp_path / "scan"
    r = run_virtual_scan(
        scan, "--mesh", asset / "mesh.obj", "--maps", asset / "maps", "--views", "24", "--scale", "0.1"
    )
    assert r.returncode == 0, r.stderr
    out = tmp_path / "rec"
    r = _ntp("register", scan, "--out", out, "--quiet")
    assert r.returncode == 2, (r.stdout, r.stderr)
    (line,) = r.stderr.strip().splitlines()
    # a plain grey hemisphere: every turn is the same placement (said, no rival), but the photos do
    # not pin it down either (measured sharpness 0.38 < 0.8): refused as unconfirmed
    assert "registration refused" in line and "cannot confirm where the mesh is" in line, line
    assert str(out / "registration.json") in line and "--force-registration" in line
    assert "a marker board under the object (ntp board)" in line  # a scan without one is told of it
    reg = json.loads((out / "registration.json").read_text())
    assert reg["confidence"]["accepted"] is False and reg["photometric"]["margin"] is None  # no rival: all equivalent
    assert "body of revolution" in reg["confidence"]["symmetry"]
    assert reg["photometric"]["mesh_symmetry"]["equivalent_turns_deg"] is None
    assert all(c["equivalent"] for c in reg["photometric"]["candidates"])
    assert len(reg["photometric"]["candidates"]) >= 2 and len(reg["alignment"]["candidates"]) == 36
    assert (out / "registration.png").stat().st_size > 1000 and not (out / "poses.json").exists()
    r = _ntp("register", scan, "--out", out, "--quiet", "--force-registration")
    assert r.returncode == 0, r.stderr
    assert "FORCED" in r.stdout and (out / "poses.json").is_file()
    assert json.loads((out / "registration.json").read_text())["registration"]["confidence"]["forced"] is True


def test_refusal_names_the_cause():
    fit = PhotometricFit(1.0, 0.8, 1000, 500)
    confirmed = PhotoCheck(None, fit, 0.9, float("inf"), [], 0, [])  # type: ignore[arg-type]
    assert refusal(confirmed) is None and refusal_kind(confirmed) is None
    rivals = [
        {"azimuth_change_deg": 0.0, "coarse_cost": 1, "mesh_turned_mm": 0.0},
        {"azimuth_change_deg": 90.0, "coarse_cost": 1.2, "mesh_turned_mm": 3.0},
        {"azimuth_change_deg": 180.0, "coarse_cost": 1.01, "mesh_turned_mm": 0.04},
    ]
    close = PhotoCheck(None, fit, 0.9, 0.01, rivals, 0, [])  # type: ignore[arg-type]
    ambiguous = refusal(close)
    assert ambiguous and "turned by 180 deg" in ambiguous and "0.0 mm from itself" in ambiguous  # the best rival
    assert refusal_kind(close) == "ambiguous" and named_rival(rivals) == 2
    flat = PhotoCheck(None, fit, 0.02, 0.01, rivals, 0, [])  # type: ignore[arg-type]
    plain = refusal(flat)
    assert plain and "cannot confirm" in plain and "2% worse" in plain  # a plateau is not an ambiguity
    assert refusal_kind(flat) == "unconfirmed" and named_rival(rivals[:1]) is None
    # a symmetry of the mesh (under a quarter pixel here) refuses nothing: the turned placement is
    # the same asset, never the rival; the symmetry is said
    same = [*rivals[:2], {**rivals[2], "equivalent": True}]
    box = PhotoCheck(None, fit, 2.0, 3.0, same, 0, [], [], (180.0, 0.01), 0.26, equivalent_turns=[-180.0])  # type: ignore[arg-type]
    assert refusal(box) is None and refusal_kind(box) is None and named_rival(same) == 1
    assert symmetry_note(box) == "symmetric under a 180 deg turn: one of 2 equivalent placements (the same asset)"
    assert "body of revolution" in (symmetry_note(replace(box, equivalent_turns=None)) or "")
    assert symmetry_note(replace(box, equivalent_turns=[])) is None
    # a near-symmetry (above the quarter pixel) is a rival: the photos must tell it apart, or it is named
    near = PhotoCheck(None, fit, 2.0, 0.02, rivals, 0, [], [], (180.0, 0.4), 0.26, equivalent_turns=[])  # type: ignore[arg-type]
    assert (why := refusal(near)) and "turned by 180 deg" in why and "from itself" in why


def test_a_refused_board_scan_is_not_told_to_print_a_board():
    from ntp_engine.pipeline.stages import refused_line

    assert "ntp board" in refused_line("the photos cannot confirm it", on_board=False)
    line = refused_line("the photos cannot confirm it", on_board=True)
    assert "ntp board" not in line and "a poses file" in line and "more photos" in line
