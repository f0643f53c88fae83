import os
import subprocess
import sys
from pathlib import Path

import numpy as np

from ntp_engine.io import jit


@jit.compiled()
def _add_one(x):
    return x + 1


def test_compiled_is_numba_and_caches_where_it_can():
    assert jit.CACHE  # the test tree is writable
    assert _add_one(np.arange(3)).tolist() == [1, 2, 3]


def test_a_read_only_install_with_a_read_only_home_still_runs(tmp_path):
    """numba's cache=True raised at import where neither the package nor HOME is writable: every
    command died (``ntp --help`` too). A package folder we cannot write to: HOME and NUMBA_CACHE_DIR
    under a file (nothing can be created there), and the package copied into a folder made
    unwritable by pointing numba's in-tree cache at a file (its __pycache__)."""
    site = tmp_path / "site"
    pkg = Path(jit.__file__).parents[1]
    (site / "ntp_engine" / "io").mkdir(parents=True)
    for f in ("__init__.py", "io/__init__.py", "io/jit.py"):
        (site / "ntp_engine" / f).write_text((pkg / f).read_text())
    blocker = tmp_path / "a-file"
    blocker.write_text("")
    (site / "ntp_engine" / "io" / "__pycache__").write_text("")  # no cache folder can go here
    env = {**os.environ, "HOME": str(blocker / "home"), "XDG_CACHE_HOME": str(blocker / "cache")}
    env.pop("NUMBA_CACHE_DIR", None)
    code = "import ntp_engine.io.jit as j; print(j.CACHE, j.compiled()(lambda x: x * 2)(21))"
    r = subprocess.run(
        [sys.executable, "-c", code], env={**env, "PYTHONPATH": str(site)}, capture_output=True, text=True, cwd=tmp_path
    )
    assert r.returncode == 0, r.stderr[-2000:]
    assert r.stdout.split() == ["False", "42"]
