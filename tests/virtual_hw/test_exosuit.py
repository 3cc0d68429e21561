"""The virtual exosuit's pure parts: gait model, table split, slope limit, force tracking, config."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from drivers.exosuit.codec import NackReason
from drivers.exosuit.profile import forces_to_raw
from virtual_hw.errors import FaultSpecError, VirtualConfigError
from virtual_hw.exosuit import (
    EXOSUIT_FAULTS,
    NACK_FAULTS,
    SUIT_JOINTS,
    DeviceLimits,
    GaitConfig,
    GaitModel,
    TrackingConfig,
    VirtualExosuit,
    _first_slope_violation,
    _joint_offsets,
    _Tracker,
    split_table,
)


def _gait(seed: int = 1, offsets: tuple[float, ...] = (0.0, 0.5), t0: float = 10.0,
          config: GaitConfig | None = None) -> GaitModel:
    return GaitModel(offsets, config or GaitConfig(), np.random.default_rng(seed), t0)


# --- gait ----------------------------------------------------------------------------------------


def test_phase_wraps_from_100_to_0_exactly_at_each_boundary() -> None:
    gait = _gait()
    t = 10.0
    for _ in range(20):
        for a in (0, 1):
            b = gait.next_boundary(a, t)
            assert b > t
            assert gait.phase_pct(a, b) == pytest.approx(0.0, abs=1e-9)
            assert gait.phase_pct(a, b - 1e-6) > 99.99
            assert gait.phase_pct(a, b - 0.5 * gait.stride_at(a, b - 1e-6)) == pytest.approx(50.0, abs=3.0)
        t = gait.next_boundary(0, t)


def test_second_leg_is_half_a_stride_after_the_first() -> None:
    gait = _gait()
    b0 = gait.next_boundary(0, 10.0)
    b1 = gait.next_boundary(1, b0)
    assert b1 - b0 == pytest.approx(0.5 * gait.stride_at(0, b0), rel=1e-9)


def test_hip_and_ankle_offsets_follow_the_gait_events() -> None:
    assert _joint_offsets(SUIT_JOINTS["hip_6d"]) == (0.0, 0.5)
    assert _joint_offsets(SUIT_JOINTS["hip_ankle_4d"]) == (0.0, 0.15)
    with pytest.raises(VirtualConfigError, match="knee"):
        _joint_offsets(("hip", "knee"))


def test_stride_statistics_match_the_config_and_repeat_with_the_seed() -> None:
    cfg = GaitConfig(stride_s=1.1, stride_cv=0.025, stride_ar1=0.5)
    gait = _gait(seed=7, config=cfg, offsets=(0.0,), t0=0.0)
    starts = [gait.next_boundary(0, 0.0)]
    for _ in range(4000):
        starts.append(gait.next_boundary(0, starts[-1]))
    strides = np.diff(starts)
    assert strides.mean() == pytest.approx(1.1, rel=0.005)
    assert strides.std() / strides.mean() == pytest.approx(0.025, rel=0.1)
    dev = strides - strides.mean()
    assert np.corrcoef(dev[:-1], dev[1:])[0, 1] == pytest.approx(0.5, abs=0.06)
    again = _gait(seed=7, config=cfg, offsets=(0.0,), t0=0.0)
    assert again.next_boundary(0, 0.0) == starts[0]
    assert again.next_boundary(0, starts[100]) == starts[101]  # lazily generated, same sequence
    assert _gait(seed=8, config=cfg, offsets=(0.0,), t0=0.0).next_boundary(0, 0.0) != starts[0]


def test_walk_starts_at_a_random_phase_and_rejects_earlier_times() -> None:
    phases = {round(_gait(seed=s).phase_pct(0, 10.0)) for s in range(10)}
    assert len(phases) > 5
    with pytest.raises(VirtualConfigError, match="before the walk started"):
        _gait().phase_pct(0, 5.0)


# --- tables --------------------------------------------------------------------------------------


def test_hip_suit_table_is_one_profile_for_both_legs() -> None:
    raw = forces_to_raw(np.linspace(0.0, 100.0, 101))
    (hip,) = split_table(raw, ("hip", "hip"))
    assert hip.actuator == "hip"
    np.testing.assert_array_equal(hip.gait_pct, np.arange(101.0))
    assert forces_to_raw(hip.force_n) == raw


def test_hip_ankle_table_is_the_concatenation_hip_first() -> None:
    hip_raw = forces_to_raw(np.full(101, 12.3))
    ankle_raw = forces_to_raw(np.full(101, 45.6))
    hip, ankle = split_table(hip_raw + ankle_raw, ("hip", "ankle"))
    assert (hip.actuator, ankle.actuator) == ("hip", "ankle")
    assert forces_to_raw(hip.force_n) == hip_raw
    assert forces_to_raw(ankle.force_n) == ankle_raw
    assert ankle.gait_pct[-1] == 100.0
    with pytest.raises(VirtualConfigError, match="201 points"):
        split_table(hip_raw + ankle_raw[:-1], ("hip", "ankle"))


def test_slope_limit_is_per_percent_gait_and_ignores_the_join_between_tables() -> None:
    # 101 points: 1 %GC apart, so a 20 N/%GC limit allows 20 N steps.
    ramp = forces_to_raw(np.linspace(0.0, 2000.0, 101))  # 20 N per point
    assert _first_slope_violation(ramp, 1, 20.0) is None
    assert _first_slope_violation(ramp, 1, 19.9) == 1
    # 11 points: 10 %GC apart, so the same 20 N/%GC allows 200 N steps.
    coarse = forces_to_raw(np.linspace(0.0, 2000.0, 11))
    assert _first_slope_violation(coarse, 1, 20.0) is None
    # Two tables: the jump from the last hip point (500 N) to the first ankle point (0 N) is not a
    # step inside a table.
    two = forces_to_raw(np.r_[np.linspace(0.0, 500.0, 101), np.zeros(101)])
    assert _first_slope_violation(two, 2, 10.1) is None
    assert _first_slope_violation(two, 1, 10.1) == 101  # as one table it would be a step


@settings(max_examples=80, deadline=None)
@given(st.lists(st.integers(0, 3000), min_size=4, max_size=40), st.floats(1.0, 300.0),
       st.sampled_from([1, 2]))
def test_first_slope_violation_is_the_first_too_steep_step_within_a_table(
    raw: list[int], max_slope: float, n_tables: int,
) -> None:
    raw = raw[: len(raw) - len(raw) % n_tables]
    m = len(raw) // n_tables
    max_step = max_slope * 100.0 / (m - 1)
    steps = [abs(raw[k] - raw[k - 1]) / 10.0 for k in range(1, len(raw))]
    assume(all(abs(step - max_step) > 1e-6 for step in steps))  # no ties at float precision
    expected = next((k for k in range(1, len(raw)) if k % m and steps[k - 1] > max_step), None)
    assert _first_slope_violation(tuple(raw), n_tables, max_slope) == expected


# --- force tracking ------------------------------------------------------------------------------


def test_tracking_lags_a_ramp_by_slope_times_tau() -> None:
    tau, slope = 0.002, 3000.0  # N/s
    tracker = _Tracker(TrackingConfig(lag_s=tau, noise_n=0.0), 0.0)
    t, measured = 0.0, 0.0
    for _ in range(100):  # 1 ms steps, 100 ms: 50 τ, settled
        t += 0.001
        measured = tracker.advance(t, slope * t, slope * (t - 0.001), slope)
    assert measured - slope * t == pytest.approx(-slope * tau, rel=1e-9)


def test_tracking_step_response_is_first_order() -> None:
    tau = 0.004
    tracker = _Tracker(TrackingConfig(lag_s=tau, noise_n=0.0), 0.0)
    tracker.measured_n = 200.0  # assisting at 200 N, then the desired force drops to 0
    assert tracker.advance(tau, 0.0, 0.0, 0.0) == pytest.approx(200.0 * math.exp(-1.0))
    # cable slack (< 5 N) well inside PROTOCOL.md's 50 ms with the default 2 ms lag
    default = _Tracker(TrackingConfig(), 0.0)
    default.measured_n = 600.0
    assert default.advance(0.010, 0.0, 0.0, 0.0) < 5.0


def test_tracking_advance_to_the_same_or_an_earlier_time_changes_nothing() -> None:
    tracker = _Tracker(TrackingConfig(noise_n=0.0), 1.0)
    tracker.measured_n = 42.0
    assert tracker.advance(1.0, 0.0, 0.0, 0.0) == 42.0
    assert tracker.advance(0.5, 0.0, 0.0, 0.0) == 42.0


# --- configuration and faults --------------------------------------------------------------------


@pytest.mark.parametrize("kwargs, match", [
    ({"max_force_n": 0.0}, "max_force_n"),
    ({"max_force_n": math.nan}, "max_force_n"),
    ({"max_slope_n_per_pct": -1.0}, "max_slope_n_per_pct"),
    ({"max_points": 1}, "max_points"),
    ({"max_points": 769}, "max_points"),
])
def test_device_limits_reject_nonsense(kwargs: dict[str, float], match: str) -> None:
    with pytest.raises(VirtualConfigError, match=match):
        DeviceLimits(**kwargs)  # type: ignore[arg-type]


@pytest.mark.parametrize("kwargs, match", [
    ({"n_actuators": 3}, "n_actuators"),
    ({"joints": ("hip",)}, "one joint per actuator"),
    ({"feedback_hz": -1.0}, "feedback_hz"),
    ({"faults": ["bus-off@1"]}, "lasts a while"),
    ({"faults": ["nack-sometimes@1x2"]}, "no fault 'nack-sometimes'"),
])
def test_device_rejects_bad_arguments(kwargs: dict[str, object], match: str) -> None:
    from drivers.exosuit.endpoint import CanBusConfig
    from virtual_hw.clock import VirtualClock

    with pytest.raises(VirtualConfigError, match=match):
        VirtualExosuit(CanBusConfig("virtual", "unused"), VirtualClock(), **kwargs)  # type: ignore[arg-type]


def test_fault_catalog_covers_every_nack_reason_and_parses_the_shared_syntax() -> None:
    assert set(NACK_FAULTS.values()) == set(NackReason) - {NackReason.NONE}
    spec = EXOSUIT_FAULTS.parse("nack-out-of-limits@2.5x3")
    assert (spec.kind, spec.start_s, spec.count) == ("nack-out-of-limits", 2.5, 3)
    assert EXOSUIT_FAULTS.parse("garbage@4").count == 1
    assert EXOSUIT_FAULTS.parse("drop-status@1+0.5").end_s == 1.5
    with pytest.raises(FaultSpecError):
        EXOSUIT_FAULTS.parse("drop-status@1x2")
