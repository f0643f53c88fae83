"""Reading TOML input files with one-line errors that name the file."""

from __future__ import annotations

import tomllib
from pathlib import Path

from .errors import NtpInputError


def read_toml(path: Path, missing: str, error: type[NtpInputError] = NtpInputError) -> dict:
    """The parsed table; ``missing`` is the message when the file does not exist."""
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
