"""BreathValidator: every reject reason, counting, sequence bookkeeping, limits from config."""

from __future__ import annotations

import math

import pytest
from hypothesis import given
from hypothesis import strategies as st

from drivers.cart.reasons import RejectReason
from drivers.cart.validate import BreathValidator, PhysioLimits
from drivers.errors import DriverConfigError
from hilbo_core.types import BreathRecord

pytestmark = pytest.mark.timeout(30)


def breath(t_s: float, vo2: float = 1000.0, vco2: float = 850.0, **kw: float | None) -> BreathRecord:
    return BreathRecord(t_s, vo2, vco2, **kw)


@pytest.mark.parametrize(
    ("record", "reason"),
    [
        (breath(1.0, vo2=math.nan), RejectReason.NON_FINITE),
        (breath(1.0, hr_bpm=math.inf), RejectReason.NON_FINITE),
        (breath(math.nan), RejectReason.NON_FINITE),
        (breath(-0.5), RejectReason.NEGATIVE_TIME),
        (breath(1.0, vo2=99.9, vco2=80.0), RejectReason.VO2_RANGE),
        (breath(1.0, vo2=8000.1, vco2=8000.0), RejectReason.VO2_RANGE),
        (breath(1.0, vo2=120.0, vco2=49.0), RejectReason.VCO2_RANGE),
        (breath(1.0, vo2=1000.0, vco2=1601.0), RejectReason.RER_RANGE),  # VCO2/VO2 = 1.601
        (breath(1.0, vo2=1000.0, vco2=499.0), RejectReason.RER_RANGE),  # 0.499
        (breath(1.0, rer=1.7), RejectReason.RER_RANGE),
        (breath(1.0, rer=0.3), RejectReason.RER_RANGE),
        (breath(1.0, ve_l_min=0.5), RejectReason.VE_RANGE),
        (breath(1.0, ve_l_min=301.0), RejectReason.VE_RANGE),
        (breath(1.0, hr_bpm=24.0), RejectReason.HR_RANGE),
        (breath(1.0, hr_bpm=251.0), RejectReason.HR_RANGE),
    ],
)
def test_impossible_records_are_rejected_with_their_reason(
    record: BreathRecord, reason: RejectReason
) -> None:
    v = BreathValidator()
    assert v.check(record) is None
    assert v.counters == {reason: 1}
    assert v.accepted == 0


@pytest.mark.parametrize(
    "record",
    [
        breath(0.0, vo2=100.0, vco2=50.0),  # every bound is inclusive
        breath(1.0, vo2=8000.0, vco2=12800.0, rer=1.6, ve_l_min=300.0, hr_bpm=250.0),
        breath(1.0, vo2=250.0, vco2=200.0, rer=0.8, ve_l_min=1.0, hr_bpm=25.0),
    ],
)
def test_edge_of_limits_is_accepted(record: BreathRecord) -> None:
    v = BreathValidator()
    assert v.check(record) is record
    assert v.accepted == 1 and not v.counters


def test_order_duplicates_and_gaps() -> None:
    v = BreathValidator()
    assert v.check(breath(10.0), seq=5) is not None
    assert v.check(breath(10.0), seq=6) is None  # same time
    assert v.check(breath(12.0), seq=5) is None  # same seq, re-stamped time
    assert v.check(breath(9.0), seq=7) is None  # earlier than the last accepted
    assert v.check(breath(250.0), seq=9) is not None  # a 4-minute gap (< max_time_jump_s) is not a reject
    assert v.check(breath(10.0), seq=5) is None  # an old breath sent again
    assert v.counters == {RejectReason.DUPLICATE: 3, RejectReason.OUT_OF_ORDER: 1}
    assert v.accepted == 2
    assert v.missing_seq == 3  # seq 6, 7, 8 never accepted
    assert v.rejected == 4


def test_counters_accept_plain_string_keys() -> None:
    v = BreathValidator()
    v.check(breath(1.0, hr_bpm=400.0))
    v.reject("bad_checksum")
    v.reject("vendor_specific")
    assert v.counters["hr_range"] == 1
    assert v.counters[RejectReason.BAD_CHECKSUM] == 1
    assert v.counters["vendor_specific"] == 1


def test_sequence_wrap_and_restart() -> None:
    v = BreathValidator()
    v.check(breath(1.0), seq=2**32 - 2)
    v.check(breath(2.0), seq=2**32 - 1)
    v.check(breath(3.0), seq=1)  # wrapped, skipping 0
    assert v.missing_seq == 1 and v.seq_resets == 0
    v.check(breath(4.0), seq=100_000)
    v.check(breath(5.0), seq=0)  # counter restarted while time went on: accepted
    assert v.accepted == 5
    assert v.seq_resets == 1
    assert v.missing_seq == 1 + 99_998


def test_records_without_seq_use_time_only() -> None:
    v = BreathValidator()
    assert v.check(breath(1.0)) is not None
    assert v.check(breath(2.0)) is not None
    assert v.check(breath(2.0)) is None
    assert v.counters == {RejectReason.DUPLICATE: 1}
    assert v.missing_seq == 0


def test_duplicate_memory_is_bounded_by_history() -> None:
    v = BreathValidator(history=2)
    for i, t in enumerate((1.0, 2.0, 3.0)):
        v.check(breath(t), seq=i)
    assert v.check(breath(1.0), seq=0) is None
    # seq 0 / t=1.0 fell out of the 2-breath memory: classified by time alone.
    assert v.counters == {RejectReason.OUT_OF_ORDER: 1}


def test_reset_forgets_order_but_keeps_counts() -> None:
    v = BreathValidator()
    v.check(breath(100.0), seq=50)
    v.check(breath(1.0), seq=0)
    v.reset()
    assert v.check(breath(1.0), seq=0) is not None
    assert v.counters == {RejectReason.OUT_OF_ORDER: 1}
    assert v.accepted == 2


def test_rejected_records_do_not_move_the_order() -> None:
    v = BreathValidator()
    v.check(breath(1.0), seq=1)
    assert v.check(breath(1000.0, vo2=1e6), seq=2) is None
    assert v.check(breath(2.0), seq=3) is not None  # not "out of order" after the absurd one


@given(
    st.lists(
        st.tuples(
            st.floats(-10, 1e4) | st.sampled_from([math.nan, math.inf]),
            st.floats(0, 1e5) | st.just(math.nan),
            st.floats(0, 1e5),
            st.none() | st.integers(0, 2**32 - 1),
        ),
        max_size=60,
    )
)
def test_never_raises_and_accepted_times_increase(
    items: list[tuple[float, float, float, int | None]],
) -> None:
    v = BreathValidator()
    out = [v.check(breath(t, vo2, vco2), seq=s) for t, vo2, vco2, s in items]
    times = [r.t_s for r in out if r is not None]
    assert times == sorted(set(times))
    assert v.accepted + v.rejected == len(items)


def test_custom_limits_from_config() -> None:
    limits = PhysioLimits.from_dict({"hr_bpm": [30, 220], "vo2_ml_min": [150.0, 7000.0]})
    assert limits.hr_bpm == (30.0, 220.0)
    v = BreathValidator(limits)
    assert v.check(breath(1.0, hr_bpm=225.0)) is None
    assert v.counters == {RejectReason.HR_RANGE: 1}


@pytest.mark.parametrize(
    ("data", "match"),
    [
        ({"heart_rate": [30, 200]}, "unknown key limits.heart_rate = "),
        ({"hr_bpm": [200, 30]}, r"^limits.hr_bpm = \[200, 30\]: expected \[low, high\] with low < high"),
        ({"hr_bpm": 200}, "expected a pair"),
        ({"hr_bpm": [30, "x"]}, r"hr_bpm\[1\] = 'x'"),
        ({"vo2_ml_min": [0, 8000]}, "must be > 0"),
    ],
)
def test_bad_limits_name_the_key(data: dict[str, object], match: str) -> None:
    with pytest.raises(DriverConfigError, match=match):
        PhysioLimits.from_dict(data)
