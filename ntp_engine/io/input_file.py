"""Input files are read only when they are regular files of a plausible size.

A name in a scan folder can be a link to ``/dev/zero`` (read forever), a FIFO (``open`` blocks, a
Ctrl-C is not seen), a device or a folder; a file can be many gigabytes where a few kilobytes are
expected. ``regular_file`` checks before anything is opened: it follows links (a link to a regular
file is a file) and refuses anything else, or a file over its kind's bound, in one line naming it.

Bounds (``MAX_BYTES``) are a hundred times the largest file of the kind a real scan holds, so no
real input comes near them and a wrong file is refused before it is read.
"""

from __future__ import annotations

import os
import stat
from pathlib import Path

from .errors import NtpInputError

MAX_BYTES = {
    # text tables: the shipped device files are <= 40 kB; scan.toml a few hundred bytes
    "toml": 16 << 20,
    # poses: ~400 bytes per photo, 10,000 photos are 4 MB
    "poses": 400 << 20,
    # meshes: a 1M-triangle OBJ with UVs and normals is ~100 MB
    "mesh": 4 << 30,
    # a pattern CSV/NPY: 512 emitters x 3 values, a few kB
    "pattern": 16 << 20,
    # a marker board's layout (board.json): a few hundred bytes
    "board": 1 << 20,
}

_KINDS = (
    (stat.S_ISDIR, "a folder"),
    (stat.S_ISFIFO, "a FIFO (named pipe)"),
    (stat.S_ISCHR, "a character device"),
    (stat.S_ISBLK, "a block device"),
    (stat.S_ISSOCK, "a socket"),
)


def what_it_is(mode: int) -> str:
    """A person's word for a file of ``st_mode`` ``mode`` that is not a regular file."""
    return next((word for test, word in _KINDS if test(mode)), "not a regular file")


def regular_file(path: str | Path, max_bytes: int | None = None, missing: str = "does not exist") -> int:
    """The size in bytes of ``path``, a regular file (links followed) of at most ``max_bytes``;
    ``NtpInputError`` naming it otherwise. Nothing is opened, so a FIFO or a device cannot block."""
    path = Path(path)
    try:
        st = os.stat(path)
    except FileNotFoundError:
        raise NtpInputError(path, missing) from None
    except OSError as err:
        raise NtpInputError(path, f"cannot read ({err.strerror})") from None
    if not stat.S_ISREG(st.st_mode):
        raise NtpInputError(path, f"is {what_it_is(st.st_mode)}, not a file")
    if max_bytes is not None and st.st_size > max_bytes:
        mb = st.st_size / 2**20
        raise NtpInputError(path, f"is {mb:.0f} MB; a file of this kind is at most {max_bytes >> 20} MB")
    return st.st_size
