"""BreathValidator re-anchoring: a cart clock reset or forward jump costs a few breaths, not the
session; a single absurd breath time costs only itself (a cart restart used to pause a session for good)."""

from __future__ import annotations

import itertools
import math
import statistics

import pytest
from hypothesis import assume, given
from hypothesis import strategies as st

from drivers.cart.reasons import ReanchorKind, RejectReason
from drivers.cart.validate import (
    DEFAULT_CONFIRM_BREATHS,
    DEFAULT_MAX_TIME_JUMP_S,
    BreathValidator,
    Reanchor,
)
from drivers.errors import DriverConfigError
from hilbo_core.types import BreathRecord

pytestmark = pytest.mark.timeout(60)

CONFIRM = DEFAULT_CONFIRM_BREATHS
JUMP_S = DEFAULT_MAX_TIME_JUMP_S


def breath(t_s: float) -> BreathRecord:
    return BreathRecord(t_s, 1000.0, 850.0)


def run(v: BreathValidator, times: list[float], seqs: list[int | None] | None = None) -> list[float | None]:
    seqs = seqs if seqs is not None else [None] * len(times)
    out = [v.check(breath(t), seq=s) for t, s in zip(times, seqs, strict=True)]
    return [None if r is None else r.t_s for r in out]


# --- reference sequences -------------------------------------------------------------------------


def test_defaults_are_five_minutes_and_two_breaths() -> None:
    assert (JUMP_S, CONFIRM) == (300.0, 2)


def test_cart_restart_reanchors_after_two_confirming_breaths() -> None:
    v = BreathValidator()
    before = [3.0 * k for k in range(101)]  # 0 .. 300 s, one breath every 3 s
    assert run(v, before) == before
    # The cart restarts: its clock starts again near 0.
    after = run(v, [0.5, 3.5, 6.5, 9.5, 12.5])
    # 0.5 and 3.5 are held (rejected) until 6.5 confirms the new clock; 0.5 lands one typical
    # interval (3 s) after the last accepted 300 s, so the offset is 302.5 s.
    assert after == [None, None, 309.0, 312.0, 315.0]
    assert v.counters == {RejectReason.OUT_OF_ORDER: 2}
    assert v.reanchors == 1 and v.reanchor_counts == {ReanchorKind.CLOCK_RESET: 1}
    assert v.last_reanchor == Reanchor(ReanchorKind.CLOCK_RESET, 1, 0.5, 303.0, 302.5, 2)
    assert v.offset_s == 302.5 and v.pending == 0
    assert v.accepted == 101 + 3


def test_cart_restart_with_its_sequence_numbers_restarting() -> None:
    v = BreathValidator()
    assert run(v, [100.0 + 3 * k for k in range(10)], list(range(10))) == [
        100.0 + 3 * k for k in range(10)
    ]
    # The restarted cart counts from 0 again: seq 0 and 1 are still in the duplicate memory.
    assert run(v, [1.0, 4.0, 7.0, 10.0], [0, 1, 2, 3]) == [None, None, 136.0, 139.0]
    assert v.counters == {RejectReason.DUPLICATE: 2}
    assert (v.missing_seq, v.seq_resets, v.reanchors) == (0, 0, 1)


def test_forward_clock_jump_reanchors_and_session_time_goes_on() -> None:
    v = BreathValidator()
    assert run(v, [0.0, 3.0, 6.0, 9.0]) == [0.0, 3.0, 6.0, 9.0]
    assert run(v, [86_400.0, 86_403.0, 86_406.0, 86_409.0]) == [None, None, 18.0, 21.0]
    assert v.counters == {RejectReason.TIME_JUMP: 2}
    assert v.reanchor_counts == {ReanchorKind.TIME_JUMP: 1}
    assert v.last_reanchor is not None and v.last_reanchor.offset_s == 12.0 - 86_400.0


def test_gap_shorter_than_the_threshold_is_not_a_jump() -> None:
    v = BreathValidator(max_time_jump_s=60.0)
    assert run(v, [0.0, 3.0, 63.0, 66.0]) == [0.0, 3.0, 63.0, 66.0]
    assert run(v, [127.0, 130.0, 133.0]) == [None, None, 75.0]  # 61 s > 60 s: a jump
    assert v.reanchors == 1


@pytest.mark.parametrize("bad_t", [1e9, 277.0 + 300.001, 0.0, 50.0, 276.999])
def test_a_single_absurd_breath_time_costs_only_that_breath(bad_t: float) -> None:
    v = BreathValidator()
    good = [3.0 * k + 100.0 for k in range(101)]  # 100 .. 400 s
    times = [*good[:60], bad_t, *good[60:]]
    out = run(v, times)
    assert out == [*good[:60], None, *good[60:]]
    assert v.rejected == 1 and v.reanchors == 0 and v.offset_s == 0.0


def test_a_bad_time_less_than_the_threshold_ahead_is_a_gap_then_a_reanchor() -> None:
    # Known limit: 120 s ahead is a plausible gap when it arrives, so it is accepted; the good
    # breaths after it then re-anchor like a reset (CONFIRM breaths lost, the session goes on).
    v = BreathValidator()
    out = run(v, [100.0, 103.0, 106.0, 226.0, 109.0, 112.0, 115.0, 118.0])
    assert out == [100.0, 103.0, 106.0, 226.0, None, None, 235.0, 238.0]
    assert v.reanchor_counts == {ReanchorKind.CLOCK_RESET: 1}


def test_two_absurd_breaths_in_a_row_still_cost_only_themselves() -> None:
    v = BreathValidator()
    good = [3.0 * k for k in range(20)]
    out = run(v, [*good[:10], 5000000.0, 5000000.0 + 3.0, *good[10:]])
    assert out == [*good[:10], None, None, *good[10:]]
    assert v.counters == {RejectReason.TIME_JUMP: 2} and v.reanchors == 0


def test_good_breaths_come_back_unchanged_before_any_reanchor() -> None:
    v = BreathValidator()
    rec = breath(5.0)
    assert v.check(rec) is rec


def test_a_late_breath_then_the_old_clock_cancels_the_pending_reset() -> None:
    v = BreathValidator()
    assert run(v, [100.0, 103.0, 106.0]) == [100.0, 103.0, 106.0]
    # 95 and 98 would continue each other, but 109 fits the old clock: no re-anchor.
    assert run(v, [95.0, 98.0, 109.0, 112.0]) == [None, None, 109.0, 112.0]
    assert v.counters == {RejectReason.OUT_OF_ORDER: 2} and v.reanchors == 0


def test_two_resets_in_one_session_stay_monotonic() -> None:
    v = BreathValidator()
    out = run(v, [10.0, 13.0, 16.0, 0.0, 3.0, 6.0, 9.0, 1.0, 4.0, 7.0, 10.0])
    assert out == [10.0, 13.0, 16.0, None, None, 25.0, 28.0, None, None, 37.0, 40.0]
    assert v.reanchors == 2 and v.last_reanchor is not None and v.last_reanchor.index == 2


def test_explicit_reset_reanchors_at_once() -> None:
    v = BreathValidator()
    run(v, [50.0, 53.0, 56.0])
    v.reset()
    assert run(v, [0.0, 3.0]) == [59.0, 62.0]
    assert v.reanchor_counts == {ReanchorKind.RESET: 1} and v.rejected == 0


def test_reset_before_any_breath_is_a_no_op() -> None:
    v = BreathValidator()
    v.reset()
    assert run(v, [7.0]) == [7.0] and v.reanchors == 0


def test_first_breath_absurd_then_the_real_clock() -> None:
    v = BreathValidator()
    out = run(v, [9e6, 1.0, 4.0, 7.0, 10.0])
    # The absurd first breath was accepted (nothing to compare it with); the real clock is
    # confirmed after two breaths and continues after it instead of being rejected for good.
    assert out[0] == 9e6 and out[1:3] == [None, None]
    assert out[3] is not None and out[4] is not None and 9e6 < out[3] < out[4]
    assert v.reanchors == 1


def test_a_breath_on_the_new_clock_repeated_is_a_duplicate() -> None:
    v = BreathValidator()
    run(v, [100.0, 103.0, 106.0, 0.0, 3.0, 6.0])
    assert run(v, [3.0, 9.0]) == [None, 118.0]
    assert v.counters[RejectReason.DUPLICATE] == 1


def test_reanchor_is_logged_as_a_warning(caplog: pytest.LogCaptureFixture) -> None:
    v = BreathValidator()
    with caplog.at_level("WARNING", logger="drivers.cart.validate"):
        run(v, [100.0, 103.0, 106.0, 0.0, 3.0, 6.0])
    assert any("clock_reset" in r.getMessage() and "re-anchored" in r.getMessage() for r in caplog.records)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"confirm_breaths": 0}, "confirm_breaths = 0: expected an integer >= 1"),
        ({"confirm_breaths": True}, "confirm_breaths = True"),
        ({"max_time_jump_s": 0.0}, r"max_time_jump_s = 0.0: expected a finite number of seconds > 0"),
        ({"max_time_jump_s": math.inf}, "max_time_jump_s = inf"),
        ({"max_time_jump_s": -1.0}, "max_time_jump_s"),
        ({"max_time_jump_s": "5 min"}, "max_time_jump_s"),
    ],
)
def test_bad_settings_name_the_value(kwargs: dict[str, object], match: str) -> None:
    with pytest.raises(DriverConfigError, match=match):
        BreathValidator(**kwargs)  # type: ignore[arg-type]


# --- properties ----------------------------------------------------------------------------------

intervals = st.floats(0.5, 8.0)


@st.composite
def good_with_outliers(draw: st.DrawFn) -> tuple[list[float], list[bool]]:
    """Increasing good times with runs of at most CONFIRM absurd ones among them."""
    start = draw(st.floats(0.0, 1e4))
    steps = draw(st.lists(intervals, min_size=1, max_size=40))
    good = list(itertools.accumulate(steps, initial=start))
    times: list[float] = []
    is_good: list[bool] = []
    for k, t in enumerate(good):
        if k > 0:
            for _ in range(draw(st.integers(0, CONFIRM))):
                prev = good[k - 1]
                ahead = st.floats(prev + JUMP_S + 1e-3, 1e8)
                bad = draw(ahead | st.floats(0.0, prev, exclude_max=True) if prev > 0.0 else ahead)
                times.append(bad)
                is_good.append(False)
        times.append(t)
        is_good.append(True)
    return times, is_good


@given(good_with_outliers())
def test_isolated_bad_times_cost_only_themselves(case: tuple[list[float], list[bool]]) -> None:
    times, is_good = case
    assume(len(set(times)) == len(times))  # an exact repeat of a good time is a duplicate
    v = BreathValidator()
    records = [breath(t) for t in times]
    out = [v.check(r) for r in records]
    for rec, got, ok in zip(records, out, is_good, strict=True):
        assert (got is rec) if ok else (got is None)
    assert v.reanchors == 0 and v.rejected == is_good.count(False)


@st.composite
def clock_segments(draw: st.DrawFn) -> list[list[float]]:
    """Runs of breaths on successive cart clocks, each one a reset or a forward jump."""
    segments: list[list[float]] = []
    for k in range(draw(st.integers(1, 5))):
        steps = draw(st.lists(intervals, min_size=CONFIRM, max_size=15))
        if k == 0:
            start = draw(st.floats(0.0, 1e4))
        elif draw(st.booleans()):  # the cart restarted: its clock begins again near 0
            start = draw(st.floats(0.0, 20.0))
            assume(start < segments[-1][-1])
        else:
            start = segments[-1][-1] + JUMP_S + draw(st.floats(1e-3, 1e6))
        seg = list(itertools.accumulate(steps, initial=start))
        if k > 0 and start < segments[-1][-1]:
            # A reset must stay behind the old clock until it is confirmed, or it is not one.
            assume(seg[CONFIRM] < segments[-1][-1])
            assume(not set(seg[: CONFIRM + 1]) & set(segments[-1]))
        segments.append(seg)
    return segments


@given(clock_segments())
def test_every_clock_change_reanchors_and_session_time_increases(segments: list[list[float]]) -> None:
    v = BreathValidator()
    out_by_segment = [run(v, seg) for seg in segments]
    out = [t for seg in out_by_segment for t in seg if t is not None]
    assert all(b > a for a, b in itertools.pairwise(out))
    assert v.reanchors == len(segments) - 1
    assert v.accepted == sum(len(s) for s in segments) - CONFIRM * (len(segments) - 1)
    assert v.accepted + v.rejected == sum(len(s) for s in segments)
    for k, (seg, got) in enumerate(zip(segments, out_by_segment, strict=True)):
        lost = 0 if k == 0 else CONFIRM
        assert got[:lost] == [None] * lost and None not in got[lost:]
        # Within one clock the intervals between breaths are kept exactly (up to rounding).
        for (a, b), (sa, sb) in zip(
            itertools.pairwise(seg[lost:]), itertools.pairwise(got[lost:]), strict=True
        ):
            assert sb - sa == pytest.approx(b - a, rel=1e-9, abs=1e-6)  # type: ignore[operator]
        if k > 0:
            # The new clock's first breath lands one typical interval after the last accepted.
            prev_seg, prev_out = segments[k - 1], out_by_segment[k - 1]
            typical = statistics.median([b - a for a, b in itertools.pairwise(prev_seg)][-16:])
            expected = prev_out[-1] + typical + (seg[CONFIRM] - seg[0])  # type: ignore[operator]
            assert got[CONFIRM] == pytest.approx(expected, rel=1e-9, abs=1e-6)


@given(
    st.lists(
        st.tuples(st.floats(0.0, 2e3) | st.floats(0.0, 1e9), st.none() | st.integers(0, 50)),
        max_size=80,
    )
)
def test_any_stream_gets_increasing_session_times_and_exact_accounting(
    items: list[tuple[float, int | None]],
) -> None:
    v = BreathValidator()
    out = [v.check(breath(t), seq=s) for t, s in items]
    times = [r.t_s for r in out if r is not None]
    assert all(b > a for a, b in itertools.pairwise(times))
    assert v.accepted + v.rejected == len(items)
    assert v.reanchors <= v.accepted and v.pending <= CONFIRM
