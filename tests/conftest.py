"""bpy must be imported before torch (both bundle native libraries); do it once for the suite."""
try:
    import bpy  # noqa: F401
except ImportError:  # the engine's tests run without Blender
    bpy = None

import subprocess  # noqa: E402
import sys  # noqa: E402

import pytest  # noqa: E402


def make_virtual_scan(out, views: int, scale: float, seed: int):
    """``ntp virtual-scan`` of the demo asset into ``out`` (a real subprocess, as users run it)."""
    r = subprocess.run([sys.executable, "-m", "ntp_engine.cli", "virtual-scan", "--out", str(out), "--views",
                        str(views), "--scale", str(scale), "--seed", str(seed)], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    return out


@pytest.fixture(scope="session")
def scan24(tmp_path_factory):
    """A 24-photo virtual scan of the demo asset at 0.25 scale (enough for SfM), shared by the suite."""
    return make_virtual_scan(tmp_path_factory.mktemp("scan24") / "scan", 24, 0.25, 5)
