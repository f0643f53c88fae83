"""Blender scene pieces: cameras from the device's OpenCV calibration and poses, a Cycles setup
that matches the engine's renderer, point lights, a key-light rig and a turntable.

Conventions: poses are camera-from-world 4x4 in OpenCV axes (x right, y down, z forward); Blender
cameras look down -Z with +Y up, so world-from-camera is flipped by diag(1, -1, -1). Device pixel
centres sit at integer coordinates, so the image centre is ((W - 1) / 2, (H - 1) / 2). A Blender
point light of power P has radiant intensity P / (4 pi) W/sr.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import bpy
import numpy as np
from mathutils import Matrix

from ntp_engine.io.images import read_image
from ntp_engine.scanner.camera import look_at
from ntp_engine.scanner.device_file import load_scanner
from ntp_engine.scanner.scanner import Scanner

FLIP = np.diag([1.0, -1.0, -1.0, 1.0])


def camera_object(
    name: str, cam: Scanner, camera_from_world: np.ndarray, collection: bpy.types.Collection | None = None
) -> bpy.types.Object:
    """A camera object with the device's pinhole intrinsics (distortion is not modelled) at a pose."""
    data = bpy.data.cameras.new(name)
    data.sensor_fit = "HORIZONTAL"
    data.sensor_width = 36.0
    W, H = cam.width, cam.height
    fx, cx, cy = float(cam.K[0, 0]), float(cam.K[0, 2]), float(cam.K[1, 2])
    data.lens = fx * data.sensor_width / W
    data.shift_x = ((W - 1) / 2 - cx) / W
    data.shift_y = (cy - (H - 1) / 2) / W
    data.clip_start, data.clip_end = 0.005, 100.0
    obj = bpy.data.objects.new(name, data)
    obj.matrix_world = Matrix((np.linalg.inv(camera_from_world) @ FLIP).tolist())
    (collection or bpy.context.scene.collection).objects.link(obj)
    return obj


def setup_cycles(scene: bpy.types.Scene, width: int, height: int, samples: int = 64) -> None:
    """Direct light only, no denoising, black world, a ~1-sample-per-pixel-area pixel filter and a
    linear view transform: Cycles then computes what the engine does (docs/design.md)."""
    scene.render.engine = "CYCLES"
    scene.cycles.device = "CPU"
    scene.cycles.samples = samples
    scene.cycles.use_denoising = False
    scene.cycles.max_bounces = 0
    scene.cycles.pixel_filter_type = "GAUSSIAN"  # Cycles' box filter is always 1 px wide
    scene.cycles.filter_width = 0.01
    scene.render.resolution_x, scene.render.resolution_y = width, height
    scene.render.resolution_percentage = 100
    scene.render.film_transparent = False
    scene.view_settings.view_transform = "Standard"
    scene.world = None  # a new World carries a grey background; none is black
    # nothing clamped or blurred: Cycles' defaults clip every indirect sample above 10 (an LED's
    # light bounced off the support is far above that in the scanner's raw units — the gallery's
    # Cycles scans held ~1/8 of the support's light) and blur glossy bounces
    scene.cycles.sample_clamp_direct = scene.cycles.sample_clamp_indirect = 0.0
    scene.cycles.blur_glossy = 0.0


def point_light(
    name: str, position: np.ndarray, power_w: float, collection: bpy.types.Collection | None = None
) -> bpy.types.Object:
    """A point light of ``power_w`` watts at ``position`` (world, metres)."""
    data = bpy.data.lights.new(name, type="POINT")
    data.energy = power_w
    data.shadow_soft_size = 0.0
    obj = bpy.data.objects.new(name, data)
    obj.location = tuple(float(v) for v in position)
    (collection or bpy.context.scene.collection).objects.link(obj)
    return obj


def render_exr(scene: bpy.types.Scene, path: Path) -> np.ndarray:
    """Render the scene's camera to a float EXR; returns linear RGB ``(H, W, 3)`` (row 0 = top)."""

    scene.render.image_settings.file_format = "OPEN_EXR"
    scene.render.image_settings.color_depth = "32"
    scene.render.filepath = str(path)
    bpy.ops.render.render(write_still=True)
    return read_image(path)[..., :3]


def bounds(obj: bpy.types.Object) -> tuple[np.ndarray, float]:
    """World-space bounding-box centre of an object and the radius of the sphere about it that holds
    every vertex (tighter than half the box's diagonal: a dome or a vase fills the frame)."""
    points = (
        np.array([obj.matrix_world @ v.co for v in obj.data.vertices]) if len(obj.data.vertices) else np.zeros((1, 3))
    )
    centre = 0.5 * (points.min(0) + points.max(0))
    return centre, float(np.linalg.norm(points - centre, axis=1).max())


RELIGHT_PREFIX = "NTP Relight"


def render_still(scene: bpy.types.Scene, path: Path, file_format: str = "PNG") -> None:
    """Render ``scene``'s camera to ``path`` (the scene's own settings; no other scene touched)."""
    scene.render.image_settings.file_format = file_format
    scene.render.filepath = str(path)
    bpy.ops.render.render(write_still=True, scene=scene.name)


def open_on(scene: bpy.types.Scene) -> None:
    """Make ``scene`` the one every window shows, so a .blend saved now opens on it (F12 renders
    it). Background mode has the startup file's window too; with no window this does nothing."""
    for window in bpy.context.window_manager.windows:
        window.scene = scene


def relight_rig(
    obj: bpy.types.Object, width: int = 640, height: int = 512, samples: int = 64, turntable_frames: int = 0
) -> dict:
    """A look-dev scene for ``obj`` of its own, ``NTP Relight (OBJECT)``: the object linked in (the
    same datablock, not a copy), Cycles, a camera and a three-point area-light rig (key, fill, rim)
    sized from its bounds, AgX; optionally a turntable — the rig orbits the object 360 degrees
    about world z over ``turntable_frames`` frames, so the object keeps its own transform and
    animation. The user's scenes, worlds, cameras and settings are left as they were; building it
    again replaces the rig scene. Returns the scene and the rig's objects."""
    name = f"{RELIGHT_PREFIX} ({obj.name})"
    old = bpy.data.scenes.get(name)
    if old is not None:
        for o in list(old.collection.all_objects):
            if o.name.startswith("NTP ") and o is not obj:
                bpy.data.objects.remove(o, do_unlink=True)
        bpy.data.scenes.remove(old)
    scene = bpy.data.scenes.new(name)
    scene.collection.objects.link(obj)
    setup_cycles(scene, width, height, samples)
    scene.cycles.max_bounces = 4
    scene.view_settings.view_transform = "AgX"
    centre, radius = bounds(obj)
    dist = max(radius, 1e-3) * 4.0
    pivot = bpy.data.objects.new(f"NTP Turntable ({obj.name})", None)
    pivot.location = tuple(float(v) for v in centre)
    scene.collection.objects.link(pivot)
    cam_pos = centre + dist * np.array([0.0, -0.82, 0.57])
    f = 0.5 * width / math.tan(math.radians(22))
    lens = dataclasses.replace(
        load_scanner(),
        width=width,
        height=height,
        K=np.array([[f, 0, (width - 1) / 2], [0, f, (height - 1) / 2], [0, 0, 1]]),
    )
    cam = camera_object(f"NTP Camera ({obj.name})", lens, look_at(cam_pos, centre), scene.collection)
    scene.camera = cam
    rig: dict = {"scene": scene, "camera": cam, "pivot": pivot}
    for label, direction, share, size in (
        ("Key", (-0.6, -0.6, 0.7), 1.0, 0.5),
        ("Fill", (0.8, -0.4, 0.3), 0.3, 1.0),
        ("Rim", (0.2, 0.9, 0.6), 0.6, 0.4),
    ):
        d = np.array(direction) / np.linalg.norm(direction)
        data = bpy.data.lights.new(f"NTP {label} ({obj.name})", type="AREA")
        # irradiance ~ P / (pi d^2) from a small area light: P = share * pi^2 d^2 puts a white
        # Lambertian surface facing the key light near display white, at any object scale
        data.energy = share * math.pi**2 * dist**2
        data.size = size * dist
        light = bpy.data.objects.new(data.name, data)
        pos = centre + dist * d
        m = np.linalg.inv(look_at(pos, centre)) @ FLIP  # area lights emit along -Z, like cameras look
        light.matrix_world = Matrix(m.tolist())
        scene.collection.objects.link(light)
        rig[label.lower()] = light
    # the rig turns about the object's centre; the pivot's matrix_world is not evaluated yet (no
    # depsgraph update in a scene nobody shows), so its inverse comes from its location
    at_pivot = Matrix.Translation(tuple(float(v) for v in centre)).inverted()
    for o in (cam, rig["key"], rig["fill"], rig["rim"]):
        o.parent = pivot
        o.matrix_parent_inverse = at_pivot
    if turntable_frames > 0:
        scene.frame_start, scene.frame_end = 1, turntable_frames
        pivot.keyframe_insert("rotation_euler", index=2, frame=1)
        # the rig turns the other way: the object appears to turn 360 degrees (last frame != first)
        pivot.rotation_euler[2] = -2 * math.pi * turntable_frames / (turntable_frames + 1)
        pivot.keyframe_insert("rotation_euler", index=2, frame=turntable_frames)
        action = pivot.animation_data.action
        for fc in action.fcurves if hasattr(action, "fcurves") else []:
            for k in fc.keyframe_points:
                k.interpolation = "LINEAR"
    return rig
