"""HILOptimizer.ask_again: after a short pause the abandoned setting is measured again (the same
parameters, phase and stopping prior), not a new proposal."""

from __future__ import annotations

import numpy as np
from test_optimizer import cost
from test_optimizer_refit import evaluate, make

from hilbo_core.optimizer import HILOptimizer, Phase


def breaths(opt: HILOptimizer, params: dict[str, float], n: int, rng: np.random.Generator) -> None:
    for k in range(1, n + 1):
        opt.observe_breath(3.0 * k, cost(params) + rng.normal(0, 40.0))


def test_the_cancelled_optimisation_setting_is_asked_again_with_its_prior() -> None:
    opt = make(stopping="sound", max_breaths=6, min_decision_s=0.0)
    rng = np.random.default_rng(1)
    while opt.phase is Phase.EXPLORATION:
        evaluate(opt, rng)
    asked = opt.ask()  # a GP proposal (a new setting)
    prior = opt.to_json()["current"]
    breaths(opt, asked, 1, rng)
    used = opt.budget_used
    assert opt.cancel_current() == asked
    assert opt.budget_used != used  # the abandoned breaths count against no budget
    again = opt.ask_again()
    assert again == asked and opt.current_params == asked
    state = opt.to_json()["current"]
    assert state["params"] == prior["params"] and state["prior"] == prior["prior"]
    assert state["breaths"] == []  # measured from its first breath again
    assert opt.ask() == asked  # the setting being measured, until it stops
    assert opt.ask_again() is None  # nothing is cancelled any more


def test_an_exploration_setting_is_asked_again_and_evaluations_go_on_from_it() -> None:
    opt = make()
    rng = np.random.default_rng(2)
    first = opt.ask()
    breaths(opt, first, 1, rng)
    opt.cancel_current()
    assert opt.ask_again() == first
    breaths(opt, first, 2, rng)  # max_breaths 2, fixed: the evaluation ends
    assert len(opt.evaluations) == 1 and opt.evaluations[0].params == first


def test_after_a_new_ask_the_cancelled_setting_is_forgotten() -> None:
    opt = make()
    first = opt.ask()
    opt.cancel_current()
    assert opt.ask() == first  # exploration asks the same design point anyway
    opt.cancel_current()
    opt.ask()
    assert opt.ask_again() is None  # a setting is being measured
    assert make().ask_again() is None  # nothing was ever cancelled
