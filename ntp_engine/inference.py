"""Network inference on ragged traces, in memory-bounded batches.

A ``RaggedTraces`` holds N traces of different lengths as one ``(E, 12)`` entry table in CSR
form: trace k is ``entries[offsets[k]:offsets[k+1]]``. An entry is (linear pixel RGB, position
in camera space in metres, geometric normal n^, geometric tangent t^), camera space of its view —
the network normalises positions itself. Traces are batched by similar length (less padding),
at most ``max_entries`` padded entries per batch, and results come back with their trace indices.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Iterator

import torch
from torch import Tensor

from .network import TraceNet


@dataclass
class RaggedTraces:
    entries: Tensor  # (E, 12) float32
    offsets: Tensor  # (N + 1,) int64, offsets[0] = 0, offsets[-1] = E

    def __post_init__(self):
        if self.entries.ndim != 2 or self.entries.shape[1] != 12:
            raise ValueError(f"entries must be (E, 12), got {tuple(self.entries.shape)}")
        if self.offsets.ndim != 1 or int(self.offsets[0]) != 0 or int(self.offsets[-1]) != len(self.entries):
            raise ValueError("offsets must start at 0 and end at the number of entries")
        if (self.offsets[1:] < self.offsets[:-1]).any():
            raise ValueError("offsets must not decrease")

    @property
    def num_traces(self) -> int:
        return len(self.offsets) - 1

    @property
    def lengths(self) -> Tensor:
        return self.offsets[1:] - self.offsets[:-1]

    def padded(self, idx: Tensor, max_views: int | None = None) -> tuple[Tensor, Tensor]:
        """Traces ``idx (n,)`` as padded entries ``(n, V, 12)`` (zeros past each length, V the
        longest of them, at least 1) and their mask ``(n, V)``. ``max_views`` keeps at most that
        many entries per trace, spread evenly over it (first and last included)."""
        lengths = self.lengths[idx]
        keep = lengths if max_views is None else lengths.clamp_max(max_views)
        width = max(int(keep.max()) if len(idx) else 0, 1)
        pos = torch.arange(width)[None, :]
        mask = pos < keep[:, None]
        if len(self.entries) == 0:
            return torch.zeros(len(idx), width, 12), mask
        if max_views is None:
            offset = pos.expand(len(idx), width)
        else:  # evenly spread: k * (L - 1) / (K - 1) for k < K
            step = (lengths - 1).clamp_min(0).double() / (keep - 1).clamp_min(1).double()
            offset = torch.round(pos.double() * step[:, None]).long()
        gather = (self.offsets[idx][:, None] + offset).clamp_max(len(self.entries) - 1)
        return torch.where(mask[..., None], self.entries[gather], torch.zeros(())), mask

    @classmethod
    def from_padded(cls, entries: Tensor, mask: Tensor) -> "RaggedTraces":
        """From ``(N, V, 12)`` entries and a ``(N, V)`` mask (any pattern of valid views)."""
        lengths = mask.sum(1)
        offsets = torch.zeros(len(lengths) + 1, dtype=torch.int64)
        offsets[1:] = torch.cumsum(lengths, 0)
        return cls(entries[mask].to(torch.float32), offsets)


def _batches(lengths: Tensor, max_entries: int) -> Iterator[Tensor]:
    order = torch.argsort(lengths, descending=True, stable=True)
    sorted_len = lengths[order].clamp_min(1)
    start, n = 0, len(order)
    while start < n:
        width = int(sorted_len[start])  # the longest in this batch (sorted descending)
        count = max(1, min(n - start, max_entries // width))
        yield order[start:start + count]
        start += count


@torch.inference_mode()
def predict(model: TraceNet, traces: RaggedTraces, max_entries: int = 1 << 16,
            device: torch.device | str | None = None) -> Iterator[tuple[Tensor, Tensor, Tensor]]:
    """Yield ``(trace indices (n,), diffuse (n, 384), specular (n, 6144))`` batch by batch.

    Lumitexels are non-negative (the specular head predicts log(1 + x)); a trace with no entry
    gives the network's answer for an empty trace. Memory is bounded by ``max_entries`` padded
    entries per batch plus ``n * 6528`` outputs."""
    model.eval()
    dev = torch.device(device) if device else next(model.parameters()).device
    for idx in _batches(traces.lengths, max_entries):
        raw, mask = traces.padded(idx)
        raw = raw.to(dev)
        x = model.entries(raw[..., 0:3], raw[..., 3:6], raw[..., 6:9], raw[..., 9:12])
        d, s = model(x, mask.to(dev))
        yield idx, d.clamp_min(0).float().cpu(), torch.expm1(s.clamp_min(0)).float().cpu()


def predict_all(model: TraceNet, traces: RaggedTraces, max_entries: int = 1 << 16) -> tuple[Tensor, Tensor]:
    """All lumitexels at once, ``(N, 384)`` and ``(N, 6144)``, in trace order (small N only)."""
    diffuse = torch.zeros(traces.num_traces, model.cfg.diffuse_size)
    specular = torch.zeros(traces.num_traces, model.cfg.specular_size)
    for idx, d, s in predict(model, traces, max_entries):
        diffuse[idx], specular[idx] = d, s
    return diffuse, specular
