"""Virtual scanner: a simulated hand-held capture of a mesh with a known SVBRDF.

Writes exactly what a real capture gives (a scan folder: ``scan.toml``, ``mesh.obj``,
``device.toml`` with the camera at the photos' resolution, ``photos/*.png``) plus
``ground_truth/`` (the five maps in the mesh's UV layout and ``poses.json``, camera-from-world).

World frame = the mesh's frame (metres, z up); the object stands on a textured backdrop at z = 0
(random grey blocks at two scales, like AR markers, so structure-from-motion finds features).

Image formation per pixel (Eq. 1): Embree primary ray; on the object, the maps sampled at the hit's
UV (bilinear) give rho_d, rho_s, alphas and the object-space shading frame; B from every emitter
with Psi, 1/r^2, the colour matrix and per-emitter shadowing. Shadows are traced to *emitter
clusters* (k-means over the emitters' quadrature points, 64 by default) and shared by a cluster's
emitters: exact per-LED shadow rays cost ~50 M rays per photo; ``ntp bench virtual-scan`` measures
the error this makes. The backdrop is diffuse, lit by the clusters without shadows. Then
auto-exposure (``Device.exposure``), multiplicative sensor noise N(1, sigma) and read noise,
the device's 8-bit response, clipping at 255, rounding; optionally linear motion blur on a
fraction of photos (listed in ``ground_truth/capture.json``) so blur rejection can be tested.

Trajectory: a hand-held sweep over the upper hemisphere (a spiral in azimuth, elevation oscillating
between 15 and 75 deg), the scanner aimed so the object's centre sits at the valid volume's centre,
with jitter in distance, aim and roll. Seeded: the same seed gives the same scan.
"""
from __future__ import annotations

import json
import math
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch
from scipy import ndimage
from tqdm import tqdm

from .atomic import write_text_atomic
from .device import Device
from .errors import NtpInputError
from .images import write_png
from .maps import SVBRDFMaps
from .measurement import measurement_rgb
from .mesh import Mesh, load_mesh, save_obj
from .raycast import RayCaster

BACKDROP_Z = -1e-4
BACKDROP_HALF = 0.4


@dataclass
class ScanConfig:
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
    chunk: int = 512


# ------------------------------------------------------------------------------ scene pieces
def marker_albedo(xy: np.ndarray) -> np.ndarray:
    """Grey albedo of the backdrop at world (x, y): random blocks of 1.5 cm and 0.5 cm cells."""
    def cell_hash(ix, iy, salt):
        h = (ix * 73856093) ^ (iy * 19349663) ^ salt
        h = (h ^ (h >> 13)) * 1274126177
        return ((h ^ (h >> 16)) & 0xFFFF) / 65535.0

    big = cell_hash(np.floor(xy[:, 0] / 0.015).astype(np.int64), np.floor(xy[:, 1] / 0.015).astype(np.int64), 17)
    small = cell_hash(np.floor(xy[:, 0] / 0.005).astype(np.int64), np.floor(xy[:, 1] / 0.005).astype(np.int64), 91)
    return 0.12 + 0.45 * big + 0.3 * small


def backdrop_triangles() -> np.ndarray:
    h, z = BACKDROP_HALF, BACKDROP_Z
    quad = np.array([[-h, -h, z], [h, -h, z], [h, h, z], [-h, h, z]])
    return quad[[[0, 1, 2], [0, 2, 3]]]


def emitter_clusters(device: Device, k: int) -> tuple[np.ndarray, np.ndarray]:
    """k-means over the emitters' quadrature points (camera space): centres ``(C, 3)`` and the
    cluster of every point ``(L, Q)``. Deterministic (initialised on a spread subset)."""
    pts, _ = device.emitter_samples(torch.float64)
    flat = pts.reshape(-1, 3).numpy()
    k = min(k, len(flat))
    centres = flat[np.linspace(0, len(flat) - 1, k).round().astype(int)].copy()
    for _ in range(20):
        assign = np.argmin(((flat[:, None] - centres[None]) ** 2).sum(-1), axis=1)
        for c in range(k):
            if (assign == c).any():
                centres[c] = flat[assign == c].mean(0)
    assign = np.argmin(((flat[:, None] - centres[None]) ** 2).sum(-1), axis=1)
    return centres, assign.reshape(pts.shape[:2])


def look_at(position: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Camera-from-world 4x4 (OpenCV axes: x right, y down, z forward) at ``position`` looking at
    ``target``, level with world z up."""
    z = (target - position) / np.linalg.norm(target - position)
    x = np.cross(z, [0.0, 0.0, 1.0])  # right = forward x up
    x /= np.linalg.norm(x)
    R = np.stack([x, np.cross(z, x), z])  # rows: camera axes in world coordinates
    pose = np.eye(4)
    pose[:3, :3], pose[:3, 3] = R, -R @ position
    return pose


def trajectory(center: np.ndarray, device: Device, cfg: ScanConfig, rng: np.random.Generator) -> list[np.ndarray]:
    """Camera-from-world 4x4 poses of a hand-held sweep around ``center``."""
    working = float(np.linalg.norm(device.valid_center))
    e0, e1 = np.radians(cfg.elevation_deg)
    poses = []
    for i in range(cfg.views):
        s = i / max(cfg.views - 1, 1)
        az = 2 * math.pi * 3.0 * s + rng.normal(0, 0.05)
        el = e0 + (e1 - e0) * (0.5 - 0.5 * math.cos(2 * math.pi * 3.5 * s)) + rng.normal(0, 0.03)
        el = float(np.clip(el, e0, e1))
        d = np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
        centre = center + (working + rng.normal(0, cfg.distance_jitter)) * d
        pose = look_at(centre, center + rng.normal(0, cfg.aim_jitter, 3))
        x, y = pose[0, :3].copy(), pose[1, :3].copy()
        roll = math.radians(rng.normal(0, cfg.roll_deg))
        pose[0, :3], pose[1, :3] = math.cos(roll) * x + math.sin(roll) * y, -math.sin(roll) * x + math.cos(roll) * y
        pose[:3, 3] = -pose[:3, :3] @ centre
        poses.append(pose)
    return poses


def scaled_device(device: Device, scale: float) -> Device:
    """The same scanner with its camera resampled to ``scale`` of the resolution."""
    import dataclasses

    K = device.K.copy()
    K[0, 0] *= scale
    K[1, 1] *= scale
    K[0, 2] = (K[0, 2] + 0.5) * scale - 0.5
    K[1, 2] = (K[1, 2] + 0.5) * scale - 0.5
    return dataclasses.replace(device, K=K, width=max(1, round(device.width * scale)),
                               height=max(1, round(device.height * scale)))


def pixel_rays(device: Device) -> np.ndarray:
    """Unit camera-space ray directions ``(H, W, 3)`` through every pixel centre (undistorted)."""
    K = device.K
    rows, cols = np.meshgrid(np.arange(device.height), np.arange(device.width), indexing="ij")
    xd, yd = (cols - K[0, 2]) / K[0, 0], (rows - K[1, 2]) / K[1, 1]
    k1, k2, p1, p2, k3 = device.distortion
    x, y = xd.copy(), yd.copy()
    if np.any(device.distortion):
        for _ in range(20):  # fixed-point inversion of OpenCV's model
            r2 = x * x + y * y
            radial = 1 + r2 * (k1 + r2 * (k2 + r2 * k3))
            dx = 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
            dy = p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
            x, y = (xd - dx) / radial, (yd - dy) / radial
    d = np.stack([x, y, np.ones_like(x)], -1)
    return d / np.linalg.norm(d, axis=-1, keepdims=True)


class Scene:
    """The object (mesh + maps) on the backdrop, ready to render with one device."""

    def __init__(self, mesh: Mesh, maps: SVBRDFMaps, device: Device, clusters: int = 64, exposure: float = 1.0):
        if mesh.uv is None:
            raise ValueError("mesh has no UVs")
        self.mesh, self.maps, self.device = mesh, maps, device
        self.caster = RayCaster([mesh.triangles, backdrop_triangles()])
        self.cluster_centres, self.cluster_of = emitter_clusters(device, clusters)
        self.pattern = torch.as_tensor(device.pattern, dtype=torch.float64)
        # per cluster: summed effective drive (quadrature-weighted) and mean emitter normal
        pts, w = device.emitter_samples(torch.float64)
        self.emitter_points = pts.numpy()  # (L, Q, 3) camera space, for exact shadows
        p_eff = device.effective_pattern(device.pattern)  # (L, 3)
        C = len(self.cluster_centres)
        drive = np.zeros((C, 3))
        np.add.at(drive, self.cluster_of.reshape(-1), (w.numpy()[..., None] * p_eff[:, None, :]).reshape(-1, 3))
        self.cluster_drive = drive
        normal = device.emitter_normals.mean(0)
        self.cluster_normal = normal / np.linalg.norm(normal)
        self.exposure = exposure * float(device.exposure(device.pattern))
        lo, hi = mesh.vertices.min(0), mesh.vertices.max(0)
        self.center = 0.5 * (lo + hi)

    def render_linear(self, pose: np.ndarray, cam: Device, chunk: int = 512, exact_shadows: bool = False,
                      pixel_subset: np.ndarray | None = None) -> tuple[np.ndarray, dict]:
        """Linear pixel values ``(H, W, 3)`` (exposure applied, before noise and quantisation) and
        per-pixel hit info. ``exact_shadows`` traces one shadow ray per emitter sample."""
        R, tr = pose[:3, :3], pose[:3, 3]
        dirs_cam = pixel_rays(cam).reshape(-1, 3)
        if pixel_subset is not None:
            dirs_cam = dirs_cam[pixel_subset]
        origin = -R.T @ tr
        dirs_w = dirs_cam @ R  # R^T d for each row
        hits = self.caster.intersect(np.broadcast_to(origin, dirs_w.shape), dirs_w)
        out = np.zeros((len(dirs_w), 3))
        obj = np.nonzero(hits.geom == 0)[0]
        back = np.nonzero(hits.geom == 1)[0]
        for s in range(0, len(obj), chunk):
            idx = obj[s:s + chunk]
            out[idx] = self._shade_object(hits, idx, origin, dirs_w, R, tr, exact_shadows)
        if len(back):
            out[back] = self._shade_backdrop(origin + hits.t[back, None] * dirs_w[back], R, tr)
        shape = (cam.height, cam.width, 3) if pixel_subset is None else (len(dirs_w), 3)
        return (self.exposure * out).reshape(shape), {"geom": hits.geom}

    def _shade_object(self, hits, idx, origin, dirs_w, R, tr, exact_shadows) -> np.ndarray:
        faces = self.mesh.faces[hits.prim[idx]]
        u, v = hits.u[idx, None], hits.v[idx, None]
        bary = (1 - u - v, u, v)
        uv = sum(b * self.mesh.uv[faces[:, k]] for k, b in enumerate(bary))
        n_geo = sum(b * self.mesh.normals[faces[:, k]] for k, b in enumerate(bary))
        n_geo /= np.linalg.norm(n_geo, axis=1, keepdims=True)
        x_w = origin + hits.t[idx, None] * dirs_w[idx]
        m = self.maps.sample(uv)
        x_c = x_w @ R.T + tr
        vis = self._visibility(x_w + 2e-5 * n_geo, R, tr, exact_shadows)
        T = lambda a: torch.as_tensor(np.ascontiguousarray(a), dtype=torch.float32)
        B = measurement_rgb(self.device, T(x_c), T(m["normal"] @ R.T), T(m["tangent"] @ R.T), T(m["diffuse_albedo"]),
                            T(m["specular_albedo"]), T(m["roughness"][:, 0]), T(m["roughness"][:, 1]),
                            self.pattern.float(), T(vis))
        return B.double().numpy()

    def _visibility(self, p_w: np.ndarray, R, tr, exact: bool) -> np.ndarray:
        """``(N, L, Q)`` 0/1: emitter sample visible from each point (cluster or exact)."""
        pts = self.emitter_points
        targets = (pts.reshape(-1, 3) if exact else self.cluster_centres) - tr  # camera -> world
        targets_w = targets @ R  # R^T (c - t)
        d = targets_w[None] - p_w[:, None]
        dist = np.linalg.norm(d, axis=-1)
        d /= np.maximum(dist[..., None], 1e-12)
        occ = self.caster.occluded(np.repeat(p_w, len(targets_w), 0), d.reshape(-1, 3),
                                   dist.reshape(-1) - 1e-4).reshape(len(p_w), -1)
        if exact:
            return (~occ).reshape(len(p_w), *pts.shape[:2]).astype(np.float64)
        return (~occ)[:, self.cluster_of].astype(np.float64)

    def _shade_backdrop(self, x_w: np.ndarray, R, tr) -> np.ndarray:
        """Diffuse backdrop lit by the emitter clusters (their summed drive), unshadowed."""
        albedo = marker_albedo(x_w)
        x_c = torch.as_tensor(x_w @ R.T + tr, dtype=torch.float32)
        n_c = torch.as_tensor(R[:, 2], dtype=torch.float32)  # world +z in camera space
        c = torch.as_tensor(self.cluster_centres, dtype=torch.float32)
        nl = torch.as_tensor(self.cluster_normal, dtype=torch.float32)
        r2 = ((c * c).sum(-1)[None] - 2 * x_c @ c.T + (x_c * x_c).sum(-1, keepdim=True)).clamp_min(1e-8)
        inv_r = torch.rsqrt(r2)
        cos_p = ((c @ n_c)[None] - (x_c @ n_c)[:, None]) * inv_r
        cos_l = ((x_c @ nl)[:, None] - (c @ nl)[None]) * inv_r
        psi = self.device.psi(cos_l)
        irr = (cos_p.clamp_min(0) * psi / r2) @ torch.as_tensor(self.cluster_drive, dtype=torch.float32)
        seen = ((-x_c) @ n_c > 0).to(torch.float32)[:, None]
        return albedo[:, None] / math.pi * (irr * seen).double().numpy()

    def photo(self, pose: np.ndarray, cam: Device, cfg: ScanConfig, rng: np.random.Generator,
              blur: bool = False) -> np.ndarray:
        """An 8-bit photo ``(H, W, 3)`` uint8."""
        lin, _ = self.render_linear(pose, cam, cfg.chunk)
        if blur:
            length = max(3, int(round(cfg.blur_px * cfg.scale / 0.25)))
            angle = rng.uniform(0, 180)
            kernel = np.zeros((length, length))
            kernel[length // 2, :] = 1.0
            kernel = ndimage.rotate(kernel, angle, reshape=False, order=1)
            kernel /= kernel.sum()
            lin = np.stack([ndimage.convolve(lin[..., c], kernel, mode="nearest") for c in range(3)], -1)
        lin = lin * (1 + cfg.noise_sigma * rng.standard_normal(lin.shape))
        code = cam.encode(torch.as_tensor(lin)).numpy() + cfg.read_noise * rng.standard_normal(lin.shape)
        return np.clip(np.round(code), 0, 255).astype(np.uint8)


# ------------------------------------------------------------------------------ the command
def load_asset(asset: str | None, mesh_path: Path | None, maps_dir: Path | None) -> tuple[Mesh, SVBRDFMaps, Path]:
    from .demo_asset import DEMO_DIR

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
    return mesh, maps, mesh_path


def virtual_scan(out: Path, asset: str | None = None, mesh_path: Path | None = None, maps_dir: Path | None = None,
                 device_path: Path | None = None, cfg: ScanConfig | None = None, progress: bool = True) -> dict:
    cfg = cfg or ScanConfig()
    mesh, maps, src_mesh = load_asset(asset, mesh_path, maps_dir)
    device = Device.load(device_path)
    cam = scaled_device(device, cfg.scale)
    cam.gain = device.gain * cfg.exposure  # what this capture used: B = pixel / cam.exposure(pattern)
    rng = np.random.default_rng(cfg.seed)
    scene = Scene(mesh, maps, device, cfg.clusters, cfg.exposure)
    poses = trajectory(scene.center, device, cfg, rng)
    n_blur = int(round(cfg.blur_fraction * cfg.views))
    blurred = set(rng.choice(cfg.views, size=n_blur, replace=False).tolist()) if n_blur else set()

    (out / "photos").mkdir(parents=True, exist_ok=True)
    gt = out / "ground_truth"
    gt.mkdir(exist_ok=True)
    names, t0 = [], time.perf_counter()
    for i in tqdm(range(cfg.views), desc="virtual scan", unit="photo", disable=not progress):
        name = f"{i:04d}.png"
        img = scene.photo(poses[i], cam, cfg, rng, blur=i in blurred)
        write_png(out / "photos" / name, img.astype(np.float64) / 255.0)
        names.append(name)
    seconds = time.perf_counter() - t0
    save_obj(out / "mesh.obj", mesh)
    cam.save(out / "device.toml")
    maps.save(gt)
    write_text_atomic(gt / "poses.json", json.dumps({n: p.tolist() for n, p in zip(names, poses)}, indent=1))
    capture = {"config": asdict(cfg), "source_mesh": str(src_mesh), "device": device.name,
               "blurred_photos": sorted(names[i] for i in blurred), "seconds": seconds,
               "seconds_per_photo": seconds / max(cfg.views, 1)}
    write_text_atomic(gt / "capture.json", json.dumps(capture, indent=2))
    write_text_atomic(out / "scan.toml", "\n".join([
        "# written by ntp virtual-scan", 'mesh = "mesh.obj"', 'photos = "photos"', 'device = "device.toml"',
        "# ground truth for evaluation: ground_truth/ (maps, poses.json, capture.json)", ""]))
    return capture


