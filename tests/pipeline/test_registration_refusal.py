"""The registration the photos cannot confirm is refused: a round, untextured object whose azimuth
no photo can tell (every turn of it looks the same), scanned and registered as a user does."""

import json
import subprocess
import sys

import numpy as np
from scans import run_virtual_scan, uniform_maps

from ntp_engine.io.mesh import Mesh, save_obj, smooth_normals


def _cap(radius: float = 0.05, n_phi: int = 96, n_theta: int = 24) -> Mesh:
    """A hemisphere standing on z = 0 with UVs (azimuth, polar angle): the same from every azimuth."""
    phi = np.linspace(0, 2 * np.pi, n_phi + 1)
    theta = np.linspace(0, np.pi / 2 * 0.999, n_theta + 1)
    P, T = np.meshgrid(phi, theta)
    v = np.stack([radius * np.sin(T) * np.cos(P), radius * np.sin(T) * np.sin(P), radius * np.cos(T)], -1)
    uv = np.stack([P / (2 * np.pi), T / (np.pi / 2)], -1).reshape(-1, 2)
    idx = np.arange(v.shape[0] * v.shape[1]).reshape(v.shape[:2])
    a, b, c, d = idx[:-1, :-1], idx[:-1, 1:], idx[1:, 1:], idx[1:, :-1]
    f = np.concatenate([np.stack([a, c, b], -1).reshape(-1, 3), np.stack([a, d, c], -1).reshape(-1, 3)])
    v = v.reshape(-1, 3)
    return Mesh(v, f, uv, smooth_normals(v, f))


def _ntp(*args) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "ntp_engine.cli", *map(str, args)], capture_output=True, text=True)


def test_an_ambiguous_azimuth_is_refused_with_its_diagnostics_and_forced_on_request(tmp_path):
    asset = tmp_path / "asset"
    asset.mkdir()
    save_obj(asset / "mesh.obj", _cap())
    uniform_maps([0.6, 0.5, 0.4], [0.3, 0.3, 0.3], 0.3, 0.3).save(asset / "maps")
    scan = tmp_path / "scan"
    r = run_virtual_scan(
        scan, "--mesh", asset / "mesh.obj", "--maps", asset / "maps", "--views", "24", "--scale", "0.1"
    )
    assert r.returncode == 0, r.stderr
    out = tmp_path / "rec"
    r = _ntp("register", scan, "--out", out, "--quiet")
    assert r.returncode == 2, (r.stdout, r.stderr)
    (line,) = r.stderr.strip().splitlines()
    # the hemisphere is the same under every turn: named as the mesh's symmetry, whatever the photos say
    assert "registration refused" in line and "symmetric under a turn" in line, line
    assert str(out / "registration.json") in line and "--force-registration" in line
    reg = json.loads((out / "registration.json").read_text())
    assert reg["confidence"]["accepted"] is False and reg["photometric"]["margin"] < 0.5
    assert reg["photometric"]["mesh_symmetry"]["turned_mm"] < reg["photometric"]["mesh_symmetry"]["invisible_below_mm"]
    assert len(reg["photometric"]["candidates"]) >= 2 and len(reg["alignment"]["candidates"]) == 36
    assert (out / "registration.png").stat().st_size > 1000 and not (out / "poses.json").exists()
    r = _ntp("register", scan, "--out", out, "--quiet", "--force-registration")
    assert r.returncode == 0, r.stderr
    assert "FORCED" in r.stdout and (out / "poses.json").is_file()
    assert json.loads((out / "registration.json").read_text())["registration"]["confidence"]["forced"] is True
