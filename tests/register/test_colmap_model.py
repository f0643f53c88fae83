"""A COLMAP model as the scan's camera solution: a model written by pycolmap from a virtual scan is
read back (binary and text) to the same poses, drives ``ntp reconstruct --colmap`` without SfM, and
bad models are one-line errors."""

import json
import shutil

import numpy as np
import pytest

from ntp_engine import cli
from ntp_engine.io.errors import NtpInputError
from ntp_engine.io.progress import read_progress
from ntp_engine.register.colmap_model import model_files, read_colmap_model
from ntp_engine.register.settings import TUNING
from ntp_engine.scanner.scan_folder import load_poses
from ntp_engine.sim.evaluate import pose_error


def test_binary_and_text_models_read_back_to_the_sfm_poses(colmap24, tmp_path):
    import pycolmap

    folder, sfm, scan = colmap24
    names = [p.name for p in scan.photo_paths]
    text = tmp_path / "text"
    text.mkdir()
    pycolmap.Reconstruction(str(folder)).write_text(str(text))
    assert [f.suffix for f in model_files(text)] == [".txt"] * 3
    for f in (folder, text):
        got = read_colmap_model(f, scan.scanner, names)
        assert sorted(got.poses) == sorted(sfm.poses) and got.unregistered == sfm.unregistered
        assert max(np.abs(got.poses[n] - sfm.poses[n]).max() for n in got.poses) < 1e-6
        assert got.points.shape == sfm.points.shape


def test_register_and_reconstruct_with_a_colmap_model_skip_sfm(
    colmap24, colmap24_registered, scan24, capsys, monkeypatch
):
    folder, out = colmap24[0], colmap24_registered  # registered with SfM switched off (conftest)
    reg = json.loads((out / "registration.json").read_text())["registration"]
    assert reg["source"] == f"COLMAP model {folder}" and reg["registered"] >= 20 and "alignment" in reg
    assert reg["photometric"]["photos"] >= 20 and reg["confidence"]["accepted"]  # the photos judged the alignment
    # the check takes minutes on a large scan: it reports its steps (the fixture's --progress file)
    check = [r for r in read_progress(out.parent / "progress.jsonl")[0] if r["stage"] == "registration check"]
    assert check[0]["done"] == 0 and check[-1]["done"] == check[-1]["total"] == 4 + TUNING.check.rivals
    err = pose_error(load_poses(out / "poses.json"), load_poses(scan24 / "ground_truth" / "poses.json"))
    # SfM's model, refined by the photos as in tests/pipeline/test_stages.py (measured 0.45 mm, 0.057 deg)
    assert err["centre_median_m"] < 1.6e-3 and err["rotation_median_deg"] < 0.45, err

    def no_sfm(*args, **kwargs):
        raise AssertionError("SfM ran although a COLMAP model was given")

    monkeypatch.setattr("ntp_engine.pipeline.stages.structure_from_motion", no_sfm)
    argv = ["reconstruct", str(scan24), "--out", str(out), "--resolution", "16", "--colmap", str(folder), "--quiet"]
    assert cli.main(argv) == 0, capsys.readouterr().err
    rep = json.loads((out / "report.json").read_text())
    assert rep["registration"]["source"] == reg["source"] and "register" in rep["cached_stages"]
    assert (out / "diffuse_albedo.exr").is_file()
    poses = scan24 / "ground_truth" / "poses.json"
    assert cli.main(argv[:-1] + ["--colmap", str(folder), "--poses", str(poses)]) == 2
    assert "either a poses file or a COLMAP model" in capsys.readouterr().err


def test_bad_models_are_one_line_errors(colmap24, tmp_path):
    import pycolmap

    folder, _, scan = colmap24
    names = [p.name for p in scan.photo_paths]
    with pytest.raises(NtpInputError, match="not a COLMAP model folder"):
        read_colmap_model(tmp_path, scan.scanner, names)
    damaged = tmp_path / "damaged"
    shutil.copytree(folder, damaged)
    (damaged / "images.bin").write_bytes((damaged / "images.bin").read_bytes()[:50])
    with pytest.raises(NtpInputError, match="damaged: cannot read the COLMAP model"):
        read_colmap_model(damaged, scan.scanner, names)
    with pytest.raises(NtpInputError, match=r"images.bin: only 0 of its images are this scan's photos"):
        read_colmap_model(folder, scan.scanner, ["other.png"])
    rec = pycolmap.Reconstruction(str(folder))
    cam = next(iter(rec.cameras.values()))
    cam.width = cam.width * 2
    wrong = tmp_path / "wrong"
    wrong.mkdir()
    rec.write(str(wrong))
    with pytest.raises(NtpInputError, match=r"cameras.bin: camera \d+ is \d+x\d+, the photos are"):
        read_colmap_model(wrong, scan.scanner, names)
