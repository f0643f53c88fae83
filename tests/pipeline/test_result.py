"""Reconstruction from a virtual scan with its true poses (the pipeline's core path)."""

import json

import numpy as np
import pytest
from scans import make_virtual_scan

from ntp_engine.fit.texel_fit import TexelFit
from ntp_engine.io.images import read_image
from ntp_engine.io.maps import SVBRDFMaps, texel_uv
from ntp_engine.io.viewers import base_colour_for_fresnel_mix, beyond_principled
from ntp_engine.pipeline.stages import reconstruct
from ntp_engine.scanner.scan_folder import load_scan


@pytest.fixture(scope="module")
def small_scan(tmp_path_factory):
    return make_virtual_scan(tmp_path_factory.mktemp("scan"), 12, 0.1, 3)


def test_maps_from_given_poses(small_scan, tmp_path):
    scan = load_scan(small_scan, small_scan / "ground_truth" / "poses.json")
    before = {p: p.stat().st_mtime_ns for p in small_scan.rglob("*")}
    rep = reconstruct(scan, tmp_path / "rec", resolution=48)
    assert {p: p.stat().st_mtime_ns for p in small_scan.rglob("*")} == before  # inputs untouched
    assert rep.texels.coverage > 0.9 and rep.photos.used >= 6
    assert rep.photos.used + rep.traces.views_seeing_no_texel == 12
    rec, gt = SVBRDFMaps.load(tmp_path / "rec"), SVBRDFMaps.load(small_scan / "ground_truth")
    for name in ("diffuse_albedo", "specular_albedo", "normal", "tangent", "roughness"):
        assert np.isfinite(getattr(rec, name)).all()
    g = gt.sample(texel_uv((48, 48)).reshape(-1, 2))
    ang = np.degrees(np.arccos(np.clip((rec.normal.reshape(-1, 3) * g["normal"]).sum(1), -1, 1)))
    assert np.median(ang) < 5.0  # frames are right (a frame mistake gives tens of degrees)
    assert np.sqrt(((rec.diffuse_albedo.reshape(-1, 3) - g["diffuse_albedo"]) ** 2).mean()) < 0.15
    assert ((rec.roughness >= 0.006) & (rec.roughness <= 0.5)).all()
    # the share of observed texels beyond Cycles' Principled 10:1, as the maps hold them
    seen = read_image(tmp_path / "rec" / "confidence.exr")[..., 1] > 0
    share = beyond_principled(rec.roughness[seen]).mean()
    assert rep.texels.beyond_cycles_principled == pytest.approx(share, abs=1e-9)
    # the share whose glTF base colour is clipped, as the maps hold them (rho_d / (1 - 0.04 rho_s) > 1)
    clipped = base_colour_for_fresnel_mix(rec.diffuse_albedo[seen], rec.specular_albedo[seen])[1].mean()
    assert rep.texels.gltf_base_colour_clipped == pytest.approx(clipped, abs=1e-9)
    assert json.loads((tmp_path / "rec" / "report.json").read_text())["texels"]["beyond_cycles_principled"] == share
    assert json.loads((tmp_path / "rec" / "material.json").read_text())["maps"]["normal"] == "normal.exr"
    assert (tmp_path / "rec" / "previews" / "normal.png").is_file()


def test_written_tangents_agree_between_neighbouring_texels(tmp_path):
    """A brushed plate whose fitted axes come with either sign: the tangent map is signed so a
    filtered lookup between texels keeps the axis (opposite neighbours would cancel)."""
    from ntp_engine.io.mesh import Mesh, smooth_normals
    from ntp_engine.io.texels import rasterize
    from ntp_engine.pipeline.result import write_result

    v = np.array([[0, 0, 0], [0.1, 0, 0], [0.1, 0.1, 0], [0, 0.1, 0]], float)
    f = np.array([[0, 1, 2], [0, 2, 3]])
    mesh = Mesh(v, f, v[:, :2] / 0.1, smooth_normals(v, f))
    tex = rasterize(mesh, (16, 16))
    T = len(tex.row)
    rng = np.random.default_rng(0)
    turn = 0.6 + 0.02 * tex.col  # in the plate's UV frame, slowly turning
    sign = rng.choice([-1.0, 1.0], T)[:, None]
    fitted = TexelFit.from_arrays(
        {
            "n_loc": np.tile([0.0, 0.0, 1.0], (T, 1)),
            "t_loc": sign * np.stack([np.cos(turn), np.sin(turn), np.zeros(T)], 1),
            "rho_d": np.full((T, 3), 0.1),
            "rho_s": np.full((T, 3), 2.0),
            "alpha": np.tile([0.3, 0.02], (T, 1)),
            "flags": np.zeros(T, np.int64),
        }
    )
    write_result(tmp_path, mesh, tex, fitted, np.full(T, 5))
    t = SVBRDFMaps.load(tmp_path).tangent
    assert ((t[:, 1:] * t[:, :-1]).sum(-1) > 0.9).all() and ((t[1:] * t[:-1]).sum(-1) > 0.9).all()
    axis = t[tex.row, tex.col]
    expected = np.stack([np.cos(turn), np.sin(turn), np.zeros(T)], 1)  # the UV frame is object x, y
    np.testing.assert_allclose(np.abs((axis * expected).sum(1)), 1.0, atol=1e-5)
