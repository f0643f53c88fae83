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
    align_to_mesh,
    azimuth_apart,
    equivalent_turns,
    mesh_symmetry,
    symmetry_profile,
    turned_distance,
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

    def to_json(self) -> dict:
        """The check as JSON values (``registration.json`` -> ``photometric``)."""
        return {
            "fit": self.fit.to_json(),
            "sharpness": self.sharpness,
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
        yaw = [float(np.degrees(np.arctan2(a.rotation[1, 0], a.rotation[0, 0]))) for a, _ in trials]
        change = [(y - yaw[chosen] + 180.0) % 360.0 - 180.0 for y in yaw]
        pixel_m = object_distance(placed(best), judge.centre) / photos.scanner.fx
        tolerance_m = TUNING.check.symmetry_px * pixel_m  # closer than this, no photo sees the difference
        apart = turned_distance(mesh, judge.centre, np.array(change))
        own = symmetry_profile(mesh, judge.centre)
        same_turns = equivalent_turns(mesh, judge.centre, tolerance_m, own)
        # candidates the refinement brought within ambiguous_deg of the chosen one's azimuth are the same
        # answer, and those it brought as near a symmetry of the mesh the same asset: neither is a rival
        same = [
            same_turns is None or any(azimuth_apart(c, t) <= TUNING.align.ambiguous_deg for t in [0.0, *same_turns])
            for c in change
        ]
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


def register_to_mesh(scan: Scan, reg: SfmResult | BoardPoses, progress: Progress = QUIET) -> MeshRegistration:
    """The similarity from ``reg``'s frame to the mesh: aligned by the point cloud (a marker board's
    poses: put on the board, ``board_poses.first_placement``), then refined and judged by (at most
    ``TUNING.check.max_photos`` of) the photos; ``NtpInputError`` when nothing can be aligned."""
    names = sorted(reg.poses)
    world = load_mesh(scan.mesh_path)
    origin = local_origin(world)
    mesh = moved(world, -origin)  # the photometric check's positions are float32: near the origin
    on_board = isinstance(reg, BoardPoses)
    t0 = time.perf_counter()
    if on_board:
        icp = first_placement(mesh, [reg.poses[n] for n in names])
    else:
        assert isinstance(reg, SfmResult)
        icp = _cloud_alignment(scan, reg, names, mesh, progress)
    t1 = time.perf_counter()
    judged = spread(names)  # the photos judge (and refine) the alignment
    with ThreadPoolExecutor(worker_threads()) as pool:  # decoded in parallel, averaged down one at a time
        photos = PhotoStack(pool.map(lambda n: read_photo(scan.photos_dir / n, scan.scanner), judged), scan.scanner)
    support_z = float(mesh.vertices[:, 2].min()) if scan.support_plane else None
    check = check_registration(icp, reg.poses, photos, judged, mesh, support_z, progress, on_board=on_board)
    return MeshRegistration(icp, check, photos, judged, mesh, origin, t1 - t0, time.perf_counter() - t1)


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
