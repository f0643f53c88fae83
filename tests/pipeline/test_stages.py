"""``ntp reconstruct`` end to end on virtual scans: SfM + alignment, given poses, caching/resume,
photo selection, bad input."""

import json
import shutil

import numpy as np
import pytest
import torch
from ray_tasks import kill_task_once

from ntp_engine.io.errors import NtpInputError
from ntp_engine.learn import models
from ntp_engine.pipeline import stages as pipeline
from ntp_engine.pipeline.stages import reconstruct
from ntp_engine.pipeline.task_pool import LOCAL
from ntp_engine.scanner.scan_folder import load_poses, load_scan
from ntp_engine.sim.evaluate import pose_error


def _mtimes(folder):
    return {p: p.stat().st_mtime_ns for p in folder.rglob("*")}


def test_sfm_end_to_end_poses_match_the_truth(scan24, colmap24, tmp_path, monkeypatch):
    # 24 photos: SfM's point cloud alone places them to 6-10 mm / 0.6-3 deg (the azimuth on ~20
    # object points; docs/pipeline.md); the photometric check's refinement takes that to ~0.5 mm
    scan = scan24
    before = _mtimes(scan)
    # SfM of these photos is the suite's shared pycolmap run (conftest ``colmap24``: the call the
    # register stage makes, on every photo); asked for any other set, SfM runs here
    _, shared, shared_scan = colmap24
    real_sfm, asked = pipeline.structure_from_motion, []

    def sfm(photos_dir, names, scanner, work, **kwargs):
        same = photos_dir == shared_scan.photos_dir and sorted(names) == sorted(p.name for p in shared_scan.photo_paths)
        asked.append(same)
        return shared if same else real_sfm(photos_dir, names, scanner, work, **kwargs)

    monkeypatch.setattr(pipeline, "structure_from_motion", sfm)
    truth = load_poses(scan / "ground_truth" / "poses.json")
    rep = reconstruct(load_scan(scan), tmp_path / "rec", resolution=64)
    assert _mtimes(scan) == before  # inputs untouched
    reg = rep.registration
    assert reg["source"] == "structure from motion" and reg["registered"] >= 18 and asked == [True]
    err = pose_error(pipeline.register_photos(load_scan(scan), tmp_path / "rec")[0], truth)
    print("pose error vs truth:", err, "alignment:", reg["alignment"])
    # SfM varies from run to run with threads; refined by the photos: measured 0.47 mm, 0.055 deg
    assert err["centre_median_m"] < 1.6e-3 and err["rotation_median_deg"] < 0.45
    assert reg["alignment"]["residual_m"] < 1e-3 and reg["alignment"]["inlier_points"] >= 8
    assert reg["confidence"]["accepted"] and (tmp_path / "rec" / "registration.png").is_file()
    assert rep.texels.coverage > 0.9
    assert set(rep.stages) == {"select", "register", "atlas", "traces", "network_and_fit", "maps"}
    for f in ("diffuse_albedo.exr", "normal.exr", "confidence.exr", "mesh.obj", "material.json", "report.json"):
        assert (tmp_path / "rec" / f).is_file()


def test_given_poses_resume_and_changed_model(scan24, tmp_path, monkeypatch):
    scan = load_scan(scan24, scan24 / "ground_truth" / "poses.json")
    out = tmp_path / "rec"

    def interrupted(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr(pipeline, "fit_blocks", interrupted)
    with pytest.raises(KeyboardInterrupt):
        reconstruct(scan, out, resolution=32)
    assert sorted(p.name for p in (out / "cache").iterdir()) == ["atlas", "select", "traces"]  # no half stage
    monkeypatch.undo()
    rep = reconstruct(scan, out, resolution=32)
    assert rep.cached_stages == ["select", "atlas", "traces"] and rep.registration["source"] == "poses file"
    rep = reconstruct(scan, out, resolution=32)
    assert rep.cached_stages == ["select", "atlas", "traces", "fit"]
    other = _retrained_copy(tmp_path / "other_model")  # a later option changed: another model, same pattern
    rep = reconstruct(scan, out, resolution=32, model=str(other))
    assert rep.cached_stages == ["select", "atlas", "traces"] and "other_model" in rep.model["name"]
    with pytest.raises(
        NtpInputError, match="pattern.csv.*another lighting pattern"
    ):  # the model's pattern is not the scan's
        reconstruct(scan, out, resolution=32, model="compare_point")


def _retrained_copy(folder):
    """The shipped model with one bias nudged: a different network trained for the same pattern."""
    shutil.copytree(models.resolve(None), folder)
    state = torch.load(folder / "model.pt", weights_only=True)
    key = next(k for k in state if k.endswith("bias"))
    state[key] = state[key] + 0.01
    torch.save(state, folder / "model.pt")
    return folder


def test_mesh_without_uvs_gets_an_xatlas_atlas(scan24, tmp_path):
    from ntp_engine.io.mesh import Mesh, load_mesh, save_obj
    from ntp_engine.io.texels import rasterize, uv_atlas

    mesh = load_mesh(scan24 / "mesh.obj")
    bare = Mesh(mesh.vertices, mesh.faces, None, mesh.normals)
    atlas = uv_atlas(bare, 64)
    assert atlas.uv is not None and atlas.uv.min() >= 0 and atlas.uv.max() <= 1
    assert abs(atlas.area() - mesh.area()) < 1e-9 * mesh.area()  # same surface, split at seams
    assert len(rasterize(atlas, (64, 64))) > 0.4 * 64 * 64  # texels_per_unit fills the map
    scan = tmp_path / "scan"
    shutil.copytree(scan24, scan)
    save_obj(scan / "mesh.obj", bare)
    rep = reconstruct(load_scan(scan, scan / "ground_truth" / "poses.json"), tmp_path / "rec", resolution=32)
    assert rep.texels.coverage > 0.8 and load_mesh(tmp_path / "rec" / "mesh.obj").uv is not None


def test_refinement_stage_writes_uncertainty_and_resumes(scan24, tmp_path):
    from ntp_engine.io.images import read_image
    from ntp_engine.sim.evaluate import map_errors

    scan = load_scan(scan24, scan24 / "ground_truth" / "poses.json")
    plain = reconstruct(scan, tmp_path / "plain", resolution=24)
    rep = reconstruct(scan, tmp_path / "rec", resolution=24, refine=True)
    assert "refine" in rep.stages and not (tmp_path / "plain" / "uncertainty.exr").exists()
    unc = read_image(tmp_path / "rec" / "uncertainty.exr")
    assert unc.shape == (24, 24, 4) and np.isfinite(unc).all() and (unc > 0).all()
    doc = json.loads((tmp_path / "rec" / "material.json").read_text())["uncertainty"]
    assert doc["file"] == "uncertainty.exr" and set(doc["channels"]) == {"R", "G", "B", "A"}
    assert np.median(unc[..., 0][unc[..., 0] < 1000]) < 5  # normals are constrained to a few degrees
    # the basis materials: a table in material.json, each texel's in confidence.exr's B, counted in the report
    basis = json.loads((tmp_path / "rec" / "material.json").read_text())["basis_materials"]
    ids = read_image(tmp_path / "rec" / "confidence.exr")[..., 2]
    assert len(basis["table"]) == rep.refine.basis_materials
    assert set(np.unique(ids).astype(int)) <= set(range(len(basis["table"]) + 1))
    assert 0 <= rep.refine.texels_lobe_from_material <= rep.texels.observed
    assert 0 <= rep.refine.texels_width_from_material <= rep.texels.observed
    if basis["table"]:  # the matte class's share, estimated on this object; which widths vary
        assert 0.05 <= rep.refine.matte_share <= 0.95
        varies = [m["width_varies"] for m in basis["table"]]
        assert all(isinstance(v, bool) for v in varies) and sum(varies) == rep.refine.materials_width_varies
    truth = scan24 / "ground_truth"
    before, after = map_errors(tmp_path / "plain", truth), map_errors(tmp_path / "rec", truth)
    assert after["normal_median_deg"] < before["normal_median_deg"] + 0.3
    assert after["diffuse_rmse"] < before["diffuse_rmse"] + 0.01
    assert rep.texels.observed >= plain.texels.observed  # dark and clipped entries count too
    again = reconstruct(scan, tmp_path / "rec", resolution=24, refine=True)
    assert again.cached_stages[-2:] == ["fit", "refine"]


def test_distilled_path_teaches_the_network_polishes_and_resumes(scan24, tmp_path):
    """``reconstruct(distil=True)``: the teacher, the fine-tuning and the polish run and are
    reported; the maps are finite and no worse than the network's alone; a re-run is served from
    the cache; with ``refine`` too it is refused in one line."""
    from ntp_engine.io.images import read_image
    from ntp_engine.sim.evaluate import map_errors

    scan = load_scan(scan24, scan24 / "ground_truth" / "poses.json")
    plain = reconstruct(scan, tmp_path / "plain", resolution=24)
    rep = reconstruct(scan, tmp_path / "rec", resolution=24, distil=True)
    assert {"teacher", "distil", "polish"} <= set(rep.stages) and "refine" not in rep.stages
    d = rep.distil
    assert d["seeds"] == plain.texels.observed  # fewer texels than seeds: every one a seed
    assert d["trained_on"] + d["held_out"] == d["seeds"] and 0 < d["steps"] <= 800
    assert d["loss_after"] < d["loss_before"]
    for name in ("normal.exr", "roughness.exr", "specular_albedo.exr", "diffuse_albedo.exr"):
        assert np.isfinite(read_image(tmp_path / "rec" / name)).all(), name
    truth = scan24 / "ground_truth"
    before, after = map_errors(tmp_path / "plain", truth), map_errors(tmp_path / "rec", truth)
    assert after["normal_median_deg"] < before["normal_median_deg"] + 0.3
    assert after["diffuse_rmse"] < before["diffuse_rmse"] + 0.01
    again = reconstruct(scan, tmp_path / "rec", resolution=24, distil=True)
    assert again.cached_stages[-4:] == ["fit", "teacher", "distil", "polish"] and again.distil == d
    with pytest.raises(NtpInputError, match="choose one"):
        reconstruct(scan, tmp_path / "both", resolution=24, distil=True, refine=True)
    assert not (tmp_path / "both").exists()


def test_fit_stage_on_ray_is_identical_even_with_a_worker_killed_mid_block(scan24, ray_local, tmp_path):
    """``reconstruct(ray=...)``: the fit stage's blocks as Ray tasks give the single-process maps bit
    for bit; a worker SIGKILLed while it fits a block is replaced and the block run again."""
    scan = load_scan(scan24, scan24 / "ground_truth" / "poses.json")
    local = reconstruct(scan, tmp_path / "local", resolution=48)
    killed = kill_task_once("_fit_block")
    with_ray = reconstruct(scan, tmp_path / "ray", resolution=48, ray=LOCAL)
    assert killed, "no worker was killed: the test did not test anything"
    assert with_ray.texels == local.texels
    for name in ("diffuse_albedo.exr", "specular_albedo.exr", "normal.exr", "tangent.exr", "roughness.exr"):
        assert (tmp_path / "ray" / name).read_bytes() == (tmp_path / "local" / name).read_bytes(), name
    with (
        np.load(tmp_path / "local" / "cache" / "fit" / "fit.npz") as a,
        np.load(tmp_path / "ray" / "cache" / "fit" / "fit.npz") as b,
    ):
        assert all(np.array_equal(a[k], b[k]) for k in a.files)


@pytest.fixture(scope="module")
def refined16(scan24, tmp_path_factory):
    """A finished ``reconstruct --refine`` of ``scan24`` at 16^2 whose re-run is served from its cache."""
    scan = load_scan(scan24, scan24 / "ground_truth" / "poses.json")
    out = tmp_path_factory.mktemp("refined16") / "rec"
    reconstruct(scan, out, resolution=16, refine=True)
    assert reconstruct(scan, out, resolution=16, refine=True).cached_stages == STAGES
    return scan, out


STAGES = ["select", "atlas", "traces", "fit", "refine"]


@pytest.mark.parametrize(
    "module, recomputed",
    [
        ("ntp_engine.pipeline.fit_traces", ["fit", "refine"]),
        ("ntp_engine.pipeline.traces", ["traces", "fit", "refine"]),
    ],
)
def test_a_change_to_a_stages_code_recomputes_that_stage_and_the_ones_after_it_only(
    refined16, tmp_path, monkeypatch, module, recomputed
):
    """An upgraded ntp run into an existing result: the stages whose code changed (their modules or
    any engine module those import) and the stages after them are computed again, the rest served."""
    from ntp_engine.io import stage_cache

    scan, finished = refined16
    out = tmp_path / "rec"
    shutil.copytree(finished, out)
    real = stage_cache._source
    monkeypatch.setattr(stage_cache, "_source", lambda m: real(m) + ("\nUPGRADED = 1\n" if m == module else ""))
    stage_cache._module_code.cache_clear()
    try:
        rep = reconstruct(scan, out, resolution=16, refine=True)
    finally:
        stage_cache._module_code.cache_clear()
    assert rep.cached_stages == [s for s in STAGES if s not in recomputed]
