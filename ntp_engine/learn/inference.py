"""Network inference on ragged traces (``ragged.RaggedTraces``), in memory-bounded batches.

Traces go through the network in CSR form (no padding: the encoder runs on each entry once, the
pooling is a per-trace max), in consecutive batches of at most ``max_entries`` entries, and results
come back with their trace indices. ``max_views`` caps the entries the network reads per trace,
spread evenly over it (``RaggedTraces.spread``).
"""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np
import torch
from torch import Tensor

from .network import TraceNet
from .ragged import RaggedTraces, spans


def _batches(offsets: np.ndarray, max_entries: int, max_traces: int) -> Iterator[tuple[int, int]]:
    """Consecutive trace ranges of at most ``max_entries`` entries and ``max_traces`` traces."""
    for first, last in spans(offsets, max_entries):
        for start in range(first, last, max_traces):
            yield start, min(start + max_traces, last)


@torch.inference_mode()
def predict(
    model: TraceNet,
    traces: RaggedTraces,
    max_entries: int = 1 << 16,
    device: torch.device | str | None = None,
    max_views: int | None = None,
    max_traces: int = 4096,
) -> Iterator[tuple[Tensor, Tensor, Tensor]]:
    """Yield ``(trace indices (n,), diffuse (n, 384), specular (n, 6144))`` batch by batch, in
    trace order; the network reads at most ``max_views`` entries per trace (evenly spread, first and
    last kept).

    Lumitexels are non-negative (the specular head predicts log(1 + x)); a trace with no entry
    gives the network's answer for an empty trace. Memory is bounded by ``max_entries`` entries and
    ``max_traces`` traces (``max_traces * 6528`` outputs) per batch."""
    model.eval()
    dev = torch.device(device) if device else next(model.parameters()).device
    table = traces if max_views is None else traces.spread(max_views)
    for start, stop in _batches(table.offsets.numpy(), max_entries, max_traces):
        b = table.block(start, stop)
        raw = b.entries.to(dev)
        x = model.entries(raw[:, 0:3], raw[:, 3:6], raw[:, 6:9], raw[:, 9:12])
        d, s = model.forward_ragged(x, b.offsets.to(dev))
        yield torch.arange(start, stop), d.clamp_min(0).float().cpu(), torch.expm1(s.clamp_min(0)).float().cpu()


def predict_all(model: TraceNet, traces: RaggedTraces, max_entries: int = 1 << 16) -> tuple[Tensor, Tensor]:
    """All lumitexels at once, ``(N, 384)`` and ``(N, 6144)``, in trace order (small N only)."""
    diffuse = torch.zeros(traces.num_traces, model.cfg.diffuse_size)
    specular = torch.zeros(traces.num_traces, model.cfg.specular_size)
    for idx, d, s in predict(model, traces, max_entries):
        diffuse[idx], specular[idx] = d, s
    return diffuse, specular
