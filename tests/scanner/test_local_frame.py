import numpy as np

from ntp_engine.io.mesh import Mesh
from ntp_engine.scanner.local_frame import local_origin, moved, pose_to_local, pose_to_world, position_digits


def _mesh(shift) -> Mesh:
    v = np.array([[0.0, 0, 0], [0.1, 0, 0], [0, 0.1, 0.05]]) + shift
    return Mesh(v, np.array([[0, 1, 2]]), None, np.tile([0.0, 0, 1], (3, 1)))


def test_the_origin_is_the_centre_rounded_to_the_metre_and_zero_near_the_world_origin():
    assert local_origin(_mesh([0.3, -0.4, 0.0])).tolist() == [0.0, 0.0, 0.0]
    assert not np.signbit(local_origin(_mesh([-0.3, -0.4, -0.2]))).any()  # no -0.0 in a file
    assert local_origin(_mesh([1000.0, 1000.0, 0.0])).tolist() == [1000.0, 1000.0, 0.0]


def test_poses_and_meshes_move_together_and_back():
    origin = np.array([1000.0, -2000.0, 3.0])
    mesh = _mesh(origin)
    rot = np.linalg.qr(np.random.default_rng(0).normal(size=(3, 3)))[0]
    pose = np.eye(4)
    pose[:3, :3], pose[:3, 3] = rot * np.sign(np.linalg.det(rot)), [0.1, 0.2, 1000.0]
    local = moved(mesh, -origin)
    world_cam = (pose @ np.c_[mesh.vertices, np.ones(3)].T).T
    local_cam = (pose_to_local(pose, origin) @ np.c_[local.vertices, np.ones(3)].T).T
    np.testing.assert_allclose(local_cam, world_cam, atol=1e-9)  # the camera sees the same points
    np.testing.assert_allclose(pose_to_world(pose_to_local(pose, origin), origin), pose, atol=1e-12)
    assert moved(mesh, np.zeros(3)) is mesh and pose_to_local(pose, np.zeros(3)) is pose  # near the origin: untouched


def test_a_world_position_keeps_a_tenth_of_a_micrometre_in_text():
    assert position_digits(np.zeros(3)) == 7
    assert position_digits(np.array([1000.0, 0, 0])) == 11
    x = 1000.0 + 0.12345678
    assert abs(float(f"{x:.{position_digits(np.array([1000.0, 0, 0]))}g}") - x) < 1e-7
