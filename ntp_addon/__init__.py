"""ntp Blender add-on: the thin Blender layer over ``ntp_engine`` (which never imports bpy).

This first version adds the "NTP" sidebar tab in the 3D view with the scanner device in use.
"""
from __future__ import annotations

import bpy

from . import panel

_CLASSES = (panel.NTP_PT_device,)


def register() -> None:
    for cls in _CLASSES:
        bpy.utils.register_class(cls)
    panel.register_properties()


def unregister() -> None:
    panel.unregister_properties()
    for cls in reversed(_CLASSES):
        bpy.utils.unregister_class(cls)
