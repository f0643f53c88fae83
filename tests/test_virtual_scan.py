"""The virtual scanner: renders agree with the physics core; scans are complete and reproducible."""
import hashlib
import json
import subprocess
import sys

import numpy as np
import torch

from ntp_engine.device import Device
from ntp_engine.images import read_image
from ntp_engine.maps import SVBRDFMaps
from ntp_engine.measurement import measure, physical_lumitexel
from ntp_engine.mesh import Mesh, save_obj, smooth_normals
from ntp_engine.virtual_scan import ScanConfig, Scene, scaled_device, trajectory


def _patch(size=0.08, res=8):
    g = np.linspace(-size / 2, size / 2, res + 1)
    X, Y = np.meshgrid(g, g)
    v = np.stack([X.ravel(), Y.ravel(), np.full(X.size, 0.002)], -1)
    idx = np.arange(v.shape[0]).reshape(res + 1, res + 1)
    a, b, c, d = idx[:-1, :-1], idx[:-1, 1:], idx[1:, 1:], idx[1:, :-1]
    f = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)])
    uv = (v[:, :2] + size / 2) / size
    return Mesh(v, f, uv, smooth_normals(v, f))


def _uniform_maps(rd, rs, ax, ay, res=4):
    full = lambda val: np.broadcast_to(np.asarray(val, float), (res, res, len(val))).copy()
    return SVBRDFMaps(full(rd), full(rs), full([0, 0, 1.0]), full([1.0, 0, 0]), full([ax, ay]))


def test_rendered_flat_patch_matches_the_physics_core():
    dev = Device.load()
    maps = _uniform_maps([0.5, 0.3, 0.2], [2.0, 1.5, 1.0], 0.2, 0.05)
    scene = Scene(_patch(), maps, dev, exposure=1.0)
    cam = scaled_device(dev, 0.08)
    pose = trajectory(scene.center, dev, ScanConfig(views=5), np.random.default_rng(1))[2]
    lin, info = scene.render_linear(pose, cam)
    obj = info["geom"].reshape(cam.height, cam.width) == 0
    assert obj.sum() > 100
    # reference: the same pixels' 3D points through physical_lumitexel + measure, float64
    rows, cols = np.nonzero(obj)
    K = cam.K
    d = np.stack([(cols - K[0, 2]) / K[0, 0], (rows - K[1, 2]) / K[1, 1], np.ones(len(rows))], -1)
    R, t = pose[:3, :3], pose[:3, 3]
    n_c = R @ np.array([0, 0, 1.0])
    s = (n_c @ (R @ np.array([0, 0, 0.002]) + t)) / (d @ n_c)  # ray / plane z = 0.002
    x = torch.tensor(d * s[:, None])
    N = len(x)
    m = physical_lumitexel(dev, x, torch.tensor(n_c).expand(N, 3), torch.tensor(R @ [1.0, 0, 0]).expand(N, 3),
                           torch.tensor([0.5, 0.3, 0.2]).double().expand(N, 3),
                           torch.tensor([2.0, 1.5, 1.0]).double().expand(N, 3),
                           torch.full((N,), 0.2, dtype=torch.float64), torch.full((N,), 0.05, dtype=torch.float64))
    ref = dev.exposure(dev.pattern) * measure(dev, m).numpy()
    got = lin[rows, cols]
    rel = np.abs(got - ref) / np.maximum(ref, 1e-3)
    assert np.median(rel) < 1e-4 and rel.max() < 2e-3  # float32 rendering vs float64 reference


def _scan(out, *extra):
    cmd = [sys.executable, "-m", "ntp_engine.cli", "virtual-scan", "--out", str(out), "--views", "3",
           "--scale", "0.05", *extra]
    return subprocess.run(cmd, capture_output=True, text=True)


def test_scan_folder_is_complete_and_seeded(tmp_path):
    r = _scan(tmp_path / "a", "--seed", "4", "--blur-fraction", "0.34")
    assert r.returncode == 0, r.stderr
    a = tmp_path / "a"
    for f in ("scan.toml", "mesh.obj", "device.toml", "ground_truth/poses.json", "ground_truth/capture.json",
              "ground_truth/diffuse_albedo.exr", "ground_truth/roughness.exr"):
        assert (a / f).is_file(), f
    photos = sorted((a / "photos").glob("*.png"))
    assert len(photos) == 3
    cam = Device.load(a / "device.toml")
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


def test_bad_inputs_name_the_file(tmp_path):
    bad = tmp_path / "broken.obj"
    bad.write_text("this is not a mesh\n")
    r = _scan(tmp_path / "o1", "--mesh", str(bad), "--maps", "assets/demo/ground_truth")
    assert r.returncode == 2 and "broken.obj" in r.stderr and len(r.stderr.strip().splitlines()) == 1

    no_uv = tmp_path / "no_uv.obj"
    m = _patch()
    save_obj(no_uv, Mesh(m.vertices, m.faces, None, m.normals))
    r = _scan(tmp_path / "o2", "--mesh", str(no_uv), "--maps", "assets/demo/ground_truth")
    assert r.returncode == 2 and "no_uv.obj" in r.stderr and "UV" in r.stderr

    maps = tmp_path / "maps"
    _uniform_maps([0.5] * 3, [1.0] * 3, 0.1, 0.1, res=4).save(maps)
    _uniform_maps([0.5] * 3, [1.0] * 3, 0.1, 0.1, res=8).save(tmp_path / "big")
    (tmp_path / "big" / "roughness.exr").replace(maps / "roughness.exr")
    good_mesh = tmp_path / "patch.obj"
    save_obj(good_mesh, _patch())
    r = _scan(tmp_path / "o3", "--mesh", str(good_mesh), "--maps", str(maps))
    assert r.returncode == 2 and "roughness.exr" in r.stderr and "differs" in r.stderr
    assert not (tmp_path / "o3" / "photos").exists() or not list((tmp_path / "o3" / "photos").iterdir())


def test_demo_asset_exercises_the_whole_model():
    maps = SVBRDFMaps.load("assets/demo/ground_truth")
    ax, ay = maps.roughness[..., 0], maps.roughness[..., 1]
    spec, diff = maps.specular_albedo.mean(-1), maps.diffuse_albedo.mean(-1)
    assert ax.min() <= 0.0101 and (ax / ay).max() > 10  # roughness down to 0.01; strong anisotropy
    assert ((spec < 0.1) & (diff > 0.3)).mean() > 0.2  # diffuse-dominant region
    assert ((ax == ay) & (spec > 1)).mean() > 0.2  # glossy isotropic region
    aniso = ax > 5 * ay
    t = maps.tangent[aniso]
    assert np.ptp(np.arctan2(t[:, 1], t[:, 0])) > 2.0  # the tangent direction varies
    assert maps.diffuse_albedo.min() >= 0.25
    np.testing.assert_allclose(np.linalg.norm(maps.normal, axis=-1), 1, atol=1e-5)
    assert np.abs((maps.normal * maps.tangent).sum(-1)).max() < 1e-5
