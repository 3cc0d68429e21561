"""One configuration model: msgspec Structs decoded from TOML, errors that name key, value, range.

A config table is a frozen :class:`msgspec.Struct` (``forbid_unknown_fields=True``) whose fields
declare what they accept: ``Annotated[float, msgspec.Meta(ge=0.0, le=600.0)]`` for a range, an
:class:`enum.Enum` or ``Literal`` for a choice, ``Meta(pattern=..., description=...)`` for a
pattern (the description is what the error says is expected). :func:`decode` converts a TOML
table with :func:`msgspec.convert` (``strict=True``: ``true`` is not a number, ``"5"`` not an
integer) and turns a :class:`msgspec.ValidationError` into the project's message: the full key
path (``protocol.max_breaths``), the value as given and what was expected, and for an unknown key
the closest allowed one (``unknown key protocol.max_breath = 50 (did you mean 'max_breaths'?);
allowed keys in [protocol]: ...``) and for a bad choice the closest choice.

TOML has ``nan`` and ``inf``; a bound refuses NaN, and :data:`FINITE` (the largest float) is the
upper bound a field without one declares so that ``inf`` is refused too. A check between fields
goes in the Struct's ``__post_init__`` and raises ``ValueError("key = value: expected ...")``;
:func:`decode` puts the table's path in front. Each package passes its own exception class (its
error root's config error): the bridge raises ``BridgeConfigError``, the drivers
``DriverConfigError``.

The cart's option dataclasses are built in code as well as from TOML; they declare their fields
with the same msgspec types and call :func:`check_fields` in ``__post_init__``, which runs each
declared field through :func:`msgspec.convert`, so both get the same checks and messages.
Pure but for :func:`os.path.expanduser` on path fields; hilbo_core keeps no msgspec (its import
contract), so the model lives here, below the bridge.
"""

from __future__ import annotations

import dataclasses
import difflib
import enum
import os
import re
import sys
import typing
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Annotated, Any, TypeVar

import msgspec
from msgspec import inspect as mi

__all__ = ["FINITE", "check_fields", "check_value", "decode", "expected_text", "range_text",
           "unknown_key_message"]

#: The upper bound that refuses ``inf`` in a field with no upper bound of its own (shown as ``inf``).
FINITE = sys.float_info.max

T = TypeVar("T")
_PATH = re.compile(r"\.([^.\[]+)|\[(\d+|\.\.\.)\]")


def unknown_key_message(where: str, key: str, value_text: str, allowed: Iterable[str]) -> str:
    """The message for an unknown key (or, with ``where`` empty, an unknown top-level table)."""
    allowed = sorted(allowed)
    close = difflib.get_close_matches(key, allowed, n=1, cutoff=0.6)
    if not where:
        hint = f" (did you mean [{close[0]}]?)" if close else ""
        return f"unknown table [{key}]{hint}; allowed tables: {', '.join(allowed)}"
    hint = f" (did you mean {close[0]!r}?)" if close else ""
    return (f"unknown key {where}.{key} = {value_text}{hint}; "
            f"allowed keys in [{where}]: {', '.join(allowed) or '(none)'}")


def range_text(lo: float | None, hi: float | None, lo_open: bool = False) -> str:
    """``[lo, hi]`` (``(lo, hi]`` if ``lo_open``), open ends (and :data:`FINITE`) as ``-inf`` and ``inf``."""
    lo_s = "-inf" if lo in (None, -FINITE) else str(lo) if isinstance(lo, int) else f"{lo:g}"
    hi_s = "inf" if hi in (None, FINITE) else str(hi) if isinstance(hi, int) else f"{hi:g}"
    return f"{'(' if lo_open else '['}{lo_s}, {hi_s}]"


def expected_text(t: mi.Type, pattern: bool = False) -> str:
    """What a field of msgspec type ``t`` (:func:`msgspec.inspect.type_info`) accepts, in words.

    A ``Meta(description=...)`` is the words, except on a string with a ``pattern``: there it
    explains the pattern, said only when the string does not match it (``pattern``).
    """
    if isinstance(t, mi.Metadata):
        patterned = isinstance(t.type, mi.StrType) and t.type.pattern is not None
        return (None if patterned and not pattern else (t.extra_json_schema or {}).get("description")
                ) or expected_text(t.type)
    if isinstance(t, mi.UnionType):
        return " or ".join(expected_text(u) for u in t.types if not isinstance(u, mi.NoneType))
    if isinstance(t, mi.FloatType):
        return f"a finite number in {range_text(t.ge if t.gt is None else t.gt, t.le, t.gt is not None)}"
    if isinstance(t, mi.IntType):
        return f"an integer in {range_text(t.ge, t.le)}"
    if isinstance(t, mi.BoolType):
        return "true or false"
    if isinstance(t, mi.EnumType | mi.LiteralType):
        values = sorted(m.value for m in t.cls) if isinstance(t, mi.EnumType) else sorted(t.values)
        return "one of " + ", ".join(repr(v) for v in values)
    if isinstance(t, mi.StrType):
        return "a non-empty string" if t.min_length else "a string"
    if isinstance(t, mi.ListType | mi.VarTupleType):
        return f"a list of {expected_text(t.item_type).removeprefix('a ')}s"
    return "a table"


def _path_hook(tp: type, obj: object) -> Any:
    # A path field: "~/hilbo-sessions" is the home folder, as in a shell; never a folder named "~".
    if tp is not Path:
        raise NotImplementedError
    if not isinstance(obj, str) or not obj:
        raise ValueError("expected a non-empty string")
    expanded = os.path.expanduser(obj)
    if expanded.startswith("~"):
        raise ValueError(f"the home folder of {obj.split('/', 1)[0]!r} is unknown; give the full path")
    return Path(expanded)


def decode(cls: type[T], data: object, where: str, error: Callable[[str], Exception],
           dec_hook: Callable[[type, Any], Any] = _path_hook) -> T:
    """``data`` (a TOML table) as a ``cls``, or ``error`` naming the key path, value and what is allowed.

    Args:
        cls: The Struct (or a type msgspec converts to).
        data: The TOML value.
        where: Its path (``protocol``, ``cart.options``) for the messages.
        error: The exception class (or factory) to raise with the message.
        dec_hook: Converts the types msgspec does not know (default: :class:`~pathlib.Path`).
    """
    try:
        return msgspec.convert(data, cls, strict=True, dec_hook=dec_hook)
    except msgspec.ValidationError as err:
        raise error(_message(str(err), data, cls, where)) from err


def check_value(value: object, tp: Any, name: str, error: Callable[[str], Exception]) -> Any:
    """``value`` converted to type ``tp`` (``5`` -> ``5.0``, ``"csv"`` -> a member), or ``error``."""
    return decode(tp, value, name, error)


def _declared(tp: Any) -> bool:
    """Whether a field's type declares a check: a range or pattern (``Annotated``), or an enum."""
    if typing.get_origin(tp) is Annotated or (isinstance(tp, type) and issubclass(tp, enum.Enum)):
        return True
    return any(_declared(a) for a in typing.get_args(tp))


def check_fields(obj: Any, error: Callable[[str], Exception]) -> None:
    """Check (and convert in place) the declared fields of a frozen dataclass instance.

    For a ``__post_init__``: a config built in code gets the checks a TOML table gets (msgspec
    checks only what it converts). Errors name the bare field (``port = 0: expected ...``).
    """
    hints = typing.get_type_hints(type(obj), include_extras=True)
    for f in dataclasses.fields(obj):
        if _declared(hints[f.name]):
            object.__setattr__(obj, f.name, check_value(getattr(obj, f.name), hints[f.name], f.name, error))


def _message(text: str, data: object, cls: type, where: str) -> str:
    """msgspec's ``"<what> - at `$.key[0].key`"`` in the project's words."""
    what, _, path = text.rpartition(" - at `") if " - at `$" in text else (text, "", "$")
    t: mi.Type = mi.type_info(cls)
    value: Any = data
    name = where
    for key, index in _PATH.findall(path.rstrip("`")[1:]):
        if index and not isinstance(_child(_child(t, index), None), mi.StructType | mi.DictType):
            break  # a bad item of a list of strings or numbers: the message names the list
        t = _child(t, key or index)
        name = f"{name}.{key}" if key else f"{name}[{index}]"
        value = value.get(key) if key and isinstance(value, dict) else \
            value[int(index)] if index.isdigit() and isinstance(value, list) else value
    table = _child(t, None)
    if m := re.fullmatch(r"Object contains unknown field `(.*)`", what):
        allowed = [f.encode_name for f in table.fields] if isinstance(table, mi.StructType) else []
        return unknown_key_message(name, m[1], f"{value.get(m[1])!r:.60}", allowed)
    if m := re.fullmatch(r"Object missing required field `(.*)`", what):
        field = next(f for f in table.fields if f.encode_name == m[1])  # type: ignore[union-attr]
        return f"{name}.{m[1]} is missing: expected {expected_text(field.type)}"
    if what.startswith("Invalid enum value"):
        c = _child(t, None)
        choices = [m.value for m in c.cls] if isinstance(c, mi.EnumType) else c.values  # type: ignore[attr-defined]
        close = difflib.get_close_matches(str(value), sorted(choices), n=1, cutoff=0.6)
        hint = f" (did you mean {close[0]!r}?)" if close else ""
        return f"{name} = {value!r}{hint}: expected {expected_text(t)}"
    if what.startswith("Expected `"):
        if isinstance(table, mi.StructType | mi.DictType):
            return f"{name} = {value!r:.60}: expected a table ([{name}])"
        # A string field with a pattern explains it when the text does not match, and when the
        # value is not text at all (file_mode = 600: say what the text looks like).
        explain = "matching regex" in what or ("Expected `str`" in what and "got `" in what)
        return f"{name} = {value!r}: expected {expected_text(t, explain)}"
    # A ValueError of a __post_init__ ("window = 40: expected ...") or of the dec_hook ("expected ...").
    return f"{name}.{what}" if isinstance(table, mi.StructType) else f"{name} = {value!r}: {what}"


def _child(t: mi.Type, key: str | None) -> mi.Type:
    """The type of ``t``'s field or item ``key`` (None: ``t`` itself without metadata and None)."""
    while isinstance(t, mi.Metadata | mi.UnionType):
        t = t.type if isinstance(t, mi.Metadata) else next(
            (u for u in t.types if isinstance(u, mi.StructType | mi.DictType | mi.ListType)),
            next(u for u in t.types if not isinstance(u, mi.NoneType)))
    if key is None:
        return t
    if isinstance(t, mi.StructType):
        return next(f.type for f in t.fields if f.encode_name == key)
    if isinstance(t, mi.DictType):
        return t.value_type
    return getattr(t, "item_type", t)
