"""The ``ntp`` command line: one handler per subcommand (``set_defaults(func=...)``), each a thin
call into the engine. Bad input is one line on stderr and exit code 2."""

from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path

from .bench import cache as bench_cache
from .bench import fit as bench_fit
from .bench import gallery as bench_gallery
from .bench import network as bench_network
from .bench import physics as bench_physics
from .bench import refine as bench_refine
from .bench import registration as bench_registration
from .bench import scale as bench_scale
from .bench import scan as bench_scan
from .bench import sfm as bench_sfm
from .bench import stability as bench_stability
from .bench import virtual_scan as bench_virtual_scan
from .io.blender_process import blender_command
from .io.errors import NtpInputError, error_line
from .io.progress import Progress
from .io.threads import set_threads
from .learn import models
from .learn.network import NetworkConfig
from .learn.train import LR_SCHEDULES, TrainConfig, train
from .pipeline.collection import SUMMARY, BatchOptions, reconstruct_collection
from .pipeline.photo_selection import BLUR_MARGIN
from .pipeline.stages import DEFAULT_RESOLUTION, reconstruct, register_photos, write_registration
from .pipeline.task_pool import LOCAL, LocalPool, RayPool, TaskPool
from .register.sfm import MAPPERS
from .scanner.device_file import DEFAULT_DEVICE, list_devices, load_scanner, write_pattern
from .scanner.scan_folder import Scan, load_scan
from .sim import demo
from .sim.cycles_scan import CyclesConfig, cycles_scan
from .sim.gallery import GALLERY
from .sim.virtual_scan import ScanConfig, virtual_scan

FORCE_HELP = "go on with a registration the photos do not confirm (see OUT/registration.png)"
COLMAP_HELP = "a COLMAP model folder (cameras/images/points3D, .bin or .txt) instead of running SfM"
REFINE_HELP = "refine every texel against its photos after the network (analysis by synthesis; slower)"
RAY_HELP = (
    "run the fit stage's texel blocks as Ray tasks: on the cluster at ADDRESS (auto, HOST:6379, "
    "ray://HOST:10001), or without ADDRESS on a Ray instance started on this machine"
)
BATCH_RAY_HELP = (
    "one Ray task per scan: on the cluster at ADDRESS (OUT on a folder every node sees), or without "
    "ADDRESS on a Ray instance started on this machine"
)
INTERRUPTED = "interrupted — finished stages are kept, re-run to resume"


def main(argv: list[str] | None = None) -> int:
    """Run ``ntp`` with ``argv`` (default: the process's); returns the exit code: 2 and one line on
    stderr for bad input or a file that cannot be read or written (read-only, disk full), 130 for
    Ctrl-C."""
    args = _parser().parse_args(argv)
    try:
        return args.func(args)
    except (NtpInputError, OSError) as err:
        return _fail(error_line(err), 2)
    except KeyboardInterrupt:
        return _fail(INTERRUPTED, 130)


def _fail(line: str, code: int) -> int:
    print(f"ntp: {line}" if code == 130 else f"ntp: error: {line}", file=sys.stderr)
    return code


def _progress(args: argparse.Namespace) -> Progress:
    return Progress(bars=not args.quiet, json_path=args.progress)


def _scan(args: argparse.Namespace, poses: Path | None = None) -> Scan:
    return load_scan(args.scan, poses, device_file=args.device, colmap=args.colmap)


def _alignment_note(reg: dict) -> str:
    """The registration's confidence in a few words (a low residual alone proves nothing)."""
    if "photometric" not in reg:
        return ""
    ph, conf = reg["photometric"], reg["confidence"]
    margin = "no rival azimuth" if ph["margin"] is None else f"azimuth margin {ph['margin']:.2f}"
    forced = " (FORCED: the photos did not confirm it)" if conf.get("forced") else ""
    return f", registration confirmed by the photos: sharpness {ph['sharpness']:.2f}, {margin}{forced}"


# ------------------------------------------------------------------------------------ handlers
def _demo(args: argparse.Namespace) -> int:
    demo.run(
        args.out,
        views=args.views,
        scale=args.scale,
        resolution=args.resolution,
        seed=args.seed,
        known_poses=args.known_poses,
        model=args.model,
        progress=_progress(args),
        blend=not args.no_blend,
        refine=args.refine,
    )
    return 0


def _register(args: argparse.Namespace) -> int:
    set_threads(args.threads)
    poses, rep, _ = register_photos(
        _scan(args),
        args.out,
        args.blur_margin,
        progress=_progress(args),
        force_registration=args.force_registration,
        cache=args.cache,
    )
    write_registration(args.out, poses, rep)
    reg = rep["registration"]
    print(f"{len(poses)} photos registered ({reg['source']}){_alignment_note(reg)}; wrote {args.out / 'poses.json'}")
    return 0


def _reconstruct(args: argparse.Namespace) -> int:
    set_threads(args.threads)
    rep = reconstruct(
        _scan(args, args.poses),
        args.out,
        resolution=args.resolution,
        model=args.model,
        blur_margin=args.blur_margin,
        progress=_progress(args),
        force_registration=args.force_registration,
        refine=args.refine,
        cache=args.cache,
        ray=args.ray,
    )
    print(
        f"wrote {args.out}: {rep['texels']['coverage']:.1%} of {rep['texels']['total']} texels observed, "
        f"{rep['photos']['used']} of {rep['photos']['total']} photos used"
        f"{_alignment_note(rep['registration'])}, {rep['seconds']:.1f} s"
    )
    return 0


def _batch(args: argparse.Namespace) -> int:
    options = BatchOptions(resolution=args.resolution, model=args.model, refine=args.refine, threads=args.threads)
    set_threads(args.threads)  # checks the value; also the CPUs of a local Ray instance
    pool: TaskPool = RayPool(args.ray, args.threads) if args.ray else LocalPool()
    outcomes = reconstruct_collection(args.scans, args.out, options, pool, _progress(args))
    for o in outcomes:
        if o["ok"]:
            print(f"done    {o['scan']} -> {o['result']}: {o['coverage']:.1%} of texels observed, {o['seconds']:.1f} s")
        else:
            print(f"failed  {o['scan']}: {o['error']}")
    failed = [o for o in outcomes if not o["ok"]]
    if failed:
        return _fail(f"{len(failed)} of {len(outcomes)} scans failed (see {args.out / SUMMARY})", 2)
    return 0


def _device(args: argparse.Namespace) -> int:
    if args.list:
        for path in list_devices():
            print(f"{path.name:24s} {load_scanner(path).description}")
    else:
        print(load_scanner(args.path).summary())
    return 0


def _virtual_scan(args: argparse.Namespace) -> int:
    cfg = ScanConfig(
        views=args.views, scale=args.scale, seed=args.seed, exposure=args.exposure, blur_fraction=args.blur_fraction
    )
    if args.renderer == "cycles":
        cycles = CyclesConfig(
            samples=args.samples,
            bounces=args.bounces,
            max_samples=_max_samples(args.max_samples, args.samples),
            noise_threshold=args.noise_threshold,
        )
        info = cycles_scan(args.out, args.asset, args.mesh, args.maps, args.device, cfg, cycles, _progress(args))
    else:
        info = virtual_scan(args.out, args.asset, args.mesh, args.maps, args.device, cfg, progress=_progress(args))
    print(f"wrote {args.out}: {args.views} photos ({args.renderer}), {info['seconds_per_photo']:.2f} s per photo")
    return 0


def _train(args: argparse.Namespace) -> int:
    ncfg = NetworkConfig(preset=args.preset, frozen_pattern=None if args.pattern == "learned" else args.pattern)
    tcfg = TrainConfig(
        steps=args.steps,
        batch=args.batch,
        lr=args.lr,
        pattern_lr=args.pattern_lr,
        seed=args.seed,
        views_max=args.views,
        validate_every=args.validate_every,
        sweep_fraction=args.sweep_fraction,
        pattern_init=args.pattern_init,
        lr_schedule=args.lr_schedule,
    )
    result = train(
        args.out, ncfg, tcfg, args.device, resume=args.resume, init_from=args.init_from, progress=_progress(args)
    )
    print(
        f"step {result['step']}: validation loss {result['val_loss']:.4f} "
        f"(diffuse {result['val_diffuse']:.4f}, specular {result['val_specular']:.3f})"
    )
    if args.export:
        models.export(args.out / "checkpoint.pt", args.export, result)
        basis = models.write_specular_basis(args.export)
        print(f"exported {args.export} (specular head compressed to {basis['rank']} output directions)")
        if args.export_pattern_to_device:
            print(f"wrote {write_pattern(args.device or DEFAULT_DEVICE, models.pattern_of(args.export))}")
    return 0


def _bench_stability(args: argparse.Namespace) -> int:
    r = bench_stability.run(samples=args.samples, seed=args.seed, json_path=args.json)
    return 1 if r["nonfinite"] or r["total"]["negative_values"] else 0


def _bench_virtual_scan(args: argparse.Namespace) -> int:
    bench_virtual_scan.run(photos=args.photos, json_path=args.json)
    return 0


def _max_samples(max_samples: int | None, samples: int) -> int:
    """``--max-samples``, or by default ``CyclesConfig``'s but at least ``--samples``."""
    return max(samples, CyclesConfig.max_samples) if max_samples is None else max_samples


def _bench_gallery(args: argparse.Namespace) -> int:
    settings = bench_gallery.settings_for(
        args.quick,
        objects=tuple(args.objects) if args.objects else None,
        scanners=tuple(args.scanners) if args.scanners else None,
        poses=tuple(args.poses) if args.poses else None,
        views=args.views,
        scale=args.scale,
        resolution=args.resolution,
        samples=args.samples,
        # without --samples the settings' own maximum stands
        max_samples=args.max_samples if args.samples is None else _max_samples(args.max_samples, args.samples),
        refine=args.refine or None,
        model=args.model,
        budget=args.budget or None,
    )
    bench_gallery.run(args.out, settings, json_path=args.json, progress=_progress(args))
    return 0


def _bench_refine(args: argparse.Namespace) -> int:
    bench = bench_refine.bench_for(
        objects=tuple(args.objects) if args.objects else None,
        scanners=tuple(args.scanners) if args.scanners else None,
        per_material=args.per_material,
        baseline_texels=args.baseline_texels,
    )
    bench_refine.run(args.out, bench, json_path=args.json, progress=_progress(args))
    return 0


def _bench_registration(args: argparse.Namespace) -> int:
    settings = bench_gallery.settings_for(
        args.quick,
        objects=tuple(args.objects) if args.objects else None,
        scanners=tuple(args.scanners) if args.scanners else None,
        poses=None,
        views=args.views,
        scale=args.scale,
        resolution=None,
        samples=args.samples,
    )
    bench_registration.run(args.out, settings, tuple(args.seeds), json_path=args.json, progress=_progress(args))
    return 0


def _bench_sfm(args: argparse.Namespace) -> int:
    bench_sfm.run(
        args.out, tuple(args.photos), tuple(args.mappers), args.scale, json_path=args.json, progress=_progress(args)
    )
    return 0


def _bench_cache(args: argparse.Namespace) -> int:
    bench_cache.run(photos=args.photos, scale=args.scale, json_path=args.json)
    return 0


def _bench_fit(args: argparse.Namespace) -> int:
    bench_fit.run(quick=args.quick, texels=args.texels, baseline_texels=args.baseline_texels, json_path=args.json)
    return 0


def _bench_network(args: argparse.Namespace) -> int:
    bench_network.run(quick=args.quick, steps=args.steps, json_path=args.json)
    return 0


def _bench_scan(args: argparse.Namespace) -> int:
    bench_scan.run(args.sizes, json_path=args.json, plot=args.plot, known_poses=args.known_poses)
    return 0


def _bench_scale(args: argparse.Namespace) -> int:
    bench_scale.run(
        args.out,
        tuple(args.photos),
        tuple(args.resolutions),
        camera_scale=args.scale,
        threads=args.threads,
        json_path=args.json,
        plot=args.plot if args.plot is not None else args.out / "bench_scale.png",
    )
    return 0


def _bench_blender(args: argparse.Namespace) -> int:
    # in its own process: the engine never imports bpy
    cmd = blender_command("bench", "--views", str(args.views), "--samples", str(args.samples))
    return subprocess.call(cmd + (["--json", str(args.json)] if args.json else []))


def _bench_physics(args: argparse.Namespace) -> int:
    bench_physics.run(json_path=args.json)
    return 0


# ------------------------------------------------------------------------------------ the parser
def _sizes(text: str) -> list[tuple[int, int]]:
    try:
        return [(int(a), int(b)) for a, b in (item.lower().split("x") for item in text.split(","))]
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r}: expected PHOTOSxRES,...") from None


def _quiet_and_progress(p: argparse.ArgumentParser) -> None:
    p.add_argument("--quiet", action="store_true", help="no progress bars")
    p.add_argument(
        "--progress",
        type=Path,
        default=None,
        metavar="FILE",
        help="append progress as JSON lines to FILE (stage, done, total, unit, elapsed_s, eta_s)",
    )


def _run_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--threads", type=int, default=0, help="CPU threads (default 0: every core)")
    p.add_argument(
        "--cache",
        type=Path,
        default=None,
        metavar="DIR",
        help="stage cache folder (default OUT/cache), e.g. on a fast local disk; one per result",
    )


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="ntp", description="Neural trace photography: hand-held reflectance scans to relightable Blender assets."
    )
    sub = p.add_subparsers(dest="command", metavar="COMMAND", required=True)

    d = sub.add_parser("demo", help="virtual-scan the bundled demo, reconstruct it, print errors vs truth")
    d.add_argument("--out", type=Path, default=Path("ntp_demo_out"), help="output folder (scan/, result/)")
    d.add_argument("--views", type=int, default=demo.DEMO_VIEWS, help="photos in the virtual scan")
    d.add_argument("--scale", type=float, default=demo.DEMO_SCALE, help="camera resolution scale (1.0 = 2448x2048)")
    d.add_argument("--resolution", type=int, default=demo.DEMO_RESOLUTION, help="texture maps are RESOLUTION^2")
    d.add_argument("--seed", type=int, default=0)
    d.add_argument("--model", default=None, help="shipped model name or a model folder (default: compact)")
    d.add_argument("--known-poses", action="store_true", help="use the scan's true poses instead of SfM")
    d.add_argument("--no-blend", action="store_true", help="skip the Blender export (.blend, .glb, preview)")
    d.add_argument(
        "--refine",
        action=argparse.BooleanOptionalAction,
        default=True,
        help="refine every texel against its photos (as reconstruct --refine; on by default): the maps that "
        "meet the demo's goals, ~40% of its run time",
    )
    _quiet_and_progress(d)
    d.set_defaults(func=_demo)

    rc = sub.add_parser("reconstruct", help="a scan folder to texture maps (resumes from OUT/cache)")
    rc.add_argument("scan", type=Path, help="scan folder (scan.toml, mesh, photos/)")
    rc.add_argument("--out", type=Path, required=True, help="result folder")
    rc.add_argument("--resolution", type=int, default=DEFAULT_RESOLUTION, help="texture maps are RESOLUTION^2")
    rc.add_argument("--model", default=None, help="shipped model name or a model folder (default: compact)")
    rc.add_argument("--poses", type=Path, default=None, help="poses JSON (camera-from-world per photo); skips SfM")
    rc.add_argument("--device", type=Path, default=None, help="device TOML instead of the one scan.toml names")
    rc.add_argument("--colmap", type=Path, default=None, help=COLMAP_HELP)
    rc.add_argument(
        "--blur-margin",
        type=float,
        default=BLUR_MARGIN,
        help="drop photos whose blur score exceeds the scan's median by this much",
    )
    rc.add_argument("--force-registration", action="store_true", help=FORCE_HELP)
    rc.add_argument("--refine", action="store_true", help=REFINE_HELP)
    rc.add_argument("--ray", nargs="?", const=LOCAL, default=None, metavar="ADDRESS", help=RAY_HELP)
    _run_options(rc)
    _quiet_and_progress(rc)
    rc.set_defaults(func=_reconstruct)

    ba = sub.add_parser("batch", help="reconstruct a collection of scans into OUT/<scan name> (resumable)")
    ba.add_argument("scans", type=Path, nargs="+", metavar="SCAN", help="scan folders")
    ba.add_argument("--out", type=Path, required=True, help="collection folder (one result per scan, batch.json)")
    ba.add_argument("--resolution", type=int, default=DEFAULT_RESOLUTION, help="texture maps are RESOLUTION^2")
    ba.add_argument("--model", default=None, help="shipped model name or a model folder (default: compact)")
    ba.add_argument("--refine", action="store_true", help=REFINE_HELP)
    ba.add_argument(
        "--threads", type=int, default=0, help="CPU threads per scan (default 0: every core; 1 per Ray task)"
    )
    ba.add_argument("--ray", nargs="?", const=LOCAL, default=None, metavar="ADDRESS", help=BATCH_RAY_HELP)
    _quiet_and_progress(ba)
    ba.set_defaults(func=_batch)

    rg = sub.add_parser("register", help="photo selection + camera poses (SfM aligned to the mesh) -> OUT/poses.json")
    rg.add_argument("scan", type=Path, help="scan folder (scan.toml, mesh, photos/)")
    rg.add_argument("--out", type=Path, required=True, help="result folder (its cache is shared with reconstruct)")
    rg.add_argument("--device", type=Path, default=None, help="device TOML instead of the one scan.toml names")
    rg.add_argument("--colmap", type=Path, default=None, help=COLMAP_HELP)
    rg.add_argument("--blur-margin", type=float, default=BLUR_MARGIN)
    rg.add_argument("--force-registration", action="store_true", help=FORCE_HELP)
    _run_options(rg)
    _quiet_and_progress(rg)
    rg.set_defaults(func=_register)

    dev = sub.add_parser("device", help="print a device calibration file, or list the shipped ones")
    dev.add_argument("path", type=Path, nargs="?", default=None, help="device TOML (default: the default device)")
    dev.add_argument("--list", action="store_true", help="list the shipped devices")
    dev.set_defaults(func=_device)

    vs = sub.add_parser("virtual-scan", help="simulate a hand-held capture of a mesh with known maps")
    vs.add_argument("--out", type=Path, required=True, help="scan folder to write")
    vs.add_argument("--asset", default=None, help="asset folder (mesh.obj + ground_truth/); default: the demo")
    vs.add_argument("--mesh", type=Path, default=None, help="a mesh with UVs (OBJ/PLY, metres) ...")
    vs.add_argument("--maps", type=Path, default=None, help="... and a folder with its five maps")
    vs.add_argument("--device", type=Path, default=None, help="device TOML (default: the paper's LED array)")
    vs.add_argument("--views", type=int, default=120)
    vs.add_argument("--scale", type=float, default=0.25, help="camera resolution scale (1.0 = 2448x2048)")
    vs.add_argument("--seed", type=int, default=0)
    vs.add_argument("--exposure", type=float, default=1.5, help="x the device's auto-exposure")
    vs.add_argument("--blur-fraction", type=float, default=0.0, help="fraction of photos with motion blur")
    vs.add_argument(
        "--renderer", choices=["engine", "cycles"], default="engine", help="cycles: Blender Cycles through bpy"
    )
    vs.add_argument("--samples", type=int, default=CyclesConfig.samples, help="Cycles samples per pixel")
    vs.add_argument("--bounces", type=int, default=CyclesConfig.bounces, help="Cycles light bounces")
    vs.add_argument(
        "--max-samples",
        type=int,
        default=None,
        help=f"Cycles samples per pixel where it sees noise (default {CyclesConfig.max_samples}, at least --samples)",
    )
    vs.add_argument(
        "--noise-threshold",
        type=float,
        default=CyclesConfig.noise_threshold,
        help="Cycles' adaptive-sampling threshold: above it a pixel keeps sampling up to --max-samples",
    )
    _quiet_and_progress(vs)
    vs.set_defaults(func=_virtual_scan)

    tr = sub.add_parser("train", help="train the trace network and its lighting pattern (resumable)")
    tr.add_argument("--preset", default="compact", choices=["compact", "paper", "small"])
    tr.add_argument("--out", type=Path, required=True, help="run folder (checkpoint.pt, log.csv)")
    tr.add_argument("--steps", type=int, default=20000, help="total steps (a resumed run continues to this)")
    tr.add_argument("--resume", action="store_true", help="continue the checkpoint in --out")
    tr.add_argument("--batch", type=int, default=64)
    tr.add_argument("--lr", type=float, default=3e-4)
    tr.add_argument(
        "--lr-schedule",
        choices=list(LR_SCHEDULES),
        default="constant",
        help="cosine: every learning rate falls to 0 at --steps (from the step the run starts at)",
    )
    tr.add_argument(
        "--pattern-lr",
        type=float,
        default=None,
        help="learning rate of the lighting layer (default: --lr; the pattern moves slowly at 3e-4)",
    )
    tr.add_argument("--seed", type=int, default=0, help="data seed")
    tr.add_argument("--views", type=int, default=64, help="maximum trace length in training")
    tr.add_argument(
        "--init-from",
        type=Path,
        default=None,
        help="start a new run from another run's (or a model folder's, e.g. assets/models/compact) weights and "
        "step (the pattern setting may differ)",
    )
    tr.add_argument(
        "--sweep-fraction",
        type=float,
        default=0.5,
        help="fraction of training traces seen from a correlated hand-held sweep (else i.i.d. views)",
    )
    tr.add_argument(
        "--pattern", default="learned", help="learned, or a frozen pattern: full_on, point, binary, or a CSV/NPY file"
    )
    tr.add_argument(
        "--pattern-init",
        default=None,
        help="a learned pattern's starting value: full_on, point, binary or a CSV/NPY file, clipped to "
        "[0.1, 0.9] (default: 0.5 everywhere, or the --init-from run's pattern)",
    )
    tr.add_argument("--device", type=Path, default=None, help="device TOML (default: the paper's LED array)")
    tr.add_argument("--validate-every", type=int, default=500)
    tr.add_argument(
        "--export",
        type=Path,
        default=None,
        help="after training, write a model folder here (e.g. assets/models/compact)",
    )
    tr.add_argument(
        "--export-pattern-to-device",
        action="store_true",
        help="also write the learned pattern, quantised to 8 bits, into the device file",
    )
    _quiet_and_progress(tr)
    tr.set_defaults(func=_train)

    b = sub.add_parser("bench", help="benchmarks: run time and error in one run")
    bsub = b.add_subparsers(dest="bench", metavar="NAME", required=True)
    st = bsub.add_parser("stability", help="GGX float32 values/gradients vs float64 over >= 1e7 samples")
    st.add_argument("--samples", type=int, default=10_000_000)
    st.add_argument("--seed", type=int, default=0)
    st.add_argument("--json", type=Path, default=None)
    st.set_defaults(func=_bench_stability)
    bv = bsub.add_parser("virtual-scan", help="seconds per photo (scale 0.25, 1.0) and shadow-cluster error")
    bv.add_argument("--photos", type=int, default=3)
    bv.add_argument("--json", type=Path, default=None)
    bv.set_defaults(func=_bench_virtual_scan)
    bg = bsub.add_parser("gallery", help="accuracy per object x material: both scanners, true and SfM poses")
    bg.add_argument("--out", type=Path, default=Path("ntp_gallery"), help="folder for assets, scans, results")
    bg.add_argument("--quick", action="store_true", help="2 objects, true poses, 16 views, 64^2 maps (<= 5 min)")
    bg.add_argument("--objects", nargs="+", choices=list(GALLERY), default=None)
    bg.add_argument("--scanners", nargs="+", choices=list(bench_gallery.SCANNERS), default=None)
    bg.add_argument("--poses", nargs="+", choices=list(bench_gallery.POSES), default=None)
    bg.add_argument("--views", type=int, default=None)
    bg.add_argument("--scale", type=float, default=None)
    bg.add_argument("--resolution", type=int, default=None)
    bg.add_argument("--samples", type=int, default=None, help="Cycles samples per pixel")
    bg.add_argument("--max-samples", type=int, default=None, help="Cycles samples per pixel where it still sees noise")
    bg.add_argument("--refine", action="store_true", help=REFINE_HELP + " (results and tables *-refined)")
    bg.add_argument(
        "--model",
        default=None,
        help="trace network: a shipped name or a model folder (results and tables *-model-NAME; default: compact)",
    )
    bg.add_argument(
        "--budget",
        action="store_true",
        help="where each run's relit SSIM is lost: the SSIM gained by one material's maps of a kind from the truth",
    )
    bg.add_argument("--json", type=Path, default=None)
    _quiet_and_progress(bg)
    bg.set_defaults(func=_bench_gallery)
    bf = bsub.add_parser("refine", help="refinement error against time per material, and a scipy baseline")
    bf.add_argument("--out", type=Path, default=Path("ntp_gallery"), help="the gallery's folder (scans shared)")
    bf.add_argument("--objects", nargs="+", choices=list(GALLERY), default=None)
    bf.add_argument("--scanners", nargs="+", choices=list(bench_gallery.SCANNERS), default=None)
    bf.add_argument("--per-material", type=int, default=None, help="sampled texels per material and scan")
    bf.add_argument("--baseline-texels", type=int, default=None, help="texels per scan for the scipy baseline")
    bf.add_argument("--json", type=Path, default=None)
    _quiet_and_progress(bf)
    bf.set_defaults(func=_bench_refine)
    br = bsub.add_parser("registration", help="SfM + alignment alone on the gallery: pose error per object x seed")
    br.add_argument("--out", type=Path, default=Path("ntp_gallery"), help="the gallery's folder (scans shared)")
    br.add_argument("--quick", action="store_true", help="the quick gallery's objects and sizes")
    br.add_argument("--objects", nargs="+", choices=list(GALLERY), default=None)
    br.add_argument("--scanners", nargs="+", choices=list(bench_gallery.SCANNERS), default=None)
    br.add_argument("--seeds", nargs="+", type=int, default=list(bench_registration.SEEDS))
    br.add_argument("--views", type=int, default=None)
    br.add_argument("--scale", type=float, default=None)
    br.add_argument("--samples", type=int, default=None, help="Cycles samples per pixel")
    br.add_argument("--json", type=Path, default=None)
    _quiet_and_progress(br)
    br.set_defaults(func=_bench_registration)
    bs = bsub.add_parser("sfm", help="SfM mappers (incremental, global, hierarchical) at 60 / 300 / 1000 photos")
    bs.add_argument("--out", type=Path, default=Path("ntp_sfm_bench"), help="folder for the scans and the table")
    bs.add_argument("--photos", nargs="+", type=int, default=list(bench_sfm.PHOTOS))
    bs.add_argument("--mappers", nargs="+", choices=list(MAPPERS), default=list(MAPPERS))
    bs.add_argument("--scale", type=float, default=bench_sfm.SCALE, help="photo size (1.0 = the device's)")
    bs.add_argument("--json", type=Path, default=None)
    _quiet_and_progress(bs)
    bs.set_defaults(func=_bench_sfm)
    bc = bsub.add_parser("cache", help="content keys: hashing photos (vs one thread, vs stat) and cache checksums")
    bc.add_argument("--photos", type=int, default=40, help="photos hashed (projected to 1000)")
    bc.add_argument("--scale", type=float, default=1.0, help="photo size (1.0 = 2448x2048)")
    bc.add_argument("--json", type=Path, default=None)
    bc.set_defaults(func=_bench_cache)
    bf = bsub.add_parser("fit", help="batched GGX fitter vs per-texel scipy L-BFGS-B (speed and error)")
    bf.add_argument("--quick", action="store_true", help="2048 texels (baseline on 32) instead of 16384 (192)")
    bf.add_argument("--texels", type=int, default=None)
    bf.add_argument("--baseline-texels", type=int, default=None)
    bf.add_argument("--json", type=Path, default=None)
    bf.set_defaults(func=_bench_fit)
    bn = bsub.add_parser("network", help="val. loss by pattern and by test views; inference traces/s")
    bn.add_argument("--quick", action="store_true", help="use the shipped comparison networks (no training)")
    bn.add_argument("--steps", type=int, default=3000, help="training steps per comparison network")
    bn.add_argument("--json", type=Path, default=None)
    bn.set_defaults(func=_bench_network)
    bs = bsub.add_parser("scan", help="whole pipeline on virtual scans of 2-3 sizes: stage times vs errors")
    bs.add_argument("--sizes", type=_sizes, default=None, help="PHOTOSxRES,... (default 24x128,48x256,96x256)")
    bs.add_argument("--known-poses", action="store_true", help="skip SfM (true poses)")
    bs.add_argument("--plot", type=Path, default=Path("bench_scan.png"), help="PNG of run time against error")
    bs.add_argument("--json", type=Path, default=None)
    bs.set_defaults(func=_bench_scan)
    sc = bsub.add_parser("scale", help="time and peak memory per stage: photos x map resolution (true poses)")
    sc.add_argument("--out", type=Path, default=Path("ntp_bench_scale"), help="folder for the scans and results")
    sc.add_argument("--photos", type=int, nargs="+", default=list(bench_scale.PHOTOS))
    sc.add_argument("--resolutions", type=int, nargs="+", default=list(bench_scale.RESOLUTIONS))
    sc.add_argument("--scale", type=float, default=bench_scale.CAMERA_SCALE, help="virtual camera resolution scale")
    sc.add_argument("--threads", type=int, default=0, help="CPU threads of each reconstruct (0: every core)")
    sc.add_argument("--plot", type=Path, default=None, help="PNG: seconds and memory (default OUT/bench_scale.png)")
    sc.add_argument("--json", type=Path, default=None)
    sc.set_defaults(func=_bench_scale)
    bb = bsub.add_parser("blender", help="Cycles (both materials) vs the engine's render; preview seconds")
    bb.add_argument("--views", type=int, default=3)
    bb.add_argument("--samples", type=int, default=64)
    bb.add_argument("--json", type=Path, default=None)
    bb.set_defaults(func=_bench_blender)
    ph = bsub.add_parser("physics", help="BRDF evaluations/s, lumitexels/s, measurements/s (f32 vs f64)")
    ph.add_argument("--json", type=Path, default=None)
    ph.set_defaults(func=_bench_physics)
    return p


if __name__ == "__main__":
    sys.exit(main())
