"""The one configuration model: declared fields, the table loader and its messages."""

from __future__ import annotations

import enum
from dataclasses import dataclass

import pytest

from hilbo_core.config_model import (
    Table,
    boolean,
    check_fields,
    choice,
    integer,
    number,
    read_fields,
    string,
    unknown_key_message,
)
from hilbo_core.errors import ConfigError


class Colour(enum.Enum):
    RED = "red"
    GREEN = "green"


@dataclass(frozen=True)
class Demo:
    rate_hz: float = number(10.0, lo=0.0, hi=100.0, lo_open=True)
    count: int = integer(3, lo=1, hi=9)
    colour: Colour = choice(Colour, Colour.RED)
    enabled: bool = boolean(False)
    label: str = string("x")
    timeout_s: float | None = number(None, lo=0.0, optional=True)


@dataclass(frozen=True)
class Required:
    name: str = string()


def _read(data: object, where: str = "demo") -> Demo:
    fields = [f for f in Demo.__dataclass_fields__]
    return Demo(**read_fields(Demo, Table(data, where, fields)))


def test_defaults_and_conversion() -> None:
    assert _read({}) == Demo()
    got = _read({"rate_hz": 5, "colour": "green", "enabled": True, "timeout_s": 2})
    assert got.rate_hz == 5.0 and isinstance(got.rate_hz, float)
    assert got.colour is Colour.GREEN and got.enabled and got.timeout_s == 2.0


def test_unknown_key_names_the_path_and_suggests() -> None:
    with pytest.raises(ConfigError, match=(
            r"^unknown key demo\.cuont = 4 \(did you mean 'count'\?\); "
            r"allowed keys in \[demo\]: colour, count, enabled, label, rate_hz, timeout_s$")):
        _read({"cuont": 4})
    with pytest.raises(ConfigError) as info:
        _read({"zzz": 1})
    assert "did you mean" not in str(info.value)


def test_unknown_table_message() -> None:
    assert unknown_key_message("", "sesion", "{}", ["session", "space"]) == (
        "unknown table [sesion] (did you mean [session]?); allowed tables: session, space")


@pytest.mark.parametrize(("data", "match"), [
    ({"rate_hz": "fast"}, r"^demo\.rate_hz = 'fast': expected a finite number in \(0, 100\]$"),
    ({"rate_hz": True}, r"^demo\.rate_hz = True: expected a finite number"),
    ({"rate_hz": 0.0}, r"^demo\.rate_hz = 0\.0: expected a finite number in \(0, 100\]$"),
    ({"rate_hz": float("nan")}, r"^demo\.rate_hz = nan: expected a finite number"),
    ({"count": 10}, r"^demo\.count = 10: expected an integer in \[1, 9\]$"),
    ({"count": 2.0}, r"^demo\.count = 2\.0: expected an integer in \[1, 9\]$"),
    ({"enabled": 1}, r"^demo\.enabled = 1: expected true or false$"),
    ({"label": ""}, r"^demo\.label = '': expected a non-empty string$"),
])
def test_wrong_type_or_range_names_key_value_and_expected(data: dict[str, object], match: str) -> None:
    with pytest.raises(ConfigError, match=match):
        _read(data)


def test_enum_choice_lists_the_choices_and_suggests() -> None:
    with pytest.raises(ConfigError, match=(
            r"^demo\.colour = 'gren' \(did you mean 'green'\?\): expected one of 'green', 'red'$")):
        _read({"colour": "gren"})


def test_nested_table_path_in_messages() -> None:
    with pytest.raises(ConfigError, match=r"^a\.b\[2\]\.count = 0: expected an integer"):
        _read({"count": 0}, "a.b[2]")
    with pytest.raises(ConfigError, match=r"^unknown key a\.b\.x = 1; allowed keys in \[a\.b\]"):
        _read({"x": 1}, "a.b")
    with pytest.raises(ConfigError, match=r"^a\.b = 3: expected a table \(\[a\.b\]\)$"):
        _read(3, "a.b")


def test_required_field_and_the_error_class() -> None:
    class OwnError(ValueError):
        pass

    with pytest.raises(OwnError, match=r"^req\.name is missing: expected a non-empty string$"):
        read_fields(Required, Table({}, "req", ["name"], OwnError))


def test_check_fields_for_post_init() -> None:
    @dataclass(frozen=True)
    class Built:
        count: int = integer(3, lo=1)
        colour: Colour = choice(Colour, Colour.RED)

        def __post_init__(self) -> None:
            check_fields(self)

    assert Built(colour="green").colour is Colour.GREEN  # type: ignore[arg-type]
    with pytest.raises(ConfigError, match=r"^count = 0: expected an integer in \[1, inf\]$"):
        Built(count=0)
