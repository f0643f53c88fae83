import numpy as np

from ntp_engine.io.maps import texel_uv
from ntp_engine.io.mesh import Mesh, smooth_normals
from ntp_engine.io.texels import rasterize
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
    # the geometric frame: rows t, b = n x t, n, orthonormal and right-handed
    f = tx.frame
    np.testing.assert_allclose(f @ f.transpose(0, 2, 1), np.broadcast_to(np.eye(3), f.shape), atol=1e-9)
    np.testing.assert_allclose(np.linalg.det(f), 1.0, atol=1e-9)
    assert np.array_equal(f[:, 0], tx.tangent) and np.array_equal(f[:, 2], tx.normal)


def test_shape_operators_are_zero_on_a_plane_and_one_over_the_radius_on_a_sphere():
    import trimesh

    from ntp_engine.io.texels import shape_operators

    r = 0.05
    s = trimesh.creation.icosphere(subdivisions=4, radius=r)
    sphere = Mesh(np.asarray(s.vertices), np.asarray(s.faces), None, smooth_normals(s.vertices, s.faces))
    F = len(sphere.faces)
    bary = np.full((F, 3), 1 / 3)
    n = np.einsum("tk,tkj->tj", bary, sphere.normals[sphere.faces])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    t = np.cross(n, [0.3, 0.5, 0.8])
    t /= np.linalg.norm(t, axis=1, keepdims=True)
    S = shape_operators(sphere, np.arange(F), bary, n, t)
    assert np.median(np.abs(S - np.eye(2) / r)) < 0.03 / r  # curvature 1/r along every direction
    flat = Mesh(
        np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0]]), np.array([[0, 1, 2]]), None, np.tile([0.0, 0, 1], (3, 1))
    )
    zero = shape_operators(flat, np.array([0]), bary[:1], np.array([[0.0, 0, 1]]), np.array([[1.0, 0, 0]]))
    assert np.abs(zero).max() == 0
    degenerate = Mesh(np.zeros((3, 3)), np.array([[0, 1, 2]]), None, np.tile([0.0, 0, 1], (3, 1)))
    up, along = np.array([[0.0, 0, 1]]), np.array([[1.0, 0, 0]])
    assert np.abs(shape_operators(degenerate, np.array([0]), bary[:1], up, along)).max() == 0


def test_rasterize_gives_shape_operators_only_when_asked():
    from ntp_engine.io.texels import shape_operators

    mesh = dome_mesh()
    plain = rasterize(mesh, (32, 32))
    curved = rasterize(mesh, (32, 32), curvature=True)
    assert plain.shape_operator is None
    assert curved.shape_operator is not None and np.abs(curved.shape_operator).max() > 0
    expect = shape_operators(mesh, curved.face, curved.bary, curved.normal, curved.tangent)
    np.testing.assert_array_equal(curved.shape_operator, expect)


def test_uv_per_metre_says_where_a_step_on_the_surface_lands_in_the_map():
    """On a tilted, sheared UV layout: a small step along (t^, b^) from a texel's point moves its uv
    by uv_per_metre times the step — the mesh's own uv at the moved point (barycentric) — and
    degenerate triangles give 0."""
    rng = np.random.default_rng(3)
    v = np.array([[0, 0, 0], [0.1, 0, 0.02], [0.1, 0.08, 0.05], [0, 0.08, 0.03]])
    f = np.array([[0, 1, 2], [0, 2, 3]])
    uv = np.array([[0.1, 0.1], [0.8, 0.2], [0.9, 0.9], [0.2, 0.7]])
    m = Mesh(v, f, uv, smooth_normals(v, f))
    tx = rasterize(m, (32, 32), curvature=True)
    assert tx.uv_per_metre is not None and len(tx) > 100
    k = rng.choice(len(tx), 20, replace=False)
    b = np.cross(tx.normal[k], tx.tangent[k])
    step = rng.normal(size=(20, 2)) * 1e-3  # metres along (t, b)
    x = tx.position[k] + step[:, :1] * tx.tangent[k] + step[:, 1:] * b
    for j, i in enumerate(k):  # the moved point's uv by the triangle's barycentric coordinates
        p = v[f[tx.face[i]]]
        e = np.stack([p[1] - p[0], p[2] - p[0]], 1)
        w = np.linalg.lstsq(e, x[j] - p[0], rcond=None)[0]
        t_uv = uv[f[tx.face[i]]]
        moved = t_uv[0] + w[0] * (t_uv[1] - t_uv[0]) + w[1] * (t_uv[2] - t_uv[0])
        here = texel_uv((32, 32))[tx.row[i], tx.col[i]]
        np.testing.assert_allclose(moved - here, tx.uv_per_metre[i] @ step[j], atol=1e-9)
    from ntp_engine.io.texels import uv_per_metre

    degenerate = Mesh(np.zeros((3, 3)), np.array([[0, 1, 2]]), uv[:3], np.tile([0.0, 0, 1], (3, 1)))
    up, along = np.array([[0.0, 0, 1]]), np.array([[1.0, 0, 0]])
    assert np.abs(uv_per_metre(degenerate, np.array([0]), up, along)).max() == 0


def test_a_texel_image_fills_what_is_not_known_from_the_nearest_known_texel():
    """``Texels.image``: the values at their texels; texels not known and uncovered ones take the
    nearest known value. ``Texels.uv``: each texel's centre as ``io.maps.texel_uv`` says."""
    v = np.array([[0, 0, 0], [0.1, 0, 0], [0.1, 0.1, 0]])  # one triangle: half the square uncovered
    f = np.array([[0, 1, 2]])
    tx = rasterize(Mesh(v, f, v[:, :2] / 0.1, smooth_normals(v, f)), (8, 8))
    np.testing.assert_array_equal(tx.uv, texel_uv((8, 8))[tx.row, tx.col])
    values = tx.col[:, None].astype(np.float64) * np.ones(2)
    img = tx.image(values)
    np.testing.assert_array_equal(img[tx.row, tx.col], values)
    assert len(tx) < 64 and np.isfinite(img).all()
    known = tx.col >= 6  # only the right-hand columns known: every other texel takes 6 or 7
    part = tx.image(values, known)
    np.testing.assert_array_equal(part[tx.row[known], tx.col[known]], values[known])
    assert set(np.unique(part)) <= {6.0, 7.0}
