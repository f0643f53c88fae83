"""The "NTP" tab in the 3D view's sidebar: scan settings, the five operators, status, device."""

from __future__ import annotations

import bpy

from ntp_engine.io.assets import DOCS_DIR
from ntp_engine.io.errors import NtpInputError
from ntp_engine.scanner.device_file import load_scanner

from . import coverage

HELP_STEPS = (
    "1  Scan folder: scan.toml, mesh, photos/",
    "2  Import mesh, Register photos (or File > Import >",
    "    COLMAP model) and check the cameras",
    "3  Reconstruct (ESC cancels, a re-run resumes)",
    "4  Coverage: red = scan there again",
    "5  Build material, Relight preview (F12)",
)
GUIDES = (("blender.md", "Blender guide"), ("pipeline.md", "Pipeline and messages"), ("accuracy.md", "Accuracy"))


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
        for prop in ("scan_folder", "device", "colmap_folder", "model", "resolution", "result_folder"):
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
        col.prop(s, "coverage", icon="MOD_UVPROJECT")
        if s.coverage != "off":
            _legend(self.layout.box(), s.coverage)
        if s.status:
            box = self.layout.box()
            box.label(text=s.status)
            if 0 < s.progress < 100:
                box.prop(s, "progress", slider=True)


class _SubPanel:
    """A closed-by-default sub-panel of the NTP tab."""

    bl_space_type = "VIEW_3D"
    bl_region_type = "UI"
    bl_category = "NTP"
    bl_parent_id = "NTP_PT_scan"
    bl_options = {"DEFAULT_CLOSED"}


class NTP_PT_device(_SubPanel, bpy.types.Panel):
    """The scanner device's summary, under the NTP tab."""

    bl_idname = "NTP_PT_device"
    bl_label = "Scanner device"

    def draw(self, context):
        """Lay out the device summary."""
        box = self.layout.box()
        for line in _device_lines(context.scene.ntp.device):
            box.label(text=line)


def _legend(box, key: str) -> None:
    """The coverage overlay's legend: the ramp, what its ends mean, what to do about red."""
    layer = coverage.LAYERS[key]
    box.label(text=layer.label)
    node = coverage.legend_node()
    if node is not None:
        box.template_color_ramp(node, "color_ramp", expand=False)
    row = box.row()
    row.label(text=layer.legend[0])
    row.alignment = "EXPAND"
    row.label(text=layer.legend[1])
    box.label(text=layer.hint)


class NTP_PT_help(_SubPanel, bpy.types.Panel):
    """The workflow in five steps and the user guides, under the NTP tab."""

    bl_idname = "NTP_PT_help"
    bl_label = "Help"

    def draw(self, context):
        """Lay out the steps and a button per guide."""
        col = self.layout.column(align=True)
        for line in HELP_STEPS:
            col.label(text=line)
        col = self.layout.column(align=True)
        for file, title in GUIDES:
            if (DOCS_DIR / file).is_file():
                col.operator("wm.path_open", text=title, icon="HELP").filepath = str(DOCS_DIR / file)


CLASSES = (NTP_PT_scan, NTP_PT_device, NTP_PT_help)
