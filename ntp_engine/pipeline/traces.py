"""Assembling each texel's trace from registered photos (paper §7, Eq. 4).

For every view j and texel p: the texel's object-space point goes into camera j (pose =
camera-from-world, the world being the mesh's frame); the entry is kept if (1) the point is in
front of the camera, projects inside the photo (OpenCV distortion included) and lies in the valid
volume, (2) nothing of the mesh lies between it and the camera (Embree, from the point offset
along its normal), (3) wo . n^ > 0.2 — flagged ``in_range = False`` up to 0.3 (``grazing``).
(4) Which emitter groups the mesh itself hides from the point (``EmitterShadow``) is the entry's
``shadow`` mask; where they carry more than ``MAX_SHADOWED_DRIVE`` of the pattern's drive the entry
is flagged ``in_range = False`` (Eq. 1 as the network learnt it assumes every emitter above the
horizon reaches the point; the refinement models the mask) — or, on a device with more groups
than a mask holds, left out. (5) The entry's pixel is a bilinear sample of four pixels; those whose
centres see another surface (``pixel_taps``: nothing, or a point off the entry's tangent plane — a
silhouette, an occluding edge, another loop of the mesh behind) are not read, their weights going
to the others; an entry none of whose four pixels sees its surface is left out. Entries whose
bilinearly sampled 8-bit pixel has a channel outside [32, 224] (dark or near clipping) are kept too,
flagged ``in_range = False``: the network and the lumitexel fit skip them
(``RaggedTraces.in_range_only``), the refinement models them (a noise floor for dark values, clipped
ones as lower bounds). The entry is (linear pixel RGB * ``pixel_scale``, x, n^, t^) in camera j's
space — the layout of ``learn.ragged.RaggedTraces``. Views that see no texel cost one projection
only. Two passes (visibility, then fill) keep the peak memory near the table's own size, or — the
table written to disk — near one block of it
(docs/performance.md).
"""

from __future__ import annotations

import warnings
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from ..io.atomic import reserve_disk
from ..io.maps import bilinear_corners, bilinear_pixels
from ..io.progress import QUIET, Progress
from ..io.raycast import RayCaster
from ..io.texels import Texels
from ..learn.ragged import RaggedTraces, spans
from ..physics.emitter_blocks import shadow_groups
from ..physics.shadows import MAX_SHADOWED_DRIVE, SupportShadow, grazing, shadowed
from ..scanner import camera
from ..scanner.scanner import Scanner
from .settings import TUNING

TABLE_FILES = ("entries", "offsets", "in_range", "shadow")  # a table on disk: one .npy each (``load_table``)
# the per-entry columns: dtype and shape after the entry axis
_COLUMNS: dict[str, tuple[type, tuple[int, ...]]] = {
    "entries": (np.float32, (12,)),
    "in_range": (np.bool_, ()),
    "shadow": (np.int64, ()),
}


@dataclass
class TraceStats:
    """What assembling traces kept and why it rejected the rest (counts of texel-view pairs)."""

    views_used: int
    entries: int
    texels_observed: int
    rejected: dict[str, int]


class EmitterShadow:
    """Which emitters the mesh itself hides from a texel in a view (a concave object shadowing its
    own light: a knot's inner loops, a box's inside corners): one shadow ray from the point (offset
    ``eps`` along its normal) to each group of ``physics.emitter_blocks.shadow_groups`` (half an
    emitter block; each sample on small devices) above the point's horizon. Texels whose
    hemisphere is open (``TUNING.traces.sky_rays`` rays, none hitting the mesh) are never tested — on convex
    parts the test is free."""

    def __init__(self, scanner: Scanner, caster: RayCaster, texels: Texels, eps: float):
        self.groups = shadow_groups(scanner)
        self.caster, self.eps = caster, eps
        self.position, self.normal = texels.position, texels.normal
        self.open = self._open_sky(texels)

    def _open_sky(self, texels: Texels) -> np.ndarray:
        """``(T,)`` True where none of ``TUNING.traces.sky_rays`` directions over the texel's hemisphere (a
        Fibonacci spiral, cosine-spread about the normal) meets the mesh."""
        k = np.arange(TUNING.traces.sky_rays) + 0.5
        r, phi = np.sqrt(k / TUNING.traces.sky_rays), np.pi * (3 - np.sqrt(5)) * k
        local = np.stack([r * np.cos(phi), r * np.sin(phi), np.sqrt(1 - r**2)], -1)  # (S, 3), z up
        n, t = texels.normal, texels.tangent
        b = np.cross(n, t)
        hit = np.zeros(len(texels), bool)
        origin = texels.position + self.eps * n
        for d in local:
            ray = d[0] * t + d[1] * b + d[2] * n
            hit |= self.caster.occluded(origin, ray, np.full(len(texels), np.inf))
        return ~hit

    def __call__(self, pose: np.ndarray, idx: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
        """For view ``pose`` (camera-from-world) and texels ``idx``: the share of the pattern's drive
        the mesh hides ``(len(idx),)``, and which groups it hides, one int64 mask per texel (bit g:
        group g; None when the groups do not fit a mask or none is hidden)."""
        blocked = np.zeros(len(idx))
        test = np.nonzero(~self.open[idx])[0]
        if len(test) == 0:
            return blocked, None
        R, t = pose[:3, :3], pose[:3, 3]
        emitters = (self.groups.points - t) @ R  # world: R^T (p - t)
        normal = self.normal[idx[test]]
        origin = self.position[idx[test]] + self.eps * normal
        mask = np.zeros(len(test), np.int64)
        for g, (e, drive) in enumerate(zip(emitters, self.groups.drive, strict=True)):
            to = e - origin
            dist = np.linalg.norm(to, axis=1)
            to /= dist[:, None]
            lit = (to * normal).sum(1) > 0  # below the horizon it lights nothing anyway
            hidden = lit & self.caster.occluded(origin, to, dist)
            blocked[test] += drive * hidden
            if self.groups.fits:
                mask |= hidden.astype(np.int64) << g
        if not self.groups.fits or not mask.any():
            return blocked, None
        out = np.zeros(len(idx), np.int64)
        out[test] = mask
        return blocked, out


def pixel_taps(
    scanner: Scanner, caster: RayCaster, pose: np.ndarray, px: np.ndarray, position: np.ndarray, normal: np.ndarray
) -> np.ndarray:
    """Which of the four pixels a bilinear sample at ``px (N, 2)`` (x = column, y = row) blends
    see the entry's own surface: ``(N, 4)`` bool in ``io.maps.bilinear_corners``' order. Each
    distinct pixel's centre ray is cast once (Embree, camera at ``pose``, camera-from-world); a tap
    sees the surface of the point ``position (N, 3)`` with unit ``normal (N, 3)`` (world) when its
    ray hits the mesh within ``TUNING.traces.max_tap_tilt_deg`` of the point's tangent plane as seen from the
    point (or within ``TUNING.traces.tap_tolerance`` of it); no hit is another surface (the background)."""
    h, w = scanner.height, scanner.width
    rows, cols, _, _ = bilinear_corners(h, w, px[:, 1], px[:, 0])
    pixel = rows * w + cols  # (N, 4)
    # neighbouring entries share pixels: each distinct one once (a lookup over the image, not a sort)
    used = np.zeros(h * w, bool)
    used[pixel] = True
    unique = np.flatnonzero(used)
    lookup = np.empty(h * w, np.int64)
    lookup[unique] = np.arange(len(unique))
    inverse = lookup[pixel]
    R, t = pose[:3, :3], pose[:3, 3]
    d = camera.pixel_directions(scanner, unique % w, unique // w) @ R  # world: R^T d
    centre = -R.T @ t
    hits = caster.intersect(np.broadcast_to(centre, d.shape), d)
    missed = (hits.geom < 0) | ~np.isfinite(hits.t)
    hit = centre + d * np.where(missed, 0.0, hits.t)[:, None]
    chord = hit[inverse] - position[:, None]  # (N, 4, 3)
    off = np.einsum("nkc,nc->nk", chord, normal)
    # within the tilt limit (squared: no square roots), or within the tolerance
    flat = (
        off**2 <= np.sin(np.radians(TUNING.traces.max_tap_tilt_deg)) ** 2 * np.einsum("nkc,nkc->nk", chord, chord)
    ) | (np.abs(off) <= TUNING.traces.tap_tolerance)
    return flat & ~missed[inverse]


def _visible(
    texels: Texels,
    pose: np.ndarray,
    scanner: Scanner,
    caster: RayCaster,
    eps: float,
    rejected: dict[str, int],
    emitter_shadow: EmitterShadow | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Texels view ``pose`` measures (conditions 1-3 and 5 of the module docstring, and 4 where
    ``emitter_shadow`` is given: entries it shadows left out; geometry only: no pixel is read):
    their indices, ascending, and which of their pixel taps see them ``(len, 4)`` (``pixel_taps``)."""
    n_tex = len(texels)
    R, t = pose[:3, :3], pose[:3, 3]
    x = texels.position @ R.T + t
    front = x[:, 2] > 1e-6
    px = np.full((n_tex, 2), -1.0)
    if front.any():
        px[front] = camera.project(scanner, torch.as_tensor(x[front])).numpy()
    inside = front & camera.in_image(scanner, px)
    rejected["behind_or_outside"] += int(n_tex - inside.sum())
    idx = np.nonzero(inside)[0]
    none = np.zeros((0, 4), bool)
    if len(idx) == 0:
        return idx, none
    in_box = scanner.in_valid_volume(torch.as_tensor(x[idx])).numpy()
    rejected["valid_volume"] += int((~in_box).sum())
    idx = idx[in_box]
    wo = -x[idx] / np.linalg.norm(x[idx], axis=1, keepdims=True)
    facing = (wo * (texels.normal[idx] @ R.T)).sum(1) > TUNING.traces.min_cos_grazing
    rejected["grazing"] += int((~facing).sum())
    idx = idx[facing]
    if len(idx) == 0:
        return idx, none
    origin = texels.position[idx] + eps * texels.normal[idx]
    to_cam = -R.T @ t - origin
    dist = np.linalg.norm(to_cam, axis=1)
    occ = caster.occluded(origin, to_cam / dist[:, None], dist - 1e-4)
    rejected["occluded"] += int(occ.sum())
    idx = idx[~occ]
    if len(idx) == 0:
        return idx, none
    taps = pixel_taps(scanner, caster, pose, px[idx], texels.position[idx], texels.normal[idx])
    some = taps.any(1)
    rejected["mixed_pixel"] += int((~some).sum())
    idx, taps = idx[some], taps[some]
    if emitter_shadow is None or len(idx) == 0:
        return idx, taps
    dark = emitter_shadow(pose, idx)[0] > MAX_SHADOWED_DRIVE
    rejected["emitter_shadow"] += int(dark.sum())
    return idx[~dark], taps[~dark]


def assemble(
    texels: Texels,
    photos: Iterable[np.ndarray],
    poses: list[np.ndarray],
    scanner: Scanner,
    caster: RayCaster,
    pixel_scale: float = 1.0,
    eps: float = 2e-5,
    progress: Progress = QUIET,
    support_z: float | None = None,
    folder: Path | None = None,
) -> tuple[RaggedTraces, TraceStats]:
    """Traces of all texels. ``photos``: 8-bit ``(H, W, 3)`` arrays (any iterable: they are read
    one at a time, once); ``poses``: 4x4 camera-from-world, one per photo. ``support_z``: the
    object stands on a plane z = support_z; in a photo where emitters carrying more than
    ``MAX_SHADOWED_DRIVE`` of the pattern's drive are below that plane the support blocks their
    light for every point of the object, which Eq. 1 as the network learnt it does not model: its
    entries are kept out of range with those emitters' groups in their shadow masks (the
    refinement models them), or, on a device whose groups do not fit a mask, the photo is skipped.

    Two passes: the first decides from geometry alone which texels each view measures (kept as
    int32 indices, 4 bytes per entry against the table's 48) and counts them per texel; the second
    reads each photo, projects its texels again (the same arithmetic, so the same pixel
    coordinates) and writes their entries: without ``folder``, straight into their final rows in
    memory (texel by texel, views in photo order; peak ~1.1x the table); with ``folder``, the table
    is written there as ``TABLE_FILES`` and returned memory-mapped (``load_table``), the same bit
    for bit: entries are streamed to disk in photo order, then regrouped by texel one block of
    ``TUNING.traces.table_block_entries`` at a time — the process holds the indices and one block, not the table."""
    n_tex = len(texels)
    rejected = {
        "behind_or_outside": 0,
        "valid_volume": 0,
        "occluded": 0,
        "grazing": 0,
        "grazing_flagged": 0,
        "mixed_pixel": 0,
        "mixed_pixel_resampled": 0,
        "pixel_range": 0,
        "support_shadow_views": 0,
        "support_shadowed": 0,  # entries of those views: kept, flagged, the support's groups masked
        "emitter_shadow": 0,
    }
    support_shadow = SupportShadow(scanner, support_z) if support_z is not None else None
    self_shadow = EmitterShadow(scanner, caster, texels, eps)
    # entries the mesh shadows are kept with their masks, found in the second pass; on a device
    # with more groups than a mask holds, this pass leaves them out
    drops = None if self_shadow.groups.fits else self_shadow
    # a view the support shadows: its entries kept with the groups below the support masked, out
    # of range for the network (the refinement reads them where a texel has nothing else); on a
    # device with more groups than a mask holds, left out whole
    support_masks = np.zeros(len(poses), np.int64)
    support_views = np.zeros(len(poses), bool)  # out of range even where no group's centre is below
    seen: list[np.ndarray | None] = []
    partial: list[tuple[np.ndarray, np.ndarray]] = []  # per view: which taps see another surface (``_pack_taps``)
    counts = np.zeros(n_tex, np.int64)
    for j, pose in enumerate(progress.track(poses, "visibility", total=len(poses), unit="photo")):
        if support_shadow is not None and support_shadow(pose):
            rejected["support_shadow_views"] += 1
            if drops is not None:  # no mask can hold the groups
                seen.append(None)
                partial.append(_pack_taps(np.zeros((0, 4), bool)))
                continue
            support_views[j], support_masks[j] = True, support_shadow.mask(pose, self_shadow.groups)
        idx, taps = _visible(texels, pose, scanner, caster, eps, rejected, drops)
        counts[idx] += 1
        seen.append(idx.astype(np.int32) if len(idx) else None)
        rejected["mixed_pixel_resampled"] += int((~taps.all(1)).sum())  # kept: read from the pixels that see it
        partial.append(_pack_taps(taps))
    # one array for all views before the table is allocated (not ~200 bytes of array per view)
    tap_start = np.zeros(len(partial) + 1, np.int64)
    tap_start[1:] = np.cumsum([len(r) for r, _ in partial])
    tap_rows, tap_bits = (np.concatenate([p[i] for p in partial]) for i in (0, 1))
    del partial
    offsets = np.zeros(n_tex + 1, np.int64)
    offsets[1:] = np.cumsum(counts)
    n_entries = int(offsets[-1])
    # photo order on disk: each view's entries are one contiguous, sequential write
    table = {k: _column(None if folder is None else folder / f".photo-order-{k}.npy", k, n_entries) for k in _COLUMNS}
    # and the table by texel that it is regrouped into, reserved now too: the disk holds both at
    # once, and one too small for that fails here, before any photo is read, not minutes later
    by_texel = {} if folder is None else {k: _column(folder / f"{k}.npy", k, n_entries) for k in _COLUMNS}
    entries, in_range, shadow = table["entries"], table["in_range"], table["shadow"]
    cursor = offsets[:-1].copy()  # in memory: each texel's next free row
    view_start = np.zeros(len(seen), np.int64)  # on disk: where each view's entries begin
    written = 0
    views_used = 0
    for k, (img, pose) in enumerate(progress.track(zip(photos, poses), "traces", total=len(poses), unit="photo")):
        visible = seen[k]
        if folder is None:
            seen[k] = None  # free this view's indices as its entries land
        if visible is None:
            continue
        idx = visible.astype(np.int64)
        R, t = pose[:3, :3], pose[:3, 3]
        x = texels.position[idx] @ R.T + t
        px = camera.project(scanner, torch.as_tensor(x)).numpy()
        view_taps = slice(tap_start[k], tap_start[k + 1])
        read = _unpack_taps(tap_rows[view_taps], tap_bits[view_taps], len(idx))
        codes = bilinear_pixels(img.astype(np.float64), px[:, 1], px[:, 0], read)
        ok = camera.code_is_valid(codes)
        rejected["pixel_range"] += int((~ok).sum())  # kept, flagged: only the refinement reads them
        views_used += 1
        if folder is None:
            rows: np.ndarray | slice = cursor[idx]
            cursor[idx] += 1
        else:
            view_start[k], rows = written, slice(written, written + len(idx))
            written += len(idx)
        entries[rows, 0:3] = camera.decode(scanner, torch.as_tensor(codes)).numpy() * pixel_scale
        entries[rows, 3:6] = x
        entries[rows, 6:9] = texels.normal[idx] @ R.T
        entries[rows, 9:12] = texels.tangent[idx] @ R.T
        steep = ~grazing(torch.from_numpy(entries[rows])).numpy()
        rejected["grazing_flagged"] += int((~steep).sum())  # kept, flagged: as the dark ones
        ok &= steep
        masks = self_shadow(pose, idx)[1] if drops is None else None
        if masks is None:
            in_range[rows], shadow[rows] = ok, 0
        else:  # entries the mesh shadows: out of range for the network, their masks for the refinement
            dark = shadowed(self_shadow.groups, torch.from_numpy(masks)).numpy()
            rejected["emitter_shadow"] += int(dark.sum())
            in_range[rows], shadow[rows] = ok & ~dark, masks
        if support_views[k]:  # the support's shadow on every entry of the view: none for the network
            in_range[rows] = False
            shadow[rows] = shadow[rows] | support_masks[k]
            rejected["support_shadowed"] += len(idx)
    stats = TraceStats(views_used, int(in_range.sum()), int((counts > 0).sum()), rejected)
    if folder is None:
        return RaggedTraces(*(torch.from_numpy(a) for a in (entries, offsets, in_range, shadow))), stats
    del entries, in_range, shadow
    _by_texel(folder, seen, view_start, table, by_texel, offsets, progress)
    del table, by_texel
    for name in _COLUMNS:
        (folder / f".photo-order-{name}.npy").unlink()
    return load_table(folder), stats


def _pack_taps(taps: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A view's ``pixel_taps (N, 4)`` as the first pass keeps them till the second: the entries
    with a tap to skip (on real scans the few at silhouettes and edges) as int32 positions, and one
    byte each (bit k: tap k)."""
    bits = (taps << np.arange(4)).sum(1).astype(np.uint8)
    some = np.nonzero(bits != 15)[0]
    return some.astype(np.int32), bits[some]


def _unpack_taps(rows: np.ndarray, bits: np.ndarray, n: int) -> np.ndarray | None:
    """``_pack_taps``' inverse for a view of ``n`` entries: ``(n, 4)`` bool, None where every tap is read."""
    if len(rows) == 0:
        return None
    taps = np.ones((n, 4), bool)
    taps[rows] = (bits[:, None] >> np.arange(4)) & 1 == 1
    return taps


def _column(path: Path | None, name: str, n_entries: int) -> np.ndarray:
    """An empty per-entry column ``name`` of the table (``_COLUMNS``): in memory, or memory-mapped at ``path``."""
    dtype, tail = _COLUMNS[name]
    if path is None:
        return np.empty((n_entries, *tail), dtype)
    column = np.lib.format.open_memmap(path, "w+", dtype, (n_entries, *tail))
    reserve_disk(path)
    return column


def _by_texel(
    folder: Path,
    seen: list[np.ndarray | None],
    view_start: np.ndarray,
    spill: dict[str, np.ndarray],
    out: dict[str, np.ndarray],
    offsets: np.ndarray,
    progress: Progress,
) -> None:
    """The photo-ordered columns ``spill`` (``_COLUMNS``) regrouped by texel into ``out``, the
    memory-mapped columns of ``folder``'s ``TABLE_FILES``, one block of texels (<=
    ``TUNING.traces.table_block_entries`` entries, at least one texel) at a time: each view's entries
    of a block are one contiguous run (its texel indices ascend)."""
    n_tex = len(offsets) - 1
    np.save(folder / "offsets.npy", offsets)
    bar = progress.counter("trace table", n_tex, "texel")
    for a, b in spans(offsets, TUNING.traces.table_block_entries):
        base = int(offsets[a])
        block = {k: _column(None, k, int(offsets[b]) - base) for k in _COLUMNS}
        cursor = offsets[a:b] - base  # each texel's next free row in the block
        for k, idx in enumerate(seen):
            if idx is None:
                continue
            lo, hi = np.searchsorted(idx, (a, b))
            if lo == hi:
                continue
            t = idx[lo:hi].astype(np.int64) - a
            rows = cursor[t]
            for name, column in block.items():
                column[rows] = spill[name][view_start[k] + lo : view_start[k] + hi]
            cursor[t] += 1
        for name, column in block.items():
            out[name][base : base + len(column)] = column
        bar.update(b - a)
    for column in out.values():
        column.flush()  # type: ignore[attr-defined]
    bar.close()


def load_table(folder: Path) -> RaggedTraces:
    """A trace table written by ``assemble(folder=...)`` (``TABLE_FILES``), memory-mapped read-only:
    a stage reads the blocks it works on from disk, never the whole table into memory, and never
    writes it (a write would fault). Not copy-on-write: a private writable mapping is counted
    against memory as a whole, and Linux refuses one larger than the machine's memory — the
    1,000-photo 1024² table (29 GB of entries) on 23 GB failed "Cannot allocate memory"."""
    with warnings.catch_warnings():  # torch warns that it cannot make a tensor read-only
        warnings.filterwarnings("ignore", "The given NumPy array is not writable", UserWarning)
        arrays = [torch.from_numpy(np.load(folder / f"{name}.npy", mmap_mode="r")) for name in TABLE_FILES]
    return RaggedTraces(*arrays)
