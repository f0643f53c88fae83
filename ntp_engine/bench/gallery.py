"""``ntp bench gallery``: ntp measured on the gallery — every object x scanner (the engine's virtual
scanner and Cycles) x poses (true, structure from motion) — reported per material.

Per run: pose error (SfM), relit SSIM under novel point lights (object pixels) and, where ntp is
given another mesh than the photographed one, that mesh's ceiling (the truth's own maps on it:
``sim.evaluate.mesh_ceiling``), seconds per stage;
per material (``sim.evaluate.material_errors``): the share of its surface texels some photo sees
(true poses), coverage (of those, the share some trace reached), normal angle, tangent angle mod 180 on
anisotropic texels, |log alpha ratio|, rho_d RMSE and ratio, the share of texels on a material
border and the rho_d RMSE of the others, the rho_d RMSE a perfect map at the maps' resolution
scores (its floor), |log rho_s ratio|, spurious-lobe rate on matte. With ``budget``
(``--budget``), where each run's relit SSIM is lost: the SSIM gained by one group of maps of one
material taken from the truth (``sim.evaluate.relit_budget``). Writes
``OUT/gallery.json``, ``OUT/gallery.md`` (the tables) and
``OUT/gallery.png`` (error per material, a bar per scanner x poses), and prints the tables; with
``refine`` (``--refine``) the results and files are ``*-refined`` beside them, from the same scans,
and with another trace network (``model``, ``--model``) ``*-model-NAME``.

Everything is cached under ``OUT`` (assets, scans keyed by their settings and asset content,
Cycles renders, pipeline stages), so a re-run after an interruption resumes.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import time
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np

from ..io.atomic import write_text_atomic
from ..io.errors import NtpInputError
from ..io.output_folder import claim
from ..io.progress import QUIET, Progress, add_progress_arguments, progress_from_args
from ..io.stage_cache import content_digest, digest
from ..pipeline.settings import PATHS
from ..pipeline.stages import reconstruct, register_photos
from ..scanner.scan_folder import load_poses, load_scan
from ..sim.cycles_scan import RENDER_VERSION, CyclesConfig, at_least_samples, cycles_scan
from ..sim.evaluate import (
    BUDGET_GROUPS,
    PARAMETER_METRICS,
    material_errors,
    mesh_ceiling,
    pose_error,
    relit_budget,
    relit_ssim,
)
from ..sim.gallery import GALLERY, SCANNER_MESH, SETS, build_asset, object_set
from ..sim.generated import FAMILIES, is_generated
from ..sim.virtual_scan import ScanConfig, scan_folder_is_current, true_mesh_path, virtual_scan
from . import finite_mean, number, print_table, tune_validate

SCANNERS = ("engine", "cycles")
# a set's default scanner: the engine's. Cycles costs 4-6 min an object at 40 photos (the gallery's
# Cycles half: 20 min for 5 objects; dome and two validation objects: 17 min), over an hour more for
# the validation set's 12: ``--scanners`` adds it
SET_SCANNERS = ("engine",)
POSES = ("true", "sfm")
# ... and its default poses: the true ones. A registration's photometric check costs 5-8 min an object
# at 40 photos (2026-12-02, docs/accuracy.md), 1-1.5 h for a set: ``ntp bench registration --set``
# measures registration, ``--poses true sfm`` adds it here
SET_POSES = ("true",)
METRICS = ("seen", "coverage", *PARAMETER_METRICS)


@dataclass(frozen=True)
class GallerySettings:
    """What one gallery run covers and at what size."""

    objects: tuple[str, ...] = tuple(GALLERY)
    scanners: tuple[str, ...] = SCANNERS
    poses: tuple[str, ...] = POSES
    views: int = 40
    scale: float = 0.125
    resolution: int = 128
    samples: int = 12  # Cycles samples per pixel (the default set's 30-minute budget)
    max_samples: int = CyclesConfig.max_samples  # ... and up to this many where Cycles sees noise (highlights)
    bounces: int = 2
    relit_lights: int = 3
    relit_scale: float = 0.125
    seed: int = 0
    refine: bool = False  # the analysis-by-synthesis refinement after the network's fit (the path "refine")
    # the reconstruction paths each scan goes through, each into its own results (PATHS: network + fit,
    # the scan's own network, every texel refined); more than one adds the run time against error table
    paths: tuple[str, ...] = ()
    distil: bool = False  # the scan's own network (the path "distil")
    model: str | None = None  # the trace network (a shipped name or a model folder; None: the default)
    budget: bool = False  # where the relit SSIM is lost, per material x group of maps (sim.evaluate.relit_budget)
    # the mesh ntp is given: a shape scanner's (coarser, smoothed, noisy: sim.scanner_mesh; the paper's
    # Fig. 11) or the photographed one; errors are measured against the truth either way
    mesh: str = "scanner"
    # more photo counts to scan each object at (accuracy against photo count: a method that uses its
    # data gets better with more of it); ``views`` is always scanned
    density: tuple[int, ...] = ()
    board: str | None = None  # the objects stand on a marker board of this paper size (scanner.board)

    @property
    def path_list(self) -> tuple[str, ...]:
        """The paths run: ``paths``, else the one ``refine`` or ``distil`` picks."""
        if self.paths:
            return self.paths
        return ("refine",) if self.refine else ("distil",) if self.distil else ("fast",)

    def on_path(self, path: str) -> GallerySettings:
        """These settings for one path alone."""
        return replace(self, paths=(), refine=path == "refine", distil=path == "distil")

    @property
    def photo_counts(self) -> tuple[int, ...]:
        """``views`` and the ``density`` counts, ascending, each once."""
        return tuple(sorted({self.views, *self.density}))


DEFAULT = GallerySettings()
QUICK = GallerySettings(
    objects=("vase", "knot"), poses=("true",), views=16, resolution=64, samples=8, max_samples=64, relit_lights=2
)


MESHES = ("scanner", "true")


def scan_folder(out: Path, settings: GallerySettings, name: str, scanner: str, views: int | None = None) -> Path:
    """Where the scan of ``name`` by ``scanner`` lives under the bench's folder ``out`` (a scan
    handing ntp the photographed mesh beside the one handing it a scanner's; one at another photo
    count, ``views``, beside the settings' own)."""
    return out / "scans" / f"{name}-{scanner}{_count_and_mesh(settings, views)}"


def scan_object(settings: GallerySettings, name: str, scanner: str, out: Path, asset: Path, progress: Progress) -> dict:
    """The scan of one object by one scanner (kept when its settings and asset are unchanged)."""
    cfg = ScanConfig(views=settings.views, scale=settings.scale, seed=settings.seed, board=settings.board)
    cycles = CyclesConfig(samples=settings.samples, bounces=settings.bounces, max_samples=settings.max_samples)
    key = digest(
        {
            "mesh": settings.mesh,
            "scanner": scanner,
            "config": asdict(cfg),
            "cycles": {**asdict(cycles), "render_version": RENDER_VERSION} if scanner == "cycles" else None,
            "asset": content_digest(sorted(p for p in asset.rglob("*") if p.is_file())),
        }
    )
    stamp = out / "ground_truth" / "bench_key.json"
    if stamp.is_file() and json.loads(stamp.read_text()).get("key") == key and scan_folder_is_current(out):
        return json.loads((out / "ground_truth" / "capture.json").read_text())
    given = asset / SCANNER_MESH if settings.mesh == "scanner" else None
    if scanner == "cycles":
        capture = cycles_scan(out, str(asset), cfg=cfg, cycles=cycles, progress=progress, given_mesh=given)
    else:
        capture = virtual_scan(out, str(asset), cfg=cfg, progress=progress, given_mesh=given)
    write_text_atomic(stamp, json.dumps({"key": key}))
    return capture


def _evaluate(settings: GallerySettings, scan_dir: Path, poses: str, out: Path, progress: Progress) -> dict:
    """Reconstruct one scan with true or SfM poses and measure it."""
    gt = scan_dir / "ground_truth"
    scan = load_scan(scan_dir, gt / "poses.json" if poses == "true" else None)
    t0 = time.perf_counter()
    try:
        rep = reconstruct(
            scan,
            out,
            resolution=settings.resolution,
            model=settings.model,
            progress=progress,
            refine=settings.refine,
            distil=settings.distil,
        )
    except NtpInputError as err:  # registration can fail on a hard object: that is a result too
        return {"failed": str(err), "seconds_reconstruct": time.perf_counter() - t0}
    seconds = time.perf_counter() - t0
    run: dict = {"stages": rep.stages, "seconds_reconstruct": seconds}
    if rep.texels is not None:
        run["texels_observed"] = rep.texels.observed
    if rep.distil is not None:
        run["distil"] = rep.distil
    if poses == "sfm":
        used, _, _ = register_photos(scan, out)
        run["pose_error"] = pose_error(used, load_poses(gt / "poses.json"))
        run["registered"] = f"{len(used)}/{settings.views}"
    relit = relit_budget if settings.budget else relit_ssim  # the budget's as-is score is relit_ssim's
    truth_mesh = true_mesh_path(scan_dir)
    scores = relit(out, truth_mesh, gt, lights=settings.relit_lights, scale=settings.relit_scale)
    run["relit_ssim"] = scores["relit_ssim"]
    if truth_mesh.resolve() != scan.mesh_path.resolve():  # ntp was given another mesh: what it allows
        run["mesh_ceiling"] = mesh_ceiling(
            scan.mesh_path, truth_mesh, gt, lights=settings.relit_lights, scale=settings.relit_scale
        )
    if settings.budget:
        run["relit_budget"] = scores
    true_poses = list(load_poses(gt / "poses.json").values())  # what the photos saw, whichever poses ran
    run["materials"] = material_errors(out, gt, scan.scanner, true_poses)
    return run


def run(
    out: Path,
    settings: GallerySettings = DEFAULT,
    json_path: Path | None = None,
    progress: Progress = QUIET,
) -> dict:
    """The gallery benchmark into ``out`` (module docstring); returns the record (also JSON)."""
    unknown = [o for o in settings.objects if o not in GALLERY and not is_generated(o)]
    if (
        unknown
        or not set(settings.scanners) <= set(SCANNERS)
        or not set(settings.poses) <= set(POSES)
        or settings.mesh not in MESHES
        or not set(settings.path_list) <= set(PATHS)
        or not all(3 <= n <= 100_000 for n in settings.photo_counts)
    ):
        raise NtpInputError(
            None,
            f"objects from {', '.join(GALLERY)} or generated ones (<family>-<seed>: {', '.join(FAMILIES)}); "
            f"scanners from {', '.join(SCANNERS)}; poses from {', '.join(POSES)}; mesh from {', '.join(MESHES)}; "
            f"paths from {', '.join(PATHS)}; "
            "3 to 100000 photos",
        )
    out = Path(out)
    with claim(out, "gallery"):
        t_all = time.perf_counter()
        runs = []
        for name in settings.objects:
            asset = build_asset(name, out / "assets" / name)
            for scanner, count in ((sc, n) for sc in settings.scanners for n in settings.photo_counts):
                at = replace(settings, views=count)
                scan_dir = scan_folder(out, settings, name, scanner, count)
                t0 = time.perf_counter()
                capture = scan_object(at, name, scanner, scan_dir, asset, progress)
                t_scan = time.perf_counter() - t0
                first: dict[str, Path] = {}  # per poses: the first path's result, whose shared stages the others take
                for poses, path in ((p, q) for p in settings.poses for q in settings.path_list):
                    one = settings.on_path(path)
                    result_dir = result_folder(out, one, name, scanner, poses, count)
                    if poses in first:
                        share_stages(first[poses], result_dir)
                    first.setdefault(poses, result_dir)
                    result = _evaluate(at.on_path(path), scan_dir, poses, result_dir, progress)
                    runs.append(
                        {
                            "object": name,
                            "set": object_set(name),
                            "views": count,
                            "scanner": scanner,
                            "poses": poses,
                            "path": path,
                            "seconds_scan": t_scan,
                            "seconds_per_photo": capture["seconds_per_photo"],
                            **result,
                        }
                    )
                    t_scan = 0.0  # counted once per scan
    record = {"settings": asdict(settings), "runs": runs, "seconds": time.perf_counter() - t_all}
    tables = markdown(record)
    stem = f"gallery{_suffix(settings)}"
    write_text_atomic(out / f"{stem}.json", json.dumps(record, indent=1, default=float))
    write_text_atomic(out / f"{stem}.md", tables)
    figure(record, out / f"{stem}.png")
    if len(settings.photo_counts) > 1:
        density_figure(record, out / f"{stem}-density.png")
    if {r["set"] for r in runs} == {"tune", "validate"}:
        sets_figure(record, out / f"{stem}-sets.png")
    if json_path:
        write_text_atomic(json_path, json.dumps(record, indent=1, default=float))
    _print(record)
    print(f"wrote {out / (stem + '.md')}, {out / (stem + '.json')}, {out / (stem + '.png')}")
    return record


# the stages every path computes alike (their keys hold no path): a later path's result takes the
# first one's by hard links (a stage folder is replaced whole, never written in place), so a scan's
# traces are assembled once, not once a path (~45 s an object at 360 photos)
SHARED_STAGES = ("select", "atlas", "traces")


def share_stages(source: Path, result: Path) -> None:
    """``result``'s stage cache given ``source``'s ``SHARED_STAGES`` (a result folder of the same
    scan and poses) where it has none of its own; its keys still decide whether a stage is used."""
    if not (source / "cache").is_dir():
        return
    with claim(result, "result"):
        for stage in SHARED_STAGES:
            src, dst = source / "cache" / stage, result / "cache" / stage
            if src.is_dir() and not dst.exists():
                shutil.copytree(src, dst, copy_function=os.link)


def _suffix(settings: GallerySettings) -> str:
    """Results and tables with another network or another path sit beside the default's (same
    scans): ``-model-<folder name>``, then ``-refined`` or ``-distilled`` (tables of several paths:
    ``-paths``)."""
    model = f"-model-{Path(settings.model).name}" if settings.model else ""
    paths = settings.path_list
    if len(paths) > 1:
        return model + "-paths"
    return model + {"fast": "", "refine": "-refined", "distil": "-distilled"}[paths[0]]


def result_folder(out: Path, settings: GallerySettings, name: str, scanner: str, poses: str, views: int) -> Path:
    """Where the reconstruction of one scan lives under the bench's folder ``out``: beside the
    default's with another photo count (``-vN``), the true mesh (``-truemesh``), another network
    or the refinement (``_suffix``)."""
    return out / "results" / f"{name}-{scanner}-{poses}{_count_and_mesh(settings, views)}{_suffix(settings)}"


def _count_and_mesh(settings: GallerySettings, views: int | None) -> str:
    """A scan's or result's name beside the default's: ``-vN`` at another photo count,
    ``-truemesh`` when ntp is given the photographed mesh, ``-board`` when the object stands on one."""
    count = "" if views is None or views == settings.views else f"-v{views}"
    return count + ("-truemesh" if settings.mesh == "true" else "") + ("-board" if settings.board else "")


def _run_rows(record: dict) -> tuple[tuple, list[tuple]]:
    header = (
        "object",
        "scanner",
        "poses",
        "path",
        "views",
        "registered",
        "pose err mm / deg",
        "relit SSIM",
        "mesh ceiling",
        "s scan",
        "s reconstruct",
        "s register / traces / net+fit",
    )
    rows = []
    for r in record["runs"]:
        pe = r.get("pose_error") or {}
        pose = f"{pe['centre_median_m'] * 1e3:.2f} / {pe['rotation_median_deg']:.2f}" if pe else "-"
        rows.append(
            (
                r["object"],
                r["scanner"],
                r["poses"],
                r.get("path", "fast"),
                r.get("views", record["settings"]["views"]),
                r.get("registered", "-") if "failed" not in r else "FAILED",
                pose,
                number(r.get("relit_ssim")),
                number(r.get("mesh_ceiling")),
                f"{r['seconds_scan']:.0f}",
                f"{r['seconds_reconstruct']:.0f}",
                " / ".join(
                    f"{r.get('stages', {}).get(k, float('nan')):.1f}" for k in ("register", "traces", "network_and_fit")
                ),
            )
        )
    return header, rows


def _material_rows(record: dict) -> tuple[tuple, list[tuple]]:
    header = ("object", "material", "scanner", "poses", "path", "views", *METRICS)
    rows = []
    for r in record["runs"]:
        views = r.get("views", record["settings"]["views"])
        path = r.get("path", "fast")
        for m in r.get("materials", []):
            rows.append(
                (r["object"], m["material"], r["scanner"], r["poses"], path, views, *(number(m[k]) for k in METRICS))
            )
    return header, rows


SET_METRICS = ("normal_deg", "tangent_deg", "log_alpha", "rho_d_rmse", "log_rho_s", "spurious_lobe")
# the stages that estimate the materials (after the traces): each path's run time is their sum
MATERIAL_STAGES = ("network_and_fit", "support", "refine", "teacher", "distil", "polish")


def material_seconds(run: dict) -> float:
    """A run's seconds estimating materials (``MATERIAL_STAGES``; a cached stage counts ~0)."""
    return float(sum(run.get("stages", {}).get(k, 0.0) for k in MATERIAL_STAGES))


def _path_rows(record: dict) -> tuple[tuple, list[tuple]]:
    """Run time against error per set x path (x scanner x poses x photo count): the materials'
    seconds and texels/s (observed texels over those seconds, summed over the runs), the mean relit
    SSIM and coverage over runs and each metric's mean over the materials."""
    header = (
        "set",
        "scanner",
        "poses",
        "views",
        "path",
        "runs",
        "s materials (mean)",
        "texels/s",
        "relit SSIM",
        "mesh ceiling",
        "coverage",
        *SET_METRICS,
    )
    groups: dict[tuple, list[dict]] = {}
    for r in record["runs"]:
        if "failed" in r:
            continue
        key = (r.get("set", "tune"), r["scanner"], r["poses"], r.get("views", record["settings"]["views"]))
        groups.setdefault((*key, r.get("path", "fast")), []).append(r)
    order = {p: i for i, p in enumerate(PATHS)}
    rows = []
    for key in sorted(groups, key=lambda k: (*k[:4], order.get(k[4], 9))):
        runs = groups[key]
        seconds = [material_seconds(r) for r in runs]
        texels = sum(r.get("texels_observed", 0) for r in runs)
        mats = [m for r in runs for m in r.get("materials", [])]
        rows.append(
            (
                *key,
                len(runs),
                number(sum(seconds) / len(seconds)),
                number(texels / sum(seconds) if sum(seconds) > 0 else None),
                number(finite_mean([r.get("relit_ssim") for r in runs])),
                number(finite_mean([r.get("mesh_ceiling") for r in runs])),
                number(finite_mean([m.get("coverage") for m in mats])),
                *(number(finite_mean([m.get(k) for m in mats])) for k in SET_METRICS),
            )
        )
    return header, rows


def _set_rows(record: dict) -> tuple[tuple, list[tuple]]:
    """Per scanner x poses x material kind (``Material.kind``): each metric's mean over the tuning
    set's materials of that kind / the validation set's, and the gap (validate - tune)."""
    header = (
        "scanner",
        "poses",
        "path",
        "kind",
        "materials tune / validate",
        *(f"{m} tune / validate (gap)" for m in SET_METRICS),
    )
    cells = _set_cells(record)
    rows = []
    for (scanner, poses, path, kind), by_set in sorted(cells.items()):
        tune, validate = by_set["tune"], by_set["validate"]
        cols = [tune_validate([m[k] for m in tune], [m[k] for m in validate]) for k in SET_METRICS]
        rows.append((scanner, poses, path, kind, f"{len(tune)} / {len(validate)}", *cols))
    return header, rows


def _at_settings_count(record: dict) -> list[dict]:
    """The runs at the settings' photo count (the others are the density table's)."""
    views = record["settings"]["views"]
    return [r for r in record["runs"] if r.get("views", views) == views]


def _set_cells(record: dict) -> dict[tuple, dict[str, list[dict]]]:
    """The materials at the settings' photo count per (scanner, poses, kind) and set."""
    cells: dict[tuple, dict[str, list[dict]]] = {}
    for r in _at_settings_count(record):
        for m in r.get("materials", []):
            key = (r["scanner"], r["poses"], r.get("path", "fast"), m.get("kind") or "?")
            cells.setdefault(key, {"tune": [], "validate": []})[r.get("set", "tune")].append(m)
    return cells


def sets_figure(record: dict, path: Path) -> None:
    """Tune against validate: each metric's mean per material kind, a bar per set (hatched:
    validate), one group per scanner x poses, one panel per metric; the dots are the materials."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cells = _set_cells(record)
    groups = sorted(cells)
    fig, axes = plt.subplots(len(SET_METRICS), 1, figsize=(max(8.0, 0.7 * len(groups)), 2.2 * len(SET_METRICS)))
    x = np.arange(len(groups))
    panels = list(np.atleast_1d(axes))
    for ax, metric in zip(panels, SET_METRICS):
        for j, which in enumerate(("tune", "validate")):
            at = x + (j - 0.5) * 0.4
            values = [[m[metric] for m in cells[g][which] if finite_mean([m[metric]]) is not None] for g in groups]
            means = [finite_mean(v) for v in values]
            ax.bar(
                at,
                [np.nan if v is None else v for v in means],
                0.4,
                color=f"C{j}",
                alpha=0.6,
                hatch="//" if which == "validate" else None,
                label=which,
            )
            for xi, v in zip(at, values):
                ax.plot([xi] * len(v), v, ".", color="k", markersize=3)
        ax.set_ylabel(metric.replace("_", " "), fontsize=8)
        ax.grid(axis="y", alpha=0.3)
        ax.set_xticks(
            x, [] if ax is not panels[-1] else [f"{g[3]}\n{g[0]}, {g[1]}, {g[2]}" for g in groups], fontsize=7
        )
    panels[0].legend(fontsize=7)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)
    plt.close(fig)


def _density(record: dict) -> dict[tuple, dict[int, dict[str, float | None]]]:
    """Each metric's mean per (scanner, poses, path, set, kind) and photo count."""
    groups: dict[tuple, dict[int, list[dict]]] = {}
    for r in record["runs"]:
        for m in r.get("materials", []):
            key = (r["scanner"], r["poses"], r.get("path", "fast"), r.get("set", "tune"), m.get("kind") or "?")
            groups.setdefault(key, {}).setdefault(r.get("views", record["settings"]["views"]), []).append(m)
    return {
        key: {n: {k: finite_mean([m[k] for m in ms]) for k in SET_METRICS} for n, ms in sorted(by_n.items())}
        for key, by_n in sorted(groups.items())
    }


def _density_rows(record: dict) -> tuple[tuple, list[tuple]]:
    """Accuracy against photo count: per scanner x poses x path x set x kind, each metric's mean at each count."""
    counts = sorted({r.get("views", record["settings"]["views"]) for r in record["runs"]})
    header = (
        "scanner",
        "poses",
        "path",
        "set",
        "kind",
        *(f"{m} at {' / '.join(map(str, counts))} photos" for m in SET_METRICS),
    )
    rows = []
    for (scanner, poses, path, which, kind), by_n in _density(record).items():
        cols = [" / ".join(number(by_n.get(n, {}).get(m)) for n in counts) for m in SET_METRICS]
        rows.append((scanner, poses, path, which, kind, *cols))
    return header, rows


def density_figure(record: dict, path: Path) -> None:
    """Each metric against photo count (log), a line per material kind, solid on tune, dashed on validate."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    data = _density(record)
    kinds = sorted({key[4] for key in data})
    fig, axes = plt.subplots(1, len(SET_METRICS), figsize=(3.2 * len(SET_METRICS), 3.2))
    for ax, metric in zip(axes, SET_METRICS):
        for (scanner, poses, run_path, which, kind), by_n in data.items():
            n = [c for c, v in by_n.items() if v[metric] is not None]
            if n:
                style = "-" if which == "tune" else "--"
                label = f"{kind} ({which}, {scanner}, {poses}, {run_path})"
                ax.plot(n, [by_n[c][metric] for c in n], style, marker="o", color=f"C{kinds.index(kind)}", label=label)
        ax.set_xscale("log")
        counts = sorted({c for by_n in data.values() for c in by_n})
        ax.set_xticks(counts, [str(c) for c in counts])
        ax.minorticks_off()
        ax.set_xlabel("photos")
        ax.set_title(metric.replace("_", " "), fontsize=9)
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=6)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)
    plt.close(fig)


def _budget_rows(record: dict) -> tuple[tuple, list[tuple]]:
    header = ("object", "scanner", "poses", "relit SSIM / ceiling", "material", *(f"+{g}" for g in BUDGET_GROUPS))
    rows = []
    for r in record["runs"]:
        b = r.get("relit_budget")
        for i, m in enumerate(b["materials"] if b else []):
            head = f"{b['relit_ssim']:.3f} / {b['ceiling']:.3f}" if i == 0 else ""
            gains = (f"{m[g]:+.3f}" for g in BUDGET_GROUPS)
            rows.append((r["object"], r["scanner"], r["poses"], head, m["material"], *gains))
    return header, rows


def markdown(record: dict) -> str:
    """The tables (runs, materials; with ``budget`` where the relit SSIM is lost) as Markdown."""

    def table(header: tuple, rows: list[tuple]) -> list[str]:
        return ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)] + [
            "| " + " | ".join(str(c) for c in row) + " |" for row in rows
        ]

    s = record["settings"]
    lines = [
        f"Gallery: {s['views']} views at scale {s['scale']}, {s['resolution']}^2 maps, Cycles {s['samples']} spp "
        f"(up to {s.get('max_samples', s['samples'])} where noisy, {s['bounces']} bounces); "
        f"total {record['seconds'] / 60:.1f} min.",
        "",
        *table(*_run_rows(record)),
        "",
        *table(*_material_rows(record)),
        "",
        "Tuning set vs validation set, per material kind (mean over the materials of that kind; the gap is "
        "validate - tune: a constant chosen on tune that does not transfer shows here):",
        "",
        *table(*_set_rows(record)),
        "",
    ]
    if len({r.get("path", "fast") for r in record["runs"]}) > 1:
        lines += [
            "Run time against error per path (seconds estimating materials: network + fit and what follows it; "
            "metrics: means over the materials):",
            "",
            *table(*_path_rows(record)),
            "",
        ]
    if len({r.get("views", s["views"]) for r in record["runs"]}) > 1:
        lines += [
            "Accuracy against photo count (mean over the materials of each kind; a method that uses its data "
            "gets better with more of it):",
            "",
            *table(*_density_rows(record)),
            "",
        ]
    budget = _budget_rows(record)
    if budget[1]:
        lines += [
            "Relit SSIM gained by one group of maps of one material taken from the truth (the rest the result's):",
            "",
            *table(*budget),
            "",
        ]
    return "\n".join(lines)


def _print(record: dict) -> None:
    header, rows = _run_rows(record)
    print_table(rows, header)
    print()
    header, rows = _material_rows(record)
    print_table(rows, header)
    print()
    header, rows = _set_rows(record)
    print_table(rows, header)
    if len({r.get("path", "fast") for r in record["runs"]}) > 1:
        print()
        print_table(*reversed(_path_rows(record)))
    if len({r.get("views", record["settings"]["views"]) for r in record["runs"]}) > 1:
        print()
        print_table(*reversed(_density_rows(record)))
    header, rows = _budget_rows(record)
    if rows:
        print()
        print_table(rows, header)


def figure(record: dict, path: Path) -> None:
    """Error per material (x: object / material), one bar per scanner x poses, one panel per metric."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    runs = _at_settings_count(record)
    cells = sorted({(r["object"], m["material"]) for r in runs for m in r.get("materials", [])})
    combos = sorted({(r["scanner"], r["poses"]) for r in runs})
    panels = ("coverage", "normal_deg", "tangent_deg", "log_alpha", "rho_d_rmse", "log_rho_s", "spurious_lobe")
    fig, axes = plt.subplots(len(panels), 1, figsize=(max(8.0, 0.55 * len(cells)), 2.3 * len(panels)), sharex=True)
    width = 0.8 / max(len(combos), 1)
    x = np.arange(len(cells))
    for ax, metric in zip(axes, panels):
        for j, combo in enumerate(combos):
            values = np.full(len(cells), np.nan)
            for r in runs:
                if (r["scanner"], r["poses"]) == combo:
                    for m in r.get("materials", []):
                        values[cells.index((r["object"], m["material"]))] = m[metric]
            ax.bar(x + (j - (len(combos) - 1) / 2) * width, values, width, label=f"{combo[0]}, {combo[1]} poses")
        ax.set_ylabel(metric.replace("_", " "))
        ax.grid(axis="y", alpha=0.3)
    axes[0].legend(fontsize=7, ncol=len(combos))
    axes[-1].set_xticks(x, [f"{o} / {m}" for o, m in cells], rotation=60, ha="right", fontsize=7)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100)
    plt.close(fig)


def set_objects(which: str, quick: bool = False) -> tuple[str, ...]:
    """The objects of ``which`` set (``tune``, ``validate`` or ``both``, tune first); ``quick``:
    each set's first two."""
    chosen = [SETS[s] for s in (("tune", "validate") if which == "both" else (which,))]
    return tuple(n for names in chosen for n in (names[:2] if quick else names))


def add_object_arguments(parser: argparse.ArgumentParser) -> None:
    """``--objects NAME ...`` or ``--set tune|validate|both`` (the gallery's benches share them)."""
    which = parser.add_mutually_exclusive_group()
    which.add_argument(
        "--objects",
        nargs="+",
        default=None,
        help=f"objects: {', '.join(GALLERY)} or generated ones, <family>-<seed> ({', '.join(FAMILIES)})",
    )
    which.add_argument(
        "--set",
        choices=("tune", "validate", "both"),
        default=None,
        help="the tuning set (the five + generated), the validation set (generated, never tuned on) or both, "
        "reported side by side (with --quick: each set's first two objects)",
    )


def chosen_objects(args: argparse.Namespace, quick: bool = False) -> tuple[str, ...] | None:
    """The objects ``add_object_arguments``' options name (None: the bench's default), checked."""
    if args.set:
        return set_objects(args.set, quick)
    if args.objects:
        unknown = [o for o in args.objects if o not in GALLERY and not is_generated(o)]
        if unknown:
            raise NtpInputError(
                None, f"--objects {unknown[0]}: not a gallery object ({', '.join(GALLERY)}) nor <family>-<seed>"
            )
        return tuple(args.objects)
    return None


def add_scanner_arguments(parser: argparse.ArgumentParser) -> None:
    """``--scanners engine|cycles ...`` (the gallery's benches share it)."""
    parser.add_argument(
        "--scanners",
        nargs="+",
        choices=list(SCANNERS),
        default=None,
        help="default: both; with --set the engine's alone (Cycles adds 4-6 min an object)",
    )


def chosen_scanners(args: argparse.Namespace) -> tuple[str, ...] | None:
    """The scanners ``--scanners`` names; with ``--set`` and none named, ``SET_SCANNERS``; else None
    (the bench's default)."""
    if args.scanners:
        return tuple(args.scanners)
    return SET_SCANNERS if args.set else None


def settings_for(quick: bool, **overrides) -> GallerySettings:
    """The default or quick settings with the given fields replaced (None leaves a field)."""
    base = QUICK if quick else DEFAULT
    return replace(base, **{k: v for k, v in overrides.items() if v is not None})


HELP = "accuracy per object x material: both scanners, true and SfM poses"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """``ntp bench gallery``'s options."""
    parser.add_argument("--out", type=Path, default=Path("ntp_gallery"), help="folder for assets, scans, results")
    parser.add_argument("--quick", action="store_true", help="2 objects, true poses, 16 views, 64^2 maps (<= 5 min)")
    add_object_arguments(parser)
    add_scanner_arguments(parser)
    parser.add_argument(
        "--poses", nargs="+", choices=list(POSES), default=None, help="default: both; with --set the true ones"
    )
    parser.add_argument("--views", type=int, default=None)
    parser.add_argument("--scale", type=float, default=None)
    parser.add_argument("--resolution", type=int, default=None)
    parser.add_argument("--samples", type=int, default=None, help="Cycles samples per pixel")
    parser.add_argument(
        "--max-samples", type=int, default=None, help="Cycles samples per pixel where it still sees noise"
    )
    parser.add_argument(
        "--refine",
        action="store_true",
        help="refine every texel against its photos after the network (results and tables *-refined)",
    )
    parser.add_argument(
        "--paths",
        nargs="+",
        choices=PATHS,
        default=None,
        help="reconstruct each scan by these paths (fast: network + fit; distil: the scan's own network; refine: "
        "every texel refined), each into its own results, and print run time against error side by side",
    )
    parser.add_argument(
        "--model",
        default=None,
        help="trace network: a shipped name or a model folder (results and tables *-model-NAME; default: compact)",
    )
    parser.add_argument(
        "--budget",
        action="store_true",
        help="where each run's relit SSIM is lost: the SSIM gained by one material's maps of a kind from the truth",
    )
    parser.add_argument(
        "--density",
        nargs="+",
        type=int,
        default=None,
        metavar="N",
        help="also scan each object with N photos (e.g. 120 360 1000): accuracy against photo count, "
        "a table and OUT/gallery-density.png",
    )
    add_mesh_argument(parser)
    parser.add_argument("--json", type=Path, default=None)
    add_progress_arguments(parser)


def add_mesh_argument(parser: argparse.ArgumentParser) -> None:
    """``--mesh scanner|true`` (the gallery's benches share it)."""
    parser.add_argument(
        "--mesh",
        choices=MESHES,
        default=None,
        help="the mesh ntp is given: a shape scanner's (default: coarser, smoothed, 0.3 mm noise) or the true one",
    )


def settings_from_args(args: argparse.Namespace) -> GallerySettings:
    """The settings ``ntp bench gallery``'s options ask for."""
    objects = chosen_objects(args, args.quick)
    return settings_for(
        args.quick,
        objects=objects,
        scanners=chosen_scanners(args),
        poses=tuple(args.poses) if args.poses else (SET_POSES if args.set else None),
        views=args.views,
        scale=args.scale,
        resolution=args.resolution,
        samples=args.samples,
        # without --samples the settings' own maximum stands
        max_samples=args.max_samples if args.samples is None else at_least_samples(args.max_samples, args.samples),
        refine=args.refine or None,
        paths=tuple(args.paths) if args.paths else None,
        model=args.model,
        mesh=args.mesh,
        density=tuple(args.density) if args.density else None,
        budget=args.budget or None,
    )


def command(args: argparse.Namespace) -> int:
    """``ntp bench gallery``: the benchmark with the command line's options; the exit code."""
    run(args.out, settings_from_args(args), json_path=args.json, progress=progress_from_args(args))
    return 0
