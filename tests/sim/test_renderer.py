"""The virtual scanner: renders agree with the physics core; scans are complete and reproducible."""

import numpy as np
import torch
from scans import flat_patch, uniform_maps

from ntp_engine.physics.measurement import measure, physical_lumitexel
from ntp_engine.scanner.camera import resampled
from ntp_engine.scanner.device_file import load_scanner
from ntp_engine.sim.renderer import Scene
from ntp_engine.sim.virtual_scan import ScanConfig, trajectory


def test_rendered_flat_patch_matches_the_physics_core():
    dev = load_scanner()
    maps = uniform_maps([0.5, 0.3, 0.2], [2.0, 1.5, 1.0], 0.2, 0.05)
    scene = Scene(flat_patch(), maps, dev, exposure=1.0)
    cam = resampled(dev, 0.08)
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
    m = physical_lumitexel(
        dev,
        x,
        torch.tensor(n_c).expand(N, 3),
        torch.tensor(R @ [1.0, 0, 0]).expand(N, 3),
        torch.tensor([0.5, 0.3, 0.2]).double().expand(N, 3),
        torch.tensor([2.0, 1.5, 1.0]).double().expand(N, 3),
        torch.full((N,), 0.2, dtype=torch.float64),
        torch.full((N,), 0.05, dtype=torch.float64),
    )
    ref = dev.exposure(dev.pattern) * measure(dev, m).numpy()
    got = lin[rows, cols]
    rel = np.abs(got - ref) / np.maximum(ref, 1e-3)
    assert np.median(rel) < 1e-4 and rel.max() < 2e-3  # float32 rendering vs float64 reference


def test_without_shadows_every_emitter_lights_what_it_faces():
    from ntp_engine.sim.gallery import object_asset

    mesh, maps, _ = object_asset("knot", 32)  # self-occlusion everywhere
    dev = load_scanner()
    scene = Scene(mesh, maps, dev, clusters=8)
    cam = resampled(dev, 0.05)
    pose = trajectory(scene.center, dev, ScanConfig(views=3), np.random.default_rng(2))[1]
    shadowed, info = scene.render_linear(pose, cam)
    bare, _ = scene.render_linear(pose, cam, shadows=False)
    obj = info["geom"].reshape(cam.height, cam.width) == 0
    assert obj.sum() > 100
    assert (bare[obj] >= shadowed[obj] - 1e-12).all()  # light only added
    assert (bare[obj].sum(-1) > 1.01 * shadowed[obj].sum(-1)).mean() > 0.01  # the knot shadows itself
    flat = Scene(flat_patch(), maps, dev, clusters=8)  # nothing to shadow: the same picture
    p = trajectory(flat.center, dev, ScanConfig(views=3), np.random.default_rng(2))[1]
    assert np.allclose(flat.render_linear(p, cam)[0], flat.render_linear(p, cam, shadows=False)[0])
