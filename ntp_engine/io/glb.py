"""A binary glTF (``.glb``) read back: its JSON, its binary chunk and its images as pixels — what
a viewer would take from the file, for the checks that compare it with ntp's own maps.

Convention: pixels float32 ``(H, W, C)`` in [0, 1] as stored (no colour decoding), row 0 = top.
"""

from __future__ import annotations

import json
import struct
import tempfile
from pathlib import Path

import numpy as np

from .errors import NtpInputError
from .images import Decoded, decode
from .viewers import khronos_alphas

GLB_MAGIC, JSON_CHUNK, BIN_CHUNK = b"glTF", 0x4E4F534A, 0x004E4942


def read_glb(path: str | Path) -> tuple[dict, bytes]:
    """The file's JSON and its binary chunk (``b""`` without one)."""
    path = Path(path)
    blob = path.read_bytes()
    if len(blob) < 20 or blob[:4] != GLB_MAGIC:
        raise NtpInputError(path, "not a binary glTF (.glb)")
    offset, gltf, binary = 12, None, b""
    while offset + 8 <= len(blob):
        length, kind = struct.unpack_from("<II", blob, offset)
        chunk = blob[offset + 8 : offset + 8 + length]
        if kind == JSON_CHUNK:
            gltf = json.loads(chunk)
        elif kind == BIN_CHUNK:
            binary = chunk
        offset += 8 + length
    if gltf is None:
        raise NtpInputError(path, "no JSON chunk")
    return gltf, binary


def texture_pixels(gltf: dict, binary: bytes, texture: int) -> np.ndarray:
    """The pixels of texture index ``texture``'s image (stored in the binary chunk)."""
    return texture_image(gltf, binary, texture).pixels


def texture_image(gltf: dict, binary: bytes, texture: int) -> Decoded:
    """Texture index ``texture``'s image as decoded (pixels and the file's own pixel format)."""
    image = gltf["images"][gltf["textures"][texture]["source"]]
    view = gltf["bufferViews"][image["bufferView"]]
    data = binary[view.get("byteOffset", 0) : view.get("byteOffset", 0) + view["byteLength"]]
    suffix = {"image/png": ".png", "image/jpeg": ".jpg"}.get(image.get("mimeType", ""), ".png")
    with tempfile.NamedTemporaryFile(suffix=suffix) as f:
        f.write(data)
        f.flush()
        return decode(f.name)


def anisotropic_alphas(path: str | Path, material: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """(alpha_t, alpha_b) ``(H, W)`` that a viewer conforming to ``KHR_materials_anisotropy`` draws
    for ``material`` of the file: roughness from the metallic-roughness texture's G times
    ``roughnessFactor``, strength from the anisotropy texture's B times ``anisotropyStrength``."""
    gltf, binary = read_glb(path)
    mat = gltf["materials"][material]
    pbr = mat.get("pbrMetallicRoughness", {})
    rough = (
        pbr.get("roughnessFactor", 1.0) * texture_pixels(gltf, binary, pbr["metallicRoughnessTexture"]["index"])[..., 1]
    )
    ext = mat["extensions"]["KHR_materials_anisotropy"]
    strength = (
        ext.get("anisotropyStrength", 1.0) * texture_pixels(gltf, binary, ext["anisotropyTexture"]["index"])[..., 2]
    )
    return khronos_alphas(rough, strength)
