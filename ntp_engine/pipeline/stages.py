"""``ntp reconstruct``: a scan folder to texture maps, stage by stage, each stage cached under
``OUT/cache`` or ``--cache DIR`` (docs/design.md data flow):

select (blur, unreadable) -> register (pycolmap SfM, or a COLMAP model, + similarity to the mesh;
skipped with a poses file)
-> atlas (mesh UVs, else xatlas) -> traces (Embree visibility, projection, validity)
-> fit (network in bounded batches + fitter) -> maps, report.json.

Each stage's key holds its inputs and the previous stage's key, so a changed option recomputes
from the first stage it affects; an interrupted run resumes from the last finished stage. The
report (``report.json``) gives each stage's wall seconds, what was kept and why, and the counts;
it is written last and marks a complete result. ``OUT`` is claimed first (``output_folder``: absent,
empty or an ntp result, outside the scan folder), and a run that measured too little is refused
before the fit (``TUNING.run.min_photos_used``, ``TUNING.run.min_coverage``; a mesh of implausible size before
any work).
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import shutil
import time
from collections.abc import Iterator
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch

from ..fit.flags import TexelFlag
from ..fit.texel_fit import TexelFit
from ..io.atomic import atomic_path, temp_dir, write_text_atomic
from ..io.errors import NtpInputError
from ..io.images import write_png
from ..io.mesh import Mesh, load_mesh, save_obj
from ..io.output_folder import claim, publish
from ..io.progress import QUIET, Progress
from ..io.raycast import RayCaster
from ..io.stage_cache import StageCache, code_version, content_digest, content_key, digest
from ..io.texels import Texels, rasterize, uv_atlas
from ..io.threads import configured_threads
from ..io.viewers import base_colour_for_fresnel_mix, beyond_principled
from ..learn import models
from ..learn.network import TraceNet
from ..learn.ragged import RaggedTraces
from ..physics.emitter_blocks import SHADOW_SPLITS
from ..refine.passes import refine_fit
from ..refine.settings import TUNING as REFINE_TUNING
from ..refine.settings import RefineSettings
from ..refine.support_light import SupportAlbedo, SupportScene, estimate_support_albedo, exposed
from ..register.board_fallback import fill_from_sfm
from ..register.board_poses import BoardPoses, poses_from_corners
from ..register.check import min_margin, register_to_mesh
from ..register.colmap_model import model_files, read_colmap_model
from ..register.refusal import outline_picture, refusal, symmetry_note
from ..register.settings import TUNING as REGISTRATION_TUNING
from ..register.sfm import SfmResult, structure_from_motion
from ..scanner import camera
from ..scanner.device_file import scanner_to_dict
from ..scanner.local_frame import local_origin, moved, pose_to_local, pose_to_world
from ..scanner.scan_folder import Scan, check_mesh_size, read_codes
from . import traces as trace_assembly
from .distil import distilled_network, seed_texels
from .fit_traces import fit_blocks
from .photo_selection import Selection, select_photos
from .report import PhotoCounts, RefineSummary, Report, TexelCounts, TraceCounts
from .result import write_result
from .settings import TUNING
from .task_pool import LocalPool, RayPool, TaskPool

DEFAULT_RESOLUTION = 1024  # texture maps are DEFAULT_RESOLUTION^2 unless asked otherwise
MIN_RESOLUTION = 8
MAX_RESOLUTION = 16384  # the largest texture GPUs, glTF viewers and Blender's viewport take
REFINE = RefineSettings()
# the distilled path's last step: every texel refined from the scan's own network's answer, which is
# close already (``TUNING.distil``: the rounds and iterations; no multi-start; the albedo edges not
# refined again: docs/distillation.md)
POLISH = dataclasses.replace(
    REFINE,
    rounds=TUNING.distil.polish_rounds,
    iterations=TUNING.distil.polish_iterations,
    starts=False,
    edge_pass=False,
)
# the code behind each stage (``io.stage_cache.code_version``: these modules and every engine module
# they import; this module's own code runs every stage, so a change to it recomputes them all)
STAGE_CODE: dict[str, tuple[str, ...]] = {
    "select": ("ntp_engine.pipeline.photo_selection",),
    "register": (
        "ntp_engine.register.sfm",
        "ntp_engine.register.colmap_model",
        "ntp_engine.register.check",
        "ntp_engine.register.board_poses",
        "ntp_engine.register.board_fallback",
        "ntp_engine.register.refusal",
        "ntp_engine.register.triangulate",
    ),
    "atlas": ("ntp_engine.io.texels",),
    "traces": ("ntp_engine.pipeline.traces",),
    "support": ("ntp_engine.refine.support_light",),
    "fit": ("ntp_engine.pipeline.fit_traces",),
    "refine": ("ntp_engine.refine.passes",),
    "distil": ("ntp_engine.pipeline.distil",),
}  # the refinement's settings when asked for (`reconstruct(refine=True)`)


def _stage_code(stage: str) -> str:
    """The code version in ``stage``'s key: its modules (``STAGE_CODE``) with their imports, and
    this runner's own code."""
    return code_version(STAGE_CODE[stage], alone=[__name__])


def register_photos(
    scan: Scan,
    out: Path,
    blur_margin: float = TUNING.select.blur_margin,
    progress: Progress = QUIET,
    force_registration: bool = False,
    cache: Path | None = None,
) -> Registration:
    """Stages 1-2 (photo selection, then the poses file or SfM + alignment), cached under
    ``cache`` (default ``out/cache``; ``out`` is claimed as an ntp result folder, a ``cache``
    elsewhere as an ntp cache folder). A registration the photos do not confirm raises ``RegistrationRefused``
    unless ``force_registration``."""
    check_mesh_size(load_mesh(scan.mesh_path), scan.scanner, scan.mesh_path)
    with claim(out, "result", inputs=scan.input_folders), _stage_cache(Path(out), cache, scan) as stages:
        return _registration(scan, Path(out), stages, blur_margin, progress, force_registration)


@contextlib.contextmanager
def _stage_cache(out: Path, cache: Path | None, scan: Scan) -> Iterator[StageCache]:
    """The run's stage cache: ``out/cache``, or ``cache`` claimed as an ntp cache folder (one run
    at a time, never the user's files, never inside the scan). ntp deletes inside its cache, so an
    ``out/cache`` that is a link is claimed as the folder it points to, like ``--cache`` (a link
    to a user's folder or into the scan is refused, not followed)."""
    default = out / "cache"
    target = default if cache is None else Path(cache)
    if target.resolve() == default.resolve() and not default.is_symlink():
        yield StageCache(default)
        return
    with claim(target.resolve(), "cache", inputs=scan.input_folders) as folder:
        yield StageCache(folder)


class Registration(NamedTuple):
    """What stages 1-2 hand on: the camera-from-world pose of each photo used, by name; the report
    with its ``photos``, ``registration`` and ``stages`` filled; and the poses' key (chained into the
    traces stage's)."""

    poses: dict[str, np.ndarray]
    report: Report
    key: str


class RegistrationRefused(NtpInputError):
    """The photos do not confirm the registration (``register.refusal.refusal``)."""


def _registration(
    scan: Scan, out: Path, cache: StageCache, blur_margin: float, progress: Progress, force: bool
) -> Registration:
    report = Report()
    t0 = time.perf_counter()
    sel, h_sel = _select_stage(scan, cache, blur_margin, progress)
    report.timed("select", t0)
    report.photos = PhotoCounts(len(scan.photo_paths), len(sel.kept), sel.blurry, sel.unreadable)
    if len(sel.kept) < REGISTRATION_TUNING.sfm.min_registered:
        raise NtpInputError(
            scan.photos_dir,
            f"only {len(sel.kept)} sharp, readable photos (need {REGISTRATION_TUNING.sfm.min_registered})",
        )
    t0 = time.perf_counter()
    if scan.poses is not None:
        poses = {n: scan.poses[n] for n in sel.kept if n in scan.poses}
        reg_info = {"source": "poses file", "unregistered": [n for n in sel.kept if n not in scan.poses]}
        # the selection's key holds the photos' content: new photos with old poses are new traces
        h_pose = digest({"select": h_sel, "poses": {n: m.round(9).tolist() for n, m in poses.items()}})
    else:
        poses, reg_info, h_pose = _register_stage(scan, cache, sel, h_sel, progress)
        _diagnostics(out, cache, reg_info, force)
    report.timed("register", t0)
    report.registration = reg_info
    if not poses:
        raise NtpInputError(scan.photos_dir, "no selected photo has a pose")
    return Registration(poses, report, h_pose)


def write_registration(out: Path, poses: dict[str, np.ndarray], report: Report) -> None:
    """``out/poses.json`` (camera-from-world per photo) and ``out/registration.json`` (the report)."""
    write_text_atomic(out / "poses.json", json.dumps({n: m.tolist() for n, m in poses.items()}, indent=1))
    write_text_atomic(out / "registration.json", json.dumps(report.to_json(), indent=2))


def _diagnostics(out: Path, cache: StageCache, reg_info: dict, force: bool) -> None:
    """``out/registration.json`` and ``out/registration.png`` (the mesh's outline over photos);
    the refusal when the photos do not confirm the registration and it is not forced."""
    write_text_atomic(out / "registration.json", json.dumps(reg_info, indent=2))
    with atomic_path(out / "registration.png") as tmp:
        shutil.copyfile(cache.folder / "register" / "registration.png", tmp)
    why = reg_info["confidence"]["refusal"]
    if why is not None and not force:
        raise RegistrationRefused(out / "registration.json", refused_line(why, on_board="board" in reg_info))
    reg_info["confidence"]["forced"] = why is not None


def refused_line(why: str, on_board: bool) -> str:
    """The one line a refused registration ends the run with: its cause ``why`` and what helps — a
    marker board only where the scan has none (``on_board``)."""
    board = "" if on_board else ", a marker board under the object (ntp board)"
    return (
        f"registration refused: {why} — look at registration.png; more photos{board} or a poses file help "
        "(--force-registration goes on anyway)"
    )


def _select_stage(scan: Scan, cache: StageCache, blur_margin: float, progress: Progress) -> tuple[Selection, str]:
    key = {
        "photos": content_key(scan.photo_paths),
        "code": _stage_code("select"),
        "margin": blur_margin,
        "camera": [scan.scanner.width, scan.scanner.height],
        "board": content_key([scan.board_path]) if scan.board_path else None,  # its corners are found here
    }

    def compute(d: Path) -> None:
        sel = select_photos(scan.photo_paths, scan.scanner, blur_margin, progress, scan.board)
        (d / "selection.json").write_text(json.dumps(sel.to_json(), indent=1))

    folder, h_sel = cache.get("select", key, compute)
    return Selection.from_json(json.loads((folder / "selection.json").read_text())), h_sel


def _register_stage(
    scan: Scan, cache: StageCache, sel: Selection, h_sel: str, progress: Progress
) -> tuple[dict[str, np.ndarray], dict, str]:
    """SfM on the kept photos, then the similarity that puts its cameras on the mesh."""

    def compute(d: Path) -> None:
        reg: SfmResult | BoardPoses
        if scan.colmap is not None:
            reg, source = read_colmap_model(scan.colmap, scan.scanner, sel.kept), f"COLMAP model {scan.colmap}"
        elif scan.board is not None:
            reg, source = _board_stage(scan, sel, d / "sfm", progress), f"marker board {scan.board_path}"
        else:
            reg = structure_from_motion(scan.photos_dir, sel.kept, scan.scanner, d / "sfm", progress=progress)
            source = "structure from motion"
        names = sorted(reg.poses)
        placed = register_to_mesh(scan, reg, progress)
        icp, check, photos, judged, mesh = placed.icp, placed.check, placed.photos, placed.judged, placed.mesh
        al = check.alignment
        why = refusal(check)
        write_png(
            d / "registration.png",
            outline_picture(photos, np.stack([al.camera_from_mesh(reg.poses[n]) for n in judged]), mesh),
        )
        (d / "poses.json").write_text(json.dumps({n: al.camera_from_mesh(reg.poses[n]).tolist() for n in names}))
        found: dict
        if isinstance(reg, BoardPoses):
            placement = {
                "points": "points triangulated on the board",
                "outline": "the object's outline against the board",
                "photos": "the photometric check",
            }[check.placed_by]
            points, outline = placed.by_points, placed.by_outline
            found = {
                "board": reg.to_json(),
                "alignment": {
                    "scale": al.scale,
                    "placed_by": placement,
                    # the points' and the outline's own placements where they found one, confirmed or not
                    "points": None if points is None else {**points.to_json(), "refusal": refusal(points)},
                    "outline": None if outline is None else {**outline.to_json(), "refusal": refusal(outline)},
                },
            }
        else:
            found = {
                "sfm_points": len(reg.points),
                "alignment": {
                    "scale": al.scale,
                    "residual_m": icp.residual_m,
                    "object_points": icp.object_points,
                    "inlier_points": icp.kept_points,
                    "support_points": icp.support_points,
                    "azimuth_margin": icp.azimuth_margin if np.isfinite(icp.azimuth_margin) else None,
                    "candidates": [{"azimuth_deg": a, "score": v} for a, v in icp.candidates],
                },
            }
        (d / "registration.json").write_text(
            json.dumps(
                {
                    "source": source,
                    "local_origin": placed.origin.tolist(),  # the frame of poses.json here (scanner.local_frame)
                    "registered": len(names),
                    "unregistered": reg.unregistered,
                    **found,
                    "photometric": {**check.to_json(), "photos": len(judged)},
                    "confidence": {
                        "accepted": why is None,
                        "refusal": why,
                        "symmetry": symmetry_note(check),
                        "min_sharpness": REGISTRATION_TUNING.refusal.min_sharpness,
                        "min_margin": min_margin(check),
                    },
                },
                indent=1,
            )
        )
        shutil.rmtree(d / "sfm", ignore_errors=True)  # the database is large and not needed again

    key = {
        "select": h_sel,
        "colmap": content_key(model_files(scan.colmap)) if scan.colmap else None,
        "board": content_key([scan.board_path]) if scan.board_path else None,
        "mesh": content_key([scan.mesh_path]),
        "support": scan.support_plane,
        "code": _stage_code("register"),
        "camera": {
            "K": scan.scanner.K,
            "distortion": scan.scanner.distortion,
            "valid_center": scan.scanner.valid_center,
        },
    }
    folder, h_pose = cache.get("register", key, compute)
    info = json.loads((folder / "registration.json").read_text())
    origin = np.array(info.get("local_origin", [0.0, 0.0, 0.0]))  # the frame of the cached poses
    poses = {n: pose_to_world(np.array(m), origin) for n, m in json.loads((folder / "poses.json").read_text()).items()}
    return poses, info, h_pose


def _board_stage(scan: Scan, sel: Selection, work: Path, progress: Progress) -> BoardPoses:
    """The marker board's pose in each kept photo, those it misses by SfM beside their neighbours
    (``register.board_fallback``; ``work`` holds its database); ``NtpInputError`` when too few
    photos see the board."""
    assert scan.board is not None
    assert sel.corners is not None  # the selection found them (``_select_stage`` with the board)
    reg = poses_from_corners({n: sel.corners[n] for n in sel.kept}, scan.board, scan.scanner)
    if reg.unregistered and len(reg.poses) >= REGISTRATION_TUNING.sfm.min_registered:
        added = fill_from_sfm(scan.photos_dir, sel.kept, reg, scan.scanner, work, progress)
        shutil.rmtree(work, ignore_errors=True)
        reg.poses.update(added.poses)
        reg.unregistered = [n for n in reg.unregistered if n not in added.poses]
        reg.sfm = added.to_json()
    if len(reg.poses) < REGISTRATION_TUNING.sfm.min_registered:
        raise NtpInputError(
            scan.board_path,
            f"the marker board is seen in {len(reg.poses)} of {len(sel.kept)} photos (need "
            f"{REGISTRATION_TUNING.sfm.min_registered}): is this the board that was printed, all of it in view?",
        )
    return reg


def reconstruct(
    scan: Scan,
    out: Path,
    resolution: int = DEFAULT_RESOLUTION,
    model: str | None = None,
    blur_margin: float = TUNING.select.blur_margin,
    progress: Progress = QUIET,
    force_registration: bool = False,
    refine: bool = False,
    cache: Path | None = None,
    ray: str | None = None,
    distil: bool = False,
) -> Report:
    """Run the pipeline on ``scan`` into ``out`` (``refine``: the analysis-by-synthesis refinement
    of every texel after the network's fit; ``distil``: of a sample of them, which the network is
    then fine-tuned on before it runs over every texel again and every texel's answer is polished
    by a short refinement, ``pipeline.distil``; ``ray``: the fit stage's blocks as tasks on that Ray
    cluster, ``task_pool.LOCAL`` for one on this machine — the same result); returns the report (also in
    ``out/report.json``, written last). ``out`` must be absent, empty or an ntp result, outside the scan folder
    (``output_folder.claim``); a run that measured too little, or whose registration the photos do
    not confirm (unless ``force_registration``), is refused, the old result kept. Stages are cached
    under ``cache`` (default ``out/cache``; elsewhere, e.g. a fast local disk, claimed as an ntp
    cache folder); a re-run resumes from the last stage whose inputs did not change."""
    if not MIN_RESOLUTION <= resolution <= MAX_RESOLUTION:
        raise NtpInputError(None, f"--resolution {resolution}: need {MIN_RESOLUTION} to {MAX_RESOLUTION}")
    if refine and distil:
        raise NtpInputError(None, "--refine and --distil: choose one (every texel refined, or a sample distilled)")
    scan_mesh = load_mesh(scan.mesh_path)
    check_mesh_size(scan_mesh, scan.scanner, scan.mesh_path)
    pool: TaskPool = RayPool(ray, configured_threads()) if ray else LocalPool()
    with claim(out, "result", inputs=scan.input_folders), _stage_cache(Path(out), cache, scan) as stages:
        return _reconstruct(
            scan,
            Path(out),
            stages,
            resolution,
            model,
            blur_margin,
            progress,
            force_registration,
            refine,
            pool,
            local_origin(scan_mesh),
            distil,
        )


def _reconstruct(
    scan: Scan,
    out: Path,
    cache: StageCache,
    resolution: int,
    model: str | None,
    blur_margin: float,
    progress: Progress,
    force_registration: bool,
    refine: bool,
    pool: TaskPool,
    origin: np.ndarray,
    distil: bool = False,
) -> Report:
    """The stages after the registration work in the scan's local frame (``scanner.local_frame``:
    float32 positions stay precise however far the mesh is from the world's origin)."""
    t_all = time.perf_counter()
    world_poses, report, h_pose = _registration(scan, out, cache, blur_margin, progress, force_registration)
    poses = {n: pose_to_local(m, origin) for n, m in world_poses.items()}
    report.scan = str(scan.folder)
    net, meta = models.load(model, scan.scanner)  # before any work: the model must fit the scanner

    t0 = time.perf_counter()
    mesh, h_atlas = _atlas_stage(scan, cache, resolution, origin, progress)
    texels = rasterize(mesh, (resolution, resolution), curvature=refine or distil)
    report.timed("atlas", t0)

    t0 = time.perf_counter()
    traces, stats, h_tr = _traces_stage(scan, cache, texels, mesh, h_atlas, poses, h_pose, progress)
    # what counts as observed: entries the fit reads — the in-range ones, or with the refinement all
    # (the distilled path's polish reads every entry too, so it counts as the refinement)
    lengths = (traces.lengths if refine or distil else traces.in_range_lengths()).numpy()
    _check_measured(scan, stats, lengths, len(poses))
    scale = net.exposure() / float(scan.scanner.exposure(scan.scanner.pattern))  # captured -> the model's
    report.traces = stats
    report.timed("traces", t0)

    t0 = time.perf_counter()
    model_folder = Path(meta["folder"])
    # the model by name and content, never by path: a moved install or copied result keeps its cache
    model_key = {
        "model": model_folder.name,
        "weights": content_digest(models.model_files(model_folder)),
    }

    # the distilled path fits the shipped network's answers on its seeds alone: they are the teacher's start,
    # and the fine-tuned network answers every texel after
    seeds = seed_texels(traces.in_range_lengths().numpy() > 0, TUNING.distil.seeds) if distil else None
    seed_traces = None if seeds is None else traces.only(torch.as_tensor(seeds))  # the fit's and the teacher's
    fitted_traces = traces if seed_traces is None else seed_traces

    def fit_stage(d: Path) -> None:
        with pool as p:
            fit_blocks(net, scan.scanner, fitted_traces, scale, p, progress).save(d / "fit.npz")

    fit_key = {
        "albedo_views": TUNING.fit.albedo_views,
        "rho_s_prior_weight": TUNING.fit.rho_s_prior_weight,
        "network_views": TUNING.fit.network_views,
        "block": TUNING.fit.fit_block,
        "code": _stage_code("fit"),
    }
    seeded = {} if seeds is None else {"seeds": TUNING.distil.seeds}
    folder, h_fit = cache.get("fit", {"traces": h_tr, **model_key, **fit_key, **seeded}, fit_stage)
    fitted = TexelFit.load(folder / "fit.npz")
    report.timed("network_and_fit", t0)
    if refine or distil:
        t0 = time.perf_counter()
        scene, h_support = None, None
        if scan.support_light:  # the photos hold the support's light: its albedo map, its mesh for the rays
            caster = RayCaster([mesh.triangles])
            support, h_support = _support_stage(scan, cache, mesh, caster, poses, h_atlas, h_pose, progress)
            scene = SupportScene(support, caster, mesh.face_normals())
            report.timed("support", t0)
            t0 = time.perf_counter()

        def refined(
            table: RaggedTraces, start: TexelFit, h_start: str, settings: RefineSettings, name: str
        ) -> tuple[TexelFit, str]:
            """``refine_fit`` of ``table``'s traces from ``start`` (the others keep its answers), cached as ``name``."""

            def stage(d: Path) -> None:
                full = scene
                if scene is not None:  # the texels whose rays above their plane meet nothing: only when it runs
                    full = dataclasses.replace(scene, exposed=exposed(mesh.vertices, texels.position, texels.normal))
                refine_fit(scan.scanner, table, start, settings, progress, texels, full).save(d / "refined.npz")

            key = {
                "fit": h_start,
                "support": h_support,
                "settings": dataclasses.asdict(settings),
                "views": REFINE_TUNING.inputs.refine_views,
                "min_clear_entries": REFINE_TUNING.inputs.min_clear_entries,
                "code": _stage_code("refine"),
                "calibration_texels": REFINE_TUNING.inputs.calibration_texels,
            }  # a table of the seeds alone: the start's key holds their count
            folder, h = cache.get(name, key, stage)
            return TexelFit.load(folder / "refined.npz"), h

        if refine:
            fitted, _ = refined(traces, fitted, h_fit, REFINE, "refine")
            report.refine = refine_summary(fitted)
            report.timed("refine", t0)
        else:
            assert seeds is not None and seed_traces is not None
            teacher, h_teacher = refined(seed_traces, fitted, h_fit, REFINE, "teacher")
            report.timed("teacher", t0)
            distilled, h_distil = _distil_stage(
                scan, cache, traces, teacher, seeds, h_teacher, net, model_key, fit_key, scale, pool, progress, report
            )
            t0 = time.perf_counter()
            fitted, _ = refined(traces, distilled, h_distil, POLISH, "polish")
            report.refine = refine_summary(fitted)
            report.timed("polish", t0)

    t0 = time.perf_counter()
    staging = temp_dir(out, "result")  # every output here first, then moved into place
    try:
        write_result(staging, mesh, texels, fitted, lengths, origin)
        report.timed("maps", t0)
        observed = lengths > 0
        coverage = float(observed.mean()) if len(texels) else 0.0
        flagged = int((fitted.flags != 0).sum())
        beyond = float(beyond_principled(fitted.alpha[observed]).mean()) if observed.any() else 0.0
        _, clipped = base_colour_for_fresnel_mix(fitted.rho_d[observed], fitted.rho_s[observed])
        clip_share = float(clipped.mean()) if observed.any() else 0.0
        report.texels = TexelCounts(len(texels), int(observed.sum()), coverage, flagged, resolution, beyond, clip_share)
        report.model = {"name": str(model_folder), **meta.get("summary", {})}
        report.cached_stages = cache.hits
        report.recomputed_damaged_stages = cache.recomputed
        report.seconds = round(time.perf_counter() - t_all, 3)
        assert report.photos is not None  # filled by the registration
        report.photos.used = stats.views_used
        publish(staging, out, json.dumps(report.to_json(), indent=2))
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return report


def _distil_stage(
    scan: Scan,
    cache: StageCache,
    traces: RaggedTraces,
    teacher: TexelFit,
    seeds: np.ndarray,
    h_teacher: str,
    net: TraceNet,
    model_key: dict,
    fit_key: dict,
    scale: float,
    pool: TaskPool,
    progress: Progress,
    report: Report,
) -> tuple[TexelFit, str]:
    """The network fine-tuned on the ``seeds``' refined answers (``teacher``; ``pipeline.distil``),
    then the fit stage again over every texel with it (cached as ``distil``); the seeds keep the
    teacher's own answers; and the stage's hash. Fills ``report.distil`` and the stage's seconds."""
    t0 = time.perf_counter()

    def compute(d: Path) -> None:
        tuned, rep = distilled_network(net, traces, scale, teacher, seeds, progress=progress)
        t1 = time.perf_counter()
        with pool as p:
            fit = fit_blocks(tuned, scan.scanner, traces, scale, p, progress)
        write_text_atomic(d / "distil.json", json.dumps({**rep.to_json(), "seconds_fit": time.perf_counter() - t1}))
        fit.save(d / "fit.npz")

    key = {
        "teacher": h_teacher,
        **model_key,
        **fit_key,
        "tuning": dataclasses.asdict(TUNING.distil),
        "code": _stage_code("distil"),
    }
    folder, h_distil = cache.get("distil", key, compute)
    fitted = TexelFit.load(folder / "fit.npz")
    for name in ("n_loc", "t_loc", "alpha", "flags", "rho_d", "rho_s"):  # the seeds: their own refinement
        getattr(fitted, name)[seeds] = getattr(teacher, name)[seeds]
    report.distil = json.loads((folder / "distil.json").read_text())  # DistilReport's fields and seconds_fit
    report.timed("distil", t0)
    return fitted, h_distil


def refine_summary(fitted: TexelFit) -> RefineSummary:
    """``report.json``'s ``refine``: the noise calibration and the basis materials' reach."""
    out = RefineSummary()
    if fitted.noise_scale is not None:
        out.noise_scale = float(fitted.noise_scale)
    if fitted.normal_prior_at_mesh is not None:  # where the normal's weak pull centred (refine.policy.calibrated)
        out.normal_prior = "mesh" if fitted.normal_prior_at_mesh else "start"
    if fitted.material is not None:
        out.basis_materials = int(len(fitted.materials["material_share"])) if fitted.materials else 0
        if fitted.matte_share is not None:  # the matte class's share estimated on this object
            out.matte_share = round(fitted.matte_share, 4)
        out.texels_lobe_from_material = int((fitted.flags & TexelFlag.FROM_MATERIAL != 0).sum())
        out.texels_width_from_material = int((fitted.flags & TexelFlag.WIDTH_FROM_MATERIAL != 0).sum())
        if fitted.width_varies is not None:  # materials whose width is a field over the object
            out.materials_width_varies = int(fitted.width_varies.sum())
    return out


def cached_fit(out: Path) -> tuple[RaggedTraces, TexelFit]:
    """The traces (linear pixels as captured) and the network's fit (``fit_traces``) that a finished
    ``reconstruct`` into ``out`` keeps in its cache: what the refinement starts from."""
    traces = trace_assembly.load_table(out / "cache" / "traces")
    return traces, TexelFit.load(out / "cache" / "fit" / "fit.npz")


def _check_measured(scan: Scan, stats: TraceCounts, lengths: np.ndarray, posed: int) -> None:
    """Refuse a run that measured too little to be a result (``TUNING.run.min_photos_used``,
    ``TUNING.run.min_coverage``), naming the likely cause: a mesh not where the photos look, or poses of
    other photos."""
    cause = "are the mesh and the poses in the same frame and units (metres)?"
    if stats.views_used < TUNING.run.min_photos_used:
        raise NtpInputError(
            scan.mesh_path,
            f"only {stats.views_used} of {posed} posed photos see this mesh "
            f"(need {TUNING.run.min_photos_used}) — {cause}",
        )
    coverage = float((lengths > 0).mean()) if len(lengths) else 0.0
    if coverage < TUNING.run.min_coverage:
        raise NtpInputError(
            scan.mesh_path,
            f"only {coverage:.1%} of the mesh's texels are seen in any photo "
            f"(need {TUNING.run.min_coverage:.0%}) — {cause}",
        )


def _atlas_stage(
    scan: Scan, cache: StageCache, resolution: int, origin: np.ndarray, progress: Progress
) -> tuple[Mesh, str]:
    """The mesh with the UVs the maps use: its own, else an xatlas atlas for ``resolution`` (minutes
    for a large mesh: shown as a one-step stage); in the scan's local frame (``origin``, a function
    of the mesh: the key's mesh content holds it)."""

    def compute(d: Path) -> None:
        with progress.counter("atlas", 1, "mesh") as bar:
            mesh = moved(load_mesh(scan.mesh_path), -origin)
            save_obj(d / "mesh.obj", mesh if mesh.uv is not None else uv_atlas(mesh, resolution))
            bar.update()

    key = {
        "mesh": content_key([scan.mesh_path]),
        "resolution": resolution,
        "code": _stage_code("atlas"),
    }
    folder, h_atlas = cache.get("atlas", key, compute)
    return load_mesh(folder / "mesh.obj"), h_atlas


def _photo_codes(scan: Scan, name: str) -> np.ndarray:
    """A kept photo's 8-bit codes (its content is in the stage key, so it is the photo selected)."""
    return read_codes(scan.photos_dir / name, scan.scanner)


def _support_stage(
    scan: Scan,
    cache: StageCache,
    mesh: Mesh,
    caster: RayCaster,
    poses: dict[str, np.ndarray],
    h_atlas: str,
    h_pose: str,
    progress: Progress,
) -> tuple[SupportAlbedo, str]:
    """The support's albedo map from the photos (``refine.support_light``) and its stage hash."""
    names = sorted(poses)

    def compute(d: Path) -> None:
        def photos() -> Iterator[tuple[np.ndarray, np.ndarray]]:
            for n in progress.track(names, "support", total=len(names), unit="photo"):
                codes = _photo_codes(scan, n)
                yield camera.decode(scan.scanner, torch.as_tensor(codes, dtype=torch.float64)).numpy(), codes

        estimate_support_albedo(photos(), [poses[n] for n in names], scan.scanner, mesh.vertices, caster).save(
            d / "support.npz"
        )

    key = {
        "atlas": h_atlas,
        "poses": h_pose,
        "cell": REFINE_TUNING.support.cell,
        "reach": REFINE_TUNING.support.reach_radii,
        "codes": REFINE_TUNING.support.code_range,
        "code": _stage_code("support"),
    }
    folder, h = cache.get("support", key, compute)
    return SupportAlbedo.load(folder / "support.npz"), h


def _traces_stage(
    scan: Scan,
    cache: StageCache,
    texels: Texels,
    mesh: Mesh,
    h_atlas: str,
    poses: dict[str, np.ndarray],
    h_pose: str,
    progress: Progress,
) -> tuple[RaggedTraces, TraceCounts, str]:
    """Every texel's trace (linear pixels as captured) and the assembly's statistics."""
    names = sorted(poses)
    support_z = float(mesh.vertices[:, 2].min()) if scan.support_plane else None

    def compute(d: Path) -> None:
        photos = (_photo_codes(scan, n) for n in names)
        tr, st = trace_assembly.assemble(
            texels,
            photos,
            [poses[n] for n in names],
            scan.scanner,
            RayCaster([mesh.triangles]),
            progress=progress,
            support_z=support_z,
            folder=d,
        )
        (d / "stats.json").write_text(
            json.dumps(
                {
                    "entries": st.entries,
                    "table_entries": int(tr.offsets[-1]),  # in range or not: the table's rows
                    "views_used": st.views_used,
                    "views_seeing_no_texel": len(names) - st.views_used,
                    "rejected": st.rejected,
                }
            )
        )
        del tr

    key = {
        "atlas": h_atlas,
        "poses": h_pose,
        "support": scan.support_plane,
        "max_shadowed_drive": trace_assembly.MAX_SHADOWED_DRIVE,
        "emitter_shadows": TUNING.traces.sky_rays,  # entries the mesh shadows: kept with their masks
        "shadow_splits": SHADOW_SPLITS,
        "min_cos_grazing": TUNING.traces.min_cos_grazing,  # grazing entries: kept, flagged
        "max_tap_tilt_deg": TUNING.traces.max_tap_tilt_deg,  # pixels that see another surface: not read
        "out_of_range_kept": True,
        "support_shadowed_kept": True,  # the support's shadow: entries kept out of range, its groups masked
        "files": trace_assembly.TABLE_FILES,
        "device": scanner_to_dict(scan.scanner),
        "code": _stage_code("traces"),
    }
    folder, h_tr = cache.get("traces", key, compute)
    stats = TraceCounts(**json.loads((folder / "stats.json").read_text()))
    return trace_assembly.load_table(folder), stats, h_tr
