"""The registration the photos cannot confirm is refused: a round, untextured object whose azimuth
no photo can tell (every turn of it looks the same), scanned and registered as a user does."""

import json
import subprocess
import sys

import numpy as np
from scans import run_virtual_scan, uniform_maps

from ntp_engine.io.mesh import Mesh, save_obj, smooth_normals
from ntp_engine.register.check import PhotoCheck
from ntp_engine.register.photometric import PhotometricFit
from ntp_engine.register.refusal import named_rival, refusal, refusal_kind


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


def test_refusal_names_the_cause():
    fit = PhotometricFit(1.0, 0.8, 1000, 500)
    confirmed = PhotoCheck(None, fit, 0.9, float("inf"), [], 0, [])  # type: ignore[arg-type]
    assert refusal(confirmed) is None and refusal_kind(confirmed) is None
    rivals = [
        {"azimuth_change_deg": 0.0, "coarse_cost": 1, "mesh_turned_mm": 0.0},
        {"azimuth_change_deg": 90.0, "coarse_cost": 1.2, "mesh_turned_mm": 3.0},
        {"azimuth_change_deg": 180.0, "coarse_cost": 1.01, "mesh_turned_mm": 0.04},
    ]
    close = PhotoCheck(None, fit, 0.9, 0.01, rivals, 0, [])  # type: ignore[arg-type]
    ambiguous = refusal(close)
    assert ambiguous and "turned by 180 deg" in ambiguous and "0.0 mm from itself" in ambiguous  # the best rival
    assert refusal_kind(close) == "ambiguous" and named_rival(rivals) == 2
    flat = PhotoCheck(None, fit, 0.02, 0.01, rivals, 0, [])  # type: ignore[arg-type]
    plain = refusal(flat)
    assert plain and "cannot confirm" in plain and "2% worse" in plain  # a plateau is not an ambiguity
    assert refusal_kind(flat) == "unconfirmed" and named_rival(rivals[:1]) is None
    # a symmetry of the mesh (under a quarter pixel here) is named first, whatever the photos say
    box = PhotoCheck(None, fit, 2.0, 3.0, rivals, 0, [], [], (180.0, 0.01), 0.26)  # type: ignore[arg-type]
    assert (why := refusal(box)) and "symmetric under a turn of 180 deg" in why and refusal_kind(box) == "symmetric"
    assert refusal(PhotoCheck(None, fit, 2.0, 3.0, rivals, 0, [], [], (16.0, 0.8), 0.26)) is None  # type: ignore[arg-type]
