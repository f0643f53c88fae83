"""``ntp batch``: a collection of scans, one result each, in this process and as Ray tasks; a
failing scan is reported and the others finish; a second run resumes from every result's cache."""

import json
import shutil
import subprocess
import sys

import numpy as np
import pytest

from ntp_engine.io.errors import NtpInputError
from ntp_engine.io.maps import SVBRDFMaps
from ntp_engine.pipeline.collection import SUMMARY, BatchOptions, reconstruct_collection
from ntp_engine.pipeline.task_pool import RayPool

OPTIONS = BatchOptions(resolution=24)


@pytest.fixture(scope="module")
def collection(scan24, tmp_path_factory):
    """Two good scans (the test scan with its poses named in scan.toml) and a folder that is not one."""
    root = tmp_path_factory.mktemp("collection")
    for name in ("vase", "cup"):
        shutil.copytree(scan24, root / name)
        with open(root / name / "scan.toml", "a") as f:
            f.write('poses = "ground_truth/poses.json"\n')
    (root / "empty").mkdir()
    return [root / "vase", root / "empty", root / "cup"]


def _maps(result):
    m = SVBRDFMaps.load(result)
    return np.concatenate([m.diffuse_albedo, m.specular_albedo, m.normal, m.tangent, m.roughness], -1)


@pytest.fixture(scope="module")
def local_batch(collection, tmp_path_factory):
    """The collection reconstructed in this process: (folder, outcomes)."""
    out = tmp_path_factory.mktemp("local") / "batch"
    return out, reconstruct_collection(collection, out, OPTIONS)


def test_a_failing_scan_is_reported_the_others_finish_and_a_rerun_resumes(collection, local_batch):
    out, outcomes = local_batch
    assert [o["ok"] for o in outcomes] == [True, False, True]
    assert "empty/scan.toml: no scan.toml" in outcomes[1]["error"]
    for name in ("vase", "cup"):
        assert (out / name / "report.json").is_file()
    assert not (out / "empty").exists()
    # the command, run again: every scan printed, resumed from its cache, exit 2 for the failed one
    cmd = [sys.executable, "-m", "ntp_engine.cli", "batch", *map(str, collection), "--out", str(out)]
    r = subprocess.run([*cmd, "--resolution", "24", "--quiet"], capture_output=True, text=True)
    assert r.returncode == 2, r.stderr
    assert r.stdout.count("done ") == 2 and "failed  " in r.stdout
    assert r.stderr.strip().splitlines()[-1] == f"ntp: error: 1 of 3 scans failed (see {out / SUMMARY})"
    again = json.loads((out / SUMMARY).read_text())
    assert [o["ok"] for o in again] == [True, False, True]
    report = json.loads((out / "vase" / "report.json").read_text())
    assert {"traces", "fit"} <= set(report["cached_stages"])


def test_on_ray_one_task_per_scan_gives_the_same_results(collection, local_batch, ray_local, tmp_path):
    local_out, local = local_batch
    with_ray = reconstruct_collection(collection, tmp_path / "ray", OPTIONS, RayPool())
    assert [o["ok"] for o in with_ray] == [True, False, True]
    assert with_ray[1]["error"] == local[1]["error"]
    for name in ("vase", "cup"):
        np.testing.assert_array_equal(_maps(tmp_path / "ray" / name), _maps(local_out / name))


def test_bad_collections_are_refused_before_any_work(collection, tmp_path):
    twin = tmp_path / "elsewhere" / "vase"
    twin.mkdir(parents=True)
    with pytest.raises(NtpInputError, match="same folder name"):
        reconstruct_collection([collection[0], twin], tmp_path / "b1", OPTIONS)
    users = tmp_path / "mine"
    users.mkdir()
    (users / "notes.txt").write_text("mine")
    with pytest.raises(NtpInputError, match="not empty and not an ntp collection"):
        reconstruct_collection(collection[:1], users, OPTIONS)
    assert sorted(p.name for p in users.iterdir()) == ["notes.txt"]
    with pytest.raises(NtpInputError, match="inside the input folder"):
        reconstruct_collection(collection[:1], collection[0] / "results", OPTIONS)
