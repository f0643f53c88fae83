"""ntp Blender add-on: the thin Blender layer over ``ntp_engine`` (which never imports bpy).

Sidebar tab "NTP" in the 3D view (``panel``), operators (``operators``, also in File → Import),
scene properties (``properties``), preferences (``preferences``), the coverage overlay
(``coverage``), material building (``material`` over the bpy-free ``derive``), Cycles scene
helpers (``scene``), headless export (``python -m ntp_addon.batch``).
"""

from __future__ import annotations

import atexit

import bpy

from . import operators, panel, preferences, properties

_CLASSES = (*preferences.CLASSES, *operators.CLASSES, *panel.CLASSES)


def register() -> None:
    """Register the add-on's properties, operators and panels with Blender."""
    properties.register()
    for cls in _CLASSES:
        bpy.utils.register_class(cls)
    bpy.types.TOPBAR_MT_file_import.append(operators.menu_import)
    if operators.stop_children not in bpy.app.handlers.load_pre:  # another file: no orphaned child
        bpy.app.handlers.load_pre.append(operators.stop_children)
    atexit.register(operators.stop_children)


def unregister() -> None:
    """Remove everything ``register`` added."""
    operators.stop_children()
    if operators.stop_children in bpy.app.handlers.load_pre:
        bpy.app.handlers.load_pre.remove(operators.stop_children)
    atexit.unregister(operators.stop_children)
    bpy.types.TOPBAR_MT_file_import.remove(operators.menu_import)
    for cls in reversed(_CLASSES):
        bpy.utils.unregister_class(cls)
    properties.unregister()
