import numpy as np

from ntp_engine.io.maps import texel_uv
from ntp_engine.io.mesh import Mesh, smooth_normals
from ntp_engine.pipeline.texels import rasterize
from ntp_engine.sim.demo_asset import HEIGHT, RADIUS, _radius_factor, dome_mesh


def test_square_covers_every_texel_with_exact_positions():
    v = np.array([[0, 0, 0], [0.1, 0, 0], [0.1, 0.1, 0], [0, 0.1, 0.0]])
    f = np.array([[0, 1, 2], [0, 2, 3]])
    uv = v[:, :2] / 0.1
    m = Mesh(v, f, uv, smooth_normals(v, f))
    tx = rasterize(m, (16, 32))
    assert len(tx) == 16 * 32 and len(np.unique(tx.index)) == 16 * 32
    uvc = texel_uv((16, 32))[tx.row, tx.col]
    np.testing.assert_allclose(tx.position[:, :2], uvc * 0.1, atol=1e-12)
    np.testing.assert_allclose(tx.normal, [[0, 0, 1.0]] * len(tx), atol=1e-12)
    np.testing.assert_allclose(tx.tangent, [[1.0, 0, 0]] * len(tx), atol=1e-12)  # dP/du


def test_dome_texels_lie_on_the_surface_with_outward_frames():
    m = dome_mesh(64, 24)
    tx = rasterize(m, (128, 128))
    assert len(tx) > 0.95 * 128 * 128
    phi = np.arctan2(tx.position[:, 1], tx.position[:, 0])
    k, _ = _radius_factor(phi)
    r = np.linalg.norm(tx.position[:, :2], axis=1) / (RADIUS * k)
    z = tx.position[:, 2] / HEIGHT
    assert np.abs(r * r + z * z - 1).max() < 0.02  # on the dome's surface (faceted)
    assert (tx.normal[:, 2] >= -1e-9).all()
    assert np.abs((tx.normal * tx.tangent).sum(1)).max() < 1e-9
