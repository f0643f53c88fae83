"""Helpers for the ``--ray`` tests: a real worker process killed while it runs a task."""

import os
import signal
import threading
import time


def kill_task_once(task_name: str, within_s: float = 120.0) -> list:
    """Start a thread that SIGKILLs the first process running Ray task ``task_name`` (its process
    title ``ray::NAME``) and returns; the list it returns gets that process's pid."""
    killed: list = []

    def hunt():
        end = time.monotonic() + within_s
        while time.monotonic() < end and not killed:
            for pid in filter(str.isdigit, os.listdir("/proc")):
                try:
                    with open(f"/proc/{pid}/cmdline", "rb") as f:
                        title = f.read().split(b"\0")[0].decode(errors="replace")
                except OSError:
                    continue
                if title == f"ray::{task_name}":
                    os.kill(int(pid), signal.SIGKILL)
                    killed.append(int(pid))
                    break
            time.sleep(0.02)

    threading.Thread(target=hunt, daemon=True).start()
    return killed


def times(x: int, k: int) -> int:
    """A task: ``x * k``."""
    return x * k


def napping(seconds: float) -> int:
    """A task that takes ``seconds`` and says which process ran it."""
    time.sleep(seconds)
    return os.getpid()
