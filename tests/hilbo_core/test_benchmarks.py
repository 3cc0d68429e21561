"""hilbo_core.studies.benchmarks: Table I functions, the measurement model, y_t and one trial."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hilbo_core.errors import ConfigError
from hilbo_core.metabolic import GaussianProductEstimator
from hilbo_core.optimizer import OptimizerConfig
from hilbo_core.space import DesignKind
from hilbo_core.studies.benchmarks import (
    FUNCTIONS,
    MEASUREMENT_INTERVAL_S,
    METHODS,
    SOUND_STUDY_FLOOR_S,
    NoiseEstimate,
    StoppingMethod,
    StoppingProtocol,
    ackley,
    branin,
    estimator_factory,
    hartmann6,
    levy,
    measure,
    stopping_trial,
    y_metric,
)

TOY = StoppingProtocol(n_explore=3, max_breaths=5, window=1, budget=20, n_candidates=64, n_local=0)


# ------------------------------------------------------------------ functions at known points
def test_hartmann6_at_its_literature_minimiser() -> None:
    x_star = [0.20169, 0.150011, 0.476874, 0.275332, 0.311652, 0.6573]
    assert float(hartmann6(x_star)) == pytest.approx(-3.32237, abs=1e-5)


def test_branin_at_its_three_minimisers_and_the_origin() -> None:
    for x in ([-math.pi, 12.275], [math.pi, 2.275], [9.42478, 2.475]):
        assert float(branin(x)) == pytest.approx(0.397887, abs=1e-6)
    # (0, 0): (−6)² + 10(1 − 1/(8π))·cos 0 + 10 = 56 − 10/(8π)
    assert float(branin([0.0, 0.0])) == pytest.approx(56.0 - 10.0 / (8.0 * math.pi), rel=1e-12)


def test_ackley_reference_values() -> None:
    assert float(ackley(np.zeros(4))) == pytest.approx(0.0, abs=1e-15)  # −a − e + a + e
    # At (1, 1, 1, 1): cos(2π) = 1, so f = 20(1 − e^{−0.2}).
    assert float(ackley(np.ones(4))) == pytest.approx(20.0 * (1.0 - math.exp(-0.2)), rel=1e-12)


def test_levy_reference_values() -> None:
    assert float(levy(np.ones(4))) == pytest.approx(0.0, abs=1e-15)
    # At the origin w = 3/4 in every coordinate.
    w = 0.75
    expected = (math.sin(math.pi * w) ** 2
                + 3 * (w - 1) ** 2 * (1 + 10 * math.sin(math.pi * w + 1) ** 2)
                + (w - 1) ** 2 * (1 + math.sin(2 * math.pi * w) ** 2))
    assert float(levy(np.zeros(4))) == pytest.approx(expected, rel=1e-12)


@pytest.mark.parametrize("name", sorted(FUNCTIONS))
def test_every_function_reaches_f_min_at_its_minimisers_and_nowhere_lower(name: str) -> None:
    fn = FUNCTIONS[name]
    for m in fn.minimizers:
        assert float(fn(np.array(m))) == pytest.approx(fn.f_min, abs=1e-5)
    rng = np.random.default_rng(11)
    lo, hi = np.array(fn.lower), np.array(fn.upper)
    values = fn(lo + (hi - lo) * rng.uniform(size=(20_000, fn.dim)))
    assert values.shape == (20_000,)
    assert values.min() >= fn.f_min - 1e-12


@pytest.mark.parametrize("name", sorted(FUNCTIONS))
def test_table_one_priors_are_the_mean_and_sd_over_the_domain(name: str) -> None:
    # Kim et al. 2019 Table I's (μ̃, σ̃) are the moments of f under a uniform x on the domain.
    fn = FUNCTIONS[name]
    rng = np.random.default_rng(5)
    lo, hi = np.array(fn.lower), np.array(fn.upper)
    values = fn(lo + (hi - lo) * rng.uniform(size=(200_000, fn.dim)))
    assert abs(values.mean() - fn.prior_mean) < 0.02 * fn.prior_std
    assert values.std() == pytest.approx(fn.prior_std, rel=0.02)


def test_functions_reject_points_of_the_wrong_dimension() -> None:
    with pytest.raises(ConfigError, match="dimension 6"):
        hartmann6(np.zeros(4))
    with pytest.raises(ConfigError, match="dimension 2"):
        branin(np.zeros((3, 5)))


def test_value_reads_a_parameter_dict_like_the_optimizer_reports_it() -> None:
    fn = FUNCTIONS["branin"]
    assert fn.value({"x1": math.pi, "x2": 2.275}) == pytest.approx(fn.f_min, abs=1e-12)
    space = fn.space()
    assert space.names == ("x1", "x2") and space.dim == 2
    assert list(space.lower) == [-5.0, 0.0] and list(space.upper) == [10.0, 15.0]


# ------------------------------------------------------------------ measurement model and metric
def test_measure_adds_gaussian_noise_of_the_given_variance() -> None:
    rng = np.random.default_rng(3)
    z = np.array([measure(2.0, 9.0, rng) for _ in range(20_000)])
    assert z.mean() == pytest.approx(2.0, abs=0.07)
    assert z.var() == pytest.approx(9.0, rel=0.05)
    assert measure(2.0, 9.0, np.random.default_rng(1)) == measure(2.0, 9.0, np.random.default_rng(1))


def test_y_metric_reference_values() -> None:
    assert y_metric(5.0, 5.0, 1.0) == 1.0
    assert y_metric(1.0, 5.0, 1.0) == 0.0
    assert y_metric(3.0, 5.0, 1.0) == 0.5
    assert y_metric(9.0, 5.0, 1.0) == 2.0  # worse than x_0
    np.testing.assert_allclose(y_metric([1.0, 3.0], 5.0, 1.0), [0.0, 0.5])
    # x_0 already optimal: y is 0 at the optimum, inf elsewhere.
    assert y_metric(1.0, 1.0, 1.0) == 0.0 and y_metric(2.0, 1.0, 1.0) == math.inf


@settings(max_examples=60, deadline=None)
@given(st.floats(-1e3, 1e3), st.floats(1e-3, 1e3), st.floats(0, 1e3), st.floats(0, 1e3))
def test_y_metric_is_non_negative_and_monotone(f_min: float, gap0: float, a: float, b: float) -> None:
    ya, yb = y_metric(f_min + a, f_min + gap0, f_min), y_metric(f_min + b, f_min + gap0, f_min)
    assert ya >= 0.0 and yb >= 0.0
    assert (ya <= yb) == (a <= b) or math.isclose(ya, yb)


# ------------------------------------------------------------------ one trial
@pytest.fixture(scope="module")
def toy_trials() -> dict[str, dict]:
    return {m: stopping_trial("branin", 1.0, m, 7, TOY) for m in ("fixed", "adaptive")}


def test_trial_respects_the_budget_and_starts_at_one(toy_trials: dict[str, dict]) -> None:
    for r in toy_trials.values():
        assert r["measurements"] == TOY.budget
        assert len(r["y"]) == TOY.budget + 1
        assert r["y"][0] == 1.0
        assert all(np.isfinite(r["y"])) and min(r["y"]) >= 0.0  # f(x_0) > f* here
        assert r["y"][-1] == pytest.approx(y_metric(r["f_final"], r["f_x0"], FUNCTIONS["branin"].f_min))


def test_fixed_measures_every_evaluation_n_times_and_changes_y_only_at_their_ends(
        toy_trials: dict[str, dict]) -> None:
    r = toy_trials["fixed"]
    assert r["evaluations"] == TOY.budget // TOY.max_breaths and r["early_stops"] == 0
    y = r["y"]
    for t in range(1, len(y)):
        if t % TOY.max_breaths:
            assert y[t] == y[t - 1]


def test_methods_of_a_trial_share_exploration_and_x0(toy_trials: dict[str, dict]) -> None:
    fixed, adaptive = toy_trials["fixed"], toy_trials["adaptive"]
    assert fixed["x0"] == adaptive["x0"] and fixed["f_x0"] == adaptive["f_x0"]
    assert adaptive["evaluations"] >= fixed["evaluations"]
    assert adaptive["early_stops"] <= adaptive["evaluations"]


def test_trial_is_deterministic_in_its_arguments(toy_trials: dict[str, dict]) -> None:
    again = stopping_trial("branin", 1.0, "adaptive", 7, TOY)
    assert again == toy_trials["adaptive"]
    other = stopping_trial("branin", 1.0, "adaptive", 8, TOY)
    assert other["x0"] != again["x0"]


def test_trial_accepts_negative_objectives_and_custom_methods() -> None:
    custom = StoppingMethod("fixed_ei_xi", "fixed stopping, ξ = 0.01", {"stopping": "fixed", "xi": 0.01})
    proto = StoppingProtocol(n_explore=3, max_breaths=4, budget=8, n_candidates=32, n_local=0)
    r = stopping_trial(FUNCTIONS["hartmann6"], 0.1, custom, 2, proto)  # Hartmann-6 is negative
    assert r["method"] == "fixed_ei_xi" and r["f_x0"] < 0 and len(r["y"]) == 9


@pytest.mark.parametrize(("kwargs", "match"), [
    ({"function": "rosenbrock"}, "unknown function 'rosenbrock'; choose one of"),
    ({"method": "bogus"},
     r"unknown method 'bogus'; choose one of \['adaptive', 'fixed', 'sound', 'sound-60s'\]"),
    ({"noise": 0.0}, "noise=0.0"),
    ({"noise": "loud"}, "noise='loud'"),
    ({"seed": -1}, "seed=-1"),
])
def test_trial_rejects_bad_input_by_name(kwargs: dict, match: str) -> None:
    args = {"function": "branin", "noise": 1.0, "method": "fixed", "seed": 0, **kwargs}
    with pytest.raises(ConfigError, match=match):
        stopping_trial(args["function"], args["noise"], args["method"], args["seed"], TOY)


def test_noise_models_agree_at_the_prior_variance_and_differ_elsewhere() -> None:
    # matched: measurement variance = σ_z²; assumed: σ̃² (σ_z² only in the estimator). At
    # σ_z² = σ̃² the two readings of Kim et al. 2019 §III.2 are the same experiment.
    proto = {"n_explore": 3, "max_breaths": 4, "budget": 8, "n_candidates": 32, "n_local": 0,
             "noise_estimate": "seed"}
    matched = StoppingProtocol(**proto, noise_model="matched")  # type: ignore[arg-type]
    assumed = StoppingProtocol(**proto, noise_model="assumed")  # type: ignore[arg-type]
    same = [stopping_trial("branin", 1.0, "adaptive", 3, p) for p in (matched, assumed)]
    assert same[0] == same[1]
    # At 10σ̃² "assumed" measures with variance σ̃² only: different data, a different run (the
    # number of evaluations may coincide; the point is only that the data differ).
    high = [stopping_trial("branin", 10.0, "adaptive", 5, p) for p in (matched, assumed)]
    assert (high[0]["y"], high[0]["x_final"]) != (high[1]["y"], high[1]["x_final"])


def test_protocol_rejects_a_budget_smaller_than_one_evaluation() -> None:
    with pytest.raises(ConfigError, match="budget=10 measurements is smaller than one full evaluation"):
        StoppingProtocol(max_breaths=45, budget=10)
    with pytest.raises(ConfigError, match="noise_model='loud'"):
        StoppingProtocol(noise_model="loud")  # type: ignore[arg-type]
    with pytest.raises(ConfigError, match="noise_estimate='guess'"):
        StoppingProtocol(noise_estimate="guess")  # type: ignore[arg-type]


def test_noise_estimate_defaults_to_pooled_and_seed_is_the_seeds_estimator() -> None:
    assert StoppingProtocol().noise_estimate is NoiseEstimate.POOLED
    assert StoppingProtocol().to_json()["noise_estimate"] == "pooled"
    fn = FUNCTIONS["branin"]
    seed = estimator_factory(fn, 0.1, "seed")()
    assert isinstance(seed, GaussianProductEstimator)
    seed.update(1.0, 10.0)
    # Kim et al. 2019's: fused with σ_z² = 0.1σ̃², whatever the data say.
    assert seed.var == pytest.approx(1.0 / (1.0 / fn.prior_std**2 + 1.0 / (0.1 * fn.prior_std**2)))
    # Pooled: the estimators of one factory (one trial) share one variance, another trial's don't.
    make = estimator_factory(fn, 0.1)
    a, b, other = make(), make(), estimator_factory(fn, 0.1)()
    for est in (b, other):
        est.update(1.0, 10.0)
    a.update(1.0, 10.0)
    before = (a.var, other.var)
    for i, z in enumerate((-100.0, 100.0, -100.0)):
        b.update(float(i + 2), z)
    assert a.var > before[0]
    assert other.var == before[1]


def test_methods_may_not_override_the_protocol() -> None:
    bad = StoppingMethod("cheat", "bigger budget", {"budget_breaths": 10_000})
    with pytest.raises(ConfigError, match="may not override protocol option"):
        stopping_trial("branin", 1.0, bad, 0, TOY)
    assert set(METHODS) == {"fixed", "adaptive", "sound", "sound-60s"}


def test_the_study_design_has_no_centre_point_so_x0_is_not_ackleys_optimum() -> None:
    # Ackley's optimum is the domain's centre: a design that starts there (a lab session's)
    # would hand every method the answer before the study begins (the seed's Fig. 2 has none).
    proto = StoppingProtocol(n_explore=6, max_breaths=3, window=1, budget=3, n_candidates=64, n_local=0)
    assert proto.design is DesignKind.SOBOL_ONLY
    fn = FUNCTIONS["ackley"]
    for seed in range(5):
        r = stopping_trial("ackley", 0.1, "fixed", seed, proto)
        assert r["f_x0"] > fn.f_min + 1.0
    lab = StoppingProtocol(n_explore=6, max_breaths=3, window=1, budget=3, n_candidates=64,
                           n_local=0, design="sobol")
    assert stopping_trial("ackley", 0.1, "fixed", 0, lab)["f_x0"] < stopping_trial(
        "ackley", 0.1, "fixed", 0, proto)["f_x0"]


def test_the_study_runs_the_lab_sound_rule_without_its_time_floor() -> None:
    # The lab's rule, only its time floor (the transition the study does not have) is 0; its
    # sequential boundary (60 s: 20 measurements) stays.
    lab = OptimizerConfig()
    assert SOUND_STUDY_FLOOR_S == 0.0 and lab.min_decision_s == 30.0 and lab.boundary_s == 60.0
    assert dict(METHODS["sound"].options) == {"stopping": "sound", "min_decision_s": 0.0}
    assert dict(METHODS["sound-60s"].options) == {"stopping": "sound-floor"}
    assert MEASUREMENT_INTERVAL_S == 3.0  # sound-60s: the 60 s floor is 20 measurements


def test_without_the_time_floor_the_sound_rule_measures_more_settings() -> None:
    proto = StoppingProtocol(n_explore=4, max_breaths=45, window=2, budget=450, n_candidates=64,
                             n_local=0)
    free = stopping_trial("branin", 0.1, "sound", 3, proto)
    floored = stopping_trial("branin", 0.1, "sound-60s", 3, proto)
    assert free["measurements"] == floored["measurements"] == 450
    # With the floor every evaluation but the last takes >= 20 of the 450 measurements.
    assert floored["early_stops"] >= 1 and floored["evaluations"] <= 450 // 20 + 1
    # Without it, the same trial measures more settings in the same 450 measurements.
    assert free["early_stops"] >= floored["early_stops"]
    assert free["evaluations"] > floored["evaluations"] + 2


def test_the_study_gp_is_kim_et_als_unless_a_prior_mean_is_given(toy_trials: dict[str, dict]) -> None:
    # Every method of a trial shares one GP: by default the seed's (prior mean at the average),
    # and the protocol of earlier campaigns reads the same (no key for the default).
    assert "prior_mean_sd" not in StoppingProtocol().to_json()
    lab = dataclasses.replace(TOY, prior_mean_sd=0.5)
    assert lab.to_json()["prior_mean_sd"] == 0.5
    runs = {m: stopping_trial("hartmann6", 1.0, m, 7, lab) for m in ("fixed", "sound")}
    assert runs["fixed"]["x0"] == runs["sound"]["x0"]
    assert stopping_trial("hartmann6", 1.0, "fixed", 7, TOY)["y"] != runs["fixed"]["y"]
    with pytest.raises(ConfigError, match="prior_mean_sd=4"):
        StoppingProtocol(prior_mean_sd=4)
