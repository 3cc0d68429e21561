"""bridge.bench.common: list parsing, rounding, JSON, BLAS threads."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from bridge.bench.common import blas_threads, choices, markdown_table, numbers, round_sig, write_json
from hilbo_core.errors import ConfigError


def test_choices_parse_and_name_the_allowed_values() -> None:
    assert choices("b, a", ["a", "b", "c"], "function", ["a"]) == ["b", "a"]
    assert choices(None, ["a", "b"], "function", ["b"]) == ["b"]
    with pytest.raises(ConfigError, match=r"unknown function 'd'; choose from \['a', 'b'\]"):
        choices("a,d", ["a", "b"], "function", ["a"])
    with pytest.raises(ConfigError, match="given more than once"):
        choices("a,a", ["a"], "function", ["a"])
    with pytest.raises(ConfigError, match="no function given"):
        choices(" , ", ["a"], "function", ["a"])


def test_numbers_parse_positive_values_only() -> None:
    assert numbers("0.1,1, 10", "noise level", (1.0,)) == [0.1, 1.0, 10.0]
    assert numbers(None, "noise level", (0.5,)) == [0.5]
    for bad in ("1,-1", "0", "nan", "x"):
        with pytest.raises(ConfigError, match="noise level"):
            numbers(bad, "noise level", (1.0,))


def test_round_sig_rounds_nested_values_and_nulls_non_finite() -> None:
    data = {"a": [1.23456789, np.float64(2.0 / 3.0)], "b": math.nan, "c": np.arange(2), "d": "x"}
    assert round_sig(data, 3) == {"a": [1.23, 0.667], "b": None, "c": [0, 1], "d": "x"}


def test_write_json_is_complete_and_readable(tmp_path: Path) -> None:
    path = tmp_path / "sub" / "r.json"
    write_json(path, {"σ": [1, 2]})
    assert json.loads(path.read_text()) == {"σ": [1, 2]}
    assert not list(path.parent.glob("*.tmp"))


def test_markdown_table_shape() -> None:
    assert markdown_table(["a", "b"], [[1, 2]]) == "| a | b |\n|---|---|\n| 1 | 2 |\n"


def test_blas_threads_sets_and_restores() -> None:
    before = blas_threads(None)
    if not before:
        pytest.skip("no OpenBLAS loaded in this process")
    try:
        blas_threads(1)
        assert set(blas_threads(None).values()) == {1}
    finally:
        for n in set(before.values()):
            blas_threads(n)
    assert blas_threads(None) == before
