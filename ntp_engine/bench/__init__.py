"""Benchmarks (`ntp bench NAME`): run time and error side by side, measured in one run."""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable
from pathlib import Path

from ..io.atomic import write_text_atomic


def timed(fn: Callable[[], object], repeat: int = 3) -> float:
    """Best wall time in seconds of ``repeat`` calls (after one warm-up call)."""
    fn()
    best = float("inf")
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def print_table(rows: list[tuple], header: tuple) -> None:
    """Rows under a header, columns padded to their widest cell."""
    cols = [header] + [tuple(str(c) for c in r) for r in rows]
    widths = [max(len(r[i]) for r in cols) for i in range(len(header))]
    for k, r in enumerate(cols):
        print("  ".join(c.ljust(w) for c, w in zip(r, widths)))
        if k == 0:
            print("  ".join("-" * w for w in widths))


def dump_json(path: str | Path | None, data: dict) -> None:
    """Write ``data`` as JSON to ``path`` (atomic) if a path is given."""
    if path:
        write_text_atomic(path, json.dumps(data, indent=2))
        print(f"wrote {path}")


def number(x: float | None, digits: int = 3) -> str:
    """``x`` to ``digits`` significant digits for a table; ``-`` for None or NaN."""
    return "-" if x is None or (isinstance(x, float) and math.isnan(x)) else f"{x:.{digits}g}"


def finite_mean(values: list) -> float | None:
    """The mean of the finite values (None and NaN left out); None when there are none."""
    finite = [v for v in values if v is not None and math.isfinite(v)]
    return float(sum(finite) / len(finite)) if finite else None


def tune_validate(tune: list, validate: list) -> str:
    """A table cell: the finite mean on the tuning set / on the validation set, and the gap
    (validate - tune) where both exist: ``2 / 4.5 (+2.5)``."""
    a, b = finite_mean(tune), finite_mean(validate)
    gap = f" ({b - a:+.3g})" if a is not None and b is not None else ""
    return f"{number(a)} / {number(b)}{gap}"
