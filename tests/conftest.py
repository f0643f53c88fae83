"""bpy must be imported before torch (both bundle native libraries); do it once for the suite."""

try:
    import bpy  # noqa: F401
except ImportError:  # the engine's tests run without Blender
    bpy = None

import pytest  # noqa: E402
from scans import make_virtual_scan  # noqa: E402


@pytest.fixture(scope="session")
def scan24(tmp_path_factory):
    """A 24-photo virtual scan of the demo asset at 0.25 scale (enough for SfM), shared by the suite."""
    return make_virtual_scan(tmp_path_factory.mktemp("scan24") / "scan", 24, 0.25, 5)
