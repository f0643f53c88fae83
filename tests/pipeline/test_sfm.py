"""Structure-from-motion on a virtual scan: the recovered camera centres match the true ones up to
the similarity SfM cannot know."""

import json

import numpy as np
import pytest

from ntp_engine.io.errors import NtpInputError
from ntp_engine.io.images import write_png
from ntp_engine.pipeline.sfm import structure_from_motion
from ntp_engine.scanner.device_file import load_scanner


def _umeyama(src: np.ndarray, dst: np.ndarray):
    ms, md = src.mean(0), dst.mean(0)
    U, S, Vt = np.linalg.svd((dst - md).T @ (src - ms) / len(src))
    D = np.eye(3)
    D[2, 2] = np.sign(np.linalg.det(U @ Vt))
    R = U @ D @ Vt
    s = np.trace(np.diag(S) @ D) / ((src - ms) ** 2).sum(1).mean()
    return s, R, md - s * R @ ms


def test_sfm_recovers_the_trajectory_up_to_a_similarity(scan24, tmp_path):
    scan = scan24
    names = sorted(p.name for p in (scan / "photos").glob("*.png"))
    reg = structure_from_motion(scan / "photos", names, load_scanner(scan / "device.toml"), tmp_path / "sfm")
    assert len(reg.poses) >= 0.8 * len(names) and len(reg.points) > 100
    gt = json.loads((scan / "ground_truth" / "poses.json").read_text())
    centre = lambda m: -m[:3, :3].T @ m[:3, 3]
    src = np.array([centre(reg.poses[n]) for n in reg.poses])
    dst = np.array([centre(np.array(gt[n])) for n in reg.poses])
    s, R, t = _umeyama(src, dst)
    err = np.linalg.norm((s * (R @ src.T)).T + t - dst, axis=1)
    assert np.median(err) < 2e-3  # metres, cameras ~0.31 m from the object
    # orientations agree too, through the same rotation
    for n in list(reg.poses)[:5]:
        R_sfm, R_gt = reg.poses[n][:3, :3], np.array(gt[n])[:3, :3]
        ang = np.degrees(np.arccos(np.clip((np.trace(R_gt @ R @ R_sfm.T) - 1) / 2, -1, 1)))  # R_gt = R_sfm R^T
        assert ang < 1.0


def test_featureless_photos_are_a_clear_error(tmp_path):
    photos = tmp_path / "photos"
    for i in range(4):
        write_png(photos / f"{i}.png", np.zeros((64, 80, 3)))
    dev = load_scanner()
    dev.width, dev.height = 80, 64
    dev.K = np.array([[80.0, 0, 39.5], [0, 80.0, 31.5], [0, 0, 1]])
    with pytest.raises(NtpInputError, match="photos"):
        structure_from_motion(photos, [f"{i}.png" for i in range(4)], dev, tmp_path / "sfm")
