"""SIGTERM ends a run as Ctrl-C does: the stage being written removes its temporaries on the way out.

``kill PID``, a job scheduler's time limit and a container's stop send SIGTERM, whose default kills
the process where it stands, leaving temporaries and no word. Inside ``terminate_as_interrupt`` it
raises ``Terminated``, a ``KeyboardInterrupt``, so every ``finally`` and ``except KeyboardInterrupt``
that cleans up after Ctrl-C runs for it too; the command line reports it (exit 143).
"""

from __future__ import annotations

import contextlib
import signal
import threading
from collections.abc import Iterator
from types import FrameType


class Terminated(KeyboardInterrupt):
    """The process was sent SIGTERM."""


def _raise(signum: int, frame: FrameType | None) -> None:
    raise Terminated


@contextlib.contextmanager
def terminate_as_interrupt() -> Iterator[None]:
    """SIGTERM raises ``Terminated`` while inside (main thread only; elsewhere nothing changes);
    the previous handler is restored on the way out."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGTERM, _raise)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)
