"""The process's memory allocator (glibc's malloc, which numpy and torch use on Linux): within
``freed_memory_kept``, large blocks come from its heap and freed memory stays there for the next.

Why: the refinement allocates per batch of texels (``TUNING.inputs.refine_batch``) arrays of 40-160
MB (each entry's directions to every emitter sample) and frees them a moment later. glibc serves a
block that large with its own ``mmap`` and unmaps it on free, so every batch faults in fresh pages
the kernel must zero — ~40% of the compiled directions loop's time (docs/performance.md, "Freed
memory kept"). With mapping off (``M_MMAP_MAX`` 0) and a 1 GB trim threshold, freed blocks stay
mapped and the next batch reuses them. Only around the refinement: kept for the whole run, the
traces and fit stages' own memory grew 12-33% for no time. Memory mapped files are not malloc's and
are unaffected. Elsewhere than glibc (musl, macOS, Windows) it does nothing.
"""

from __future__ import annotations

import contextlib
import ctypes
import ctypes.util
import functools
from collections.abc import Callable, Iterator

M_TRIM_THRESHOLD, M_MMAP_MAX = -1, -4  # glibc's mallopt parameters (malloc.h)
TRIM_THRESHOLD = 1 << 30  # within the block: free memory at the heap's top beyond this goes back
# glibc's default values, set again after the block; any mallopt leaves glibc's dynamic mmap threshold
# where it stands from then on (it rises only up to 32 MB, below the refinement's blocks anyway)
DEFAULT_TRIM_THRESHOLD, DEFAULT_MMAP_MAX = 128 * 1024, 65536


@functools.cache
def _mallopt() -> Callable[[int, int], int] | None:
    try:
        mallopt = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6").mallopt
    except (OSError, AttributeError):  # not glibc
        return None
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    return mallopt


@contextlib.contextmanager
def freed_memory_kept() -> Iterator[bool]:
    """Within the block, large blocks from the heap and freed memory kept (module docstring); yields
    whether glibc took the settings. After it, glibc's default mapping count and trim threshold again
    (its mmap threshold no longer adapts: fixed where the run had taken it)."""
    mallopt = _mallopt()
    kept = mallopt is not None and bool(mallopt(M_MMAP_MAX, 0)) and bool(mallopt(M_TRIM_THRESHOLD, TRIM_THRESHOLD))
    try:
        yield kept
    finally:
        if mallopt is not None:
            mallopt(M_MMAP_MAX, DEFAULT_MMAP_MAX)
            mallopt(M_TRIM_THRESHOLD, DEFAULT_TRIM_THRESHOLD)
