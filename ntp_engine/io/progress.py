"""Progress of long stages, for a person and for a program.

A person at a terminal sees tqdm bars on stderr. A program (the Blender add-on) names a file and
reads JSON lines from it, one object per update: ``{"stage": str, "done": int, "total": int | null,
"unit": str, "elapsed_s": float, "eta_s": float | null}`` — the stage's name, units done of
``total``, seconds since the stage began and the estimated seconds left. A stage writes a line when
it starts, at most every ``min_interval_s`` while it runs, and when it ends, so the file stays small.
``warn`` is the third channel: one line on stderr when something is skipped or redone and the run
goes on (an unreadable photo, a damaged cache entry).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import TypeVar

from tqdm import tqdm

T = TypeVar("T")


@dataclass(frozen=True)
class Progress:
    """Where progress goes: ``bars`` (tqdm on stderr) and/or ``json_path`` (JSON lines appended)."""

    bars: bool = False
    json_path: Path | None = None
    min_interval_s: float = 0.2

    def counter(self, stage: str, total: int | None, unit: str = "it") -> StageCounter:
        """A counter for one stage (a context manager); ``update(n)`` as work is done."""
        return StageCounter(self, stage, total, unit)

    def track(self, items: Iterable[T], stage: str, total: int | None = None, unit: str = "it") -> Iterator[T]:
        """``items`` unchanged, counting one unit per item (``total`` defaults to ``len(items)``)."""
        if total is None and hasattr(items, "__len__"):
            total = len(items)  # type: ignore[arg-type]
        with self.counter(stage, total, unit) as c:
            for item in items:
                yield item
                c.update()


QUIET = Progress()  # no bars, no file


def warn(message: str) -> None:
    """One line on stderr for a person: something was skipped or redone, and the run goes on
    (printed through tqdm so a running bar is not broken)."""
    tqdm.write(f"ntp: warning: {' '.join(message.split())}", file=sys.stderr)


class StageCounter:
    """One stage's count, shown as a bar and/or written as JSON lines (see the module docstring)."""

    def __init__(self, progress: Progress, stage: str, total: int | None, unit: str):
        self.progress, self.stage, self.total, self.unit = progress, stage, total, unit
        self.done = 0
        self.start = self._last = time.perf_counter()
        self._bar = tqdm(total=total, desc=stage, unit=unit) if progress.bars else None
        self._write()

    def update(self, n: int = 1) -> None:
        """Count ``n`` more units done."""
        self.done += n
        if self._bar is not None:
            self._bar.update(n)
        if time.perf_counter() - self._last >= self.progress.min_interval_s:
            self._write()

    def close(self) -> None:
        """End the stage (writes its last line)."""
        if self._bar is not None:
            self._bar.close()
            self._bar = None
        self._write()

    def __enter__(self) -> StageCounter:
        return self

    def __exit__(self, kind: type[BaseException] | None, err: BaseException | None, tb: TracebackType | None) -> None:
        self.close()

    def _write(self) -> None:
        path = self.progress.json_path
        self._last = time.perf_counter()
        if path is None:
            return
        elapsed = self._last - self.start
        eta = None
        if self.total and self.done > 0:
            eta = round(elapsed * (self.total - self.done) / self.done, 2)
        line = {
            "stage": self.stage,
            "done": self.done,
            "total": self.total,
            "unit": self.unit,
            "elapsed_s": round(elapsed, 2),
            "eta_s": eta,
        }
        try:
            with open(path, "a", encoding="utf-8") as fh:
                fh.write(json.dumps(line) + "\n")
        except OSError as err:  # the progress file's own problem (e.g. a full disk): name it, not the stage
            raise OSError(err.errno, err.strerror, str(path)) from None


def read_progress(path: Path, offset: int = 0) -> tuple[list[dict], int]:
    """The complete JSON lines written to ``path`` since byte ``offset``, and the offset to read
    from next time (a line still being written is left for then). A missing file reads as empty."""
    try:
        with open(path, "rb") as fh:
            fh.seek(offset)
            data = fh.read()
    except FileNotFoundError:
        return [], offset
    end = data.rfind(b"\n") + 1
    records = []
    for raw in data[:end].splitlines():
        try:
            records.append(json.loads(raw))
        except json.JSONDecodeError:
            continue  # not ours: skip it rather than stop reading
    return records, offset + end


def add_progress_arguments(parser: argparse.ArgumentParser) -> None:
    """``--quiet`` and ``--progress FILE`` on a command line (``progress_from_args`` reads them)."""
    parser.add_argument("--quiet", action="store_true", help="no progress bars")
    parser.add_argument(
        "--progress",
        type=Path,
        default=None,
        metavar="FILE",
        help="append progress as JSON lines to FILE (stage, done, total, unit, elapsed_s, eta_s)",
    )


def progress_from_args(args: argparse.Namespace) -> Progress:
    """The ``Progress`` a command line asked for (``add_progress_arguments``)."""
    return Progress(bars=not args.quiet, json_path=args.progress)
