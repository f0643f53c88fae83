"""Coverage on the mesh: the result's confidence and uncertainty maps as a colour overlay on the
active object, red where the photos measured too little (scan more there), green where they
measured well, with a legend in the NTP panel.

``LAYERS`` is the bpy-free description (``ntp_engine.pipeline.coverage_layers``, which the result page
shares); this module is the glue:
an emission material "NTP coverage" that maps the channel through a red-yellow-green ramp, swapped
onto the object's material slots while shown and swapped back (the user's materials, exactly) when
turned off.
"""

from __future__ import annotations

from pathlib import Path

import bpy

from ntp_engine.io.errors import NtpInputError
from ntp_engine.pipeline.coverage_layers import LAYERS, RAMP
from ntp_engine.pipeline.result import UNCERTAINTY_FILE

MATERIAL = "NTP coverage"
RESTORE = "ntp_coverage_restore"  # object property: the slots' material names before the overlay
ITEMS = [("off", "Off", "The object's own materials")] + [(k, v.label, v.hint) for k, v in LAYERS.items()]


def layer_material(result: Path, key: str) -> bpy.types.Material:
    """The overlay material for ``LAYERS[key]`` of ``result`` (rebuilt in place on each call).
    ``NtpInputError`` naming the file if the result lacks it."""
    layer = LAYERS[key]
    path = Path(result) / layer.file
    if not path.is_file():
        why = "missing (reconstruct with --refine for uncertainties)" if layer.file == UNCERTAINTY_FILE else "missing"
        raise NtpInputError(path, why)
    name = f"{MATERIAL} {Path(result).resolve().name} {layer.file}"
    img = bpy.data.images.get(name)
    if img is None or Path(bpy.path.abspath(img.filepath)) != path:
        if img is not None:
            bpy.data.images.remove(img)
        img = bpy.data.images.load(str(path), check_existing=False)
        img.name = name
    else:
        img.reload()
    img.colorspace_settings.name = "Non-Color"
    mat = bpy.data.materials.get(MATERIAL) or bpy.data.materials.new(MATERIAL)
    if mat.node_tree is None:  # Blender < 5 makes materials without a node tree
        mat.use_nodes = True
    nodes, links = mat.node_tree.nodes, mat.node_tree.links
    nodes.clear()
    tex = nodes.new("ShaderNodeTexImage")
    tex.image, tex.interpolation = img, "Closest"  # one texel, one value: no blending across the legend
    split = nodes.new("ShaderNodeSeparateColor")
    links.new(tex.outputs["Color"], split.inputs["Color"])
    source = tex.outputs["Alpha"] if layer.channel == 3 else split.outputs[layer.channel]
    scale = nodes.new("ShaderNodeMapRange")  # bad → 0, good → 1, clamped
    scale.clamp = True
    scale.inputs["From Min"].default_value, scale.inputs["From Max"].default_value = layer.bad, layer.good
    links.new(source, scale.inputs["Value"])
    ramp = nodes.new("ShaderNodeValToRGB")
    ramp.name = "legend"
    elements = ramp.color_ramp.elements
    while len(elements) < len(RAMP):
        elements.new(0.5)
    for element, (position, colour) in zip(elements, RAMP, strict=True):
        element.position, element.color = position, colour
    links.new(scale.outputs["Result"], ramp.inputs["Fac"])
    emit = nodes.new("ShaderNodeEmission")
    links.new(ramp.outputs["Color"], emit.inputs["Color"])
    out = nodes.new("ShaderNodeOutputMaterial")
    links.new(emit.outputs["Emission"], out.inputs["Surface"])
    for i, n in enumerate((tex, split, scale, ramp, emit, out)):
        n.location = (i * 220.0, 0.0)
    mat["ntp_layer"] = key
    return mat


def show(obj: bpy.types.Object, result: Path, key: str) -> None:
    """Show ``key`` of ``result`` on ``obj`` (``"off"``: give the object its materials back)."""
    if key == "off":
        hide(obj)
        return
    mat = layer_material(result, key)
    if RESTORE not in obj:  # the first overlay remembers the user's materials; later ones keep that
        obj[RESTORE] = [s.material.name if s.material else "" for s in obj.material_slots]
    if not obj.material_slots:
        obj.data.materials.append(mat)
    for slot in obj.material_slots:
        slot.material = mat


def hide(obj: bpy.types.Object) -> None:
    """Restore ``obj``'s materials as they were before the overlay (nothing if none is shown)."""
    if RESTORE not in obj:
        return
    names = list(obj[RESTORE])
    if not names:
        obj.data.materials.clear()
    for slot, name in zip(obj.material_slots, names, strict=False):
        slot.material = bpy.data.materials.get(name) if name else None
    del obj[RESTORE]


def on_change(settings, context) -> None:
    """Update of the ``coverage`` setting: show the layer on the active mesh, or report why not."""
    from .operators import result_folder  # the operators' rule for the result folder (no import cycle)

    obj = context.active_object
    if obj is None or obj.type != "MESH":
        settings.status = "coverage: select the scanned mesh first"
        return
    try:
        show(obj, result_folder(context), settings.coverage)
    except NtpInputError as err:
        settings.status = f"coverage: {err}"
        return
    if settings.coverage != "off":
        settings.status = f"coverage: {LAYERS[settings.coverage].hint}"


def legend_node():
    """The overlay's ramp node (the panel draws it as the legend), or ``None``."""
    mat = bpy.data.materials.get(MATERIAL)
    return mat.node_tree.nodes.get("legend") if mat is not None and mat.node_tree else None
