"""bpy must be imported before torch (both bundle native libraries); do it once for the suite.

The ``slow`` tier: a test that runs SfM, Cycles, Ray or a whole pipeline (a scan, a registration, a
reconstruction, a batch, the demo) is marked ``slow`` here, by what it uses — the suite's shared
scans and Ray instance, the ``blender`` marker, or a call of one of those entry points in its body
— so that no one has to remember the marker. ``make test-fast`` runs the rest (``-m "not slow"``);
``make test`` runs everything."""

try:
    import bpy  # noqa: F401
except ImportError:  # the engine's tests run without Blender
    bpy = None

import inspect  # noqa: E402
from pathlib import Path  # noqa: E402

import pytest  # noqa: E402
from scans import make_virtual_scan  # noqa: E402


@pytest.fixture(scope="session")
def scan24(tmp_path_factory):
    """A 24-photo virtual scan of the demo asset at 0.25 scale (enough for SfM), shared by the suite."""
    return make_virtual_scan(tmp_path_factory.mktemp("scan24") / "scan", 24, 0.25, 5)


@pytest.fixture(scope="session")
def colmap24(scan24, tmp_path_factory):
    """pycolmap's SfM of ``scan24`` as pycolmap wrote it (binary): (model folder, the SfM result, scan)."""
    import pycolmap

    from ntp_engine.register.sfm import structure_from_motion
    from ntp_engine.scanner.scan_folder import load_scan

    scan = load_scan(scan24)
    work = tmp_path_factory.mktemp("colmap24") / "sfm"
    sfm = structure_from_motion(scan.photos_dir, [p.name for p in scan.photo_paths], scan.scanner, work)
    folder = max((work / "sparse").iterdir(), key=lambda d: pycolmap.Reconstruction(str(d)).num_reg_images())
    return folder, sfm, scan


@pytest.fixture(scope="session")
def colmap24_registered(scan24, colmap24, tmp_path_factory):
    """``ntp register SCAN24 --colmap MODEL``'s result folder, made with SfM switched off (the model
    must stand in for it); the suite's COLMAP tests read it, and re-runs on it find its cache."""
    from ntp_engine import cli

    def no_sfm(*args, **kwargs):
        raise AssertionError("SfM ran although a COLMAP model was given")

    out = tmp_path_factory.mktemp("colmap24_registered") / "rec"
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr("ntp_engine.pipeline.stages.structure_from_motion", no_sfm)
        argv = ["register", str(scan24), "--out", str(out), "--colmap", str(colmap24[0]), "--quiet"]
        assert cli.main([*argv, "--progress", str(out.parent / "progress.jsonl")]) == 0
    return out


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


# what makes a test slow: the shared fixtures that run SfM / Ray, and calls in a test's body
SLOW_FIXTURES = {"scan24", "colmap24", "colmap24_registered", "ray_local"}
SLOW_CALLS = (
    "reconstruct(",
    "register_photos(",
    "structure_from_motion(",
    "fill_from_sfm(",
    "cycles_scan(",
    "make_virtual_scan(",
    "virtual_scan(",
    "run_demo(",
    "reconstruct_collection(",
    "subprocess",
    '"reconstruct"',
    '"register"',
    '"batch"',
    '"demo"',
    '"virtual-scan"',
    '"bench"',
)


def _is_slow(item: pytest.Item) -> bool:
    if SLOW_FIXTURES & set(getattr(item, "fixturenames", ())) or item.get_closest_marker("blender"):
        return True
    fn = getattr(item, "function", None)
    try:
        body = inspect.getsource(fn) if fn is not None else ""
    except (OSError, TypeError):
        return False
    return any(call in body for call in SLOW_CALLS)


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    """Mark the slow tier (module docstring)."""
    for item in items:
        if _is_slow(item):
            item.add_marker(pytest.mark.slow)


# ``make test`` runs the suite in one process per core (pytest-xdist), each test a unit of work,
# except the modules whose tests take the COLMAP fixtures (``colmap24``, ``colmap24_registered``:
# an SfM run and a registration, ~2 minutes): one unit, so that one process builds them. A test
# elsewhere that takes them is still right, it builds its own. (xdist's own ``--dist loadgroup``
# does not group under pytest 9: it renames node ids that pytest 9 no longer reads.)
SHARED_COLMAP_MODULES = (
    "tests/addon/test_addon.py",
    "tests/register/test_colmap_model.py",
    "tests/pipeline/test_stages.py",
    "tests/register/test_sfm.py",
)

try:
    from xdist.scheduler import LoadScopeScheduling
except ImportError:  # the suite runs in one process without xdist
    LoadScopeScheduling = None

if LoadScopeScheduling is not None:

    class _SharedFixtureScheduling(LoadScopeScheduling):
        """Each test its own unit of work but those of ``SHARED_COLMAP_MODULES``, which are one."""

        def _split_scope(self, nodeid: str) -> str:
            module = nodeid.split("::", 1)[0]
            return "colmap24" if module in SHARED_COLMAP_MODULES else nodeid

    def pytest_xdist_make_scheduler(config, log):
        """The suite's scheduler when run with ``-n`` (see ``SHARED_COLMAP_MODULES``)."""
        return _SharedFixtureScheduling(config, log)
