"""The gallery: five objects, every material present in its labels, deterministic asset folders."""

import hashlib

import numpy as np
import pytest

from ntp_engine.io.maps import SVBRDFMaps
from ntp_engine.sim.gallery import GALLERY, build_asset, object_asset, object_materials
from ntp_engine.sim.materials import load_labels


def test_gallery_has_the_objects_the_issue_names():
    assert set(GALLERY) == {"dome", "vase", "blob", "box", "knot"}


@pytest.mark.parametrize("name", list(GALLERY))
def test_every_material_is_painted_somewhere(name):
    _, maps, labels = object_asset(name, 64)
    counts = np.bincount(labels.reshape(-1), minlength=len(object_materials(name)))
    assert len(counts) == len(object_materials(name)) and (counts > 0.02 * labels.size).all(), counts
    assert maps.shape == (64, 64) and np.isfinite(maps.roughness).all()


def test_dome_keeps_the_demo_maps():
    from ntp_engine.sim.demo_asset import demo_maps

    _, maps, labels = object_asset("dome", 32)
    np.testing.assert_array_equal(maps.roughness, demo_maps(32).roughness)
    assert labels[0, 0] == 2 and labels[-1, 0] == 0  # top row = v near 1 = gold; bottom = tiles


def test_build_asset_is_deterministic(tmp_path):
    a, b = build_asset("box", tmp_path / "a", 32), build_asset("box", tmp_path / "b", 32)
    files = sorted(p.relative_to(a) for p in a.rglob("*") if p.is_file())
    assert {str(f) for f in files} >= {"mesh.obj", "ground_truth/labels.png", "ground_truth/materials.json"}

    def digest(p):
        return hashlib.sha256(p.read_bytes()).hexdigest()

    assert [digest(a / f) for f in files] == [digest(b / f) for f in files]
    SVBRDFMaps.load(a / "ground_truth")
    _, table = load_labels(a / "ground_truth")
    assert [m["name"] for m in table] == [m.name for m in object_materials("box")]


def test_unknown_object():
    with pytest.raises(KeyError, match="unknown gallery object 'teapot'"):
        object_asset("teapot")


def test_the_sets_hold_the_gallery_and_generated_objects():
    from ntp_engine.sim.gallery import SETS, object_set

    assert set(GALLERY) < set(SETS["tune"]) and not set(SETS["tune"]) & set(SETS["validate"])
    assert len(SETS["validate"]) >= 10 and all(object_set(n) == "validate" for n in SETS["validate"])
    assert object_set("vase") == "tune"
    _, maps, labels = object_asset(SETS["validate"][0], 32)  # a generated object is an asset like any other
    assert maps.shape == (32, 32) and labels.max() < len(object_materials(SETS["validate"][0]))


def test_a_generated_objects_asset_folder_is_written_like_the_gallerys(tmp_path):
    folder = build_asset("star-1001", tmp_path / "a", 32)
    _, table = load_labels(folder / "ground_truth")
    assert [m["name"] for m in table] == [m.name for m in object_materials("star-1001")]
    assert [m["kind"] for m in table] == [m.name.rpartition("_")[0] for m in object_materials("star-1001")]
