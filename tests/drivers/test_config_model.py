"""The one configuration model: msgspec Structs, decode() and its messages (key, value, range)."""

from __future__ import annotations

import enum
from dataclasses import dataclass
from typing import Annotated

import msgspec
import pytest
from msgspec import Meta

from drivers.config_model import FINITE, check_fields, decode, unknown_key_message


class Colour(enum.Enum):
    RED = "red"
    GREEN = "green"


class Demo(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    rate_hz: Annotated[float, Meta(gt=0.0, le=100.0)] = 10.0
    count: Annotated[int, Meta(ge=1, le=9)] = 3
    colour: Colour = Colour.RED
    enabled: bool = False
    label: Annotated[str, Meta(min_length=1)] = "x"
    timeout_s: Annotated[float, Meta(ge=0.0, le=FINITE)] | None = None
    names: list[str] = []

    def __post_init__(self) -> None:
        if self.timeout_s is not None and self.timeout_s > self.rate_hz:
            raise ValueError(f"timeout_s = {self.timeout_s:g}: expected at most rate_hz = {self.rate_hz:g}")


class Required(msgspec.Struct, forbid_unknown_fields=True):
    name: Annotated[str, Meta(min_length=1)]


class ConfigError(ValueError):
    pass


def _read(data: object, where: str = "demo") -> Demo:
    return decode(Demo, data, where, ConfigError)


def test_defaults_and_conversion() -> None:
    assert _read({}) == Demo()
    got = _read({"rate_hz": 5, "colour": "green", "enabled": True, "timeout_s": 2})
    assert got.rate_hz == 5.0 and isinstance(got.rate_hz, float)
    assert got.colour is Colour.GREEN and got.enabled and got.timeout_s == 2.0


def test_unknown_key_names_the_path_and_suggests() -> None:
    with pytest.raises(ConfigError, match=(
            r"^unknown key demo\.cuont = 4 \(did you mean 'count'\?\); "
            r"allowed keys in \[demo\]: colour, count, enabled, label, names, rate_hz, timeout_s$")):
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
    ({"timeout_s": float("inf")}, r"^demo\.timeout_s = inf: expected a finite number in \[0, inf\]$"),
    ({"count": 10}, r"^demo\.count = 10: expected an integer in \[1, 9\]$"),
    ({"count": 2.0}, r"^demo\.count = 2\.0: expected an integer in \[1, 9\]$"),
    ({"enabled": 1}, r"^demo\.enabled = 1: expected true or false$"),
    ({"label": ""}, r"^demo\.label = '': expected a non-empty string$"),
    ({"names": ["a", 5]}, r"^demo\.names = \['a', 5\]: expected a list of strings$"),
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


def test_a_check_between_fields_is_named_under_the_table() -> None:
    with pytest.raises(ConfigError, match=r"^demo\.timeout_s = 20: expected at most rate_hz = 10$"):
        _read({"timeout_s": 20})


def test_required_field_and_the_error_class() -> None:
    with pytest.raises(ConfigError, match=r"^req\.name is missing: expected a non-empty string$"):
        decode(Required, {}, "req", ConfigError)


def test_check_fields_for_post_init() -> None:
    @dataclass(frozen=True)
    class Built:
        count: Annotated[int, Meta(ge=1)] = 3
        colour: Colour = Colour.RED

        def __post_init__(self) -> None:
            check_fields(self, ConfigError)

    assert Built(colour="green").colour is Colour.GREEN  # type: ignore[arg-type]
    with pytest.raises(ConfigError, match=r"^count = 0: expected an integer in \[1, inf\]$"):
        Built(count=0)
