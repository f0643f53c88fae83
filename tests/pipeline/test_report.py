"""report.json from typed sections: the file's layout, a section no stage filled left out, a round trip."""

import json
import time

from ntp_engine.pipeline.report import PhotoCounts, RefineSummary, Report, TexelCounts, TraceCounts


def _finished() -> Report:
    rep = Report(scan="/scans/vase")
    rep.stages["select"] = 0.5
    rep.photos = PhotoCounts(40, 38, {"0003.png": 2.1}, ["0007.png"])
    rep.registration = {"source": "poses file", "unregistered": []}
    rep.traces = TraceCounts(9000, 12000, 37, 3, {"grazing": 10})
    rep.refine = RefineSummary(noise_scale=1.4, basis_materials=2)
    rep.texels = TexelCounts(4096, 4000, 4000 / 4096, 12, 64)
    rep.model = {"name": "default"}
    rep.cached_stages, rep.recomputed_damaged_stages, rep.seconds = ["select"], [], 12.5
    rep.photos.used = 37
    return rep


def test_the_sections_are_written_in_the_files_order_with_unset_fields_left_out():
    data = _finished().to_json()
    assert list(data) == [
        "scan", "stages", "photos", "registration", "traces", "refine", "texels", "model",
        "cached_stages", "recomputed_damaged_stages", "seconds",
    ]  # fmt: skip
    assert list(data["photos"]) == ["total", "kept", "blurry", "unreadable", "used"]
    assert data["refine"] == {"noise_scale": 1.4, "basis_materials": 2}  # what the refinement did not compute: absent
    assert data["texels"]["coverage"] == 4000 / 4096 and data["traces"]["rejected"] == {"grazing": 10}


def test_a_registration_alone_writes_only_its_sections():
    rep = Report()
    rep.timed("select", time.perf_counter())
    rep.photos = PhotoCounts(3, 3, {}, [])
    rep.registration = {"source": "poses file"}
    assert list(rep.to_json()) == ["stages", "photos", "registration"] and rep.stages["select"] >= 0


def test_a_report_read_back_from_its_json_is_the_same_report():
    rep = _finished()
    back = Report.from_json(json.loads(json.dumps(rep.to_json())))
    assert back == rep and isinstance(back.texels, TexelCounts) and back.refine.matte_share is None
