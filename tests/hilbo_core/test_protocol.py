"""SessionProtocol: the walking protocol as a pure, breath-driven state machine (walked time)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hilbo_core.errors import ConfigError, MeasurementError
from hilbo_core.metabolic import GaussianProductEstimator
from hilbo_core.optimizer import HILOptimizer, OptimizerConfig
from hilbo_core.presets import hip_6d
from hilbo_core.protocol import (
    Action,
    ActionKind,
    EndReason,
    ProtocolStateError,
    SessionPhase,
    SessionProtocol,
    SessionProtocolConfig,
    WalkingTime,
    drive,
    expected_end_s,
)

K, P = ActionKind, SessionPhase


def kp(a: Action) -> tuple[ActionKind, SessionPhase]:
    return a.kind, a.phase


# ------------------------------------------------------------------ reference sequences


def test_reference_sequence_two_bouts_pause_transition_and_a_pause_that_runs_out_the_budget() -> None:
    # short_pause_s = 0: every pause ends with a warm-up (short pauses: test_protocol_short_pause.py)
    cfg = SessionProtocolConfig(warmup_s=6.0, n_explore=1, budget_s=14.0, pause_between_bouts=True,
                                short_pause_s=0.0)
    p = SessionProtocol(cfg, t_start_s=0.0)
    a = p.start()
    assert kp(a) == (K.WARM_UP, P.WARM_UP_EXPLORATION) and a.starts and a.t_s == 0.0
    assert kp(p.on_breath(3.0)) == (K.WARM_UP, P.WARM_UP_EXPLORATION)
    a = p.on_breath(6.0)  # 6 s of warm-up: the breath ends it, the first setting is needed now
    assert kp(a) == (K.PROPOSE, P.EXPLORATION) and a.t_s == 6.0
    p.on_setting_applied(6.0)
    a = p.on_breath(9.0)
    assert kp(a) == (K.MEASURE, P.EXPLORATION) and a.t_setting_s == 3.0 and not a.final
    assert p.on_breath(12.0).t_setting_s == 6.0
    a = p.on_evaluation_done()  # E = 1: the exploration bout is complete
    assert kp(a) == (K.PAUSE_BETWEEN_BOUTS, P.BOUT_PAUSE) and a.starts
    assert kp(p.on_breath(15.0)) == (K.PAUSED, P.BOUT_PAUSE)
    a = p.on_resume()
    assert kp(a) == (K.WARM_UP, P.WARM_UP_OPTIMIZATION) and a.starts
    assert p.t_end_s is None  # the optimisation bout has not begun
    assert kp(p.on_breath(18.0)) == (K.WARM_UP, P.WARM_UP_OPTIMIZATION)
    a = p.on_breath(21.0)
    assert kp(a) == (K.PROPOSE, P.OPTIMIZATION)
    assert p.optimization_started and p.t_end_s == 21.0 + 14.0
    assert kp(p.on_breath(24.0)) == (K.TRANSITION, P.OPTIMIZATION)  # the push is under way
    p.on_setting_applied(25.0)
    a = p.on_breath(27.0)
    assert kp(a) == (K.MEASURE, P.OPTIMIZATION) and a.t_setting_s == 2.0
    assert kp(p.on_evaluation_done()) == (K.PROPOSE, P.OPTIMIZATION)  # stopped by the rule
    p.on_setting_applied()  # at the last breath
    assert p.on_breath(30.0).t_setting_s == 3.0
    a = p.on_pause()  # the operator pauses: the setting is abandoned
    assert kp(a) == (K.PAUSED, P.OPTIMIZATION) and a.starts and p.paused
    assert kp(p.on_breath(31.0)) == (K.PAUSED, P.OPTIMIZATION)
    a = p.on_resume()
    assert kp(a) == (K.WARM_UP, P.WARM_UP_OPTIMIZATION) and a.starts
    assert kp(p.on_breath(34.0)) == (K.WARM_UP, P.WARM_UP_OPTIMIZATION)
    a = p.on_breath(36.0)  # 15 s since the bout began >= 14: the budget counts the pause and warm-up
    assert kp(a) == (K.END, P.ENDED) and a.end_reason is EndReason.BUDGET and a.starts
    assert p.ended and p.end_reason is EndReason.BUDGET
    assert p.walking == WalkingTime(session_s=36.0, warm_up_s=17.0, transition_s=4.0, measured_s=11.0,
                                    paused_s=4.0, after_end_s=0.0, optimization_s=15.0,
                                    optimization_breaths=6)
    assert kp(p.on_breath(40.0)) == (K.END, P.ENDED) and p.walking.after_end_s == 4.0


def test_reference_sequence_the_evaluation_running_at_the_end_is_closed_with_its_breaths() -> None:
    cfg = SessionProtocolConfig(warmup_s=0.0, n_explore=1, session_s=20.0, budget_s=None,
                                pause_between_bouts=False)
    p = SessionProtocol(cfg, t_start_s=0.0)
    assert kp(p.start()) == (K.PROPOSE, P.EXPLORATION)  # no warm-up
    p.on_setting_applied(0.0)
    assert [p.on_breath(t).t_setting_s for t in (4.0, 8.0)] == [4.0, 8.0]
    assert kp(p.on_evaluation_done()) == (K.PROPOSE, P.OPTIMIZATION)  # no pause, no warm-up
    p.on_setting_applied()
    assert [p.on_breath(t).final for t in (12.0, 16.0)] == [False, False]
    a = p.on_breath(21.0)  # past 20 s: measured, then the evaluation is closed
    assert kp(a) == (K.MEASURE, P.OPTIMIZATION) and a.final and a.t_setting_s == 13.0
    with pytest.raises(ProtocolStateError, match="after the final breath"):
        p.on_breath(24.0)
    a = p.on_evaluation_done()
    assert kp(a) == (K.END, P.ENDED) and a.end_reason is EndReason.SESSION
    assert p.walking.session_s == 21.0 and p.walking.measured_s == 21.0


def test_exploration_cut_by_the_end_is_dropped_and_breath_budget_counts_every_breath() -> None:
    p = SessionProtocol(SessionProtocolConfig(warmup_s=0.0, n_explore=2, session_s=10.0, budget_s=None),
                        t_start_s=0.0)
    p.start()
    p.on_setting_applied()
    assert p.on_breath(5.0).kind is K.MEASURE
    assert p.on_breath(10.0).final
    a = p.on_setting_dropped()
    assert a.kind is K.END and not p.optimization_started and p.n_explored == 0

    p = SessionProtocol(SessionProtocolConfig(warmup_s=0.0, n_explore=0, budget_s=None, budget_breaths=3,
                                              pause_between_bouts=False), t_start_s=0.0)
    assert kp(p.start()) == (K.PROPOSE, P.OPTIMIZATION)
    assert p.on_breath(1.0).kind is K.TRANSITION  # not measured, but it is a breath of the bout
    p.on_setting_applied()
    assert [p.on_breath(t).final for t in (2.0, 3.0)] == [False, True]
    assert p.on_evaluation_done().end_reason is EndReason.BUDGET_BREATHS


def test_first_warm_up_starts_at_the_first_breath_without_a_start_time() -> None:
    p = SessionProtocol(SessionProtocolConfig(warmup_s=5.0, budget_s=60.0))
    assert p.start().t_s is None and p.t_s is None
    assert [p.on_breath(t).kind for t in (100.0, 103.0, 105.0)] == [K.WARM_UP, K.WARM_UP, K.PROPOSE]
    assert p.walking.session_s == 5.0 and p.walking.warm_up_s == 5.0


def test_resumed_session_warms_up_in_its_bout_and_counts_what_was_walked() -> None:
    cfg = SessionProtocolConfig(warmup_s=3.0, n_explore=2, budget_s=100.0)
    p = SessionProtocol.resumed(cfg, n_explored=2, optimization_used_s=90.0, optimization_used_breaths=30)
    a = p.start()
    assert kp(a) == (K.WARM_UP, P.WARM_UP_OPTIMIZATION)  # no pause between the bouts again
    assert p.on_breath(50.0).kind is K.WARM_UP
    assert p.t_end_s == 50.0 + 10.0  # the first breath after the resume; 10 s of budget left
    assert p.on_breath(53.0).kind is K.PROPOSE
    p.on_setting_applied()
    assert not p.on_breath(56.0).final and p.on_breath(60.0).final
    assert p.walking.optimization_s == 100.0 and p.walking.optimization_breaths == 33

    q = SessionProtocol.resumed(cfg, n_explored=1, t_start_s=0.0)
    assert kp(q.start()) == (K.WARM_UP, P.WARM_UP_EXPLORATION) and q.n_explored == 1
    # Stopped between the bouts: the optimisation bout (and its budget) begins after the warm-up.
    r = SessionProtocol.resumed(cfg, n_explored=2, t_start_s=0.0, session_used_s=700.0)
    assert kp(r.start()) == (K.WARM_UP, P.WARM_UP_OPTIMIZATION) and not r.optimization_started
    assert r.on_breath(3.0).kind is K.PROPOSE and r.t_end_s == 103.0
    assert r.walking.session_s == 703.0


def test_stop_ends_the_session_anywhere() -> None:
    p = SessionProtocol(SessionProtocolConfig(), t_start_s=0.0)
    p.start()
    a = p.stop()
    assert kp(a) == (K.END, P.ENDED) and a.end_reason is EndReason.STOPPED
    assert p.on_pause().kind is K.END and p.on_resume().kind is K.END and p.stop().kind is K.END


# ------------------------------------------------------------------ misuse and bad input


def test_calls_the_state_does_not_allow_are_clear_errors() -> None:
    p = SessionProtocol(SessionProtocolConfig(warmup_s=3.0), t_start_s=0.0)
    with pytest.raises(ProtocolStateError, match="before start"):
        p.on_breath(1.0)
    p.start()
    with pytest.raises(ProtocolStateError, match="twice"):
        p.start()
    with pytest.raises(ProtocolStateError, match="without a proposal"):
        p.on_setting_applied(0.0)
    with pytest.raises(ProtocolStateError, match="without a measured setting"):
        p.on_evaluation_done()
    with pytest.raises(ProtocolStateError, match="without a setting"):
        p.on_setting_dropped()
    with pytest.raises(ProtocolStateError, match="while not paused"):
        p.on_resume()
    p.on_breath(3.0)  # PROPOSE
    with pytest.raises(ProtocolStateError, match="without a measured setting"):
        p.on_evaluation_done()  # proposed, not yet applied
    with pytest.raises(MeasurementError, match="before the last breath"):
        p.on_setting_applied(2.0)


@pytest.mark.parametrize("t", [2.0, 1.0, math.nan, math.inf, "3"])
def test_breath_times_must_increase_and_be_finite(t) -> None:
    p = SessionProtocol(SessionProtocolConfig(), t_start_s=0.0)
    p.start()
    p.on_breath(2.0)
    with pytest.raises(MeasurementError, match="t_s="):
        p.on_breath(t)
    assert p.t_s == 2.0  # unchanged


@pytest.mark.parametrize(("kw", "match"), [
    ({"session_s": None, "budget_s": None, "budget_breaths": None}, "no budget"),
    ({"warmup_s": -1.0}, r"warmup_s=-1\.0; expected"),
    ({"n_explore": -1}, "n_explore=-1; expected an integer >= 0"),
    ({"budget_s": 0.0}, r"budget_s=0\.0; expected a positive"),
    ({"session_s": math.nan}, "session_s=nan"),
    ({"budget_breaths": 0}, "budget_breaths=0"),
    ({"pause_between_bouts": "yes"}, "pause_between_bouts='yes'"),
])
def test_bad_config(kw, match) -> None:
    with pytest.raises(ConfigError, match=match):
        SessionProtocolConfig(**kw)


def test_defaults_are_the_seeds_and_the_optimizers() -> None:
    c = SessionProtocolConfig()
    assert (c.warmup_s, c.budget_s, c.pause_between_bouts) == (180.0, 2400.0, True)  # Kim et al. 2019 §IV.A.3
    assert (c.n_explore, c.max_breaths) == (OptimizerConfig().n_explore, OptimizerConfig().max_breaths)


def test_expected_end_reference_values() -> None:
    # 2 x 3-min warm-ups + 6 x 45 breaths x 3 s + the 40-min bout = 59.5 min
    assert expected_end_s(SessionProtocolConfig()) == pytest.approx(360.0 + 810.0 + 2400.0)
    assert expected_end_s(SessionProtocolConfig(), bout_pause_s=60.0) == pytest.approx(3630.0)
    assert expected_end_s(SessionProtocolConfig(session_s=3600.0, budget_s=None)) == 3600.0
    assert expected_end_s(SessionProtocolConfig(session_s=3600.0)) == pytest.approx(3570.0)  # the first
    assert expected_end_s(SessionProtocolConfig(budget_s=None, budget_breaths=100),
                          breath_interval_s=2.0) == pytest.approx(360.0 + 540.0 + 200.0)
    with pytest.raises(ConfigError, match="breath_interval_s=0"):
        expected_end_s(SessionProtocolConfig(), breath_interval_s=0)


def test_expected_end_of_a_running_session_moves_to_the_deadline() -> None:
    p = SessionProtocol(SessionProtocolConfig(warmup_s=6.0, n_explore=1, max_breaths=2, budget_s=30.0,
                                              pause_between_bouts=False), t_start_s=0.0)
    p.start()
    assert p.expected_t_end_s() == pytest.approx(6.0 + 6.0 + 6.0 + 30.0)
    p.on_breath(6.0)
    p.on_setting_applied()
    p.on_breath(9.0)
    assert p.expected_t_end_s() == pytest.approx(9.0 + 3.0 + 6.0 + 30.0)  # one breath and a warm-up left
    p.on_breath(12.0)
    p.on_evaluation_done()
    p.on_breath(15.0)
    p.on_breath(18.0)  # PROPOSE: the bout begins, the deadline is fixed
    assert p.t_end_s == p.expected_t_end_s() == 48.0


# ------------------------------------------------------------------ properties


def _walk(cfg: SessionProtocolConfig, intervals: list[float], eval_breaths: int, transition_breaths: int,
          pause_every: int) -> tuple[SessionProtocol, list[tuple[float, Action]]]:
    """A driver: evaluations of ``eval_breaths`` breaths, ``transition_breaths`` before each
    setting is applied, an operator pause of two breaths every ``pause_every`` breaths (0: none).

    Returns the protocol and every (t, action) in order (t: the breath's, or the call's time).
    """
    p = SessionProtocol(cfg, t_start_s=0.0)
    act, t, k, n, pending, paused_for = p.start(), 0.0, 0, 0, -1, -1
    log: list[tuple[float, Action]] = [(t, act)]
    while act.kind is not K.END:
        if k > 100_000:
            raise AssertionError(f"no end after {k} breaths (t = {t:.0f} s, {p.phase.value})")
        if act.kind is K.PAUSE_BETWEEN_BOUTS or (act.kind is K.PAUSED and paused_for >= 2):
            act, paused_for = p.on_resume(), -1
            log.append((t, act))
            continue
        if act.kind is K.PROPOSE and pending < 0:
            pending = transition_breaths
        if pending == 0:
            p.on_setting_applied(t)
            pending = -1
        t += intervals[k % len(intervals)]
        k += 1
        act = p.on_breath(t)
        log.append((t, act))
        if pending > 0:
            pending -= 1
        if act.kind is K.PAUSED:
            paused_for += 1
        if act.kind is K.MEASURE:
            n += 1
            if n >= eval_breaths or act.final:
                act, n = p.on_evaluation_done(), 0
                log.append((t, act))
        if pause_every and k % pause_every == 0 and act.kind in (K.MEASURE, K.WARM_UP, K.TRANSITION,
                                                                   K.PROPOSE):
            act, n, pending, paused_for = p.on_pause(), 0, -1, 0
            log.append((t, act))
    return p, log


_intervals = st.lists(st.floats(0.5, 8.0), min_size=1, max_size=30)


@settings(max_examples=150, deadline=None)
@given(intervals=_intervals, session_s=st.floats(60.0, 900.0), warmup_s=st.floats(0.0, 60.0),
       n_explore=st.integers(0, 4), eval_breaths=st.integers(1, 12), transition=st.integers(0, 3),
       pause_every=st.sampled_from([0, 0, 17, 41]), bout_pause=st.booleans())
def test_the_session_ends_within_one_breath_of_its_minutes(intervals, session_s, warmup_s, n_explore,
                                                           eval_breaths, transition, pause_every,
                                                           bout_pause) -> None:
    cfg = SessionProtocolConfig(warmup_s=warmup_s, n_explore=n_explore, session_s=session_s,
                                budget_s=None, pause_between_bouts=bout_pause)
    p, log = _walk(cfg, intervals, eval_breaths, transition, pause_every)
    times = [t for t, _ in log]
    breath_times = sorted(set(times))
    t_end = breath_times[-1]
    # Ends at the first breath at or past the session's end: less than one breath over.
    assert p.end_reason is EndReason.SESSION and t_end >= session_s
    assert len(breath_times) == 1 or breath_times[-2] < session_s
    assert t_end - session_s < max(intervals)
    w = p.walking
    # Every second is accounted once; pauses are walking time but never measurement.
    assert w.session_s == pytest.approx(t_end)
    assert w.warm_up_s + w.transition_s + w.measured_s + w.paused_s == pytest.approx(w.session_s)
    paused = False
    for _, a in log:
        paused = (a.kind is K.PAUSED) or (paused and a.kind not in (K.WARM_UP, K.PROPOSE, K.END))
        assert not (paused and a.kind is K.MEASURE)
    # Each warm-up lasts at least warmup_s of breath time, and ends with the first breath that
    # completes it.
    t_w = prev = None
    for t, a in log:
        if a.kind is K.WARM_UP and a.starts:
            t_w = prev = a.t_s
        elif a.kind is K.PAUSED and a.starts:
            t_w = None
        elif a.kind is K.WARM_UP and t_w is not None:
            assert t - t_w < warmup_s
            prev = t
        elif a.kind is K.PROPOSE and t_w is not None:
            assert t - t_w >= warmup_s and prev - t_w < warmup_s
            t_w = None


@settings(max_examples=100, deadline=None)
@given(intervals=_intervals, budget_s=st.floats(30.0, 600.0), eval_breaths=st.integers(1, 12),
       transition=st.integers(0, 3), pause_every=st.sampled_from([0, 97]))
def test_the_optimisation_bout_ends_within_one_breath_of_its_budget(intervals, budget_s, eval_breaths,
                                                                    transition, pause_every) -> None:
    # Pauses rarer than a warm-up (<= 40 breaths) plus an evaluation (<= 15): else every resume
    # warm-up is paused again and the optimisation bout (whose budget ends the session) never begins.
    cfg = SessionProtocolConfig(warmup_s=20.0, n_explore=2, budget_s=budget_s, pause_between_bouts=True)
    p, log = _walk(cfg, intervals, eval_breaths, transition, pause_every)
    t_opt = next(t for t, a in log if a.kind is K.PROPOSE and a.phase is P.OPTIMIZATION)
    t_end = log[-1][0]
    assert p.end_reason is EndReason.BUDGET
    assert budget_s <= t_end - t_opt < budget_s + max(intervals)
    assert p.walking.optimization_s == pytest.approx(t_end - t_opt)
    measured = [a for _, a in log if a.kind is K.MEASURE]
    assert sum(a.final for a in measured) <= 1


# ------------------------------------------------------------------ drive() with the optimizer


def _product() -> GaussianProductEstimator:
    return GaussianProductEstimator(prior_mean=400.0, prior_var=100.0**2, meas_var=40.0**2)


def test_drive_runs_a_whole_session_and_ends_within_one_breath() -> None:
    space = hip_6d()
    opt = HILOptimizer(space, n_explore=3, max_breaths=6, window=1, seed=2, n_candidates=64, n_local=0,
                       estimator_factory=_product)
    proto = SessionProtocol(SessionProtocolConfig(warmup_s=10.0, n_explore=3, max_breaths=6, session_s=200.0,
                                                  budget_s=None, pause_between_bouts=True), t_start_s=0.0)
    rng = np.random.default_rng(5)
    clock = {"t": 0.0}
    applied: list[tuple[object, float]] = []
    evals: list[tuple[object, float, float]] = []

    def next_breath() -> tuple[float, float]:
        clock["t"] += float(rng.uniform(2.0, 4.0))
        return clock["t"], 400.0 + float(rng.normal(0.0, 30.0))

    drive(proto, opt, next_breath, lambda params, t: applied.append((params, t)),
          on_evaluation=lambda ev, t0, t1: evals.append((ev, t0, t1)))
    assert proto.ended and proto.end_reason is EndReason.SESSION
    assert 200.0 <= clock["t"] < 204.0
    assert [ev for ev, _, _ in evals] == list(opt.evaluations) and len(evals) > 3
    assert all(ev.phase == "exploration" and ev.breaths == 6 for ev, _, _ in evals[:3])
    assert evals[-1][2] == clock["t"]  # the last evaluation ends with the session's last breath
    assert evals[-1][0].reason in ("budget", "threshold", "max_measurements")
    # assistance off for the first warm-up, for the pause between the bouts and for the second warm-up
    assert [t for params, t in applied if params is None] == [0.0, evals[2][2], evals[2][2]]
    assert opt.current_params is None


def test_close_current_keeps_an_optimisation_evaluation_and_drops_an_exploration_one() -> None:
    opt = HILOptimizer(hip_6d(), n_explore=1, max_breaths=4, window=1, seed=1, n_candidates=64,
                       estimator_factory=_product)
    assert opt.close_current() is None
    opt.ask()
    opt.observe_breath(3.0, 400.0)
    assert opt.close_current() is None and opt.evaluations == () and opt.current_params is None
    opt.ask()
    for i in range(4):
        opt.observe_breath(3.0 * (i + 1), 400.0)
    opt.ask()
    assert opt.close_current() is None  # no breaths yet: nothing to keep
    opt.ask()
    step = opt.observe_breath(3.0, 390.0)
    ev = opt.close_current()
    assert ev is not None and ev.reason == "budget" and not ev.stopped_early
    assert ev.breaths == 1 and ev.mean == step.mean and opt.evaluations[-1] == ev
