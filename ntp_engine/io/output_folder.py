"""The folders ntp writes (results, virtual scans, demo and gallery runs) and the rules that keep a
user's files safe (docs/design.md output contract):

- ntp writes only into a folder that is absent, empty, or one it made itself for the same purpose,
  known by its marker file ``.ntp`` (``{"ntp": KIND}``); anything else is refused in one line;
- never into (or under) an input folder, e.g. the scan folder;
- one run at a time per folder (the marker is locked while a run writes; where the platform has
  no ``fcntl``, e.g. Windows, this lock is skipped);
- temporary files and folders a killed run left (ntp's own names, ``io.atomic.TEMP_PREFIX``) are
  removed when the next run claims the folder; nothing else is ever deleted.

A result is complete when its ``report.json`` exists: ``publish`` moves a finished set of outputs
from a staging folder into place and writes the report last.
"""

from __future__ import annotations

import contextlib
import errno
import json
import os
import shutil
import tempfile
from collections.abc import Iterator
from pathlib import Path

from .atomic import TEMP_PREFIX, umask_mode, write_text_atomic
from .errors import NtpInputError

try:
    import fcntl
except ImportError:  # Windows: no advisory locks (documented above)
    fcntl = None  # type: ignore[assignment]

MARKER = ".ntp"
REPORT = "report.json"
PAGE = "index.html"  # the result page (pipeline.result_page): it shows one result, so a new one removes it
# file systems without hard links answer os.link with one of these
_NO_HARD_LINKS = (errno.EPERM, errno.EOPNOTSUPP, errno.ENOSYS, errno.EMLINK, errno.EXDEV)
# cache: a stage cache kept apart (--cache); collection: ntp batch's folder of results
KINDS = ("result", "scan", "demo", "gallery", "cache", "collection")


def check_not_inside(out: Path, inputs: tuple[Path, ...]) -> None:
    """``NtpInputError`` if ``out`` is one of the ``inputs`` folders or inside one."""
    target = out.resolve()
    for folder in inputs:
        f = folder.resolve()
        if target == f or f in target.parents:
            where = "the input folder" if target == f else f"inside the input folder {folder}"
            raise NtpInputError(out, f"is {where}; ntp never writes there — choose another")


def check_claimable(out: Path, kind: str) -> None:
    """``NtpInputError`` unless ``out`` is absent, an empty folder, or an ntp ``kind`` folder."""
    if not out.exists():
        return
    if not out.is_dir():
        raise NtpInputError(out, "is a file, not a folder — choose a folder for the output")
    marker = out / MARKER
    if marker.is_file():
        try:
            found = json.loads(marker.read_text(encoding="utf-8")).get("ntp")
        except (OSError, ValueError, AttributeError):
            found = None
        if found != kind:
            raise NtpInputError(out, f"is an ntp {found or 'unknown'} folder, not a {kind} folder — choose another")
        return
    try:
        entries = sorted(p.name for p in out.iterdir())
    except OSError as err:
        raise NtpInputError(out, f"cannot list the folder ({err.strerror})") from None
    if entries:
        raise NtpInputError(
            out,
            f"is not empty and not an ntp {kind} folder (it has {entries[0]!r}{' …' if len(entries) > 1 else ''}, "
            f"no {MARKER} marker) — choose an empty or new folder; ntp does not overwrite your files",
        )


@contextlib.contextmanager
def claim(out: str | Path, kind: str, inputs: tuple[Path, ...] = ()) -> Iterator[Path]:
    """Make ``out`` an ntp ``kind`` folder (checks above) and hold it for this run: yields the path.
    Raises ``NtpInputError`` naming ``out`` for every refusal, including a folder it cannot write."""
    assert kind in KINDS, kind
    out = Path(out)
    check_not_inside(out, inputs)
    check_claimable(out, kind)
    marker = out / MARKER
    try:
        out.mkdir(parents=True, exist_ok=True)
        if not marker.is_file():
            _create_marker(marker, kind)
        lock = open(marker, "rb")  # noqa: SIM115 - held for the whole run
    except OSError as err:
        raise NtpInputError(out, f"cannot write here ({err.strerror})") from None
    try:
        if fcntl is not None:
            try:
                fcntl.flock(lock.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
            except BlockingIOError:
                raise NtpInputError(out, "another ntp run is writing to this folder — wait for it to finish") from None
        remove_temporaries(out)
        yield out
    finally:
        lock.close()  # releases the lock


def _create_marker(marker: Path, kind: str) -> None:
    """Write ``marker`` complete, and only if it does not exist: written under a temporary name and
    *linked* into place, which fails where another run made it first. (A rename would replace that
    run's marker after it locked it, and both runs would hold a lock, each on its own file.) Where
    the file system has no hard links (FAT, some network mounts) it is created exclusively instead."""
    text = json.dumps({"ntp": kind}) + "\n"
    fd, tmp = tempfile.mkstemp(prefix=f"{TEMP_PREFIX}{MARKER}.", dir=marker.parent)
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as fh:
            fh.write(text)
        os.chmod(tmp, umask_mode(0o666))
        try:
            os.link(tmp, marker)
        except FileExistsError:
            pass  # another run's: the lock decides who writes
        except OSError as err:
            if err.errno not in _NO_HARD_LINKS:
                raise
            with contextlib.suppress(FileExistsError), open(marker, "x", encoding="utf-8") as fh:
                fh.write(text)
    finally:
        os.unlink(tmp)


def remove_temporaries(folder: Path) -> None:
    """Delete the temporary files/folders a killed run left in ``folder`` and its subfolders
    (ntp's temporary names only); subfolders with their own marker are claimed on their own."""
    for root, dirs, files in os.walk(folder):
        if Path(root) != folder and MARKER in files:
            dirs.clear()
            continue
        for name in files:
            if name.startswith(TEMP_PREFIX):
                Path(root, name).unlink(missing_ok=True)
        for name in list(dirs):
            if name.startswith(TEMP_PREFIX):
                shutil.rmtree(Path(root, name), ignore_errors=True)
                dirs.remove(name)


def is_complete(result: Path) -> bool:
    """Whether ``result`` holds a finished result (its report, written last, exists)."""
    return (Path(result) / REPORT).is_file()


def publish(staging: Path, out: Path, report_json: str) -> None:
    """Move every file of ``staging`` to the same place under ``out``, then write ``report.json``
    (the completion marker) and remove ``staging``. The old report goes first, so a run killed
    between two moves leaves a folder that says it is incomplete, never a mix that looks finished.
    A result page of the old result goes too (``ntp view`` writes the new one)."""
    (out / REPORT).unlink(missing_ok=True)
    (out / PAGE).unlink(missing_ok=True)
    for src in sorted(p for p in staging.rglob("*") if p.is_file()):
        dst = out / src.relative_to(staging)
        dst.parent.mkdir(parents=True, exist_ok=True)
        os.replace(src, dst)
    write_text_atomic(out / REPORT, report_json)
    shutil.rmtree(staging, ignore_errors=True)
