"""Reconstruction from a virtual scan with its true poses (the pipeline's core path)."""

import json

import numpy as np
import pytest
from scans import make_virtual_scan

from ntp_engine.io.maps import SVBRDFMaps, texel_uv
from ntp_engine.pipeline.scan_folder import load_scan
from ntp_engine.pipeline.stages import reconstruct


@pytest.fixture(scope="module")
def small_scan(tmp_path_factory):
    return make_virtual_scan(tmp_path_factory.mktemp("scan"), 12, 0.1, 3)


def test_maps_from_given_poses(small_scan, tmp_path):
    scan = load_scan(small_scan, small_scan / "ground_truth" / "poses.json")
    before = {p: p.stat().st_mtime_ns for p in small_scan.rglob("*")}
    rep = reconstruct(scan, tmp_path / "rec", resolution=48)
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
