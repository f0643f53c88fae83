"""The virtual scanner: renders agree with the physics core; scans are complete and reproducible."""

import hashlib
import json

import numpy as np
import pytest
from scans import flat_patch, run_virtual_scan, uniform_maps

from ntp_engine.io.images import read_image
from ntp_engine.io.mesh import Mesh, save_obj
from ntp_engine.scanner.device_file import load_scanner


def _scan(out, *extra):
    return run_virtual_scan(out, "--views", "3", "--scale", "0.05", *extra)


@pytest.mark.slow  # measured over 5 s on 2 cores
def test_scan_folder_is_complete_and_seeded(tmp_path):
    r = _scan(tmp_path / "a", "--seed", "4", "--blur-fraction", "0.34")
    assert r.returncode == 0, r.stderr
    a = tmp_path / "a"
    for f in (
        "scan.toml",
        "mesh.obj",
        "device.toml",
        "ground_truth/poses.json",
        "ground_truth/capture.json",
        "ground_truth/diffuse_albedo.exr",
        "ground_truth/roughness.exr",
    ):
        assert (a / f).is_file(), f
    photos = sorted((a / "photos").glob("*.png"))
    assert len(photos) == 3
    cam = load_scanner(a / "device.toml")
    img = read_image(photos[0])
    assert img.shape == (cam.height, cam.width, 3) and cam.width == round(2448 * 0.05)
    poses = json.loads((a / "ground_truth/poses.json").read_text())
    assert set(poses) == {p.name for p in photos}
    R = np.array(poses[photos[0].name])[:3, :3]
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-9)
    assert len(json.loads((a / "ground_truth/capture.json").read_text())["blurred_photos"]) == 1
    assert (img * 255).max() > 50  # something is lit
    r2 = _scan(tmp_path / "b", "--seed", "4", "--blur-fraction", "0.34")
    assert r2.returncode == 0
    digest = lambda p: hashlib.sha256(p.read_bytes()).hexdigest()
    assert [digest(p) for p in photos] == [digest(p) for p in sorted((tmp_path / "b" / "photos").glob("*.png"))]


@pytest.mark.slow  # measured over 5 s on 2 cores
def test_bad_inputs_name_the_file(tmp_path):
    bad = tmp_path / "broken.obj"
    bad.write_text("this is not a mesh\n")
    r = _scan(tmp_path / "o1", "--mesh", str(bad), "--maps", "assets/demo/ground_truth")
    assert r.returncode == 2 and "broken.obj" in r.stderr and len(r.stderr.strip().splitlines()) == 1

    no_uv = tmp_path / "no_uv.obj"
    m = flat_patch()
    save_obj(no_uv, Mesh(m.vertices, m.faces, None, m.normals))
    r = _scan(tmp_path / "o2", "--mesh", str(no_uv), "--maps", "assets/demo/ground_truth")
    assert r.returncode == 2 and "no_uv.obj" in r.stderr and "UV" in r.stderr

    maps = tmp_path / "maps"
    uniform_maps([0.5] * 3, [1.0] * 3, 0.1, 0.1, res=4).save(maps)
    uniform_maps([0.5] * 3, [1.0] * 3, 0.1, 0.1, res=8).save(tmp_path / "big")
    (tmp_path / "big" / "roughness.exr").replace(maps / "roughness.exr")
    good_mesh = tmp_path / "patch.obj"
    save_obj(good_mesh, flat_patch())
    r = _scan(tmp_path / "o3", "--mesh", str(good_mesh), "--maps", str(maps))
    assert r.returncode == 2 and "roughness.exr" in r.stderr and "differs" in r.stderr
    assert not (tmp_path / "o3" / "photos").exists() or not list((tmp_path / "o3" / "photos").iterdir())


def test_a_rescan_with_fewer_photos_leaves_no_stale_ones(tmp_path):
    from ntp_engine.sim.virtual_scan import ScanConfig, virtual_scan

    out = tmp_path / "scan"
    virtual_scan(out, cfg=ScanConfig(views=3, scale=0.05))
    (out / "photos" / "mine.txt").write_text("a note")  # not ntp's: kept
    virtual_scan(out, cfg=ScanConfig(views=2, scale=0.05))
    assert sorted(p.name for p in (out / "photos").iterdir()) == ["0000.png", "0001.png", "mine.txt"]


def test_a_given_mesh_is_what_the_scan_hands_ntp_and_the_photographed_one_the_truth(tmp_path):
    from ntp_engine.io.errors import NtpInputError
    from ntp_engine.io.mesh import load_mesh
    from ntp_engine.sim.scanner_mesh import scanner_mesh
    from ntp_engine.sim.virtual_scan import ScanConfig, true_mesh_path, virtual_scan

    demo = load_mesh("assets/demo/mesh.obj")
    given = tmp_path / "given" / "scanner.obj"
    given.parent.mkdir()
    save_obj(given, scanner_mesh(demo, seed=1))
    cfg, s = ScanConfig(views=2, scale=0.04), tmp_path / "s"
    virtual_scan(s, cfg=cfg, given_mesh=given)  # in-process: the CLI's option is one argument on to this
    np.testing.assert_allclose(load_mesh(s / "mesh.obj").vertices, load_mesh(given).vertices, atol=1e-9)
    assert true_mesh_path(s) == s / "ground_truth" / "mesh.obj"
    np.testing.assert_allclose(load_mesh(true_mesh_path(s)).vertices, demo.vertices, atol=1e-6)
    virtual_scan(s, cfg=cfg)  # scanned again without one: the scan's mesh is the truth again
    assert true_mesh_path(s) == s / "mesh.obj" and not (s / "ground_truth" / "mesh.obj").exists()
    far = tmp_path / "given" / "far.obj"
    save_obj(far, Mesh(demo.vertices + [0.5, 0, 0], demo.faces, demo.uv, demo.normals))
    with pytest.raises(NtpInputError, match="far.obj: the given mesh is 500.0 mm from the rendered one"):
        virtual_scan(tmp_path / "f", cfg=cfg, given_mesh=far)


def test_the_command_line_hands_the_given_mesh_on():
    from pathlib import Path

    from ntp_engine import cli

    args = cli._parser().parse_args(["virtual-scan", "--out", "x", "--given-mesh", "m.obj"])
    assert args.given_mesh == Path("m.obj") and args.func is cli._virtual_scan
