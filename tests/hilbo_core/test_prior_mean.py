"""The GP's constant prior mean (``GaussianProcess.fit(prior_mean_sd=)``) and the optimizer's
``OptimizerConfig.prior_mean_sd``."""

from __future__ import annotations

import math

import numpy as np
import pytest

from hilbo_core.acquisition import expected_improvement
from hilbo_core.errors import ConfigError
from hilbo_core.gp import GaussianProcess, GPHyperparameters, KernelKind, kernel_matrix
from hilbo_core.optimizer import (
    SOUND_PRIOR_MEAN_SD,
    HILOptimizer,
    OptimizerConfig,
    fit_hyperparameters,
)
from hilbo_core.presets import hip_6d

HYP = GPHyperparameters(lengthscales=(0.3, 0.3), signal_var=1.0, noise_var=1e-4)


def _data(n: int = 8) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(5)
    X = rng.uniform(0.3, 0.7, (n, 2))
    y = 400.0 + 30.0 * np.sin(4.0 * X[:, 0]) + rng.normal(0.0, 5.0, n)
    v = rng.uniform(20.0, 60.0, n)
    return X, y, v


def _fit(X, y, v, k: float, hyp: GPHyperparameters = HYP) -> GaussianProcess:
    return GaussianProcess(KernelKind.MATERN52).fit(X, y, v, rng=np.random.default_rng(0), init=hyp,
                                                   optimize=False, prior_mean_sd=k)


def test_the_posterior_with_a_constant_prior_mean_matches_the_textbook_formula() -> None:
    # R&W eq. 2.25-2.26 with prior mean m (standardised: k SDs above the targets' average):
    # mean = m + K*ᵀ K_y⁻¹ (y − m); the variance does not depend on m.
    X, y, v = _data()
    k = 0.5
    gp = _fit(X, y, v, k)
    Xs = np.random.default_rng(2).uniform(0.0, 1.0, (5, 2))
    mean, var = gp.predict(Xs)
    ys = y.std()
    m = y.mean() + k * ys
    ls = np.array(HYP.lengthscales)
    Ky = kernel_matrix(KernelKind.MATERN52, X, X, ls, HYP.signal_var) + np.diag(v / ys**2) \
        + HYP.noise_var * np.eye(len(y))
    Ks = kernel_matrix(KernelKind.MATERN52, Xs, X, ls, HYP.signal_var)
    r = (y - m) / ys
    np.testing.assert_allclose(mean, m + ys * Ks @ np.linalg.solve(Ky, r), rtol=1e-10)
    np.testing.assert_allclose(var, _fit(X, y, v, 0.0).predict(Xs)[1], rtol=1e-10)
    ref_ll = -0.5 * r @ np.linalg.solve(Ky, r) - 0.5 * np.linalg.slogdet(Ky)[1] \
        - 0.5 * len(y) * math.log(2 * math.pi)
    assert gp.log_marginal_likelihood() == pytest.approx(ref_ll, rel=1e-10)
    assert gp.y_mean == pytest.approx(m)


def test_far_from_every_measurement_the_posterior_returns_to_the_prior_mean() -> None:
    X, y, v = _data()
    short = GPHyperparameters(lengthscales=(0.02, 0.02), signal_var=1.0, noise_var=1e-4)
    corner = np.array([[1.0, 1.0]])
    for k in (0.0, 0.5, 1.0):
        mean, _ = _fit(X, y, v, k, short).predict(corner)
        assert mean[0] == pytest.approx(y.mean() + k * y.std(), rel=1e-9)


def test_a_pessimistic_mean_makes_the_unmeasured_corner_less_attractive_to_ei() -> None:
    # What the option is for: with the mean at the average, EI rates an unmeasured corner by its
    # large SD alone; half an SD above it, the corner loses against the measured best.
    X, y, v = _data()
    corner, best = np.array([[1.0, 1.0]]), X[[int(np.argmin(y))]]
    ei = {}
    for k in (0.0, 0.5):
        gp = _fit(X, y, v, k)
        ei[k] = []
        for p in (corner, best):
            m, var = gp.predict(p)
            ei[k].append(float(expected_improvement(m, np.sqrt(var), float(y.min()))[0]))
    assert ei[0.5][0] < 0.6 * ei[0.0][0]
    assert ei[0.5][0] / ei[0.5][1] < 0.8 * ei[0.0][0] / ei[0.0][1]


@pytest.mark.parametrize("bad", [math.nan, math.inf, "0.5", True])
def test_a_bad_prior_mean_is_refused_by_the_gp_with_its_value(bad: object) -> None:
    X, y, v = _data()
    with pytest.raises(ConfigError, match="prior_mean_sd"):
        _fit(X, y, v, bad)  # type: ignore[arg-type]


@pytest.mark.parametrize("bad", [-0.1, 3.5, math.nan, True, "0.5"])
def test_a_bad_prior_mean_is_refused_by_the_config_with_its_value(bad: object) -> None:
    with pytest.raises(ConfigError, match=r"prior_mean_sd=.*expected a number of SDs in \[0, 3\]"):
        OptimizerConfig(prior_mean_sd=bad)  # type: ignore[arg-type]


def test_the_sound_rules_default_to_the_pessimistic_mean_and_the_seeds_to_the_average() -> None:
    assert OptimizerConfig().prior_mean_sd == SOUND_PRIOR_MEAN_SD == 0.5
    assert OptimizerConfig(stopping="sound-floor").prior_mean_sd == 0.5
    assert OptimizerConfig(stopping="adaptive").prior_mean_sd == 0.0
    assert OptimizerConfig(stopping="fixed").prior_mean_sd == 0.0
    assert OptimizerConfig(stopping="adaptive", prior_mean_sd=1).prior_mean_sd == 1.0
    cfg = OptimizerConfig(prior_mean_sd=0.25)
    assert OptimizerConfig.from_json(cfg.to_json()) == cfg


def _explored(config: OptimizerConfig) -> HILOptimizer:
    """An optimizer past its exploration, measured on a smooth bowl with fixed estimates."""
    space = hip_6d()
    opt = HILOptimizer(space, config=config)
    while len(opt.evaluations) < 5:
        x = opt.ask()
        u = space.to_unit(space.from_dict(x))
        cost = 350.0 + 200.0 * float(np.sum((u - 0.4) ** 2))
        t = 0.0
        while True:
            t += 3.0
            if opt.observe(t, cost).stop:
                break
    return opt


def test_an_old_state_without_the_option_resumes_with_the_mean_it_ran_with() -> None:
    opt = _explored(OptimizerConfig(n_explore=3, max_breaths=4))
    state = opt.to_json()
    assert state["config"]["prior_mean_sd"] == 0.5
    del state["config"]["prior_mean_sd"]
    old = HILOptimizer.from_json(state)
    assert old.config.prior_mean_sd == 0.0
    assert HILOptimizer.from_json(opt.to_json()).config.prior_mean_sd == 0.5


def test_a_fit_ahead_fits_with_the_mean_the_proposals_use() -> None:
    opt = _explored(OptimizerConfig(n_explore=3, max_breaths=4, prior_mean_sd=1.0))
    fit = opt.hyperparameter_fit()
    assert fit is not None and fit.prior_mean_sd == 1.0
    hyp = fit_hyperparameters(fit)
    ref = GaussianProcess(fit.kernel).fit(fit.X_unit, fit.y, fit.var, rng=np.random.default_rng(fit.seed),
                                          init=fit.init, prior_mean_sd=1.0).hyperparameters
    at_average = GaussianProcess(fit.kernel).fit(fit.X_unit, fit.y, fit.var,
                                                 rng=np.random.default_rng(fit.seed),
                                                 init=fit.init).hyperparameters
    assert hyp == ref
    assert hyp != at_average
