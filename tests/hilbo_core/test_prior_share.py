"""The GP's share of the sound rule's stop decision (``OptimizerConfig.gp_prior_max_share``)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from hilbo_core.errors import ConfigError
from hilbo_core.metabolic import GaussianProductEstimator
from hilbo_core.optimizer import HILOptimizer, OptimizerConfig
from hilbo_core.presets import hip_6d
from hilbo_core.stopping import StopReason

SPACE = hip_6d()


def _estimator() -> GaussianProductEstimator:
    return GaussianProductEstimator(prior_mean=400.0, prior_var=200.0**2, meas_var=100.0**2)


def _proposing(share: float) -> HILOptimizer:
    """An optimizer past exploration, measuring its first proposal (breath every 3 s)."""
    opt = HILOptimizer(SPACE, estimator_factory=_estimator, n_explore=4, max_breaths=40, window=1,
                       seed=3, n_candidates=256, min_decision_s=30.0, gp_prior_max_share=share)
    rng = np.random.default_rng(5)
    while len(opt.evaluations) < 4:
        params = opt.ask()
        u = SPACE.to_unit(SPACE.from_dict(params))
        for i in range(40):
            opt.observe_breath(3.0 * (i + 1), 380.0 + 100.0 * float(np.sum((u - 0.4) ** 2))
                               + rng.normal(0.0, 20.0))
    opt.ask()
    return opt


def test_the_gp_carries_at_most_its_share_of_the_decision() -> None:
    for share in (0.5, 0.25, 1.0):
        opt = _proposing(share)
        opt.observe_breath(3.0, 410.0)
        # A tight GP predictive far above the incumbent, and one breath of data.
        opt._current.prior = (520.0, 10.0**2)
        d_mean, d_var = opt._estimator.data_only()
        mean, var = opt._candidate_estimate(opt._current.means[-1], opt._current.vars[-1])
        p_prec = 1.0 / 100.0
        if share < 1.0:
            p_prec = min(p_prec, share / (1.0 - share) / d_var)
        prec = 1.0 / d_var + p_prec
        assert var == pytest.approx(1.0 / prec, rel=1e-12)
        assert mean == pytest.approx((d_mean / d_var + 520.0 * p_prec) / prec, rel=1e-12)
        # the cap binds here: the data's variance is far above the GP's
        assert (var >= d_var * (1.0 - share) * (1 - 1e-12)) if share < 1.0 else var < 100.0


def _first_decision(share: float) -> StopReason:
    """The sound rule's decision at its first look, with the GP's predictive 60 W above the
    incumbent at SD 10 W and breaths that say nothing either way (the incumbent's level)."""
    opt = _proposing(share)
    opt._current.prior = (opt.incumbent[1] + 60.0, 10.0**2)
    t, step = 0.0, None
    while t < 30.0:
        t += 3.0
        step = opt.observe_breath(t, opt.incumbent[1])
    assert step is not None and step.decision is not None
    return step.decision.reason


def test_a_reject_needs_the_settings_own_breaths() -> None:
    assert _first_decision(1.0) is StopReason.THRESHOLD  # the plain product: the GP alone decides
    assert _first_decision(0.5) is StopReason.CONTINUE


@pytest.mark.parametrize("bad", [0.0, -0.1, 1.5, math.nan, True, "half"])
def test_bad_share(bad: object) -> None:
    with pytest.raises(ConfigError, match="gp_prior_max_share"):
        OptimizerConfig(gp_prior_max_share=bad)


def test_an_old_state_resumes_with_the_plain_product() -> None:
    opt = _proposing(0.5)
    state = opt.to_json()
    assert state["config"]["gp_prior_max_share"] == 0.5
    del state["config"]["gp_prior_max_share"]
    assert HILOptimizer.from_json(state).config.gp_prior_max_share == 1.0
    assert HILOptimizer.from_json(opt.to_json()).config.gp_prior_max_share == 0.5
