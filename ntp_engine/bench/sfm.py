"""``ntp bench sfm``: the SfM mappers at scale — incremental, global (GLOMAP) and hierarchical, on
virtual scans of the dome with 60 / 300 / 1000 photos at low scale: seconds and the poses' own error
(camera centre / rotation medians after the best similarity to the truth, which is the alignment's
job, not the mapper's), registered photos. Scans are kept under ``OUT/scans/dome-<photos>/`` and
re-used; every mapper runs on the same photos. Writes ``OUT/sfm.json`` and ``OUT/sfm.md``.
"""

from __future__ import annotations

import argparse
import json
import shutil
import time
from dataclasses import replace
from pathlib import Path

from ..io.atomic import temp_dir, write_text_atomic
from ..io.errors import NtpInputError
from ..io.output_folder import claim
from ..io.progress import QUIET, Progress, add_progress_arguments, progress_from_args
from ..register.sfm import MAPPERS, structure_from_motion
from ..scanner.scan_folder import load_poses, load_scan
from ..sim.evaluate import pose_error, similarity_fit
from ..sim.gallery import build_asset
from .gallery import DEFAULT, scan_object

PHOTOS = (60, 300, 1000)
SCALE = 0.0625  # 153 x 128 px: virtual scans of 1000 photos within minutes


def run(
    out: Path,
    photos: tuple[int, ...] = PHOTOS,
    mappers: tuple[str, ...] = MAPPERS,
    scale: float = SCALE,
    seed: int = 0,
    json_path: Path | None = None,
    progress: Progress = QUIET,
) -> dict:
    """Every mapper on a dome scan of each photo count into ``out``; returns the record."""
    out = Path(out)
    rows = []
    with claim(out, "gallery"):
        asset = build_asset("dome", out / "assets" / "dome")
        for count in photos:
            scan_dir = out / "scans" / f"dome-{count}"
            settings = replace(DEFAULT, views=count, scale=scale, seed=seed)
            scan_object(settings, "dome", "engine", scan_dir, asset, progress)
            scan = load_scan(scan_dir)
            truth = load_poses(scan_dir / "ground_truth" / "poses.json")
            names = [p.name for p in scan.photo_paths]
            for mapper in mappers:
                row: dict = {"photos": count, "mapper": mapper}
                work = temp_dir(out, f"sfm-{mapper}-{count}")
                t0 = time.perf_counter()
                try:
                    reg = structure_from_motion(
                        scan.photos_dir, names, scan.scanner, work, progress=progress, seed=seed, mapper=mapper
                    )
                except NtpInputError as failure:
                    row.update(failed=str(failure), seconds=time.perf_counter() - t0)
                    rows.append(row)
                    continue
                finally:
                    shutil.rmtree(work, ignore_errors=True)
                row["seconds"] = time.perf_counter() - t0
                err = pose_error(similarity_fit(reg.poses, truth), truth)
                row.update(
                    registered=len(reg.poses),
                    points=len(reg.points),
                    centre_mm=err["centre_median_m"] * 1e3,
                    rotation_deg=err["rotation_median_deg"],
                    centre_max_mm=err["centre_max_m"] * 1e3,
                )
                rows.append(row)
                write_text_atomic(out / "sfm.json", json.dumps({"runs": rows}, indent=1))  # progress survives a kill
    record = {"scale": scale, "seed": seed, "runs": rows}
    table = _table(rows)
    write_text_atomic(out / "sfm.json", json.dumps(record, indent=1))
    write_text_atomic(out / "sfm.md", table)
    if json_path:
        write_text_atomic(json_path, json.dumps(record, indent=1))
    print(table)
    return record


def _table(rows: list[dict]) -> str:
    lines = [
        "| photos | mapper | registered | seconds | x incremental | centre mm (median / max) | rotation deg |",
        "|---|---|---|---|---|---|---|",
    ]
    base = {r["photos"]: r["seconds"] for r in rows if r["mapper"] == "incremental"}
    for r in rows:
        ratio = f"{r['seconds'] / base[r['photos']]:.2f}" if r["photos"] in base else "-"
        if "failed" in r:
            failed = f"FAILED: {r['failed'][:60]}"
            lines.append(f"| {r['photos']} | {r['mapper']} | {failed} | {r['seconds']:.0f} | {ratio} | | |")
            continue
        lines.append(
            f"| {r['photos']} | {r['mapper']} | {r['registered']} | {r['seconds']:.0f} | {ratio} | "
            f"{r['centre_mm']:.2f} / {r['centre_max_mm']:.2f} | {r['rotation_deg']:.3f} |"
        )
    return "\n".join(lines) + "\n"


HELP = "SfM mappers (incremental, global, hierarchical) at 60 / 300 / 1000 photos"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """``ntp bench sfm``'s options."""
    parser.add_argument("--out", type=Path, default=Path("ntp_sfm_bench"), help="folder for the scans and the table")
    parser.add_argument("--photos", nargs="+", type=int, default=list(PHOTOS))
    parser.add_argument("--mappers", nargs="+", choices=list(MAPPERS), default=list(MAPPERS))
    parser.add_argument("--scale", type=float, default=SCALE, help="photo size (1.0 = the device's)")
    parser.add_argument("--json", type=Path, default=None)
    add_progress_arguments(parser)


def command(args: argparse.Namespace) -> int:
    """``ntp bench sfm``: the benchmark with the command line's options; the exit code."""
    run(
        args.out,
        tuple(args.photos),
        tuple(args.mappers),
        args.scale,
        json_path=args.json,
        progress=progress_from_args(args),
    )
    return 0
