"""Photos the marker board misses, placed by SfM beside their neighbours and joined to the board frame."""

import numpy as np
import pytest

from ntp_engine.register.board_fallback import fill_from_sfm, sfm_subset
from ntp_engine.register.board_poses import board_poses
from ntp_engine.register.settings import TUNING
from ntp_engine.scanner.scan_folder import load_scan
from ntp_engine.sim.virtual_scan import ScanConfig, virtual_scan


def test_the_subset_is_the_missing_photos_and_their_neighbours():
    names = [f"{i:04d}.png" for i in range(20)]
    assert sfm_subset(names, ["0003.png"], reach=2) == names[1:6]
    assert sfm_subset(names, ["0000.png", "0019.png"], reach=1) == ["0000.png", "0001.png", "0018.png", "0019.png"]


@pytest.fixture(scope="module")
def board_scan(tmp_path_factory):
    """Eight photos of the demo standing on an A4 board (quarter size)."""
    out = tmp_path_factory.mktemp("board") / "scan"
    virtual_scan(out, cfg=ScanConfig(views=8, scale=0.25, board="A4"))
    return out


def test_a_photo_the_board_misses_is_placed_by_sfm_beside_its_neighbours(board_scan, tmp_path):
    scan = load_scan(board_scan)
    assert scan.board is not None
    names = [p.name for p in scan.photo_paths]
    found = board_poses(scan.photos_dir, names, scan.board, scan.scanner)
    hidden = names[3]
    known = found.poses.pop(hidden)  # as if the board were out of this photo
    added = fill_from_sfm(scan.photos_dir, names, found, scan.scanner, tmp_path / "sfm")
    assert added.anchors >= 3 and added.anchor_rms_px <= TUNING.board.max_anchor_rms_px, added.to_json()
    assert list(added.poses) == [hidden] and not added.unplaced
    pose = added.poses[hidden]
    centre, centre_board = -pose[:3, :3].T @ pose[:3, 3], -known[:3, :3].T @ known[:3, 3]
    assert np.linalg.norm(centre - centre_board) < 3e-3  # metres: SfM joined by its neighbours' board poses
