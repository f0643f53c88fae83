"""``ntp reconstruct`` end to end on virtual scans: SfM + alignment, given poses, caching/resume,
photo selection, bad input."""

import shutil

import numpy as np
from scipy.ndimage import gaussian_filter
from skimage.measure import blur_effect

from ntp_engine.io.images import read_image, write_png
from ntp_engine.pipeline.photo_selection import blur_score
from ntp_engine.pipeline.stages import reconstruct
from ntp_engine.scanner.scan_folder import load_scan


def test_blurry_and_corrupt_photos_are_skipped_and_listed(scan24, tmp_path):
    scan = tmp_path / "scan"
    shutil.copytree(scan24, scan)
    photo = read_image(scan / "photos" / "0003.png")
    write_png(scan / "photos" / "0003.png", gaussian_filter(photo, (1.5, 1.5, 0)))
    (scan / "photos" / "0007.png").write_bytes(b"\x89PNG\r\n\x1a\n not really")
    (scan / "photos" / "0008.png").write_bytes((scan / "photos" / "0008.png").read_bytes()[:200])  # truncated
    assert blur_score(np.round(photo * 255)) < blur_score(np.round(gaussian_filter(photo, (1.5, 1.5, 0)) * 255))
    rep = reconstruct(load_scan(scan, scan / "ground_truth" / "poses.json"), tmp_path / "rec", resolution=24)
    assert list(rep.photos.blurry) == ["0003.png"]
    assert sorted(rep.photos.unreadable) == ["0007.png", "0008.png"]
    assert rep.photos.kept == 21


def test_the_blur_score_is_crete_et_al_as_scikit_image_computes_it():
    rng = np.random.default_rng(3)
    sharp = rng.integers(0, 256, (120, 160, 3)).astype(np.float64)
    sharp[40:80, 50:110] = 230.0  # a patch with edges
    soft = np.stack([gaussian_filter(sharp[..., c], 1.5) for c in range(3)], -1)
    for codes in (sharp, soft, sharp[:, :97]):
        reference = float(blur_effect(codes.mean(-1) / 255.0))
        assert abs(blur_score(codes) - reference) < 1e-5, (blur_score(codes), reference)
    assert blur_score(soft) > blur_score(sharp) + 0.2
