"""The virtual scanner: a simulated hand-held capture of a mesh with a known SVBRDF.

Writes exactly what a real capture gives (a scan folder: ``scan.toml``, ``mesh.obj``,
``device.toml`` with the camera at the photos' resolution, ``photos/*.png``) plus
``ground_truth/`` (the five maps in the mesh's UV layout, ``poses.json`` camera-from-world, and
``capture.json`` with the settings, the blurred photos and the timing). Photos are rendered by
``renderer.Scene``.

With ``board`` (a paper size), the object stands on a printed marker board (``scanner.board``),
turned and shifted at random under it (seeded apart from the photos: the same photos' poses as
without); the scan folder gets ``board.json`` and ``ground_truth/capture.json`` its placement.

Trajectory: a hand-held sweep over the upper hemisphere (a spiral in azimuth, elevation oscillating
between 15 and 75 deg), the scanner aimed so the object's centre sits at the valid volume's centre,
with jitter in distance, aim and roll. Seeded: the same seed gives the same scan.
"""

from __future__ import annotations

import json
import math
import shutil
import time
from collections import deque
from collections.abc import Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
from scipy import ndimage
from scipy.spatial import cKDTree

from ..io.assets import DEMO_DIR
from ..io.atomic import write_text_atomic
from ..io.errors import NtpInputError
from ..io.images import write_png
from ..io.maps import SVBRDFMaps
from ..io.mesh import Mesh, load_mesh, save_obj
from ..io.output_folder import claim
from ..io.progress import QUIET, Progress
from ..register.align import surface_samples
from ..scanner import camera
from ..scanner.board import Board, board_for_paper
from ..scanner.device_file import load_scanner, save_scanner
from ..scanner.scan_folder import load_scan, write_scan_toml
from ..scanner.scanner import Scanner
from .materials import LABELS_FILE, MATERIALS_FILE
from .renderer import BACKDROP_Z, Scene


@dataclass
class ScanConfig:
    """Settings of a virtual capture (trajectory, sensor, motion blur, rendering)."""

    views: int = 120
    scale: float = 0.25
    seed: int = 0
    elevation_deg: tuple[float, float] = (15.0, 75.0)
    distance_jitter: float = 0.008  # m
    aim_jitter: float = 0.006  # m
    roll_deg: float = 20.0
    noise_sigma: float = 0.02  # multiplicative sensor noise
    read_noise: float = 0.5  # 8-bit codes
    exposure: float = 1.5  # x the device's auto-exposure; recorded in the scan's device.toml gain
    blur_fraction: float = 0.0
    blur_px: float = 12.0  # motion-blur streak length in pixels at scale 0.25 (scales with resolution)
    clusters: int = 64
    chunk: int = 2048  # object pixels shaded at once (512: 15% slower per photo, 8192: 10%)
    board: str | None = None  # a marker board of this paper size (scanner.board.PAPERS) under the object
    board_shift: float = 0.01  # m, the board's centre from the object's foot (each axis, normal sigma)


def trajectory(center: np.ndarray, scanner: Scanner, cfg: ScanConfig, rng: np.random.Generator) -> list[np.ndarray]:
    """Camera-from-world 4x4 poses of a hand-held sweep around ``center``."""
    working = float(np.linalg.norm(scanner.valid_center))
    e0, e1 = np.radians(cfg.elevation_deg)
    poses = []
    for i in range(cfg.views):
        s = i / max(cfg.views - 1, 1)
        az = 2 * math.pi * 3.0 * s + rng.normal(0, 0.05)
        el = e0 + (e1 - e0) * (0.5 - 0.5 * math.cos(2 * math.pi * 3.5 * s)) + rng.normal(0, 0.03)
        el = float(np.clip(el, e0, e1))
        d = np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
        centre = center + (working + rng.normal(0, cfg.distance_jitter)) * d
        pose = camera.look_at(centre, center + rng.normal(0, cfg.aim_jitter, 3))
        x, y = pose[0, :3].copy(), pose[1, :3].copy()
        roll = math.radians(rng.normal(0, cfg.roll_deg))
        pose[0, :3], pose[1, :3] = math.cos(roll) * x + math.sin(roll) * y, -math.sin(roll) * x + math.cos(roll) * y
        pose[:3, 3] = -pose[:3, :3] @ centre
        poses.append(pose)
    return poses


def take_photo(
    scene: Scene, pose: np.ndarray, cam: Scanner, cfg: ScanConfig, rng: np.random.Generator, blur: bool = False
) -> np.ndarray:
    """An 8-bit photo ``(H, W, 3)`` uint8 of ``scene`` by the camera ``cam`` at ``pose`` (the linear
    render through ``sensor``)."""
    lin, _ = scene.render_linear(pose, cam, cfg.chunk)
    return sensor(lin, cam, cfg, rng, blur)


BOARD_FILE = "board.json"  # the marker board's layout in a virtual scan folder
RENDER_THREADS = 2  # photos rendered at once: Embree, numpy and torch leave each other's gaps (2 cores: x1.25)


def linear_renders(scene: Scene, poses: list[np.ndarray], cam: Scanner, chunk: int) -> Iterator[np.ndarray]:
    """``scene.render_linear`` of each pose in order, the next ``RENDER_THREADS`` rendering while the
    caller uses one. Each render is the same as alone (torch's threads as set; nothing random)."""
    with ThreadPoolExecutor(RENDER_THREADS) as pool:

        def submit(pose: np.ndarray) -> Future:
            return pool.submit(scene.render_linear, pose, cam, chunk)

        pending = deque(submit(p) for p in poses[:RENDER_THREADS])
        for i in range(len(poses)):
            lin = pending.popleft().result()[0]
            if i + RENDER_THREADS < len(poses):
                pending.append(submit(poses[i + RENDER_THREADS]))
            yield lin


def sensor(lin: np.ndarray, cam: Scanner, cfg: ScanConfig, rng: np.random.Generator, blur: bool = False) -> np.ndarray:
    """The device's sensor on a linear image ``(H, W, 3)`` (exposure applied): optional motion
    blur, multiplicative noise N(1, sigma), the 8-bit response, read noise, clipping at 255 and
    rounding; ``(H, W, 3)`` uint8."""
    if blur:
        length = max(3, int(round(cfg.blur_px * cfg.scale / 0.25)))
        angle = rng.uniform(0, 180)
        kernel = np.zeros((length, length))
        kernel[length // 2, :] = 1.0
        kernel = ndimage.rotate(kernel, angle, reshape=False, order=1)
        kernel /= kernel.sum()
        lin = np.stack([ndimage.convolve(lin[..., c], kernel, mode="nearest") for c in range(3)], -1)
    lin = lin * (1 + cfg.noise_sigma * rng.standard_normal(lin.shape))
    code = camera.encode(cam, torch.as_tensor(lin)).numpy() + cfg.read_noise * rng.standard_normal(lin.shape)
    return np.clip(np.round(code), 0, 255).astype(np.uint8)


def load_given_mesh(path: Path | None, rendered: Mesh) -> Mesh | None:
    """The mesh ntp is to be given instead of the rendered one (a scanner's, ``sim.scanner_mesh``):
    read, and checked to share the rendered mesh's UV layout (the maps are compared texel by texel)."""
    if path is None:
        return None
    given = load_mesh(path)
    if given.uv is None or rendered.uv is None:
        raise NtpInputError(path, "the given mesh needs UVs in the rendered mesh's layout")
    extent = float((rendered.vertices.max(0) - rendered.vertices.min(0)).max())
    offset = float(np.abs(given.vertices.mean(0) - rendered.vertices.mean(0)).max())
    if offset > 0.05 * extent:
        raise NtpInputError(path, f"the given mesh is {offset * 1e3:.1f} mm from the rendered one: not the same object")
    return given


def load_asset(asset: str | None, mesh_path: Path | None, maps_dir: Path | None) -> tuple[Mesh, SVBRDFMaps, Path, Path]:
    """The mesh and maps of an asset folder (``mesh.obj`` + ``ground_truth/``; default the demo), or
    of ``mesh_path`` with ``maps_dir``; and the mesh's path and the maps' folder."""
    if mesh_path is None:
        folder = DEMO_DIR if asset in (None, "demo") else Path(asset)
        if not (folder / "mesh.obj").is_file():
            raise NtpInputError(folder, "not an asset folder (needs mesh.obj and ground_truth/)")
        mesh_path, maps_dir = folder / "mesh.obj", folder / "ground_truth"
    if maps_dir is None:
        raise NtpInputError(mesh_path, "--mesh needs --maps DIR with the five ground-truth maps")
    mesh = load_mesh(mesh_path)
    if mesh.uv is None:
        raise NtpInputError(mesh_path, "mesh has no UVs, but maps were given (maps need a UV layout)")
    maps = SVBRDFMaps.load(maps_dir)
    return mesh, maps, mesh_path, maps_dir


def virtual_scan(
    out: Path,
    asset: str | None = None,
    mesh_path: Path | None = None,
    maps_dir: Path | None = None,
    device_path: Path | None = None,
    cfg: ScanConfig | None = None,
    progress: Progress = QUIET,
    given_mesh: Path | None = None,
) -> dict:
    """Capture the asset into the scan folder ``out`` (see the module docstring); returns the
    capture record (also ``ground_truth/capture.json``). ``given_mesh``: the mesh the scan folder
    hands ntp (e.g. a scanner's) — the photos are of the asset's; the truth keeps that one."""
    cfg = cfg or ScanConfig()
    mesh, maps, src_mesh, maps_dir = load_asset(asset, mesh_path, maps_dir)
    given = load_given_mesh(given_mesh, mesh)
    scanner = load_scanner(device_path)
    plan = plan_capture(mesh, scanner, cfg)
    scene = Scene(mesh, maps, scanner, cfg.clusters, cfg.exposure, board=plan.board)
    inputs = (src_mesh.parent, maps_dir) + ((given_mesh.parent,) if given_mesh is not None else ())
    with claim(out, "scan", inputs=inputs):
        remove_old_photos(out, plan.names)
        t0 = time.perf_counter()
        renders = linear_renders(scene, plan.poses, plan.cam, cfg.chunk)
        for i in progress.track(range(cfg.views), "virtual scan", unit="photo"):
            # = take_photo, the sensor drawing from the seeded generator in the photos' order
            img = sensor(next(renders), plan.cam, cfg, plan.rng, blur=i in plan.blurred)
            write_png(out / "photos" / plan.names[i], img.astype(np.float64) / 255.0)
        capture = plan.record("engine", src_mesh, scanner, time.perf_counter() - t0)
        write_scan(out, mesh, maps, plan.cam, plan.named_poses, capture, maps_dir, given, plan.board_layout)
    return capture


def remove_old_photos(out: Path, names: list[str]) -> None:
    """Before a capture into the scan folder ``out`` (claimed): delete the photos an earlier capture
    wrote there (its ``capture.json`` lists them) that this one will not overwrite, so a re-scan with
    fewer photos leaves no stale ones; then make ``out/photos``."""
    record = out / "ground_truth" / "capture.json"
    old = json.loads(record.read_text()).get("photos", []) if record.is_file() else []
    record.unlink(missing_ok=True)  # the scan is incomplete until the new record is written
    for name in set(old) - set(names):
        (out / "photos" / Path(name).name).unlink(missing_ok=True)
    (out / "photos").mkdir(parents=True, exist_ok=True)


@dataclass
class CapturePlan:
    """What a capture takes before any pixel: the camera at the photos' resolution (its gain the
    capture's exposure), the seeded generator (the sensor draws from it next), the poses, the
    photos to blur and the photo names."""

    cfg: ScanConfig
    cam: Scanner
    rng: np.random.Generator
    poses: list[np.ndarray]
    blurred: set[int]
    names: list[str]
    board: tuple[Board, np.ndarray] | None = None  # the marker board and its world-from-board 4x4

    @property
    def board_layout(self) -> Board | None:
        """The marker board's layout, where the object stands on one."""
        return None if self.board is None else self.board[0]

    @property
    def named_poses(self) -> dict[str, np.ndarray]:
        """Camera-from-world pose per photo name."""
        return dict(zip(self.names, self.poses))

    def record(self, renderer: str, src_mesh: Path, scanner: Scanner, seconds: float, **extra) -> dict:
        """The capture record (``ground_truth/capture.json``)."""
        return {
            "config": asdict(self.cfg),
            "renderer": renderer,
            **extra,
            "source_mesh": str(src_mesh),
            "device": scanner.name,
            "photos": self.names,
            "blurred_photos": sorted(self.names[i] for i in self.blurred),
            "seconds": seconds,
            "seconds_per_photo": seconds / max(self.cfg.views, 1),
            **({} if self.board is None else {"board": self.board_record}),
        }

    @property
    def board_record(self) -> dict:
        """The marker board's layout and placement (world-from-board 4x4) for ``capture.json``."""
        assert self.board is not None
        return {**self.board[0].to_json(), "world_from_board": self.board[1].tolist()}


def plan_capture(mesh: Mesh, scanner: Scanner, cfg: ScanConfig) -> CapturePlan:
    """The plan of a seeded capture of ``mesh`` (the same for every renderer); checks ``cfg``."""
    if not 0 < cfg.scale <= 1 or cfg.views < 1 or not 0 <= cfg.blur_fraction <= 1:
        raise NtpInputError(None, "need 0 < --scale <= 1, --views >= 1, 0 <= --blur-fraction <= 1")
    cam = camera.resampled(scanner, cfg.scale)
    cam.gain = scanner.gain * cfg.exposure  # what this capture used: B = pixel / cam.exposure(pattern)
    rng = np.random.default_rng(cfg.seed)
    centre = 0.5 * (mesh.vertices.min(0) + mesh.vertices.max(0))  # = renderer.Scene.center
    poses = trajectory(centre, scanner, cfg, rng)
    n_blur = int(round(cfg.blur_fraction * cfg.views))
    blurred = set(rng.choice(cfg.views, size=n_blur, replace=False).tolist()) if n_blur else set()
    board = None if cfg.board is None else (board_for_paper(cfg.board), board_placement(mesh, cfg))
    return CapturePlan(cfg, cam, rng, poses, blurred, [f"{i:04d}.png" for i in range(cfg.views)], board)


def board_placement(mesh: Mesh, cfg: ScanConfig) -> np.ndarray:
    """World-from-board 4x4 of the board under ``mesh``: turned uniformly, its centre
    ``cfg.board_shift`` (normal sigma, each axis) from the mesh's foot, on the backdrop; drawn from its own
    generator (the seed's), so the photos' poses and noise are those of the scan without a board."""
    rng = np.random.default_rng([cfg.seed, 1])
    turn = rng.uniform(0, 2 * math.pi)
    m = np.eye(4)
    m[:2, :2] = [[math.cos(turn), -math.sin(turn)], [math.sin(turn), math.cos(turn)]]
    m[:2, 3] = 0.5 * (mesh.vertices.min(0) + mesh.vertices.max(0))[:2] + rng.normal(0, cfg.board_shift, 2)
    m[2, 3] = BACKDROP_Z  # printed on the backdrop, a tenth of a millimetre under the object's foot
    return m


def holds_support_light(capture: dict) -> bool:
    """Whether a virtual scan's photos (its ``capture.json`` record) hold light the support reflects
    onto the object: the engine renders Eq. 1's direct light only, Cycles without bounces too."""
    return capture["renderer"] == "cycles" and capture["cycles"]["bounces"] > 0


def scan_folder_is_current(folder: Path) -> bool:
    """A virtual scan folder whose ``scan.toml`` says what its photos hold (older ones did not say
    ``support_light = false``): one a re-run may keep."""
    try:
        capture = json.loads((folder / "ground_truth" / "capture.json").read_text())
        return load_scan(folder).support_light == holds_support_light(capture)
    except (OSError, ValueError, KeyError):  # NtpInputError is a ValueError
        return False


def write_scan(
    out: Path,
    mesh: Mesh,
    maps: SVBRDFMaps,
    cam: Scanner,
    poses: dict[str, np.ndarray],
    capture: dict,
    labels_from: Path,
    given: Mesh | None = None,
    board: Board | None = None,
) -> None:
    """Everything of a scan folder but its photos (``out/photos/`` holds them already): the mesh
        (``given`` where there is one, the photographed ``mesh`` then in ``ground_truth/mesh.obj``),
        the device file at the photos' resolution, ``ground_truth/`` (maps, material labels when
        ``labels_from`` has them, poses, ``capture.json``), the marker board's layout (``board.json``)
    where the object stands on one, and ``scan.toml`` (with the given mesh's ``surface_error`` as its
    stated accuracy)."""
    gt = out / "ground_truth"
    gt.mkdir(parents=True, exist_ok=True)
    save_obj(out / "mesh.obj", mesh if given is None else given)
    if given is not None:
        save_obj(gt / "mesh.obj", mesh)
    else:
        (gt / "mesh.obj").unlink(missing_ok=True)  # a re-scan without one: the truth is the scan's mesh
    save_scanner(cam, out / "device.toml")
    maps.save(gt)
    for f in (LABELS_FILE, MATERIALS_FILE):
        if (labels_from / f).is_file():
            shutil.copyfile(labels_from / f, gt / f)
    write_text_atomic(gt / "poses.json", json.dumps({n: p.tolist() for n, p in poses.items()}, indent=1))
    write_text_atomic(gt / "capture.json", json.dumps(capture, indent=2))
    if board is not None:
        write_text_atomic(out / BOARD_FILE, json.dumps(board.to_json(), indent=1))
    else:
        (out / BOARD_FILE).unlink(missing_ok=True)  # a re-scan without one
    write_scan_toml(
        out,
        comments=(
            f"written by ntp virtual-scan (renderer: {capture['renderer']})",
            "ground truth for evaluation: ground_truth/ (maps, poses.json, capture.json)",
        ),
        support_light=holds_support_light(capture),
        board=BOARD_FILE if board is not None else None,
        mesh_accuracy_mm=None if given is None else 1e3 * surface_error(given, mesh),
    )


def surface_error(given: Mesh, truth: Mesh, count: int = 50_000) -> float:
    """The RMS distance (metres) of ``given``'s surface from ``truth``'s: area-uniform samples of
    ``given``, each one's point-to-plane distance to the nearest of as many samples of ``truth`` —
    what a shape scanner's spec states as its accuracy (1 sigma)."""
    points = surface_samples(given, count, seed=2)
    ref, normals = surface_samples(truth, 4 * count, seed=3, normals=True)
    _, near = cKDTree(ref).query(points)
    return float(np.sqrt(np.mean(((points - ref[near]) * normals[near]).sum(1) ** 2)))


def true_mesh_path(scan: Path) -> Path:
    """The photographed mesh of a virtual scan: ``ground_truth/mesh.obj`` where the scan hands ntp
    another (``given_mesh``), else the scan's ``mesh.obj``."""
    truth = scan / "ground_truth" / "mesh.obj"
    return truth if truth.is_file() else scan / "mesh.obj"
