"""bpy must be imported before torch (both bundle native libraries); do it once for the suite."""
try:
    import bpy  # noqa: F401
except ImportError:  # the engine's tests run without Blender
    bpy = None

import subprocess  # noqa: E402
import sys  # noqa: E402

import pytest  # noqa: E402


@pytest.fixture(scope="session")
def scan24(tmp_path_factory):
    """A 24-photo virtual scan of the demo asset at 0.25 scale (enough for SfM), shared by the suite."""
    out = tmp_path_factory.mktemp("scan24") / "scan"
    r = subprocess.run([sys.executable, "-m", "ntp_engine.cli", "virtual-scan", "--out", str(out), "--views", "24",
                        "--scale", "0.25", "--seed", "5"], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    return out
