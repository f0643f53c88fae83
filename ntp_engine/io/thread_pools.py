"""The thread pools beside torch's: numba's parallel loops run on as many threads as torch uses
(so ``--threads N`` and the add-on's preference hold for them too; ``io.threads`` sets
torch's), and numpy's and scipy's OpenBLAS run single-threaded inside ``single_threaded_blas`` —
their threads and torch's spin-wait against each other on few cores (measured on 2 cores, torch at
2 threads: a batch of three 68 x 68 float64 solves took 9.0 ms, 0.38 ms with OpenBLAS at 1 thread)."""

from __future__ import annotations

import contextlib
import functools
from collections.abc import Iterator

import numba
import torch
from threadpoolctl import ThreadpoolController


@contextlib.contextmanager
def numba_threads_as_torch() -> Iterator[None]:
    """Within the block, numba's parallel loops run on ``torch.get_num_threads()`` threads (at most
    numba's pool); the previous count is restored after it."""
    before = numba.get_num_threads()
    numba.set_num_threads(min(torch.get_num_threads(), numba.config.NUMBA_NUM_THREADS))
    try:
        yield
    finally:
        numba.set_num_threads(before)


@functools.cache
def _controller() -> ThreadpoolController:
    return ThreadpoolController()  # scans the loaded libraries once (~ms); limiting is ~30 us


@contextlib.contextmanager
def single_threaded_blas() -> Iterator[None]:
    """Within the block, OpenBLAS (numpy's, scipy's) uses one thread; torch's pools are untouched."""
    with _controller().select(internal_api="openblas").limit(limits=1):
        yield
