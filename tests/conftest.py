"""bpy must be imported before torch (both bundle native libraries); do it once for the suite."""

try:
    import bpy  # noqa: F401
except ImportError:  # the engine's tests run without Blender
    bpy = None

from pathlib import Path  # noqa: E402

import pytest  # noqa: E402
from scans import make_virtual_scan  # noqa: E402


@pytest.fixture(scope="session")
def scan24(tmp_path_factory):
    """A 24-photo virtual scan of the demo asset at 0.25 scale (enough for SfM), shared by the suite."""
    return make_virtual_scan(tmp_path_factory.mktemp("scan24") / "scan", 24, 0.25, 5)


@pytest.fixture(scope="session")
def ray_local():
    """A local Ray instance (2 CPUs) for the suite's ``--ray`` tests; ``RayPool`` reuses it."""
    ray = pytest.importorskip("ray")
    tests = str(Path(__file__).parent)  # the tasks of tests/ray_tasks.py, importable by the workers
    ray.init(
        num_cpus=2,
        include_dashboard=False,
        log_to_driver=False,
        configure_logging=False,
        runtime_env={"env_vars": {"PYTHONPATH": tests}},
    )
    yield ray
    ray.shutdown()
