"""How many CPU threads a run uses (``ntp reconstruct|register --threads N``, the add-on's
preference): one home for the setting, read by torch, by COLMAP's feature extraction, matching
and mapping, and by the pools that decode photos. 0 means every core (torch's and COLMAP's own
default)."""

from __future__ import annotations

import os

import numba
import torch

from .errors import NtpInputError

_threads = 0
_TORCH_DEFAULT = torch.get_num_threads()  # torch's own choice (every physical core), for 0

MAX_THREADS = 8192  # Linux's largest CPU count (CONFIG_NR_CPUS on x86-64)


def set_threads(n: int) -> None:
    """Use ``n`` CPU threads from now on (0: every core). ``NtpInputError`` for a negative ``n``."""
    global _threads
    if not 0 <= n <= MAX_THREADS:
        raise NtpInputError(None, f"--threads {n}: need 0 (every core) to {MAX_THREADS}")
    _threads = n
    # numba's OpenMP threading layer, started by its first parallel loop, sets the starting thread's
    # OpenMP count to numba's pool size — torch's count too (one libgomp in the process): started
    # after this, it undid ``--threads 1`` (two such runs side by side took 3x as long as one each)
    numba.get_num_threads()  # starts the layer now, before torch's count is set
    torch.set_num_threads(n or _TORCH_DEFAULT)


def configured_threads() -> int:
    """The setting (0: every core), e.g. the CPUs of a local Ray instance (``task_pool.RayPool``)."""
    return _threads


def worker_threads() -> int:
    """How many threads to decode or score photos on: the setting, every core for 0."""
    return _threads or max(len(os.sched_getaffinity(0)), 1)


def colmap_threads() -> int:
    """COLMAP's ``num_threads`` option for the setting (-1: every core)."""
    return _threads or -1
