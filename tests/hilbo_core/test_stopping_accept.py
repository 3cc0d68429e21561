"""The sound rule's optional accept stop (``accept_z``, reason DECIDED)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from hilbo_core.errors import ConfigError
from hilbo_core.metabolic import GaussianProductEstimator
from hilbo_core.optimizer import HILOptimizer, OptimizerConfig
from hilbo_core.presets import hip_6d
from hilbo_core.stopping import SoundRule, StopReason

RULE = SoundRule([-0.5, -0.3, 0.2, 2.0, 0.0], min_decision_s=60.0, a_floor=0.5, accept_z=2.0)


def test_accept_stop_when_better_by_accept_z_sigma_after_min_decision_s() -> None:
    # μ = 350 − 400 = −50, σ = √(300 + 100) = 20, z = −2.5 < −2: decided better.
    d = RULE.decide(2, 350.0, 300.0, 400.0, 100.0, t_s=60.0)
    assert (d.stop, d.reason, d.z) == (True, StopReason.DECIDED, -2.5)
    # Not before min_decision_s.
    d = RULE.decide(2, 350.0, 300.0, 400.0, 100.0, t_s=59.9)
    assert (d.stop, d.reason) == (False, StopReason.CONTINUE)
    # z = −40/20 = −2 exactly: not beyond the margin, continue.
    assert not RULE.decide(2, 360.0, 300.0, 400.0, 100.0, t_s=90.0).stop
    # The rejection side is unchanged: z = 2.5 > 0.5 stops with THRESHOLD.
    assert RULE.decide(2, 450.0, 300.0, 400.0, 100.0, t_s=90.0).reason is StopReason.THRESHOLD


def test_accept_is_off_in_the_rule_and_on_at_2_sigma_in_the_optimizer() -> None:
    rule = SoundRule([0.0] * 5, min_decision_s=0.0, a_floor=0.5)
    assert rule.accept_z is None
    d = rule.decide(1, 100.0, 1.0, 400.0, 1.0, t_s=100.0)
    assert (d.stop, d.reason) == (False, StopReason.CONTINUE)
    assert OptimizerConfig().accept_z == 2.0
    assert OptimizerConfig(accept_z=None).accept_z is None
    opt = HILOptimizer(hip_6d(), n_explore=2, max_breaths=5, budget_breaths=20)
    rule = opt._rule()  # the optimizer's sound rule gets the defaults, with the sequential boundary
    assert (rule.accept_z, rule.min_decision_s, rule.boundary_s) == (2.0, 30.0, 60.0)
    floor = HILOptimizer(hip_6d(), n_explore=2, max_breaths=5, budget_breaths=20,
                         stopping="sound-floor")._rule()
    assert (floor.min_decision_s, floor.boundary_s) == (60.0, None)


@pytest.mark.parametrize("value", [-0.1, math.nan, math.inf, True])
def test_bad_accept_z(value) -> None:
    with pytest.raises(ConfigError, match="accept_z"):
        SoundRule([0.0, 0.0], accept_z=value)
    with pytest.raises(ConfigError, match="accept_z"):
        OptimizerConfig(accept_z=value)


def test_optimizer_labels_accept_stops_decided_not_early() -> None:
    space = hip_6d()
    opt = HILOptimizer(space, n_explore=2, max_breaths=20, window=1, budget_breaths=60, seed=3,
                       n_candidates=64, min_decision_s=15.0, accept_z=0.0,
                       estimator_factory=lambda: GaussianProductEstimator(
                           prior_mean=400.0, prior_var=100.0**2, meas_var=10.0**2))
    rng = np.random.default_rng(0)
    n_eval = 0
    while not opt.done:
        opt.ask()
        # Exploration at 500 W, every optimisation candidate at 300 W: always better.
        level = 500.0 if n_eval < 2 else 300.0
        t = 0.0
        while True:
            t += 3.0
            step = opt.observe_breath(t, level + rng.normal(0.0, 10.0))
            if step.stop:
                break
        n_eval += 1
    opt_evals = [e for e in opt.evaluations if e.phase == "optimization"]
    assert opt_evals and opt_evals[0].reason == "decided"
    assert opt_evals[0].breaths == 5  # the first breath at >= 15 s
    assert not any(e.stopped_early for e in opt_evals)
