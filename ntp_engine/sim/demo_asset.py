"""The bundled demo asset: a dome with UVs and spatially varying ground-truth GGX maps.

Shape: a dome standing on z = 0 — half an ellipsoid (height 7.5 cm) whose radius varies with the
azimuth, r = 5 cm * k(phi), k = 1 + 0.12 cos phi + 0.07 sin 2 phi - 0.05 cos 3 phi (no rotational
symmetry, so the photos' registration to the mesh is unambiguous). Every surface normal has
n_z >= 0, so a scanner moving over the upper hemisphere can observe all of it. UVs: u = azimuth
/ 2 pi, v = elevation / (pi / 2). Material bands (by v), chosen to exercise the whole model:

- v < 0.30, *glazed tiles*: diffuse-dominant (two alternating colours of different brightness,
  rho_s 0.08, alpha 0.35),
  with a normal-map ripple (shading normal up to ~12 deg off the geometric one);
- 0.30 <= v < 0.62, *lacquer*: glossy isotropic, alpha log-spaced from 0.01 to 0.25 around the
  circumference, over a printed block pattern (diffuse albedo x 0.72..1.38 in 64 x 16 cells);
- v >= 0.62, *brushed gold*: strongly anisotropic (alpha_x 0.30, alpha_y 0.025), tangent direction
  swirling with height and azimuth.

All albedo channels are >= 0.25 so every channel of a lit pixel can pass the [32, 224] test. The
object carries grey-level texture (tiles of different brightness, the printed blocks) because
structure-from-motion sees in grey: like the paper's real objects, an untextured one would leave
SfM nothing on the object to align to the mesh.
``ntp_engine.sim.demo_asset.build(folder)`` rewrites ``assets/demo`` deterministically.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from ..io.assets import DEMO_DIR
from ..io.maps import SVBRDFMaps, texel_uv
from ..io.mesh import Mesh, save_obj, smooth_normals

RADIUS, HEIGHT = 0.05, 0.075


def _radius_factor(phi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """k(phi) and dk/dphi of the asymmetric base outline."""
    k = 1 + 0.12 * np.cos(phi) + 0.07 * np.sin(2 * phi) - 0.05 * np.cos(3 * phi)
    dk = -0.12 * np.sin(phi) + 0.14 * np.cos(2 * phi) + 0.15 * np.sin(3 * phi)
    return k, dk


def _surface(phi: np.ndarray, theta: np.ndarray):
    """Point, outward unit normal and unit dP/dphi tangent at (azimuth, elevation)."""
    k, dk = _radius_factor(phi)
    c, s = np.cos(theta), np.sin(theta)
    p = np.stack([RADIUS * k * c * np.cos(phi), RADIUS * k * c * np.sin(phi), HEIGHT * s], -1)
    # dP/dphi / cos(theta) (the cos cancels in the normal, keeping it defined at the pole)
    d_phi = np.stack(
        [
            RADIUS * (dk * np.cos(phi) - k * np.sin(phi)),
            RADIUS * (dk * np.sin(phi) + k * np.cos(phi)),
            np.zeros_like(phi),
        ],
        -1,
    )
    d_theta = np.stack([-RADIUS * k * s * np.cos(phi), -RADIUS * k * s * np.sin(phi), HEIGHT * c], -1)
    n = np.cross(d_phi, d_theta)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    t = d_phi / np.linalg.norm(d_phi, axis=-1, keepdims=True)
    return p, n, t


def dome_mesh(n_phi: int = 128, n_theta: int = 48) -> Mesh:
    """The dome as a grid of ``n_phi`` x ``n_theta`` quads (two triangles each) with its UVs."""
    u = np.linspace(0, 1, n_phi + 1)
    v = np.linspace(0, 1, n_theta + 1)
    vv, uu = np.meshgrid(v, u, indexing="ij")  # (n_theta + 1, n_phi + 1)
    p, _, _ = _surface(2 * math.pi * uu, 0.5 * math.pi * vv)
    idx = np.arange((n_theta + 1) * (n_phi + 1)).reshape(n_theta + 1, n_phi + 1)
    a, b, c, d = idx[:-1, :-1], idx[:-1, 1:], idx[1:, 1:], idx[1:, :-1]
    faces = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)])
    vertices = p.reshape(-1, 3)
    return Mesh(vertices, faces, np.stack([uu, vv], -1).reshape(-1, 2), smooth_normals(vertices, faces))


def _rotate_about(t: np.ndarray, n: np.ndarray, angle: np.ndarray) -> np.ndarray:
    b = np.cross(n, t)
    return np.cos(angle)[..., None] * t + np.sin(angle)[..., None] * b


def demo_maps(res: int = 256) -> SVBRDFMaps:
    """The ground-truth maps at ``res``^2 (the bands and patterns of the module docstring)."""
    uv = texel_uv((res, res))
    u, v = uv[..., 0], uv[..., 1]
    phi, theta = 2 * math.pi * u, 0.5 * math.pi * v
    _, n_geo, t_geo = _surface(phi, theta)
    tiles, lacquer, gold = v < 0.30, (v >= 0.30) & (v < 0.62), v >= 0.62

    checker = ((np.floor(u * 16) + np.floor(v / 0.30 * 3)) % 2 == 0)[..., None]
    rho_d = np.where(checker, [0.85, 0.62, 0.40], [0.26, 0.34, 0.62])
    # a printed, non-repeating block pattern on the lacquer (SfM needs grey-level texture on the object)
    blocks = np.random.default_rng(7).uniform(0.72, 1.38, (64, 16))
    mottle = blocks[np.minimum((u * 64).astype(int), 63), np.minimum((v * 16).astype(int), 15)][..., None]
    rho_d = np.where(lacquer[..., None], mottle * np.array([0.62, 0.40, 0.36]), rho_d)
    rho_d = np.where(gold[..., None], [0.26, 0.25, 0.28], rho_d)
    rho_s = np.where(tiles[..., None], [0.08, 0.08, 0.08], [1.2, 1.2, 1.2])
    rho_s = np.where(gold[..., None], [4.0, 3.0, 1.6], rho_s)

    alpha_iso = np.exp(math.log(0.01) + (math.log(0.25) - math.log(0.01)) * u)
    ax = np.where(tiles, 0.35, np.where(lacquer, alpha_iso, 0.30))
    ay = np.where(tiles, 0.35, np.where(lacquer, alpha_iso, 0.025))

    # tiles: a ripple height field h(phi, v) tilts the shading normal (object space)
    ripple = 0.2 * np.sin(12 * phi) * np.sin(math.pi * np.clip(v / 0.30, 0, 1))
    b_geo = np.cross(n_geo, t_geo)
    n = n_geo + np.where(tiles[..., None], ripple[..., None] * t_geo + 0.5 * ripple[..., None] * b_geo, 0.0)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    swirl = np.where(gold, 3.0 * math.pi * (v - 0.62) + 0.6 * np.sin(3 * phi), 0.0)
    t = _rotate_about(t_geo, n_geo, swirl)
    t = t - (t * n).sum(-1, keepdims=True) * n
    t /= np.linalg.norm(t, axis=-1, keepdims=True)
    return SVBRDFMaps(rho_d.astype(np.float64), rho_s.astype(np.float64), n, t, np.stack([ax, ay], -1))


def build(folder: str | Path = DEMO_DIR, res: int = 256) -> None:
    """Write ``mesh.obj`` and ``ground_truth/`` of the demo asset into ``folder``."""
    folder = Path(folder)
    save_obj(folder / "mesh.obj", dome_mesh())
    demo_maps(res).save(folder / "ground_truth")
