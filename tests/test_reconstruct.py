"""Reconstruction from a virtual scan with its true poses (the pipeline's core path)."""
import json

import numpy as np
import pytest

from conftest import make_virtual_scan
from ntp_engine.errors import NtpInputError
from ntp_engine.maps import SVBRDFMaps, texel_uv
from ntp_engine.reconstruct import reconstruct_with_poses
from ntp_engine.scan import load_scan


@pytest.fixture(scope="module")
def small_scan(tmp_path_factory):
    return make_virtual_scan(tmp_path_factory.mktemp("scan"), 12, 0.1, 3)


def test_maps_from_given_poses(small_scan, tmp_path):
    scan = load_scan(small_scan, small_scan / "ground_truth" / "poses.json")
    before = {p: p.stat().st_mtime_ns for p in small_scan.rglob("*")}
    rep = reconstruct_with_poses(scan, tmp_path / "rec", resolution=48)
    assert {p: p.stat().st_mtime_ns for p in small_scan.rglob("*")} == before  # inputs untouched
    assert rep["texels"]["coverage"] > 0.9 and rep["photos"]["used"] >= 6
    assert rep["photos"]["used"] + rep["traces"]["rejected"]["support_shadow_views"] == 12
    rec, gt = SVBRDFMaps.load(tmp_path / "rec"), SVBRDFMaps.load(small_scan / "ground_truth")
    for name in ("diffuse_albedo", "specular_albedo", "normal", "tangent", "roughness"):
        assert np.isfinite(getattr(rec, name)).all()
    g = gt.sample(texel_uv((48, 48)).reshape(-1, 2))
    ang = np.degrees(np.arccos(np.clip((rec.normal.reshape(-1, 3) * g["normal"]).sum(1), -1, 1)))
    assert np.median(ang) < 5.0  # frames are right (a frame mistake gives tens of degrees)
    assert np.sqrt(((rec.diffuse_albedo.reshape(-1, 3) - g["diffuse_albedo"]) ** 2).mean()) < 0.15
    assert ((rec.roughness >= 0.006) & (rec.roughness <= 0.5)).all()
    assert json.loads((tmp_path / "rec" / "material.json").read_text())["maps"]["normal"] == "normal.exr"
    assert (tmp_path / "rec" / "previews" / "normal.png").is_file()


def test_scan_folder_errors_name_the_file(small_scan, tmp_path):
    with pytest.raises(NtpInputError, match="scan.toml"):
        load_scan(tmp_path)
    bad = tmp_path / "poses.json"
    bad.write_text(json.dumps({"0000.png": [[1, 0], [0, 1]]}))
    with pytest.raises(NtpInputError, match="poses.json.*4x4"):
        load_scan(small_scan, bad)
    with pytest.raises(NtpInputError, match="no poses"):
        reconstruct_with_poses(load_scan(small_scan), tmp_path / "o")
