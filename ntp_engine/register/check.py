"""A registration checked against the photos (``check_registration``): the photometric refinement
of the alignment (``register.photometric``), its rival azimuths refined and compared, and the
sharpness of the cost around the answer, gathered in a ``PhotoCheck`` that the refusal reads
(``register.refusal``).

Convention: camera_from_mesh poses rigid 4x4 (OpenCV axes); the mesh frame in metres, z up; turns
in degrees about the support's normal.
"""

from __future__ import annotations

import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace

import numpy as np

from ..io.errors import NtpInputError
from ..io.mesh import Mesh, load_mesh
from ..io.progress import QUIET, Progress
from ..io.threads import worker_threads
from ..scanner.local_frame import local_origin, moved
from ..scanner.scan_folder import Scan, read_photo
from .align import (
    Alignment,
    align_on_board,
    align_to_mesh,
    azimuth_apart,
    convergence_point,
    equivalent_turns,
    mesh_symmetry,
    symmetry_profile,
    turned_distance,
    yaw_deg,
)
from .board_poses import BoardPoses, first_placement
from .photo_stack import PhotoStack
from .photometric import (
    Correction,
    PhotometricFit,
    PhotometricRegistration,
    edge_stride,
    frees_height,
    object_distance,
    rotation_matrix,
)
from .settings import TUNING
from .sfm import SfmResult
from .silhouette import SilhouettePlacement, Silhouettes
from .triangulate import Features, photo_features, triangulated_points


@dataclass
class PhotoCheck:
    """A registration chosen, refined and judged by the photos.

    ``fit``: the refined registration's photometric fit; ``sharpness``: how much the cost rises
    (relative) when it is moved ``TUNING.photometric.sharpness_shift_px`` along each mesh axis — a right registration
    is a sharp minimum, a wrong one sits on a plateau of random matches; ``margin``: how much worse
    (relative cost) the best other azimuth fits the photos after the same refinement (inf: none);
    ``candidates``: per candidate its azimuth change from the chosen one, coarse cost, how far
    the mesh turned so lies from itself (mm) and whether it is the chosen placement up to a
    symmetry of the mesh (``equivalent``: within ``TUNING.align.ambiguous_deg`` of 0 or of one of
    ``equivalent_turns`` — the same asset, not a rival); ``profile``:
    the sweep's (turn from the point cloud's alignment in degrees, cost) over the whole circle;
    ``equivalent_turns``: the mesh's symmetries about the vertical (``align.equivalent_turns``: None
    for every turn, a body of revolution)."""

    alignment: Alignment
    fit: PhotometricFit
    sharpness: float
    margin: float
    candidates: list[dict]
    chosen: int  # index of the chosen candidate (0: the point cloud's own alignment)
    profile: list[tuple[float, float]]
    trials: list[Alignment] = field(default_factory=list)  # each candidate after its coarse refinement
    # the mesh's own closest symmetry (turn deg, how far the turned mesh lies from itself in mm) and
    # the distance no photo at this size can see (TUNING.check.symmetry_px at the object's distance, mm)
    symmetry: tuple[float, float] = (float("nan"), float("inf"))
    symmetry_tolerance_mm: float = 0.0
    height_from_photos: bool = False  # on a support: the refinement moved the height (``frees_height``)
    pixel_mm: float = float("nan")  # a working-size pixel at the object's distance
    equivalent_turns: list[float] | None = field(default_factory=list)
    # placed by points triangulated on the marker board (``cloud_check``): their fit; None: by the photos
    cloud: dict | None = None
    # placed by the object's outline against the marker board (``outline_check``): its fit
    outline: dict | None = None

    @property
    def placed_by(self) -> str:
        """What placed the mesh: ``"points"`` (``cloud_check``), ``"outline"`` (``outline_check``) or
        ``"photos"`` (``check_registration``)."""
        return "points" if self.cloud is not None else "outline" if self.outline is not None else "photos"

    def to_json(self) -> dict:
        """The check as JSON values (``registration.json`` -> ``photometric``)."""
        return {
            "fit": None if self.cloud is not None or self.outline is not None else self.fit.to_json(),
            "sharpness": self.sharpness if np.isfinite(self.sharpness) else None,
            "margin": self.margin if np.isfinite(self.margin) else None,
            "chosen_candidate": self.chosen,
            "candidates": self.candidates,
            "azimuth_profile": [[t, c if np.isfinite(c) else None] for t, c in self.profile],
            "mesh_symmetry": {
                "turn_deg": self.symmetry[0] if np.isfinite(self.symmetry[0]) else None,
                "turned_mm": self.symmetry[1] if np.isfinite(self.symmetry[1]) else None,
                "invisible_below_mm": self.symmetry_tolerance_mm,
                # the placements no photo can tell apart, which give the same asset (None: every turn)
                "equivalent_turns_deg": self.equivalent_turns,
                "equivalent_placements": None if self.equivalent_turns is None else 1 + len(self.equivalent_turns),
            },
            "height_from_photos": self.height_from_photos,
            "pixel_mm": self.pixel_mm if np.isfinite(self.pixel_mm) else None,
            "triangulated_points": self.cloud,
            "outline": self.outline,
        }


def corrected(alignment: Alignment, g: Correction) -> Alignment:
    """G o A: the alignment that puts the cameras where the correction moved them."""
    Rw, e = rotation_matrix(g.omega), np.exp(g.log_scale)
    t = g.centre + e * Rw @ (alignment.translation - g.centre) + g.tau
    return replace(alignment, scale=e * alignment.scale, rotation=Rw @ alignment.rotation, translation=t)


def spread(names: list[str], count: int = TUNING.check.max_photos) -> list[str]:
    """At most ``count`` of ``names`` (sorted: the sweep's order), evenly spread."""
    names = sorted(names)
    if len(names) <= count:
        return names
    return [names[i] for i in np.linspace(0, len(names) - 1, count).round().astype(int)]


def rival_turns(turns: np.ndarray, costs: np.ndarray, count: int = TUNING.check.rivals) -> list[float]:
    """The ``count`` lowest local minima of a circular azimuth profile (degrees) more than
    ``TUNING.align.ambiguous_deg`` from 0 (the alignment swept) and from each other."""
    lower = (costs <= np.roll(costs, 1)) & (costs <= np.roll(costs, -1)) & np.isfinite(costs)
    taken: list[float] = []
    for i in np.argsort(costs):
        if len(taken) == count:
            break
        turn = float(turns[i])
        if lower[i] and all(azimuth_apart(turn, t) > TUNING.align.ambiguous_deg for t in [0.0, *taken]):
            taken.append(turn)
    return taken


def check_registration(
    alignment: Alignment,
    camera_from_sfm: dict[str, np.ndarray],
    photos: PhotoStack,
    names: list[str],
    mesh: Mesh,
    support_z: float | None,
    progress: Progress = QUIET,
    on_board: bool = False,
    accuracy_m: float | None = None,
) -> PhotoCheck:
    """``alignment`` refined by the photos ``photos`` (of ``names``; similarity only: SfM's relative
    poses are kept), its rivals found by sweeping the azimuth over the whole circle and refined the
    same way, the best chosen and judged (see ``PhotoCheck``). ``on_board``: the poses are a marker
    board's (metric, the support its plane): only the azimuth and the shift on the plane move.
    Minutes on a large scan: ``progress`` counts its steps (the first refinement, the sweep, each
    rival's, the final one, the sharpness)."""
    with progress.counter("registration check", 4 + TUNING.check.rivals, unit="step") as steps:
        # candidates are compared on half the photos and fewer points (the chosen one is refined on all)
        pick = [names.index(n) for n in spread(names, TUNING.check.sweep_photos)]
        judge = PhotometricRegistration(
            mesh,
            photos.subset(pick),
            support_z,
            points=TUNING.photometric.candidate_points,
            edge_stride=edge_stride(photos),
            free_scale=not on_board,
        )
        sfm = np.stack([camera_from_sfm[n] for n in names])

        def placed(al: Alignment) -> np.ndarray:
            return np.stack([al.camera_from_mesh(m) for m in sfm])

        def coarse(al: Alignment) -> tuple[Alignment, PhotometricFit]:
            g, fit = judge.refine(
                placed(al)[pick], levels=TUNING.photometric.blur_levels_px[:1], max_rounds=TUNING.check.candidate_rounds
            )
            return corrected(al, g), fit

        trials = [coarse(alignment)]
        steps.update()
        # a point cloud with few points on the object can land at any azimuth: the photos vote on all
        scout = PhotometricRegistration(
            mesh,
            photos.subset(pick),
            support_z,
            points=TUNING.check.sweep_points,
            edge_stride=TUNING.check.sweep_edge_stride,
            free_scale=not on_board,
        )
        turns, costs = scout.azimuth_profile(
            placed(trials[0][0])[pick], TUNING.photometric.blur_levels_px[0], TUNING.check.sweep_step_deg
        )
        steps.update()
        rivals = rival_turns(turns, costs)
        steps.update(TUNING.check.rivals - len(rivals))  # rivals not found: no work to wait for
        for turn in rivals:
            turned = Correction(np.array([0.0, 0.0, np.radians(turn)]), np.zeros(3), 0.0, judge.pivot)
            trials.append(coarse(corrected(trials[0][0], turned)))
            steps.update()
        chosen = int(np.argmin([fit.cost for _, fit in trials]))
        best = trials[chosen][0]
        yaw = [yaw_deg(a) for a, _ in trials]
        change = [(y - yaw[chosen] + 180.0) % 360.0 - 180.0 for y in yaw]
        pixel_m = object_distance(placed(best), judge.centre) / photos.scanner.fx
        same_as = _SamePlacement(mesh, judge.centre, pixel_m, change, accuracy_m)
        same, apart, own, same_turns, tolerance_m = (
            same_as.same,
            same_as.apart,
            same_as.own,
            same_as.turns,
            same_as.tolerance_m,
        )
        others = [fit.cost for (_, fit), eq in zip(trials, same, strict=True) if not eq]
        margin = (min(others) - trials[chosen][1].cost) / trials[chosen][1].cost if others else float("inf")
        free_height = support_z is not None and frees_height(pixel_m) and not on_board
        finisher = PhotometricRegistration(
            mesh,
            photos,
            support_z,
            points=TUNING.photometric.fine_points,
            edge_stride=edge_stride(photos),
            free_height=free_height,
            free_scale=not on_board,
        )
        g, fit = finisher.refine(placed(best), levels=TUNING.photometric.blur_levels_px[1:])
        steps.update()
        best = corrected(best, g)
        sharpness = finisher.sharpness(placed(best), TUNING.photometric.sharpness_sigma_px)
        steps.update()
        candidates = [
            {
                "azimuth_change_deg": c,
                "coarse_cost": f.cost,
                "mesh_turned_mm": 1e3 * d,
                "equivalent": bool(eq),  # the chosen placement itself, or one a symmetry relates
            }
            for c, (_, f), d, eq in zip(change, trials, apart, same, strict=True)
        ]
        profile = [(float(t), float(c)) for t, c in zip(turns, costs, strict=True)]
        turn, turned_m = mesh_symmetry(mesh, judge.centre, own)
        return PhotoCheck(
            best,
            fit,
            sharpness,
            float(margin),
            candidates,
            chosen,
            profile,
            [a for a, _ in trials],
            (turn, 1e3 * turned_m),
            1e3 * tolerance_m,
            free_height,
            1e3 * pixel_m,
            same_turns,
        )


class _SamePlacement:
    """Which candidates (turned ``change`` degrees from the chosen one) are the chosen placement: within
    ``TUNING.align.ambiguous_deg`` of it — the same answer — or of one of the mesh's symmetries that
    no photo of ``pixel_m`` metres a pixel can see, nor the mesh's own accuracy ``accuracy_m`` tell
    (``align.equivalent_turns``) — the same asset. Neither is a rival."""

    def __init__(
        self, mesh: Mesh, centre: np.ndarray, pixel_m: float, change: list[float], accuracy_m: float | None = None
    ):
        # closer than this, no photo sees the difference; nor does the mesh where two independent
        # errors of its stated 1 sigma would differ by as much (RMS sqrt(2) sigma: a symmetric shape
        # scanned so lies a median 0.95 sigma from its turned self for Gaussian errors)
        self.tolerance_m = max(TUNING.check.symmetry_px * pixel_m, np.sqrt(2.0) * (accuracy_m or 0.0))
        self.apart = turned_distance(mesh, centre, np.array(change))
        self.own = symmetry_profile(mesh, centre)
        self.turns = equivalent_turns(mesh, centre, self.tolerance_m, self.own)
        self.same = [
            self.turns is None or any(azimuth_apart(c, t) <= TUNING.align.ambiguous_deg for t in [0.0, *self.turns])
            for c in change
        ]


def weakest_rival(significance: list[float]) -> float:
    """The margin of a placement by points over its rivals: the least of their significances
    (``Alignment.candidate_z``); a rival whose significance could not be measured (nan: too few
    points for the regions) leaves no margin (-inf), whatever its place in the list; none: inf."""
    return min((-np.inf if np.isnan(z) else z for z in significance), default=np.inf)


def cloud_check(
    alignment: Alignment,
    camera_from_board: dict[str, np.ndarray],
    names: list[str],
    mesh: Mesh,
    fx: float,
    accuracy_m: float | None = None,
) -> PhotoCheck:
    """A placement on the marker board found from triangulated points (``align.align_on_board``),
    judged by its own fit: its rivals are the search's other start azimuths, equivalent where a
    symmetry of the mesh relates them; ``margin``: how significantly the best rival fits the points
    worse — the least of the rivals' ``Alignment.candidate_z`` (the paired difference of their
    points' terms over its standard error between surface regions). ``fx``: the photos' focal
    length in pixels, and ``accuracy_m`` the mesh's stated accuracy, for the symmetry's tolerance."""
    chosen_yaw = yaw_deg(alignment)
    # the starts converge to few azimuths: one candidate each (within a degree), the best score kept
    found: list[tuple[float, float, float | None]] = []
    for (azimuth, score), z in zip(alignment.candidates, alignment.candidate_z, strict=True):  # best first
        turn = (azimuth - chosen_yaw + 180.0) % 360.0 - 180.0
        if all(azimuth_apart(turn, t) > 1.0 for t, _, _ in found):
            found.append((turn, score, z))
    found.sort(key=lambda c: abs(c[0]))  # the chosen placement first
    check, spread_m, pixel_m = _judged_by_own_fit(
        alignment,
        found,
        [alignment.camera_from_mesh(camera_from_board[n]) for n in names],
        mesh,
        fx,
        accuracy_m,
        (alignment.azimuth_sigma, alignment.shift_sigma),
    )
    check.profile = sorted((t, score) for t, score, _ in found)
    check.cloud = {
        "spread_mm": 1e3 * spread_m if np.isfinite(spread_m) else None,
        "spread_px": spread_m / pixel_m if np.isfinite(spread_m) else None,
        "azimuth_sigma_deg": float(np.degrees(alignment.azimuth_sigma))
        if np.isfinite(alignment.azimuth_sigma)
        else None,
        "shift_sigma_mm": (1e3 * alignment.shift_sigma).tolist() if np.isfinite(alignment.shift_sigma).all() else None,
        "object_points": alignment.object_points,
        "inliers": alignment.kept_points,
        "inlier_fraction": alignment.kept_points / max(alignment.object_points, 1),
        "residual_mm": 1e3 * alignment.residual_m,
        "board_points": alignment.support_points,
    }
    return check


def outline_check(
    placement: SilhouettePlacement,
    camera_from_board: dict[str, np.ndarray],
    names: list[str],
    mesh: Mesh,
    fx: float,
    accuracy_m: float | None = None,
) -> PhotoCheck:
    """A placement on the marker board found from the object's outline against the print
    (``Silhouettes.place``), judged by its own fit: its rivals are the sweep's other minima,
    equivalent where a symmetry of the mesh relates them; ``margin``: the least significance of the
    others (how many standard errors over photos they fit the outlines worse); ``outline``: the fit,
    its jackknife spread (px at the object's distance) and the share of points outside the outline.
    ``fx`` (the working size's) and ``accuracy_m`` as ``cloud_check``'s."""
    found: list[tuple[float, float, float | None]] = [(0.0, float(placement.costs.mean()), None)]
    found += [(t, c, z) for t, z, c in placement.rivals]
    alignment = placement.alignment
    check, spread_m, pixel_m = _judged_by_own_fit(
        alignment,
        found,
        [alignment.camera_from_mesh(camera_from_board[n]) for n in names],
        mesh,
        fx,
        accuracy_m,
        (placement.turn_sigma, np.concatenate([placement.shift_sigma, [0.0]])),
    )
    check.outline = {**placement.to_json(), "spread_mm": 1e3 * spread_m, "spread_px": spread_m / pixel_m}
    return check


def _judged_by_own_fit(
    alignment: Alignment,
    found: list[tuple[float, float, float | None]],
    placed: list[np.ndarray],
    mesh: Mesh,
    fx: float,
    accuracy_m: float | None,
    sigma: tuple[float, np.ndarray],
) -> tuple[PhotoCheck, float, float]:
    """A metric placement judged by its own fit (points or outline): ``found`` its candidates as
    (turn from it in degrees, score, significance; the placement itself first), ``placed`` the
    cameras it puts (camera from mesh), ``sigma`` its 1-sigma turn (radians) and shift ``(3,)``
    (metres). The check (margin: the least significance of the rivals no symmetry of the mesh
    relates), its spread where it moves the surface most (metres: the shift plus the turn's at the
    rim; no turn for a body of revolution) and a photo pixel at the object's distance (metres)."""
    centre = 0.5 * (mesh.vertices.min(0) + mesh.vertices.max(0))
    pixel_m = object_distance(np.stack(placed), centre) / fx
    same_as = _SamePlacement(mesh, centre, pixel_m, [t for t, _, _ in found], accuracy_m)
    rivals = [np.nan if z is None else z for (_, _, z), eq in zip(found, same_as.same, strict=True) if not eq]
    candidates = [
        {
            "azimuth_change_deg": t,
            "coarse_cost": score,
            "significance": z if z is not None and np.isfinite(z) else None,
            "mesh_turned_mm": 1e3 * d,
            "equivalent": bool(eq),
        }
        for (t, score, z), d, eq in zip(found, same_as.apart, same_as.same, strict=True)
    ]
    turn, turned_m = mesh_symmetry(mesh, centre, same_as.own)
    rim_m = float(np.linalg.norm(mesh.vertices[:, :2] - centre[:2], axis=1).max())
    turning = 0.0 if same_as.turns is None else rim_m * sigma[0]  # a body of revolution: any turn
    spread_m = float(np.linalg.norm(sigma[1]) + turning)
    check = PhotoCheck(
        alignment,
        PhotometricFit(float("nan"), float("nan"), 0, 0),
        float("nan"),
        float(weakest_rival(rivals)),
        candidates,
        0,
        [],
        [],
        (turn, 1e3 * turned_m),
        1e3 * same_as.tolerance_m,
        False,
        1e3 * pixel_m,
        same_as.turns,
    )
    return check, spread_m, pixel_m


def outline_fits(check: PhotoCheck) -> bool:
    """Whether a placement by the outline (``outline_check``) fits it: at most
    ``TUNING.silhouette.max_outside`` of its points lie deeper than ``fit_px`` into print a photo sees,
    and its spread is within ``TUNING.silhouette.max_spread_px``."""
    assert check.outline is not None
    return (
        check.outline["points_outside"] <= TUNING.silhouette.max_outside
        and check.outline["spread_px"] <= TUNING.silhouette.max_spread_px
    )


def confirmed_by_outline(check: PhotoCheck) -> bool:
    """Whether a placement by the outline stands on its own: it fits (``outline_fits``) and no
    rival azimuth that is not a symmetry of the mesh fits within ``min_margin``. Otherwise the
    photometric check places the mesh (a body of revolution's azimuth is its texture's to tell)."""
    return outline_fits(check) and check.margin >= min_margin(check)


def min_margin(check: PhotoCheck) -> float:
    """The margin a rival azimuth must leave: the photometric cost's, or, for a placement by points
    triangulated on the board (``cloud_check``), their trimmed score's, or for one by the outline
    (``outline_check``), its significance over photos."""
    if check.outline is not None:
        return TUNING.silhouette.min_significance
    return TUNING.refusal.min_margin if check.cloud is None else TUNING.triangulation.min_margin


def spread_within_bar(check: PhotoCheck) -> bool:
    """Whether a placement by points (``cloud_check``) spreads at most
    ``TUNING.triangulation.max_spread_px``; a spread that could not be measured (too few inliers for
    the jackknife) is not within it."""
    assert check.cloud is not None
    spread = check.cloud["spread_px"]
    return spread is not None and spread <= TUNING.triangulation.max_spread_px


def confirmed_by_points(check: PhotoCheck) -> bool:
    """Whether a placement by points (``cloud_check``) stands on its own: its spread within the bar
    (``spread_within_bar``) and no rival azimuth within ``min_margin``. Otherwise the photometric
    check judges it (it may still be right: a nearly round shape's azimuth is the photos' texture's
    to tell)."""
    return spread_within_bar(check) and check.margin >= min_margin(check)


def placed_by_points(alignment: Alignment) -> bool:
    """Whether triangulated points fix a placement on the board: enough of them lie on the placed
    mesh (``TUNING.triangulation.min_points``, ``min_inlier_fraction``); otherwise the photometric
    check places the mesh (a plain object, or a mesh that is not the photographed one)."""
    fraction = alignment.kept_points / max(alignment.object_points, 1)
    return (
        alignment.kept_points >= TUNING.triangulation.min_points
        and fraction >= TUNING.triangulation.min_inlier_fraction
    )


@dataclass
class MeshRegistration:
    """An SfM (or COLMAP) model put on the mesh: the point cloud's alignment (``icp``), the photos'
    check of it (``check.alignment`` is the one to use), the judged photos and the stage's seconds."""

    icp: Alignment
    check: PhotoCheck
    photos: PhotoStack
    judged: list[str]
    mesh: Mesh  # in the scan's local frame (``scanner.local_frame``), as the poses the alignment gives
    origin: np.ndarray
    seconds_align: float
    seconds_photometric: float
    # on a marker board: the placement by triangulated points (``cloud_check``) and by the object's
    # outline (``outline_check``), whether or not they decided
    by_points: PhotoCheck | None = None
    by_outline: PhotoCheck | None = None


def register_to_mesh(scan: Scan, reg: SfmResult | BoardPoses, progress: Progress = QUIET) -> MeshRegistration:
    """The similarity from ``reg``'s frame to the mesh: aligned by the point cloud, then refined and
    judged by (at most ``TUNING.check.max_photos`` of) the photos; ``NtpInputError`` when nothing can
    be aligned. On a marker board the photos' features, triangulated with the board's poses, place
    the mesh (``cloud_check``) where they confirm it (``confirmed_by_points``); where they do not, or
    are too few, the photometric check places it from ``board_poses.first_placement``."""
    names = sorted(reg.poses)
    world = load_mesh(scan.mesh_path)
    origin = local_origin(world)
    mesh = moved(world, -origin)  # the photometric check's positions are float32: near the origin
    on_board = isinstance(reg, BoardPoses)
    judged = spread(names)  # the photos judge (and refine) the alignment
    support_z = float(mesh.vertices[:, 2].min()) if scan.support_plane else None
    photos = None
    by_points = by_outline = None
    t0 = time.perf_counter()
    if on_board:  # the board's poses are metric: the photos' features, found as they are read, place the mesh
        features: dict[str, Features] = {}
        photos = _judged_photos(scan, judged, features, progress)
        icp = _board_alignment(scan, reg.poses, judged, [features[n] for n in judged], mesh, progress)
        if placed_by_points(icp):
            by_points = cloud_check(icp, reg.poses, judged, mesh, scan.scanner.fx, scan.mesh_accuracy_m)
            if confirmed_by_points(by_points):
                t1 = time.perf_counter()
                return MeshRegistration(icp, by_points, photos, judged, mesh, origin, t1 - t0, 0.0, by_points)
        # unconfirmed or too few points (a plain or glossy object): the outline against the print
        # places the mesh from the cameras' aim, then, where it does not confirm (a near-symmetric
        # outline), the photometric check does from there. Started from the points' placement
        # instead, 1 of 5 validation objects came out right against 3 of 5 from the aim (docs/pipeline.md)
        icp = first_placement(mesh, [reg.poses[n] for n in names])
        assert scan.board is not None  # board poses come from the scan's board
        outline = Silhouettes(photos, np.stack([reg.poses[n] for n in judged]), scan.board, mesh)
        by_outline = outline_check(outline.place(icp), reg.poses, judged, mesh, photos.scanner.fx, scan.mesh_accuracy_m)
        if confirmed_by_outline(by_outline):
            t1 = time.perf_counter()
            return MeshRegistration(icp, by_outline, photos, judged, mesh, origin, t1 - t0, 0.0, by_points, by_outline)
    else:
        assert isinstance(reg, SfmResult)
        icp = _cloud_alignment(scan, reg, names, mesh, progress)
    t1 = time.perf_counter()
    if photos is None:
        photos = _judged_photos(scan, judged, None, progress)
    check = check_registration(
        icp, reg.poses, photos, judged, mesh, support_z, progress, on_board=on_board, accuracy_m=scan.mesh_accuracy_m
    )
    return MeshRegistration(
        icp, check, photos, judged, mesh, origin, t1 - t0, time.perf_counter() - t1, by_points, by_outline
    )


def _judged_photos(
    scan: Scan, judged: list[str], features: dict[str, Features] | None, progress: Progress
) -> PhotoStack:
    """The photos ``judged``, decoded in parallel and averaged down one at a time; with ``features``,
    each photo's SIFT features (``triangulate.photo_features``) found from the same decode, by name."""

    def read(name: str) -> np.ndarray:
        codes = read_photo(scan.photos_dir / name, scan.scanner)
        if features is not None:
            features[name] = photo_features(codes, scan.scanner)
        return codes

    with ThreadPoolExecutor(worker_threads()) as pool:
        return PhotoStack(progress.track(pool.map(read, judged), "photos", len(judged), "photo"), scan.scanner)


def _board_alignment(
    scan: Scan,
    camera_from_board: dict[str, np.ndarray],
    names: list[str],
    features: list[Features],
    mesh: Mesh,
    progress: Progress,
) -> Alignment:
    """The mesh placed on the points the photos ``names`` triangulate on the board
    (``triangulate``, ``align.align_on_board``); an empty alignment where too few lie on the object."""
    with progress.counter("points on the object", 1, "step") as bar:
        poses = [camera_from_board[n] for n in names]
        points = triangulated_points(features, poses, scan.scanner, convergence_point(poses))
        try:
            icp = align_on_board(points, poses, mesh)
        except ValueError:
            icp = Alignment(1.0, np.eye(3), np.zeros(3), float("inf"), 0, 0, 0)
        bar.update()
    return icp


def _cloud_alignment(scan: Scan, reg: SfmResult, names: list[str], mesh: Mesh, progress: Progress) -> Alignment:
    """The SfM point cloud's alignment to the mesh (``align.align_to_mesh``)."""
    try:
        with progress.counter("alignment to the mesh", 1, "step") as bar:
            icp = align_to_mesh(
                reg.points,
                [reg.poses[n] for n in names],
                mesh,
                float(np.linalg.norm(scan.scanner.valid_center)),
                support_plane=scan.support_plane,
            )
            bar.update()
    except ValueError as err:
        raise NtpInputError(scan.mesh_path, f"cannot align the SfM points to this mesh: {err}") from None
    return icp
