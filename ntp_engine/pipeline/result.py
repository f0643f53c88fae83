"""The result folder (docs/design.md output contract): maps, confidence, previews, mesh and material.json.

Per-trace fits (``fit_traces``) are turned from each texel's geometric frame into object space and
laid out in the UV map; texels no trace reached keep the geometric frame and take their values from
the nearest observed texel (seams and holes dilated), marked in ``confidence.exr`` (R = a usable
lobe was fitted, G = trace length).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..fit.flags import TexelFlag
from ..fit.texel_fit import TexelFit
from ..io.atomic import write_text_atomic
from ..io.images import write_exr, write_png
from ..io.maps import MAP_FILES, SVBRDFMaps, axis_weight, consistent_axes
from ..io.mesh import Mesh, save_obj
from ..io.texels import Texels
from ..physics.brdf import ALPHA_MAX, F0_DIELECTRIC, RHO_S_MAX
from ..refine.materials import BasisMaterials
from ..scanner.local_frame import moved, position_digits

PREVIEW_GAMMA = 2.2
UNCERTAINTY_FILE = "uncertainty.exr"  # with the refinement: per-parameter 1-sigma (material.json says how)
UNCONSTRAINED_STD = 1000.0  # an uncertainty this large or more: the photos do not determine the parameter


def basis_materials_doc(materials: BasisMaterials, width_varies: np.ndarray | None = None) -> dict:
    """``material.json``'s description of the basis materials and where each texel's is;
    ``width_varies (K,)``: which materials' widths are fields over the object."""
    varies = np.zeros(len(materials), bool) if width_varies is None else width_varies
    return {
        "file": "confidence.exr",
        "channel": "B",
        "meaning": "1 + index into table: the lobe material the texel belongs to (0: none, matte or unseen); "
        "a texel whose own photos did not show its lobe has its material's, refined against its photos",
        "table": [
            {
                "rho_d": [round(float(v), 4) for v in materials.lobe_rho_d[k]],  # under its own lobe
                "alpha": [round(float(v), 4) for v in materials.alpha[k]],
                "rho_s": [round(float(v), 4) for v in materials.rho_s[k]],
                "share": round(float(materials.share[k]), 3),
                # alpha is then its pooled width; its texels take the width their neighbours' photos show
                "width_varies": bool(varies[k]),
            }
            for k in range(len(materials))
        ],
    }


def write_result(
    out: Path, mesh: Mesh, texels: Texels, fitted: TexelFit, lengths: np.ndarray, origin: np.ndarray | None = None
) -> None:
    """Maps (EXR), confidence, previews, mesh, material.json into ``out`` (each file atomically;
    ``reconstruct`` passes a staging folder and publishes it, ``output_folder.publish``).
    Texels without a trace keep the geometric frame and get their values from the nearest observed
    texel (seams and holes dilated)."""
    observed = lengths > 0
    frame = texels.frame
    n_obj = np.einsum("tji,tj->ti", frame, fitted.n_loc)
    t_obj = np.einsum("tji,tj->ti", frame, fitted.t_loc)
    n_obj = np.where(observed[:, None], n_obj, texels.normal)
    t_obj = np.where(observed[:, None], t_obj, texels.tangent)
    H, W = texels.shape

    def to_map(values: np.ndarray) -> np.ndarray:
        return texels.image(values, known=observed)

    n_map, t_map = to_map(n_obj), to_map(t_obj)
    n_map /= np.maximum(np.linalg.norm(n_map, axis=-1, keepdims=True), 1e-12)
    t_map -= (t_map * n_map).sum(-1, keepdims=True) * n_map
    t_map /= np.maximum(np.linalg.norm(t_map, axis=-1, keepdims=True), 1e-12)
    alpha_map = to_map(fitted.alpha)
    t_map = consistent_axes(t_map, axis_weight(alpha_map))
    maps = SVBRDFMaps(to_map(fitted.rho_d), to_map(fitted.rho_s), n_map, t_map, alpha_map)
    out.mkdir(parents=True, exist_ok=True)
    maps.save(out)
    conf = np.zeros((H, W, 3))
    conf[texels.row, texels.col, 0] = observed & ((fitted.flags & TexelFlag.NO_LOBE) == 0)
    conf[texels.row, texels.col, 1] = lengths
    documented = {}
    if fitted.material is not None:  # the refinement's basis materials (refine.materials, refine.material_pass)
        conf[texels.row, texels.col, 2] = fitted.material + 1  # 0: no lobe material (-1 matte, -2 unseen)
        table = BasisMaterials.from_arrays(fitted.materials) if fitted.materials else BasisMaterials.empty()
        documented["basis_materials"] = basis_materials_doc(table, fitted.width_varies)
    write_exr(out / "confidence.exr", conf)
    if fitted.std is not None:  # the refinement's 1-sigma uncertainties (refine.policy.Refined.std)
        unc = np.full((H, W, 4), UNCONSTRAINED_STD)
        std = np.nan_to_num(fitted.std, nan=UNCONSTRAINED_STD, posinf=UNCONSTRAINED_STD)
        unc[texels.row, texels.col] = np.minimum(std, UNCONSTRAINED_STD)
        write_exr(out / UNCERTAINTY_FILE, unc)
        documented["uncertainty"] = {
            "file": UNCERTAINTY_FILE,
            "channels": {
                "R": "normal, deg",
                "G": "tangent angle, deg",
                "B": "log alpha (the larger)",
                "A": "log rho_s (channel mean)",
            },
            "meaning": (
                "1-sigma of each parameter given the texel's photos (Gauss-Newton at the refined answer); "
                "normal and tangent: after fusing with the neighbours' where the field is smooth"
            ),
            "unconstrained": f">= {UNCONSTRAINED_STD:g}: the photos do not determine it (or no photo saw the texel, "
            "or it settled on its range's bound -- alpha 0.006 or 0.5, rho_s 10 -- and the photos bound it from one "
            "side only: flag AT_BOUND)",
        }
    previews = out / "previews"
    write_png(previews / "diffuse_albedo.png", maps.diffuse_albedo ** (1 / PREVIEW_GAMMA))
    write_png(previews / "specular_albedo.png", (maps.specular_albedo / RHO_S_MAX) ** (1 / PREVIEW_GAMMA))
    write_png(previews / "normal.png", 0.5 * (maps.normal + 1))
    write_png(previews / "tangent.png", 0.5 * (maps.tangent + 1))
    write_png(previews / "roughness.png", np.concatenate([maps.roughness / ALPHA_MAX, np.zeros((H, W, 1))], -1))
    origin = np.zeros(3) if origin is None else origin  # ``mesh`` is in the scan's local frame: back to the world's
    save_obj(out / "mesh.obj", moved(mesh, origin), position_digits(origin))
    write_text_atomic(
        out / "material.json",
        json.dumps(
            {
                "model": "anisotropic GGX (ntp)",
                "maps": dict(MAP_FILES),
                "conventions": {
                    "normal": "object space, unit",
                    "tangent": "object space, unit, alpha_x along it; an axis (t and -t are the same lobe), "
                    "signed to agree between neighbouring texels so filtered lookups keep it",
                    "roughness": "R = alpha_x, G = alpha_y",
                    "albedo": "linear",
                    "units": "metres",
                    "fresnel_f0": F0_DIELECTRIC,
                    "uv_origin": "bottom-left",
                },
                **documented,
            },
            indent=2,
        ),
    )
