"""Reading TOML input files with one-line errors that name the file."""

from __future__ import annotations

import difflib
import tomllib
from collections.abc import Iterable
from pathlib import Path

from .errors import NtpInputError
from .input_file import MAX_BYTES, regular_file


def read_toml(path: Path, missing: str, error: type[NtpInputError] = NtpInputError) -> dict:
    """The parsed table; ``missing`` is the message when the file does not exist. Only a regular
    file of at most ``MAX_BYTES["toml"]`` is read (``io.input_file``)."""
    try:
        regular_file(path, MAX_BYTES["toml"], missing)
    except NtpInputError as err:
        raise error(path, err.problem) from None
    try:
        with open(path, "rb") as fh:
            return tomllib.load(fh)
    except FileNotFoundError:
        raise error(path, missing) from None
    except UnicodeDecodeError as err:
        raise error(path, f"not UTF-8 text (byte 0x{err.object[err.start]:02x} at offset {err.start})") from None
    except tomllib.TOMLDecodeError as err:
        raise error(path, f"not valid TOML ({err})") from None
    except OSError as err:
        raise error(path, f"cannot read ({err.strerror})") from None


def unknown_key(key: str, known: Iterable[str]) -> str:
    """The problem with an unknown ``key``: ``unknown key (did you mean 'poses'?)`` with the nearest
    known key where one is close, else the known keys."""
    close = difflib.get_close_matches(key, list(known), n=1, cutoff=0.6)
    hint = f"did you mean {close[0]!r}?" if close else f"known keys: {', '.join(sorted(known))}"
    return f"unknown key ({hint})"


def check_keys(table: dict, known: Iterable[str], path: Path, error: type[NtpInputError] = NtpInputError) -> None:
    """``error`` naming ``path`` and the first key of ``table`` not in ``known`` (a typo must not
    silently leave a setting at its default)."""
    for key in table:
        if key not in known:
            raise error(path, f"key {key!r}: {unknown_key(key, known)}")
