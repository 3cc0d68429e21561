"""The sound stopping rule, the GP-posterior incumbent and the recommendation."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hilbo_core.errors import ConfigError
from hilbo_core.gp import GaussianProcess
from hilbo_core.metabolic import GaussianProductEstimator
from hilbo_core.optimizer import HILOptimizer, OptimizerConfig, RecommendKind, StoppingKind
from hilbo_core.presets import hip_6d
from hilbo_core.stopping import SoundRule, StopReason

SPACE = hip_6d()
OPT_U = np.array([0.2, 0.5, 0.7, 0.6, 0.5, 0.5])


def cost(params: dict[str, float]) -> float:
    u = SPACE.to_unit(SPACE.from_dict(params))
    return 300.0 + 400.0 * float(np.sum((u - OPT_U) ** 2))


def product_estimator() -> GaussianProductEstimator:
    return GaussianProductEstimator(prior_mean=400.0, prior_var=100.0**2, meas_var=40.0**2)


def make(**kw) -> HILOptimizer:
    opts = {"n_explore": 4, "max_breaths": 20, "window": 1, "budget_breaths": 120, "seed": 3,
            "n_candidates": 256, "min_decision_s": 30.0}
    opts.update(kw)
    return HILOptimizer(SPACE, estimator_factory=product_estimator, **opts)


def drive(opt: HILOptimizer, rng: np.random.Generator) -> list:
    """Run to the end with a breath every 3 s; returns every optimisation-phase BreathStep."""
    steps = []
    while not opt.done:
        params = opt.ask()
        t = 0.0
        while True:
            t += 3.0
            step = opt.observe_breath(t, cost(params) + rng.normal(0, 40.0))
            if step.decision is not None:
                steps.append((t, step))
            if step.stop:
                break
    return steps


# ---------------------------------------------------------------- the rule, hand-computed values
RULE = SoundRule([-0.5, -0.3, 0.2, 2.0, 0.0], min_decision_s=60.0, a_floor=0.5)


def test_thresholds_are_floored() -> None:
    np.testing.assert_array_equal(RULE.thresholds, [0.5, 0.5, 0.5, 2.0, 0.5])
    assert RULE.n_max == 5 and RULE.min_decision_s == 60.0 and RULE.a_floor == 0.5


def test_no_stop_before_min_decision_s() -> None:
    # μ = 450 − 400 = 50, σ = √(300 + 100) = 20, z = 2.5 > 0.5: confidently worse, but too early.
    d = RULE.decide(2, 450.0, 300.0, 400.0, 100.0, t_s=59.9)
    assert (d.stop, d.reason, d.z, d.threshold) == (False, StopReason.CONTINUE, 2.5, 0.5)
    d = RULE.decide(2, 450.0, 300.0, 400.0, 100.0, t_s=60.0)
    assert (d.stop, d.reason) == (True, StopReason.THRESHOLD)


def test_boundary_and_schedule_above_the_floor() -> None:
    # μ = 10 = 0.5·σ exactly: not greater, continue (Kim et al. 2019's strict μ > A·σ).
    d = RULE.decide(1, 410.0, 300.0, 400.0, 100.0, t_s=90.0)
    assert (d.stop, d.z) == (False, 0.5)
    # i = 3 has A = 2.0 > floor: z = 1.5 does not stop there, stops at i = 2 (A floored to 0.5).
    assert not RULE.decide(3, 430.0, 300.0, 400.0, 100.0, t_s=90.0).stop
    assert RULE.decide(2, 430.0, 300.0, 400.0, 100.0, t_s=90.0).stop


def test_last_measurement_ends_even_before_min_decision_s() -> None:
    d = RULE.decide(4, 300.0, 300.0, 400.0, 100.0, t_s=12.0)
    assert (d.stop, d.reason) == (True, StopReason.MAX_MEASUREMENTS)


@settings(max_examples=200, deadline=None)
@given(a=st.lists(st.floats(-5, 5), min_size=2, max_size=10), floor=st.floats(0, 3),
       best=st.floats(100, 1000), gap=st.floats(0, 500), v=st.floats(1e-3, 1e4),
       bv=st.floats(0, 1e4), t=st.floats(0, 1e4), data=st.data())
def test_a_candidate_looking_at_least_as_good_is_never_stopped(a, floor, best, gap, v, bv, t, data):
    rule = SoundRule(a, min_decision_s=0.0, a_floor=floor)
    i = data.draw(st.integers(0, len(a) - 2))
    d = rule.decide(i, best - gap, v, best, bv, t_s=t)
    assert not d.stop and d.reason is StopReason.CONTINUE


@pytest.mark.parametrize("kw, match", [
    ({"min_decision_s": -1.0}, "min_decision_s"), ({"a_floor": -0.1}, "a_floor"),
    ({"a_floor": math.nan}, "a_floor"), ({"min_decision_s": True}, "min_decision_s"),
])
def test_bad_rule_options(kw, match) -> None:
    with pytest.raises(ConfigError, match=match):
        SoundRule([0.0, 0.0], **kw)


def test_time_is_required() -> None:
    with pytest.raises(ConfigError, match="t_s"):
        RULE.decide(0, 400.0, 1.0, 400.0, 1.0)


# ---------------------------------------------------------------- in the optimizer
def test_sound_is_the_default_with_the_global_posterior_recommendation() -> None:
    cfg = OptimizerConfig()
    assert cfg.stopping is StoppingKind.SOUND and cfg.recommend is RecommendKind.GLOBAL
    assert (cfg.min_decision_s, cfg.boundary_s, cfg.a_floor, cfg.accept_z) == (30.0, 60.0, 1.0, 2.0)
    floor = OptimizerConfig(stopping="sound-floor")
    assert floor.min_decision_s == 60.0 and floor.recommend is RecommendKind.GLOBAL
    assert OptimizerConfig(stopping="adaptive").recommend is RecommendKind.SEED
    assert OptimizerConfig.from_json(cfg.to_json()) == cfg


@pytest.mark.parametrize("kw, match", [
    ({"a_floor": -1.0}, "a_floor"), ({"min_decision_s": math.inf}, "min_decision_s"),
    ({"recommend": "lowest"}, "recommend"), ({"explore_rel_sd": 0.0}, "explore_rel_sd"),
    ({"recommend_beta": -1.0}, "recommend_beta"), ({"gp_prior_stopping": 1}, "gp_prior_stopping"),
    ({"boundary_s": 0.0}, "boundary_s"), ({"boundary_s": math.nan}, "boundary_s"),
])
def test_bad_optimizer_options(kw, match) -> None:
    with pytest.raises(ConfigError, match=match):
        OptimizerConfig(**kw)


def _gp_like(opt: HILOptimizer) -> GaussianProcess:
    """The optimizer's GP, rebuilt from its training set with its last hyperparameters."""
    U, y, v = opt._training_set()
    return GaussianProcess(opt.config.kernel).fit(U, y, v, rng=np.random.default_rng(0),
                                                  init=opt._hyp, optimize=False,
                                                  prior_mean_sd=float(opt.config.prior_mean_sd or 0.0))


def test_incumbent_is_the_gp_posterior_at_the_best_evaluated_setting() -> None:
    opt = make()
    rng = np.random.default_rng(1)
    for _ in range(4):  # exploration
        params = opt.ask()
        for i in range(20):
            opt.observe_breath(3.0 * (i + 1), cost(params) + rng.normal(0, 40.0))
    opt.ask()  # the first proposal sets x*
    mu, var = _gp_like(opt).predict(opt._evaluation_units())
    k = int(np.argmin(mu))
    params, m_star, v_star = opt.incumbent
    assert params == opt.evaluations[k].params
    assert m_star == pytest.approx(mu[k], rel=1e-9) and v_star == pytest.approx(var[k], rel=1e-9)
    assert m_star != opt.evaluations[k].mean  # not the raw estimate


def test_sound_session_never_stops_early_or_when_looking_better() -> None:
    steps = drive(make(), np.random.default_rng(2))
    stops = [(t, s) for t, s in steps if s.stop and s.evaluation.reason == "threshold"]
    assert stops, "no early stop on a landscape with clearly bad settings"
    for t, s in stops:
        assert t >= 30.0  # min_decision_s
        assert s.decision.z > s.decision.threshold >= 1.0  # floored: the candidate looked worse


def test_adaptive_keeps_the_seed_rule() -> None:
    steps = drive(make(stopping="adaptive"), np.random.default_rng(2))
    early = [t for t, s in steps if s.stop and s.evaluation.reason == "threshold"]
    assert early and min(early) < 30.0  # Kim et al. 2019's rule decides from the first breaths


# ---------------------------------------------------------------- best()
def _told(recommend: str | None = None, beta: float = 1.0) -> HILOptimizer:
    """Five well-measured settings around 360–400 W and one far corner 'measured' at 250 W
    with the variance of a single breath."""
    opt = HILOptimizer(SPACE, estimator_factory=product_estimator, n_explore=2, seed=0,
                       n_candidates=64, recommend=recommend, recommend_beta=beta)
    rng = np.random.default_rng(5)
    for k in range(5):
        x = SPACE.from_unit(np.clip(OPT_U + rng.normal(0, 0.05, 6), 0, 1))
        if SPACE.is_feasible(x):
            opt.tell(SPACE.to_dict(x), 360.0 + 10.0 * k, 15.0**2, breaths=45)
    lucky = SPACE.design(8, np.random.default_rng(9), kind="maximin")[7]  # a corner
    opt.tell(SPACE.to_dict(lucky), 250.0, 150.0**2, breaths=1)
    return opt


def _best_gp(opt: HILOptimizer) -> GaussianProcess:
    """The GP best() fits before any proposal: hyperparameters refitted with its private rng."""
    U, y, v = opt._training_set()
    rng = np.random.default_rng([opt.config.seed, len(opt.evaluations)])
    return GaussianProcess(opt.config.kernel).fit(U, y, v, rng=rng, optimize=True,
                                                  prior_mean_sd=float(opt.config.prior_mean_sd or 0.0))


def test_best_is_the_posterior_not_the_raw_estimate() -> None:
    opt = _told("posterior")
    params, mean, var = opt.best()
    gp = _best_gp(opt)
    mu, v = gp.predict(opt._evaluation_units())
    k = int(np.argmin(mu + np.sqrt(v)))
    assert params == opt.evaluations[k].params
    assert (mean, var) == pytest.approx((mu[k], v[k]), rel=1e-9)
    assert opt.evaluations[k].breaths == 45  # not the one-breath 250 W setting


def test_best_seed_kind_reports_the_raw_estimate() -> None:
    opt = _told("seed")
    params, mean, var = opt.best()
    mu = _best_gp(opt).predict_mean(opt._evaluation_units())
    ev = opt.evaluations[int(np.argmin(mu))]
    assert (params, mean, var) == (ev.params, ev.mean, ev.var)


def test_confirmation_measures_the_frozen_recommendation_in_full_and_reports_its_own_estimate() -> None:
    import json

    opt = HILOptimizer(SPACE, estimator_factory=product_estimator, n_explore=2, seed=0,
                       n_candidates=64, max_breaths=10, min_decision_s=0.0, a_floor=0.0)
    rng = np.random.default_rng(3)
    for k in range(4):
        x = SPACE.from_unit(np.clip(OPT_U + rng.normal(0, 0.1, 6), 0, 1))
        if SPACE.is_feasible(x):
            opt.tell(SPACE.to_dict(x), 330.0 + 20.0 * k, 20.0**2, breaths=3)
    assert opt.confirmation is None
    recommended, p_mean, p_var = opt.best()
    assert opt.begin_confirmation() and opt.begin_confirmation()  # idempotent
    assert opt.confirmation is None  # chosen by the next ask (the proposal worker's GP work)
    assert opt.ask() == recommended
    conf = opt.confirmation
    assert conf.params == recommended and conf.mean_w is None and conf.n_evaluations == 0
    assert (conf.predicted_mean_w, conf.predicted_sd_w**2) == pytest.approx((p_mean, p_var))
    for k in range(2):
        if k:
            assert opt.ask() == recommended
        for i in range(9):
            step = opt.observe_breath(3.0 * (i + 1), 900.0)  # looks terrible: still not stopped
            assert not step.stop
        step = opt.observe_breath(30.0, 900.0)
        assert step.stop and step.evaluation.reason == "max_measurements"
    conf = opt.confirmation
    assert conf.n_evaluations == 2 and conf.breaths == 20
    # Its own breaths, not the GP: the estimate is near what was measured (900 W).
    assert conf.mean_w == pytest.approx(900.0, rel=0.05)
    assert opt.best() == (recommended, conf.mean_w, conf.sd_w**2)
    assert "confirmed at" in conf.describe()
    clone = HILOptimizer.from_json(json.loads(json.dumps(opt.to_json())),
                                   estimator_factory=product_estimator)
    assert clone.confirmation == conf and clone.ask() == recommended


def test_no_confirmation_during_exploration() -> None:
    opt = HILOptimizer(SPACE, estimator_factory=product_estimator, n_explore=2, seed=0, n_candidates=64)
    assert not opt.begin_confirmation() and opt.confirmation is None


def test_exploration_ends_once_precise_and_algorithm_2_reads_the_padded_trace() -> None:
    opt = HILOptimizer(SPACE, n_explore=2, max_breaths=45, seed=0, n_candidates=64,
                       explore_rel_sd=0.04, min_decision_s=60.0)
    rng = np.random.default_rng(8)
    ends = []
    for _ in range(2):
        opt.ask()
        t = 0.0
        while True:
            t += 3.0
            step = opt.observe_breath(t, 400.0 * (1 + 0.08 * rng.standard_normal()))
            if step.stop:
                break
        ends.append((t, step))
    for t, step in ends:
        assert 60.0 <= t < 45 * 3.0 and step.evaluation.reason == "precise"
        assert not step.evaluation.stopped_early  # not a rejection
        assert math.sqrt(step.var) <= 0.04 * step.mean
    M, _S = opt.exploration_traces
    assert M.shape == (2, 45) and opt.thresholds is not None and opt.thresholds.shape == (45,)
    assert M[0, -1] == opt.evaluations[0].mean


def test_json_round_trip_mid_evaluation_keeps_the_candidate_prior() -> None:
    import json

    opt = make(budget_breaths=60)
    rng = np.random.default_rng(4)
    for _ in range(4):
        params = opt.ask()
        for i in range(20):
            opt.observe_breath(3.0 * (i + 1), cost(params) + rng.normal(0, 40.0))
    params = opt.ask()
    for i in range(5):
        opt.observe_breath(3.0 * (i + 1), cost(params))
    state = json.loads(json.dumps(opt.to_json()))
    assert state["current"]["prior"] is not None and state["current"]["remeasure"] is False
    clone = HILOptimizer.from_json(state, estimator_factory=product_estimator)
    assert clone.to_json() == opt.to_json()
    for o in (opt, clone):
        r = np.random.default_rng(11)
        t = 15.0
        while not o.done:
            p = o.ask()
            t += 3.0
            if o.observe_breath(t, cost(p) + r.normal(0, 40.0)).stop:
                t = 0.0
    assert [e.to_json() for e in opt.evaluations] == [e.to_json() for e in clone.evaluations]


def test_drift_time_input_predicts_now_and_follows_a_falling_cost() -> None:
    """With drift_hours, the GP has one more input (the evaluation's session time), and the
    posterior of a setting measured early follows what later measurements of it say."""
    opt = HILOptimizer(SPACE, estimator_factory=product_estimator, n_explore=2, seed=0,
                       n_candidates=64, drift_hours=2.0)
    x = SPACE.to_dict(SPACE.from_unit(OPT_U))
    far = SPACE.to_dict(SPACE.design(8, np.random.default_rng(9), kind="maximin")[7])
    for k in range(8):  # the same setting, 10 min apart, its cost falling 2 W per measurement
        opt.tell(x, 400.0 - 2.0 * k, 3.0**2, duration_s=600.0)
        opt.tell(far, 500.0, 3.0**2, duration_s=1.0)
    U, _, _ = opt._training_set()
    assert U.shape == (16, SPACE.dim + 1)
    scale = 0.25 * math.sqrt(SPACE.dim + 1) / 2.0
    assert U[2, -1] == pytest.approx(1201.0 / 3600.0 * scale)
    _, mean, _ = opt.best()
    assert mean < 392.0  # closer to the latest 386 W than to the 393 W average
    opt.ask()  # a proposal with the time input works end to end
    with pytest.raises(ConfigError, match="drift_hours"):
        OptimizerConfig(drift_hours=0.0)
