"""Checks shared by the cart's config dataclasses (keys, types, ranges) with naming errors.

The config comes from TOML, so values arrive as ``str``, ``int``, ``float``, ``bool``, lists and
tables. Every error names the key, the value and what was expected, and derives from
:class:`drivers.errors.DriverConfigError`.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from enum import Enum
from typing import Any, TypeVar

from drivers.errors import DriverConfigError

__all__ = [
    "check_keys",
    "check_mapping",
    "enum_value",
    "int_value",
    "number",
    "optional_number",
    "text",
]

E = TypeVar("E", bound=Enum)


def check_mapping(data: object, where: str) -> Mapping[str, Any]:
    """Return ``data`` if it is a mapping (a TOML table), else raise naming ``where``."""
    if not isinstance(data, Mapping):
        raise DriverConfigError(f"{where} = {data!r}: expected a table (mapping of key to value)")
    return data


def check_keys(data: Mapping[str, Any], allowed: Iterable[str], where: str) -> None:
    """Reject keys of ``data`` that are not in ``allowed``, naming the first unknown key."""
    allowed_set = set(allowed)
    for key in data:
        if key not in allowed_set:
            raise DriverConfigError(
                f"{where}: unknown key {key!r} = {data[key]!r}; allowed keys: "
                + ", ".join(sorted(allowed_set))
            )


def number(
    value: object,
    name: str,
    *,
    lo: float | None = None,
    hi: float | None = None,
    lo_open: bool = False,
) -> float:
    """Return ``value`` as a finite float within ``[lo, hi]`` (``(lo, hi]`` if ``lo_open``)."""
    lo_s = "-inf" if lo is None else f"{lo:g}"
    hi_s = "inf" if hi is None else f"{hi:g}"
    expected = f"a finite number in {'(' if lo_open else '['}{lo_s}, {hi_s}]"
    # bool is an int subclass; `true` for a port or a speed is a config mistake, not 1.
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise DriverConfigError(f"{name} = {value!r}: expected {expected}")
    out = float(value)
    if not math.isfinite(out):
        raise DriverConfigError(f"{name} = {value!r}: expected {expected}")
    if lo is not None and (out <= lo if lo_open else out < lo):
        raise DriverConfigError(f"{name} = {value!r}: expected {expected}")
    if hi is not None and out > hi:
        raise DriverConfigError(f"{name} = {value!r}: expected {expected}")
    return out


def optional_number(
    value: object,
    name: str,
    *,
    lo: float | None = None,
    hi: float | None = None,
    lo_open: bool = False,
) -> float | None:
    """Like :func:`number` but ``None`` passes through (an option that is switched off)."""
    if value is None:
        return None
    return number(value, name, lo=lo, hi=hi, lo_open=lo_open)


def int_value(value: object, name: str, *, lo: int | None = None, hi: int | None = None) -> int:
    """Return ``value`` if it is an int (not a bool) within ``[lo, hi]``."""
    lo_s = "-inf" if lo is None else str(lo)
    hi_s = "inf" if hi is None else str(hi)
    if (
        isinstance(value, bool)
        or not isinstance(value, int)
        or (lo is not None and value < lo)
        or (hi is not None and value > hi)
    ):
        raise DriverConfigError(f"{name} = {value!r}: expected an integer in [{lo_s}, {hi_s}]")
    return value


def text(value: object, name: str, *, non_empty: bool = True) -> str:
    """Return ``value`` if it is a string (non-empty unless told otherwise)."""
    if not isinstance(value, str) or (non_empty and not value):
        raise DriverConfigError(f"{name} = {value!r}: expected a {'non-empty ' if non_empty else ''}string")
    return value


def enum_value(value: object, enum_cls: type[E], name: str) -> E:
    """Return the member of ``enum_cls`` whose value is ``value`` (members pass through)."""
    if isinstance(value, enum_cls):
        return value
    for member in enum_cls:
        if member.value == value:
            return member
    allowed = ", ".join(repr(m.value) for m in enum_cls)
    raise DriverConfigError(f"{name} = {value!r}: expected one of {allowed}")
