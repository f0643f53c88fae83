"""The Blender add-on with the real bpy: registration, every operator in background mode, the
material's node links, .blend / .glb output, and Cycles against the engine's own render."""

import json
import os
import shutil
import struct
import subprocess
import sys
from pathlib import Path

import bpy  # noqa: E402  (a pinned dependency: a missing bpy must fail, not skip)
import numpy as np
import pytest
from scans import make_virtual_scan  # noqa: E402

import ntp_addon  # noqa: E402
from ntp_addon import compare, derive, gltf, material  # noqa: E402
from ntp_addon import scene as bscene  # noqa: E402
from ntp_engine.sim.demo_asset import DEMO_DIR  # noqa: E402

pytestmark = pytest.mark.slow  # real bpy

DEMO = DEMO_DIR
REPO = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def demo_result(tmp_path_factory):
    """The demo asset's true maps laid out as a result folder."""
    d = tmp_path_factory.mktemp("demo_result")
    for f in (DEMO / "ground_truth").glob("*.exr"):
        shutil.copy(f, d / f.name)
    shutil.copy(DEMO / "mesh.obj", d / "mesh.obj")
    (d / "report.json").write_text("{}")  # complete
    return d


@pytest.fixture(scope="module")
def posed_scan(tmp_path_factory):
    out = make_virtual_scan(tmp_path_factory.mktemp("posed") / "scan", 6, 0.1, 4)
    with open(out / "scan.toml", "a") as f:
        f.write('poses = "ground_truth/poses.json"\n')
    return out


def _fresh():
    bpy.ops.wm.read_factory_settings(use_empty=True)


def test_register_unregister_twice():
    for _ in range(2):
        ntp_addon.register()
        assert hasattr(bpy.types.Scene, "ntp") and hasattr(bpy.ops.ntp, "reconstruct")
        assert "NTP_PT_scan" in dir(bpy.types)
        ntp_addon.unregister()
        assert not hasattr(bpy.types.Scene, "ntp") and "NTP_PT_scan" not in dir(bpy.types)


@pytest.fixture
def addon():
    """Enabled through Blender's add-on system, as a user does (so its preferences exist)."""
    _fresh()
    assert bpy.ops.preferences.addon_enable(module="ntp_addon") == {"FINISHED"}
    yield bpy.context.scene.ntp
    bpy.ops.preferences.addon_disable(module="ntp_addon")


def test_every_operator_in_background_mode(addon, posed_scan, tmp_path):
    s = addon
    s.scan_folder, s.resolution, s.result_folder = str(posed_scan), 24, str(tmp_path / "result")
    prefs = bpy.context.preferences.addons["ntp_addon"].preferences
    prefs.threads, prefs.cache_root = 1, str(tmp_path / "caches")  # the engine child obeys the preferences
    assert bpy.ops.ntp.import_mesh() == {"FINISHED"}
    obj = bpy.context.view_layer.objects.active
    assert obj.type == "MESH" and len(obj.data.vertices) > 100
    assert bpy.ops.ntp.register_photos() == {"FINISHED"}
    cams = bpy.data.collections["NTP Cameras"].objects
    assert len(cams) == 6 and all(c.type == "CAMERA" and c.data.background_images[0].image for c in cams)
    truth = json.loads((posed_scan / "ground_truth" / "poses.json").read_text())
    c0 = np.array(cams["NTP 0000.png"].matrix_world)
    g = np.array(truth["0000.png"])
    assert np.abs(c0[:3, 3] - (-g[:3, :3].T @ g[:3, 3])).max() < 1e-5  # camera centre
    assert np.abs(c0[:3, 2] + g[2, :3]).max() < 1e-5  # Blender looks down -Z, OpenCV along +z
    from ntp_engine.scanner.scan_folder import load_scan

    dev = load_scan(posed_scan).scanner
    r = bpy.context.scene.render
    assert (r.resolution_x, r.resolution_y, r.resolution_percentage) == (dev.width, dev.height, 100)
    assert bpy.ops.ntp.register_photos() == {"FINISHED"}  # again: replaced, not added
    assert len(bpy.data.collections["NTP Cameras"].objects) == 6 and len(bpy.data.cameras) == 6
    assert bpy.ops.ntp.reconstruct() == {"FINISHED"}  # background mode: waits for the child process
    assert (tmp_path / "result" / "normal.exr").is_file() and "texels observed" in s.status
    caches = list((tmp_path / "caches").iterdir())
    assert [c.name[:7] for c in caches] == ["result-"] and (caches[0] / "fit").is_dir()
    assert not (tmp_path / "result" / "cache").exists()
    assert bpy.ops.ntp.build_material() == {"FINISHED"}
    assert obj.data.materials[0].name.startswith(material.ACCURATE)
    s.turntable_frames = 24
    assert bpy.ops.ntp.relight_preview() == {"FINISHED"}
    rig = bpy.data.scenes[f"NTP Relight ({obj.name})"]
    assert rig.camera is not None and rig.frame_end == 24 and obj.name in rig.collection.objects
    assert len([o for o in rig.collection.objects if o.type in ("CAMERA", "LIGHT")]) == 4


def test_relight_preview_leaves_the_users_scene_alone(demo_result):
    _fresh()
    scene = bpy.context.scene
    world = bpy.data.worlds.new("user HDRI")
    scene.world = world
    cam = bpy.data.objects.new("user camera", bpy.data.cameras.new("user camera"))
    scene.collection.objects.link(cam)
    scene.camera = cam
    scene.render.resolution_x, scene.render.resolution_y = 1234, 567
    scene.view_settings.view_transform = "Standard"
    scene.cycles.use_denoising, scene.cycles.filter_width = True, 1.7
    obj = material.import_result_mesh(demo_result)
    obj.location.x = 0.25
    obj.keyframe_insert("location", index=0, frame=10)
    settings = lambda: (  # noqa: E731
        scene.world, scene.camera, scene.render.resolution_x, scene.render.resolution_y,
        scene.view_settings.view_transform, scene.cycles.use_denoising, scene.cycles.filter_width,
        scene.frame_end, tuple(obj.matrix_world.translation), len(scene.objects),
    )  # fmt: skip
    before = settings()
    for _ in range(2):  # built again: replaced, not duplicated
        rig = bscene.relight_rig(obj, 64, 48, samples=2, turntable_frames=12)
    assert settings() == before and world.users > 0 and cam.name in bpy.data.objects
    assert obj.animation_data.action is not None  # the user's animation is kept
    assert len([s for s in bpy.data.scenes if s.name.startswith("NTP Relight")]) == 1
    assert rig["scene"].frame_end == 12 and rig["pivot"].animation_data.action is not None
    from bpy_extras.object_utils import world_to_camera_view
    from mathutils import Vector

    centre = Vector(bscene.bounds(obj)[0].tolist())
    depsgraph = rig["scene"].view_layers[0].depsgraph
    for frame in (1, 7):  # as rendered, at any turntable frame the object is in the middle of the picture
        rig["scene"].frame_set(frame)
        depsgraph.update()
        cam = rig["camera"].evaluated_get(depsgraph)
        assert (world_to_camera_view(rig["scene"], cam, centre).xy - Vector((0.5, 0.5))).length < 1e-3
    assert len([o for o in bpy.data.objects if o.name.startswith("NTP Key")]) == 1  # no orphaned rig objects


def test_bad_result_folder_is_reported_and_builds_nothing(addon, demo_result, tmp_path):
    broken = tmp_path / "broken"
    shutil.copytree(demo_result, broken)
    (broken / "roughness.exr").unlink()
    addon.result_folder = str(broken)
    n_mat, n_img = len(bpy.data.materials), len(bpy.data.images)
    with pytest.raises(RuntimeError, match="roughness.exr.*missing"):  # bpy turns an ERROR report into this
        bpy.ops.ntp.build_material()
    assert len(bpy.data.materials) == n_mat and len(bpy.data.images) == n_img
    incomplete = tmp_path / "incomplete"
    shutil.copytree(demo_result, incomplete)
    (incomplete / "report.json").unlink()
    addon.result_folder = str(incomplete)
    with pytest.raises(RuntimeError, match="report.json: missing: the result is incomplete"):
        bpy.ops.ntp.build_material()
    assert len(bpy.data.materials) == n_mat and len(bpy.data.images) == n_img
    addon.scan_folder = str(tmp_path / "nowhere")
    with pytest.raises(RuntimeError, match="scan.toml"):
        bpy.ops.ntp.import_mesh()

    # a selected mesh without the result's UVs (the default cube, a raw scan) is refused, not painted
    addon.result_folder = str(demo_result)
    bpy.ops.mesh.primitive_cube_add()
    cube = bpy.context.active_object
    n_mat, n_img = len(bpy.data.materials), len(bpy.data.images)
    with pytest.raises(RuntimeError, match="'Cube' does not carry the result's UVs"):
        bpy.ops.ntp.build_material()
    assert len(bpy.data.materials) == n_mat and len(bpy.data.images) == n_img and not cube.data.materials
    cube.data.uv_layers.remove(cube.data.uv_layers[0])
    assert not material.carries_result_uvs(cube, material.read_result(demo_result).mesh)
    cube.select_set(False)  # active but not selected: no choice made, the result's mesh is imported
    assert bpy.ops.ntp.build_material() == {"FINISHED"} and not cube.data.materials
    built = bpy.context.view_layer.objects.active
    assert built != cube and material.carries_result_uvs(built, material.read_result(demo_result).mesh)


def test_operators_poll_and_children_stop_with_the_file(addon, posed_scan, tmp_path):
    from types import SimpleNamespace

    from ntp_addon import operators

    addon.scan_folder, addon.result_folder = "", str(tmp_path / "none")
    for op in (bpy.ops.ntp.import_mesh, bpy.ops.ntp.register_photos, bpy.ops.ntp.reconstruct):
        assert not op.poll()  # greyed out: no scan folder
    assert not bpy.ops.ntp.build_material.poll() and not bpy.ops.ntp.relight_preview.poll()
    addon.scan_folder = str(posed_scan)
    assert bpy.ops.ntp.import_mesh.poll() and bpy.ops.ntp.reconstruct.poll()
    assert bpy.ops.ntp.import_mesh() == {"FINISHED"} and bpy.ops.ntp.relight_preview.poll()  # an active mesh
    # ESC on press only
    assert operators.is_cancel(SimpleNamespace(type="ESC", value="PRESS"))
    assert not operators.is_cancel(SimpleNamespace(type="ESC", value="RELEASE"))
    assert not operators.is_cancel(SimpleNamespace(type="A", value="PRESS"))
    # a running engine child blocks new runs and is stopped when another file is loaded
    child = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    operators._CHILDREN.add(child)
    try:
        assert not bpy.ops.ntp.reconstruct.poll()
        bpy.ops.wm.read_homefile(use_empty=True)
        assert child.wait(timeout=15) is not None and child not in operators._CHILDREN
    finally:
        child.kill()
        operators._CHILDREN.discard(child)


def test_a_stopped_engine_child_leaves_no_temporaries(posed_scan, tmp_path):
    """What ESC, loading another file or quitting do to a running reconstruct: SIGINT, exit 130,
    the engine's temporaries gone (finished stages kept for a resume), the child no longer tracked."""
    import time

    from ntp_addon import operators

    out = tmp_path / "result"
    for attempt in range(5):  # a busy machine may let the small run finish first: again, fresh
        shutil.rmtree(out, ignore_errors=True)
        progress = tmp_path / f"progress{attempt}.jsonl"
        progress.touch()
        args = ["reconstruct", str(posed_scan), "--out", str(out), "--resolution", "32"]
        proc = operators.spawn_engine(args, progress)
        t0 = time.time()
        while proc.poll() is None and '"stage": "traces"' not in progress.read_text() and time.time() - t0 < 120:
            time.sleep(0.05)
        operators.stop_children()  # the load_pre / exit handler
        if proc.returncode != 0:
            break
    assert proc.returncode == 130 and proc not in operators._CHILDREN
    assert "interrupted" in proc.stderr.read()
    assert out.is_dir() and not [p for p in out.rglob(".ntp-tmp.*")]


def _link_from(sock):
    assert sock.is_linked, sock.name
    return sock.links[0].from_node


def test_material_links_are_the_intended_ones(demo_result):
    _fresh()
    obj = material.import_result_mesh(demo_result)
    p, a = material.build_materials(demo_result, obj, "principled")
    assert obj.data.materials[0] == p and a.use_fake_user
    bsdf = next(n for n in p.node_tree.nodes if n.type == "BSDF_PRINCIPLED")
    # colours as glTF reads them: 8-bit sRGB PNGs held in the file
    for name in ("Base Color", "Specular Tint"):
        img = _link_from(bsdf.inputs[name]).image
        assert img.packed_file is not None and img.colorspace_settings.name == material.SRGB and not img.is_float
    level = _link_from(bsdf.inputs["Specular IOR Level"])  # strength (alpha) x a factor
    assert level.operation == "MULTIPLY" and level.inputs[0].links[0].from_socket.name == "Alpha"
    assert level.inputs[1].default_value > 0.5  # the demo's rho_s exceeds 1: the factor carries it
    assert _link_from(bsdf.inputs["Tangent"]).type == "TANGENT"
    assert _link_from(bsdf.inputs["Normal"]).type == "NORMAL_MAP"
    mul = _link_from(bsdf.inputs["Anisotropic"])
    assert mul.operation == "MULTIPLY" and _link_from(mul.inputs[0]).type == "SEPXYZ"
    div = _link_from(bsdf.inputs["Anisotropic Rotation"])
    assert div.operation == "DIVIDE" and abs(div.inputs[1].default_value - 2 * np.pi) < 1e-5
    for name in ("Roughness",):
        img = _link_from(bsdf.inputs[name]).image
        assert img.packed_file is not None and img.colorspace_settings.name == material.DATA
    glossy = next(n for n in a.node_tree.nodes if n.type == "BSDF_GLOSSY")
    assert glossy.distribution == "GGX"
    for sock, path, vtype in (("Tangent", "tangent.exr", "VECTOR"), ("Normal", "normal.exr", "NORMAL")):
        unit = _link_from(glossy.inputs[sock])
        xf = _link_from(unit.inputs[0])
        assert unit.operation == "NORMALIZE" and xf.type == "VECT_TRANSFORM" and xf.vector_type == vtype
        assert xf.convert_from == "OBJECT" and xf.convert_to == "WORLD"
        assert _link_from(xf.inputs[0]).image.filepath.endswith(path)
    scale = _link_from(glossy.inputs["Color"])
    assert scale.operation == "SCALE" and _link_from(scale.inputs[0]).image.filepath.endswith("specular_albedo.exr")
    add = _link_from(next(n for n in a.node_tree.nodes if n.type == "OUTPUT_MATERIAL").inputs["Surface"])
    assert {_link_from(add.inputs[0]).type, _link_from(add.inputs[1]).type} == {"BSDF_DIFFUSE", "BSDF_GLOSSY"}


def test_rebuilding_replaces_in_place_and_two_scans_do_not_collide(demo_result, tmp_path):
    _fresh()
    other = tmp_path / "vase_scan"
    shutil.copytree(demo_result, other)
    obj = material.import_result_mesh(demo_result)
    material.build_materials(demo_result, obj)
    before = sorted(i.name for i in bpy.data.images), sorted(m.name for m in bpy.data.materials)
    p, a = material.build_materials(demo_result, obj)  # again: the same datablocks, rebuilt
    assert (sorted(i.name for i in bpy.data.images), sorted(m.name for m in bpy.data.materials)) == before
    assert not any(".00" in n for names in before for n in names)
    assert not [i for i in bpy.data.images if i.users == 0 and not i.use_fake_user]  # no orphans
    obj2 = material.import_result_mesh(other)
    p2, a2 = material.build_materials(other, obj2)
    assert obj.name == demo_result.name and obj2.name == obj2.data.name == "vase_scan"
    assert {p2.name, a2.name}.isdisjoint({p.name, a.name}) and "vase_scan" in p2.name
    assert all("vase_scan" in i.name or demo_result.name in i.name for i in bpy.data.images)
    assert len(bpy.data.images) == 2 * len(before[0])

    # a third result in a folder of the same name as the first (two scans' "result" folders): its own
    # materials and images; the first object keeps its maps, and rebuilding either finds its own
    twin = tmp_path / "elsewhere" / demo_result.name
    shutil.copytree(demo_result, twin)
    accurate_images = {n.image.name for n in a.node_tree.nodes if getattr(n, "image", None)}
    obj3 = material.import_result_mesh(twin)
    p3, a3 = material.build_materials(twin, obj3)
    assert {p3.name, a3.name}.isdisjoint({p.name, a.name}) and obj.data.materials[0] == a
    assert {n.image.name for n in a.node_tree.nodes if getattr(n, "image", None)} == accurate_images
    assert material.build_materials(demo_result)[1] == a and material.build_materials(twin)[1] == a3
    assert len(bpy.data.images) == 3 * len(before[0])


def test_derived_inputs_reproduce_the_alphas(demo_result):
    from ntp_engine.io.maps import SVBRDFMaps

    maps = SVBRDFMaps.load(demo_result)
    ax, ay = maps.roughness[..., 0], maps.roughness[..., 1]
    g = derive.glossy_inputs(maps)
    gx, gy = derive.glossy_alphas(g["roughness"][..., 0], g["anisotropy"][..., 0])
    assert np.allclose(gx, ax, rtol=1e-6) and np.allclose(gy, ay, rtol=1e-6)  # ratios <= 10^4: exact
    from ntp_engine.io.mesh import load_mesh

    p = derive.principled_inputs(maps, load_mesh(demo_result / "mesh.obj"))
    hi, lo = derive.principled_alphas(p["roughness"][..., 0], p["anisotropy"][..., 2])
    ok = np.maximum(ax, ay) / np.minimum(ax, ay) <= 10
    assert np.allclose(hi[ok], np.maximum(ax, ay)[ok], rtol=1e-5) and np.allclose(hi * lo, ax * ay, rtol=1e-5)
    assert (~ok).any()  # the demo's brushed gold (12:1) is beyond what Principled can express
    assert np.allclose(np.linalg.norm(2 * p["anisotropy"][..., :2] - 1, axis=-1), 1, atol=1e-6)


def test_batch_writes_blend_glb_preview_that_reopen(demo_result, tmp_path):
    out = tmp_path / "o"
    r = subprocess.run(
        [
            sys.executable,
            "-m",
            "ntp_addon.batch",
            str(demo_result),
            "--blend",
            str(out / "a.blend"),
            "--gltf",
            str(out / "a.glb"),
            "--preview",
            str(out / "a.png"),
            "--samples",
            "4",
        ],
        capture_output=True,
        text=True,
    )
    assert r.returncode == 0, r.stderr[-2000:]
    assert sorted(p.name for p in out.iterdir()) == ["a.blend", "a.glb", "a.png"]  # no temporary files left
    blob = (out / "a.glb").read_bytes()
    n = struct.unpack("<I", blob[12:16])[0]
    gltf = json.loads(blob[20 : 20 + n])
    assert "KHR_materials_anisotropy" in gltf["extensionsUsed"]
    assert len(gltf["scenes"]) == 1 and len(gltf["nodes"]) == 1  # the mesh once, not once per Blender scene
    mat = gltf["materials"][0]
    assert mat["name"].startswith(material.PRINCIPLED)
    assert "anisotropyTexture" in mat["extensions"]["KHR_materials_anisotropy"] and "normalTexture" in mat
    spec = mat["extensions"]["KHR_materials_specular"]  # strength texture (alpha) and rho_s > 1 in the factor
    assert "specularTexture" in spec and "specularColorTexture" in spec and min(spec["specularColorFactor"]) > 1
    assert {i["mimeType"] for i in gltf["images"]} == {"image/png"}
    # roughness and anisotropy as KHR_materials_anisotropy defines them: a conforming viewer's alphas
    # are ntp's (before: 3.33x the larger and 3.46x the smaller on the gold's texels)
    from ntp_engine.io.glb import anisotropic_alphas, read_glb, texture_image
    from ntp_engine.io.maps import SVBRDFMaps

    alpha_t, alpha_b = anisotropic_alphas(out / "a.glb")
    truth = SVBRDFMaps.load(demo_result).roughness
    hi, lo = truth.max(-1), truth.min(-1)
    aniso = hi > 2 * lo
    assert aniso.mean() > 0.3
    assert np.median(alpha_t[aniso] / hi[aniso]) == pytest.approx(1, abs=0.03)
    assert np.median(alpha_b[aniso] / lo[aniso]) == pytest.approx(1, abs=0.03)
    doc, binary = read_glb(out / "a.glb")  # normal and anisotropy maps 16-bit (no banding); roughness 8
    assert texture_image(doc, binary, mat["normalTexture"]["index"]).format == "uint16"
    if shutil.which("node"):  # the Khronos validator (make setup installs it where npm exists)
        validate = ["node", str(REPO / "tools" / "gltf_validate.js"), str(out / "a.glb")]
        v = subprocess.run(validate, capture_output=True, text=True)
        assert v.returncode == 0, v.stderr[-500:]
        issues = json.loads(v.stdout)
        assert issues["numErrors"] == 0 and issues["numWarnings"] == 0, issues["messages"][:5]
    bpy.ops.wm.open_mainfile(filepath=str(out / "a.blend"))
    opened = bpy.context.scene  # F12 renders it: the relight rig, in Cycles, with its camera and lights
    assert opened.name.startswith(bscene.RELIGHT_PREFIX) and opened.render.engine == "CYCLES"
    assert opened.camera is not None and any(o.type == "LIGHT" for o in opened.objects)
    names = {m.name.split(" (")[0] for m in bpy.data.materials}
    assert {material.PRINCIPLED, material.ACCURATE} <= names
    assert bpy.data.objects[demo_result.name].data.materials[0].name.startswith(material.ACCURATE)
    files = [i for i in bpy.data.images if i.source == "FILE"]
    assert files and all(i.packed_file is not None for i in files)  # self-contained: moved, it still renders
    from ntp_engine.io.images import read_image

    assert read_image(out / "a.png").mean() > 0.02  # lit, not black
    bad = subprocess.run(
        [sys.executable, "-m", "ntp_addon.batch", str(tmp_path / "missing"), "--blend", str(out / "b.blend")],
        capture_output=True,
        text=True,
    )
    assert bad.returncode == 2 and "missing" in bad.stderr and "Traceback" not in bad.stderr
    # linked, not packed, from a relative result path in another working directory: every path resolves
    cwd = tmp_path / "w"
    cwd.mkdir()
    rel = os.path.relpath(demo_result, cwd)
    linked = [sys.executable, "-m", "ntp_addon.batch", rel, "--blend", "y/linked.blend", "--no-pack"]
    assert subprocess.run(linked, cwd=cwd, capture_output=True).returncode == 0
    bpy.ops.wm.open_mainfile(filepath=str(cwd / "y" / "linked.blend"))
    stored = [i.filepath for i in bpy.data.images if i.source == "FILE" and i.packed_file is None]
    assert len(stored) >= 4 and all(Path(bpy.path.abspath(f)).is_file() for f in stored), stored
    umask = os.umask(0)
    os.umask(umask)
    for f in ("a.blend", "a.glb", "a.png"):  # modes follow the umask (temporary files are 0600)
        assert (out / f).stat().st_mode & 0o777 == 0o666 & ~umask, f
    (tmp_path / "a_file").write_text("x")
    own_map = (demo_result / "diffuse_albedo.exr").read_bytes()
    for option, target, named, what in (
        ("--gltf", tmp_path / "a_file" / "x.glb", tmp_path / "a_file", "File exists"),  # its folder is a file
        ("--gltf", demo_result, demo_result, "is the input folder"),
        # the result's own files are the export's input: it replaced a map and the result still looked complete
        ("--blend", demo_result / "diffuse_albedo.exr", demo_result / "diffuse_albedo.exr", "inside the input folder"),
        ("--blend", Path("/proc/x.blend"), Path("/proc/x.blend"), "No such file"),  # the target named, not a temporary
    ):
        bad = subprocess.run(
            [sys.executable, "-m", "ntp_addon.batch", str(demo_result), option, str(target)],
            capture_output=True,
            text=True,
        )
        lines = bad.stderr.strip().splitlines()
        assert bad.returncode == 2 and len(lines) == 1 and what in lines[0] and str(named) in lines[0], bad.stderr
        assert ".ntp-tmp" not in lines[0]
    assert (demo_result / "diffuse_albedo.exr").read_bytes() == own_map
    incomplete = tmp_path / "incomplete"
    shutil.copytree(demo_result, incomplete)
    (incomplete / "report.json").unlink()
    bad = subprocess.run(
        [sys.executable, "-m", "ntp_addon.batch", str(incomplete), "--blend", str(out / "c.blend")],
        capture_output=True,
        text=True,
    )
    assert bad.returncode == 2 and "report.json: missing" in bad.stderr and not (out / "c.blend").exists()


def test_the_glb_texture_size_is_chosen_at_export_and_the_blend_keeps_the_maps(demo_result, tmp_path):
    from ntp_engine.io.glb import read_glb, texture_image

    cmd = [sys.executable, "-m", "ntp_addon.batch", str(demo_result), "--gltf", str(tmp_path / "s.glb")]
    r = subprocess.run(cmd + ["--blend", str(tmp_path / "s.blend"), "--gltf-texture-size", "64"], capture_output=True)
    assert r.returncode == 0, r.stderr[-1000:]
    doc, binary = read_glb(tmp_path / "s.glb")
    sizes = {texture_image(doc, binary, k).pixels.shape[:2] for k in range(len(doc["images"]))}
    assert sizes == {(64, 64)}  # every texture of the .glb (the maps are 256^2)
    bpy.ops.wm.open_mainfile(filepath=str(tmp_path / "s.blend"))
    principled = next(m for m in bpy.data.materials if m.name.startswith(material.PRINCIPLED))
    own = {tuple(n.image.size) for n in principled.node_tree.nodes if getattr(n, "image", None)}
    assert own == {(256, 256)}  # the .blend keeps the maps' own size
    bad = subprocess.run(cmd + ["--gltf-texture-size", "4"], capture_output=True, text=True)
    assert bad.returncode == 2 and "--gltf-texture-size: 4: need 8 to 16384" in bad.stderr


def test_gltf_reimport_renders_like_the_blend(demo_result):
    """The .glb, re-imported by Blender's glTF importer, under the same camera and light as the
    material it came from: colours, specular strength and normals carried (measured: SSIM 0.9889,
    mean colour within 0.1%; before the colours were sRGB and the strength in alpha, SSIM 0.84 and
    colour x0.37-0.56). Not 1: the file's anisotropy is glTF's, which Blender's importer reads as
    Cycles' own inputs (0.9998 while the file carried Cycles' values; docs/blender.md)."""
    r = gltf.round_trip(demo_result, views=1, scale=0.15, samples=16)
    print(f"glTF round trip: SSIM {r['ssim']:.4f}, mean colour ratio {np.round(r['mean_colour_ratio'], 4)}")
    assert r["ssim"] >= 0.95
    assert np.all(np.abs(np.array(r["mean_colour_ratio"]) - 1) <= 0.03)


def test_cycles_render_agrees_with_the_engine(demo_result):
    """Threshold: the accurate variant differs from the engine only by Monte Carlo noise (32 spp,
    direct light), Schlick's Fresnel on n.v instead of w_i.h and the height-correlated G — measured
    SSIM ~0.98 at this size; 0.95 leaves room for noise, while a wrong frame, colour space or
    roughness mapping drops it below 0.9. The Principled variant is reported (capped anisotropy,
    different Fresnel and diffuse), with a loose floor."""
    r = compare.run(demo_result, views=1, scale=0.15, samples=32)
    print(f"SSIM accurate {r['accurate']['ssim']:.4f} principled {r['principled']['ssim']:.4f}")
    assert r["accurate"]["ssim"] > 0.95 and r["accurate"]["psnr_db"] > 28
    assert r["principled"]["ssim"] > 0.75


def test_the_blender_bench_runs_on_the_demos_true_maps(tmp_path):
    """``ntp bench blender`` builds its materials from the demo's true maps, which have no
    report.json (they are not a pipeline result): it refused them once."""
    from ntp_addon import bench as addon_bench

    out = addon_bench.run(views=1, scale=0.05, samples=1, json_path=tmp_path / "b.json")
    assert out["accurate"]["ssim"] > 0 and out["principled"]["ssim"] > 0 and (tmp_path / "b.json").is_file()


def test_reconstruct_progress_is_read_from_the_engines_structured_channel(tmp_path):
    """The add-on reads what the engine's Progress writes (the same file a child process appends to)."""
    from ntp_addon.operators import progress_status
    from ntp_engine.io.progress import Progress, read_progress

    path = tmp_path / "progress.jsonl"
    channel = Progress(json_path=path, min_interval_s=0.0)
    with channel.counter("network + fit", 200, "texel") as c:
        c.update(26)
        records, offset = read_progress(path)
        assert progress_status(records[-1])[0].startswith("network + fit: 13%")
        assert progress_status(records[-1])[1] == 13.0 and "s left" in progress_status(records[-1])[0]
        c.update(174)
    records, _ = read_progress(path, offset)
    assert progress_status(records[-1]) == ("network + fit: 100%", 100.0)
    assert progress_status({"stage": "SfM", "done": 0, "total": None}) == ("SfM: 0%", 0.0)


def test_import_menu_entries_and_preferences(addon, posed_scan, tmp_path):
    from ntp_addon import operators, preferences

    assert operators.menu_import in bpy.types.TOPBAR_MT_file_import._dyn_ui_initialize()
    assert {"import_scene.ntp_result", "import_scene.ntp_colmap"} <= {
        f"import_scene.{n}" for n in dir(bpy.ops.import_scene)
    }
    prefs = bpy.context.preferences.addons[preferences.PACKAGE].preferences
    addon.scan_folder, addon.result_folder = str(posed_scan), str(tmp_path / "a" / "scan_result")
    assert operators.NTP_OT_reconstruct._command(None, bpy.context)[-2:] == ["--model", "compact"]
    prefs.model, prefs.threads, prefs.cache_root = "small", 3, str(tmp_path / "c")
    addon.colmap_folder = str(tmp_path / "colmap")
    cmd = operators.NTP_OT_reconstruct._command(None, bpy.context)
    assert cmd[cmd.index("--threads") + 1] == "3" and cmd[cmd.index("--model") + 1] == "small"
    assert cmd[cmd.index("--colmap") + 1] == str(tmp_path / "colmap")
    other = preferences.engine_options(bpy.context).cache_for(tmp_path / "b" / "scan_result")
    assert Path(cmd[cmd.index("--cache") + 1]).parent == tmp_path / "c" and Path(cmd[cmd.index("--cache") + 1]) != other
    from ntp_addon import panel
    from ntp_engine.io.assets import DOCS_DIR

    assert all((DOCS_DIR / f).is_file() for f, _ in panel.GUIDES)  # the help panel's guides exist
    addon.model = "paper"  # the scene's own setting overrides the preference
    assert operators.NTP_OT_reconstruct._command(None, bpy.context)[-1] == "paper"


def test_import_result_from_the_file_menu(addon, demo_result, tmp_path):
    n_obj = len(bpy.data.objects)
    with pytest.raises(RuntimeError, match="report.json: missing"):
        bpy.ops.import_scene.ntp_result(directory=str(tmp_path))
    assert len(bpy.data.objects) == n_obj
    assert bpy.ops.import_scene.ntp_result(directory=str(demo_result)) == {"FINISHED"}
    obj = bpy.context.view_layer.objects.active
    assert obj.name == demo_result.name and obj.data.materials[0].name.startswith(material.ACCURATE)
    assert Path(addon.result_folder) == demo_result


def test_colmap_import_runs_the_engine_and_reports_a_bad_model(addon, posed_scan, tmp_path):
    scan = tmp_path / "scan"
    shutil.copytree(posed_scan, scan)
    toml = scan / "scan.toml"
    toml.write_text("".join(ln for ln in toml.read_text().splitlines(True) if not ln.startswith("poses")))
    addon.result_folder = str(tmp_path / "result")
    assert not bpy.ops.import_scene.ntp_colmap.poll()  # greyed out without a scan folder
    addon.scan_folder = str(scan)
    (tmp_path / "model").mkdir()
    with pytest.raises(RuntimeError, match="not a COLMAP model folder"):
        bpy.ops.import_scene.ntp_colmap(directory=str(tmp_path / "model"))
    assert "NTP Cameras" not in bpy.data.collections and Path(addon.colmap_folder) == tmp_path / "model"


def test_coverage_overlay_bakes_to_its_legend_and_gives_the_materials_back(addon, demo_result, tmp_path):
    from ntp_addon import coverage
    from ntp_engine.io.images import write_exr

    result = tmp_path / "cov_result"
    shutil.copytree(demo_result, result)
    n = 64
    conf = np.zeros((n, n, 3))
    conf[..., 1] = np.arange(n)[None, :] * 0.4  # photos per point: 0 .. 25 across the columns
    conf[n // 2 :, :, 0] = 1.0
    write_exr(result / "confidence.exr", conf)
    assert bpy.ops.import_scene.ntp_result(directory=str(result)) == {"FINISHED"}
    obj = bpy.context.view_layer.objects.active
    own = [sl.material.name for sl in obj.material_slots]
    addon.coverage = "photos"
    assert [sl.material.name for sl in obj.material_slots] == [coverage.MATERIAL] * len(own)
    assert "scan that side again" in addon.status
    # bake the overlay's emission into UV space: each texel must be the legend's colour of its value
    scene = bpy.context.scene
    scene.render.engine, scene.cycles.samples, scene.render.bake.margin = "CYCLES", 1, 0
    target = bpy.data.images.new("bake", n, n, float_buffer=True)
    target.colorspace_settings.name = "Non-Color"
    target.generated_color = (1.0, 0.0, 1.0, 1.0)  # magenta: not baked
    nodes = bpy.data.materials[coverage.MATERIAL].node_tree.nodes
    node = nodes.new("ShaderNodeTexImage")
    node.image, nodes.active = target, node
    obj.select_set(True)
    assert bpy.ops.object.bake(type="EMIT") == {"FINISHED"}
    baked = np.array(target.pixels[:]).reshape(n, n, 4)[::-1, :, :3]  # Blender's rows run bottom-up
    got = (baked[:, :, 1] < 0.5) & (baked[:, :, 0] > 0.99) & (baked[:, :, 2] > 0.99)
    seen = ~got
    assert seen.mean() > 0.2
    fac = np.clip(conf[..., 1] / 16.0, 0, 1)
    stops = np.array([c for _, c in coverage.RAMP])[:, :3]
    expect = np.stack([np.interp(fac, [0, 0.5, 1], stops[:, k]) for k in range(3)], -1)
    assert np.abs(baked[seen] - expect[seen]).max() < 2e-3
    nodes.remove(node)
    # a layer the result lacks: reported, nothing changed; off: the user's materials back
    addon.coverage = "normal"
    assert "uncertainty.exr" in addon.status and "--refine" in addon.status
    addon.coverage = "off"
    assert [sl.material.name for sl in obj.material_slots] == own and coverage.RESTORE not in obj


def test_colmap_model_imports_as_cameras_aligned_to_the_mesh(addon, scan24, colmap24, colmap24_registered):
    """File → Import → COLMAP model: a model COLMAP (pycolmap) wrote for the scan's photos becomes
    cameras in the mesh's frame (the engine aligns it and checks it against the photos; here into
    the suite's result folder of that registration, so the engine finds it cached)."""
    from ntp_engine.scanner.scan_folder import load_poses

    model = colmap24[0]
    addon.scan_folder, addon.result_folder = str(scan24), str(colmap24_registered)
    assert bpy.ops.import_scene.ntp_colmap(directory=str(model)) == {"FINISHED"}
    assert "COLMAP model" in addon.status
    cams = bpy.data.collections["NTP Cameras"].objects
    truth = load_poses(scan24 / "ground_truth" / "poses.json")
    assert len(cams) >= 20
    err = [
        np.linalg.norm(np.array(c.matrix_world)[:3, 3] + truth[c.name[4:]][:3, :3].T @ truth[c.name[4:]][:3, 3])
        for c in cams
    ]
    assert np.median(err) < 0.02  # 24 photos: the alignment's own accuracy (as tests/pipeline/test_colmap_model.py)
