"""Camera poses from the marker board: corners where they are, poses where the cameras were, the
object hiding part of the board, an outlying corner, too little board, another board."""

import json
from dataclasses import replace

import cv2
import numpy as np
import pytest

from ntp_engine.io.mesh import load_mesh
from ntp_engine.register.board_poses import (
    board_poses,
    detect_corners,
    first_placement,
    robust_pose,
    solve_pose,
)
from ntp_engine.register.settings import TUNING
from ntp_engine.scanner.board import board_for_paper
from ntp_engine.scanner.scan_folder import load_scan
from ntp_engine.sim.virtual_scan import ScanConfig, virtual_scan


def _drawn(board, turn_deg: float, px_per_mm: float, size=(1100, 900)) -> tuple[np.ndarray, np.ndarray]:
    """The board drawn by its own albedo at pixel centres, turned in the image; and where each
    corner is (pixels, integer centres)."""
    t = np.radians(turn_deg)
    R = np.array([[np.cos(t), -np.sin(t)], [np.sin(t), np.cos(t)]])
    w, h = size
    ys, xs = np.mgrid[0:h, 0:w].astype(float)
    p = np.stack([xs.ravel() - w / 2, ys.ravel() - h / 2], 1) / px_per_mm * 1e-3 @ R  # metres, y down
    albedo, on = board.albedo(np.stack([p[:, 0], -p[:, 1]], 1))
    image = (np.where(on, albedo, 0.85).reshape(h, w) * 255).astype(np.uint8)
    corners = board.corner_points()[:, :2] * [1, -1] @ R.T * 1e3 * px_per_mm + [w / 2, h / 2]
    return image, corners


@pytest.mark.parametrize(("turn", "scale"), [(30.0, 2.0), (60.0, 3.3)])
def test_corners_are_found_where_they_are(turn, scale):
    board = board_for_paper("A4")
    image, truth = _drawn(board, turn, scale)
    ids, px = detect_corners(image, board)
    assert len(ids) >= 37
    offset = (px - truth[ids]).mean(0)
    # without TUNING.board.corner_offset_px, OpenCV's corners lie +0.5 px off in x and y
    assert np.abs(offset).max() < 0.05, offset
    assert TUNING.board.corner_offset_px == 0.5


@pytest.fixture(scope="module")
def board_scan(tmp_path_factory):
    """Eight photos of the demo standing on an A4 board (quarter size: 0.53 mm a pixel at the object)."""
    out = tmp_path_factory.mktemp("board") / "scan"
    virtual_scan(out, cfg=ScanConfig(views=8, scale=0.25, board="A4"))
    return out


def _truth(scan_dir):
    capture = json.loads((scan_dir / "ground_truth" / "capture.json").read_text())
    poses = json.loads((scan_dir / "ground_truth" / "poses.json").read_text())
    world_from_board = np.array(capture["board"]["world_from_board"])
    return {n: np.array(p) @ world_from_board for n, p in poses.items()}, world_from_board


def test_every_photo_of_a_board_scan_gets_its_pose(board_scan):
    scan = load_scan(board_scan)
    assert scan.board == board_for_paper("A4")
    names = [p.name for p in scan.photo_paths]
    found = board_poses(scan.photos_dir, names, scan.board, scan.scanner)
    truth, _ = _truth(board_scan)
    assert sorted(found.poses) == names and not found.unregistered
    centre_mm, turn_deg = [], []
    for name, pose in found.poses.items():
        c, c_true = -pose[:3, :3].T @ pose[:3, 3], -truth[name][:3, :3].T @ truth[name][:3, 3]
        centre_mm.append(1e3 * np.linalg.norm(c - c_true))
        cos = (np.trace(pose[:3, :3] @ truth[name][:3, :3].T) - 1) / 2
        turn_deg.append(np.degrees(np.arccos(np.clip(cos, -1, 1))))
    # measured 0.2-0.5 mm / 0.03-0.12 deg at 0.53 mm a pixel (the most oblique photo the worst)
    assert np.median(centre_mm) < 0.5 and max(centre_mm) < 2.0, centre_mm
    assert np.median(turn_deg) < 0.1 and max(turn_deg) < 0.4, turn_deg
    summary = found.to_json()
    assert summary["photos_with_pose"] == len(names) and summary["rms_px_median"] < 0.3


def test_the_object_hides_part_of_the_board_and_the_rest_suffices(board_scan):
    scan = load_scan(board_scan)
    assert scan.board is not None
    seen = []
    for path in scan.photo_paths:
        ids, _ = detect_corners(cv2.imread(str(path), cv2.IMREAD_GRAYSCALE), scan.board)
        seen.append(len(ids))
    # the object stands on the board's middle: no photo sees all 40 corners, every one enough
    assert max(seen) < len(scan.board.corner_points()) and min(seen) >= TUNING.board.min_corners, seen


def test_an_outlying_corner_is_dropped_and_the_pose_kept(board_scan):
    scan = load_scan(board_scan)
    assert scan.board is not None
    path = scan.photo_paths[4]
    ids, px = detect_corners(cv2.imread(str(path), cv2.IMREAD_GRAYSCALE), scan.board)
    clean = robust_pose(path.name, ids, px, scan.board, scan.scanner)
    moved = px.copy()
    moved[3] += [6.0, -4.0]  # a corner pulled onto the object's outline
    view = robust_pose(path.name, ids, moved, scan.board, scan.scanner)
    assert view.pose is not None and clean.pose is not None and view.dropped >= 1 and ids[3] not in view.ids
    assert np.abs(view.pose[:3, 3] - clean.pose[:3, 3]).max() < 5e-4
    raw = solve_pose(ids, moved, scan.board, scan.scanner)
    assert (
        raw is not None
        and np.abs(raw[0][:3, 3] - clean.pose[:3, 3]).max() > np.abs(view.pose[:3, 3] - clean.pose[:3, 3]).max()
    )  # kept, the corner would have moved the pose


def test_too_little_board_and_another_board_give_no_pose(board_scan):
    scan = load_scan(board_scan)
    assert scan.board is not None
    path = scan.photo_paths[4]
    ids, px = detect_corners(cv2.imread(str(path), cv2.IMREAD_GRAYSCALE), scan.board)
    few = robust_pose(path.name, ids[:5], px[:5], scan.board, scan.scanner)
    assert few.pose is None and "board not seen (5 corners" in (few.rejected or "")
    row = ids // (scan.board.squares[0] - 1) == ids[0] // (scan.board.squares[0] - 1)  # one row: a line
    if row.sum() >= TUNING.board.min_corners:
        assert solve_pose(ids[row], px[row], scan.board, scan.scanner) is None
    other = replace(scan.board, dictionary="DICT_5X5_250")  # a board printed from another dictionary
    found = board_poses(scan.photos_dir, [path.name], other, scan.scanner)
    assert not found.poses and found.unregistered == [path.name]


def test_the_first_placement_stands_the_mesh_on_the_board_under_the_cameras_aim(board_scan):
    scan = load_scan(board_scan)
    truth, world_from_board = _truth(board_scan)
    mesh = load_mesh(scan.mesh_path)
    placed = first_placement(mesh, list(truth.values()))
    assert placed.scale == 1.0 and np.allclose(placed.rotation, np.eye(3))
    # the board's centre in the mesh frame, up to the board's own turn: the cameras aimed at the object
    # within 6 mm (the trajectory's jitter), so their aim finds its foot within a few mm
    centre = 0.5 * (mesh.vertices.min(0) + mesh.vertices.max(0))  # where the trajectory aims
    foot_board = np.linalg.inv(world_from_board) @ np.array([*centre[:2], 0.0, 1.0])
    foot_placed = placed.rotation.T @ (np.array([*centre[:2], 0.0]) - placed.translation)
    assert abs(placed.translation[2] - mesh.vertices[:, 2].min()) < 1e-12  # the foot on the plane
    assert np.hypot(*(foot_board[:2] - foot_placed[:2])) < 0.01
