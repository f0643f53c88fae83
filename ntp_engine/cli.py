"""The ``ntp`` command line: one handler per subcommand (``set_defaults(func=...)``), each a thin
call into the engine. Bad input is one line on stderr and exit code 2."""

from __future__ import annotations

import argparse
import functools
import signal
import sys
import webbrowser
from pathlib import Path

from .bench import (
    blender,
    browser,
    cache,
    fit,
    gallery,
    network,
    physics,
    refine,
    registration,
    scale,
    scan,
    sfm,
    stability,
)
from .bench import virtual_scan as virtual_scan_bench
from .io.arguments import OneLineParser, bound_numbers, float_in, int_in
from .io.blender_process import GLB_HOWTO
from .io.errors import NtpInputError, error_line
from .io.progress import add_progress_arguments, progress_from_args
from .io.signals import Terminated, terminate_as_interrupt
from .io.threads import MAX_THREADS, set_threads
from .learn import models
from .learn.network import NetworkConfig
from .learn.train import LR_SCHEDULES, TrainConfig, train
from .pipeline.collection import SUMMARY, BatchOptions, reconstruct_collection
from .pipeline.result_page import write_page
from .pipeline.settings import TUNING as PIPELINE_TUNING
from .pipeline.stages import (
    DEFAULT_RESOLUTION,
    MAX_RESOLUTION,
    MIN_RESOLUTION,
    reconstruct,
    register_photos,
    write_registration,
)
from .pipeline.task_pool import LOCAL, LocalPool, RayPool, TaskPool
from .scanner.board import PAPERS, board_for_paper, write_board
from .scanner.device_file import DEFAULT_DEVICE, list_devices, load_scanner, write_pattern
from .scanner.scan_folder import Scan, load_scan
from .sim import demo
from .sim.cycles_scan import CyclesConfig, at_least_samples, cycles_scan
from .sim.virtual_scan import ScanConfig, virtual_scan

FORCE_HELP = "go on with a registration the photos do not confirm (see OUT/registration.png)"
COLMAP_HELP = "a COLMAP model folder (cameras/images/points3D, .bin or .txt) instead of running SfM"
REFINE_HELP = "refine every texel against its photos after the network (analysis by synthesis; slower)"
DISTIL_HELP = (
    "refine a sample of the texels against their photos, fine-tune the network on them, and run it over "
    "every texel again: the scan's own network (docs/distillation.md)"
)
RAY_HELP = (
    "run the fit stage's texel blocks as Ray tasks: on the cluster at ADDRESS (auto, HOST:6379, "
    "ray://HOST:10001), or without ADDRESS on a Ray instance started on this machine"
)
BATCH_RAY_HELP = (
    "one Ray task per scan: on the cluster at ADDRESS (OUT on a folder every node sees), or without "
    "ADDRESS on a Ray instance started on this machine"
)
Subcommands = argparse._SubParsersAction  # what ``add_subparsers`` returns
# ``ntp bench NAME``: each benchmark's module holds its options (``add_arguments``) and handler (``command``)
BENCHES = {
    "stability": stability,
    "virtual-scan": virtual_scan_bench,
    "gallery": gallery,
    "refine": refine,
    "registration": registration,
    "sfm": sfm,
    "cache": cache,
    "fit": fit,
    "network": network,
    "scan": scan,
    "scale": scale,
    "blender": blender,
    "browser": browser,
    "physics": physics,
}
# the ranges of the command line's numbers (``io.arguments``), each with where its bounds come from
RESOLUTION = int_in(MIN_RESOLUTION, MAX_RESOLUTION, "the largest texture GPUs and Blender take")
THREADS = int_in(0, MAX_THREADS, "0: every core; Linux's largest CPU count")
VIEWS = int_in(1, 100_000, "100x the paper's ~1,000 photos")
SCALE = float_in(0.01, 2.0, "of the 2448x2048 camera")
SEED = int_in(0, 2**32 - 1, "numpy's seeds")
EXPOSURE = float_in(1e-3, 1e3, "times the device's auto-exposure")
FRACTION = float_in(0.0, 1.0)
BLUR_MARGIN = float_in(0.0, 1.0, "blur scores lie in [0, 1]")
SAMPLES = int_in(1, 1 << 20)
BOUNCES = int_in(0, 1024, "Cycles' own limit")
INTERRUPTED = "interrupted — finished stages are kept, re-run to resume"
TERMINATED = "terminated — finished stages are kept, re-run to resume"


def main(argv: list[str] | None = None) -> int:
    """Run ``ntp`` with ``argv`` (default: the process's); returns the exit code: 2 and one line on
    stderr for bad input or a file that cannot be read or written (read-only, disk full), 130 for
    Ctrl-C, 143 for SIGTERM (both clean up as they go)."""
    try:
        args = _parser().parse_args(argv)
    except SystemExit as done:  # --help, or a bad option (one line on stderr: ``OneLineParser``)
        return int(done.code or 0)
    try:
        with terminate_as_interrupt():
            return args.func(args)
    except (NtpInputError, OSError) as err:
        return _fail(error_line(err), 2)
    except Terminated:
        return _fail(TERMINATED, 128 + signal.SIGTERM)
    except KeyboardInterrupt:
        return _fail(INTERRUPTED, 130)


def _fail(line: str, code: int) -> int:
    print(f"ntp: {line}" if code >= 128 else f"ntp: error: {line}", file=sys.stderr)  # 128 + a signal
    return code


def _scan(args: argparse.Namespace, poses: Path | None = None) -> Scan:
    return load_scan(args.scan, poses, device_file=args.device, colmap=args.colmap)


def _alignment_note(reg: dict) -> str:
    """The registration's confidence in a few words (a low residual alone proves nothing)."""
    if "photometric" not in reg:
        return ""
    ph, conf = reg["photometric"], reg["confidence"]
    margin = "no rival azimuth" if ph["margin"] is None else f"azimuth margin {ph['margin']:.2f}"
    forced = " (FORCED: the photos did not confirm it)" if conf.get("forced") else ""
    symmetry = f"; the mesh is {conf['symmetry']}" if conf.get("symmetry") else ""
    points = ph.get("triangulated_points")
    if points is not None:  # placed on the marker board by the object's triangulated points
        return (
            f", placed by {points['inliers']} of {points['object_points']} points triangulated on the object "
            f"({points['residual_mm']:.2f} mm RMS from the mesh), {margin}{forced}{symmetry}"
        )
    outline = ph.get("outline")
    if outline is not None:  # placed on the marker board by the object's outline against the print
        return (
            f", placed by the object's outline against the board over {outline['photos']} photos "
            f"(spread {outline['spread_mm']:.2f} mm), {margin}{forced}{symmetry}"
        )
    sharpness = "unmeasured" if ph["sharpness"] is None else f"{ph['sharpness']:.2f}"
    return f", registration confirmed by the photos: sharpness {sharpness}, {margin}{forced}{symmetry}"


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
        progress=progress_from_args(args),
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
        progress=progress_from_args(args),
        force_registration=args.force_registration,
        cache=args.cache,
    )
    write_registration(args.out, poses, rep)
    reg = rep.registration or {}
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
        progress=progress_from_args(args),
        force_registration=args.force_registration,
        refine=args.refine,
        cache=args.cache,
        ray=args.ray,
        distil=args.distil,
    )
    assert rep.texels is not None and rep.photos is not None and rep.seconds is not None  # a finished run
    print(
        f"wrote {args.out}: {rep.texels.coverage:.1%} of {rep.texels.total} texels observed, "
        f"{rep.photos.used} of {rep.photos.total} photos used"
        f"{_alignment_note(rep.registration or {})}, {rep.seconds:.1f} s"
    )
    return 0


def _batch(args: argparse.Namespace) -> int:
    options = BatchOptions(
        resolution=args.resolution, model=args.model, refine=args.refine, distil=args.distil, threads=args.threads
    )
    set_threads(args.threads)  # checks the value; also the CPUs of a local Ray instance
    pool: TaskPool = RayPool(args.ray, args.threads) if args.ray else LocalPool()
    outcomes = reconstruct_collection(args.scans, args.out, options, pool, progress_from_args(args))
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


def _view(args: argparse.Namespace) -> int:
    page = write_page(args.result, args.glb)
    print(page)
    if not args.no_open:
        webbrowser.open(page.resolve().as_uri())
    return 0


def _board(args: argparse.Namespace) -> int:
    board = board_for_paper(args.size)
    layout = write_board(args.out, board)
    print(
        f"wrote {args.out} and {layout}: {board.squares[0]} x {board.squares[1]} squares of {board.square_mm:g} mm. "
        f"Print at 100% and check the 100 mm bar; put {layout.name} in the scan folder and name it in scan.toml "
        f'(board = "{layout.name}"); stand the object on the board.'
    )
    return 0


def _virtual_scan(args: argparse.Namespace) -> int:
    cfg = ScanConfig(
        views=args.views,
        scale=args.scale,
        seed=args.seed,
        exposure=args.exposure,
        blur_fraction=args.blur_fraction,
        board=args.board,
    )
    scan = virtual_scan
    if args.renderer == "cycles":
        cycles = CyclesConfig(
            samples=args.samples,
            bounces=args.bounces,
            max_samples=at_least_samples(args.max_samples, args.samples),
            noise_threshold=args.noise_threshold,
        )
        scan = functools.partial(cycles_scan, cycles=cycles)
    info = scan(
        args.out,
        args.asset,
        args.mesh,
        args.maps,
        args.device,
        cfg,
        progress=progress_from_args(args),
        given_mesh=args.given_mesh,
    )
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
        args.out,
        ncfg,
        tcfg,
        args.device,
        resume=args.resume,
        init_from=args.init_from,
        progress=progress_from_args(args),
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


# ------------------------------------------------------------------------------------ the parser
def _run_options(p: argparse.ArgumentParser) -> None:
    p.add_argument("--threads", type=THREADS, default=0, help="CPU threads (default 0: every core)")
    p.add_argument(
        "--cache",
        type=Path,
        default=None,
        metavar="DIR",
        help="stage cache folder (default OUT/cache), e.g. on a fast local disk; one per result",
    )


def _parser() -> argparse.ArgumentParser:
    p = OneLineParser(
        prog="ntp", description="Neural trace photography: hand-held reflectance scans to relightable Blender assets."
    )
    sub = p.add_subparsers(dest="command", metavar="COMMAND", required=True)
    _add_demo(sub)
    _add_reconstruct(sub)
    _add_batch(sub)
    _add_register(sub)
    _add_device(sub)
    _add_view(sub)
    _add_board(sub)
    _add_virtual_scan(sub)
    _add_train(sub)
    _add_bench(sub)
    return bound_numbers(p)


def _add_demo(sub: Subcommands) -> None:
    """``ntp demo``'s options and handler."""
    d = sub.add_parser("demo", help="virtual-scan the bundled demo, reconstruct it, print errors vs truth")
    d.add_argument("--out", type=Path, default=Path("ntp_demo_out"), help="output folder (scan/, result/)")
    d.add_argument("--views", type=VIEWS, default=demo.DEMO_VIEWS, help="photos in the virtual scan")
    d.add_argument("--scale", type=SCALE, default=demo.DEMO_SCALE, help="camera resolution scale (1.0 = 2448x2048)")
    d.add_argument("--resolution", type=RESOLUTION, default=demo.DEMO_RESOLUTION, help="texture maps are RESOLUTION^2")
    d.add_argument("--seed", type=SEED, default=0)
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
    add_progress_arguments(d)
    d.set_defaults(func=_demo)


def _add_reconstruct(sub: Subcommands) -> None:
    """``ntp reconstruct``'s options and handler."""
    rc = sub.add_parser("reconstruct", help="a scan folder to texture maps (resumes from OUT/cache)")
    rc.add_argument("scan", type=Path, help="scan folder (scan.toml, mesh, photos/)")
    rc.add_argument("--out", type=Path, required=True, help="result folder")
    rc.add_argument("--resolution", type=RESOLUTION, default=DEFAULT_RESOLUTION, help="texture maps are RESOLUTION^2")
    rc.add_argument("--model", default=None, help="shipped model name or a model folder (default: compact)")
    rc.add_argument("--poses", type=Path, default=None, help="poses JSON (camera-from-world per photo); skips SfM")
    rc.add_argument("--device", type=Path, default=None, help="device TOML instead of the one scan.toml names")
    rc.add_argument("--colmap", type=Path, default=None, help=COLMAP_HELP)
    rc.add_argument(
        "--blur-margin",
        type=BLUR_MARGIN,
        default=PIPELINE_TUNING.select.blur_margin,
        help="drop photos whose blur score exceeds the scan's median by this much",
    )
    rc.add_argument("--force-registration", action="store_true", help=FORCE_HELP)
    paths = rc.add_mutually_exclusive_group()
    paths.add_argument("--refine", action="store_true", help=REFINE_HELP)
    paths.add_argument("--distil", action="store_true", help=DISTIL_HELP)
    rc.add_argument("--ray", nargs="?", const=LOCAL, default=None, metavar="ADDRESS", help=RAY_HELP)
    _run_options(rc)
    add_progress_arguments(rc)
    rc.set_defaults(func=_reconstruct)


def _add_batch(sub: Subcommands) -> None:
    """``ntp batch``'s options and handler."""
    ba = sub.add_parser("batch", help="reconstruct a collection of scans into OUT/<scan name> (resumable)")
    ba.add_argument("scans", type=Path, nargs="+", metavar="SCAN", help="scan folders")
    ba.add_argument("--out", type=Path, required=True, help="collection folder (one result per scan, batch.json)")
    ba.add_argument("--resolution", type=RESOLUTION, default=DEFAULT_RESOLUTION, help="texture maps are RESOLUTION^2")
    ba.add_argument("--model", default=None, help="shipped model name or a model folder (default: compact)")
    batch_paths = ba.add_mutually_exclusive_group()
    batch_paths.add_argument("--refine", action="store_true", help=REFINE_HELP)
    batch_paths.add_argument("--distil", action="store_true", help=DISTIL_HELP)
    ba.add_argument(
        "--threads", type=THREADS, default=0, help="CPU threads per scan (default 0: every core; 1 per Ray task)"
    )
    ba.add_argument("--ray", nargs="?", const=LOCAL, default=None, metavar="ADDRESS", help=BATCH_RAY_HELP)
    add_progress_arguments(ba)
    ba.set_defaults(func=_batch)


def _add_view(sub: Subcommands) -> None:
    """``ntp view``'s options and handler."""
    v = sub.add_parser("view", help="write RESULT/index.html (the asset in 3D, maps, coverage, numbers) and open it")
    v.add_argument("result", type=Path, help="result folder")
    v.add_argument("--glb", type=Path, default=None, help=f"the asset; {GLB_HOWTO} makes one")
    v.add_argument("--no-open", action="store_true", help="write the page only (headless machines, scripts)")
    v.set_defaults(func=_view)


def _add_register(sub: Subcommands) -> None:
    """``ntp register``'s options and handler."""
    rg = sub.add_parser("register", help="photo selection + camera poses (SfM aligned to the mesh) -> OUT/poses.json")
    rg.add_argument("scan", type=Path, help="scan folder (scan.toml, mesh, photos/)")
    rg.add_argument("--out", type=Path, required=True, help="result folder (its cache is shared with reconstruct)")
    rg.add_argument("--device", type=Path, default=None, help="device TOML instead of the one scan.toml names")
    rg.add_argument("--colmap", type=Path, default=None, help=COLMAP_HELP)
    rg.add_argument("--blur-margin", type=BLUR_MARGIN, default=PIPELINE_TUNING.select.blur_margin)
    rg.add_argument("--force-registration", action="store_true", help=FORCE_HELP)
    _run_options(rg)
    add_progress_arguments(rg)
    rg.set_defaults(func=_register)


def _add_device(sub: Subcommands) -> None:
    """``ntp device``'s options and handler."""
    dev = sub.add_parser("device", help="print a device calibration file, or list the shipped ones")
    dev.add_argument("path", type=Path, nargs="?", default=None, help="device TOML (default: the default device)")
    dev.add_argument("--list", action="store_true", help="list the shipped devices")
    dev.set_defaults(func=_device)


def _add_board(sub: Subcommands) -> None:
    """``ntp board``'s options and handler."""
    bo = sub.add_parser("board", help="write a printable marker board (PDF) and its layout (JSON) for registration")
    bo.add_argument("--size", choices=list(PAPERS), default="A4", help="paper size (landscape)")
    bo.add_argument("--out", type=Path, default=Path("board.pdf"), help="the PDF; the layout is written beside it")
    bo.set_defaults(func=_board)


def _add_virtual_scan(sub: Subcommands) -> None:
    """``ntp virtual-scan``'s options and handler."""
    vs = sub.add_parser("virtual-scan", help="simulate a hand-held capture of a mesh with known maps")
    vs.add_argument("--out", type=Path, required=True, help="scan folder to write")
    vs.add_argument("--asset", default=None, help="asset folder (mesh.obj + ground_truth/); default: the demo")
    vs.add_argument("--mesh", type=Path, default=None, help="a mesh with UVs (OBJ/PLY, metres) ...")
    vs.add_argument("--maps", type=Path, default=None, help="... and a folder with its five maps")
    vs.add_argument(
        "--given-mesh",
        type=Path,
        default=None,
        help="the mesh the scan folder hands ntp (e.g. a scanner's, same UV layout); the photos are of the "
        "asset's mesh, kept as ground_truth/mesh.obj",
    )
    vs.add_argument("--device", type=Path, default=None, help="device TOML (default: the paper's LED array)")
    vs.add_argument("--views", type=VIEWS, default=120)
    vs.add_argument("--scale", type=SCALE, default=0.25, help="camera resolution scale (1.0 = 2448x2048)")
    vs.add_argument("--seed", type=SEED, default=0)
    vs.add_argument("--exposure", type=EXPOSURE, default=1.5, help="x the device's auto-exposure")
    vs.add_argument("--blur-fraction", type=FRACTION, default=0.0, help="fraction of photos with motion blur")
    vs.add_argument(
        "--board", choices=list(PAPERS), default=None, help="stand the object on a marker board (ntp board)"
    )
    vs.add_argument(
        "--renderer", choices=["engine", "cycles"], default="engine", help="cycles: Blender Cycles through bpy"
    )
    vs.add_argument("--samples", type=SAMPLES, default=CyclesConfig.samples, help="Cycles samples per pixel")
    vs.add_argument("--bounces", type=BOUNCES, default=CyclesConfig.bounces, help="Cycles light bounces")
    vs.add_argument(
        "--max-samples",
        type=SAMPLES,
        default=None,
        help=f"Cycles samples per pixel where it sees noise (default {CyclesConfig.max_samples}, at least --samples)",
    )
    vs.add_argument(
        "--noise-threshold",
        type=float_in(0.0, 1.0, "a pixel's relative noise"),
        default=CyclesConfig.noise_threshold,
        help="Cycles' adaptive-sampling threshold: above it a pixel keeps sampling up to --max-samples",
    )
    add_progress_arguments(vs)
    vs.set_defaults(func=_virtual_scan)


def _add_train(sub: Subcommands) -> None:
    """``ntp train``'s options and handler."""
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
        type=FRACTION,
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
    add_progress_arguments(tr)
    tr.set_defaults(func=_train)


def _add_bench(sub: Subcommands) -> None:
    """``ntp bench``'s options and handler."""
    b = sub.add_parser("bench", help="benchmarks: run time and error in one run")
    bsub = b.add_subparsers(dest="bench", metavar="NAME", required=True)
    for name, module in BENCHES.items():
        bp = bsub.add_parser(name, help=module.HELP)
        module.add_arguments(bp)
        bp.set_defaults(func=module.command)


if __name__ == "__main__":
    sys.exit(main())
