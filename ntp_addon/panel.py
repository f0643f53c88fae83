"""The "NTP" tab in the 3D view's sidebar."""
from __future__ import annotations

import bpy

from ntp_engine.device import Device
from ntp_engine.errors import NtpInputError

def _device_lines(path: str) -> list[str]:
    try:
        return Device.load(bpy.path.abspath(path) if path else None).summary().splitlines()
    except NtpInputError as err:
        return [f"error: {err}"]

class NTP_PT_device(bpy.types.Panel):
    bl_idname = "NTP_PT_device"
    bl_label = "Scanner device"
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "NTP"

    def draw(self, context):
        layout = self.layout
        layout.prop(context.scene, "ntp_device_path")
        box = layout.box()
        for line in _device_lines(context.scene.ntp_device_path):
            box.label(text=line)

def register_properties() -> None:
    bpy.types.Scene.ntp_device_path = bpy.props.StringProperty(
        name="Device", description="Scanner calibration TOML (empty: the paper's 32x16 LED array)",
        subtype="FILE_PATH", default="",
    )

def unregister_properties() -> None:
    del bpy.types.Scene.ntp_device_path
