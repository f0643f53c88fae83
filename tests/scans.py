"""Scenes and virtual scans for the tests: a flat patch with uniform maps, and virtual scans made
the way a user makes them (the ``ntp`` command in a subprocess)."""

import subprocess
import sys
from pathlib import Path

import numpy as np

from ntp_engine.io.maps import SVBRDFMaps
from ntp_engine.io.mesh import Mesh, smooth_normals


def run_virtual_scan(out: Path, *args: str) -> subprocess.CompletedProcess:
    """``ntp virtual-scan --out OUT ARGS...`` in a subprocess, as users run it."""
    cmd = [sys.executable, "-m", "ntp_engine.cli", "virtual-scan", "--out", str(out), *args]
    return subprocess.run(cmd, capture_output=True, text=True)


def make_virtual_scan(out: Path, views: int, scale: float, seed: int) -> Path:
    """A virtual scan of the demo asset into ``out``; fails the test if the command fails."""
    r = run_virtual_scan(out, "--views", str(views), "--scale", str(scale), "--seed", str(seed))
    assert r.returncode == 0, r.stderr
    return out


def flat_patch(size: float = 0.08, res: int = 8) -> Mesh:
    """A square patch ``size`` m wide, 2 mm above z = 0, ``res`` x ``res`` quads, UVs over [0, 1]^2."""
    g = np.linspace(-size / 2, size / 2, res + 1)
    X, Y = np.meshgrid(g, g)
    v = np.stack([X.ravel(), Y.ravel(), np.full(X.size, 0.002)], -1)
    idx = np.arange(v.shape[0]).reshape(res + 1, res + 1)
    a, b, c, d = idx[:-1, :-1], idx[:-1, 1:], idx[1:, 1:], idx[1:, :-1]
    f = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)])
    uv = (v[:, :2] + size / 2) / size
    return Mesh(v, f, uv, smooth_normals(v, f))


def uniform_maps(rd, rs, ax: float, ay: float, res: int = 4) -> SVBRDFMaps:
    """Maps with one material everywhere, normal +z and tangent +x."""

    def full(val):
        return np.broadcast_to(np.asarray(val, float), (res, res, len(val))).copy()

    return SVBRDFMaps(full(rd), full(rs), full([0, 0, 1.0]), full([1.0, 0, 0]), full([ax, ay]))


def hemisphere(radius: float = 0.05, n_phi: int = 96, n_theta: int = 24) -> Mesh:
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
