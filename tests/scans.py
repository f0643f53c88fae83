"""Virtual scans for the tests, made the way a user makes them (the ``ntp`` command in a subprocess)."""

import subprocess
import sys
from pathlib import Path


def make_virtual_scan(out: Path, views: int, scale: float, seed: int) -> Path:
    """``ntp virtual-scan`` of the demo asset into ``out`` (a real subprocess, as users run it)."""
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "ntp_engine.cli",
            "virtual-scan",
            "--out",
            str(out),
            "--views",
            str(views),
            "--scale",
            str(scale),
            "--seed",
            str(seed),
        ],
        capture_output=True,
        text=True,
    )
    assert r.returncode == 0, r.stderr
    return out
