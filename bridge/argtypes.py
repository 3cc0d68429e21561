"""Argument types of the command line: a number in a range, named in argparse's usage error."""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable

__all__ = ["bounded", "minutes", "nonnegative", "nonnegative_int", "positive_int", "seconds",
           "two_or_more"]


def bounded(kind: type[int] | type[float], what: str, *, low: float, high: float = math.inf,
            low_open: bool = False) -> Callable[[str], float]:
    """An argparse ``type`` reading ``kind`` in [low, high] ((low, high] when ``low_open``);
    anything else is a usage error ``expected WHAT, got 'TEXT'`` (argparse names the option)."""

    def parse(text: str) -> float:
        try:
            value = kind(text)
        except ValueError as err:
            raise argparse.ArgumentTypeError(f"expected {what}, got {text!r}") from err
        above = value > low if low_open else value >= low
        if not (above and value <= high and math.isfinite(value)):
            raise argparse.ArgumentTypeError(f"expected {what}, got {text!r}")
        return value

    return parse


seconds = bounded(float, "seconds >= 0", low=0.0)
nonnegative = bounded(float, "a number >= 0", low=0.0)
minutes = bounded(float, "minutes in (0, 600]", low=0.0, high=600.0, low_open=True)
nonnegative_int = bounded(int, "an integer >= 0", low=0)
positive_int = bounded(int, "a whole number >= 1", low=1)
two_or_more = bounded(int, "a whole number >= 2", low=2)
