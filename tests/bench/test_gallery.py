"""The gallery benchmark's machinery on one tiny object (not its accuracy): runs, tables, figure,
failed registrations reported as such, re-runs resume from the cache, bad settings refused."""

import json
from dataclasses import replace

import pytest

from ntp_engine.bench import gallery
from ntp_engine.io.errors import NtpInputError
from ntp_engine.sim.gallery import SETS

TINY = gallery.GallerySettings(
    objects=("box",), scanners=("engine",), views=5, scale=0.05, resolution=16, relit_lights=1, relit_scale=0.05
)


@pytest.mark.slow  # measured over 5 s on 2 cores
def test_tiny_gallery_writes_tables_json_and_figure(tmp_path):
    r = gallery.run(tmp_path, TINY)
    assert [(x["object"], x["scanner"], x["poses"]) for x in r["runs"]] == [
        ("box", "engine", "true"),
        ("box", "engine", "sfm"),
    ]
    true_run = r["runs"][0]
    names = [m["material"] for m in true_run["materials"]]
    assert names == ["lacquer_mirror", "metal_brushed_line", "matte_white", "metal_rough"]
    assert 0 < true_run["relit_ssim"] <= 1 and {"atlas", "traces"} <= set(true_run["stages"])
    # ntp was given the scanner's mesh: what the truth's own maps score on it, beside the result
    assert 0 < true_run["mesh_ceiling"] <= 1
    md = (tmp_path / "gallery.md").read_text()
    assert "| relit SSIM | mesh ceiling |" in md
    assert md.count("| box | metal_rough |") == sum("materials" in x for x in r["runs"])
    sfm = r["runs"][1]
    assert ("failed" in sfm) == ("FAILED" in md)  # 5 tiny photos: SfM may fail, and then says so
    assert json.loads((tmp_path / "gallery.json").read_text())["settings"]["views"] == 5
    assert (tmp_path / "gallery.png").stat().st_size > 10_000

    capture = tmp_path / "scans" / "box-engine" / "ground_truth" / "capture.json"
    stamp = capture.stat().st_mtime_ns
    again = gallery.run(tmp_path, replace(TINY, poses=("true",), budget=True))
    assert capture.stat().st_mtime_ns == stamp  # the scan was kept
    # with the budget: where the relit SSIM is lost, per material and for all of them
    budget = again["runs"][0]["relit_budget"]
    assert [m["material"] for m in budget["materials"]] == [*names, "all"]
    assert budget["relit_ssim"] == pytest.approx(again["runs"][0]["relit_ssim"])
    assert budget["ceiling"] == pytest.approx(budget["relit_ssim"] + budget["materials"][-1]["everything"])
    md = (tmp_path / "gallery.md").read_text()
    assert "| +diffuse | +normal | +lobe | +tangent | +everything |" in md
    assert md.count("| box | engine | true |") == 1 + 5  # the run's row and its 5 budget rows

    # both sets and a second photo count: the tune / validate table and accuracy against photo count
    other = SETS["validate"][0]
    both = gallery.run(tmp_path, replace(TINY, objects=("box", other), poses=("true",), density=(7,)))
    assert [(x["object"], x["set"], x["views"]) for x in both["runs"]] == [
        ("box", "tune", 5),
        ("box", "tune", 7),
        (other, "validate", 5),
        (other, "validate", 7),
    ]
    assert capture.stat().st_mtime_ns == stamp  # the box's 5 photos kept; 7 beside them
    md = (tmp_path / "gallery.md").read_text()
    assert "materials tune / validate" in md and "at 5 / 7 photos" in md
    assert (tmp_path / "gallery-density.png").stat().st_size > 5_000
    assert (tmp_path / "gallery-sets.png").stat().st_size > 5_000


def test_bad_settings_are_refused(tmp_path):
    with pytest.raises(NtpInputError, match="objects from"):
        gallery.run(tmp_path, gallery.settings_for(True, objects=("teapot",)))
    assert gallery.settings_for(True, views=7).views == 7 and gallery.settings_for(False).views == 40


def test_the_sets_choose_the_objects():
    assert gallery.set_objects("tune") == SETS["tune"] and gallery.set_objects("validate") == SETS["validate"]
    assert gallery.set_objects("both", quick=True) == (*SETS["tune"][:2], *SETS["validate"][:2])


def test_tune_and_validate_are_reported_side_by_side_per_material_kind():
    def run(obj, which, materials):
        return {"object": obj, "set": which, "scanner": "engine", "poses": "true", "materials": materials}

    def mat(kind, normal):
        return {"kind": kind, **{m: normal for m in gallery.SET_METRICS}}

    record = {
        "settings": {"views": 40},
        "runs": [
            run("vase", "tune", [mat("lacquer", 1.0), mat("matte", 0.5)]),
            run("box", "tune", [mat("lacquer", 3.0)]),
            run("star-1001", "validate", [mat("lacquer", 4.0), mat("plastic", float("nan"))]),
        ],
    }
    header, rows = gallery._set_rows(record)
    by_kind = {r[3]: r for r in rows}
    assert header[4] == "materials tune / validate" and set(by_kind) == {"lacquer", "matte", "plastic"}
    assert by_kind["lacquer"][4] == "2 / 1" and by_kind["lacquer"][5] == "2 / 4 (+2)"  # means 2 and 4, gap +2
    assert by_kind["matte"][5] == "0.5 / -" and by_kind["plastic"][5] == "- / -"


def test_a_set_is_scanned_by_the_engine_with_true_poses_unless_asked_otherwise():
    import argparse

    p = argparse.ArgumentParser()
    gallery.add_arguments(p)
    assert gallery.settings_from_args(p.parse_args([])).scanners == ("engine", "cycles")
    validate = gallery.settings_from_args(p.parse_args(["--set", "validate"]))
    assert validate.scanners == ("engine",) and validate.poses == ("true",)
    both = gallery.settings_from_args(p.parse_args(["--set", "both", "--scanners", "engine", "cycles"]))
    assert both.scanners == ("engine", "cycles") and len(both.objects) == len(SETS["tune"] + SETS["validate"])


def test_objects_are_named_or_a_set_is_chosen_never_both():
    import argparse

    p = argparse.ArgumentParser()
    gallery.add_object_arguments(p)
    assert gallery.chosen_objects(p.parse_args(["--objects", "vase", "star-1001"])) == ("vase", "star-1001")
    assert (
        gallery.chosen_objects(p.parse_args(["--set", "validate"]), quick=True) == gallery.set_objects("validate")[:2]
    )
    assert gallery.chosen_objects(p.parse_args([])) is None
    with pytest.raises(NtpInputError, match="--objects teapot: not a gallery object"):
        gallery.chosen_objects(p.parse_args(["--objects", "teapot"]))
    with pytest.raises(SystemExit):
        p.parse_args(["--objects", "vase", "--set", "tune"])


def test_the_mesh_ntp_is_given_is_a_setting_with_its_own_scans(tmp_path):
    from pathlib import Path

    assert gallery.DEFAULT.mesh == "scanner"  # a shape scanner's mesh, as a user has (the paper's Fig. 11)
    scanner = gallery.scan_folder(Path("g"), gallery.DEFAULT, "vase", "engine")
    truth = gallery.scan_folder(Path("g"), replace(gallery.DEFAULT, mesh="true"), "vase", "engine")
    assert scanner == Path("g/scans/vase-engine") and truth == Path("g/scans/vase-engine-truemesh")
    # ... and its own results, whichever bench reconstructs them
    true_mesh = replace(gallery.DEFAULT, mesh="true", refine=True)
    assert gallery.result_folder(Path("g"), true_mesh, "vase", "engine", "sfm", 120) == Path(
        "g/results/vase-engine-sfm-v120-truemesh-refined"
    )
    assert gallery.result_folder(Path("g"), gallery.DEFAULT, "vase", "engine", "true", 40) == Path(
        "g/results/vase-engine-true"
    )
    import argparse

    from ntp_engine.bench import refine, registration

    for bench in (gallery, registration, refine):
        p = argparse.ArgumentParser()
        bench.add_arguments(p)
        assert p.parse_args(["--mesh", "true"]).mesh == "true" and p.parse_args([]).mesh is None
    with pytest.raises(NtpInputError, match="mesh from scanner, true"):
        gallery.run(tmp_path, replace(TINY, mesh="perfect"))


def test_accuracy_against_photo_count_per_set_and_kind(tmp_path):
    from pathlib import Path

    assert replace(gallery.DEFAULT, density=(360, 120, 40)).photo_counts == (40, 120, 360)
    assert gallery.scan_folder(Path("g"), gallery.DEFAULT, "vase", "engine", 360) == Path("g/scans/vase-engine-v360")
    assert gallery.scan_folder(Path("g"), gallery.DEFAULT, "vase", "engine", 40) == Path("g/scans/vase-engine")

    def run(views, which, normal):
        m = {"kind": "lacquer", **{k: normal for k in gallery.SET_METRICS}}
        return {"object": "o", "set": which, "views": views, "scanner": "engine", "poses": "true", "materials": [m]}

    record = {
        "settings": {"views": 40},
        "runs": [run(40, "tune", 2.0), run(120, "tune", 1.0), run(40, "validate", 3.0)],
    }
    header, rows = gallery._density_rows(record)
    assert header[5] == "normal_deg at 40 / 120 photos"
    assert rows == [
        ("engine", "true", "fast", "tune", "lacquer", *["2 / 1"] * len(gallery.SET_METRICS)),
        ("engine", "true", "fast", "validate", "lacquer", *["3 / -"] * len(gallery.SET_METRICS)),
    ]
    assert gallery._set_rows(record)[1][0][4] == "1 / 1"  # the set table is at the settings' count only
    gallery.density_figure(record, tmp_path / "d.png")
    assert (tmp_path / "d.png").stat().st_size > 5_000
    with pytest.raises(NtpInputError, match="3 to 100000 photos"):
        gallery.run(tmp_path / "x", replace(TINY, density=(2,)))


def test_each_path_reconstructs_into_its_own_results_from_the_first_ones_traces(tmp_path):
    """``--paths fast refine``: one run per path, each into its own results; the refinement's run
    takes the first path's select / atlas / traces stages (hard links, used because their keys
    match) instead of assembling the traces again."""
    settings = replace(TINY, poses=("true",), paths=("fast", "refine"))
    r = gallery.run(tmp_path, settings)
    assert [(x["path"], "refine" in x["stages"]) for x in r["runs"]] == [("fast", False), ("refine", True)]
    fast = gallery.result_folder(tmp_path, settings.on_path("fast"), "box", "engine", "true", 5)
    refined = gallery.result_folder(tmp_path, settings.on_path("refine"), "box", "engine", "true", 5)
    assert fast != refined
    report = json.loads((refined / "report.json").read_text())
    assert set(gallery.SHARED_STAGES) <= set(report["cached_stages"])
    table = refined / "cache" / "traces" / "entries.npy"
    assert table.stat().st_ino == (fast / "cache" / "traces" / "entries.npy").stat().st_ino
    assert "refine" not in json.loads((fast / "report.json").read_text())["stages"]
