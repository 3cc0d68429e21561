"""HILOptimizer's ``refit_lag``: hyperparameters fitted ahead, off the proposal's critical path."""

from __future__ import annotations

import json
import pickle

import numpy as np
import pytest
from test_optimizer import cost  # the same synthetic session as test_optimizer_refit
from test_optimizer_refit import evaluate, make, run

from hilbo_core import fit_hyperparameters
from hilbo_core.errors import ConfigError, OptimizerStateError
from hilbo_core.gp import GPHyperparameters
from hilbo_core.optimizer import HILOptimizer, OptimizerConfig


def evaluate_fitting_ahead(opt: HILOptimizer, rng: np.random.Generator) -> dict[str, float]:
    """One evaluation as the bridge runs it: ask, fit ahead on what is complete, then measure."""
    params = opt.ask()
    fit = opt.hyperparameter_fit()
    if fit is not None:
        opt.apply_hyperparameters(fit, fit_hyperparameters(pickle.loads(pickle.dumps(fit))))
    t = 0.0
    while not opt.observe_breath(t := t + 3.0, cost(params) + rng.normal(0, 40.0)).stop:
        pass
    return params


@pytest.mark.parametrize("bad", [-1, 1.5, "1", True, None])
def test_refit_lag_is_validated_and_the_error_names_the_value(bad: object) -> None:
    with pytest.raises(ConfigError, match=rf"refit_lag={bad!r}; expected an integer >= 0"):
        OptimizerConfig(refit_lag=bad)  # type: ignore[arg-type]


def test_refit_lag_and_refit_growth_are_exclusive() -> None:
    with pytest.raises(ConfigError, match=r"refit_lag=1 with refit_growth=1.25; expected one of them only"):
        OptimizerConfig(refit_lag=1, refit_growth=1.25)


def test_fitting_ahead_takes_every_fit_off_the_proposals(optimize_calls: list[int]) -> None:
    opt = make(refit_lag=1)
    rng = np.random.default_rng(0)
    n_before = []
    while not opt.done:
        n_before.append(len(optimize_calls))
        evaluate_fitting_ahead(opt, rng)
    # Every fit ran in fit_hyperparameters, on 2, 3, ... completed observations (the one
    # being measured is not in it); asks on 4..23 observations never optimised themselves:
    # 24 evaluations, fits ahead during evaluations 3..24 on 2..23 observations.
    assert optimize_calls == list(range(2, 24))
    assert len(opt.evaluations) == 24
    state = opt.to_json()
    assert state["n_at_fit"] == 23 and state["config"]["refit_lag"] == 1


def test_without_fits_ahead_a_lag_of_one_refits_every_other_proposal(optimize_calls: list[int]) -> None:
    run(make(refit_lag=1), np.random.default_rng(0))
    # 4 (no hyperparameters yet), then due whenever more than one observation is new.
    assert optimize_calls == list(range(4, 24, 2))


def test_a_fit_is_a_snapshot_and_pure() -> None:
    opt = make(refit_lag=1)
    rng = np.random.default_rng(1)
    for _ in range(5):
        evaluate(opt, rng)
    fit = opt.hyperparameter_fit()
    assert fit is not None and fit.n_obs == 5 and fit.X_unit.shape == (5, opt.space.dim)
    y0 = fit.y.copy()
    evaluate(opt, rng)  # later evaluations do not reach into the snapshot
    assert fit.n_obs == 5 and np.array_equal(fit.y, y0)
    a = fit_hyperparameters(fit)
    b = fit_hyperparameters(pickle.loads(pickle.dumps(fit)))  # as in a worker process
    assert a == b and len(a.lengthscales) == opt.space.dim


def test_apply_keeps_only_newer_fits_and_rejects_foreign_ones() -> None:
    opt = make(refit_lag=1)
    rng = np.random.default_rng(2)
    for _ in range(5):
        evaluate(opt, rng)
    old = opt.hyperparameter_fit()
    assert old is not None
    evaluate(opt, rng)
    new = opt.hyperparameter_fit()
    assert new is not None and new.n_obs == 6
    assert opt.apply_hyperparameters(new, fit_hyperparameters(new))
    assert opt.hyperparameter_fit() is None  # nothing new to fit
    assert not opt.apply_hyperparameters(old, fit_hyperparameters(old))  # stale: ignored
    assert opt.to_json()["n_at_fit"] == 6

    other = make(refit_lag=1)
    with pytest.raises(OptimizerStateError,
                       match="a hyperparameter fit on 6 observations; this optimizer has 0"):
        other.apply_hyperparameters(new, fit_hyperparameters(new))
    with pytest.raises(OptimizerStateError, match="do not fit a 6-D GP"):
        opt.apply_hyperparameters(new, GPHyperparameters((1.0,), 1.0, 0.1))


def test_fewer_than_two_observations_have_nothing_to_fit() -> None:
    opt = make(refit_lag=1)
    assert opt.hyperparameter_fit() is None
    evaluate(opt, np.random.default_rng(3))
    assert opt.hyperparameter_fit() is None


def test_sessions_fitting_ahead_are_reproducible_and_survive_a_json_round_trip() -> None:
    a = make(refit_lag=1)
    ra = np.random.default_rng(5)
    for _ in range(9):
        evaluate_fitting_ahead(a, ra)
    clone = HILOptimizer.from_json(json.loads(json.dumps(a.to_json())),
                                   estimator_factory=a._estimator_factory)
    rb = np.random.default_rng(6)
    rc = np.random.default_rng(6)
    got_a = [evaluate_fitting_ahead(a, rb) for _ in range(6)]
    got_c = [evaluate_fitting_ahead(clone, rc) for _ in range(6)]
    assert got_a == got_c
    assert a.to_json() == clone.to_json()
