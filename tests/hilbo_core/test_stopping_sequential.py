"""The sound rule's sequential boundaries: strict early, the late levels from ``boundary_s`` on."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.stats import norm

from hilbo_core.errors import ConfigError
from hilbo_core.stopping import SoundRule, StopReason

# The optimizer's defaults: no decision before 30 s, boundaries reach 1 σ (reject) and 2 σ
# (accept) at 60 s.
RULE = SoundRule([0.0] * 6, min_decision_s=30.0, a_floor=1.0, accept_z=2.0, boundary_s=60.0)


# ---------------------------------------------------------------- reference values
@pytest.mark.parametrize("t_s, factor", [(15.0, 2.0), (30.0, math.sqrt(2.0)), (45.0, math.sqrt(60.0 / 45.0)),
                                         (60.0, 1.0), (120.0, 1.0), (0.0, math.inf)])
def test_the_boundary_factor(t_s, factor) -> None:
    assert RULE.scale(t_s) == pytest.approx(factor)
    assert SoundRule([0.0] * 6, min_decision_s=30.0).scale(t_s) == 1.0  # the floor rule: no factor


def test_a_reject_needs_the_early_margin() -> None:
    # μ = 426 − 400 = 26, σ = √(300 + 100) = 20, z = 1.3: above the late 1 σ, below √2 σ at 30 s.
    d = RULE.decide(2, 426.0, 300.0, 400.0, 100.0, t_s=30.0)
    assert (d.stop, d.reason, d.z) == (False, StopReason.CONTINUE, pytest.approx(1.3))
    assert d.threshold == pytest.approx(math.sqrt(2.0))
    d = RULE.decide(2, 426.0, 300.0, 400.0, 100.0, t_s=45.0)  # threshold 1.155 σ
    assert (d.stop, d.reason) == (True, StopReason.THRESHOLD)
    assert d.threshold == pytest.approx(1.1547005)
    # z = 1.5 > √2: decisive already at 30 s, never before it.
    assert RULE.decide(2, 430.0, 300.0, 400.0, 100.0, t_s=30.0).reason is StopReason.THRESHOLD
    assert not RULE.decide(2, 430.0, 300.0, 400.0, 100.0, t_s=29.9).stop


def test_an_accept_needs_the_early_margin() -> None:
    # z = −2.5: below −2 σ late, above −2√2 = −2.83 σ at 30 s, below −2·√1.2 = −2.19 σ at 50 s.
    assert not RULE.decide(2, 350.0, 300.0, 400.0, 100.0, t_s=30.0).stop
    d = RULE.decide(2, 350.0, 300.0, 400.0, 100.0, t_s=50.0)
    assert (d.stop, d.reason) == (True, StopReason.DECIDED)


def test_algorithm_2s_schedule_still_raises_the_threshold() -> None:
    rule = SoundRule([0.0, 3.0, 0.0], min_decision_s=30.0, a_floor=1.0, boundary_s=60.0)
    assert rule.decide(1, 450.0, 300.0, 400.0, 100.0, t_s=90.0).threshold == 3.0  # A_1 above the floor
    assert not rule.decide(1, 450.0, 300.0, 400.0, 100.0, t_s=90.0).stop  # z = 2.5 < 3


def test_no_look_at_time_zero_decides() -> None:
    rule = SoundRule([0.0] * 3, min_decision_s=0.0, a_floor=0.0, accept_z=0.0, boundary_s=60.0)
    d = rule.decide(0, 1000.0, 1.0, 400.0, 1.0, t_s=0.0)
    assert (d.stop, d.threshold) == (False, math.inf)
    assert rule.decide(0, 1000.0, 1.0, 400.0, 1.0, t_s=1.0).stop  # at 1 s: μ > 0 = 0·√60 σ


@pytest.mark.parametrize("value", [0.0, -1.0, math.nan, math.inf, True, "60"])
def test_bad_boundary_s(value) -> None:
    with pytest.raises(ConfigError, match="boundary_s"):
        SoundRule([0.0] * 3, boundary_s=value)


# ---------------------------------------------------------------- properties
_finite = st.floats(-1e3, 1e3, allow_nan=False)


@settings(max_examples=300, deadline=None)
@given(a=st.lists(st.floats(-5.0, 5.0), min_size=3, max_size=3), floor=st.floats(0.0, 3.0),
       accept=st.floats(0.0, 4.0), boundary=st.floats(1.0, 300.0), t=st.floats(0.0, 600.0),
       mean=_finite, below=st.floats(0.0, 1e3), var=st.floats(0.01, 1e4), best_var=st.floats(0.0, 1e4),
       i=st.integers(0, 1))
def test_an_estimate_at_or_below_the_incumbent_is_never_rejected(a, floor, accept, boundary, t, mean, below,
                                                                   var, best_var, i) -> None:
    rule = SoundRule(a, min_decision_s=0.0, a_floor=floor, accept_z=accept, boundary_s=boundary)
    d = rule.decide(i, mean - below, var, mean, best_var, t_s=t)
    assert d.reason is not StopReason.THRESHOLD


@settings(max_examples=300, deadline=None)
@given(mean=_finite, best=_finite, var=st.floats(0.01, 1e4), t=st.floats(30.0, 59.9),
       later=st.floats(0.0, 100.0))
def test_a_decision_early_holds_later_and_needs_more_than_the_late_level(mean, best, var, t, later) -> None:
    # The boundary only relaxes with time: what stops at t stops at every later look with the same
    # evidence; and before boundary_s a stop needs more than the late levels (1 σ, 2 σ).
    d = RULE.decide(2, mean, var, best, var, t_s=t)
    if d.stop:
        z = (mean - best) / math.sqrt(2.0 * var)
        assert z > 1.0 * RULE.scale(t) if d.reason is StopReason.THRESHOLD else z < -2.0 * RULE.scale(t)
        assert abs(z) > 1.0
        again = RULE.decide(2, mean, var, best, var, t_s=t + later)
        assert (again.stop, again.reason) == (True, d.reason)


def test_the_early_decision_bound_of_the_boundary() -> None:
    """At zero true difference, a Brownian score (information t/60) looked at every second from
    6 to 60 s crosses the sequential boundary in at most 2·(1 − Φ(1)) of paths (the reflection
    bound of the docstring), where a constant 1 σ at the same looks crosses in far more: the error
    of a repeated test accumulates unless early looks are stricter."""
    rng = np.random.default_rng(7)
    t = np.arange(6.0, 60.0 + 1e-9, 1.0)
    info = t / 60.0
    steps = np.diff(np.concatenate([[0.0], info]))
    score = np.cumsum(rng.normal(0.0, 1.0, (20000, t.size)) * np.sqrt(steps), axis=1)  # W(I)
    z = score / np.sqrt(info)
    factors = np.array([RULE.scale(x) for x in t])
    sequential = float((z > 1.0 * factors).any(axis=1).mean())
    constant = float((z > 1.0).any(axis=1).mean())
    one_look = 1.0 - norm.cdf(1.0)
    assert one_look < sequential <= 2.0 * one_look
    assert constant > 2.0 * one_look + 0.1


# ---------------------------------------------------------------- in the optimizer
def _session_steps(**kw) -> list:
    """A short session on a quadratic landscape with breath noise, a breath every 3 s: every
    optimisation-phase (t_s, BreathStep) that carries a decision."""
    from hilbo_core.metabolic import GaussianProductEstimator
    from hilbo_core.optimizer import HILOptimizer
    from hilbo_core.presets import hip_6d

    space = hip_6d()
    opt_u = np.array([0.2, 0.5, 0.7, 0.6, 0.5, 0.5])
    opt = HILOptimizer(space, n_explore=4, max_breaths=40, window=1, budget_breaths=300, seed=3,
                       n_candidates=256,
                       estimator_factory=lambda: GaussianProductEstimator(400.0, 100.0**2, 40.0**2), **kw)
    rng = np.random.default_rng(4)
    steps = []
    while not opt.done:
        params = opt.ask()
        true = 300.0 + 400.0 * float(np.sum((space.to_unit(space.from_dict(params)) - opt_u) ** 2))
        t = 0.0
        while True:
            t += 3.0
            step = opt.observe_breath(t, true + rng.normal(0.0, 40.0))
            if step.decision is not None:
                steps.append((t, step))
            if step.stop:
                break
    return steps


def test_the_default_session_decides_from_30_s_on_the_sequential_boundary() -> None:
    steps = _session_steps()  # the defaults: 30 s, boundary 60 s, 1 σ / 2 σ
    early = [(t, s) for t, s in steps if s.stop and s.evaluation.reason in ("threshold", "decided")]
    assert early, "no early decision on a landscape with clearly bad settings"
    assert min(t for t, _ in early) < 60.0  # the old fixed clock would not have decided yet
    for t, s in early:
        assert t >= 30.0
        factor = math.sqrt(max(1.0, 60.0 / t))
        if s.evaluation.reason == "threshold":
            assert s.decision.z > s.decision.threshold >= 1.0 * factor - 1e-12
        else:
            assert s.decision.z < -2.0 * factor
    floor = _session_steps(stopping="sound-floor")
    assert all(t >= 60.0 for t, s in floor if s.stop and s.evaluation.reason in ("threshold", "decided"))
