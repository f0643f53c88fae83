"""Network inference on ragged traces (``ragged.RaggedTraces``), in memory-bounded batches.

Traces are batched by similar length (less padding), at most ``max_entries`` padded entries per
batch, and results come back with their trace indices. ``max_views`` caps the entries the network
reads per trace, spread evenly over it (``RaggedTraces.padded``).
"""

from __future__ import annotations

from collections.abc import Iterator

import torch
from torch import Tensor

from .network import TraceNet
from .ragged import RaggedTraces


def _batches(lengths: Tensor, max_entries: int) -> Iterator[Tensor]:
    order = torch.argsort(lengths, descending=True, stable=True)
    sorted_len = lengths[order].clamp_min(1)
    start, n = 0, len(order)
    while start < n:
        width = int(sorted_len[start])  # the longest in this batch (sorted descending)
        count = max(1, min(n - start, max_entries // width))
        yield order[start : start + count]
        start += count


@torch.inference_mode()
def predict(
    model: TraceNet,
    traces: RaggedTraces,
    max_entries: int = 1 << 16,
    device: torch.device | str | None = None,
    max_views: int | None = None,
) -> Iterator[tuple[Tensor, Tensor, Tensor]]:
    """Yield ``(trace indices (n,), diffuse (n, 384), specular (n, 6144))`` batch by batch; the
    network reads at most ``max_views`` entries per trace (evenly spread, first and last kept).

    Lumitexels are non-negative (the specular head predicts log(1 + x)); a trace with no entry
    gives the network's answer for an empty trace. Memory is bounded by ``max_entries`` padded
    entries per batch plus ``n * 6528`` outputs."""
    model.eval()
    dev = torch.device(device) if device else next(model.parameters()).device
    lengths = traces.lengths if max_views is None else traces.lengths.clamp_max(max_views)
    for idx in _batches(lengths, max_entries):
        raw, mask = traces.padded(idx, max_views=max_views)
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
