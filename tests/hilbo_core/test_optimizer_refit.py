"""HILOptimizer's ``refit_growth``: when GP hyperparameters are refitted, and what is kept."""

from __future__ import annotations

import json

import numpy as np
import pytest
from test_optimizer import SPACE, cost, product_estimator  # the same synthetic session

from hilbo_core.errors import ConfigError
from hilbo_core.gp import GaussianProcess
from hilbo_core.optimizer import HILOptimizer, OptimizerConfig, PriorObservation


def make(**kw) -> HILOptimizer:
    # stopping="fixed" with max_breaths 2: every evaluation is 2 breaths, so the evaluation count
    # after k proposals is known exactly.
    opts = {"n_explore": 4, "max_breaths": 2, "window": 0, "budget_breaths": 40, "seed": 3,
            "n_candidates": 64, "n_local": 0, "stopping": "fixed"}
    opts.update(kw)
    return HILOptimizer(SPACE, estimator_factory=product_estimator, **opts)


def evaluate(opt: HILOptimizer, rng: np.random.Generator) -> dict[str, float]:
    """Ask once and measure that setting until its evaluation ends; returns the setting."""
    params = opt.ask()
    t = 0.0
    while not opt.observe_breath(t := t + 3.0, cost(params) + rng.normal(0, 40.0)).stop:
        pass
    return params


def run(opt: HILOptimizer, rng: np.random.Generator) -> list[dict[str, float]]:
    asked = []
    while not opt.done:
        asked.append(evaluate(opt, rng))
    return asked


@pytest.mark.parametrize("bad", [0.5, 0.999, 0.0, -1.0, float("nan"), float("inf"), "2", True, None])
def test_refit_growth_is_validated_and_the_error_names_the_value(bad: object) -> None:
    with pytest.raises(ConfigError, match=rf"refit_growth={bad!r}; expected a finite factor >= 1.0"):
        OptimizerConfig(refit_growth=bad)  # type: ignore[arg-type]
    with pytest.raises(ConfigError, match="refit_growth="):
        HILOptimizer(SPACE, refit_growth=bad)


def test_default_refits_at_every_proposal(optimize_calls: list[int]) -> None:
    opt = make()
    assert opt.config.refit_growth == 1.0
    run(opt, np.random.default_rng(0))
    # 4 exploration evaluations, then 20 proposals on 4, 5, ..., 23 observations.
    assert optimize_calls == list(range(4, 24))


def test_growth_two_refits_when_the_observations_have_doubled(optimize_calls: list[int]) -> None:
    opt = make(refit_growth=2.0)
    run(opt, np.random.default_rng(0))
    assert len(opt.evaluations) == 24
    # First proposal on 4 observations, then at 8 and 16; the others re-condition only.
    assert optimize_calls == [4, 8, 16]


def test_fractional_growth_rounds_up_and_is_robust_to_round_off(optimize_calls: list[int]) -> None:
    opt = make(refit_growth=1.1, n_explore=10, budget_breaths=16)
    run(opt, np.random.default_rng(0))
    # ceil(1.1·10) = 11 (1.1·10 is 11.000000000000002 in floating point), ceil(1.1·11) = 13,
    # ceil(1.1·13) = 15, ceil(1.1·15) = 17 (past the 18 evaluations' last proposal at 17).
    assert optimize_calls == [10, 11, 13, 15, 17]


def test_best_and_incumbent_use_the_proposal_model_between_refits(optimize_calls: list[int]) -> None:
    opt = make(refit_growth=2.0)
    rng = np.random.default_rng(1)
    for _ in range(6):  # 4 exploration + 2 proposals (refit at 4, re-conditioned at 5)
        evaluate(opt, rng)
    assert optimize_calls == [4]
    before = json.dumps(opt.to_json())
    best = opt.best()  # 6 observations < 8: re-conditioned, no optimisation, no state change
    assert optimize_calls == [4]
    assert json.dumps(opt.to_json()) == before
    evaluate(opt, rng)  # the proposal on 6 observations: the same model as best() had
    assert optimize_calls == [4]
    assert opt.incumbent == best


def test_best_refits_privately_when_a_refit_is_due(optimize_calls: list[int]) -> None:
    a, b = make(refit_growth=2.0), make(refit_growth=2.0)
    ra, rb = np.random.default_rng(2), np.random.default_rng(2)
    for _ in range(8):
        evaluate(a, ra)
        evaluate(b, rb)
    n = len(optimize_calls)
    a.best()  # 8 observations >= 2·4: due, so best() optimises, but keeps nothing
    assert len(optimize_calls) == n + 1
    assert run(a, ra) == run(b, rb)


def test_json_round_trip_mid_session_gives_identical_proposals() -> None:
    rng = np.random.default_rng(9)
    opt = make(refit_growth=1.5, budget_breaths=30)
    for _ in range(7):  # refits at 4 and 6; 7 observations, next refit at 9
        evaluate(opt, rng)
    params = opt.ask()
    opt.observe_breath(3.0, cost(params))
    state = json.loads(json.dumps(opt.to_json()))
    assert state["n_at_fit"] == 6 and state["config"]["refit_growth"] == 1.5
    clone = HILOptimizer.from_json(state, estimator_factory=product_estimator)
    assert clone.to_json() == opt.to_json()
    for o in (opt, clone):  # the evaluation in progress ends with its second breath
        assert o.observe_breath(6.0, cost(params)).stop
    r1, r2 = np.random.default_rng(11), np.random.default_rng(11)
    assert run(opt, r1) == run(clone, r2)
    assert [e.to_json() for e in opt.evaluations] == [e.to_json() for e in clone.evaluations]


def test_state_without_the_new_keys_loads_and_refits_next(optimize_calls: list[int]) -> None:
    rng = np.random.default_rng(4)
    opt = make()
    for _ in range(6):
        evaluate(opt, rng)
    state = json.loads(json.dumps(opt.to_json()))
    del state["n_at_fit"]  # a state written before refit_growth existed
    del state["config"]["refit_growth"]
    clone = HILOptimizer.from_json(state, estimator_factory=product_estimator)
    assert clone.config.refit_growth == 1.0
    n = len(optimize_calls)
    evaluate(clone, rng)
    assert len(optimize_calls) == n + 1


def test_refit_growth_is_deterministic_for_a_seed() -> None:
    a, b = make(refit_growth=1.25, seed=7), make(refit_growth=1.25, seed=7)
    assert run(a, np.random.default_rng(5)) == run(b, np.random.default_rng(5))


def test_cached_unit_points_match_a_fresh_conversion() -> None:
    prior = PriorObservation(SPACE.to_dict(SPACE.from_unit(np.full(SPACE.dim, 0.5))), 350.0, 50.0**2)
    opt = make(refit_growth=1.5, budget_breaths=12)
    opt.add_prior(prior)
    rng = np.random.default_rng(6)
    for _ in range(6):
        evaluate(opt, rng)
    opt.tell(opt.evaluations[0].params, 333.0, 20.0)  # evaluations told from outside count too
    U, y, v = opt._training_set()
    fresh = [SPACE.from_dict(e.params) for e in opt.evaluations] + [SPACE.from_dict(prior.params)]
    np.testing.assert_array_equal(U, SPACE.to_unit(np.array(fresh)))
    assert y[-2:].tolist() == [333.0, 350.0] and v[-1] == 50.0**2
    clone = HILOptimizer.from_json(json.loads(json.dumps(opt.to_json())), estimator_factory=product_estimator)
    np.testing.assert_array_equal(clone._training_set()[0], U)


@pytest.mark.parametrize("feature_map", [None, lambda X: np.hstack([X, X[:, :1] ** 2])])
def test_predict_mean_is_predicts_mean_bit_for_bit(feature_map) -> None:
    # HILOptimizer's incumbent uses predict_mean; it must pick the same point predict would.
    rng = np.random.default_rng(0)
    X = rng.uniform(size=(40, 3))
    y = np.sin(6 * X[:, 0]) + X[:, 1] + rng.normal(0, 0.1, 40)
    gp = GaussianProcess(feature_map=feature_map).fit(X, y, np.full(40, 0.01), rng=rng)
    Xs = np.vstack([X, rng.uniform(size=(25, 3))])
    np.testing.assert_array_equal(gp.predict_mean(Xs), gp.predict(Xs)[0])
