"""``ntp bench blender`` hands its options to the add-on's bench script in Blender's Python."""

import argparse
import subprocess
import sys

from ntp_engine.bench import blender


def test_the_options_reach_the_add_ons_bench_script(monkeypatch, tmp_path):
    parser = argparse.ArgumentParser()
    blender.add_arguments(parser)
    assert vars(parser.parse_args([])) == {"views": 3, "samples": 64, "json": None}
    calls = []
    monkeypatch.setattr(subprocess, "call", lambda cmd: calls.append(cmd) or 7)
    args = parser.parse_args(["--views", "2", "--samples", "8", "--json", str(tmp_path / "b.json")])
    assert blender.command(args) == 7  # the script's exit code is the command's
    assert calls == [
        [sys.executable, "-m", "ntp_addon.bench", "--views", "2", "--samples", "8", "--json", str(tmp_path / "b.json")]
    ]
