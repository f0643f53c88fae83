"""The registration's tuned values hold the relations their derivations state (register.settings)."""

import numpy as np

from ntp_engine.io.tuned import Kind, provenance
from ntp_engine.register.settings import TUNING, RegistrationTuning


def test_the_searches_grids_leave_no_basin_between_them():
    align, photometric, check = TUNING.align, TUNING.photometric, TUNING.check
    coarse_step = float(np.diff(align.coarse_azimuths_deg).max())
    assert coarse_step / 2 <= align.fine_azimuths_deg.max()  # the fine search reaches half a coarse step
    assert align.coarse_azimuths_deg.min() == 0 and align.coarse_azimuths_deg.max() + coarse_step == 360
    assert check.sweep_step_deg <= photometric.azimuth_grid_deg.max()  # a sweep step lands in the coarse grid
    assert photometric.edge_clearance * photometric.sharpness_sigma_px + 1 <= photometric.sharpness_shift_px


def test_the_scouts_are_smaller_than_what_they_scout_for():
    assert TUNING.check.sweep_photos <= TUNING.check.max_photos
    assert TUNING.check.sweep_points <= TUNING.photometric.candidate_points <= TUNING.photometric.fine_points
    assert sorted(TUNING.photometric.blur_levels_px, reverse=True) == list(TUNING.photometric.blur_levels_px)


def test_every_section_is_listed_with_provenance():
    rows = provenance(RegistrationTuning)
    sections = {r.name.split(".")[0] for r in rows}
    assert sections == {
        "stack",
        "photometric",
        "check",
        "refusal",
        "align",
        "sfm",
        "board",
        "triangulation",
        "silhouette",
    }
    assert {r.kind for r in rows} <= set(Kind)
