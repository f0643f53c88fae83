"""The gallery: five objects (``shapes``) painted with labelled materials (``materials``), written as
asset folders the scanners take (``mesh.obj`` + ``ground_truth/`` with the five maps, ``labels.png``
and ``materials.json``).

Which material goes where (regions by object-space position and normal):

- ``dome``: the demo asset's own maps; labels by band: ``tiles`` (diffuse-dominant, rho_s 0.08,
  normal ripple), ``lacquer`` (alpha 0.01..0.25), ``gold`` (brushed, 0.30 x 0.025, swirling tangents).
- ``vase``: matte printed foot, glossy plastic belly, dark brushed metal neck (1:80, circular
  tangents), mirror lacquer lip and stopper.
- ``blob``: rough plastic top, satin with radial tangents on the +x lobe, noisy brushed underside.
- ``box``: mirror lacquer top, dark brushed metal along one direction on the long sides, matte white
  and rough metal on the short sides.
- ``knot``: glossy plastic, noisy brushed metal along the tube, matte white and rough metal (by
  position along the knot).

Assets are deterministic: ``build_asset`` writes the same files every time.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..io.maps import SVBRDFMaps
from ..io.mesh import Mesh, save_obj
from ..io.texels import Texels
from .demo_asset import demo_maps
from .generated import generated_asset, generated_object, is_generated, object_names
from .materials import LIBRARY, Material, label_image, paint, save_labels
from .scanner_mesh import scanner_mesh
from .shapes import SHAPES

MAP_RESOLUTION = 256


@dataclass(frozen=True)
class GalleryObject:
    """One gallery object: its shape, its materials and where each goes (``labeller``)."""

    name: str
    materials: tuple[str, ...]
    labeller: Callable[[Texels], np.ndarray]
    what: str  # what it is there to break


def _height(tex: Texels) -> np.ndarray:
    z = tex.position[:, 2]
    return (z - z.min()) / max(float(z.max() - z.min()), 1e-9)


def _vase(tex: Texels) -> np.ndarray:
    z = tex.position[:, 2]
    return np.select([z < 0.03, z < 0.07, z < 0.09], [0, 1, 2], 3)


def _blob(tex: Texels) -> np.ndarray:
    h, x = _height(tex), tex.position[:, 0]
    return np.select([h < 0.35, x > 0.02], [2, 1], 0)


def _box(tex: Texels) -> np.ndarray:
    n = tex.normal
    top = n[:, 2] > 0.9
    # the box is turned 25 deg: its long sides face +-(sin 25, -cos 25)... pick by the local axes
    turn = np.radians(25.0)
    local_x = n[:, 0] * np.cos(turn) + n[:, 1] * np.sin(turn)
    short_side = np.abs(local_x) > 0.9
    return np.select([top, short_side & (local_x > 0), short_side], [0, 2, 3], 1)


def _knot(tex: Texels) -> np.ndarray:
    # position along the knot: the azimuth of the point about z (the knot winds twice around it)
    s = (np.arctan2(tex.position[:, 1], tex.position[:, 0]) / (2 * np.pi)) % 1.0
    return np.select([s < 0.4, s < 0.7, s < 0.85], [0, 1, 2], 3)


def _dome(tex: Texels) -> np.ndarray:  # the demo's bands by v (demo_asset)
    v = 1.0 - (tex.row + 0.5) / tex.shape[0]
    return np.select([v < 0.30, v < 0.62], [0, 1], 2)


# the demo's bands as labels (descriptive: the dome keeps demo_asset's own maps)
DEMO_MATERIALS = (
    Material("tiles", (0.85, 0.62, 0.40), (0.08, 0.08, 0.08), (0.35, 0.35), texture="checker"),
    Material("lacquer", (0.62, 0.40, 0.36), (1.2, 1.2, 1.2), (0.05, 0.05), texture="blocks"),  # alpha 0.01..0.25
    Material("gold", (0.26, 0.25, 0.28), (4.0, 3.0, 1.6), (0.30, 0.025), tangents="swirl"),
)

GALLERY: dict[str, GalleryObject] = {
    o.name: o
    for o in (
        GalleryObject(
            "dome", tuple(m.name for m in DEMO_MATERIALS), _dome, "the demo: round, bright, nothing faces down"
        ),
        GalleryObject(
            "vase",
            ("matte_print", "plastic_glossy", "metal_brushed_dark", "lacquer_mirror"),
            _vase,
            "near rotational symmetry (azimuth ambiguity), 1:80 dark metal",
        ),
        GalleryObject(
            "blob",
            ("plastic_rough", "satin_radial", "brushed_noisy"),
            _blob,
            "overhangs, concavities, an underside facing down",
        ),
        GalleryObject(
            "box",
            ("lacquer_mirror", "metal_brushed_line", "matte_white", "metal_rough"),
            _box,
            "flat faces, sharp edges, 180 deg symmetry",
        ),
        GalleryObject(
            "knot",
            ("plastic_glossy", "brushed_noisy", "matte_white", "metal_rough"),
            _knot,
            "thin and holed: self-occlusion everywhere",
        ),
    )
}


# the objects constants are chosen on, and the ones that judge them (docs/accuracy.md)
SETS = {"tune": (*GALLERY, *object_names("tune")), "validate": tuple(object_names("validate"))}


def object_set(name: str) -> str:
    """``"tune"`` or ``"validate"``: the set an object belongs to."""
    return "validate" if name in SETS["validate"] else "tune"


def object_materials(name: str) -> list[Material]:
    """The materials of a gallery (or generated) object in label order."""
    if name == "dome":
        return list(DEMO_MATERIALS)
    if is_generated(name):
        return list(generated_object(name).materials)
    return [LIBRARY[m] for m in GALLERY[name].materials]


def object_asset(name: str, resolution: int = MAP_RESOLUTION) -> tuple[Mesh, SVBRDFMaps, np.ndarray]:
    """Mesh, ground-truth maps and label image of a gallery object or a generated one (``sim.generated``)."""
    if is_generated(name):
        return generated_asset(name, resolution)[:3]
    if name not in GALLERY:
        raise KeyError(f"unknown gallery object {name!r} (have {', '.join(GALLERY)} and generated <family>-<seed>)")
    mesh = SHAPES[name]()
    if name == "dome":
        return mesh, demo_maps(resolution), label_image(mesh, _dome, resolution)[2]
    maps, labels = paint(mesh, object_materials(name), GALLERY[name].labeller, resolution)
    return mesh, maps, labels


SCANNER_MESH = "scanner_mesh.obj"  # in an asset folder: the mesh a shape scanner would deliver


def build_asset(name: str, folder: Path, resolution: int = MAP_RESOLUTION) -> Path:
    """Write the asset folder of a gallery or generated object (``mesh.obj``, ``scanner_mesh.obj``:
    the mesh a shape scanner would deliver (``sim.scanner_mesh``; a generated object's on a coarser
    grid of its surface, a gallery object's on its own triangulation, seeded by the name),
    ``ground_truth/``); returns it."""
    if is_generated(name):
        obj = generated_object(name)  # made once: its mesh, maps, materials and the scanner's mesh
        mesh, maps, labels, materials = obj.asset(resolution)
        given = obj.scanner_mesh()
    else:
        mesh, maps, labels = object_asset(name, resolution)
        materials = object_materials(name)
        given = scanner_mesh(mesh, int.from_bytes(name.encode()[:4].ljust(4, b"\0"), "little"))
    gt = folder / "ground_truth"
    gt.mkdir(parents=True, exist_ok=True)
    save_obj(folder / "mesh.obj", mesh)
    save_obj(folder / SCANNER_MESH, given)
    maps.save(gt)
    save_labels(gt, labels, materials)
    return folder
