"""Similarity alignment of an SfM-like cloud (a support plane + a few object points) to the mesh."""

import numpy as np
import pytest
from scans import hemisphere

from ntp_engine.register.align import (
    _AzimuthSearch,
    align_to_mesh,
    convergence_point,
    equivalent_turns,
    is_turn_group,
    mesh_symmetry,
    ransac_plane,
    surface_samples,
    trim_threshold,
)
from ntp_engine.sim.demo_asset import dome_mesh
from ntp_engine.sim.shapes import blob_mesh, box_mesh, vase_mesh


def _random_similarity(rng):
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    w, x, y, z = q
    R = np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )
    return float(rng.uniform(5, 20)), R, rng.normal(size=3)


def _look_at(c, target, up=(0.0, 0.0, 1.0)):
    """Camera-from-world (OpenCV axes) at ``c`` looking at ``target``."""
    z = (target - c) / np.linalg.norm(target - c)
    x = np.cross(up, z)
    x /= np.linalg.norm(x)
    R = np.stack([x, np.cross(z, x), z])
    m = np.eye(4)
    m[:3, :3], m[:3, 3] = R, -R @ c
    return m


def test_ransac_plane_ignores_outliers_and_convergence_point():
    rng = np.random.default_rng(1)
    pts = np.column_stack([rng.uniform(-1, 1, (400, 2)), 0.3 + 1e-4 * rng.normal(size=400)])
    pts = np.concatenate([pts, rng.uniform(-1, 1, (150, 3))])
    n, d, inl = ransac_plane(pts, 1e-3)
    assert abs(abs(n[2]) - 1) < 1e-5 and abs(abs(d) - 0.3) < 1e-4 and inl[:400].mean() > 0.99
    target = np.array([0.1, -0.2, 0.05])
    poses = [_look_at(c, target, up=[0.3, 1, 0.1]) for c in rng.normal(size=(6, 3)) + [0, 0, 3]]
    assert np.abs(convergence_point(poses) - target).max() < 1e-9


def _dome_scene(rng):
    """An SfM-like cloud of the dome (40 object points, the support, 15 spurious points) and its
    cameras in an unknown similarity's frame: (sfm points, sfm poses, mesh, world poses, object
    points, scale)."""
    mesh = dome_mesh(64, 24)
    top = surface_samples(mesh, 4000, seed=3)
    obj = top[rng.choice(np.nonzero(top[:, 2] > 0.005)[0], 40, replace=False)]
    obj += 2e-4 * rng.normal(size=obj.shape)
    ring = rng.uniform(-0.25, 0.25, (6000, 2))
    k_out = np.linalg.norm(ring, axis=1) > 0.075  # the support, minus the object's footprint
    support = np.column_stack([ring[k_out], 1e-4 * rng.normal(size=k_out.sum())])
    clutter = rng.uniform(-0.3, 0.3, (15, 3)) * [1, 1, 0.3] + [0, 0, 0.05]  # spurious points
    world = np.concatenate([obj, support, clutter])
    # cameras on a ring 0.31 m from the object centre, looking at it
    centre = np.array([0.0, 0.0, 0.035])
    poses_w = [
        _look_at(centre + 0.31 * np.array([np.cos(a) * 0.7, np.sin(a) * 0.7, 0.71]), centre)
        for a in np.linspace(0, 2 * np.pi, 12, endpoint=False)
    ]
    s, R, t = _random_similarity(rng)  # SfM frame = an unknown similarity of the world
    sfm_pts = s * world @ R.T + t
    sfm_poses = []
    for m in poses_w:  # x_c = R_c (X_w) + t_c, X_w = R^T (X_s - t) / s, camera units scale by s
        p = np.eye(4)
        p[:3, :3] = m[:3, :3] @ R.T
        p[:3, 3] = s * m[:3, 3] - p[:3, :3] @ t
        sfm_poses.append(p)
    return sfm_pts, sfm_poses, mesh, poses_w, obj, s


def test_align_recovers_a_similarity_from_support_and_few_object_points():
    sfm_pts, sfm_poses, mesh, poses_w, obj, s = _dome_scene(np.random.default_rng(2))
    al = align_to_mesh(sfm_pts, sfm_poses, mesh, working_distance=0.31)
    assert np.abs(al.apply(sfm_pts[:40]) - obj).max() < 2e-3
    scores = [v for _, v in al.candidates]
    assert len(al.candidates) == 36 and scores == sorted(scores)  # one converged candidate per start
    assert al.azimuth_margin > 1  # the footprint and the 40 points single out the true azimuth
    assert abs(al.scale * s - 1) < 5e-3 and al.residual_m < 5e-4 and al.kept_points >= 30
    for m_s, m_w in zip(sfm_poses, poses_w):
        back = al.camera_from_mesh(m_s)
        centre_err = np.linalg.norm(back[:3, :3].T @ back[:3, 3] - m_w[:3, :3].T @ m_w[:3, 3])
        angle = np.degrees(np.arccos(np.clip((np.trace(back[:3, :3] @ m_w[:3, :3].T) - 1) / 2, -1, 1)))
        assert centre_err < 3e-3 and angle < 1.0


@pytest.mark.slow  # measured over 5 s on 2 cores
def test_bounded_nearest_sample_queries_change_nothing(monkeypatch):
    # the ICP asks the kd-tree for distances up to twice its last trimming threshold only (far
    # points make a query slow): the alignment must equal the one with every distance exact
    sfm_pts, sfm_poses, mesh, *_ = _dome_scene(np.random.default_rng(2))
    sfm_pts = np.concatenate([sfm_pts, sfm_pts[:40] * 3.0])  # far outliers too
    bounded = align_to_mesh(sfm_pts, sfm_poses, mesh, working_distance=0.31)
    exact_query = _AzimuthSearch.nearest
    monkeypatch.setattr(_AzimuthSearch, "nearest", lambda self, X, bound: exact_query(self, X, np.inf))
    exact = align_to_mesh(sfm_pts, sfm_poses, mesh, working_distance=0.31)
    assert bounded.candidates == exact.candidates and bounded.azimuth_margin == exact.azimuth_margin
    assert np.array_equal(bounded.apply(sfm_pts), exact.apply(sfm_pts))


@pytest.mark.parametrize("n", [9, 10, 11, 40, 41])
def test_trim_threshold_reads_only_distances_below_the_bound(n):
    rng = np.random.default_rng(n)
    exact = rng.uniform(0, 1, n)
    for bound in (np.inf, 2.0, 0.7, 0.5, 0.4, 0.05):
        cut = np.where(exact < bound, exact, np.inf)
        t = trim_threshold(cut, 0.5, 0.01)
        if t is not None:  # determined: the same as from the exact distances, never NaN
            assert t == max(float(np.quantile(exact, 0.5)), 0.01)
        else:
            assert (exact >= bound).sum() >= n // 2  # only when the bound cut into the upper half
    assert trim_threshold(np.where(exact < 0.05, exact, np.inf), 0.5, 0.01) is None


def test_align_needs_points_on_the_object():
    rng = np.random.default_rng(3)
    flat = np.column_stack([rng.uniform(-1, 1, (500, 2)), np.zeros(500)])
    a, b = np.eye(4), np.eye(4)  # two cameras 3 units above, looking down at the origin
    a[:3, :3], b[:3, :3] = np.diag([1.0, -1, -1]), np.diag([-1.0, 1, -1])
    a[:3, 3] = b[:3, 3] = [0, 0, 3]
    with pytest.raises(ValueError, match="on the object"):
        align_to_mesh(flat, [a, b], dome_mesh(16, 8), working_distance=0.31)


@pytest.mark.slow  # measured over 5 s on 2 cores
def test_mesh_symmetry_finds_the_half_turn_of_a_box_and_none_on_an_asymmetric_mesh():
    box = box_mesh(turn_deg=25.0)
    centre = (box.vertices.min(0) + box.vertices.max(0)) / 2
    turn, dist = mesh_symmetry(box, centre)
    assert abs(abs(turn) - 180.0) < 0.2 and dist < 1e-5
    blob = blob_mesh()
    turn, dist = mesh_symmetry(blob, (blob.vertices.min(0) + blob.vertices.max(0)) / 2)
    assert dist > 2e-3  # the nearest it comes to itself is millimetres away


@pytest.mark.slow  # measured over 5 s on 2 cores
def test_equivalent_turns_are_the_meshs_symmetries_every_turn_for_a_body_of_revolution():
    box = box_mesh(turn_deg=25.0)
    centre = (box.vertices.min(0) + box.vertices.max(0)) / 2
    (turn,) = equivalent_turns(box, centre, 2e-4)  # a 9 x 6.5 cm box: the half turn only
    assert abs(abs(turn) - 180.0) < 0.2
    blob = blob_mesh()
    assert equivalent_turns(blob, (blob.vertices.min(0) + blob.vertices.max(0)) / 2, 2e-4) == []
    cap = hemisphere()  # a body of revolution
    assert equivalent_turns(cap, np.array([0.0, 0.0, 0.025]), 2e-4) is None
    vase = vase_mesh()  # a 2% ellipse: symmetric under the half turn only, the quarter turn ~1 mm off
    vc = (vase.vertices.min(0) + vase.vertices.max(0)) / 2
    assert [round(abs(t)) for t in equivalent_turns(vase, vc, 2e-4)] == [180]


def test_symmetries_form_a_group_scattered_near_misses_do_not():
    assert is_turn_group([]) and is_turn_group([-180.0]) and is_turn_group([-90.0, 90.0, -180.0])
    assert is_turn_group([120.3, -119.8])  # a three-fold symmetry, refined to a fraction of a degree
    # a nearly-revolved wavy profile (revolution-1000 of the validation set): its turned mesh lay
    # within a quarter pixel of itself at these turns, and at no others
    assert not is_turn_group([-100.0, -98.0, -96.0, -94.0, -65.0, 47.0, 57.0, 94.0, 97.0, 99.0])
    assert not is_turn_group([90.0])  # a quarter turn without its inverse and the half turn
