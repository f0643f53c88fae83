import argparse

import pytest

from ntp_engine.io.arguments import OneLineParser, bound_numbers, float_in, int_in


def _parser() -> argparse.ArgumentParser:
    p = OneLineParser(prog="tool")
    sub = p.add_subparsers(dest="cmd", required=True)
    run = sub.add_parser("run")
    run.add_argument("--size", type=int_in(8, 64, "a texture's side"), default=8)
    run.add_argument("--count", type=int, default=1)
    run.add_argument("--gain", type=float, default=1.0)
    run.add_argument("--share", type=float_in(0.0, 1.0), default=0.5)
    return bound_numbers(p)


@pytest.mark.parametrize(
    "argv, message",
    [
        (["--size", "4"], "argument --size: 4: need 8 to 64 (a texture's side)"),
        (["--size", "99999999999999999999999"], "need 8 to 64"),
        (["--size", "x"], "x: not an integer"),
        (["--count", "99999999999999999999"], "need a value within ±9.22e+18"),
        (["--gain", "nan"], "nan: not a finite number"),
        (["--gain", "inf"], "inf: not a finite number"),
        (["--share", "1.5"], "1.5: need 0 to 1"),
    ],
)
def test_a_number_out_of_range_is_one_line_and_exit_2(argv, message, capsys):
    with pytest.raises(SystemExit) as done:
        _parser().parse_args(["run", *argv])
    err = capsys.readouterr().err
    assert done.value.code == 2 and len(err.strip().splitlines()) == 1
    assert err.startswith("tool: error: ") and message in err and "tool run --help" in err


def test_numbers_in_range_pass_through():
    a = _parser().parse_args(["run", "--size", "64", "--count", "-3", "--gain", "1e300", "--share", "0"])
    assert (a.size, a.count, a.gain, a.share) == (64, -3, 1e300, 0.0)
