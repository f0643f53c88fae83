"""The registration's tuned constants (``RegistrationTuning``, one section per part: the photo stack,
the photometric refinement, the check, the refusal, the mesh alignment, SfM and COLMAP import, the
marker board), every
value declared with its provenance (``io.tuned``; the table of them all is ``docs/tuning.md``,
generated from here).

Every measurement so far was made on the gallery's five objects (and the demo) at 40 photos: the
tuning set. A value of kind *unmeasured* is a choice that no measurement backs yet.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..io.tuned import budget, derived, measured, unmeasured

REGISTRATION_BENCH = "the gallery's registrations (40 photos): ntp bench registration"


@dataclass(frozen=True)
class StackTuning:
    """The photos as the photometric registration reads them (``register.photo_stack``)."""

    code_range: tuple[float, float] = derived((6.0, 249.0), "8-bit codes used: above the noise floor, below clipping")
    max_working_width: int = budget(
        640, "photos are averaged down to at most this width (a registration needs no more)"
    )
    shading_cells: tuple[int, int] = unmeasured(
        (8, 4), "the emitters are merged into this many groups along the array's two axes"
    )


@dataclass(frozen=True)
class PhotometricTuning:
    """The photometric refinement of a registration (``register.photometric``)."""

    surface_points: int = budget(3000, "surface samples of a PhotometricRegistration by default")
    candidate_points: int = budget(1500, "... that compare the candidate azimuths (on the sweep's photos)")
    fine_points: int = measured(
        8000,
        "... and that refine the chosen one: its error is sampling noise (3000 points left 1.10 mm / 0.36 deg, "
        "8000 points 0.54 mm / 0.14 deg)",
        on="the gallery dome, 40 photos: " + REGISTRATION_BENCH,
    )
    blur_levels_px: tuple[float, ...] = measured(
        (2.0, 1.0, 0.5),
        "Gaussian sigma of the photos per level, pixels of the working size: the coarse level widens the basin, "
        "the finest takes out the blur's own bias (at the dome's true poses the cost's minimum lies 0.20 deg off "
        "in azimuth at sigma 1 px, 0.04 deg at 0.5 px)",
        on="the gallery dome at its true poses: " + REGISTRATION_BENCH,
    )
    cauchy_log: float = unmeasured(0.1, "scale of the robust loss on log residuals (10%)")
    agree_log: float = unmeasured(0.1, "an observation within 10% of its point's albedo and photo's field agrees")
    edge_clearance: float = derived(
        2.0, "points used lie this many blur sigmas (+ 1 px) from every edge of the mesh's image: 95% of the blur"
    )
    min_views: int = derived(
        3, "a point enters the cost once this many photos see it: its albedo is fitted, 3 leave it 2 residuals"
    )
    max_rounds: int = budget(5, "re-linearisations per blur level")
    settled_rad: float = budget(2e-4, "a round that turns the pose less than this (rad) ...")
    settled_m: float = budget(5e-5, "... and moves it less than this (m) ends the level")
    azimuth_grid_deg: np.ndarray = budget(
        np.arange(-4.0, 4.01, 0.25), "searched before the first level's descent: a quarter degree, +-4 deg"
    )
    max_log_scale: float = unmeasured(
        0.2,
        "a correction scales the point cloud's alignment within 20% (and shifts it within max_shift): beyond, the "
        "alignment was wrong, not imprecise. Unbounded, the descent wandered off on an untextured body of "
        "revolution (scale x2.5) until no photo saw the mesh; the bound's value was not measured",
    )
    max_shift: float = unmeasured(0.25, "a correction's shift at most, in object sizes (see max_log_scale)")
    height_pixel_m: float = measured(
        0.75e-3,
        "photos this sharp at the object move the height too (frees_height): between the demo's working pixel "
        "(0.53 mm) and the gallery's (1.05 mm)",
        on="the demo (ntp demo) and " + REGISTRATION_BENCH,
    )
    sharpness_shift_px: float = derived(
        4.0, "the registration moved this far along each mesh axis for its sharpness: beyond the edge clearance"
    )
    sharpness_sigma_px: float = measured(
        1.0,
        "the blur the sharpness is measured at (refusal.min_sharpness was set at this blur)",
        on=REGISTRATION_BENCH,
    )
    edge_grid_width: int = budget(
        320, "the mesh's image (for edge distances) is cast on a grid at most about this wide"
    )
    patch_radius_px: float = derived(
        1.0,
        "a texture patch's samples lie this far (working pixels) from its centre: one blur sigma at the sharpness's "
        "blur (sharpness_sigma_px), far enough for the texture to differ, near enough for the shading not to",
    )
    patch_offsets: tuple[tuple[float, float], ...] = derived(
        ((0.0, 0.0), (1.0, 0.0), (-1.0, 0.0), (0.0, 1.0), (0.0, -1.0)),
        "a texture patch: its centre and four neighbours along the tangent plane's two axes (in patch radii)",
    )


@dataclass(frozen=True)
class CheckTuning:
    """The check of a registration against its rivals (``register.check``)."""

    candidate_rounds: int = budget(2, "re-linearisations a candidate gets before the candidates are compared")
    max_photos: int = budget(40, "photos (evenly spread over the sweep) that judge and refine a registration")
    sweep_step_deg: float = derived(
        3.0,
        "the whole-circle azimuth sweep's step: within the coarse refinement's own azimuth grid (+-4 deg), so a "
        "rival's basin is not stepped over",
    )
    sweep_photos: int = budget(20, "the sweep is a scout: fewer photos ...")
    sweep_points: int = budget(1000, "... fewer points ...")
    sweep_edge_stride: int = budget(3, "... and a coarser edge map")
    rivals: int = budget(3, "the sweep's best other azimuths (more than align.ambiguous_deg apart) refined as rivals")
    symmetry_px: float = unmeasured(
        0.25, "a turned mesh lying closer to itself than this (at the object's distance) is a symmetry"
    )


@dataclass(frozen=True)
class RefusalTuning:
    """When a registration is refused (``register.refusal``)."""

    min_sharpness: float = measured(
        0.8,
        "right registrations had sharpness >= 1.01 and margin >= 0.73; wrong ones that were not a symmetry of the "
        "mesh sharpness <= 0.48 (docs/pipeline.md)",
        on=REGISTRATION_BENCH,
    )
    min_margin: float = unmeasured(0.5, "the best other azimuth must fit the photos at least 50% worse")


@dataclass(frozen=True)
class AlignTuning:
    """The alignment of an SfM cloud to the mesh (``register.align``)."""

    inlier_fraction: float = unmeasured(
        0.006, "of the object's size: an SfM point this close to the mesh is an inlier (1 mm at 16 cm)"
    )
    surface_samples: int = budget(200_000, "mesh surface samples the cloud's distances are measured to")
    coarse_azimuths_deg: np.ndarray = derived(
        np.arange(0, 360, 10), "the whole circle, 10 deg apart: within the fine search's +-8 deg"
    )
    fine_azimuths_deg: np.ndarray = budget(np.arange(-8, 8.01, 0.25), "around the best coarse one, a quarter degree")
    ambiguous_deg: float = unmeasured(15.0, "candidates further than this from the best are alternatives to it")
    symmetry_step_deg: float = budget(1.0, "the turns a mesh is tried under for a symmetry (then refined to 0.05 deg)")
    symmetry_samples: int = budget(5000, "surface samples a turned mesh is compared with itself on")


@dataclass(frozen=True)
class SfmTuning:
    """Structure from motion (``register.sfm``) and COLMAP import (``register.colmap_model``)."""

    min_registered: int = unmeasured(3, "photos a scan needs registered")
    global_from_photos: int = measured(
        300,
        "``auto`` maps this many photos or more with the global mapper, fewer with the incremental one",
        on="ntp bench sfm (docs/pipeline.md)",
    )
    focal_tolerance: float = unmeasured(
        0.02, "a COLMAP model's focal length this far off the device file's is refused (relative)"
    )


@dataclass(frozen=True)
class BoardTuning:
    """Camera poses from the marker board (``register.board_poses``, ``register.board_fallback``)."""

    corner_offset_px: float = measured(
        0.5,
        "OpenCV 4.10's ChArUco corners lie this far right of and below the integer-centre convention (+0.49-0.50 "
        "px in x and y on boards drawn at known positions, 1-3.3 px/mm, turned 0-60 deg); subtracted. Left in, "
        "the demo on the board registered 2.0 mm / 0.46 deg off and was refused; taken out, 0.29 mm / 0.04 deg",
        on="boards drawn by Board.albedo (tests/register/test_board_poses.py) and the demo on an A4 board, 40 photos",
    )
    min_corners: int = derived(
        6, "a planar pose has 6 unknowns and each corner 2 equations: 6 corners leave 6 residuals to judge it by"
    )
    outlier_z: float = derived(
        3.5, "a corner beyond this many robust sigmas of its photo's residuals is dropped (Iglewicz and Hoaglin)"
    )
    noise_floor_px: float = measured(
        0.05,
        "the robust sigma is never taken below this: corners of engine renders scatter 0.04-0.07 px RMS",
        on="the demo on an A4 board (virtual scanner, quarter size, 40 photos)",
    )
    fallback_reach: int = derived(
        5, "photos the board misses are mapped by SfM with this many neighbours a side (SfM's sequential pairing: 10)"
    )
    max_anchor_rms_px: float = unmeasured(
        2.0,
        "SfM's model joins the board frame when its photos that the board placed lie within this (at the object) "
        "of their board poses; measured 1.4 px on the demo at quarter size",
    )


@dataclass(frozen=True)
class TriangulationTuning:
    """Surface points triangulated from the board's poses (``register.triangulate``) and the mesh
    placed on them (``register.align.align_on_board``, ``register.check.cloud_check``)."""

    features_per_photo: int = budget(4000, "SIFT features kept per photo (the strongest): bounds the matching's time")
    max_feature_width: int = budget(
        1280,
        "SIFT reads a photo averaged down by a whole factor to at most this width: the device's full 2448 px cost "
        "~2.5 s a photo (40 photos: 53 s of a 1000-photo board registration); the points' placement was measured "
        "at 612 px (docs/pipeline.md), and its floor is the scanned mesh's deformation, not the features' precision",
    )
    contrast_threshold: float = unmeasured(
        0.02, "SIFT's contrast threshold (OpenCV's default 0.04 keeps half as many features on printed labels)"
    )
    neighbours: int = budget(4, "each photo is matched with this many others nearest in viewing direction")
    max_pair_deg: float = unmeasured(40.0, "photos further apart than this in viewing direction are not matched")
    ratio: float = derived(0.8, "Lowe's ratio test: a match this much closer than the second best (Lowe 2004)")
    max_reprojection_px: float = derived(
        1.0, "a triangulated point reprojects within this of the feature in both photos (SIFT's ~0.3 px, ~3 sigma)"
    )
    min_parallax_deg: float = derived(
        2.0, "rays closer than this in angle set depth to worse than ~0.5 mm at 0.3 m from a 0.3 px feature"
    )
    search_points: int = budget(
        600, "object (and board) points the azimuth search scores every start on; the polish takes all"
    )
    search_samples: int = budget(
        20_000, "mesh surface samples the azimuth search measures to (the polish: all of align.surface_samples)"
    )
    search_iterations: int = budget(15, "ICP iterations per start azimuth of the search (the winner is then polished)")
    tukey: float = derived(4.685, "Tukey's biweight constant in robust sigmas: 95% efficiency on Gaussian residuals")
    azimuth_pull: float = measured(
        1e-3,
        "the polish pulls the placement to the search's answer by this fraction of its best-seen direction's "
        "curvature: holds an azimuth the points do not see (a body of revolution: 1e-6 let it wander 51 deg in the "
        "jackknife) and kept the polish from drifting along a near-round shape's shallow azimuth on a scanned mesh "
        "(camera error dome 2.28 -> 0.47 mm, blob 0.62 -> 0.42 mm against no pull)",
        on="the tuning set's dome and blob on an A4 board, scanner's mesh, 40 photos at quarter size",
    )
    jackknife_blocks: int = derived(
        16, "regions of the surface the placement's spread is measured over (block jackknife): enough for a variance"
    )
    max_spread_px: float = derived(
        0.5,
        "a placement by points is confirmed where its 1-sigma spread (block jackknife: the shift plus the azimuth's "
        "at the object's rim) is at most this at the object's distance: 2 sigma within a pixel",
    )
    min_points: int = unmeasured(
        30,
        "fewer object points within the inlier distance of the placed mesh leave the placement to the photometric "
        "check",
    )
    min_inlier_fraction: float = unmeasured(
        0.25,
        "of the object points: fewer within the inlier distance of the placed mesh leave the placement to the "
        "photometric check (the blob on the board: 48% with the scanner's mesh)",
    )
    min_margin: float = derived(
        3.0,
        "a rival azimuth must fit the points worse by this many standard errors (its paired score difference "
        "over the spread between jackknife_blocks surface regions): a one-sided test at 0.1% were the regions' "
        "totals independent and normal (0.45% by Student's t with 15 degrees of freedom). Points counted as "
        "independent made revolution-1000 on a 0.1 mm-noise mesh, 19 deg off, 47 chi-square units sure "
        "(docs/pipeline.md)",
    )


@dataclass(frozen=True)
class SilhouetteTuning:
    """The board as a backdrop: the object's outline where a photo shows the print
    (``register.silhouette``)."""

    print_texel_mm: float = budget(0.2, "the print is rasterised at this texel (a working pixel is ~0.5 mm)")
    min_paper_px: int = unmeasured(
        500, "a photo with fewer white-paper pixels than this has no gain fit (sees no print)"
    )
    gain_rounds: int = budget(8, "reweightings of the print's gain fit")
    ink_floor: float = derived(
        0.05,
        "relative residuals are over the prediction plus this share of the gain: the ink's albedo (0.04) "
        "and a margin, so the black print's noise does not count as not seen",
    )
    seen_sigmas: float = unmeasured(
        5.0,
        "a pixel shows the print where each channel lies within this many robust sigmas of the gain fit's "
        "relative residual",
    )
    points: int = budget(2000, "mesh surface samples the sweep scores a placement's outline on")
    fine_points: int = budget(8000, "... and the distinct minima are refined and compared on")
    cap_px: float = unmeasured(
        8.0,
        "penetrations are capped softly here (pixels) when placements are compared: a point deeper than the "
        "object's outline could be is wrong, whatever its depth",
    )
    sweep_cap_px: float = unmeasured(20.0, "... and under this wider cap in the sweep (a basin for the shift)")
    sweep_step_deg: float = unmeasured(10.0, "the sweep's start azimuths are this far apart")
    sweep_rounds: int = budget(4, "Levenberg-Marquardt rounds per start of the sweep")
    final_rounds: int = budget(10, "... and per distinct minimum after it")
    jacobian_rad: float = budget(1e-3, "the numerical Jacobian's step in azimuth")
    jacobian_m: float = budget(1e-4, "... and along the board")
    rivals: int = budget(3, "distinct minima besides the best refined and compared with it")
    rim_cos: float = derived(
        0.1,
        "a surface point is on a photo's contour generator where its normal is this close to perpendicular to "
        "the view: on a 40 mm radius it projects within ~0.2 mm (r cos^2 / 2) of the outline",
    )
    fit_px: float = derived(2.0, "a surface point deeper than this into seen print lies outside the object's outline")
    jackknife_blocks: int = derived(
        16, "regions of the surface the placement's spread is measured over (as triangulation.jackknife_blocks)"
    )
    jackknife_rounds: int = budget(3, "Levenberg-Marquardt rounds per region left out, from the answer")
    max_outside: float = measured(
        0.05,
        "a placement fits the outline where at most this share of its points lie deeper than fit_px into print "
        "a photo sees: right placements 0.006-2.1% (a dark object over the ink reads as print), the demo's mesh "
        "made 5% wider 12.5% (25% wider: 24%); about the geometric mean of the two",
        on="the tuning set on an A4 board (scanner's mesh, 40 photos at quarter size: ntp bench registration "
        "--board A4) and the demo's mesh widened (tests/register/test_silhouette.py's scan)",
    )
    max_spread_px: float = derived(
        0.5,
        "... and its 1-sigma spread (block jackknife: the shift plus the turn's at the rim) is at most this at "
        "the object's distance: 2 sigma within a pixel (as triangulation.max_spread_px)",
    )
    min_significance: float = derived(
        3.0,
        "a rival azimuth must fit the outlines worse by this many standard errors over photos (paired): "
        "one-sided 0.1% were the photos' differences independent and normal (as triangulation.min_margin)",
    )


@dataclass(frozen=True)
class RegistrationTuning:
    """The registration's tuned constants, one section per part (fixed per release; ``docs/tuning.md``)."""

    stack: StackTuning = field(default_factory=StackTuning)
    photometric: PhotometricTuning = field(default_factory=PhotometricTuning)
    check: CheckTuning = field(default_factory=CheckTuning)
    refusal: RefusalTuning = field(default_factory=RefusalTuning)
    align: AlignTuning = field(default_factory=AlignTuning)
    sfm: SfmTuning = field(default_factory=SfmTuning)
    board: BoardTuning = field(default_factory=BoardTuning)
    triangulation: TriangulationTuning = field(default_factory=TriangulationTuning)
    silhouette: SilhouetteTuning = field(default_factory=SilhouetteTuning)


TUNING = RegistrationTuning()
