"""Per-texel inputs of the two Blender materials, derived from a result folder's maps (bpy-free).

Convention: arrays are ``(H, W, C)`` in the maps' layout (row 0 = top, v = 1). The mesh's UV tangent
frame per texel (``ntp_engine.io.texels``: dP/du made orthogonal to the interpolated normal) stands in
for Blender's UV tangent (MikkTSpace), which it matches up to the per-vertex averaging.

Cycles facts these follow (Cycles 4.x/5.x kernel, ``svm_closure.h``):
- Principled BSDF: alpha_x = r^2 / s, alpha_y = r^2 s with s = sqrt(1 - 0.9 a), a in [0, 1], the
  larger alpha along the tangent — so r = (alpha_x alpha_y)^(1/4) exactly and the ratio is capped
  at 10:1. F0 = F0(IOR 1.5) x 2 x Specular IOR Level x Specular Tint.
- Glossy BSDF (GGX): alpha_x = r^2 (1 - a), alpha_y = r^2 / (1 - a) for a >= 0 and
  alpha_x = r^2 / (1 + a), alpha_y = r^2 (1 + a) for a < 0, a clamped to +-0.99 — ratios up to
  10^4, so the accurate variant keeps every measured ratio of the paper's range (0.006..0.5).
"""

from __future__ import annotations

import numpy as np

from ntp_engine.io.colour import srgb_encode
from ntp_engine.io.maps import SVBRDFMaps, fill_missing
from ntp_engine.io.mesh import Mesh
from ntp_engine.io.texels import rasterize
from ntp_engine.io.viewers import CYCLES_PRINCIPLED_MAX_ANISOTROPY, base_colour_for_fresnel_mix

_PRINCIPLED_SPAN = 1 - 1 / CYCLES_PRINCIPLED_MAX_ANISOTROPY  # Cycles' 0.9: Anisotropic 1 gives 10:1


def uv_frames(mesh: Mesh, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Interpolated normal and UV tangent per texel, ``(H, W, 3)`` each (gaps filled by nearest)."""
    tex = rasterize(mesh, shape)
    known = np.zeros(shape, bool)
    known[tex.row, tex.col] = True
    n, t = np.zeros(shape + (3,)), np.zeros(shape + (3,))
    n[tex.row, tex.col], t[tex.row, tex.col] = tex.normal, tex.tangent
    return fill_missing(n, known), fill_missing(t, known)


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-12)


def principled_inputs(maps: SVBRDFMaps, mesh: Mesh) -> dict[str, np.ndarray]:
    """Principled BSDF inputs per texel, laid out as glTF reads them: ``base_color_srgb`` (H, W, 3,
    sRGB-encoded rho_d / (1 - 0.04 rho_s): glTF's fresnel_mix dims the diffuse by the specular's
    F, ``base_colour_for_fresnel_mix``), ``roughness`` (H, W, 1), ``anisotropy`` (H, W, 3) in the
    KHR_materials_anisotropy layout (RG = direction of the larger alpha in the UV tangent frame,
    encoded 0.5 v + 0.5; B = Blender's Anisotropic), KHR_materials_specular's ``specular_strength``
    (H, W, 1, in [0, 1]: max_c rho_s / ``specular_scale``, the scalar that becomes the material's
    factor) and ``specular_tint_srgb`` (H, W, 3, sRGB-encoded rho_s / max_c rho_s),
    ``normal_tangent_space`` (H, W, 3, encoded 0.5 v + 0.5). Blender's Specular IOR Level is
    strength x scale / 2 (F0 = 0.04 x 2 x level x tint = 0.04 rho_s)."""
    ax, ay = maps.roughness[..., 0], maps.roughness[..., 1]
    hi, lo = np.maximum(ax, ay), np.minimum(ax, ay)
    strength = np.clip((1 - lo / hi) / _PRINCIPLED_SPAN, 0.0, 1.0)
    n_geo, t_uv = uv_frames(mesh, maps.normal.shape[:2])
    n = _unit(maps.normal)
    t = _unit(maps.tangent - (maps.tangent * n).sum(-1, keepdims=True) * n)
    major = np.where((ax >= ay)[..., None], t, np.cross(n, t))  # axis of the larger alpha
    tu = _unit(t_uv - (t_uv * n).sum(-1, keepdims=True) * n)  # Cycles orthogonalises T against N
    bu = np.cross(n, tu)
    theta = np.arctan2((major * bu).sum(-1), (major * tu).sum(-1))
    aniso = np.stack([0.5 * np.cos(theta) + 0.5, 0.5 * np.sin(theta) + 0.5, strength], -1)
    s = np.maximum(maps.specular_albedo.max(-1, keepdims=True), 1e-6)
    scale = float(s.max())  # glTF's specular strength is a texture in [0, 1] times a factor
    tg = _unit(t_uv - (t_uv * n_geo).sum(-1, keepdims=True) * n_geo)
    bg = np.cross(n_geo, tg)
    n_ts = np.stack([(n * tg).sum(-1), (n * bg).sum(-1), (n * n_geo).sum(-1)], -1)
    return {
        "roughness": ((ax * ay) ** 0.25)[..., None],
        "anisotropy": aniso,
        "base_color_srgb": srgb_encode(base_colour_for_fresnel_mix(maps.diffuse_albedo, maps.specular_albedo)[0]),
        "specular_strength": s / scale,
        "specular_scale": np.array(scale),
        "specular_tint_srgb": srgb_encode(np.clip(maps.specular_albedo / s, 0, 1)),
        "normal_tangent_space": 0.5 * _unit(n_ts) + 0.5,
    }


def glossy_inputs(maps: SVBRDFMaps) -> dict[str, np.ndarray]:
    """Glossy BSDF (GGX) inputs of the accurate variant: ``roughness`` (H, W, 1) and signed
    ``anisotropy`` (H, W, 1) with alpha_x along the tangent map."""
    ax, ay = maps.roughness[..., 0], maps.roughness[..., 1]
    a = np.where(ax <= ay, 1 - np.sqrt(ax / ay), np.sqrt(ay / ax) - 1)
    return {"roughness": ((ax * ay) ** 0.25)[..., None], "anisotropy": np.clip(a, -0.99, 0.99)[..., None]}


def principled_alphas(roughness: np.ndarray, anisotropic: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(larger, smaller) alpha Cycles' Principled BSDF makes of Roughness and Anisotropic."""
    s = np.sqrt(1 - _PRINCIPLED_SPAN * np.clip(anisotropic, 0, 1))
    return roughness**2 / s, roughness**2 * s


def glossy_alphas(roughness: np.ndarray, anisotropy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(alpha_x, alpha_y) Cycles' Glossy BSDF makes of Roughness and Anisotropy."""
    a = np.clip(anisotropy, -0.99, 0.99)
    r2 = roughness**2
    return np.where(a >= 0, r2 * (1 - a), r2 / (1 + a)), np.where(a >= 0, r2 / (1 - a), r2 * (1 + a))
