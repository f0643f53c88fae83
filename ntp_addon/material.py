"""Blender materials from a result folder (docs/design.md output contract): two node trees over the
same maps.

- ``NTP Principled``: an anisotropic Principled BSDF, arranged so the bundled glTF exporter writes
  KHR_materials_anisotropy (Tangent node on the UV map; a direction/strength texture through
  Separate XYZ -> ArcTan2 -> Add -> Divide 2 pi into Anisotropic Rotation, its B channel x 1 into
  Anisotropic — the layout the glTF importer builds) and a tangent-space normal map (glTF has no
  object-space normals). Colours are sRGB PNGs, as glTF reads base and specular colour; F0 = 0.04 x
  rho_s through Specular IOR Level (a strength texture's alpha, as KHR_materials_specular reads it,
  times half the scene's largest rho_s: a factor the exporter writes) and Specular Tint
  (rho_s / max_c rho_s). Limits: anisotropy capped at 10:1, Fresnel rises to 1 (not rho_s) at
  grazing, the diffuse is dimmed by the specular layer.
- ``NTP Accurate``: Diffuse BSDF (rho_d) + Glossy BSDF (GGX) whose colour is rho_s times Schlick's
  Fresnel with F0 = 0.04 on n.v (the engine uses w_i.h; equal at the mirror peak); the object-space
  normal and tangent maps through Vector Transform nodes; any alpha ratio up to 10^4. No built-in
  node puts a Fresnel on w_i.h under a Glossy BSDF's 10^4 anisotropy (the Metallic BSDF caps it at
  10:1). Built ``exact_fresnel`` (the Cycles scanner's photos), the Glossy BSDF is replaced by the
  engine's lobe itself, Schlick on w_i.h (bounded: F90 = min(1, 1 / rho_s)), an OSL node
  (``schlick_lobe``: CPU only) fed the alpha map directly.

All inputs are read and derived before any datablock is created: a bad result folder raises
``NtpInputError`` naming the file, and nothing half-built is left behind.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import bpy
import numpy as np

from ntp_engine.io.errors import NtpInputError
from ntp_engine.io.maps import MAP_FILES, SVBRDFMaps
from ntp_engine.io.mesh import Mesh, load_mesh
from ntp_engine.io.output_folder import REPORT, is_complete
from ntp_engine.physics.brdf import F0_DIELECTRIC

from . import derive
from .schlick_lobe import schlick_lobe_node

PRINCIPLED, ACCURATE = "NTP Principled", "NTP Accurate"
DEFAULT_VARIANT = "accurate"  # chosen by `ntp bench blender` (docs/blender.md)
LINEAR, DATA, SRGB = "Linear Rec.709", "Non-Color", "sRGB"


@dataclass
class ResultInputs:
    """A result folder's maps and the node inputs derived from them."""

    folder: Path
    maps: SVBRDFMaps
    mesh: Mesh  # the result's mesh.obj: the UV layout the maps are laid out on
    principled: dict[str, np.ndarray]
    glossy: dict[str, np.ndarray]


def read_result(folder: str | Path, require_report: bool = True) -> ResultInputs:
    """Validate a result folder (complete: its report exists; ``require_report=False`` for a folder
    of maps that is not a pipeline result, e.g. a virtual-scan asset) and derive every node input
    (no bpy datablock touched)."""
    folder = Path(folder)
    if not folder.is_dir():
        raise NtpInputError(folder, "result folder does not exist")
    if require_report and not is_complete(folder):  # report.json is written last: without it the maps may be mixed
        raise NtpInputError(
            folder / REPORT, "missing: the result is incomplete (interrupted?) — run ntp reconstruct again"
        )
    for f in (*MAP_FILES.values(), "mesh.obj"):
        if not (folder / f).is_file():
            raise NtpInputError(folder / f, "map file missing" if f.endswith(".exr") else "mesh missing")
    maps = SVBRDFMaps.load(folder)
    mesh = load_mesh(folder / "mesh.obj")
    if mesh.uv is None:
        raise NtpInputError(folder / "mesh.obj", "mesh has no UVs (the maps need them)")
    return ResultInputs(folder, maps, mesh, derive.principled_inputs(maps, mesh), derive.glossy_inputs(maps))


UV_TOLERANCE = 1e-4  # a tenth of a texel at 1024^2: float32 in Blender, 6 decimals in the OBJ


def carries_result_uvs(obj: bpy.types.Object, result: Mesh) -> bool:
    """Whether ``obj``'s mesh holds the UV layout the result's maps are laid out on: the result's
    mesh (``ResultInputs.mesh``) triangles in the same order with the same (u, v) at their corners,
    within ``UV_TOLERANCE`` (Blender's OBJ import keeps face and corner order). Another mesh — one
    without UVs, the scan's raw mesh, the default cube — would sample the maps at the wrong places."""
    if obj.type != "MESH" or obj.data.uv_layers.active is None:
        return False
    me, layer = obj.data, obj.data.uv_layers.active
    if result.uv is None or len(me.polygons) != len(result.faces) or len(me.loops) != result.faces.size:
        return False
    corners = np.empty(2 * len(me.loops), np.float32)
    layer.data.foreach_get("uv", corners)
    return bool(np.abs(corners.reshape(-1, 3, 2) - result.uv[result.faces]).max() <= UV_TOLERANCE)


def asset_name(result: str | Path) -> str:
    """The name an asset's datablocks derive from: its result folder's name."""
    return Path(result).resolve().name


def _fresh_image(name: str) -> None:
    """Remove an image of this name (a previous build's), so a rebuild replaces it in place."""
    old = bpy.data.images.get(name)
    if old is not None:
        bpy.data.images.remove(old)


def _file_image(path: Path, colorspace: str, name: str) -> bpy.types.Image:
    """A map file of the result as image ``name`` (a rebuild reloads it under the same name)."""
    _fresh_image(name)
    # absolute: Blender reads a relative path against the working directory but stores it against
    # the .blend's folder when saving, so a relative result folder gave paths that do not resolve
    img = bpy.data.images.load(str(path.resolve()), check_existing=False)
    img.name = name
    img.colorspace_settings.name = colorspace
    return img


def set_pixels(img: bpy.types.Image, data: np.ndarray) -> None:
    """``img``'s pixels from ``data (H, W, C)``, row 0 = top (one channel: grey; alpha 1)."""
    h, w, c = data.shape
    rgba = np.ones((h, w, 4), np.float32)
    rgba[..., :c] = data
    if c == 1:
        rgba[..., 1:3] = data
    img.pixels.foreach_set(rgba[::-1].reshape(-1))  # Blender rows start at the bottom


def packed_image(name: str, data: np.ndarray) -> bpy.types.Image:
    """A float image held in the .blend (packed), ``data (H, W, C)`` row 0 = top."""
    _fresh_image(name)
    h, w, _ = data.shape
    img = bpy.data.images.new(name, w, h, alpha=False, float_buffer=True, is_data=True)
    set_pixels(img, data)
    img.file_format = "OPEN_EXR"
    img.pack()
    img.colorspace_settings.name = DATA
    return img


def packed_png(name: str, data: np.ndarray, colorspace: str, alpha: np.ndarray | None = None) -> bpy.types.Image:
    """An 8-bit image held in the .blend as PNG, ``data (H, W, 3)`` in [0, 1] as the file stores it
    (sRGB-encoded for ``colorspace`` sRGB), row 0 = top; ``alpha (H, W, 1)`` (linear, kept apart
    from the colour: channel-packed). The glTF exporter copies such an image's PNG as it is."""
    _fresh_image(name)
    h, w, _ = data.shape
    rgba = np.ones((h, w, 4), np.float32)
    rgba[..., :3] = np.clip(data, 0, 1)
    if alpha is not None:
        rgba[..., 3] = np.clip(alpha[..., 0], 0, 1)
    img = bpy.data.images.new(name, w, h, alpha=alpha is not None, float_buffer=False)
    img.colorspace_settings.name = colorspace
    img.alpha_mode = "CHANNEL_PACKED"
    img.pixels.foreach_set(rgba[::-1].reshape(-1))  # Blender rows start at the bottom
    img.file_format = "PNG"
    img.pack()
    return img


class _Tree:
    """Small helper: nodes laid out in columns, links by socket name or index."""

    def __init__(self, mat: bpy.types.Material):
        if mat.node_tree is None:
            mat.use_nodes = True
        self.nt = mat.node_tree
        self.nt.nodes.clear()

    def node(self, kind: str, x: float, y: float, label: str = "", **attrs):
        n = self.nt.nodes.new(kind)
        n.location = (x * 220.0, y * 200.0)
        if label:
            n.label = label
        for k, v in attrs.items():
            setattr(n, k, v)
        return n

    def image(self, img, x, y, label):
        return self.node("ShaderNodeTexImage", x, y, label, image=img, interpolation="Linear")

    def link(self, a, out, b, inp):
        self.nt.links.new(a.outputs[out], b.inputs[inp])


RESULT_KEY, VARIANT_KEY = "ntp_result", "ntp_variant"  # custom properties: whose material this is
# the Principled material's two image nodes whose values glTF defines otherwise than Cycles (gltf.export_glb)
ROUGHNESS_LABEL, ANISOTROPY_LABEL = "roughness (ax ay)^1/4", "anisotropy (dir RG, strength B)"


def result_material(folder: Path, variant: str, name: str) -> bpy.types.Material:
    """The ``variant`` material of the result at ``folder``: the one an earlier build made for the
    same folder (found by its resolved path, so a rebuild replaces it in place), else a new one
    called ``name`` — Blender's ``.001`` suffix where another result's holds that name (two results
    in folders of the same name stay two materials)."""
    key = str(Path(folder).resolve())
    for mat in bpy.data.materials:
        if mat.get(RESULT_KEY) == key and mat.get(VARIANT_KEY) == variant:
            return mat
    mat = bpy.data.materials.new(name)
    mat[RESULT_KEY], mat[VARIANT_KEY] = key, variant
    return mat


def _principled(ri: ResultInputs, name: str) -> bpy.types.Material:
    p = ri.principled
    mat = result_material(ri.folder, "principled", name)
    name = mat.name  # its images are named after it: unique as it is
    T = _Tree(mat)
    out = T.node("ShaderNodeOutputMaterial", 2, 0)
    bsdf = T.node("ShaderNodeBsdfPrincipled", 0, 0)
    T.link(bsdf, "BSDF", out, "Surface")
    bsdf.inputs["Metallic"].default_value = 0.0
    bsdf.inputs["IOR"].default_value = 1.5
    # colours as glTF reads them (sRGB PNGs), the specular strength in alpha times a factor
    T.link(
        T.image(packed_png(f"{name} base color", p["base_color_srgb"], SRGB), -3, 4, "diffuse albedo (sRGB)"),
        "Color",
        bsdf,
        "Base Color",
    )
    strength = p["specular_strength"]
    level_tex = T.image(
        packed_png(f"{name} specular strength", np.repeat(strength, 3, -1), DATA, alpha=strength),
        -4,
        3,
        "specular strength (alpha)",
    )
    level = T.node("ShaderNodeMath", -3, 3, "Specular level factor", operation="MULTIPLY")
    level.inputs[1].default_value = 0.5 * float(p["specular_scale"])
    T.link(level_tex, "Alpha", level, 0)
    T.link(level, 0, bsdf, "Specular IOR Level")
    T.link(
        T.image(packed_png(f"{name} specular color", p["specular_tint_srgb"], SRGB), -3, 2, "specular tint (sRGB)"),
        "Color",
        bsdf,
        "Specular Tint",
    )
    T.link(
        T.image(packed_image(f"{name} roughness", p["roughness"]), -3, 1, ROUGHNESS_LABEL),
        "Color",
        bsdf,
        "Roughness",
    )
    # anisotropy: the glTF importer's arrangement, so the exporter recognises it
    tex = T.image(packed_image(f"{name} anisotropy", p["anisotropy"]), -7, -1, ANISOTROPY_LABEL)
    mad = T.node("ShaderNodeVectorMath", -6, -1, operation="MULTIPLY_ADD")
    mad.inputs[1].default_value, mad.inputs[2].default_value = (2, 2, 1), (-1, -1, 0)
    sep = T.node("ShaderNodeSeparateXYZ", -5, -1)
    atan = T.node("ShaderNodeMath", -4, -1, "ArcTan2", operation="ARCTAN2")
    add = T.node("ShaderNodeMath", -3, -1, "Anisotropy rotation", operation="ADD")
    add.inputs[1].default_value = 0.0
    div = T.node("ShaderNodeMath", -2, -1, "Rotation conversion", operation="DIVIDE")
    div.inputs[1].default_value = 2 * math.pi
    mul = T.node("ShaderNodeMath", -2, 0, "Anisotropy strength", operation="MULTIPLY")
    mul.inputs[1].default_value = 1.0
    T.link(tex, "Color", mad, 0)
    T.link(mad, 0, sep, 0)
    T.link(sep, "Y", atan, 0)
    T.link(sep, "X", atan, 1)
    T.link(atan, 0, add, 0)
    T.link(add, 0, div, 0)
    T.link(div, 0, bsdf, "Anisotropic Rotation")
    T.link(sep, "Z", mul, 0)
    T.link(mul, 0, bsdf, "Anisotropic")
    tangent = T.node("ShaderNodeTangent", -2, -2, direction_type="UV_MAP")
    T.link(tangent, "Tangent", bsdf, "Tangent")
    nmap = T.node("ShaderNodeNormalMap", -2, -3, space="TANGENT")
    T.link(
        T.image(
            packed_image(f"{name} normal (tangent space)", p["normal_tangent_space"]), -3, -3, "normal, tangent space"
        ),
        "Color",
        nmap,
        "Color",
    )
    T.link(nmap, "Normal", bsdf, "Normal")
    return mat


def _accurate(ri: ResultInputs, name: str, exact_fresnel: bool = False) -> bpy.types.Material:
    mat = result_material(ri.folder, "accurate", name)
    name = mat.name
    T = _Tree(mat)
    out = T.node("ShaderNodeOutputMaterial", 3, 0)
    add = T.node("ShaderNodeAddShader", 2, 0)
    T.link(add, 0, out, "Surface")
    diffuse = T.node("ShaderNodeBsdfDiffuse", 1, 1)
    diffuse.inputs["Roughness"].default_value = 0.0
    T.link(diffuse, 0, add, 0)
    T.link(
        T.image(_file_image(ri.folder / "diffuse_albedo.exr", LINEAR, f"{name} diffuse albedo"), -1, 2, "rho_d"),
        "Color",
        diffuse,
        "Color",
    )
    # object-space frame maps -> world space
    n_img = T.image(_file_image(ri.folder / "normal.exr", DATA, f"{name} normal"), -4, 0, "normal (object space)")
    n_xf = T.node("ShaderNodeVectorTransform", -3, 0, vector_type="NORMAL", convert_from="OBJECT", convert_to="WORLD")
    n_unit = T.node("ShaderNodeVectorMath", -2, 0, operation="NORMALIZE")
    T.link(n_img, "Color", n_xf, 0)
    T.link(n_xf, 0, n_unit, 0)
    t_img = T.image(_file_image(ri.folder / "tangent.exr", DATA, f"{name} tangent"), -4, -2, "tangent (object space)")
    t_xf = T.node("ShaderNodeVectorTransform", -3, -2, vector_type="VECTOR", convert_from="OBJECT", convert_to="WORLD")
    t_unit = T.node("ShaderNodeVectorMath", -2, -2, operation="NORMALIZE")
    T.link(t_img, "Color", t_xf, 0)
    T.link(t_xf, 0, t_unit, 0)
    T.link(n_unit, "Vector", diffuse, "Normal")
    spec_file = _file_image(ri.folder / "specular_albedo.exr", LINEAR, f"{name} specular albedo")
    spec = T.image(spec_file, -1, 0, "specular albedo")
    if exact_fresnel:  # the engine's lobe, Fresnel on w_i.h (OSL; module docstring)
        lobe = schlick_lobe_node(T.nt)
        lobe.location = (220.0, -200.0)
        alphas = T.image(_file_image(ri.folder / "roughness.exr", DATA, f"{name} alphas"), -1, -2, "alpha_x, alpha_y")
        split = T.node("ShaderNodeSeparateColor", 0, -2)
        T.link(alphas, "Color", split, "Color")
        T.link(split, "Red", lobe, "alpha_x")
        T.link(split, "Green", lobe, "alpha_y")
        T.link(spec, "Color", lobe, "rho_s")
        T.link(n_unit, "Vector", lobe, "Normal")
        T.link(t_unit, "Vector", lobe, "Tangent")
        T.link(lobe, "BSDF", add, 1)
        return mat
    g = ri.glossy
    glossy = T.node("ShaderNodeBsdfGlossy", 1, -1, distribution="GGX")
    T.link(glossy, 0, add, 1)
    T.link(n_unit, "Vector", glossy, "Normal")
    T.link(t_unit, "Vector", glossy, "Tangent")
    T.link(
        T.image(packed_image(f"{name} roughness", g["roughness"]), -1, -2, "roughness (ax ay)^1/4"),
        "Color",
        glossy,
        "Roughness",
    )
    T.link(
        T.image(packed_image(f"{name} anisotropy", g["anisotropy"]), -1, -3, "anisotropy (signed)"),
        "Color",
        glossy,
        "Anisotropy",
    )
    scale = T.node("ShaderNodeVectorMath", 0, 0, "rho_s x Fresnel", operation="SCALE")
    T.link(spec, "Color", scale, 0)
    T.link(scale, "Vector", glossy, "Color")
    # colour = rho_s * (0.04 + 0.96 (1 - n.v)^5)
    lw = T.node("ShaderNodeLayerWeight", -2, 1, "Schlick: 1 - n.v")
    lw.inputs["Blend"].default_value = 0.5
    T.link(n_unit, "Vector", lw, "Normal")
    pw = T.node("ShaderNodeMath", -1, 1, "^5", operation="POWER")
    pw.inputs[1].default_value = 5.0
    fr = T.node("ShaderNodeMath", 0, 1, "0.04 + 0.96 x", operation="MULTIPLY_ADD")
    fr.inputs[1].default_value, fr.inputs[2].default_value = 1 - F0_DIELECTRIC, F0_DIELECTRIC
    T.link(lw, "Facing", pw, 0)
    T.link(pw, 0, fr, 0)
    T.link(fr, 0, scale, "Scale")
    return mat


def build_materials(
    result: str | Path,
    obj: bpy.types.Object | None = None,
    variant: str = DEFAULT_VARIANT,
    require_report: bool = True,
    exact_fresnel: bool = False,
) -> tuple[bpy.types.Material, bpy.types.Material]:
    """Both materials for a result folder (``read_result``); ``obj`` (if given) gets ``variant`` in
    its first slot. The other material is kept with a fake user so a saved .blend holds both.
    Names derive from the result folder's (``asset_name``), the materials are keyed by its path
    (``result_material``): building again replaces both materials and their images in place (no
    ``.001`` copies, no orphans), and another result in a folder of the same name gets its own.
    ``exact_fresnel``: the accurate variant with the engine's Fresnel on w_i.h (OSL: the scene must
    ``schlick_lobe.use_osl``; the Cycles scanner's photos; module docstring)."""
    if variant not in ("principled", "accurate"):
        raise ValueError(f"variant must be 'principled' or 'accurate', not {variant!r}")
    ri = read_result(result, require_report)  # may raise: nothing created yet
    stem = asset_name(result)
    principled = _principled(ri, f"{PRINCIPLED} ({stem})")
    accurate = _accurate(ri, f"{ACCURATE} ({stem})", exact_fresnel)
    for m in (principled, accurate):
        m.use_fake_user = True
    if obj is not None:
        chosen = principled if variant == "principled" else accurate
        if obj.data.materials:
            obj.data.materials[0] = chosen
        else:
            obj.data.materials.append(chosen)
    return principled, accurate


def import_result_mesh(result: str | Path, name: str | None = None) -> bpy.types.Object:
    """The result's mesh.obj as a smooth-shaded object, coordinates unchanged (z up, metres);
    object and mesh named ``name`` (default ``asset_name``)."""
    path = Path(result) / "mesh.obj"
    if not path.is_file():
        raise NtpInputError(path, "mesh missing")
    before = set(bpy.data.objects)
    bpy.ops.wm.obj_import(filepath=str(path), forward_axis="Y", up_axis="Z")
    new = [o for o in bpy.data.objects if o not in before and o.type == "MESH"]
    if not new:
        raise NtpInputError(path, "no mesh could be imported")
    obj = new[0]
    obj.name = obj.data.name = name or asset_name(result)
    for poly in obj.data.polygons:
        poly.use_smooth = True
    return obj


def pack_file_images(materials: tuple[bpy.types.Material, ...]) -> None:
    """Pack the map files ``materials`` reference into the .blend, so a saved file is self-contained."""
    for mat in materials:
        for node in mat.node_tree.nodes:
            img = getattr(node, "image", None)
            if img is not None and img.packed_file is None and img.source == "FILE":
                img.pack()
