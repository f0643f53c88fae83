import numpy as np
import torch

from ntp_engine.io.raycast import RayCaster
from ntp_engine.physics.measurement import measurement_rgb
from ntp_engine.pipeline.texels import rasterize
from ntp_engine.pipeline.traces import MIN_COS_VIEW, assemble
from ntp_engine.scanner.camera import look_at, resampled
from ntp_engine.scanner.device_file import load_scanner
from ntp_engine.sim.renderer import Scene
from ntp_engine.sim.virtual_scan import ScanConfig, load_asset, take_photo, trajectory


def test_traces_from_a_virtual_scan_match_the_renderer_and_respect_the_filters():
    mesh, maps, _, _ = load_asset(None, None, None)
    dev = load_scanner()
    cfg = ScanConfig(views=8, scale=0.15, noise_sigma=0.0, read_noise=0.0)
    scene = Scene(mesh, maps, dev, exposure=cfg.exposure)
    cam = resampled(dev, cfg.scale)
    poses = trajectory(scene.center, dev, cfg, np.random.default_rng(0))
    photos = [take_photo(scene, p, cam, cfg, np.random.default_rng(1)) for p in poses]
    tx = rasterize(mesh, (64, 64))
    traces, stats = assemble(tx, photos, poses, cam, scene.caster, pixel_scale=1.0 / cfg.exposure)
    assert stats.views_used == 8 and stats.texels_observed > 0.5 * len(tx)
    e = traces.entries.double().numpy()
    # filters: facing the camera, inside the valid volume; dark and near-clipped entries kept, flagged
    wo = -e[:, 3:6] / np.linalg.norm(e[:, 3:6], axis=1, keepdims=True)
    assert ((wo * e[:, 6:9]).sum(1) > MIN_COS_VIEW).all()
    assert dev.in_valid_volume(torch.as_tensor(e[:, 3:6])).all()
    codes = 255 * e[:, :3] * cfg.exposure
    in_range = ((codes >= 32) & (codes <= 224)).all(1)
    edge = ((np.abs(codes - 32) < 1e-3) | (np.abs(codes - 224) < 1e-3)).any(1)  # float32 entries
    assert traces.in_range is not None
    np.testing.assert_array_equal(traces.in_range.numpy()[~edge], in_range[~edge])
    in_range = traces.in_range.numpy()
    assert 0 < (~in_range).sum() and stats.entries == in_range.sum()
    assert stats.rejected["pixel_range"] == (~in_range).sum()
    only = traces.in_range_only()
    assert len(only.entries) == in_range.sum() and (only.lengths <= traces.lengths).all()
    # the entry's pixel is the scene's radiance at that surface point (bilinear + 8-bit aside)
    lengths = traces.lengths.numpy()
    texel_of_entry = np.repeat(np.arange(len(tx)), lengths)
    m = maps.sample(np.stack([(tx.col + 0.5) / 64, 1 - (tx.row + 0.5) / 64], 1)[texel_of_entry])
    view_of = [
        int(np.argmin([np.abs((p[:3, :3] @ tx.position[k] + p[:3, 3]) - e[i, 3:6]).sum() for p in poses]))
        for i, k in zip(range(len(e)), texel_of_entry)
    ]
    R = np.stack([poses[v][:3, :3] for v in view_of])
    T = lambda a: torch.as_tensor(np.ascontiguousarray(a))
    ref = measurement_rgb(
        dev,
        T(e[:, 3:6]),
        T(np.einsum("nij,nj->ni", R, m["normal"])),
        T(np.einsum("nij,nj->ni", R, m["tangent"])),
        T(m["diffuse_albedo"]),
        T(m["specular_albedo"]),
        T(m["roughness"][:, 0]),
        T(m["roughness"][:, 1]),
    ).numpy()
    ref *= dev.exposure(dev.pattern)
    rel = np.abs(e[:, :3] - ref).max(1) / ref.max(1)
    assert np.median(rel) < 0.03


def test_photos_whose_leds_the_support_shadows_are_skipped():
    mesh, _, _, _ = load_asset(None, None, None)
    cam = resampled(load_scanner(), 0.05)
    tx = rasterize(mesh, (16, 16))

    target = np.array([0.0, 0.0, 0.03])
    above = look_at(target + [0.0, -0.15, 0.27], target)  # the panel is well above the table
    level = look_at(np.array([0.31, 0.0, 0.01]), np.array([0.0, 0.0, 0.01]))  # half the panel below it
    photos = [np.full((cam.height, cam.width, 3), 100.0)] * 2
    caster = RayCaster([mesh.triangles])
    _, st = assemble(tx, photos, [above, level], cam, caster, support_z=0.0)
    assert st.rejected["support_shadow_views"] == 1 and st.views_used == 1
    _, st = assemble(tx, photos, [above, level], cam, caster)  # no support declared: both used
    assert st.rejected["support_shadow_views"] == 0 and st.views_used == 2
