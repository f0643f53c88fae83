"""The engine's compiled loops: ``numba.njit`` with its on-disk cache where one can be written.

numba caches a compiled function beside its source (``__pycache__``) or, where the install is
read-only, in the user's cache folder; with neither writable (a read-only install and a read-only
HOME: a container, a shared site-packages) ``cache=True`` raises at import, and every command —
``ntp --help`` included — would die. ``compiled`` asks numba once, at import, whether it can cache
here (``NUMBA_CACHE_DIR`` chooses the place); where it cannot, the loops compile in each process
instead (seconds per run), with the same results.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numba


def _probe() -> None:  # a function of this package: numba looks for a cache place for its file
    return None


def _can_cache() -> bool:
    try:
        numba.njit(cache=True)(_probe)  # numba picks the cache's place at decoration
    except RuntimeError:  # "cannot cache function ...: no locator available"
        return False
    return True


CACHE = _can_cache()


def compiled(**options: Any) -> Callable:
    """``numba.njit(**options)``, cached on disk where numba can write a cache (``CACHE``)."""
    return numba.njit(cache=CACHE, **options)
