"""Command-line numbers checked at the boundary, errors in one line.

Every integer or float option of a parser is range-checked when it is parsed: an option given an
explicit range (``int_in``, ``float_in``) says where its bounds come from; every other gets the
general bound (``bound_numbers``: a finite float, an integer that fits in 63 bits), so no number a
person types reaches numpy or torch as an overflow or a NaN. ``OneLineParser`` reports a bad
option as ``PROG: error: --opt VALUE: problem`` on one line (exit 2), as the engine's errors are.
"""

from __future__ import annotations

import argparse
import math
import sys
from collections.abc import Callable
from typing import NoReturn

INT_LIMIT = 2**63 - 1  # numpy's int64: any larger value overflows the first array it meets


class OneLineParser(argparse.ArgumentParser):
    """An ``ArgumentParser`` whose errors are one line on stderr (``ntp: error: ...``), exit 2."""

    def error(self, message: str) -> NoReturn:
        """Print ``message`` as one line naming the command and exit 2."""
        prog = self.prog.split()[0]
        print(f"{prog}: error: {' '.join(message.split())} (see {self.prog} --help)", file=sys.stderr)
        sys.exit(2)


class _Number:
    """An argparse ``type``: parse with ``kind`` and require ``lo <= x <= hi`` (finite)."""

    def __init__(self, kind: Callable[[str], float], lo: float, hi: float, why: str = ""):
        self.kind, self.lo, self.hi, self.why = kind, lo, hi, why
        self.__name__ = kind.__name__  # argparse names the type in its messages

    def __call__(self, text: str) -> float:
        try:
            value = self.kind(text)
        except (ValueError, OverflowError):
            raise argparse.ArgumentTypeError(f"{text}: not a{'n integer' if self.kind is int else ' number'}") from None
        if not math.isfinite(value):
            raise argparse.ArgumentTypeError(f"{text}: not a finite number")
        if not self.lo <= value <= self.hi:
            why = f" ({self.why})" if self.why else ""
            raise argparse.ArgumentTypeError(f"{text}: need {_range(self.lo, self.hi, self.kind)}{why}")
        return value


def _range(lo: float, hi: float, kind: Callable) -> str:
    if lo <= -INT_LIMIT:
        return f"a value within ±{hi:.3g}"
    if hi >= INT_LIMIT or math.isinf(hi):
        return f"{lo:g} or more"
    return f"{lo:g} to {hi:g}" if kind is float else f"{int(lo)} to {int(hi)}"


def int_in(lo: int, hi: int = INT_LIMIT, why: str = "") -> Callable[[str], int]:
    """An argparse ``type`` accepting integers in ``[lo, hi]``; ``why`` names where the bounds come from."""
    return _Number(int, lo, hi, why)  # type: ignore[return-value]


def float_in(lo: float, hi: float = math.inf, why: str = "") -> Callable[[str], float]:
    """An argparse ``type`` accepting finite floats in ``[lo, hi]``."""
    return _Number(float, lo, hi, why)


def bound_numbers(parser: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """Give every plain ``int``/``float`` option of ``parser`` and its subcommands the general bound
    (an integer within int64, a finite float); options with their own range keep it."""
    for action in parser._actions:
        if action.type is int:
            action.type = int_in(-INT_LIMIT)
        elif action.type is float:
            action.type = float_in(-math.inf)
        if isinstance(action, argparse._SubParsersAction):
            for sub in action.choices.values():
                bound_numbers(sub)
    return parser
