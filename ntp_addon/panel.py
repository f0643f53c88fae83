"""The "NTP" tab in the 3D view's sidebar: scan settings, the five operators, status, device."""

from __future__ import annotations

import bpy

from ntp_engine.io.errors import NtpInputError
from ntp_engine.scanner.device_file import load_scanner


def _device_lines(path: str) -> list[str]:
    try:
        return load_scanner(bpy.path.abspath(path) if path else None).summary().splitlines()
    except NtpInputError as err:
        return [f"error: {err}"]


class NTP_PT_scan(bpy.types.Panel):
    """The NTP sidebar tab: scan settings, operators and status."""

    bl_idname = "NTP_PT_scan"
    bl_label = "Neural Trace Photography"
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "NTP"

    def draw(self, context):
        """Lay out the panel."""
        s = context.scene.ntp
        col = self.layout.column(align=True)
        for prop in ("scan_folder", "device", "model", "resolution", "result_folder"):
            col.prop(s, prop)
        col = self.layout.column(align=True)
        col.operator("ntp.import_mesh", icon="IMPORT")
        col.operator("ntp.register_photos", icon="OUTLINER_OB_CAMERA")
        col.operator("ntp.reconstruct", icon="PLAY")
        row = col.row(align=True)
        row.prop(s, "variant", text="")
        row.operator("ntp.build_material", icon="MATERIAL")
        row = col.row(align=True)
        row.prop(s, "turntable_frames", text="Turntable")
        row.operator("ntp.relight_preview", icon="LIGHT_AREA")
        if s.status:
            box = self.layout.box()
            box.label(text=s.status)
            if 0 < s.progress < 100:
                box.prop(s, "progress", slider=True)


class NTP_PT_device(bpy.types.Panel):
    """The scanner device's summary, under the NTP tab."""

    bl_idname = "NTP_PT_device"
    bl_label = "Scanner device"
    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "NTP"
    bl_parent_id = "NTP_PT_scan"
    bl_options = {"DEFAULT_CLOSED"}

    def draw(self, context):
        """Lay out the device summary."""
        box = self.layout.box()
        for line in _device_lines(context.scene.ntp.device):
            box.label(text=line)


CLASSES = (NTP_PT_scan, NTP_PT_device)
