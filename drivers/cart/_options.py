"""Checks shared by the cart's config dataclasses (keys, types, ranges) with naming errors.

The config comes from TOML, so values arrive as ``str``, ``int``, ``float``, ``bool``, lists and
tables. The dataclasses declare their fields' ranges and choices as msgspec types
(``Annotated[int, msgspec.Meta(ge=1)]``, enums); the checks are the one configuration model's
(:mod:`drivers.config_model`, which the bridge's config uses too), raising
:class:`drivers.errors.DriverConfigError`: every error names the key, the value and what was
expected.
"""

from __future__ import annotations

import re
from collections.abc import Iterable, Mapping
from enum import Enum
from typing import Annotated, Any, TypeVar

from msgspec import Meta

from drivers.config_model import FINITE, check_fields, check_value, unknown_key_message
from drivers.errors import DriverConfigError

__all__ = [
    "check_declared",
    "check_keys",
    "check_mapping",
    "enum_value",
    "number",
    "text",
    "within",
]

E = TypeVar("E", bound=Enum)


def check_mapping(data: object, where: str) -> Mapping[str, Any]:
    """Return ``data`` if it is a mapping (a TOML table), else raise naming ``where``."""
    if not isinstance(data, Mapping):
        raise DriverConfigError(f"{where} = {data!r}: expected a table (mapping of key to value)")
    return data


def check_keys(data: Mapping[str, Any], allowed: Iterable[str], where: str) -> None:
    """Reject keys of ``data`` that are not in ``allowed``, naming the first unknown key.

    The message is :func:`drivers.config_model.unknown_key_message`'s (full key path, the
    closest allowed key, the allowed keys), the same as every other config table's.
    """
    allowed = tuple(allowed)
    for key, value in data.items():
        if key not in allowed:
            raise DriverConfigError(unknown_key_message(where, key, f"{value!r:.60}", allowed))


def check_declared(obj: Any) -> None:
    """Check a config dataclass's declared fields (:func:`drivers.config_model.check_fields`).

    For a ``__post_init__``: errors name the bare field (``from_dict`` puts the table's path in
    front, :func:`within`); numbers become floats, enum values members.
    """
    check_fields(obj, DriverConfigError)


def within(where: str, err: DriverConfigError) -> DriverConfigError:
    """``err`` (raised naming a key relative to a table) with the key path under ``where``."""
    msg = str(err)
    m = _UNKNOWN.match(msg)
    if m:  # "unknown key channels.o2 ... allowed keys in [channels]" -> under where
        return DriverConfigError(msg.replace(f"{m['key']} = ", f"{where}.{m['key']} = ", 1)
                                 .replace(f"allowed keys in [{m['table']}]",
                                          f"allowed keys in [{where}.{m['table']}]", 1))
    return DriverConfigError(f"{where}.{msg}")


_UNKNOWN = re.compile(r"^unknown key (?P<key>(?P<table>[\w.\[\]]+)\.[^ ]+) = ")


def number(value: object, name: str, *, lo: float | None = None, hi: float | None = None,
           lo_open: bool = False) -> float:
    """Return ``value`` as a finite float within ``[lo, hi]`` (``(lo, hi]`` if ``lo_open``)."""
    low = {"gt": lo} if lo_open else {"ge": -FINITE if lo is None else lo}
    return check_value(value, Annotated[float, Meta(**low, le=FINITE if hi is None else hi)], name,
                       DriverConfigError)


def text(value: object, name: str) -> str:
    """Return ``value`` if it is a non-empty string."""
    return check_value(value, Annotated[str, Meta(min_length=1)], name, DriverConfigError)


def enum_value(value: object, enum_cls: type[E], name: str) -> E:
    """Return the member of ``enum_cls`` whose value is ``value`` (members pass through)."""
    return check_value(value, enum_cls, name, DriverConfigError)
