"""``ntp bench registration``: registration alone on the gallery — every object x scanner x SfM seed:
pycolmap SfM as a user runs it, the similarity to the mesh, the error of the resulting poses against
the truth (camera centre and rotation medians) and the alignment's own diagnostics (residual,
inliers, the azimuth margin: how much worse the best alternative azimuth scores), a second cue — the
check's answer refined by the photos' texture alone (``PhotometricRegistration.refine_texture``) and
its error — and the check's sharpnesses (shading, texture) at the true poses, what a right
registration of the scan scores. Right and wrong alignments side by side are what a registration
confidence is set from.

Scans are the gallery's (``bench.gallery.scan_object``, shared with ``ntp bench gallery`` under the
same ``--out``); each SfM model is kept as a COLMAP folder under ``OUT/sfm/<object>-<scanner>-s<seed>/``
and reused (``register.colmap_model``), so re-runs only re-align. With ``--board PAPER`` the objects
stand on a marker board and the board registers the photos (``register.board_poses``; no SfM, so
one row per object x scanner, its seed ``-``). Writes ``OUT/registration.json`` and
``OUT/registration.md`` (``registration-board.*`` with the board).
"""

from __future__ import annotations

import argparse
import json
import shutil
import time
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np

from ..io.atomic import temp_dir, write_text_atomic
from ..io.errors import NtpInputError
from ..io.mesh import load_mesh
from ..io.output_folder import claim
from ..io.progress import QUIET, Progress, add_progress_arguments, progress_from_args
from ..register.align import Alignment, equivalent_turns
from ..register.board_poses import BoardPoses, board_poses
from ..register.check import MeshRegistration, corrected, register_to_mesh
from ..register.colmap_model import model_files, read_colmap_model
from ..register.photometric import PhotometricRegistration, edge_stride
from ..register.refusal import named_rival, refusal, refusal_kind, symmetry_note
from ..register.settings import TUNING
from ..register.sfm import SfmResult, structure_from_motion
from ..scanner.board import PAPERS
from ..scanner.local_frame import pose_to_local, pose_to_world
from ..scanner.scan_folder import load_poses, load_scan
from ..sim.evaluate import pose_error, pose_error_modulo, similarity_fit
from ..sim.gallery import build_asset, object_set
from ..sim.virtual_scan import true_mesh_path
from . import gallery as gallery_bench
from .gallery import DEFAULT, GallerySettings, scan_folder, scan_object

SEEDS = (0, 1, 2)
RIGHT_MM, RIGHT_DEG = 1.0, 0.3  # the goal: a registration this close is right


def _sfm(scan_dir: Path, model_dir: Path, seed: int, progress: Progress) -> tuple[SfmResult, float]:
    """The SfM of a scan for ``seed``: read back from ``model_dir`` if kept, else run and kept."""
    scan = load_scan(scan_dir)
    names = [p.name for p in scan.photo_paths]
    if model_dir.is_dir():
        return read_colmap_model(model_dir, scan.scanner, names), 0.0
    work = temp_dir(model_dir.parent, model_dir.name)
    try:
        t0 = time.perf_counter()
        reg = structure_from_motion(scan.photos_dir, names, scan.scanner, work / "sfm", progress=progress, seed=seed)
        seconds = time.perf_counter() - t0
        assert reg.model is not None
        shutil.copytree(reg.model, work / "model")
        model_files(work / "model")  # complete
        (work / "model").rename(model_dir)
    finally:
        shutil.rmtree(work, ignore_errors=True)
    return reg, seconds


def run(
    out: Path,
    settings: GallerySettings = DEFAULT,
    seeds: tuple[int, ...] = SEEDS,
    json_path: Path | None = None,
    progress: Progress = QUIET,
) -> dict:
    """Registration of every gallery object x scanner x seed into ``out``; returns the record."""
    settings = replace(settings, poses=("sfm",))
    out = Path(out)
    stem = "registration-board" if settings.board else "registration"
    rows = []
    with claim(out, "gallery"):
        for name in settings.objects:
            asset = build_asset(name, out / "assets" / name)
            for scanner in settings.scanners:
                scan_dir = scan_folder(out, settings, name, scanner)
                scan_object(settings, name, scanner, scan_dir, asset, progress)
                scan = load_scan(scan_dir)
                truth = load_poses(scan_dir / "ground_truth" / "poses.json")
                for seed in (None,) if settings.board else seeds:
                    row: dict = {"object": name, "set": object_set(name), "scanner": scanner, "seed": seed}
                    (out / "sfm").mkdir(exist_ok=True)
                    reg: SfmResult | BoardPoses
                    try:
                        if seed is None:
                            assert scan.board is not None, scan_dir
                            t0 = time.perf_counter()
                            reg = board_poses(
                                scan.photos_dir, [p.name for p in scan.photo_paths], scan.board, scan.scanner
                            )
                            row["seconds_board"] = time.perf_counter() - t0
                            # the board's poses' own error, whatever placement the mesh gets: the
                            # floor every placement's camera errors stand on
                            own = pose_error(similarity_fit(reg.poses, truth, scale=False), truth)
                            if own:  # at least 3 photos placed
                                row["board_centre_mm"] = own["centre_median_m"] * 1e3
                                row["board_rotation_deg"] = own["rotation_median_deg"]
                        else:
                            reg, row["seconds_sfm"] = _sfm(
                                scan_dir, out / "sfm" / f"{name}-{scanner}-s{seed}", seed, progress
                            )
                        names = sorted(reg.poses)
                        placed = register_to_mesh(scan, reg)
                        al, check = placed.icp, placed.check
                        row["seconds_align"] = placed.seconds_align
                        row["seconds_photometric"] = placed.seconds_photometric
                    except NtpInputError as failure:
                        row["failed"] = str(failure)
                        row["diagnosis"] = "refused: " + str(failure).split(": ", 1)[-1][:80]
                        rows.append(row)
                        continue

                    def world(a, reg=reg, names=names, placed=placed):  # the check's frame is the scan's local one
                        return {n: pose_to_world(a.camera_from_mesh(reg.poses[n]), placed.origin) for n in names}

                    # errors modulo the photographed shape's symmetries: a turned placement of a symmetric
                    # object is the same asset. The truth's, exact (a scanner's mesh puts its half turn
                    # 0.1-0.5 deg off, ~1 mm at the cameras), not the ones the registration found
                    centre, symmetric = _true_symmetry(scan_dir, 1e-3 * check.pixel_mm)
                    row["true_symmetry_turns"] = symmetric
                    icp = pose_error_modulo(world(al), truth, centre, symmetric)
                    err = pose_error_modulo(world(check.alignment), truth, centre, symmetric)
                    why = refusal(check)
                    # where the truth is among the candidates the photos compared (coarse refinement)
                    near = [
                        pose_error_modulo(world(a), truth, centre, symmetric)["rotation_median_deg"]
                        for a in check.trials
                    ]
                    rival = named_rival(check.candidates)
                    row.update(
                        registered=len(names),
                        icp_centre_mm=icp["centre_median_m"] * 1e3,
                        icp_rotation_deg=icp["rotation_median_deg"],
                        centre_mm=err["centre_median_m"] * 1e3,
                        rotation_deg=err["rotation_median_deg"],
                        residual_mm=al.residual_m * 1e3 if np.isfinite(al.residual_m) else None,
                        inliers=f"{al.kept_points}/{al.object_points}",
                        inlier_fraction=al.kept_points / max(al.object_points, 1),
                        azimuth_margin=al.azimuth_margin if np.isfinite(al.azimuth_margin) else None,
                        sharpness=check.sharpness if np.isfinite(check.sharpness) else None,
                        photometric_margin=check.margin if np.isfinite(check.margin) else None,
                        agreement=check.fit.agreement if np.isfinite(check.fit.agreement) else None,
                        placed_by=check.placed_by,
                        accepted=why is None,
                        refusal=why,
                        candidate_rotation_deg=near,
                        chosen=check.chosen,
                        rival=rival,
                        rival_mesh_turned_mm=check.candidates[rival]["mesh_turned_mm"] if rival is not None else None,
                        symmetry_turn_deg=check.symmetry[0] if np.isfinite(check.symmetry[0]) else None,
                        symmetry_mm=check.symmetry[1] if np.isfinite(check.symmetry[1]) else None,
                        equivalent_turns=check.equivalent_turns,
                        symmetry=symmetry_note(check),
                        truth_turn_deg=err["symmetry_turn_deg"],
                        kind=refusal_kind(check) or "accepted",
                        height_from_photos=check.height_from_photos,
                        pixel_mm=check.pixel_mm,
                    )
                    if placed.by_outline is not None:  # the outline's own placement, decided or not
                        o = placed.by_outline
                        oe = pose_error_modulo(world(o.alignment), truth, centre, symmetric)
                        row.update(
                            outline_centre_mm=oe["centre_median_m"] * 1e3,
                            outline_rotation_deg=oe["rotation_median_deg"],
                            outline_margin=o.margin if np.isfinite(o.margin) else None,
                            outline_spread_px=o.outline["spread_px"] if o.outline else None,
                            outline_outside=o.outline["points_outside"] if o.outline else None,
                            outline_refusal=refusal(o),
                        )
                    # the texture's own answer (``refine_texture`` from the check's): a second cue,
                    # free of the mesh's normals, and both cues' statistics at the true poses
                    cues, by_texture = _texture_cues(placed, reg, truth, scan.support_plane, on_board=seed is None)
                    tex = pose_error_modulo(world(by_texture), truth, centre, symmetric)
                    apart = pose_error_modulo(world(by_texture), world(check.alignment), centre, [])
                    row.update(
                        cues,
                        texture_centre_mm=tex["centre_median_m"] * 1e3,
                        texture_rotation_deg=tex["rotation_median_deg"],
                        cues_apart_mm=apart["centre_median_m"] * 1e3,
                        cues_apart_deg=apart["rotation_median_deg"],
                    )
                    row["right"] = row["centre_mm"] <= RIGHT_MM and row["rotation_deg"] <= RIGHT_DEG
                    row["diagnosis"] = _diagnosis(row)
                    rows.append(row)
                    # rows so far survive an interrupted run (the SfM models are kept anyway)
                    write_text_atomic(out / f"{stem}.json", json.dumps({"runs": rows}, indent=1, default=float))
    record = {"settings": asdict(settings), "seeds": list(seeds), "runs": rows}
    table = _table(rows)
    write_text_atomic(out / f"{stem}.json", json.dumps(record, indent=1, default=float))
    write_text_atomic(out / f"{stem}.md", table)
    if json_path:
        write_text_atomic(json_path, json.dumps(record, indent=1, default=float))
    print(table)
    return record


def _true_symmetry(scan_dir: Path, pixel_m: float) -> tuple[np.ndarray, list[float] | None]:
    """The photographed mesh's centre (world, metres) and its exact symmetries about the vertical
    (``align.equivalent_turns`` within what a photo of ``pixel_m`` metres a pixel sees, on the true
    mesh: no scanner's noise in it)."""
    true_mesh = load_mesh(true_mesh_path(scan_dir))
    centre = 0.5 * (true_mesh.vertices.min(0) + true_mesh.vertices.max(0))
    pixel_m = pixel_m if np.isfinite(pixel_m) else 5e-4  # unmeasured: the benches' quarter-size pixel
    turns = equivalent_turns(true_mesh, centre, TUNING.check.symmetry_px * pixel_m)
    return centre, turns


def _texture_cues(
    placed: MeshRegistration,
    reg: SfmResult | BoardPoses,
    truth: dict[str, np.ndarray],
    support_plane: bool,
    on_board: bool,
) -> tuple[dict, Alignment]:
    """The check's answer refined by the texture alone (``PhotometricRegistration.refine_texture``,
    the finisher's blur levels), the texture's sharpness there (a placement by photos) and both
    sharpnesses at the true poses — what a right registration of the scan scores —, measured as the
    check's finisher measures them."""
    mesh = placed.mesh
    support_z = float(mesh.vertices[:, 2].min()) if support_plane else None
    judge = PhotometricRegistration(
        mesh,
        placed.photos,
        support_z,
        points=TUNING.photometric.fine_points,
        edge_stride=edge_stride(placed.photos),
        free_scale=not on_board,
    )
    answer = np.stack([placed.check.alignment.camera_from_mesh(reg.poses[n]) for n in placed.judged])
    true = np.stack([pose_to_local(truth[n], placed.origin) for n in placed.judged])
    sigma = TUNING.photometric.sharpness_sigma_px
    stats = {
        "texture_sharpness": judge.texture_sharpness(answer, sigma) if placed.check.cloud is None else None,
        "truth_sharpness": judge.sharpness(true, sigma),
        "truth_texture_sharpness": judge.texture_sharpness(true, sigma),
    }
    g, _ = judge.refine_texture(answer, TUNING.photometric.blur_levels_px[1:])
    return stats, corrected(placed.check.alignment, g)


NEAR_DEG = 5.0  # a candidate this close (rotation median) to the truth holds it: finer refinement finds it


def _diagnosis(row: dict) -> str:
    """Whether a row's verdict is right (modulo the mesh's symmetries): a right registration
    accepted, a wrong one refused — and whether the rival an ambiguity names holds the truth."""
    kind = row["kind"]
    if kind == "accepted":
        return "right" if row["right"] else "WRONG ACCEPTED"
    if row["right"]:
        return f"RIGHT REFUSED ({kind})"
    if kind == "ambiguous":
        near = row["candidate_rotation_deg"]
        at = [
            f"{w} ({near[i]:.1f} deg)"
            for w, i in (("chosen", row["chosen"]), ("rival", row["rival"]))
            if near[i] <= NEAR_DEG
        ]
        return "wrong, refused: ambiguous; truth at " + (" and ".join(at) if at else "neither")
    return "wrong, refused: unconfirmed"


def _table(rows: list[dict]) -> str:
    header = (
        "object",
        "set",
        "scanner",
        "seed",
        "registered",
        "the board's own mm / deg",
        "point-cloud fit mm / deg",
        "residual mm",
        "inliers",
        "cloud margin",
        "outline mm / deg (margin, spread px)",
        "refined mm / deg",
        "the texture's mm / deg",
        "sharpness shading / texture (at the truth)",
        "photo margin",
        "mesh symmetry deg / mm (equivalent placements)",
        "right",
        "accepted",
        "diagnosis",
    )
    cells = []
    for r in rows:
        if "failed" in r:
            cells.append(
                (
                    r["object"],
                    r.get("set", "tune"),
                    r["scanner"],
                    r["seed"],
                    "FAILED",
                    *[""] * 12,
                    "refused",
                    r["diagnosis"],
                )
            )
            continue
        margin = "-" if r["azimuth_margin"] is None else f"{r['azimuth_margin']:.3g}"
        photo_margin = "-" if r["photometric_margin"] is None else f"{r['photometric_margin']:.3g}"
        cells.append(
            (
                r["object"],
                r.get("set", "tune"),
                r["scanner"],
                "-" if r["seed"] is None else r["seed"],
                r["registered"],
                _board_cell(r),
                f"{r['icp_centre_mm']:.2f} / {r['icp_rotation_deg']:.2f}",
                "-" if r["residual_mm"] is None else f"{r['residual_mm']:.2f}",
                r["inliers"],
                margin,
                _outline_cell(r),
                f"{r['centre_mm']:.2f} / {r['rotation_deg']:.2f}",
                f"{_number(r.get('texture_centre_mm'))} / {_number(r.get('texture_rotation_deg'))}",
                f"{_number(r['sharpness'])} / {_number(r.get('texture_sharpness'))} "
                f"({_number(r.get('truth_sharpness'))} / {_number(r.get('truth_texture_sharpness'))})",
                photo_margin,
                _symmetry_cell(r),
                "yes" if r["right"] else "NO",
                "yes" if r["accepted"] else "refused",
                r["diagnosis"],
            )
        )
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(str(c) for c in row) + " |" for row in cells]
    lines += ["", _summary(rows, "")]
    sets = sorted({r.get("set", "tune") for r in rows})
    if len(sets) > 1:  # the tuning set's outcome and the validation set's, side by side
        lines += [_summary([r for r in rows if r.get("set", "tune") == s], f"{s}: ") for s in sets]
    return "\n".join(lines) + "\n"


def _outline_cell(r: dict) -> str:
    """The outline's own placement (error modulo symmetry), its rival margin and spread; - where none."""
    if r.get("outline_centre_mm") is None:
        return "-"
    return (
        f"{r['outline_centre_mm']:.2f} / {r['outline_rotation_deg']:.2f} "
        f"({_number(r.get('outline_margin'))}, {_number(r.get('outline_spread_px'))})"
    )


def _board_cell(r: dict) -> str:
    """The board's poses' own error (mm / deg: after the rigid motion that best puts them on the
    truth); - without a board."""
    if r.get("board_centre_mm") is None:
        return "-"
    return f"{r['board_centre_mm']:.2f} / {r['board_rotation_deg']:.3f}"


def _number(value: float | None) -> str:
    """A statistic to two decimals, "-" where it was not measured."""
    return "-" if value is None or not np.isfinite(value) else f"{value:.2f}"


def _symmetry_cell(r: dict) -> str:
    """The mesh's nearest symmetry (turn deg / mm) and how many placements the photos cannot tell apart."""
    if r.get("equivalent_turns", []) is None:
        return "every turn"
    near = "-" if r["symmetry_mm"] is None else f"{r['symmetry_turn_deg']:.0f} / {r['symmetry_mm']:.2f}"
    same = len(r.get("equivalent_turns") or [])
    return f"{near} ({same + 1} placements)" if same else near


def _summary(rows: list[dict], prefix: str) -> str:
    """The outcome of ``rows`` in one line: right/wrong x accepted/refused, and failures."""
    done = [r for r in rows if "failed" not in r]
    wrong_accepted = sum(1 for r in done if r["accepted"] and not r["right"])
    right_refused = sum(1 for r in done if r["right"] and not r["accepted"])
    right_accepted = sum(1 for r in done if r["right"] and r["accepted"])
    wrong_refused = sum(1 for r in done if not r["right"] and not r["accepted"])
    return (
        f"{prefix}{len(rows)} registrations: right and accepted {right_accepted}, wrong and refused {wrong_refused}, "
        f"SfM or point-cloud alignment refused {len(rows) - len(done)}; "
        f"**wrong accepted: {wrong_accepted}; right refused: {right_refused}** "
        f"(right: <= {RIGHT_MM:g} mm and {RIGHT_DEG:g} deg, camera centre and rotation medians)"
    )


HELP = "SfM + alignment alone on the gallery: pose error per object x seed"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """``ntp bench registration``'s options."""
    parser.add_argument("--out", type=Path, default=Path("ntp_gallery"), help="the gallery's folder (scans shared)")
    parser.add_argument("--quick", action="store_true", help="the quick gallery's objects and sizes")
    gallery_bench.add_object_arguments(parser)
    gallery_bench.add_scanner_arguments(parser)
    gallery_bench.add_mesh_argument(parser)
    parser.add_argument("--seeds", nargs="+", type=int, default=list(SEEDS))
    parser.add_argument("--views", type=int, default=None)
    parser.add_argument("--scale", type=float, default=None)
    parser.add_argument("--samples", type=int, default=None, help="Cycles samples per pixel")
    parser.add_argument("--json", type=Path, default=None)
    parser.add_argument(
        "--board", choices=list(PAPERS), default=None, help="the objects stand on a marker board, which registers them"
    )
    add_progress_arguments(parser)


def command(args: argparse.Namespace) -> int:
    """``ntp bench registration``: the benchmark with the command line's options; the exit code."""
    settings = gallery_bench.settings_for(
        args.quick,
        objects=gallery_bench.chosen_objects(args, args.quick),
        scanners=gallery_bench.chosen_scanners(args),
        poses=None,
        views=args.views,
        scale=args.scale,
        resolution=None,
        samples=args.samples,
        mesh=args.mesh,
        board=args.board,
    )
    run(args.out, settings, tuple(args.seeds), json_path=args.json, progress=progress_from_args(args))
    return 0
