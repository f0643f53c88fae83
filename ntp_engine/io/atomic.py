"""Atomic file output: write to a temporary file beside the target, then rename over it.

Every temporary file or folder ntp makes is named ``TEMP_PREFIX + ...`` (``temp_dir``,
``atomic_path``), so what a killed run leaves can be recognised and removed, and nothing else.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path

TEMP_PREFIX = ".ntp-tmp."


def temp_dir(parent: Path, stem: str) -> Path:
    """A new empty folder ``parent/.ntp-tmp.<stem>.XXXXXXXX`` (mode 0700 until renamed)."""
    parent.mkdir(parents=True, exist_ok=True)
    return Path(tempfile.mkdtemp(prefix=f"{TEMP_PREFIX}{stem}.", dir=parent))


def umask_mode(mode: int) -> int:
    """``mode`` less the process's umask: what ``open``/``mkdir`` would give a new file/folder."""
    umask = os.umask(0)
    os.umask(umask)
    return mode & ~umask


@contextlib.contextmanager
def atomic_path(target: str | Path) -> Iterator[Path]:
    """Yield a temporary path in the target's folder (same suffix); rename it onto ``target`` on
    success, delete it on failure. A reader never sees a half-written file."""
    target = Path(target)
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f"{TEMP_PREFIX}{target.stem}.", suffix=target.suffix, dir=target.parent)
    except OSError as err:  # the user knows the target, not our temporary
        raise OSError(err.errno, err.strerror, str(target)) from None
    os.close(fd)
    os.chmod(tmp, umask_mode(0o666))  # mkstemp makes 0600; a finished file gets the usual mode
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        os.replace(tmp_path, target)
    except OSError as err:
        if err.filename in (None, tmp, str(tmp_path)):  # the user knows the target, not our temporary
            raise OSError(err.errno, err.strerror, str(target)) from err
        raise
    finally:
        if tmp_path.exists():
            tmp_path.unlink()


def write_text_atomic(target: str | Path, text: str) -> None:
    """Write ``text`` (UTF-8) to ``target`` atomically."""
    with atomic_path(target) as tmp:
        tmp.write_text(text, encoding="utf-8")


def reserve_disk(path: Path) -> None:
    """Allocate the disk blocks of the whole (sparse) file ``path`` now. A memory-mapped file's
    holes are filled when a page is first written; on a full disk that write is a SIGBUS that kills
    the process without a word. Reserved here, a full disk is an ``OSError`` naming ``path``."""
    if not hasattr(os, "posix_fallocate"):  # macOS, Windows: no reservation, as before
        return
    with open(path, "r+b") as fh:
        try:
            os.posix_fallocate(fh.fileno(), 0, os.fstat(fh.fileno()).st_size)
        except OSError as err:
            raise OSError(err.errno, err.strerror, str(path)) from None
