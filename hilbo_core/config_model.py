"""One configuration model: typed tables, declared ranges, unknown keys refused with a suggestion.

Config tables come from TOML, so values arrive as ``str``, ``int``, ``float``, ``bool``, lists
and tables. A config table is a frozen dataclass whose fields declare what they accept
(:func:`number`, :func:`integer`, :func:`choice`, :func:`boolean`, :func:`string`); the one
loader, :func:`read_fields` over a :class:`Table`, converts a TOML table into the dataclass's
keyword arguments. Every error names the full key path (``protocol.max_breaths``), the offending
value and what was expected; an unknown key also gets the closest allowed key
(``unknown key protocol.max_breath = 50 (did you mean 'max_breaths'?); allowed keys in
[protocol]: ...``). Each package passes its own exception class (its error root's config error),
so the bridge raises ``BridgeConfigError`` and the drivers ``DriverConfigError``.

Pure: no I/O. A range check between several fields (``window < max_breaths``) stays with the
table that has both.
"""

from __future__ import annotations

import dataclasses
import difflib
import enum
import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Any

from hilbo_core.errors import ConfigError

__all__ = [
    "MISSING",
    "FieldSpec",
    "Table",
    "boolean",
    "check_fields",
    "check_integer",
    "check_number",
    "choice",
    "integer",
    "number",
    "range_text",
    "read_fields",
    "reject_unknown",
    "string",
    "unknown_key_message",
]

#: A required key's "default".
MISSING: Any = object()

_ErrorType = type[Exception]


def unknown_key_message(where: str, key: str, value_text: str, allowed: Iterable[str]) -> str:
    """The message for an unknown key (or, with ``where`` empty, an unknown top-level table).

    Args:
        where: The table's path (``protocol``, ``cart.options.backoff``), or ``""`` for the
            document's top level.
        key: The unknown key.
        value_text: Its value as it should be shown (already shortened).
        allowed: The keys the table allows.
    """
    allowed = sorted(allowed)
    close = difflib.get_close_matches(key, allowed, n=1, cutoff=0.6)
    if not where:
        hint = f" (did you mean [{close[0]}]?)" if close else ""
        return f"unknown table [{key}]{hint}; allowed tables: {', '.join(allowed)}"
    hint = f" (did you mean {close[0]!r}?)" if close else ""
    return (f"unknown key {where}.{key} = {value_text}{hint}; "
            f"allowed keys in [{where}]: {', '.join(allowed) or '(none)'}")


def reject_unknown(data: Mapping[str, Any], allowed: Iterable[str], where: str,
                   error: _ErrorType = ConfigError) -> None:
    """Raise ``error`` naming the first key of ``data`` that is not in ``allowed``."""
    allowed = tuple(allowed)
    for key, value in data.items():
        if key not in allowed:
            raise error(unknown_key_message(where, key, f"{value!r:.60}", allowed))


def range_text(lo: float | None, hi: float | None, lo_open: bool = False) -> str:
    """``[lo, hi]`` (``(lo, hi]`` if ``lo_open``), open ends as ``-inf`` and ``inf``."""
    lo_s = "-inf" if lo is None else str(lo) if isinstance(lo, int) else f"{lo:g}"
    hi_s = "inf" if hi is None else str(hi) if isinstance(hi, int) else f"{hi:g}"
    return f"{'(' if lo_open else '['}{lo_s}, {hi_s}]"


def check_number(value: object, name: str, *, lo: float | None = None, hi: float | None = None,
                 lo_open: bool = False, error: _ErrorType = ConfigError) -> float:
    """Return ``value`` as a finite float within ``[lo, hi]`` (``(lo, hi]`` if ``lo_open``)."""
    expected = f"a finite number in {range_text(lo, hi, lo_open)}"
    # bool is an int subclass in Python; `true` for a timeout is a mistake, not 1.
    ok = not isinstance(value, bool) and isinstance(value, int | float)
    out = float(value) if ok else math.nan  # type: ignore[arg-type]
    if (not ok or not math.isfinite(out) or (lo is not None and (out <= lo if lo_open else out < lo))
            or (hi is not None and out > hi)):
        raise error(f"{name} = {value!r}: expected {expected}")
    return out


def check_integer(value: object, name: str, *, lo: int | None = None, hi: int | None = None,
                  error: _ErrorType = ConfigError) -> int:
    """Return ``value`` if it is an int (not a bool) within ``[lo, hi]``."""
    if (isinstance(value, bool) or not isinstance(value, int) or (lo is not None and value < lo)
            or (hi is not None and value > hi)):
        raise error(f"{name} = {value!r}: expected an integer in {range_text(lo, hi)}")
    return value


def _check_string(value: object, name: str, *, choices: Iterable[str] | None, non_empty: bool,
                  error: _ErrorType) -> str:
    options = sorted(choices) if choices is not None else None
    expected = (f"one of {', '.join(repr(c) for c in options)}" if options is not None
                else "a non-empty string" if non_empty else "a string")
    if not isinstance(value, str) or (non_empty and not value):
        raise error(f"{name} = {value!r}: expected {expected}")
    if options is not None and value not in options:
        close = difflib.get_close_matches(value, options, n=1, cutoff=0.6)
        hint = f" (did you mean {close[0]!r}?)" if close else ""
        raise error(f"{name} = {value!r}{hint}: expected {expected}")
    return value


# --------------------------------------------------------------------------------------------
# Declarations: what a dataclass field accepts
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class FieldSpec:
    """What one config field accepts (kept in the dataclass field's ``metadata["config"]``).

    Attributes:
        kind: ``number``, ``integer``, ``choice``, ``boolean`` or ``string``.
        lo: Lower bound (numbers and integers), or None.
        hi: Upper bound, or None.
        lo_open: The lower bound is excluded.
        optional: None is allowed (a switched-off option); a key that is absent keeps the default.
        enum_cls: The enum of a ``choice``.
        non_empty: A ``string`` must not be empty.
    """

    kind: str
    lo: float | None = None
    hi: float | None = None
    lo_open: bool = False
    optional: bool = False
    enum_cls: type[enum.Enum] | None = None
    non_empty: bool = True

    def check(self, value: object, name: str, error: _ErrorType = ConfigError) -> Any:
        """Return ``value`` converted (a float, an enum member) or raise ``error`` naming ``name``."""
        if value is None and self.optional:
            return None
        if self.kind == "number":
            return check_number(value, name, lo=self.lo, hi=self.hi, lo_open=self.lo_open, error=error)
        if self.kind == "integer":
            return check_integer(value, name, lo=self.lo, hi=self.hi, error=error)  # type: ignore[arg-type]
        if self.kind == "boolean":
            if not isinstance(value, bool):
                raise error(f"{name} = {value!r}: expected true or false")
            return value
        if self.kind == "choice":
            enum_cls = self.enum_cls
            if enum_cls is None:  # a declaration mistake in code, not a config mistake
                raise TypeError(f"{name}: a choice field needs its enum class")
            if isinstance(value, enum_cls):
                return value
            values = [m.value for m in enum_cls]
            return enum_cls(_check_string(value, name, choices=values, non_empty=True, error=error))
        return _check_string(value, name, choices=None, non_empty=self.non_empty, error=error)


def _field(default: Any, spec: FieldSpec) -> Any:
    if default is MISSING:
        return dataclasses.field(metadata={"config": spec})
    return dataclasses.field(default=default, metadata={"config": spec})


def number(default: Any = MISSING, *, lo: float | None = None, hi: float | None = None,
           lo_open: bool = False, optional: bool = False) -> Any:
    """A finite float field within ``[lo, hi]`` (``(lo, hi]`` if ``lo_open``); None if ``optional``."""
    return _field(default, FieldSpec("number", lo, hi, lo_open, optional))


def integer(default: Any = MISSING, *, lo: int | None = None, hi: int | None = None,
            optional: bool = False) -> Any:
    """An int field (not a bool) within ``[lo, hi]``; None if ``optional``."""
    return _field(default, FieldSpec("integer", lo, hi, False, optional))


def choice(enum_cls: type[enum.Enum], default: Any = MISSING) -> Any:
    """An enum field, given in TOML by the member's value (errors list the values)."""
    return _field(default, FieldSpec("choice", enum_cls=enum_cls))


def boolean(default: Any = MISSING, *, optional: bool = False) -> Any:
    """A ``true``/``false`` field; None if ``optional`` (absent: a default decided elsewhere)."""
    return _field(default, FieldSpec("boolean", optional=optional))


def string(default: Any = MISSING, *, non_empty: bool = True, optional: bool = False) -> Any:
    """A string field (non-empty unless told otherwise); None if ``optional``."""
    return _field(default, FieldSpec("string", optional=optional, non_empty=non_empty))


def _specs(cls: type[Any]) -> list[tuple[dataclasses.Field[Any], FieldSpec]]:
    return [(f, f.metadata["config"]) for f in dataclasses.fields(cls) if "config" in f.metadata]


def check_fields(obj: Any, where: str = "", error: _ErrorType = ConfigError) -> None:
    """Check (and convert in place) every declared field of a frozen dataclass instance.

    For a ``__post_init__``: the dataclass may be built in code as well as from TOML, and both
    get the same checks. Numbers become floats, enum values become members.

    Args:
        obj: The instance.
        where: Prefix of the names in errors (``""``: the bare field name).
        error: The exception class to raise.
    """
    for f, spec in _specs(type(obj)):
        name = f"{where}.{f.name}" if where else f.name
        value = spec.check(getattr(obj, f.name), name, error)
        object.__setattr__(obj, f.name, value)


# --------------------------------------------------------------------------------------------
# Reading a TOML table
# --------------------------------------------------------------------------------------------


class Table:
    """One config table: refuses unknown keys at once, then reads typed, range-checked values.

    Args:
        data: The TOML table.
        where: Its path (``protocol``, ``space.parameters[0]``).
        allowed: The keys it may have.
        error: The exception class to raise.
    """

    def __init__(self, data: object, where: str, allowed: Iterable[str],
                 error: _ErrorType = ConfigError) -> None:
        if not isinstance(data, Mapping):
            raise error(f"{where} = {data!r:.60}: expected a table ([{where}])")
        self.where = where
        self.data: Mapping[str, Any] = data
        self.error = error
        reject_unknown(data, allowed, where, error)

    def name(self, key: str) -> str:
        """The key's full path."""
        return f"{self.where}.{key}"

    def has(self, key: str) -> bool:
        """Whether the table gives ``key``."""
        return key in self.data

    def raw(self, key: str, default: Any, expected: str) -> Any:
        """The value as given, ``default`` if absent (missing and required: an error)."""
        if key in self.data:
            return self.data[key]
        if default is MISSING:
            raise self.error(f"{self.name(key)} is missing: expected {expected}")
        return default

    def number(self, key: str, default: Any = MISSING, *, lo: float | None = None,
               hi: float | None = None, lo_open: bool = False) -> float:
        """A finite float within the range."""
        value = self.raw(key, default, f"a finite number in {range_text(lo, hi, lo_open)}")
        return check_number(value, self.name(key), lo=lo, hi=hi, lo_open=lo_open, error=self.error)

    def integer(self, key: str, default: Any = MISSING, *, lo: int | None = None,
                hi: int | None = None) -> int:
        """An int within the range."""
        value = self.raw(key, default, f"an integer in {range_text(lo, hi)}")
        return check_integer(value, self.name(key), lo=lo, hi=hi, error=self.error)

    def string(self, key: str, default: Any = MISSING, *, choices: Iterable[str] | None = None,
               non_empty: bool = True) -> str:
        """A string, one of ``choices`` if given (with a suggestion for a near miss)."""
        options = sorted(choices) if choices is not None else None
        expected = (f"one of {', '.join(repr(c) for c in options)}" if options is not None
                    else "a non-empty string" if non_empty else "a string")
        value = self.raw(key, default, expected)
        return _check_string(value, self.name(key), choices=options, non_empty=non_empty,
                             error=self.error)

    def boolean(self, key: str, default: Any = MISSING) -> bool:
        """``true`` or ``false``."""
        return FieldSpec("boolean").check(self.raw(key, default, "true or false"), self.name(key),
                                          self.error)

    def choice(self, key: str, enum_cls: type[enum.Enum], default: Any = MISSING) -> Any:
        """An enum member, given by its value."""
        values = [m.value for m in enum_cls]
        raw = self.string(key, default.value if isinstance(default, enum.Enum) else default,
                          choices=values)
        return enum_cls(raw)

    def strings(self, key: str, default: Any = MISSING) -> tuple[str, ...]:
        """A list of strings."""
        value = self.raw(key, default, "a list of strings")
        if not isinstance(value, list | tuple) or not all(isinstance(v, str) for v in value):
            raise self.error(f"{self.name(key)} = {value!r:.80}: expected a list of strings")
        return tuple(value)

    def table(self, key: str, default: Any = MISSING) -> Mapping[str, Any]:
        """A sub-table (as a mapping; wrap it in a :class:`Table` to read it)."""
        value = self.raw(key, default, "a table")
        if not isinstance(value, Mapping):
            raise self.error(f"{self.name(key)} = {value!r:.60}: expected a table ([{self.name(key)}])")
        return value


def read_fields(cls: type[Any], t: Table, *, skip: Iterable[str] = ()) -> dict[str, Any]:
    """The keyword arguments of dataclass ``cls`` that ``t`` gives, by the fields' declarations.

    A declared field that the table does not give takes its default (a field without one is
    required: its absence is an error naming the key). Fields in ``skip`` are left to the
    caller (cross-field checks, nested tables).

    Returns:
        ``{field name: converted value}`` for every declared field not skipped.
    """
    skipped = set(skip)
    out: dict[str, Any] = {}
    for f, spec in _specs(cls):
        if f.name in skipped:
            continue
        if not t.has(f.name):
            if f.default is dataclasses.MISSING:
                raise t.error(f"{t.name(f.name)} is missing: expected {_expected(spec)}")
            out[f.name] = f.default
            continue
        out[f.name] = spec.check(t.data[f.name], t.name(f.name), t.error)
    return out


def _expected(spec: FieldSpec) -> str:
    if spec.kind == "number":
        return f"a finite number in {range_text(spec.lo, spec.hi, spec.lo_open)}"
    if spec.kind == "integer":
        return f"an integer in {range_text(spec.lo, spec.hi)}"
    if spec.kind == "boolean":
        return "true or false"
    if spec.kind == "choice" and spec.enum_cls is not None:
        return "one of " + ", ".join(repr(v) for v in sorted(m.value for m in spec.enum_cls))
    return "a non-empty string" if spec.non_empty else "a string"
