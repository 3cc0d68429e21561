"""The bus-budget analysis of drivers/PROTOCOL.md: reference values and invariants."""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from drivers.exosuit.busload import budget_table, segment_response
from drivers.exosuit.endpoint import DEFAULT_PACE_S


def test_the_critical_instant_of_protocol_md() -> None:
    # No jitter, 2 ms: w = 770·ceil(w/1000) + 315 = 1855 µs, plus the segment's 135 µs.
    r = segment_response(2000, 0)
    assert (r.busy_period_us, r.instances, r.response_us) == (1990, 1, 1990)
    assert r.assistance_off_us == 1990 + 135 + 65
    assert r.utilisation == pytest.approx(0.78575 + 135 / 2000)  # 85.3 %


def test_the_default_pace_keeps_an_assistance_off_within_3_ms() -> None:
    r = segment_response(round(DEFAULT_PACE_S * 1e6))
    assert (r.pace_us, r.jitter_us) == (1000, 500)
    # By hand: t = 135·ceil((t + 500)/1000) + 770·ceil(t/1000) + 315 converges at 4975 µs with 6
    # segments (1220, 2125, 3030, 3935, 4070, 4840, 4975).
    assert (r.busy_period_us, r.instances, r.response_us, r.assistance_off_us) == (4975, 6, 2490, 2690)
    # ...no worse than the 1.5 ms default before it, nor 2 ms pacing with its catch-up rule.
    assert r.assistance_off_us <= segment_response(1500).assistance_off_us == 2940
    assert r.assistance_off_us <= segment_response(2000).assistance_off_us == 3190
    # The bus stays schedulable during a push: 92.0 % worst case.
    assert r.utilisation == pytest.approx(0.78575 + 135 / 1000)


def test_a_pace_that_saturates_the_bus_is_refused() -> None:
    with pytest.raises(ValueError, match=r"pace_us=500: bus load 105\.6%"):
        segment_response(500)


@given(st.integers(min_value=700, max_value=20000))
def test_the_response_covers_the_segment_and_the_busy_period_holds_it(pace_us: int) -> None:
    r = segment_response(pace_us)
    assert r.response_us >= 135 and r.busy_period_us >= 135 and r.instances >= 1
    assert r.assistance_off_us == r.response_us + 200
    assert 0.78 < r.utilisation < 1.0


def test_the_table_has_a_row_per_pace() -> None:
    lines = budget_table().splitlines()
    assert len(lines) == 2 + 4 and lines[4].startswith("| 1.5 ms | 0.75 ms | 3.935 ms | 4 | 2.74 ms")
