"""The Cycles scanner's renderer (runs as ``python -m ntp_addon.scan_render JOB.json``): linear EXR
photos of an asset through a scanner's emitters, for ``ntp_engine.sim.cycles_scan``.

The job (written by the engine; see there) names the asset folder (``mesh.obj`` + the five maps),
the camera's device file, the emitters in camera space (centre, normal, axis, size, RGB drive), the
camera-from-world poses, samples (every pixel; up to max_samples where Cycles' noise estimate is
above noise_threshold), bounces and seed, and the calibration patch (centre, normal,
in-plane axis, size). The scene: the asset with the ``NTP Accurate`` material built with the
engine's Fresnel (Diffuse + the engine's GGX lobe with Schlick on w_i.h, bounded, as an OSL node, rendered
with OSL on the CPU: ``material``, ``schlick_lobe``), the marker backdrop
(``ntp_engine.sim.renderer.marker_albedo``, one texel per 5 mm cell, closest-texel lookup), the
marker board on it where the job has one (``board``: its layout and world-from-board 4x4; the
printed page's albedo at ``BOARD_TEXEL_MM``, linear lookup, a hair above the backdrop), and one
rectangular area light per lit emitter (Lambertian, as the device's cos^1 LEDs), moved with the
camera for every pose. Direct and indirect light (``bounces``), exact shadows. Each photo is written
as ``OUT/NAME.exr`` through a temporary name, so an interrupted job resumes where it stopped;
existing photos are kept. ``calibration.exr`` is the white Lambertian patch alone, seen from the
identity pose. One line ``rendered NAME`` per photo on stdout (the engine's progress).
"""

from __future__ import annotations

import json
import os
import sys
from pathlib import Path

import bpy  # noqa: F401  (before torch, which the engine imports)
import numpy as np
from mathutils import Matrix

from ntp_engine.scanner.board import board_from_json
from ntp_engine.scanner.device_file import load_scanner
from ntp_engine.sim.renderer import BACKDROP_HALF, BACKDROP_Z, marker_albedo

from . import material
from . import scene as bscene
from .schlick_lobe import use_osl

MARKER_CELL = 0.005  # m: the backdrop's small cells (renderer.marker_albedo); its big cells are 3 of them
BOARD_TEXEL_MM = 0.2  # the board's texture: the engine renderer's (scanner.board.Board.albedo)
BOARD_LIFT = 0.5e-4  # m above the backdrop (BACKDROP_Z = -0.1 mm): on top of it, under the object's foot


def _diffuse_material(name: str) -> tuple[bpy.types.Material, bpy.types.Node]:
    """A material of one Diffuse BSDF (roughness 0: Lambertian) and that node."""
    mat = bpy.data.materials.new(name)
    if mat.node_tree is None:  # Blender < 5 creates materials without nodes
        mat.use_nodes = True
    nt = mat.node_tree
    nt.nodes.clear()
    diffuse = nt.nodes.new("ShaderNodeBsdfDiffuse")
    diffuse.inputs["Roughness"].default_value = 0.0
    out = nt.nodes.new("ShaderNodeOutputMaterial")
    nt.links.new(diffuse.outputs[0], out.inputs["Surface"])
    return mat, diffuse


def _textured_quad(
    collection: bpy.types.Collection, name: str, half: tuple[float, float], z: float, albedo: np.ndarray, lookup: str
) -> bpy.types.Object:
    """A ``2 half[0]`` x ``2 half[1]`` rectangle at height ``z`` with a diffuse material of the grey
    ``albedo (rows, cols)`` (row 0 = top = +y) read by ``lookup`` (Blender's interpolation name)."""
    w, h = half
    mesh = bpy.data.meshes.new(name)
    mesh.from_pydata([(-w, -h, z), (w, -h, z), (w, h, z), (-w, h, z)], [], [(0, 1, 2, 3)])
    uv = mesh.uv_layers.new(name="UVMap")
    for loop, (u, v) in zip(uv.data, ((0, 0), (1, 0), (1, 1), (0, 1))):
        loop.uv = (u, v)
    img = material.packed_image(f"{name} albedo", np.repeat(albedo[..., None], 3, -1))
    mat, diffuse = _diffuse_material(name)
    tex = mat.node_tree.nodes.new("ShaderNodeTexImage")
    tex.image, tex.interpolation = img, lookup
    mat.node_tree.links.new(tex.outputs["Color"], diffuse.inputs["Color"])
    mesh.materials.append(mat)
    obj = bpy.data.objects.new(name, mesh)
    collection.objects.link(obj)
    return obj


def _backdrop(collection: bpy.types.Collection) -> bpy.types.Object:
    """The marker backdrop square at z = BACKDROP_Z, its albedo one texel per cell."""
    h = BACKDROP_HALF
    n = int(round(2 * h / MARKER_CELL))
    centres = -h + (np.arange(n) + 0.5) * MARKER_CELL
    yy, xx = np.meshgrid(centres[::-1], centres, indexing="ij")  # row 0 = top = +y
    albedo = marker_albedo(np.stack([xx, yy], -1).reshape(-1, 2)).reshape(n, n)
    return _textured_quad(collection, "backdrop", (h, h), BACKDROP_Z, albedo, "Closest")


def _board(collection: bpy.types.Collection, record: dict) -> bpy.types.Object:
    """The marker board's page on the backdrop: its albedo image (``Board.paper_image``) on a plane the
    paper's size, placed by the record's world-from-board 4x4."""
    board = board_from_json(record)
    w, h = (1e-3 * v / 2 for v in board.paper_mm)
    # row 0 = the page's top = +y
    obj = _textured_quad(collection, "marker board", (w, h), 0.0, board.paper_image(BOARD_TEXEL_MM), "Linear")
    placed = np.array(record["world_from_board"], float)
    placed[2, 3] += BOARD_LIFT  # the record places it on the backdrop: lifted clear of it
    obj.matrix_world = Matrix(placed.tolist())
    return obj


def _emitters(job: dict, collection: bpy.types.Collection) -> list[tuple[bpy.types.Object, np.ndarray]]:
    """One area light per lit emitter and its camera-from-light 4x4 (light -Z along the normal)."""
    lights = []
    for k, e in enumerate(job["emitters"]):
        rgb = np.array(e["rgb"], float)
        peak = float(rgb.max())
        data = bpy.data.lights.new(f"emitter {k}", type="AREA")
        data.shape = "RECTANGLE"
        data.size, data.size_y = e["size"]
        data.energy = peak * job["watts_per_unit_drive"]
        data.color = tuple(float(c) for c in rgb / peak)
        obj = bpy.data.objects.new(f"emitter {k}", data)
        collection.objects.link(obj)
        z = -np.array(e["normal"], float)
        x = np.array(e["axis"], float)
        m = np.eye(4)
        m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = x, np.cross(z, x), z, e["centre"]
        lights.append((obj, m))
    return lights


def _place(camera: bpy.types.Object, lights: list, camera_from_world: np.ndarray) -> None:
    world_from_camera = np.linalg.inv(camera_from_world)
    camera.matrix_world = Matrix((world_from_camera @ bscene.FLIP).tolist())
    for obj, m in lights:
        obj.matrix_world = Matrix((world_from_camera @ m).tolist())


def _render(scene: bpy.types.Scene, target: Path) -> None:
    tmp = target.with_name(f".{target.stem}.partial.exr")
    bscene.render_exr(scene, tmp)
    os.replace(tmp, target)


def _calibration(job: dict, out: Path) -> None:
    """The white Lambertian patch alone (no object, no backdrop, no bounces), identity pose."""
    scene = bpy.context.scene
    for obj in list(scene.collection.objects):
        if obj.type == "MESH":
            obj.hide_render = True
    c = job["calibration"]
    half = c["size"] / 2
    z, x = np.array(c["normal"], float), np.array(c["axis"], float)
    y = np.cross(z, x)
    corners = [np.array(c["centre"]) + half * (sx * x + sy * y) for sx, sy in ((-1, -1), (1, -1), (1, 1), (-1, 1))]
    mesh = bpy.data.meshes.new("calibration patch")
    mesh.from_pydata([tuple(v) for v in corners], [], [(0, 1, 2, 3)])
    mat, diffuse = _diffuse_material("white lambertian")
    diffuse.inputs["Color"].default_value = (1.0, 1.0, 1.0, 1.0)
    mesh.materials.append(mat)
    patch = bpy.data.objects.new("calibration patch", mesh)
    scene.collection.objects.link(patch)
    scene.cycles.samples = c["samples"]
    scene.cycles.use_adaptive_sampling = False  # a fixed count: the gain of every photo rests on it
    scene.cycles.max_bounces = 0
    _render(scene, out / "calibration.exr")


def run(job_path: Path) -> None:
    """Render every photo of the job that is not there yet, then the calibration patch."""
    job = json.loads(job_path.read_text())
    out = Path(job["out"])
    out.mkdir(parents=True, exist_ok=True)
    bpy.ops.wm.read_factory_settings(use_empty=True)
    scene = bpy.context.scene
    cam = load_scanner(Path(job["device"]))
    bscene.setup_cycles(scene, cam.width, cam.height, job["max_samples"])
    use_osl(scene)  # the asset's lobe is an OSL node (schlick_lobe)
    # every pixel gets ``samples``; a noisy one (a sharp highlight: rare hits of a small light) more
    scene.cycles.use_adaptive_sampling = job["max_samples"] > job["samples"]
    scene.cycles.adaptive_min_samples = job["samples"]
    scene.cycles.adaptive_threshold = job["noise_threshold"]
    b = job["bounces"]
    scene.cycles.max_bounces = b
    scene.cycles.diffuse_bounces = scene.cycles.glossy_bounces = b
    scene.cycles.transmission_bounces = scene.cycles.volume_bounces = scene.cycles.transparent_max_bounces = 0
    obj = material.import_result_mesh(Path(job["asset"]))
    # ground truth, not a result: the engine's BRDF, its Fresnel on w_i.h (bounded) on every path, bounces too
    material.build_materials(Path(job["asset"]), obj, "accurate", require_report=False, exact_fresnel=True)
    _backdrop(scene.collection)
    if job.get("board") is not None:
        _board(scene.collection, job["board"])
    camera = bscene.camera_object("scanner camera", cam, np.eye(4))
    scene.camera = camera
    lights = _emitters(job, scene.collection)
    for k, (name, pose) in enumerate(job["poses"].items()):
        target = out / f"{Path(name).stem}.exr"
        if not target.is_file():
            scene.cycles.seed = job["seed"] + k
            _place(camera, lights, np.array(pose, float))
            _render(scene, target)
        print(f"rendered {name}", flush=True)
    if not (out / "calibration.exr").is_file():
        _place(camera, lights, np.eye(4))
        _calibration(job, out)


def main(argv: list[str] | None = None) -> int:
    """``python -m ntp_addon.scan_render JOB.json``."""
    args = sys.argv[1:] if argv is None else argv
    if len(args) != 1:
        print("usage: python -m ntp_addon.scan_render JOB.json", file=sys.stderr)
        return 2
    run(Path(args[0]))
    return 0


if __name__ == "__main__":
    sys.exit(main())
