"""``ntp bench blender``: Cycles rendering the accurate and the Principled material against the
engine's render of the same result, and the preview's seconds — run by the add-on's bench script in
Blender's Python (``io.blender_process``: the engine never imports bpy)."""

from __future__ import annotations

import argparse
import subprocess
from pathlib import Path

from ..io.blender_process import blender_command

HELP = "Cycles (both materials) vs the engine's render; preview seconds"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """``ntp bench blender``'s options."""
    parser.add_argument("--views", type=int, default=3)
    parser.add_argument("--samples", type=int, default=64)
    parser.add_argument("--json", type=Path, default=None)


def command(args: argparse.Namespace) -> int:
    """``ntp bench blender``: the benchmark with the command line's options; the exit code."""
    cmd = blender_command("bench", "--views", str(args.views), "--samples", str(args.samples))
    return subprocess.call(cmd + (["--json", str(args.json)] if args.json else []))
