import numpy as np

from ntp_engine.io.raycast import RayCaster


def test_hits_and_occlusion_of_a_triangle():
    tri = np.array([[[-1, -1, 0], [1, -1, 0], [0, 1, 0]]], float)
    rc = RayCaster([tri])
    o = np.array([[0, 0, 1.0], [5, 5, 1.0]])
    d = np.array([[0, 0, -1.0], [0, 0, -1.0]])
    hits = rc.intersect(o, d)
    assert hits.geom.tolist() == [0, -1] and abs(hits.t[0] - 1.0) < 1e-6
    assert rc.occluded(o, d, np.array([2.0, 2.0])).tolist() == [True, False]
    assert rc.occluded(o, d, np.array([0.5, 0.5])).tolist() == [False, False]  # stops before the triangle
