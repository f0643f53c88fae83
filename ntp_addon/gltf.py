"""glTF binary export of a result's Principled material (roughness and anisotropy as
``KHR_materials_anisotropy`` defines them), and the round trip: the ``.glb`` re-imported with
Blender's own glTF importer and rendered in Cycles beside the material it came from, under the
same camera and point light (``compare``'s novel views). SSIM and mean colour on the object's
pixels say whether glTF carries colour spaces, specular strength and normals as the .blend shows
them; on anisotropic texels they also show that Blender's importer reads the extension as its own
inputs (docs/blender.md) — what other viewers draw is checked on the file (``io/glb.py``).
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import bpy
import numpy as np

from ntp_engine.io.atomic import atomic_path
from ntp_engine.io.images import read_image
from ntp_engine.io.maps import MAP_FILES
from ntp_engine.io.viewers import khronos_inputs
from ntp_engine.sim.evaluate import compare_images

from . import compare, material
from . import scene as bscene


def export_glb(obj: bpy.types.Object, mat: bpy.types.Material, path: Path, texture_size: int | None = None) -> None:
    """``obj`` alone, wearing the Principled material ``mat`` for the export (its first slot
    restored after), as a .glb with tangents (KHR_materials_anisotropy needs them), written
    atomically. Roughness and anisotropy strength are written as glTF defines them
    (``ntp_engine.io.viewers.khronos_inputs``: alpha_b = r^2, alpha_t = mix(alpha_b, 1, strength^2)), not as
    Cycles reads its own inputs: for the export, ``mat``'s images hold the glTF values, then
    their own again. ``texture_size``: every texture of the .glb scaled to that many pixels a side
    (Blender's ``Image.scale``; the viewer normalises the normal and anisotropy directions), the
    .blend keeping the maps' own. Only the active scene is exported: the object is linked into the
    relight scene too, and every scene holding it would be a glTF scene with its own node."""
    nodes = {n.label: n for n in mat.node_tree.nodes}
    images = (nodes[material.ROUGHNESS_LABEL].image, nodes[material.ANISOTROPY_LABEL].image)
    # the images the export changes: the two swapped, or every one when the textures are scaled
    touched = list(images)
    if texture_size is not None:
        every = {n.image.name: n.image for n in mat.node_tree.nodes if getattr(n, "image", None) is not None}
        touched = list(every.values())
    own = {}
    for img in touched:
        pixels = np.empty(len(img.pixels), np.float32)
        img.pixels.foreach_get(pixels)
        own[img.name] = (tuple(img.size), pixels, img.packed_file is not None)
    # the glTF values from the result's alphas; the anisotropy's direction (RG) is the image's own
    alpha = read_image(Path(mat[material.RESULT_KEY]) / MAP_FILES["roughness"])[..., :2]
    roughness, strength = khronos_inputs(alpha.max(-1), alpha.min(-1))
    (w, h), aniso, _ = own[images[1].name]
    direction = aniso.reshape(h, w, 4)[::-1, :, :2]  # Blender rows start at the bottom
    swaps = zip(images, (roughness[..., None], np.concatenate([direction, strength[..., None]], -1)))
    chosen = obj.data.materials[0]
    obj.data.materials[0] = mat
    try:
        for img, data in swaps:
            material.set_pixels(img, data)
        if texture_size is not None:
            for img in touched:
                img.scale(texture_size, texture_size)
        bpy.ops.object.select_all(action="DESELECT")
        obj.select_set(True)
        bpy.context.view_layer.objects.active = obj
        with atomic_path(path) as tmp:
            bpy.ops.export_scene.gltf(
                filepath=str(tmp),
                export_format="GLB",
                use_selection=True,
                use_active_scene=True,
                export_tangents=True,
                export_cameras=False,
                export_lights=False,
            )
    finally:
        obj.data.materials[0] = chosen
        for img in touched:
            size, pixels, packed = own[img.name]
            if tuple(img.size) != size:
                img.scale(*size)
            img.pixels.foreach_set(pixels)
            if packed:
                img.pack()  # the .blend keeps Cycles' values at the maps' size, packed as before


def import_glb(path: Path) -> bpy.types.Object:
    """The mesh object of a .glb, imported with Blender's glTF importer."""
    before = set(bpy.data.objects)
    bpy.ops.import_scene.gltf(filepath=str(path))
    new = [o for o in bpy.data.objects if o not in before and o.type == "MESH"]
    if not new:
        raise RuntimeError(f"{path}: no mesh imported")
    return new[0]


def round_trip(result: str | Path, views: int = 2, scale: float = 0.2, samples: int = 32) -> dict:
    """Render the Principled material and its .glb re-import in Cycles from ``views`` novel views;
    per view and mean: SSIM, and the ratio of mean colours (re-import / original) on object pixels."""
    result = Path(result)
    bpy.ops.wm.read_factory_settings(use_empty=True)
    obj = material.import_result_mesh(result)
    principled, _ = material.build_materials(result, obj, "principled")
    cam = compare.point_device(scale)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        work = Path(tmp)
        export_glb(obj, principled, work / "asset.glb")
        twin = import_glb(work / "asset.glb")
        for k, (pose, light) in enumerate(compare.novel_views(result, views, scale=scale)):
            _, mask = compare.engine_render(result, pose, light, cam)  # the object's pixels
            imgs = []
            for shown, hidden in ((obj, twin), (twin, obj)):
                shown.hide_render, hidden.hide_render = False, True
                img, _ = compare.cycles_render(
                    shown, shown.data.materials[0], pose, light, cam, work / f"{k}_{shown.name}.exr", samples
                )
                imgs.append(img)
            ratio = imgs[1][mask].mean(0) / np.maximum(imgs[0][mask].mean(0), 1e-12)
            rows.append({"ssim": compare_images(imgs[0], imgs[1], mask)["ssim"], "mean_colour_ratio": ratio.tolist()})
    return {
        "ssim": float(np.mean([r["ssim"] for r in rows])),
        "mean_colour_ratio": np.mean([r["mean_colour_ratio"] for r in rows], 0).tolist(),
        "per_view": rows,
    }


def preview_renders(
    result: str | Path, out: dict[str, Path], size: tuple[int, int] = (480, 384), samples: int = 64
) -> None:
    """Look-dev renders of ``result`` from one relight rig (camera, key/fill/rim lights), each to
    ``out[name]``: ``"accurate"`` and ``"principled"`` the .blend's object with that material,
    ``"glb"`` the Principled material exported to .glb and re-imported with Blender's glTF
    importer (docs/blender.md shows the three side by side)."""
    bpy.ops.wm.read_factory_settings(use_empty=True)
    obj = material.import_result_mesh(Path(result))
    principled, accurate = material.build_materials(Path(result), obj)
    with tempfile.TemporaryDirectory() as tmp:
        export_glb(obj, principled, Path(tmp) / "asset.glb")
        twin = import_glb(Path(tmp) / "asset.glb")
        for name, path in out.items():
            shown = twin if name == "glb" else obj
            if name != "glb":
                obj.data.materials[0] = accurate if name == "accurate" else principled
            rig = bscene.relight_rig(shown, *size, samples=samples)
            with atomic_path(path) as target:
                bscene.render_still(rig["scene"], target)
