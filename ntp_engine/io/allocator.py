"""The process's memory allocator (glibc's malloc, which numpy and torch use on Linux): large blocks
from its heap, freed memory kept for the next, instead of a fresh mapping per block.

Why: the refinement allocates per batch of 512 texels arrays of 20-80 MB (each entry's directions to
every emitter sample) and frees them a moment later. glibc serves a block that large with its own
``mmap`` and unmaps it on free, so every batch faults in fresh pages the kernel must zero — ~40% of
the compiled directions loop's time (docs/performance.md, "Freed memory kept"). With mapping off
(``M_MMAP_MAX`` 0) and a 1 GB trim threshold, freed blocks stay mapped and the next batch reuses
them. Memory mapped files (the traces table) are not malloc's and are unaffected. Called once by the
command line (``ntp``) at start; elsewhere (other C libraries, musl, macOS, Windows) it does nothing.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import functools

M_TRIM_THRESHOLD, M_MMAP_MAX = -1, -4  # glibc's mallopt parameters (malloc.h)
TRIM_THRESHOLD = 1 << 30  # free memory at the heap's top beyond this goes back to the system


@functools.cache
def keep_freed_memory() -> bool:
    """Large blocks from the heap and freed memory kept (module docstring); returns whether glibc took
    both settings. Idempotent."""
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
        mallopt = libc.mallopt
    except (OSError, AttributeError):  # not glibc
        return False
    mallopt.argtypes, mallopt.restype = [ctypes.c_int, ctypes.c_int], ctypes.c_int
    return bool(mallopt(M_MMAP_MAX, 0)) and bool(mallopt(M_TRIM_THRESHOLD, TRIM_THRESHOLD))
