"""Errors shown to users as one line that names the file and what is wrong."""

from __future__ import annotations

from pathlib import Path


class NtpInputError(ValueError):
    """Bad user input: ``str(err)`` is ``"<file>: <problem>"`` on one line."""

    def __init__(self, path: str | Path | None, problem: str):
        self.path = None if path is None else Path(path)
        self.problem = " ".join(str(problem).split())  # always one line
        super().__init__(f"{self.path}: {self.problem}" if self.path else self.problem)

    def __reduce__(self) -> tuple:
        # pickled by its two fields (a Ray task's error comes back to the driver as itself)
        return (type(self), (self.path, self.problem))


def error_line(err: NtpInputError | OSError) -> str:
    """What a person reads, one line naming the file: the input error, or an operating-system
    error as ``path: No space left on device``."""
    if isinstance(err, NtpInputError) or not err.filename:
        return " ".join(str(err).split())
    return f"{err.filename}: {' '.join((err.strerror or str(err)).split())}"
