"""bridge.argtypes: numbers in a range, refused as usage errors that name what was expected."""

from __future__ import annotations

import argparse
import math

import pytest

from bridge.argtypes import bounded, minutes, nonnegative_int, positive_int, seconds


@pytest.mark.parametrize("parse, text, value", [
    (seconds, "0", 0.0), (seconds, "2.5", 2.5), (minutes, "600", 600.0), (minutes, "0.5", 0.5),
    (nonnegative_int, "0", 0), (positive_int, "3", 3),
])
def test_values_in_range_are_read_as_their_kind(parse, text: str, value: float) -> None:
    got = parse(text)
    assert got == value and type(got) is type(value)


@pytest.mark.parametrize("parse, text, expected", [
    (seconds, "-1", "seconds >= 0"), (seconds, "inf", "seconds >= 0"), (seconds, "nan", "seconds >= 0"),
    (seconds, "soon", "seconds >= 0"), (minutes, "0", "minutes in (0, 600]"),
    (minutes, "601", "minutes in (0, 600]"), (minutes, "-5", "minutes in (0, 600]"),
    (nonnegative_int, "-1", "an integer >= 0"), (nonnegative_int, "1.5", "an integer >= 0"),
    (positive_int, "0", "a whole number >= 1"),
])
def test_values_out_of_range_are_usage_errors_naming_what_was_expected(
        parse, text: str, expected: str) -> None:
    with pytest.raises(argparse.ArgumentTypeError) as err:
        parse(text)
    assert str(err.value) == f"expected {expected}, got {text!r}"


def test_argparse_names_the_option() -> None:
    p = argparse.ArgumentParser(prog="hilbo sim", exit_on_error=False)
    p.add_argument("--minutes", type=bounded(float, "minutes in (0, 10]", low=0.0, high=10.0, low_open=True))
    assert p.parse_args(["--minutes", "10"]).minutes == 10.0
    with pytest.raises(argparse.ArgumentError, match="argument --minutes: expected minutes in"):
        p.parse_args(["--minutes", str(math.pi * 4)])
