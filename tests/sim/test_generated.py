"""Generated objects: deterministic by name, every family in both sets, sized for the scanner,
outward-facing, their materials of the class they were drawn as, over the paper's ranges."""

import numpy as np
import pytest

from ntp_engine.sim.generated import (
    ALPHA_RANGE,
    FAMILIES,
    family_of,
    generated_asset,
    generated_object,
    is_generated,
    object_names,
    random_material,
    voronoi_labels,
)
from ntp_engine.sim.materials import KINDS

ALL = object_names("tune") + object_names("validate")


def test_the_sets_are_disjoint_and_each_holds_every_family():
    tune, validate = object_names("tune"), object_names("validate")
    assert not set(tune) & set(validate) and len(validate) >= 10
    for names in (tune, validate):
        assert {n.rpartition("-")[0] for n in names} == set(FAMILIES)
    with pytest.raises(ValueError, match="unknown set"):
        object_names("test")


def test_names_say_what_is_generated():
    assert is_generated("star-1") and is_generated(f"{family_of(1003)}-1003")
    assert not is_generated("star-2") and not is_generated("vase") and not is_generated("star-x")
    with pytest.raises(KeyError, match="not a generated object"):
        generated_object("vase")


@pytest.mark.parametrize("name", ALL)
def test_every_object_fits_the_scanner_stands_on_the_ground_and_faces_out(name):
    mesh = generated_object(name).mesh
    v = mesh.vertices
    extent = v.max(0) - v.min(0)
    assert np.isfinite(v).all() and 0.04 < extent.max() <= 0.15, extent  # the valid volume is 15 cm
    assert abs(v[:, 2].min()) < 1e-12 and np.abs(v[:, :2].max(0) + v[:, :2].min(0)).max() < 1e-9
    tri = mesh.triangles
    volume = np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])).sum() / 6
    assert volume > 0  # outward normals (the open base closes on the ground)
    assert mesh.uv is not None and mesh.uv.min() >= 0 and mesh.uv.max() <= 1


def test_the_same_name_makes_the_same_object():
    a, b = generated_object("extrusion-1002"), generated_object("extrusion-1002")
    np.testing.assert_array_equal(a.mesh.vertices, b.mesh.vertices)
    assert a.materials == b.materials and np.array_equal(a.sites, b.sites)
    other = generated_object("extrusion-1007")
    assert other.materials != a.materials and other.mesh.vertices.shape != a.mesh.vertices.shape


def test_drawn_materials_are_of_their_class_and_span_the_papers_ranges():
    rng = np.random.default_rng(1)
    drawn = [(k, random_material(rng, k, k, plain=False)) for k in KINDS for _ in range(300)]
    assert all(m.kind == k for k, m in drawn)
    alphas = np.array([a for _, m in drawn for a in m.alpha])
    assert alphas.min() >= ALPHA_RANGE[0] and alphas.max() <= ALPHA_RANGE[1]
    aniso = [m.anisotropy for k, m in drawn if k == "aniso_metal"]
    assert min(aniso) >= 3 and max(aniso) > 40  # up to 1:80
    lacquer = [min(m.alpha) for k, m in drawn if k == "lacquer"]
    assert min(lacquer) < 0.012  # down to alpha 0.01
    assert {m.tangents for k, m in drawn if k == "aniso_metal"} == {"circular", "direction", "noisy"}
    with pytest.raises(ValueError, match="unknown material class"):
        random_material(rng, "velvet", "v", plain=False)


def test_regions_are_the_nearest_sites_and_every_material_is_painted():
    mesh, maps, labels, materials = generated_asset("star-1001", 64)
    counts = np.bincount(labels.reshape(-1), minlength=len(materials))
    assert len(counts) == len(materials) and (counts > 0).all(), counts
    assert maps.shape == (64, 64) and np.isfinite(maps.roughness).all()
    assert maps.roughness.min() >= ALPHA_RANGE[0] - 1e-6 and maps.roughness.max() <= ALPHA_RANGE[1] + 1e-6

    class Tex:
        position = np.array([[0.0, 0, 0], [1.0, 0, 0], [0.0, 2, 0]])

    sites = np.array([[0.9, 0, 0], [0.0, 0, 0.1], [0.0, 1.9, 0]])
    assert voronoi_labels(sites, 2, Tex()).tolist() == [1, 0, 0]  # site 2 has material 2 % 2 = 0
