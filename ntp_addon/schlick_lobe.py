"""The engine's specular lobe in Cycles: rho_s x anisotropic GGX x Schlick's Fresnel on w_i.h, as
an OSL script node (``schlick_lobe.osl``; Cycles' ``generalized_schlick_bsdf`` with f0 = 0.04,
exponent 5, evaluated per microfacet on w_i.h) — docs/design.md's F, its rise bounded: F90 =
min(1, 1 / rho_s) per channel (``ntp_engine.physics.brdf.bounded_f90``), so no lobe reflects more
than all the light. docs/design.md's F90 = 1 differs only for rho_s > 1 and w_i.h < 0.9: never on a
path from the scanner's emitters (beside the camera), only for light bounced onto the object —
where it made the gallery's rho_s 5-10 metals reflect up to 10x the light grazing them (their
interreflections under Cycles; docs/virtual-scanner.md).

No built-in node has this: the Glossy BSDF has no Fresnel, the Metallic BSDF's F82 caps the
anisotropy at 10:1, and node colours see only n.v. OSL runs on the CPU (and OptiX): the scene must
set ``scene.cycles.shading_system = True`` (``use_osl``) or Cycles renders the node black.

The node is compiled here (Cycles' own ``_cycles.osl_compile``) and its sockets made from the
shader's known parameters, not through the add-on's script-node update, which needs Blender's
bundled ``oslquery`` and fails in a process that imported PyPI's OpenImageIO first (the engine's
image I/O does). Sockets: ``rho_s`` (colour), ``alpha_x`` / ``alpha_y`` (GGX widths, alpha_x
along the tangent), ``f0`` (0.04), ``Normal`` and ``Tangent`` (world space); output ``BSDF``.
"""

from __future__ import annotations

import hashlib
import tempfile
from functools import cache
from pathlib import Path

import bpy

from ntp_engine.physics.brdf import F0_DIELECTRIC

SOURCE = Path(__file__).with_name("schlick_lobe.osl")
INPUTS = (
    ("NodeSocketColor", "rho_s"),
    ("NodeSocketFloat", "alpha_x"),
    ("NodeSocketFloat", "alpha_y"),
    ("NodeSocketFloat", "f0"),
    ("NodeSocketVector", "Normal"),
    ("NodeSocketVector", "Tangent"),
)


@cache
def bytecode() -> str:
    """The shader's OSL bytecode (compiled once per process)."""
    import _cycles  # Cycles' Python module, present wherever bpy is

    with tempfile.TemporaryDirectory() as tmp:
        oso = Path(tmp) / "schlick_lobe.oso"
        if not _cycles.osl_compile(str(SOURCE), str(oso)) or not oso.is_file():
            raise RuntimeError(f"{SOURCE}: OSL compilation failed (Blender built without OSL?)")
        return oso.read_text()


def use_osl(scene: bpy.types.Scene) -> None:
    """Render ``scene`` with OSL on the CPU, as the lobe node needs."""
    scene.cycles.device = "CPU"
    scene.cycles.shading_system = True


def schlick_lobe_node(node_tree: bpy.types.NodeTree) -> bpy.types.Node:
    """A new script node of the lobe in ``node_tree`` (f0 = 0.04; link or set its other inputs)."""
    code = bytecode()
    node = node_tree.nodes.new("ShaderNodeScript")
    node.label = "rho_s x GGX x Schlick on w_i.h (OSL)"
    for kind, name in INPUTS:
        node.inputs.new(type=kind, name=name, identifier=name)
    node.outputs.new(type="NodeSocketShader", name="BSDF", identifier="BSDF")
    node.bytecode, node.bytecode_hash = code, hashlib.md5(code.encode(), usedforsecurity=False).hexdigest()
    node.inputs["f0"].default_value = F0_DIELECTRIC
    return node
