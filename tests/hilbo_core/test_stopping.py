"""Tests of hilbo_core.stopping: Algorithm 2's schedule and the stopping rules."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from hilbo_core.errors import ConfigError, MeasurementError
from hilbo_core.stopping import (
    FixedIntervalRule,
    SigmaScaledRule,
    StopDecision,
    StoppingRule,
    StopReason,
    threshold_schedule,
)

# Two exploration points × four measurements, chosen so every S_ij + S_iN is a square:
#   row 0: M_iN = 6,  S_iN = 1 -> X = (12-6)/4, (8-6)/2, (7-6)/3, 0      = 1.5, 1.0, 1/3, 0
#   row 1: M_iN = 21, S_iN = 4 -> X = (15-21)/3, (25-21)/4, (23.5-21)/5, 0 = -2, 1.0, 0.5, 0
# Column maxima: 1.5, 1.0, 0.5, 0.
M_HAND = [[12.0, 8.0, 7.0, 6.0], [15.0, 25.0, 23.5, 21.0]]
S_HAND = [[15.0, 3.0, 8.0, 1.0], [5.0, 12.0, 21.0, 4.0]]


@pytest.mark.parametrize(
    ("window", "expected"),
    [
        (0, [1.5, 1.0, 0.5, 0.0]),
        (1, [1.5, 1.5, 1.0, 0.5]),  # A_i = max over columns i-1..i+1, clipped
        (2, [1.5, 1.5, 1.5, 1.0]),
        (10, [1.5, 1.5, 1.5, 1.5]),  # window wider than the trace covers every column
    ],
)
def test_threshold_schedule_by_hand(window: int, expected: list[float]) -> None:
    a = threshold_schedule(M_HAND, S_HAND, window)
    assert a.shape == (4,)
    np.testing.assert_allclose(a, expected, rtol=1e-12)


def _traces(n_rows: int, n_cols: int) -> st.SearchStrategy[tuple[np.ndarray, np.ndarray]]:
    shape = (n_rows, n_cols)
    means = hnp.arrays(float, shape, elements=st.floats(-1e3, 1e3))
    variances = hnp.arrays(float, shape, elements=st.floats(1e-3, 1e3))
    return st.tuples(means, variances)


traces = st.tuples(st.integers(1, 4), st.integers(1, 12)).flatmap(lambda s: _traces(*s))


def _x_matrix(m: np.ndarray, s: np.ndarray) -> np.ndarray:
    """X of Algorithm 2 lines 4–10, written as the loops of Kim et al. 2019."""
    x = np.empty_like(m)
    for i in range(m.shape[0]):
        for j in range(m.shape[1]):
            x[i, j] = (m[i, j] - m[i, -1]) / math.sqrt(s[i, j] + s[i, -1])
    return x


@given(ms=traces, window=st.integers(0, 15))
def test_threshold_schedule_properties(ms: tuple[np.ndarray, np.ndarray], window: int) -> None:
    m, s = ms
    a = threshold_schedule(m, s, window)
    x = _x_matrix(m, s)
    n = m.shape[1]
    assert a.shape == (n,)
    assert a[-1] >= 0.0  # column N of X is zero and always in the last window
    # Line 12 written out directly.
    for i in range(n):
        lo, hi = max(0, i - window), min(n - 1, i + window)
        assert a[i] == pytest.approx(x[:, lo : hi + 1].max(), rel=1e-12, abs=1e-12)
    np.testing.assert_allclose(threshold_schedule(m, s, 0), x.max(axis=0), rtol=1e-12, atol=1e-12)
    # A wider window is never less risk-averse.
    assert np.all(threshold_schedule(m, s, window + 1) >= a)


@pytest.mark.parametrize(
    ("m", "s", "window", "error", "match"),
    [
        (M_HAND, S_HAND, -1, ConfigError, "window=-1"),
        (M_HAND, S_HAND, 1.5, ConfigError, "window=1.5"),
        (M_HAND, S_HAND, True, ConfigError, "window=True"),
        ([1.0, 2.0], [1.0, 1.0], 1, ConfigError, "M must have shape"),
        (np.zeros((0, 3)), np.zeros((0, 3)), 1, ConfigError, "M must have shape"),
        (M_HAND, [[1.0, 1.0]], 1, ConfigError, "S must have the shape"),
        ([[1.0, math.nan]], [[1.0, 1.0]], 1, MeasurementError, r"M\[0, 1\]=nan"),
        ([[1.0, 2.0]], [[1.0, 0.0]], 1, MeasurementError, r"S\[0, 1\]=0.0"),
        ([[1.0, 2.0]], [[-1.0, 1.0]], 1, MeasurementError, r"S\[0, 0\]=-1.0"),
        ([[1.0, 2.0]], [[math.inf, 1.0]], 1, MeasurementError, r"S\[0, 0\]=inf"),
    ],
)
def test_threshold_schedule_validation(m, s, window, error, match) -> None:  # type: ignore[no-untyped-def]
    with pytest.raises(error, match=match):
        threshold_schedule(m, s, window)


# ---------------------------------------------------------------- rules
# mean 13, best 10 -> μ = 3; var 3 + best_var 1 -> σ = 2; so the boundary is A_i = 1.5.


def test_sigma_scaled_boundary() -> None:
    rule = SigmaScaledRule([1.5, 1.49, -0.5, 1.5])
    assert rule.n_max == 4
    at_boundary = rule.decide(0, 13.0, 3.0, 10.0, 1.0)
    assert at_boundary == StopDecision(False, StopReason.CONTINUE, 0, 1.5, 1.5)  # 3 > 3 is false
    above = rule.decide(0, 13.5, 3.0, 10.0, 1.0)
    assert (above.stop, above.reason, above.z) == (True, StopReason.THRESHOLD, 1.75)
    below_threshold = rule.decide(1, 13.0, 3.0, 10.0, 1.0)  # 3 > 1.49·2 = 2.98
    assert below_threshold == StopDecision(True, StopReason.THRESHOLD, 1, 1.5, 1.49)


def test_sigma_scaled_negative_threshold_and_better_setting() -> None:
    rule = SigmaScaledRule([1.0, 1.0, -0.5, 1.0])
    # A better setting (μ < 0) continues under a positive threshold ...
    assert not rule.decide(1, 9.0, 3.0, 10.0, 1.0).stop
    # ... but A_i = -0.5 stops it once μ = -0.5 > -0.5·2 = -1.
    decision = rule.decide(2, 9.5, 3.0, 10.0, 1.0)
    assert (decision.stop, decision.reason, decision.z) == (True, StopReason.THRESHOLD, -0.25)


@pytest.mark.parametrize("mean", [-1e6, 10.0, 1e6])
def test_max_measurements_at_last_index(mean: float) -> None:
    for rule in (SigmaScaledRule([0.0, 0.0, 0.0]), FixedIntervalRule(3)):
        decision = rule.decide(2, mean, 3.0, 10.0, 1.0)
        assert (decision.stop, decision.reason, decision.index) == (
            True,
            StopReason.MAX_MEASUREMENTS,
            2,
        )


def test_fixed_interval_never_stops_early() -> None:
    rule = FixedIntervalRule(3)
    for i in (0, 1):
        decision = rule.decide(i, 1e6, 3.0, 10.0, 1.0)
        assert decision == StopDecision(False, StopReason.CONTINUE, i, (1e6 - 10.0) / 2.0, None)
    assert rule.n_max == 3


def test_constant_rule() -> None:
    rule = SigmaScaledRule.constant(2.0, 5)
    assert rule.n_max == 5
    np.testing.assert_array_equal(rule.thresholds, [2.0] * 5)
    assert not rule.decide(0, 14.0, 3.0, 10.0, 1.0).stop  # 4 > 4 is false
    assert rule.decide(0, 14.5, 3.0, 10.0, 1.0).reason is StopReason.THRESHOLD
    with pytest.raises(ConfigError, match="n_max=0"):
        SigmaScaledRule.constant(2.0, 0)
    with pytest.raises(ConfigError, match="k=nan"):
        SigmaScaledRule.constant(math.nan, 3)


def test_thresholds_are_copied_and_read_only() -> None:
    a = np.array([1.0, 2.0])
    rule = SigmaScaledRule(a)
    a[0] = 100.0
    assert rule.thresholds[0] == 1.0
    with pytest.raises(ValueError, match="read-only"):
        rule.thresholds[0] = 5.0


@pytest.mark.parametrize("rule", [SigmaScaledRule([1.0, 1.0, 1.0]), FixedIntervalRule(3)])
@pytest.mark.parametrize(
    ("args", "error", "match"),
    [
        ((-1, 1.0, 1.0, 0.0, 1.0), ConfigError, r"i=-1 must be in \[0, 2\]"),
        ((3, 1.0, 1.0, 0.0, 1.0), ConfigError, r"i=3 must be in \[0, 2\]"),
        ((1.0, 1.0, 1.0, 0.0, 1.0), ConfigError, "i=1.0 must be an integer"),
        ((0, math.nan, 1.0, 0.0, 1.0), MeasurementError, "mean=nan"),
        ((0, 1.0, 1.0, math.inf, 1.0), MeasurementError, "best_mean=inf"),
        ((0, 1.0, -1.0, 0.0, 2.0), MeasurementError, "var=-1.0"),
        ((0, 1.0, 1.0, 0.0, math.nan), MeasurementError, "best_var=nan"),
        ((0, 1.0, 0.0, 0.0, 0.0), MeasurementError, "must be > 0"),
    ],
)
def test_decide_validation(rule: StoppingRule, args: tuple, error: type, match: str) -> None:
    with pytest.raises(error, match=match):
        rule.decide(*args)


@pytest.mark.parametrize("bad", [[], [[1.0, 2.0]], [1.0, math.inf]])
def test_sigma_scaled_rejects_bad_thresholds(bad: list) -> None:
    with pytest.raises(ConfigError, match="thresholds"):
        SigmaScaledRule(bad)


def test_fixed_interval_rejects_bad_n_max() -> None:
    with pytest.raises(ConfigError, match="n_max=0"):
        FixedIntervalRule(0)
    with pytest.raises(ConfigError, match=r"n_max=2\.5"):
        FixedIntervalRule(2.5)  # type: ignore[arg-type]


def test_protocol_and_frozen_decision() -> None:
    assert isinstance(SigmaScaledRule([1.0]), StoppingRule)
    assert isinstance(FixedIntervalRule(1), StoppingRule)
    decision = FixedIntervalRule(1).decide(0, 1.0, 1.0, 0.0, 1.0)
    assert decision.stop and decision.reason is StopReason.MAX_MEASUREMENTS
    with pytest.raises(dataclasses.FrozenInstanceError):
        decision.stop = False  # type: ignore[misc]
