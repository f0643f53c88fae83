"""Generated objects: seeded families of shapes and random material layouts that no constant was
chosen on — the validation set's objects (docs/accuracy.md: tune on one set, judge on another).

An object is named ``<family>-<seed>``; the name alone makes it (``generated_asset``), the same on
every machine. Families, each for what it breaks:

- ``revolution``: a surface of revolution with a random profile (bulges, necks, a closed top) and a
  small random out-of-roundness: near-symmetric, like the gallery's vase but not tuned on it.
- ``star``: a star-shaped body, its radius a random sum of low harmonics with bumps and dents:
  overhangs, concavities, an underside facing down.
- ``extrusion``: a polygon (3-8 sides, random radii) extruded and capped, its edges bevelled by
  0.5-3 mm: flat faces, sharp edges, corners.
- ``torus``: a ring or a (p, q) torus knot swept by a thin tube: thin, holed, self-occluding.
- ``relief``: an ellipsoidal cap with fine relief (0.2-0.8 mm bumps, 2-6 mm across): normals that
  vary faster than a scanner's mesh follows.

Sizes: 6-14 cm across, within the scanner's 15 cm valid volume; every object stands on z = 0,
centred in x, y, turned by a random yaw. UVs: (u, v) of each parametric grid.

Materials (``random_material``) are drawn per class (``materials.KINDS``; the classes' ranges are
disjoint, so a drawn material's ``Material.kind`` is its class) over the paper's ranges (alpha
log-uniform in [0.006, 0.5]; Appendix): matte; near-matte weak lobes (rho_s 0.1-0.5, alpha
0.3-0.5); plastics (rho_s 0.6-1.5, alpha 0.07-0.3); lacquers (rho_s 1-3, alpha 0.01-0.05); dark
metals (rho_d <= 0.05, rho_s 3-10, alpha 0.05-0.5); anisotropic metals up to 1:80 with tangent
fields that vary (circular, along a direction, noisy). Each object has 2-4 regions, a Voronoi
partition of its surface by random sites; albedo is textured so SfM finds features, except on
plain objects (15%).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from ..io.maps import SVBRDFMaps
from ..io.mesh import Mesh
from ..io.texels import Texels
from .materials import KINDS, Material, paint, value_noise
from .scanner_mesh import NOISE_M, scanner_mesh
from .shapes import SurfaceFn, grid_mesh

FAMILIES = ("revolution", "star", "extrusion", "torus", "relief")
# the two sets: seeds of the tuning set's generated objects and of the validation set (never used
# to choose a constant); each seed's family is FAMILIES[seed % 5], so both sets hold every family
TUNE_SEEDS = tuple(range(5))
VALIDATE_SEEDS = tuple(range(1000, 1012))
ALPHA_RANGE = (0.006, 0.5)  # the paper's roughness range (log-uniform in its training data)
COARSE = 0.6  # the scanner's mesh: the surface on a grid of this fraction of the true one's, each way
Grid = tuple[SurfaceFn, int, int]  # a parametric surface and its grid (n_u, n_v)


@dataclass(frozen=True)
class GeneratedObject:
    """A generated object: its mesh, its materials in label order and its Voronoi sites (m)."""

    name: str
    mesh: Mesh
    materials: tuple[Material, ...]
    sites: np.ndarray  # (K, 3) one per region; region k has material k % len(materials)
    plain: bool  # albedo without texture: SfM has little to hold on to
    coarse: Mesh  # the same surface on a coarser grid, placed as ``mesh`` (the scanner's triangulation)
    seed: int

    def asset(self, resolution: int) -> tuple[Mesh, SVBRDFMaps, np.ndarray, list[Material]]:
        """Mesh, ground-truth maps ``resolution``^2, label image and materials."""
        maps, labels = paint(
            self.mesh,
            list(self.materials),
            lambda tex: voronoi_labels(self.sites, len(self.materials), tex),
            resolution,
        )
        return self.mesh, maps, labels, list(self.materials)

    def scanner_mesh(self, noise_m: float = NOISE_M) -> Mesh:
        """The mesh a shape scanner would deliver (``sim.scanner_mesh``): coarser, smoothed, noisy."""
        return scanner_mesh(self.mesh, self.seed, noise_m, coarse=self.coarse)


def family_of(seed: int) -> str:
    """The family of a generated object's seed."""
    return FAMILIES[seed % len(FAMILIES)]


def object_names(which: str) -> list[str]:
    """The generated objects of the ``"tune"`` or ``"validate"`` set."""
    if which not in ("tune", "validate"):
        raise ValueError(f"unknown set {which!r} (tune or validate)")
    return [f"{family_of(s)}-{s}" for s in (TUNE_SEEDS if which == "tune" else VALIDATE_SEEDS)]


def is_generated(name: str) -> bool:
    """Whether ``name`` names a generated object (``<family>-<seed>``)."""
    family, _, seed = name.rpartition("-")
    return family in FAMILIES and seed.isdigit() and family_of(int(seed)) == family


def _log_uniform(rng: np.random.Generator, lo: float, hi: float) -> float:
    return float(np.exp(rng.uniform(np.log(lo), np.log(hi))))


def _placement(mesh: Mesh, yaw: float) -> Callable[[Mesh], Mesh]:
    """The move that turns ``mesh`` by ``yaw`` about z and stands it on z = 0, centred in x, y — as a
    function, so a mesh of the same surface is placed exactly alike."""
    c, s = math.cos(yaw), math.sin(yaw)
    turn = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    v = mesh.vertices @ turn.T
    lo, hi = v.min(0), v.max(0)
    shift = np.array([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, lo[2]])

    def place(m: Mesh) -> Mesh:
        return Mesh(m.vertices @ turn.T - shift, m.faces, m.uv, m.normals @ turn.T)

    return place


def revolution_mesh(rng: np.random.Generator) -> Grid:
    """A random profile revolved about z: 4-6 radii (1.2-5 cm) over a height of 6-13 cm, closed at the top."""
    height = rng.uniform(0.06, 0.13)
    k = int(rng.integers(4, 7))
    z_k = np.concatenate([[0.0], np.sort(rng.uniform(0.1, 0.9, k - 2)), [0.97]]) * height
    r_k = rng.uniform(0.012, 0.05, k)
    z_k, r_k = np.append(z_k, height), np.append(r_k, 0.0)  # the top closes
    lobes, ellipticity = int(rng.integers(2, 4)), rng.uniform(0.0, 0.08)

    def surface(u, v):
        phi = 2 * math.pi * u
        z = np.interp(v, np.linspace(0, 1, len(z_k)), z_k)
        r = np.interp(z, z_k, r_k) * (1 + ellipticity * np.cos(lobes * phi))
        return np.stack([r * np.cos(phi), r * np.sin(phi), z], -1)

    return surface, 128, 64


def star_mesh(rng: np.random.Generator) -> Grid:
    """A star-shaped body of radius 3-5 cm times (1 + random harmonics + bumps - dents)."""
    radius = rng.uniform(0.03, 0.05)
    terms = [
        (int(rng.integers(1, 5)), int(rng.integers(0, 4)), rng.uniform(-0.15, 0.15), rng.uniform(0, 6.3))
        for _ in range(4)
    ]
    blobs = [
        (rng.uniform(0, 2 * math.pi), rng.uniform(0.5, 2.6), rng.uniform(-0.2, 0.15), rng.uniform(0.05, 0.2))
        for _ in range(3)
    ]
    squash = rng.uniform(0.7, 1.0, 3)

    def surface(u, v):
        phi, theta = 2 * math.pi * u, math.pi * v
        k = np.ones_like(phi)
        for m, n, a, ph in terms:
            k = k + a * np.sin(theta) ** 2 * np.cos(m * phi + ph) * np.cos(n * theta)
        for p0, t0, a, w in blobs:
            dphi = np.angle(np.exp(1j * (phi - p0)))
            k = k + a * np.exp(-(dphi**2 + (theta - t0) ** 2) / w)
        d = np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), -np.cos(theta)], -1)
        return (radius * np.clip(k, 0.4, None))[..., None] * d * squash

    return surface, 128, 64


def extrusion_mesh(rng: np.random.Generator) -> Grid:
    """A 3-8-sided polygon (radius 3-6 cm at each corner) extruded 3-9 cm high and capped; the top
    edge bevelled by 0.5-3 mm (u along the outline, v up the wall, over the bevel, across the cap)."""
    sides = int(rng.integers(3, 9))
    corners = rng.uniform(0.03, 0.06, sides)
    height, bevel = rng.uniform(0.03, 0.09), rng.uniform(0.0005, 0.003)
    angle = np.linspace(0, 2 * math.pi, sides, endpoint=False) + rng.uniform(0, 0.4, sides)
    outline = np.stack([corners * np.cos(angle), corners * np.sin(angle)], -1)

    def boundary(u):  # the polygon's outline at u in [0, 1], corner to corner
        t = u * sides
        i = np.floor(t).astype(int) % sides
        f = (t - np.floor(t))[..., None]
        return outline[i] * (1 - f) + outline[(i + 1) % sides] * f

    def surface(u, v):
        b = boundary(u)
        # v: 0-0.6 the wall, 0.6-0.7 the bevel (a quarter circle), 0.7-1 the cap to the centre
        wall = np.clip(v / 0.6, 0, 1)
        arc = np.clip((v - 0.6) / 0.1, 0, 1) * (math.pi / 2)
        cap = np.clip((v - 0.7) / 0.3, 0, 1)
        r = np.linalg.norm(b, axis=-1, keepdims=True)
        inward = -b / r
        xy = b + inward * bevel * (1 - np.cos(arc))[..., None] + inward * (r - bevel) * cap[..., None]
        z = (height - bevel) * wall + bevel * np.sin(arc)
        return np.concatenate([xy, z[..., None]], -1)

    return surface, 32 * sides, 80


def torus_mesh(rng: np.random.Generator) -> Grid:
    """A ring or a (p, q) torus knot (ring 2.5-4 cm, tube 5-10 mm, thinner where a knot's strands come close)."""
    p, q = [(1, 0), (2, 3), (3, 2), (2, 5)][int(rng.integers(0, 4))]
    ring, wind = rng.uniform(0.025, 0.04), rng.uniform(0.01, 0.015)
    tube = rng.uniform(0.005, 0.01)
    if q == 0:
        wind = 0.0

    def curve(s):
        rr = ring + wind * np.cos(q * s)
        return np.stack([rr * np.cos(p * s), rr * np.sin(p * s), wind * np.sin(q * s) + tube + 0.01 * (q == 0)], -1)

    if q:  # a knot's strands must not touch: the tube at most 0.45 of their closest approach
        tube = min(tube, 0.45 * _closest_strands(curve(np.linspace(0, 2 * math.pi, 720, endpoint=False)), tube))

    def surface(u, v):
        s, a = 2 * math.pi * u, -2 * math.pi * v
        eps = 1e-4
        c = curve(s)
        t = curve(s + eps) - curve(s - eps)
        t /= np.linalg.norm(t, axis=-1, keepdims=True)
        up = np.broadcast_to([0.0, 0.0, 1.0], t.shape)
        nrm = np.cross(t, up) if q == 0 else curve(s + eps) - 2 * c + curve(s - eps)
        nrm = nrm - (nrm * t).sum(-1, keepdims=True) * t
        nrm /= np.linalg.norm(nrm, axis=-1, keepdims=True)
        bi = np.cross(t, nrm)
        return c + tube * (np.cos(a)[..., None] * nrm + np.sin(a)[..., None] * bi)

    return surface, 384 * max(p, 1), 24


def _closest_strands(points: np.ndarray, tube: float) -> float:
    """The smallest distance between points of a closed curve ``(N, 3)`` more than ``4 tube`` apart along it."""
    seg = np.linalg.norm(np.roll(points, -1, 0) - points, axis=1)
    arc = np.concatenate([[0.0], np.cumsum(seg)[:-1]])
    along = np.abs(arc[:, None] - arc[None])
    along = np.minimum(along, seg.sum() - along)
    apart = np.linalg.norm(points[:, None] - points[None], axis=-1)
    return float(apart[along > 4 * tube].min())


def relief_mesh(rng: np.random.Generator) -> Grid:
    """An ellipsoidal cap (4-6 cm radius, 3-6 cm high) with fine relief: value noise of 2-6 mm
    cells, 0.2-0.8 mm deep, along the normal."""
    a, b, h = rng.uniform(0.04, 0.06), rng.uniform(0.04, 0.06), rng.uniform(0.03, 0.06)
    cell, depth, salt = rng.uniform(0.002, 0.006), rng.uniform(0.0002, 0.0008), int(rng.integers(0, 1 << 20))

    def surface(u, v):
        phi, theta = 2 * math.pi * u, 0.5 * math.pi * (1 - v)  # v = 1 at the top
        n = np.stack([np.sin(theta) * np.cos(phi) / a, np.sin(theta) * np.sin(phi) / b, np.cos(theta) / h], -1)
        n /= np.linalg.norm(n, axis=-1, keepdims=True)
        p = np.stack([a * np.sin(theta) * np.cos(phi), b * np.sin(theta) * np.sin(phi), h * np.cos(theta)], -1)
        bump = value_noise(p.reshape(-1, 3), cell, salt).reshape(p.shape[:-1]) - 0.5
        return p + (depth * bump * np.sin(theta) ** 0.5)[..., None] * n  # the rim stays on the ground

    return surface, 256, 96


MESHES = {
    "revolution": revolution_mesh,
    "star": star_mesh,
    "extrusion": extrusion_mesh,
    "torus": torus_mesh,
    "relief": relief_mesh,
}


def _material(name: str, rho_d, rho_s, alpha, **kind) -> Material:
    """A ``Material`` of plain Python floats (what a JSON table of it holds)."""
    d, s, a = (tuple(float(x) for x in v) for v in (rho_d, rho_s, alpha))
    return Material(name, (d[0], d[1], d[2]), (s[0], s[1], s[2]), (a[0], a[1]), **kind)


def random_material(rng: np.random.Generator, kind: str, name: str, plain: bool) -> Material:
    """A material of class ``kind`` (``materials.KINDS``) drawn over its range (module docstring);
    its ``Material.kind`` is ``kind``."""
    hue = rng.dirichlet([4.0, 4.0, 4.0]) * 3  # a colour around grey
    texture = "none" if plain else str(rng.choice(["blocks", "noise", "print"]))
    if kind == "matte":
        return _material(
            name, tuple(np.clip(rng.uniform(0.15, 0.9) * hue, 0.02, 0.95)), (0.0, 0.0, 0.0), (0.3, 0.3), texture=texture
        )
    if kind == "near_matte":
        rs = rng.uniform(0.1, 0.5)
        a = _log_uniform(rng, 0.3, 0.5)
        return _material(
            name, tuple(np.clip(rng.uniform(0.2, 0.8) * hue, 0.02, 0.95)), (rs, rs, rs), (a, a), texture=texture
        )
    if kind == "plastic":
        rs, a = rng.uniform(0.6, 1.5), _log_uniform(rng, 0.07, 0.3)
        return _material(
            name,
            tuple(np.clip(rng.uniform(0.1, 0.7) * hue, 0.02, 0.95)),
            (rs, rs, rs),
            (a, a),
            texture=texture,
            alpha_noise=bool(rng.random() < 0.5),
        )
    if kind == "lacquer":
        rs, a = rng.uniform(1.0, 3.0), _log_uniform(rng, 0.01, 0.05)
        return _material(
            name, tuple(np.clip(rng.uniform(0.08, 0.5) * hue, 0.02, 0.95)), (rs, rs, rs), (a, a), texture=texture
        )
    tint = rng.uniform(3.0, 10.0) * rng.dirichlet([6.0, 6.0, 6.0]) * 3
    rho_d = tuple(np.full(3, rng.uniform(0.01, 0.05)))
    if kind == "dark_metal":
        a = _log_uniform(rng, 0.05, 0.5)
        return _material(name, rho_d, tuple(tint), (a, a))
    if kind == "aniso_metal":
        ax = _log_uniform(rng, 0.1, 0.5)
        ratio = _log_uniform(rng, 4.0, 80.0)
        tangents = str(rng.choice(["circular", "direction", "noisy"]))
        return _material(name, rho_d, tuple(tint), (ax, max(ax / ratio, ALPHA_RANGE[0])), tangents=tangents)
    raise ValueError(f"unknown material class {kind!r}")


def _surface_points(mesh: Mesh, count: int, rng: np.random.Generator) -> np.ndarray:
    """``count`` points uniformly over the mesh's area ``(count, 3)``."""
    tri = mesh.triangles
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    face = rng.choice(len(tri), count, p=area / area.sum())
    w = rng.dirichlet([1.0, 1.0, 1.0], count)
    return np.einsum("nk,nkc->nc", w, tri[face])


def generated_object(name: str) -> GeneratedObject:
    """The generated object ``name`` (``<family>-<seed>``): the same for the same name everywhere."""
    if not is_generated(name):
        raise KeyError(f"{name!r} is not a generated object (<family>-<seed>, family {', '.join(FAMILIES)})")
    seed = int(name.rpartition("-")[2])
    rng = np.random.default_rng([71, seed])  # 71: this generator's own stream
    surface, n_u, n_v = MESHES[family_of(seed)](rng)
    true = grid_mesh(surface, n_u, n_v)
    place = _placement(true, rng.uniform(0, 2 * math.pi))
    mesh = place(true)
    coarse = place(grid_mesh(surface, max(round(COARSE * n_u), 8), max(round(COARSE * n_v), 4)))
    plain = bool(rng.random() < 0.15)
    count = int(rng.integers(2, 5))
    kinds = rng.choice(KINDS, count, replace=False)
    materials = tuple(random_material(rng, str(k), f"{k}_{i}", plain) for i, k in enumerate(kinds))
    sites = _surface_points(mesh, int(rng.integers(count, 2 * count + 1)), rng)
    return GeneratedObject(name, mesh, materials, sites, plain, coarse, seed)


def voronoi_labels(sites: np.ndarray, materials: int, tex: Texels) -> np.ndarray:
    """Each texel's material: that of its nearest site (site k has material k % ``materials``)."""
    d = np.linalg.norm(tex.position[:, None, :] - sites[None], axis=-1)
    return np.argmin(d, axis=1) % materials


def generated_asset(name: str, resolution: int) -> tuple[Mesh, SVBRDFMaps, np.ndarray, list[Material]]:
    """``GeneratedObject.asset`` of the generated object ``name``."""
    return generated_object(name).asset(resolution)
