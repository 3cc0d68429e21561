"""Fault specs: the text syntax, catalog checks, and the run-time schedule."""

from __future__ import annotations

import math

import pytest
from hypothesis import given
from hypothesis import strategies as st

from virtual_hw.errors import FaultSpecError
from virtual_hw.faults import FaultCatalog, FaultKind, FaultSchedule, FaultShape, FaultSpec

CATALOG = FaultCatalog(
    "test device",
    (
        FaultKind("drop-heartbeat", FaultShape.WINDOW, "no heartbeat"),
        FaultKind("nack", FaultShape.EVENTS, "refuse a profile"),
    ),
)


@pytest.mark.parametrize(
    ("text", "expected"),
    [
        ("drop-heartbeat@120+10", FaultSpec("drop-heartbeat", 120.0, duration_s=10.0)),
        ("drop-heartbeat@0.5+.25", FaultSpec("drop-heartbeat", 0.5, duration_s=0.25)),
        ("nack@300x2", FaultSpec("nack", 300.0, count=2)),
        ("nack@300", FaultSpec("nack", 300.0, count=1)),
        ("nack@30+5", FaultSpec("nack", 30.0, duration_s=5.0)),
        (" nack@7 ", FaultSpec("nack", 7.0, count=1)),
        ("nack@1.5e3x4", FaultSpec("nack", 1500.0, count=4)),
    ],
)
def test_parse_reads_every_form(text: str, expected: FaultSpec) -> None:
    assert CATALOG.parse(text) == expected


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("drop-heartbeat@120", "lasts a while"),
        ("drop-heartbeat@120x3", "lasts a while"),
        ("bus-off@10+1", "no fault 'bus-off'"),
        ("nack@-1", "expected KIND@START"),
        ("nack@10+0", "duration_s"),
        ("nack@10x0", "count"),
        ("nack", "expected KIND@START"),
        ("nack@1e3y", "expected KIND@START"),
        ("Nack@1", "expected KIND@START"),
    ],
)
def test_parse_refuses_bad_specs_with_a_reason(text: str, match: str) -> None:
    with pytest.raises(FaultSpecError, match=match):
        CATALOG.parse(text)


def test_spec_validation_names_the_field() -> None:
    with pytest.raises(FaultSpecError, match="start_s"):
        FaultSpec("nack", math.nan)
    with pytest.raises(FaultSpecError, match="not both"):
        FaultSpec("nack", 1.0, duration_s=1.0, count=1)
    with pytest.raises(FaultSpecError, match="count"):
        FaultSpec("nack", 1.0, count=True)
    with pytest.raises(FaultSpecError, match="duplicate"):
        FaultCatalog("d", (FaultKind("a", FaultShape.EVENTS, ""), FaultKind("a", FaultShape.WINDOW, "")))
    with pytest.raises(FaultSpecError, match="shape"):
        FaultKind("a", "sometimes", "")  # type: ignore[arg-type]


@given(
    st.sampled_from(["drop-heartbeat", "nack"]),
    st.floats(min_value=0, max_value=1e6, allow_nan=False),
    st.floats(min_value=1e-3, max_value=1e4, allow_nan=False),
    st.integers(min_value=1, max_value=1000),
    st.booleans(),
)
def test_str_parses_back_to_the_same_spec(kind: str, start: float, dur: float, n: int, window: bool) -> None:
    spec = FaultSpec(kind, start, duration_s=dur) if window or kind == "drop-heartbeat" else FaultSpec(
        kind, start, count=n
    )
    assert CATALOG.parse(str(spec)) == spec


def test_window_is_half_open() -> None:
    spec = CATALOG.parse("drop-heartbeat@10+5")
    assert spec.end_s == 15.0
    assert [spec.covers(t) for t in (9.99, 10.0, 14.99, 15.0)] == [False, True, True, False]
    assert CATALOG.parse("nack@10x2").end_s is None


def test_schedule_hands_out_counted_events_in_start_order() -> None:
    sched = FaultSchedule(CATALOG, ["nack@20x1", "nack@10x2"])
    assert not sched.take("nack", 5.0)  # nothing started yet
    assert sched.left("nack") == 3
    assert [sched.take("nack", t) for t in (12.0, 13.0, 14.0)] == [True, True, False]
    assert sched.take("nack", 20.0)
    assert not sched.take("nack", 21.0)
    assert sched.taken["nack"] == 3 and sched.left("nack") == 0


def test_schedule_windows_and_boundaries() -> None:
    sched = FaultSchedule(CATALOG, ["drop-heartbeat@100+10", "nack@50+5", "nack@200x1"])
    assert sched.active("drop-heartbeat", 105.0) and not sched.active("drop-heartbeat", 110.0)
    assert sched.take("nack", 52.0) and sched.take("nack", 54.9) and not sched.take("nack", 55.0)
    assert sched.left("nack") == 1  # the window took none of the counted event
    boundaries = [sched.next_boundary(t) for t in (0.0, 50.0, 55.0, 105.0, 200.0)]
    assert boundaries == [50.0, 55.0, 100.0, 110.0, None]
    with pytest.raises(FaultSpecError, match="no fault"):
        sched.active("bus-off", 1.0)


def test_describe_lists_every_kind_with_its_form() -> None:
    text = CATALOG.describe()
    assert "drop-heartbeat (+DURATION)" in text and "nack (xCOUNT or +DURATION)" in text
