"""The trace table: N traces of different lengths as one ``(E, 12)`` entry table in CSR form.

Trace k is ``entries[offsets[k]:offsets[k+1]]``. An entry is (linear pixel RGB, position in camera
space in metres, geometric normal n^, geometric tangent t^), in the camera space of its view (paper
Eq. 4); the network normalises positions itself. Entries of one trace are in photo order. Optional
per-entry columns: ``in_range`` (the 8-bit code was in the valid range and the mesh hides too little
of the pattern for the network) and ``shadow`` (int64 masks: the emitter groups of
``physics.emitter_blocks.shadow_groups`` the mesh hides from the entry's point, bit g = group g) and
``albedo_blend`` (RGB: how much of the neighbours' albedo the entry's pixel sample may blend in,
``refine.footprint.albedo_blend``; set by the refinement).
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

ENTRY_SIZE = 12  # pixel RGB, x, n^, t^
# entries per step when counting over a whole table: a 1000-photo x 1024² table has 333 M, whose
# int64 running count alone would be 2.7 GB
COUNT_CHUNK = 1 << 24


def spans(offsets: np.ndarray, max_entries: int) -> Iterator[tuple[int, int]]:
    """Consecutive trace ranges ``[start, stop)`` covering every trace of the CSR ``offsets (N + 1,)``,
    each of at most ``max_entries`` entries — or one trace, where that trace alone is longer."""
    n = len(offsets) - 1
    start = 0
    while start < n:
        stop = int(np.searchsorted(offsets, offsets[start] + max_entries, side="right")) - 1
        stop = min(max(stop, start + 1), n)
        yield start, stop
        start = stop


def concatenated_rows(starts: Tensor, lengths: Tensor) -> tuple[Tensor, Tensor]:
    """The table rows of traces that start at ``starts (n,)`` and hold ``lengths (n,)`` entries,
    concatenated in that order ``(sum lengths,)``, and the CSR offsets ``(n + 1,)`` of the result."""
    offsets = torch.zeros(len(lengths) + 1, dtype=torch.int64)
    offsets[1:] = torch.cumsum(lengths, 0)
    first = torch.repeat_interleave(starts - offsets[:-1], lengths)
    return first + torch.arange(int(offsets[-1])), offsets


def spread_rows(rows: Tensor, usable: Tensor, max_views: int | None = None) -> tuple[Tensor, Tensor]:
    """``padded_rows``'s selection over the ``usable (n, W)`` entries of ``rows (n, W)`` alone: at
    most ``max_views`` of them per trace, spread evenly (first and last included), in trace order;
    the rows ``(n, V)`` and their mask."""
    order = torch.argsort((~usable).to(torch.int8), dim=1, stable=True)  # usable first, in trace order
    count = usable.sum(1)
    keep = count if max_views is None else count.clamp_max(max_views)
    pos = torch.arange(max(int(keep.max()) if len(rows) else 0, 1))[None, :]
    k = _spread(pos, count[:, None], keep[:, None]).clamp_max(rows.shape[1] - 1)
    return rows.gather(1, order.gather(1, k)), pos < keep[:, None]


def _spread(k: Tensor, length: Tensor, keep: Tensor) -> Tensor:
    """The ``k``-th of ``keep`` entries spread evenly over a trace of ``length``: round(k (L - 1) /
    (K - 1)), so the first and the last are kept (broadcasting; int64)."""
    step = (length - 1).clamp_min(0).double() / (keep - 1).clamp_min(1).double()
    return torch.round(k.double() * step).long()


@dataclass
class RaggedTraces:
    """N traces of any lengths as one ``(E, 12)`` entry table with CSR ``offsets (N + 1,)``."""

    entries: Tensor  # (E, 12) float32
    offsets: Tensor  # (N + 1,) int64, offsets[0] = 0, offsets[-1] = E
    in_range: Tensor | None = None  # (E,) bool: what the network may read (None: every entry)
    shadow: Tensor | None = None  # (E,) int64: emitter groups the mesh hides (None: none)
    albedo_blend: Tensor | None = None  # (E, 3): the neighbours' albedo the pixel may blend in (None: none)

    def __post_init__(self):
        if self.entries.ndim != 2 or self.entries.shape[1] != ENTRY_SIZE:
            raise ValueError(f"entries must be (E, 12), got {tuple(self.entries.shape)}")
        if self.offsets.ndim != 1 or int(self.offsets[0]) != 0 or int(self.offsets[-1]) != len(self.entries):
            raise ValueError("offsets must start at 0 and end at the number of entries")
        if (self.offsets[1:] < self.offsets[:-1]).any():
            raise ValueError("offsets must not decrease")
        if self.in_range is not None and self.in_range.shape != (len(self.entries),):
            raise ValueError("in_range must hold one flag per entry")
        if self.shadow is not None and self.shadow.shape != (len(self.entries),):
            raise ValueError("shadow must hold one mask per entry")
        if self.albedo_blend is not None and self.albedo_blend.shape != (len(self.entries), 3):
            raise ValueError("albedo_blend must hold one RGB value per entry")

    def in_range_only(self) -> RaggedTraces:
        """The traces with only their in-range entries (what the network and the lumitexel fit
        use; no ``shadow``: theirs hide too little to count); the refinement also reads the dark,
        clipped and shadowed ones."""
        if self.in_range is None:
            return self
        keep = self.in_range
        kept = torch.zeros(len(keep) + 1, dtype=torch.int64)
        kept[1:] = torch.cumsum(keep.long(), 0)
        return RaggedTraces(self.entries[keep], kept[self.offsets])

    def in_range_lengths(self) -> Tensor:
        """``in_range_only().lengths`` without copying the entries ``(N,)``: counted over blocks of
        traces of ~``COUNT_CHUNK`` entries (a memory-mapped table is read block by block)."""
        if self.in_range is None:
            return self.lengths
        out = torch.zeros(self.num_traces, dtype=torch.int64)
        for start, stop in spans(self.offsets.numpy(), COUNT_CHUNK):
            b = self.block(start, stop)
            assert b.in_range is not None
            kept = torch.zeros(len(b.in_range) + 1, dtype=torch.int64)
            kept[1:] = torch.cumsum(b.in_range, 0, dtype=torch.int64)
            out[start:stop] = kept[b.offsets[1:]] - kept[b.offsets[:-1]]
        return out

    def block(self, start: int, stop: int) -> RaggedTraces:
        """Traces ``start:stop`` as a table of their own (entries and columns are views, not copies)."""
        a, b = int(self.offsets[start]), int(self.offsets[stop])
        flags = None if self.in_range is None else self.in_range[a:b]
        shadow = None if self.shadow is None else self.shadow[a:b]
        albedo = None if self.albedo_blend is None else self.albedo_blend[a:b]
        return RaggedTraces(self.entries[a:b], self.offsets[start : stop + 1] - a, flags, shadow, albedo)

    @property
    def num_traces(self) -> int:
        """N."""
        return len(self.offsets) - 1

    @property
    def lengths(self) -> Tensor:
        """Entries per trace ``(N,)``."""
        return self.offsets[1:] - self.offsets[:-1]

    def padded(self, idx: Tensor, max_views: int | None = None) -> tuple[Tensor, Tensor]:
        """Traces ``idx (n,)`` as padded entries ``(n, V, 12)`` (zeros past each length, V the
        longest of them, at least 1) and their mask ``(n, V)``. ``max_views`` keeps at most that
        many entries per trace, spread evenly over it (first and last included)."""
        rows, mask = self.padded_rows(idx, max_views)
        return self.entries_at(rows, mask), mask

    def padded_rows(self, idx: Tensor, max_views: int | None = None) -> tuple[Tensor, Tensor]:
        """The table rows ``(n, V)`` of ``padded``'s entries (clamped into the table past each
        length) and their mask."""
        lengths = self.lengths[idx]
        keep = lengths if max_views is None else lengths.clamp_max(max_views)
        width = max(int(keep.max()) if len(idx) else 0, 1)
        pos = torch.arange(width)[None, :]
        mask = pos < keep[:, None]
        offset = pos.expand(len(idx), width) if max_views is None else _spread(pos, lengths[:, None], keep[:, None])
        return (self.offsets[idx][:, None] + offset).clamp(0, max(len(self.entries) - 1, 0)), mask

    def entries_at(self, rows: Tensor, mask: Tensor) -> Tensor:
        """The entries ``(n, V, 12)`` at ``rows (n, V)`` where ``mask``, zeros elsewhere."""
        if len(self.entries) == 0:
            return torch.zeros(*mask.shape, ENTRY_SIZE)
        return torch.where(mask[..., None], self.entries[rows], torch.zeros(()))

    def shadow_at(self, rows: Tensor, mask: Tensor) -> Tensor:
        """The ``shadow`` masks ``(n, V)`` at ``rows`` where ``mask``, 0 elsewhere (and everywhere
        without a ``shadow`` column)."""
        if self.shadow is None or len(self.entries) == 0:
            return torch.zeros(mask.shape, dtype=torch.int64)
        return torch.where(mask, self.shadow[rows], torch.zeros((), dtype=torch.int64))

    def albedo_blend_at(self, rows: Tensor, mask: Tensor) -> Tensor | None:
        """The ``albedo_blend`` ``(n, V, 3)`` at ``rows`` where ``mask``, 0 elsewhere; None without
        that column."""
        if self.albedo_blend is None:
            return None
        if len(self.entries) == 0:
            return torch.zeros(*mask.shape, 3, dtype=self.albedo_blend.dtype)
        return torch.where(mask[..., None], self.albedo_blend[rows], torch.zeros((), dtype=self.albedo_blend.dtype))

    def only(self, idx: Tensor) -> RaggedTraces:
        """The same N traces with only those of ``idx`` (sorted, distinct) keeping their entries, the
        others empty, every column carried: a stage run on a sample of the texels, trace i still
        texel i. Reads only those traces' rows (a memory-mapped table stays on disk)."""
        lengths = torch.zeros(self.num_traces, dtype=torch.int64)
        lengths[idx] = self.lengths[idx]
        rows, _ = concatenated_rows(self.offsets[idx], lengths[idx])
        return self.taking(rows, lengths)

    def taking(self, rows: Tensor, lengths: Tensor) -> RaggedTraces:
        """The same N traces holding only the entries at the table ``rows`` (grouped trace by trace,
        in trace order), ``lengths (N,)`` of them each; every column carried."""
        offsets = torch.zeros_like(self.offsets)
        offsets[1:] = torch.cumsum(lengths, 0)

        def column(c: Tensor | None) -> Tensor | None:
            return None if c is None else c[rows]

        return RaggedTraces(
            self.entries[rows], offsets, column(self.in_range), column(self.shadow), column(self.albedo_blend)
        )

    def spread(self, max_views: int) -> RaggedTraces:
        """The table with at most ``max_views`` entries per trace, the same ones ``padded`` keeps
        (evenly spread, first and last included); ``in_range``, ``shadow`` and ``albedo_blend`` are not
        carried (read them first)."""
        lengths = self.lengths
        keep = lengths.clamp_max(max_views)
        offsets = torch.zeros_like(self.offsets)
        offsets[1:] = torch.cumsum(keep, 0)
        trace = torch.repeat_interleave(torch.arange(len(keep)), keep)
        k = torch.arange(int(offsets[-1])) - offsets[trace]
        return RaggedTraces(self.entries[self.offsets[trace] + _spread(k, lengths[trace], keep[trace])], offsets)

    @classmethod
    def from_padded(cls, entries: Tensor, mask: Tensor) -> RaggedTraces:
        """From ``(N, V, 12)`` entries and a ``(N, V)`` mask (any pattern of valid views)."""
        lengths = mask.sum(1)
        offsets = torch.zeros(len(lengths) + 1, dtype=torch.int64)
        offsets[1:] = torch.cumsum(lengths, 0)
        return cls(entries[mask].to(torch.float32), offsets)
