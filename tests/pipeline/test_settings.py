"""The pipeline stages' tuned values hold the relations their reasons state (pipeline.settings)."""

from ntp_engine.io.tuned import provenance
from ntp_engine.physics.shadows import MIN_COS_VIEW
from ntp_engine.pipeline.settings import TUNING, PipelineTuning


def test_the_grazing_band_lies_below_the_views_the_network_reads():
    assert 0 < TUNING.traces.min_cos_grazing < MIN_COS_VIEW < 1
    assert 0 < TUNING.traces.max_tap_tilt_deg < 90


def test_the_albedo_check_reads_no_more_entries_than_the_network():
    assert 0 < TUNING.fit.albedo_views <= TUNING.fit.network_views


def test_every_stage_is_a_section_with_provenance():
    assert {r.name.split(".")[0] for r in provenance(PipelineTuning)} == {"select", "traces", "fit", "distil", "run"}
