"""Tests of the issue-16 estimator (hilbo_core.estimation) and of data-only GP observations."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hilbo_core.errors import ConfigError, EstimatorError, MeasurementError
from hilbo_core.estimation import EstimatorKind, StartState, TransitionConfig, TransitionEstimator
from hilbo_core.metabolic import (
    DataOnlyEstimator,
    GaussianProductEstimator,
    MetabolicUKF,
    UKFConfig,
    divide_gaussian,
)
from hilbo_core.optimizer import HILOptimizer, OptimizerConfig
from hilbo_core.space import Parameter, ParameterSpace

# ---------------------------------------------------------------- Gaussian division


def test_divide_gaussian_hand_computed() -> None:
    # posterior N(1.6, 0.8) = prior N(0, 4) × likelihood: 1/0.8 − 1/4 = 1 → var 1;
    # mean = 1·(1.6/0.8 − 0/4) = 2.
    assert divide_gaussian(1.6, 0.8, 0.0, 4.0) == pytest.approx((2.0, 1.0), rel=1e-12)
    # posterior N(10, 1), prior N(4, 2): precision 1 − 0.5 = 0.5 → var 2; mean 2·(10 − 2) = 16.
    assert divide_gaussian(10.0, 1.0, 4.0, 2.0) == pytest.approx((16.0, 2.0), rel=1e-12)


def test_divide_gaussian_without_information_is_a_harmless_observation() -> None:
    # posterior == prior (or wider, from an approximate filter): no data information.
    assert divide_gaussian(5.0, 2.0, 5.0, 2.0) == (5.0, 2e6)
    assert divide_gaussian(5.5, 3.0, 5.0, 2.0) == (5.5, 2e6)


@pytest.mark.parametrize("args", [(math.nan, 1.0, 0.0, 1.0), (0.0, 0.0, 0.0, 1.0), (0.0, 1.0, 0.0, -1.0)])
def test_divide_gaussian_rejects_bad_input(args: tuple[float, float, float, float]) -> None:
    with pytest.raises(EstimatorError, match="divide_gaussian"):
        divide_gaussian(*args)


def test_gaussian_product_data_only_hand_computed() -> None:
    # Prior (0, 4), measurement variance 2, z = 1 and 3: posterior var 1/(1/4 + 2/2) = 0.8,
    # mean 0.8·(0 + 4/2) = 1.6; the data alone: mean of z = 2, variance 2/2 = 1.
    est = GaussianProductEstimator(0.0, 4.0, 2.0)
    est.update(1.0, 1.0)
    assert est.update(2.0, 3.0) == pytest.approx((1.6, 0.8), rel=1e-12)
    assert est.data_only() == pytest.approx((2.0, 1.0), rel=1e-12)
    assert isinstance(est, DataOnlyEstimator)


def test_ukf_data_only_hand_computed() -> None:
    ukf = MetabolicUKF(UKFConfig(c_rel_std=0.5))
    ukf.update(0.0, 400.0)
    # The first breath only sets the prior: c ~ N(400, (0.5·400)²) = N(400, 40000), so the
    # breaths carry no information about c yet (their information sits in the prior of c0).
    assert ukf.var == pytest.approx(40000.0)
    assert ukf.data_only() == (400.0, 40000.0 * 1e6)
    for t, w in [(3.0, 410.0), (6.0, 430.0), (9.0, 445.0), (12.0, 440.0)]:
        mean, var = ukf.update(t, w)
    prec = 1.0 / var - 1.0 / 40000.0
    assert ukf.data_only() == pytest.approx((1.0 / prec * (mean / var - 400.0 / 40000.0), 1.0 / prec),
                                           rel=1e-12)
    assert ukf.data_only()[1] > var  # less certain than the posterior: the prior is gone


# ---------------------------------------------------------------- TransitionEstimator


def _transition(seed: int, b0: float, c: float, tau: float, t_end: float, cv: float = 0.1,
                outliers: dict[int, float] | None = None) -> list[tuple[float, float]]:
    rng = np.random.default_rng(seed)
    out, t = [], rng.uniform(0.5, 3.0)
    while t <= t_end:
        m = c + (b0 - c) * math.exp(-t / tau)
        out.append((t, m * (1.0 + cv * rng.normal())))
        t += rng.uniform(2.0, 3.5)
    for i, factor in (outliers or {}).items():
        out[i] = (out[i][0], out[i][1] * factor)
    return out


def test_noise_free_step_converges_to_the_steady_state() -> None:
    est = TransitionEstimator()
    est.start_from(300.0, 1.0)
    for t in np.arange(1.0, 240.0, 2.5):
        est.update(float(t), 450.0 + (300.0 - 450.0) * math.exp(-t / 40.0))
    assert est.mean == pytest.approx(450.0, rel=0.01)
    # σ ends at the model-error floor (3 % of c: the drift a real steady state has), not below,
    # and the fit adds little to it after four minutes of noise-free breaths.
    assert 0.03 * 450.0 <= math.sqrt(est.var) < 0.035 * 450.0
    assert est.noise_cv < 0.11  # noise-free breaths pull the CV below its prior median


def test_starting_level_is_used_and_helps() -> None:
    errs = {True: [], False: []}
    for seed in range(40):
        # τ at the prior's median (25 s) and 20 s in, while b0 still matters (later the breaths
        # pin b0 themselves: 0.92× at 30 s): the test is about the starting level, not τ.
        breaths = _transition(seed, 300.0, 480.0, 25.0, 20.0)
        for chained in (True, False):
            est = TransitionEstimator()
            if chained:
                est.start_from(300.0, 15.0**2)
            for t, w in breaths:
                est.update(t, w)
            errs[chained].append(abs(est.mean - 480.0))
    assert np.mean(errs[True]) < 0.85 * np.mean(errs[False])  # 0.77× measured


def test_a_swallow_does_not_drag_the_estimate() -> None:
    clean = _transition(3, 400.0, 400.0, 40.0, 150.0, cv=0.08)
    # 1.8×: a swallow still plausible for the level (2.2× and more is left out altogether),
    # so the Student-t weights are what keeps it from dragging the estimate.
    dirty = _transition(3, 400.0, 400.0, 40.0, 150.0, cv=0.08, outliers={40: 1.8})
    robust, gauss = [], []
    for cfg, out in ((TransitionConfig(), robust), (TransitionConfig(t_dof=1e6), gauss)):
        for breaths in (clean, dirty):
            est = TransitionEstimator(cfg)
            est.start_from(400.0, 100.0)
            for t, w in breaths:
                est.update(t, w)
            out.append(est.mean)
    shift_robust, shift_gauss = abs(robust[1] - robust[0]), abs(gauss[1] - gauss[0])
    assert shift_robust < 0.35 * shift_gauss
    assert shift_robust < 0.01 * 400.0


def test_noise_cv_is_estimated_online() -> None:
    breaths = _transition(11, 400.0, 400.0, 40.0, 600.0, cv=0.07)
    est = TransitionEstimator()
    est.start_from(400.0, 100.0)
    for t, w in breaths:
        est.update(t, w)
    assert 0.06 < est.noise_cv < 0.08


def test_tau_posterior_is_handed_over_and_narrows() -> None:
    est = TransitionEstimator()
    est.start_from(250.0, 100.0)
    for t, w in _transition(5, 250.0, 600.0, 35.0, 240.0):
        est.update(t, w)
    tau, post = est.tau_posterior()
    ho = est.handover()
    assert ho.level_w == pytest.approx(600.0, rel=0.05)
    nxt = TransitionEstimator()
    nxt.start_from_state(StartState.from_json(json.loads(json.dumps(ho.to_json()))))
    _, prior = nxt.tau_posterior()
    _, population = TransitionEstimator().tau_posterior()

    def log_sd(w: np.ndarray) -> float:
        m = float(w @ np.log(tau))
        return math.sqrt(float(w @ (np.log(tau) - m) ** 2))

    assert log_sd(post) < log_sd(prior) < log_sd(population)
    assert 28.0 < math.exp(float(prior @ np.log(tau))) < 42.0  # moved from 42 s towards 35 s


@pytest.mark.parametrize("t_s, watts", [
    (5.0, math.nan), (5.0, -10.0), (5.0, 0.0), (5.0, 9000.0), (5.0, math.inf),
    (2.0, 400.0), (3.0, 400.0), (math.nan, 400.0), (-1.0, 400.0), ("x", 400.0),
])
def test_bad_breaths_are_rejected_and_leave_the_estimate_unchanged(t_s: object, watts: object) -> None:
    est = TransitionEstimator()
    est.start_from(400.0, 100.0)
    est.update(1.0, 390.0)
    est.update(3.0, 410.0)
    before = json.dumps(est.state_dict())
    level_before = est.level()
    with pytest.raises(MeasurementError):
        est.update(t_s, watts)  # type: ignore[arg-type]
    assert json.dumps(est.state_dict()) == before
    assert est.level() == level_before
    est.update(6.0, 405.0)  # still usable
    assert est.n_updates == 3


def test_a_gap_of_minutes_neither_crashes_nor_corrupts() -> None:
    est = TransitionEstimator()
    est.start_from(300.0, 100.0)
    breaths = _transition(2, 300.0, 420.0, 40.0, 240.0)
    early = [(t, w) for t, w in breaths if t < 60.0]
    late = [(t + 300.0, w) for t, w in breaths if t >= 150.0]  # five minutes lost
    for t, w in early + late:
        mean, var = est.update(t, w)
        assert math.isfinite(mean) and var > 0.0
    assert est.mean == pytest.approx(420.0, rel=0.05)


def test_start_from_validates_and_only_before_the_first_breath() -> None:
    est = TransitionEstimator()
    for args in [(math.nan, 1.0), (-5.0, 1.0), (400.0, -1.0), (400.0, 1.0, 5.0), (400.0, 1.0, None, [0.0])]:
        with pytest.raises(MeasurementError):
            est.start_from(*args)  # type: ignore[arg-type]
    est.update(1.0, 400.0)
    with pytest.raises(EstimatorError, match="after the first breath"):
        est.start_from(400.0, 1.0)
    with pytest.raises(EstimatorError, match="before the first breath"):
        _ = TransitionEstimator().mean


def test_config_rejects_bad_values() -> None:
    with pytest.raises(ConfigError, match="tau_log_sd"):
        TransitionConfig(tau_log_sd=0.0)
    with pytest.raises(ConfigError, match="n_tau"):
        TransitionConfig(n_tau=2.5)  # type: ignore[arg-type]
    with pytest.raises(ConfigError, match="tau_min_s"):
        TransitionConfig(tau_min_s=100.0, tau_max_s=50.0)


def test_transition_data_only_divides_the_c_prior() -> None:
    est = TransitionEstimator()
    est.start_from(300.0, 100.0)
    for t, w in _transition(4, 300.0, 360.0, 40.0, 45.0):
        mean, var = est.update(t, w)
    # prior of c: N(start level, (c_rel_sd·level)²) = N(300, 900²), divided out of the fit's
    # posterior (the variance without the 3 % model error); the model error is added back to
    # the data-only variance (it is an error of the observation, not a prior).
    var_fit = var - (0.03 * mean) ** 2
    prec = 1.0 / var_fit - 1.0 / 900.0**2
    mean_d = (mean / var_fit - 300.0 / 900.0**2) / prec
    expected = (mean_d, 1.0 / prec + (0.03 * mean_d) ** 2)
    assert est.data_only() == pytest.approx(expected, rel=1e-9)


@settings(max_examples=40, deadline=None)
@given(st.lists(st.tuples(st.floats(0.5, 6.0), st.floats(20.0, 2000.0)), min_size=1, max_size=40),
       st.one_of(st.none(), st.floats(50.0, 1500.0)))
def test_any_valid_breaths_give_a_finite_positive_variance(
        steps: list[tuple[float, float]], start: float | None) -> None:
    est = TransitionEstimator()
    if start is not None:
        est.start_from(start, (0.05 * start) ** 2)
    t = 0.0
    for dt, w in steps:
        t += dt
        mean, var = est.update(t, w)
        assert math.isfinite(mean) and math.isfinite(var) and var > 0.0
        m, v = est.data_only()
        assert math.isfinite(m) and v > 0.0
        assert est.level()[1] >= 0.0


# ---------------------------------------------------------------- the optimizer


def _space() -> ParameterSpace:
    return ParameterSpace([Parameter("a", 0.0, 1.0), Parameter("b", 0.0, 1.0)])


def test_default_estimator_is_the_transition_fit_and_the_ukf_stays_selectable() -> None:
    opt = HILOptimizer(_space(), n_explore=2, max_breaths=3, budget_breaths=6)
    opt.ask()
    assert isinstance(opt._estimator, TransitionEstimator)
    assert OptimizerConfig().estimator is EstimatorKind.TRANSITION
    ukf = HILOptimizer(_space(), n_explore=2, max_breaths=3, budget_breaths=6, estimator="seed_ukf")
    ukf.ask()
    assert isinstance(ukf._estimator, MetabolicUKF)
    with pytest.raises(ConfigError, match="estimator='kalman'"):
        OptimizerConfig(estimator="kalman")  # type: ignore[arg-type]


def test_gp_is_told_data_only_observations() -> None:
    # Gaussian-product estimator, prior (300, 400), measurement variance 100: after z = 310, 330
    # the posterior is var 1/(1/400 + 2/100) = 44.44.., mean 44.44..·(300/400 + 640/100) = 317.78;
    # the GP gets the data alone: mean 320, variance 50.
    opt = HILOptimizer(_space(), n_explore=2, max_breaths=2, budget_breaths=4,
                       estimator_factory=lambda: GaussianProductEstimator(300.0, 400.0, 100.0))
    opt.ask()
    opt.observe(1.0, 310.0)
    ev = opt.observe(2.0, 330.0).evaluation
    assert ev is not None
    assert (ev.mean, ev.var) == pytest.approx((317.7777777778, 44.4444444444), rel=1e-9)
    assert (ev.obs_mean, ev.obs_var) == pytest.approx((320.0, 50.0), rel=1e-9)
    _, y, v = opt._training_set()
    assert (y[0], v[0]) == pytest.approx((320.0, 50.0), rel=1e-9)
    # The stopping rule keeps the posterior: the incumbent statistics are the evaluation's own.
    assert opt._incumbent_stats() == (ev.mean, ev.var)


def test_settings_are_chained_and_the_state_round_trips() -> None:
    opt = HILOptimizer(_space(), n_explore=2, max_breaths=30, budget_breaths=60)
    opt.ask()
    steps = [opt.observe_breath(t, w) for t, w in _transition(1, 300.0, 500.0, 40.0, 200.0)[:30]]
    assert steps[-1].stop and not any(s.stop for s in steps[:-1])
    opt.ask()
    est = opt._estimator
    assert isinstance(est, TransitionEstimator)
    assert est._start is not None and est._start[0] == pytest.approx(500.0, rel=0.15)
    for t, w in _transition(2, 480.0, 350.0, 40.0, 20.0):
        opt.observe_breath(t, w)
    state = json.loads(json.dumps(opt.to_json()))
    again = HILOptimizer.from_json(state)
    a, b = opt.observe_breath(25.0, 400.0), again.observe_breath(25.0, 400.0)
    assert (a.mean, a.var) == (b.mean, b.var)


def test_states_from_before_issue_16_keep_the_seed_ukf() -> None:
    opt = HILOptimizer(_space(), n_explore=2, max_breaths=3, budget_breaths=6)
    state = opt.to_json()
    del state["config"]["estimator"]
    del state["handover"]
    assert HILOptimizer.from_json(state).config.estimator is EstimatorKind.SEED_UKF


def test_many_early_stopped_settings_do_not_drift_the_persons_tau() -> None:
    # 30 settings of 6 breaths each (≈ 15 s) say almost nothing about τ: the τ prior they hand
    # on must stay near the population's (a random walk of τ, or the marginal evidence, drifted
    # it to > 80 s here).
    rng = np.random.default_rng(0)
    level, state = 400.0, None
    for _ in range(30):
        c = rng.uniform(350.0, 800.0)
        est = TransitionEstimator()
        if state is not None:
            est.start_from_state(state)
        t = rng.uniform(0.5, 3.0)
        for _ in range(6):
            m = c + (level - c) * math.exp(-t / 45.0)
            est.update(t, m * (1.0 + 0.1 * rng.normal()))
            t += rng.uniform(2.0, 3.5)
        level = m
        state = est.handover()
    nxt = TransitionEstimator()
    nxt.start_from_state(state)
    tau, prior = nxt.tau_posterior()
    # the population's median is 25 s (the data's τ is 45 s, but six breaths cannot tell)
    assert 21.0 < math.exp(float(prior @ np.log(tau))) < 31.0
