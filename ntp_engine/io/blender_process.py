"""The one way the engine reaches Blender: the add-on's headless scripts, each run as its own
Python process (``python -m ntp_addon.<script>``) so that the engine never imports bpy.

``BLENDER_SCRIPTS`` names every add-on module the engine may start (the architecture test holds
that no other engine module names the add-on); ``blender_command`` builds the command line and
``has_bpy`` says whether this Python can run it at all.
"""

from __future__ import annotations

import importlib.util
import sys

# the add-on modules the engine starts, by what they do
BLENDER_SCRIPTS = {
    "scan_render": "ntp_addon.scan_render",  # the Cycles scanner's renderer (``sim.cycles_scan``)
    "batch": "ntp_addon.batch",  # .blend / .glb / preview export (``ntp demo``)
    "bench": "ntp_addon.bench",  # ``ntp bench blender``
}


def has_bpy() -> bool:
    """Whether Blender's Python module is installed (the scripts need it; the engine does not)."""
    return importlib.util.find_spec("bpy") is not None


def blender_command(script: str, *args: str) -> list[str]:
    """The command line that runs the add-on's ``script`` (a key of ``BLENDER_SCRIPTS``) with
    ``args`` in this Python."""
    if script not in BLENDER_SCRIPTS:
        raise ValueError(f"no Blender script {script!r} (known: {', '.join(BLENDER_SCRIPTS)})")
    return [sys.executable, "-m", BLENDER_SCRIPTS[script], *args]


# what a user types to make a result's .glb (help texts and the result page say it)
GLB_HOWTO = f"python -m {BLENDER_SCRIPTS['batch']} RESULT --gltf A.glb"
