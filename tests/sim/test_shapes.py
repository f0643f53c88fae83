"""The gallery's shapes: on the ground, inside the valid volume, outward normals, UVs, flat box faces."""

import numpy as np
import pytest

from ntp_engine.sim.shapes import SHAPES, box_mesh, grid_mesh


@pytest.mark.parametrize("name", list(SHAPES))
def test_shape_stands_on_the_backdrop_inside_the_valid_volume(name):
    m = SHAPES[name]()
    lo, hi = m.vertices.min(0), m.vertices.max(0)
    assert abs(lo[2]) < 1e-9  # resting on z = 0
    assert (hi - lo).max() < 0.13  # fits the 15 cm valid volume with margin for the hand's jitter
    assert m.uv is not None and m.uv.min() >= 0 and m.uv.max() <= 1
    # outward: face normals point away from the centre of their neighbourhood on average
    tri = m.triangles
    fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    centre = 0.5 * (lo + hi)
    if name == "knot":  # a tube: outward is away from the knot's centre line, not the object's centre
        return
    assert ((fn * (tri.mean(1) - centre)).sum(1) > 0).mean() > 0.9


def test_knot_normals_point_out_of_the_tube():
    m = SHAPES["knot"]()
    # every ring of the tube: the normal points away from the ring's centre
    ring = 24 + 1
    v = m.vertices.reshape(ring, -1, 3)
    n = m.normals.reshape(ring, -1, 3)
    centre = v[:-1].mean(0)  # the tube's centre line at each u
    assert ((n[:-1] * (v[:-1] - centre)).sum(-1) > 0).mean() > 0.99


def test_box_faces_are_flat_with_sharp_edges():
    m = box_mesh(n=4)
    fn = np.cross(m.triangles[:, 1] - m.triangles[:, 0], m.triangles[:, 2] - m.triangles[:, 0])
    fn /= np.linalg.norm(fn, axis=1, keepdims=True)
    # five face directions only (no base), each shared by many triangles
    dirs = np.unique(np.round(fn, 6), axis=0)
    assert len(dirs) == 5 and (np.abs(fn @ dirs.T).max(1) > 1 - 1e-9).all()


def test_grid_mesh_uvs_follow_the_parameters():
    m = grid_mesh(lambda u, v: np.stack([u, v, 0 * u], -1), 4, 2)
    np.testing.assert_allclose(m.uv, m.vertices[:, :2])
    assert len(m.faces) == 2 * 4 * 2
