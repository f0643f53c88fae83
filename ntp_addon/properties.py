"""Scene properties of the add-on (``scene.ntp``): saved with the .blend, undoable."""

from __future__ import annotations

import bpy

from ntp_engine.pipeline.stages import DEFAULT_RESOLUTION, MIN_RESOLUTION

from . import coverage


class NTPSettings(bpy.types.PropertyGroup):
    """The add-on's settings on the scene (``scene.ntp``)."""

    scan_folder: bpy.props.StringProperty(
        name="Scan folder", subtype="DIR_PATH", description="Folder with scan.toml, the pre-scanned mesh and photos/"
    )
    device: bpy.props.StringProperty(
        name="Device", subtype="FILE_PATH", description="Scanner calibration TOML (empty: the scan's own device file)"
    )
    model: bpy.props.StringProperty(
        name="Model", default="", description="Shipped model name or a model folder (empty: the add-on preference's)"
    )
    colmap_folder: bpy.props.StringProperty(
        name="COLMAP model",
        subtype="DIR_PATH",
        description="An existing COLMAP model (cameras/images/points3D) to register from instead of running SfM",
    )
    resolution: bpy.props.IntProperty(
        name="Resolution",
        default=DEFAULT_RESOLUTION,
        min=MIN_RESOLUTION,
        max=8192,
        description="Texture maps are resolution x resolution",
    )
    result_folder: bpy.props.StringProperty(
        name="Result folder", subtype="DIR_PATH", description="Where Reconstruct writes maps (empty: next to the scan)"
    )
    variant: bpy.props.EnumProperty(
        name="Material",
        default="accurate",
        items=[
            ("accurate", "Accurate", "Diffuse + Glossy GGX: the engine's model as closely as nodes allow"),
            ("principled", "Principled", "Anisotropic Principled BSDF (what glTF exports)"),
        ],
    )
    turntable_frames: bpy.props.IntProperty(
        name="Turntable frames", default=0, min=0, max=10000, description="0: no turntable"
    )
    coverage: bpy.props.EnumProperty(
        name="Coverage",
        default="off",
        items=coverage.ITEMS,
        update=coverage.on_change,
        description="Show on the active mesh where the photos measured well and where to scan more",
    )
    status: bpy.props.StringProperty(name="Status", default="")
    progress: bpy.props.FloatProperty(name="Progress", default=0.0, min=0.0, max=100.0, subtype="PERCENTAGE")


def register() -> None:
    """Register the settings and attach them to every scene."""
    bpy.utils.register_class(NTPSettings)
    bpy.types.Scene.ntp = bpy.props.PointerProperty(type=NTPSettings)


def unregister() -> None:
    """Detach and unregister the settings."""
    del bpy.types.Scene.ntp
    bpy.utils.unregister_class(NTPSettings)
