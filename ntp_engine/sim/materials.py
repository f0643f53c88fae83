"""The gallery's materials: named GGX materials over the paper's ranges, their tangent fields and
textures, and the labelled ground-truth maps of a shape painted with them.

Ranges covered: rho_d 0.02 (dark metal) .. 0.9, rho_s 0 (matte: no lobe at all) .. 10, alpha 0.006
.. 0.5, anisotropy up to 1:80. Textures are procedural in object space (3D cells and value noise,
metres), so they do not depend on the UV layout: ``blocks`` multiplies rho_d by a per-cell factor
(8 mm cells — grey-level texture that structure-from-motion can see), ``noise`` by a smooth factor,
and ``alpha_noise`` makes alpha vary log-uniformly across a factor of two.

Tangent fields (object space, projected into the tangent plane of the normal; where the
projection vanishes the UV tangent dP/du is used): ``uv`` along dP/du, ``circular`` around the
vertical axis through the object's centre, ``radial`` away from the region's centroid,
``direction`` along world (1, 0.3, 0), ``noisy`` dP/du turned by +-25 deg of smooth noise plus
+-8 deg per texel. alpha_x is along the tangent.

Ground truth of a painted shape (``paint``): the five maps, ``labels.png`` (8-bit, value = label of
the material each texel belongs to) and ``materials.json`` (the label table).
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from ..io.atomic import write_text_atomic
from ..io.errors import NtpInputError
from ..io.images import read_image, write_png
from ..io.maps import SVBRDFMaps
from ..io.mesh import Mesh
from ..io.texels import Texels, rasterize

LABELS_FILE, MATERIALS_FILE = "labels.png", "materials.json"
KINDS = ("matte", "near_matte", "plastic", "lacquer", "dark_metal", "aniso_metal")  # ``Material.kind``
DIRECTION = np.array([1.0, 0.3, 0.0]) / math.hypot(1.0, 0.3)


@dataclass(frozen=True)
class Material:
    """One named material: base parameters and how they vary (module docstring)."""

    name: str
    rho_d: tuple[float, float, float]
    rho_s: tuple[float, float, float]  # all zero: matte, no specular lobe
    alpha: tuple[float, float]  # (alpha_x along the tangent, alpha_y)
    tangents: str = "uv"  # uv | circular | radial | direction | noisy
    texture: str = "none"  # none | blocks | noise
    alpha_noise: bool = False

    @property
    def matte(self) -> bool:
        """True when the material has no specular lobe."""
        return max(self.rho_s) == 0.0

    @property
    def anisotropy(self) -> float:
        """Ratio of the larger to the smaller alpha (1 = isotropic)."""
        return max(self.alpha) / min(self.alpha)

    @property
    def kind(self) -> str:
        """Its class by its parameters (``KINDS``), so materials of any object compare: matte (no
        lobe); anisotropic (alpha ratio >= 3); dark metal (rho_d <= 0.06 with a lobe); near-matte
        (rho_s <= 0.5, alpha >= 0.25); lacquer (alpha <= 0.06); else plastic."""
        if self.matte:
            return "matte"
        if self.anisotropy >= 3.0:
            return "aniso_metal"
        if max(self.rho_d) <= 0.06:
            return "dark_metal"
        if max(self.rho_s) <= 0.5 and min(self.alpha) >= 0.25:
            return "near_matte"
        return "lacquer" if max(self.alpha) <= 0.06 else "plastic"


LIBRARY: dict[str, Material] = {
    m.name: m
    for m in (
        Material("matte_white", (0.9, 0.86, 0.8), (0.0, 0.0, 0.0), (0.3, 0.3), texture="blocks"),
        Material("matte_print", (0.9, 0.9, 0.9), (0.0, 0.0, 0.0), (0.3, 0.3), texture="print"),
        Material("plastic_glossy", (0.6, 0.14, 0.09), (1.0, 1.0, 1.0), (0.02, 0.02), texture="noise"),
        Material("plastic_rough", (0.22, 0.5, 0.28), (0.5, 0.5, 0.5), (0.35, 0.35), texture="blocks", alpha_noise=True),
        Material(
            "lacquer_mirror", (0.12, 0.14, 0.4), (2.5, 2.5, 2.5), (0.006, 0.006), texture="blocks", alpha_noise=True
        ),
        Material("metal_brushed_dark", (0.02, 0.02, 0.02), (8.0, 7.0, 6.0), (0.48, 0.006), tangents="circular"),
        Material("metal_brushed_line", (0.02, 0.02, 0.02), (8.0, 7.0, 6.0), (0.48, 0.006), tangents="direction"),
        Material("satin_radial", (0.5, 0.4, 0.3), (3.0, 3.0, 3.0), (0.2, 0.04), tangents="radial", texture="noise"),
        Material("brushed_noisy", (0.15, 0.15, 0.16), (5.0, 5.0, 5.0), (0.25, 0.02), tangents="noisy", texture="noise"),
        Material("metal_rough", (0.05, 0.05, 0.05), (10.0, 9.0, 7.0), (0.5, 0.5)),
    )
}


def _hash3(cells: np.ndarray, salt: int) -> np.ndarray:
    """Uniform [0, 1) per integer cell ``(N, 3)``."""
    h = (cells[:, 0] * 73856093) ^ (cells[:, 1] * 19349663) ^ (cells[:, 2] * 83492791) ^ salt
    h = (h ^ (h >> 13)) * 1274126177
    return ((h ^ (h >> 16)) & 0xFFFF) / 65535.0


def value_noise(p: np.ndarray, cell: float, salt: int) -> np.ndarray:
    """Smooth noise in [0, 1] at points ``p (N, 3)`` (m): trilinear over a lattice of ``cell`` m."""
    q = p / cell
    base = np.floor(q).astype(np.int64)
    f = q - base
    f = f * f * (3 - 2 * f)
    out = np.zeros(len(p))
    for corner in np.ndindex(2, 2, 2):
        c = np.array(corner)
        w = np.prod(np.where(c == 1, f, 1 - f), axis=1)
        out += w * _hash3(base + c, salt)
    return out


def _texture(kind: str, p: np.ndarray) -> np.ndarray:
    """Multiplier of rho_d ``(N,)`` for a texture kind."""
    if kind == "blocks":
        return 0.55 + 0.45 * _hash3(np.floor(p / 0.008).astype(np.int64), 5)
    if kind == "print":  # black "print" on white: rho_d from 0.04 x 0.9 to 0.9
        return np.where(_hash3(np.floor(p / 0.006).astype(np.int64), 11) < 0.35, 0.045, 1.0)
    if kind == "noise":
        return 0.6 + 0.4 * value_noise(p, 0.012, 3)
    return np.ones(len(p))


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-12)


def _tangent_field(kind: str, tex: Texels, sel: np.ndarray, centre: np.ndarray) -> np.ndarray:
    """Unit tangents ``(M, 3)`` of the ``sel`` texels, orthogonal to their normals."""
    p, n, t_uv = tex.position[sel], tex.normal[sel], tex.tangent[sel]
    if kind == "circular":
        d = np.cross([0.0, 0.0, 1.0], p - centre)
    elif kind == "radial":
        d = p - p.mean(0)
    elif kind == "direction":
        d = np.broadcast_to(DIRECTION, p.shape).copy()
    elif kind == "noisy":
        b = np.cross(n, t_uv)
        turn = np.radians(
            50 * (value_noise(p, 0.01, 7) - 0.5) + 16 * (_hash3(np.floor(p / 0.001).astype(np.int64), 9) - 0.5)
        )
        d = np.cos(turn)[:, None] * t_uv + np.sin(turn)[:, None] * b
    else:
        d = t_uv.copy()
    d = d - (d * n).sum(-1, keepdims=True) * n
    weak = np.linalg.norm(d, axis=-1) < 1e-3 * max(float(np.abs(d).max()), 1e-12)
    d[weak] = t_uv[weak]
    return _unit(d)


Painter = Callable[[Texels], np.ndarray]  # texels -> label per texel (index into the material list)


def label_image(mesh: Mesh, labeller: Painter, resolution: int) -> tuple[Texels, np.ndarray, np.ndarray]:
    """The texels of a ``resolution``^2 map, their labels ``(T,)`` and the label image ``(H, W)``
    uint8 (uncovered texels take the nearest label)."""
    tex = rasterize(mesh, (resolution, resolution))
    label = labeller(tex)
    return tex, label, np.rint(tex.image(label[:, None].astype(np.float64))[..., 0]).astype(np.uint8)


def paint(mesh: Mesh, materials: list[Material], labeller: Painter, resolution: int) -> tuple[SVBRDFMaps, np.ndarray]:
    """Ground-truth maps ``resolution``^2 of ``mesh`` painted with ``materials`` where ``labeller``
    puts them, and the label image (``label_image``)."""
    tex, label, labels = label_image(mesh, labeller, resolution)
    centre = 0.5 * (mesh.vertices.min(0) + mesh.vertices.max(0))
    N = len(tex)
    rho_d, rho_s, alpha = np.zeros((N, 3)), np.zeros((N, 3)), np.zeros((N, 2))
    tangent = tex.tangent.copy()
    for k, m in enumerate(materials):
        sel = label == k
        if not sel.any():
            continue
        p = tex.position[sel]
        rho_d[sel] = np.clip(np.array(m.rho_d) * _texture(m.texture, p)[:, None], 0.0, 1.0)
        rho_s[sel] = m.rho_s
        a = np.array(m.alpha)[None].repeat(len(p), 0)
        if m.alpha_noise:
            a = a * 2.0 ** (value_noise(p, 0.015, 13) - 0.5)[:, None]
        alpha[sel] = np.clip(a, 0.006, 0.5)
        tangent[sel] = _tangent_field(m.tangents, tex, sel, centre)
    maps = SVBRDFMaps(
        tex.image(rho_d),
        tex.image(rho_s),
        _unit(tex.image(tex.normal)),
        _unit(tex.image(tangent)),
        tex.image(alpha),
    )
    return maps, labels


def save_labels(folder: Path, labels: np.ndarray, materials: list[Material]) -> None:
    """``labels.png`` and ``materials.json`` (the label table) into ``folder``."""
    write_png(folder / LABELS_FILE, labels.astype(np.float64) / 255.0)
    table = [
        {"label": k, **asdict(m), "matte": m.matte, "anisotropy": m.anisotropy, "kind": m.kind}
        for k, m in enumerate(materials)
    ]
    write_text_atomic(folder / MATERIALS_FILE, json.dumps({"materials": table}, indent=1))


def load_labels(folder: Path) -> tuple[np.ndarray, list[dict]]:
    """The label image ``(H, W)`` int and the label table of a ground-truth folder."""
    path, table = folder / LABELS_FILE, folder / MATERIALS_FILE
    for f in (path, table):
        if not f.is_file():
            raise NtpInputError(f, "ground truth has no material labels (gallery assets have them)")
    labels = np.rint(read_image(path)[..., 0] * 255.0).astype(np.int64)
    materials = json.loads(table.read_text())["materials"]
    if labels.max() >= len(materials):
        raise NtpInputError(path, f"label {labels.max()} is not in {MATERIALS_FILE} ({len(materials)} materials)")
    return labels, materials
