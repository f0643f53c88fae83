"""The Cycles scanner: the virtual scanner's capture of the same scene, rendered by Blender Cycles
instead of the engine — an independent renderer, so errors of the engine's own forward model cannot
cancel in the evaluation.

Same trajectory (same seed, same poses), same sensor (``virtual_scan.sensor``) and the same scan
folder and ``ground_truth/`` as ``virtual_scan``; only the linear images differ. Cycles renders them
in its own process (``python -m ntp_addon.scan_render``; the engine never imports bpy) with a
diffuse + GGX material (Cycles' height-correlated Smith G — not the engine's separable one),
interreflections (``bounces``), exact shadows and Monte Carlo noise (``samples`` per pixel, and up to
``max_samples`` where Cycles still sees noise: a sharp highlight is a few rare hits of a 2 mm light, so
at a fixed 12 spp its pixels' median is ~1/3 of their mean and the sensor clips the hits). Each
emitter is a small Lambertian area light (so only cos^1 emitters can be modelled) driven by the
pattern through the colour matrix. The lobe is the engine's own — rho_s x GGX x Schlick's Fresnel
on w_i.h, its rise bounded so no lobe reflects more than all the light (F90 = min(1, 1 / rho_s),
``physics.brdf.bounded_f90``: docs/design.md's F on every path from an emitter) — as an OSL node
(``ntp_addon.schlick_lobe``; Cycles renders with OSL on the CPU), so light the support or the
object bounces onto the object reflects with a Fresnel too, as on a real object.
Until 2026-11-29 it was a Glossy BSDF of colour rho_s F0, right for the direct paths (every emitter
beside the camera: w_i.h ~ 1) but not for bounced light, which arrives from anywhere: the box's
metals facing the backdrop came out darker than the truth's BRDF makes them (docs/virtual-scanner.md).

Radiometric calibration, as on a real device: Cycles also renders a white Lambertian patch at the
valid volume's centre facing the panel; the engine predicts that patch's measurement (Eq. 1) for
the same pixels, and the per-channel ratio scales every render. Then exposure and the sensor.

Renders are cached in ``ground_truth/cycles/`` under a key of everything they depend on (asset
content, camera, emitters, pattern, poses, samples, bounces, seed): a re-run with only sensor
settings changed re-uses them, an interrupted one resumes.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch

from ..io.assets import DEVICES_DIR
from ..io.blender_process import blender_command, has_bpy
from ..io.errors import NtpInputError
from ..io.images import read_image, write_png
from ..io.maps import MAP_FILES
from ..io.mesh import save_obj
from ..io.output_folder import claim
from ..io.progress import QUIET, Progress
from ..io.stage_cache import content_digest, digest
from ..physics.measurement import measurement_rgb
from ..scanner import camera
from ..scanner.device_file import load_scanner, save_scanner
from ..scanner.scanner import Scanner
from .virtual_scan import (
    ScanConfig,
    load_asset,
    load_given_mesh,
    plan_capture,
    remove_old_photos,
    sensor,
    write_scan,
)

RENDER_DIR = "cycles"
POINT_LED_SIZE = 0.002  # m: side of the square area light standing in for a point LED
LINEAR_LED_WIDTH = 0.001  # m: width of the rectangle standing in for a linear light
CALIBRATION_PATCH = 0.03  # m: side of the white calibration patch
# how the scene is rendered (part of the render cache key: bump when the same settings render
# differently): 2 = the Glossy colour rho_s F0 (was rho_s Schlick on n.v); 3 = no clamp on indirect
# samples, no glossy blur (Cycles' defaults held back most of the light bounced off the support);
# 4 = adaptive sampling up to ``max_samples`` (was Blender's default: adaptive within ``samples``),
# the calibration patch at a fixed sample count; 5 = the engine's lobe as an OSL node, Schlick's
# Fresnel on w_i.h on every path (was the Glossy colour rho_s F0: light bounced onto the object
# reflected without the Fresnel's rise); 6 = that Fresnel bounded, F90 = min(1, 1 / rho_s)
RENDER_VERSION = 6


@dataclass
class CyclesConfig:
    """Cycles settings of a scan (the sensor's are ``ScanConfig``): every pixel gets ``samples``, and
    one whose noise Cycles estimates above ``noise_threshold`` (Cycles' adaptive-sampling threshold
    on the renders' raw scale, 1 W per unit drive) keeps sampling up to ``max_samples``. Chosen on
    the gallery box's mirror lacquer (alpha 0.006): at 12 spp fixed its brightest 1% of pixels read
    a median 0.37 of a 384-spp render's (their mean is right: the rare hits carry it, and the 8-bit
    sensor clips them), and the refinement's rho_s came out 0.34 of the truth; threshold 0.05 up to
    384 gives them all 384 samples (the gallery's scans: ~1.3x the 12-spp time); 0.1 stopped short on
    some, their q10 0.72-0.82 of the 384-spp values (photos 0005, 0017)."""

    samples: int = 16
    bounces: int = 2
    calibration_samples: int = 256
    max_samples: int = 384
    noise_threshold: float = 0.05


def emitter_lights(scanner: Scanner) -> list[dict]:
    """Area lights standing in for the lit emitters: camera-space centre, normal, axis, size (m) and
    RGB drive (the pattern through the colour matrix). Raises for emitters Cycles cannot model."""
    if scanner.angular_kind != "cosine" or scanner.angular_exponent != 1.0:
        raise NtpInputError(
            scanner.source or scanner.name,
            "the Cycles scanner models Lambertian emitters only (angular cosine exponent 1)",
        )
    if scanner.emitter_kind == "area":
        size = tuple(float(s) for s in scanner.emitter_size)
    elif scanner.emitter_kind == "linear":
        size = (float(scanner.emitter_size[0]), LINEAR_LED_WIDTH)
    else:
        size = (POINT_LED_SIZE, POINT_LED_SIZE)
    drive = scanner.effective_pattern(scanner.pattern)
    return [
        {
            "centre": scanner.emitter_positions[k].tolist(),
            "normal": scanner.emitter_normals[k].tolist(),
            "axis": scanner.emitter_axes[k].tolist(),
            "size": list(size),
            "rgb": drive[k].tolist(),
        }
        for k in range(scanner.num_emitters)
        if drive[k].max() > 0
    ]


def _render(job: dict, folder: Path, progress: Progress) -> None:
    """Run the renderer process on ``job`` (photos into ``folder``), advancing ``progress``."""
    if not has_bpy():
        raise NtpInputError(None, "the Cycles scanner needs bpy (Blender as a module; `make setup` installs it)")
    job_path = folder / "job.json"
    job_path.write_text(json.dumps(job, indent=1))
    cmd = blender_command("scan_render", str(job_path))
    log = folder / "render.log"  # Blender's own messages (a file: a full pipe would stall it)
    with log.open("w") as err, subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=err, text=True) as proc:
        assert proc.stdout is not None
        lines = (line for line in proc.stdout if line.startswith("rendered "))
        for _ in progress.track(lines, "cycles scan", total=len(job["poses"]), unit="photo"):
            pass
    if proc.returncode != 0:
        tail = [line for line in log.read_text().strip().splitlines() if line.strip()] or ["no message"]
        raise RuntimeError(f"the Cycles renderer failed (exit {proc.returncode}, log {log}): {tail[-1]}")


def calibration_patch(scanner: Scanner) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The white patch's centre (the valid volume's), unit normal (facing the panel) and in-plane x
    axis, camera space ``(3,)`` each."""
    centre = np.asarray(scanner.valid_center, float)
    normal = -scanner.emitter_normals.mean(0)
    normal /= np.linalg.norm(normal)
    x_axis = np.cross([0.0, 1.0, 0.0], normal)
    return centre, normal, x_axis / np.linalg.norm(x_axis)


def calibration_gain(scanner: Scanner, cam: Scanner, render: np.ndarray) -> np.ndarray:
    """Per-channel factor ``(3,)`` taking Cycles' render of the white patch (identity pose) to the
    engine's measurement B of it: means over the pixels of the patch's central half."""
    centre, normal, x_axis = calibration_patch(scanner)
    rays = camera.pixel_rays(cam).reshape(-1, 3)
    t = (centre @ normal) / (rays @ normal)
    x = rays * t[:, None]
    y_axis = np.cross(normal, x_axis)
    d = x - centre
    inside = (np.abs(d @ x_axis) < CALIBRATION_PATCH / 4) & (np.abs(d @ y_axis) < CALIBRATION_PATCH / 4)
    if inside.sum() < 4:
        raise RuntimeError("calibration patch covers fewer than 4 pixels; raise the scale")
    n = int(inside.sum())

    def T(a):
        return torch.as_tensor(np.ascontiguousarray(a), dtype=torch.float64)

    B = measurement_rgb(
        scanner,
        T(x[inside]),
        T(np.broadcast_to(normal, (n, 3))),
        T(np.broadcast_to(x_axis, (n, 3))),
        T(np.ones((n, 3))),
        T(np.zeros((n, 3))),
        T(np.full(n, 0.3)),
        T(np.full(n, 0.3)),
        torch.as_tensor(scanner.pattern, dtype=torch.float64),
    ).numpy()
    seen = render.reshape(-1, 3)[inside]
    return B.mean(0) / np.maximum(seen.mean(0), 1e-20)


def cycles_scan(
    out: Path,
    asset: str | None = None,
    mesh_path: Path | None = None,
    maps_dir: Path | None = None,
    device_path: Path | None = None,
    cfg: ScanConfig | None = None,
    cycles: CyclesConfig | None = None,
    progress: Progress = QUIET,
    given_mesh: Path | None = None,
) -> dict:
    """Capture the asset into the scan folder ``out`` with Cycles (module docstring); returns the
    capture record (also ``ground_truth/capture.json``); ``given_mesh`` as ``virtual_scan``'s."""
    cfg, cycles = cfg or ScanConfig(), cycles or CyclesConfig()
    if cycles.samples < 1 or cycles.bounces < 0:
        raise NtpInputError(None, "need --samples >= 1 and --bounces >= 0")
    if cycles.max_samples < cycles.samples or not cycles.noise_threshold > 0:
        raise NtpInputError(None, "need --max-samples >= --samples and --noise-threshold > 0")
    mesh, maps, src_mesh, maps_dir = load_asset(asset, mesh_path, maps_dir)
    given = load_given_mesh(given_mesh, mesh)
    scanner = load_scanner(device_path)
    lights = emitter_lights(scanner)
    plan = plan_capture(mesh, scanner, cfg)
    cam = plan.cam
    if np.any(np.asarray(cam.distortion) != 0):
        raise NtpInputError(device_path or DEVICES_DIR, "the Cycles scanner models a pinhole camera (distortion 0)")

    inputs = (src_mesh.parent, maps_dir) + ((given_mesh.parent,) if given_mesh is not None else ())
    with claim(out, "scan", inputs=inputs):
        remove_old_photos(out, plan.names)
        folder = out / "ground_truth" / RENDER_DIR
        key = {
            "asset": content_digest([src_mesh, *(maps_dir / f for f in MAP_FILES.values())]),
            "camera": [cam.width, cam.height, cam.K.tolist()],
            "emitters": lights,
            "poses": [p.tolist() for p in plan.poses],
            "cycles": asdict(cycles),
            "seed": cfg.seed,
            "render_version": RENDER_VERSION,
            **({"board": plan.board_record} if plan.board is not None else {}),  # scans without: keys as before
        }
        key_digest = digest(key)
        stamp = folder / "key.json"
        if not (stamp.is_file() and json.loads(stamp.read_text()).get("digest") == key_digest):
            if folder.exists():
                shutil.rmtree(folder)
            (folder / "asset").mkdir(parents=True)
            save_obj(folder / "asset" / "mesh.obj", mesh)
            maps.save(folder / "asset")
            stamp.write_text(json.dumps({"digest": key_digest}))
        save_scanner(cam, folder / "device.toml")
        job = {
            "asset": str(folder / "asset"),
            "device": str(folder / "device.toml"),
            "emitters": lights,
            "watts_per_unit_drive": 1.0,  # any constant: the calibration absorbs it (noise_threshold is on it)
            "poses": {n: p.tolist() for n, p in plan.named_poses.items()},
            "samples": cycles.samples,
            "max_samples": cycles.max_samples,
            "noise_threshold": cycles.noise_threshold,
            "bounces": cycles.bounces,
            "seed": cfg.seed,
            "calibration": dict(
                zip(("centre", "normal", "axis"), (v.tolist() for v in calibration_patch(scanner))),
                size=CALIBRATION_PATCH,
                samples=cycles.calibration_samples,
            ),
            "out": str(folder),
            "board": plan.board_record if plan.board is not None else None,
        }
        t0 = time.perf_counter()
        renders = [folder / f"{Path(n).stem}.exr" for n in plan.names] + [folder / "calibration.exr"]
        if not all(r.is_file() for r in renders):  # all cached: no Blender process to start
            _render(job, folder, progress)
        seconds = time.perf_counter() - t0
        gain = calibration_gain(scanner, cam, read_image(folder / "calibration.exr")[..., :3].astype(np.float64))
        exposure = cfg.exposure * float(scanner.exposure(scanner.pattern))
        for i, name in enumerate(plan.names):
            lin = exposure * gain * read_image(folder / f"{Path(name).stem}.exr")[..., :3].astype(np.float64)
            img = sensor(lin, cam, cfg, plan.rng, blur=i in plan.blurred)
            write_png(out / "photos" / name, img.astype(np.float64) / 255.0)
        extra = {"cycles": asdict(cycles), "calibration_gain": gain.tolist()}
        capture = plan.record("cycles", src_mesh, scanner, seconds, **extra)
        write_scan(out, mesh, maps, cam, plan.named_poses, capture, maps_dir, given, plan.board_layout)
    return capture


def at_least_samples(max_samples: int | None, samples: int) -> int:
    """``--max-samples``, or by default ``CyclesConfig``'s but at least ``--samples``."""
    return max(samples, CyclesConfig.max_samples) if max_samples is None else max_samples
