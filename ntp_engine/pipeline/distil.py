"""The scan's own network (``distilled_network``): the trace network fine-tuned on a sample of the
scan's texels whose reflectance the refinement measured against their photos (the teacher), so
that run over every texel it answers this scan's traces — their geometry, exposure, noise and
materials — rather than the synthetic ones it was trained on. Design and measurements:
docs/distillation.md.

Convention: traces as ``pipeline.fit_traces`` reads them (linear pixels as captured, multiplied by
``pixel_scale`` to the network's exposure; the in-range entries, at most ``TUNING.fit.network_views``
spread evenly); the teacher's parameters per trace in the texel's geometric frame
(``fit.texel_fit``); the labels are the grayscale lumitexels of those parameters in that frame
(``physics.lumitexel``) and the loss the training's Eq. 5 with every trace's specular part counted
(the teacher's lobe, or its absence, is a measurement).
"""

from __future__ import annotations

import copy
import time
from dataclasses import asdict, dataclass

import numpy as np
import torch
from torch import Tensor

from ..fit.texel_fit import TexelFit
from ..io.progress import QUIET, Progress
from ..learn.network import TraceNet, lumitexel_loss
from ..learn.ragged import RaggedTraces, concatenated_rows
from ..physics.lumitexel import render_lumitexels
from .settings import TUNING, DistilTuning


@dataclass
class DistilReport:
    """What one fine-tuning did (``report.json``'s ``distil``)."""

    seeds: int  # texels the teacher refined
    trained_on: int  # ... of which the fine-tuning read
    held_out: int  # ... and held out to decide when it stops
    steps: int  # steps taken (the best weights are those after ``best_step``)
    best_step: int
    loss_before: float  # held-out Eq. 5 loss of the shipped network
    loss_after: float  # ... and of the fine-tuned one
    seconds: float

    def to_json(self) -> dict:
        """The fields, floats rounded to 4 decimals."""
        return {k: round(v, 4) if isinstance(v, float) else v for k, v in asdict(self).items()}


def seed_texels(usable: np.ndarray, count: int, seed: int = 0) -> np.ndarray:
    """Up to ``count`` of the texels where ``usable (N,)`` holds, drawn without replacement
    (seeded: the same scan gives the same seeds), sorted ``(n,)``."""
    pool = np.flatnonzero(usable)
    if len(pool) <= count:
        return pool
    return np.sort(np.random.default_rng(seed).choice(pool, count, replace=False))


def teacher_lumitexels(fit: TexelFit, idx: np.ndarray) -> tuple[Tensor, Tensor]:
    """The grayscale diffuse ``(n, 384)`` and specular ``(n, 6144)`` lumitexels of ``fit``'s
    parameters at the traces ``idx`` (float32; the albedos' channel means, as the training's labels)."""

    def col(a: np.ndarray) -> Tensor:
        return torch.as_tensor(np.asarray(a[idx], np.float32))

    alpha = col(fit.alpha)
    d, s = render_lumitexels(
        col(fit.n_loc),
        col(fit.t_loc),
        col(fit.rho_d).mean(1, keepdim=True),
        col(fit.rho_s).mean(1, keepdim=True),
        alpha[:, 0],
        alpha[:, 1],
    )
    return d[..., 0], s[..., 0]


class _SeedTraces:
    """The seeds' network inputs, gathered once: entries ``(E, 12)`` (as ``TraceNet.entries`` makes
    them) and each seed's rows."""

    def __init__(self, net: TraceNet, traces: RaggedTraces, seeds: np.ndarray, pixel_scale: float):
        at = torch.as_tensor(seeds)
        table = traces.only(at).in_range_only().spread(TUNING.fit.network_views)
        raw = table.entries.float().clone()
        raw[:, :3] *= pixel_scale
        with torch.no_grad():
            self.entries = net.entries(raw[:, 0:3], raw[:, 3:6], raw[:, 6:9], raw[:, 9:12])
        self.starts, self.lengths = table.offsets[at], table.lengths[at]

    def batch(self, k: np.ndarray) -> tuple[Tensor, Tensor]:
        """Entries and CSR offsets of the seeds at positions ``k``."""
        rows, offsets = concatenated_rows(self.starts[k], self.lengths[k])
        return self.entries[rows], offsets


def distilled_network(
    net: TraceNet,
    traces: RaggedTraces,
    pixel_scale: float,
    teacher: TexelFit,
    seeds: np.ndarray,
    tuning: DistilTuning | None = None,
    progress: Progress = QUIET,
    seed: int = 0,
) -> tuple[TraceNet, DistilReport]:
    """A copy of ``net`` fine-tuned (Adam, ``tuning``, default ``TUNING.distil``) toward
    ``teacher``'s answers on the traces ``seeds`` (those with in-range entries;
    ``tuning.held_out`` of them kept out), stopped when the held-out loss has not fallen for
    ``tuning.patience`` evaluations, with the weights of its lowest; in eval mode. ``net`` is left
    as it was. Deterministic for a given ``seed`` (dropout included: the global generator is
    forked and seeded for the run)."""
    with torch.random.fork_rng():
        torch.manual_seed(seed)
        return _distilled(net, traces, pixel_scale, teacher, seeds, tuning or TUNING.distil, progress, seed)


def _distilled(
    net: TraceNet,
    traces: RaggedTraces,
    pixel_scale: float,
    teacher: TexelFit,
    seeds: np.ndarray,
    tuning: DistilTuning,
    progress: Progress,
    seed: int,
) -> tuple[TraceNet, DistilReport]:
    t0 = time.perf_counter()
    gen = torch.Generator().manual_seed(seed)
    model = copy.deepcopy(net).float()
    data = _SeedTraces(model, traces, seeds, pixel_scale)
    usable = np.flatnonzero(data.lengths.numpy() > 0)
    order = usable[torch.randperm(len(usable), generator=gen).numpy()]
    n_out = max(1, int(round(tuning.held_out * len(order)))) if len(order) > 1 else 0
    held, train = order[:n_out], order[n_out:]
    labels = teacher_lumitexels(teacher, seeds)

    def loss(k: np.ndarray) -> Tensor:
        x, offsets = data.batch(k)
        d, s = model.forward_ragged(x, offsets)
        return lumitexel_loss(d, s, labels[0][k], labels[1][k], torch.ones(len(k)))[0]

    @torch.no_grad()
    def held_loss() -> float:
        model.eval()
        parts = [float(loss(held[a : a + 256])) * len(held[a : a + 256]) for a in range(0, len(held), 256)]
        return sum(parts) / max(len(held), 1)

    before = held_loss() if len(held) else float("nan")
    best, best_state, best_step, step, stale = before, copy.deepcopy(model.state_dict()), 0, 0, 0
    if len(train) and len(held):
        # fused: one pass per tensor; the per-op form spent 26 of its 38 ms a step in sqrt, whose
        # vectorised kernel slows ~10x on the zeros and denormals of rarely reached outputs' moments
        opt = torch.optim.Adam(model.parameters(), lr=tuning.learning_rate, fused=True)
        bar = progress.counter("distil", tuning.max_steps, "step")
        while step < tuning.max_steps and stale < tuning.patience:
            model.train()
            pick = torch.randint(len(train), (min(tuning.batch, len(train)),), generator=gen).numpy()
            value = loss(train[pick])
            opt.zero_grad()
            value.backward()
            opt.step()
            step += 1
            bar.update()
            if step % tuning.check_every == 0:
                v = held_loss()
                if v < best:
                    best, best_state, best_step, stale = v, copy.deepcopy(model.state_dict()), step, 0
                else:
                    stale += 1
        bar.close()
    model.load_state_dict(best_state)
    model.eval()
    report = DistilReport(
        seeds=len(seeds),
        trained_on=len(train),
        held_out=len(held),
        steps=step,
        best_step=best_step,
        loss_before=before,
        loss_after=best,
        seconds=time.perf_counter() - t0,
    )
    return model, report
