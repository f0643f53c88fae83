"""SVBRDF texture maps in a mesh's UV layout (docs/design.md output contract).

Files (linear float EXR): ``diffuse_albedo.exr`` (RGB rho_d), ``specular_albedo.exr`` (RGB rho_s),
``normal.exr`` (object-space unit normal), ``tangent.exr`` (object-space unit tangent, alpha_x
along it), ``roughness.exr`` (R = alpha_x, G = alpha_y, B = 0).
Convention: texel (row, col) of an H x W map has its centre at uv = ((col + 0.5) / W,
1 - (row + 0.5) / H): row 0 is the top of the file and v = 1 (Blender's UV origin is bottom-left).
Sampling is bilinear with clamped edges; normal/tangent samples are re-normalised. A tangent is an
axis (t and -t are the same lobe), so a written tangent map is signed to agree between neighbouring
texels (``consistent_axes``): bilinear filtering of opposite vectors cancels them.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .errors import NtpInputError
from .images import read_image, write_exr

MAP_FILES = {
    "diffuse_albedo": "diffuse_albedo.exr",
    "specular_albedo": "specular_albedo.exr",
    "normal": "normal.exr",
    "tangent": "tangent.exr",
    "roughness": "roughness.exr",
}


@dataclass
class SVBRDFMaps:
    """The five SVBRDF maps of one asset, ``(H, W, C)`` float64 in the UV layout above."""

    diffuse_albedo: np.ndarray  # (H, W, 3)
    specular_albedo: np.ndarray  # (H, W, 3)
    normal: np.ndarray  # (H, W, 3) unit, object space
    tangent: np.ndarray  # (H, W, 3) unit, object space
    roughness: np.ndarray  # (H, W, 2): alpha_x, alpha_y

    @property
    def shape(self) -> tuple[int, int]:
        """(H, W) of the maps."""
        h, w = self.diffuse_albedo.shape[:2]
        return h, w

    def save(self, folder: str | Path) -> None:
        """Write the five EXR files into ``folder`` (roughness gets a zero B channel)."""
        folder = Path(folder)
        for name, file in MAP_FILES.items():
            data = getattr(self, name)
            if name == "roughness":
                data = np.concatenate([data, np.zeros(data.shape[:2] + (1,))], -1)
            write_exr(folder / file, data)

    @classmethod
    def load(cls, folder: str | Path) -> SVBRDFMaps:
        """Read the five maps; one-line errors name the file (missing, unreadable, wrong size)."""
        folder = Path(folder)
        arrays, shape = {}, None
        for name, file in MAP_FILES.items():
            path = folder / file
            if not path.is_file():
                raise NtpInputError(path, "map file missing")
            img = read_image(path)
            if img.shape[2] < 3:
                raise NtpInputError(path, f"expected 3 channels, got {img.shape[2]}")
            if shape is None:
                shape = img.shape[:2]
            elif img.shape[:2] != shape:
                raise NtpInputError(
                    path,
                    f"size {img.shape[1]}x{img.shape[0]} differs from "
                    f"{shape[1]}x{shape[0]} of {MAP_FILES['diffuse_albedo']}",
                )
            if not np.isfinite(img).all():
                raise NtpInputError(path, "map contains NaN or Inf")
            arrays[name] = img[..., :2] if name == "roughness" else img[..., :3]
        return cls(**{k: v.astype(np.float64) for k, v in arrays.items()})

    def sample(self, uv: np.ndarray, taps: np.ndarray | None = None) -> dict[str, np.ndarray]:
        """Bilinear samples at ``uv (N, 2)``: each map ``(N, C)``; normals/tangents re-normalised,
        the tangent made orthogonal to the normal. ``taps (N, 4)``: which texels each sample may
        read (``bilinear_pixels``)."""
        out = {name: bilinear(getattr(self, name), uv, taps) for name in MAP_FILES}
        n = _unit(out["normal"])
        t = out["tangent"] - (out["tangent"] * n).sum(-1, keepdims=True) * n
        out["normal"], out["tangent"] = n, _unit(t)
        return out


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.maximum(np.linalg.norm(v, axis=-1, keepdims=True), 1e-12)


def uv_to_pixel(uv: np.ndarray, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Continuous (row, col) pixel coordinates (centres at integers) of ``uv (N, 2)``."""
    h, w = shape
    return (1.0 - uv[:, 1]) * h - 0.5, uv[:, 0] * w - 0.5


def texel_uv(shape: tuple[int, int]) -> np.ndarray:
    """uv ``(H, W, 2)`` of every texel centre."""
    h, w = shape
    rows, cols = np.meshgrid(np.arange(h), np.arange(w), indexing="ij")
    return np.stack([(cols + 0.5) / w, 1.0 - (rows + 0.5) / h], -1)


def bilinear(img: np.ndarray, uv: np.ndarray, taps: np.ndarray | None = None) -> np.ndarray:
    """Bilinear samples ``(N, C)`` of a map at ``uv (N, 2)`` (edges clamped); ``taps (N, 4)``,
    optional: which of the four texels each may read (``bilinear_pixels``)."""
    r, c = uv_to_pixel(uv, (img.shape[0], img.shape[1]))
    return bilinear_pixels(img, r, c, taps)


def bilinear_corners(
    h: int, w: int, r: np.ndarray, c: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The four pixels a bilinear sample of an ``(h, w)`` image at continuous (row, col) ``r, c (N,)``
    reads (pixel centres at integers, clamped to the image): their rows and columns ``(N, 4)`` in
    the order r0c0, r0c1, r1c0, r1c1 (r0 = floor(r)), and the fractions ``fr, fc (N, 1)`` past r0, c0."""
    r = np.clip(r, 0, h - 1)
    c = np.clip(c, 0, w - 1)
    r0, c0 = np.floor(r).astype(np.int64), np.floor(c).astype(np.int64)
    r1, c1 = np.minimum(r0 + 1, h - 1), np.minimum(c0 + 1, w - 1)
    return np.stack([r0, r0, r1, r1], 1), np.stack([c0, c1, c0, c1], 1), (r - r0)[:, None], (c - c0)[:, None]


def bilinear_weights(fr: np.ndarray, fc: np.ndarray) -> np.ndarray:
    """The weights ``(N, 4)`` of the four pixels of ``bilinear_corners`` (its order) for the
    fractions ``fr, fc (N, 1)`` past r0, c0."""
    return np.concatenate([(1 - fr) * (1 - fc), (1 - fr) * fc, fr * (1 - fc), fr * fc], 1)


def bilinear_pixels(img: np.ndarray, r: np.ndarray, c: np.ndarray, taps: np.ndarray | None = None) -> np.ndarray:
    """Bilinear samples ``(N, C)`` of an ``(H, W, C)`` image at continuous (row, col) pixel
    coordinates, pixel centres at integers, clamped to the image. ``taps (N, 4)`` bool, optional:
    which of the four pixels (``bilinear_corners``' order) a sample may read — the others' weights
    go to them in proportion to their own (each at least ``1e-6``, so a sample on an excluded
    pixel's centre still reads its neighbours); each row needs one True."""
    rows, cols, fr, fc = bilinear_corners(img.shape[0], img.shape[1], r, c)
    v = [img[rows[:, k], cols[:, k]] for k in range(4)]
    out = (1 - fr) * ((1 - fc) * v[0] + fc * v[1]) + fr * ((1 - fc) * v[2] + fc * v[3])
    if taps is None:
        return out
    some = np.nonzero(~taps.all(1))[0]
    fr, fc = fr[some], fc[some]
    wt = np.maximum(bilinear_weights(fr, fc), 1e-6) * taps[some]
    wt /= wt.sum(1, keepdims=True)
    out[some] = sum(wt[:, k : k + 1] * v[k][some] for k in range(4))
    return out


def axis_weight(alpha: np.ndarray) -> np.ndarray:
    """How much a lobe's axis matters ``(...)`` from its widths ``alpha (..., 2)``: its anisotropy
    1 - alpha_min / alpha_max (0: isotropic, the axis is arbitrary) — ``consistent_axes``' weight."""
    return 1.0 - alpha.min(-1) / np.maximum(alpha.max(-1), 1e-12)


def consistent_axes(axes: np.ndarray, weight: np.ndarray | None = None) -> np.ndarray:
    """``axes (H, W, 3)`` (unit, axial: a and -a mean the same) each multiplied by +-1 so that
    neighbouring texels point the same way wherever the field allows. A filtered lookup between an
    axis and its negation cancels to a vector off both (a sharp anisotropic highlight broken into
    streaks between texels), so signs are propagated over the maximum spanning tree of the image's
    4-neighbour grid under edge weights ``|a_i . a_j| min(w_i, w_j)``: the best-agreeing pairs
    decide, and where the axial field cannot be signed (a turn of 180 deg around a point) the
    disagreement falls between texels that agree least. ``weight (H, W)`` in [0, 1] (default 1):
    how much a texel's axis matters (its anisotropy: an isotropic lobe's axis is arbitrary).
    Convention: the texel at the tree's root (row 0, col 0) keeps its sign. Returns a new array."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import breadth_first_order, minimum_spanning_tree

    H, W, _ = axes.shape
    a = axes.reshape(-1, 3)
    w = np.ones(H * W) if weight is None else np.clip(weight, 0.0, 1.0).reshape(-1)
    idx = np.arange(H * W).reshape(H, W)
    i = np.concatenate([idx[:, :-1].ravel(), idx[:-1, :].ravel()])
    j = np.concatenate([idx[:, 1:].ravel(), idx[1:, :].ravel()])
    agree = np.abs((a[i] * a[j]).sum(1)) * np.minimum(w[i], w[j])
    # a minimum spanning tree over 2 - agreement (every weight > 0: all edges stay in the graph)
    tree = minimum_spanning_tree(coo_matrix((2.0 - agree, (i, j)), shape=(H * W, H * W)).tocsr())
    _, parent = breadth_first_order(tree, 0, directed=False, return_predecessors=True)
    parent[0] = 0  # the grid is connected: only the root has no parent
    # flip[k]: whether texel k disagrees with the root, the parity of disagreements up its branch
    # (pointer jumping: log2(depth) vectorised rounds, no loop over texels)
    flip = (a * a[parent]).sum(1) < 0
    up = parent
    while (up != up[up]).any():
        flip, up = flip ^ flip[up], up[up]
    return np.where(flip[:, None], -a, a).reshape(H, W, 3)


def fill_missing(img: np.ndarray, known: np.ndarray) -> np.ndarray:
    """Every unknown texel takes the value of the nearest known one (seams, holes, unobserved
    texels); ``known (H, W)`` bool. Returns a new array; all-unknown input is returned unchanged."""
    from scipy import ndimage

    if known.all() or not known.any():
        return img.copy()
    _, (ri, ci) = ndimage.distance_transform_edt(~known, return_indices=True)
    return img[ri, ci]
