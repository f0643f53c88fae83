"""Emitter blocks: the scanner's emitter samples grouped into spatially compact blocks, each also
seen as one coarse emitter, so a lobe can be summed exactly where it is sharp and coarsely elsewhere.

Convention: the samples are ``Scanner.emitter_samples`` flattened (K = L * Q, sample k = l * Q + q).
Blocks come from sorting the samples along the two principal axes of their positions (columns of
equal count, then rows within each column), so on the paper's 32 x 16 LED grid they are 4 x 4 LED
squares. A block's coarse emitter sits at the drive-weighted centroid of its samples with their mean
normal, and carries their summed, quadrature-weighted drive: for a lobe that changes little across
the block (a broad one, or one far from the block) Eq. 1 over the block equals the coarse emitter's
term. ``members (C, S)`` pads short blocks with the index K, a sample that emits nothing.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from functools import cached_property

import numpy as np
import torch
from torch import Tensor

from ..scanner.scanner import Scanner

BLOCK_SIZE = 16  # samples per block (4 x 4 LEDs on a grid)
EXACT_UP_TO = 128  # devices with at most this many samples are always summed exactly
SHADOW_BITS = 64  # shadow groups one entry's mask can hold (an int64's bits)
SHADOW_SPLITS = 2  # shadow groups per emitter block: a block's halves are hidden or not as their centres


@dataclass(frozen=True)
class EmitterBlocks:
    """Blocks of a scanner's K emitter samples (see the module docstring)."""

    members: Tensor  # (C, S) int64 sample indices, K = padding
    coarse: Scanner  # one point emitter per block (centroid, mean normal; Psi as the device's)
    coarse_drive: Tensor  # (C, 3) summed quadrature-weighted effective drive per camera channel

    @property
    def count(self) -> int:
        """C, the number of blocks."""
        return int(self.members.shape[0])


def emitter_blocks(scanner: Scanner, size: int = BLOCK_SIZE) -> EmitterBlocks | None:
    """The blocks of ``scanner``'s samples, or None when it has few enough to sum exactly."""
    pts_t, w_t = scanner.emitter_samples(torch.float64)
    L, Q = w_t.shape
    K = L * Q
    if K <= EXACT_UP_TO:
        return None
    pts = pts_t.reshape(K, 3).numpy()
    w = w_t.reshape(K).numpy()
    drive = np.repeat(scanner.effective_pattern(), Q, axis=0) * w[:, None]  # (K, 3)
    normals = np.repeat(scanner.emitter_normals, Q, axis=0)
    centred = pts - pts.mean(0)
    _, sv, axes = np.linalg.svd(centred, full_matrices=False)
    u, v = centred @ axes[0], centred @ axes[1]
    count = math.ceil(K / size)
    ratio = sv[0] / max(sv[1], 1e-12 * sv[0])
    cols = min(count, max(1, round(math.sqrt(count * ratio))))
    groups = []
    for col in np.array_split(np.argsort(u, kind="stable"), cols):
        rows = max(1, round(len(col) / size))
        groups += np.array_split(col[np.argsort(v[col], kind="stable")], rows)
    S = max(len(g) for g in groups)
    members = np.full((len(groups), S), K, np.int64)
    for i, g in enumerate(groups):
        members[i, : len(g)] = g
    weight = drive.sum(1)
    centroid, normal = np.zeros((len(groups), 3)), np.zeros((len(groups), 3))
    for i, g in enumerate(groups):
        wg = weight[g] if weight[g].sum() > 0 else np.ones(len(g))
        centroid[i] = (pts[g] * wg[:, None]).sum(0) / wg.sum()
        nm = normals[g].sum(0)
        normal[i] = nm / max(np.linalg.norm(nm), 1e-12)
    coarse = dataclasses.replace(
        scanner,
        emitter_kind="point",
        emitter_positions=centroid,
        emitter_normals=normal,
        emitter_axes=np.repeat(scanner.emitter_axes[:1], len(groups), 0),
        pattern=np.zeros((len(groups), 3)),
        grid_shape=None,
    )
    block_drive = np.stack([drive[g].sum(0) for g in groups])
    return EmitterBlocks(torch.from_numpy(members), coarse, torch.from_numpy(block_drive))


@dataclass(frozen=True)
class ShadowGroups:
    """What a test of the mesh shadowing its own emitters traces: P groups of emitter samples — each
    block's halves (``SHADOW_SPLITS``; whole blocks where the halves would not fit a mask), or each
    sample on a device summed exactly — as points (camera space, the drive-weighted centroid), their
    share of the pattern's drive (summing to 1), each sample's group and each group's block. An
    entry's shadow is an int64 mask, bit g set where the mesh hides group g from its point: ``fits``
    says whether P bits are enough."""

    points: np.ndarray  # (P, 3)
    drive: np.ndarray  # (P,)
    group: Tensor  # (K,) int64: the group of each emitter sample
    block: Tensor | None  # (P,) int64: the emitter block of each group (None: no blocks)

    @property
    def fits(self) -> bool:
        """True when one int64 mask can say which of the P groups are hidden."""
        return len(self.points) <= SHADOW_BITS

    def hidden(self, shadow: Tensor) -> Tensor:
        """Per group ``(..., P)`` bool: hidden by ``shadow (...)`` int64 masks."""
        bit = torch.arange(len(self.points), dtype=torch.int64)
        return (shadow[..., None] >> bit) & 1 == 1

    def share(self, shadow: Tensor) -> Tensor:
        """The share ``(...)`` of the pattern's drive (float64) that ``shadow (...)`` masks hide: a
        mask's eight bytes looked up in ``byte_shares`` and summed (8 gathers, not 64 bit tests)."""
        table = torch.from_numpy(self.byte_shares)
        total = torch.zeros(shadow.shape, dtype=torch.float64)
        for b in range(8):  # >> on int64 sign-extends; & 255 keeps the byte either way
            total += table[b][(shadow >> (8 * b)) & 255]
        return total

    @cached_property
    def byte_shares(self) -> np.ndarray:
        """``(8, 256)`` float64: entry [b, v] the drive share of the groups whose bits are set in
        byte value ``v`` at byte ``b`` of a mask (groups past P carry none)."""
        drive = np.zeros(8 * 8)
        drive[: min(len(self.drive), 64)] = self.drive[:64]
        bits = (np.arange(256)[:, None] >> np.arange(8)) & 1  # (256, 8)
        return np.stack([bits @ drive[8 * b : 8 * b + 8] for b in range(8)])

    def block_visibility(self, shadow: Tensor, dtype: torch.dtype) -> Tensor:
        """Per emitter block ``(..., C)``: the share of its drive ``shadow (...)`` leaves visible."""
        assert self.block is not None
        C = int(self.block.max()) + 1
        drive = torch.from_numpy(self.drive).to(dtype)
        hidden = torch.zeros(*shadow.shape, C, dtype=dtype)
        hidden.index_add_(-1, self.block, self.hidden(shadow).to(dtype) * drive)
        total = torch.zeros(C, dtype=dtype).index_add_(0, self.block, drive)
        return 1 - hidden / total.clamp_min(1e-30)


def sample_drive(scanner: Scanner) -> tuple[np.ndarray, np.ndarray]:
    """The emitter samples ``(K, 3)`` (camera space) and their share of the pattern's drive ``(K,)``
    (quadrature weight x drive summed over the channels; summing to 1): what a shadow test weighs."""
    pts, w = scanner.emitter_samples(torch.float64)
    drive = (w.numpy() * scanner.effective_pattern().sum(1)[:, None]).reshape(-1)
    return pts.numpy().reshape(-1, 3), drive / max(drive.sum(), 1e-300)


def shadow_groups(scanner: Scanner) -> ShadowGroups:
    """The groups a shadow test traces for ``scanner`` (``ShadowGroups``): a block's samples are
    ordered along its rows (``emitter_blocks``), so its halves are 4 x 2 LED halves of a 4 x 4 square."""
    pts, drive = sample_drive(scanner)
    blocks = emitter_blocks(scanner)
    K = len(pts)
    if blocks is None:
        return ShadowGroups(pts, drive, torch.arange(K), None)
    parts = SHADOW_SPLITS if blocks.count * SHADOW_SPLITS <= SHADOW_BITS else 1
    group, block = np.zeros(K, np.int64), list[int]()
    for c, members in enumerate(blocks.members.numpy()):
        for part in np.array_split(members[members < K], parts):  # index K pads the members
            group[part] = len(block)
            block.append(c)
    P = len(block)
    share = np.bincount(group, weights=drive, minlength=P)
    w = np.where(share[group] > 0, drive, 1.0)  # a group that emits nothing: its plain centroid
    sums = np.stack([np.bincount(group, weights=w * pts[:, i], minlength=P) for i in range(3)], 1)
    points = sums / np.bincount(group, weights=w, minlength=P)[:, None]
    return ShadowGroups(points, share, torch.from_numpy(group), torch.tensor(block))
