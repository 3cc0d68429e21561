"""Tests for hilbo_core.gp: kernels, marginal likelihood, posterior and hyperparameter fitting."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from scipy.optimize import approx_fprime, check_grad
from scipy.stats import multivariate_normal, qmc

from hilbo_core.errors import ConfigError, EstimatorError, MeasurementError, OptimizerStateError
from hilbo_core.gp import (
    GaussianProcess,
    GPHyperparameters,
    KernelKind,
    kernel_matrix,
    log_marginal_likelihood,
    matern52_kernel,
    se_kernel,
)


def _smooth6(X: np.ndarray) -> np.ndarray:
    return (
        np.sin(3 * X[:, 0])
        + 2 * X[:, 1] ** 2
        + 0.5 * X[:, 2]
        - X[:, 3] * X[:, 4]
        + 0.3 * np.cos(2 * X[:, 5])
    )


# ---- kernels --------------------------------------------------------------------------------


@pytest.mark.parametrize("r", [0.0, 0.1, 0.37, 1.5])
def test_kernels_match_closed_forms(r: float) -> None:
    ls, sv = 0.4, 2.5
    x1, x2 = np.array([[0.2]]), np.array([[0.2 + r]])
    s = r / ls
    assert se_kernel(x1, x2, [ls], sv)[0, 0] == pytest.approx(sv * math.exp(-0.5 * s * s))
    matern = sv * (1 + math.sqrt(5) * s + 5 * s * s / 3) * math.exp(-math.sqrt(5) * s)
    assert matern52_kernel(x1, x2, [ls], sv)[0, 0] == pytest.approx(matern, rel=1e-13)


def test_ard_scales_each_dimension() -> None:
    x1, x2 = np.array([[0.0, 0.0]]), np.array([[0.3, 0.4]])
    ls = np.array([0.5, 2.0])
    r2 = (0.3 / 0.5) ** 2 + (0.4 / 2.0) ** 2  # = 0.4
    assert se_kernel(x1, x2, ls, 1.0)[0, 0] == pytest.approx(math.exp(-0.2))
    r = math.sqrt(r2)
    expected = (1 + math.sqrt(5) * r + 5 * r2 / 3) * math.exp(-math.sqrt(5) * r)
    assert matern52_kernel(x1, x2, ls, 1.0)[0, 0] == pytest.approx(expected)


@pytest.mark.parametrize("kind", list(KernelKind))
def test_kernel_matrix_symmetric_psd(kind: KernelKind) -> None:
    X = np.random.default_rng(0).random((25, 3))
    K = kernel_matrix(kind, X, X, np.array([0.3, 0.8, 2.0]), 1.7)
    np.testing.assert_array_equal(K, K.T)
    np.testing.assert_allclose(np.diag(K), 1.7)
    assert np.min(np.linalg.eigvalsh(K)) > -1e-10
    Ks = kernel_matrix(kind, X[:4], X, np.array([0.3, 0.8, 2.0]), 1.7)
    np.testing.assert_allclose(Ks, K[:4])


def test_kernel_rejects_bad_arguments() -> None:
    X = np.zeros((2, 2))
    with pytest.raises(ConfigError, match="lengthscales"):
        se_kernel(X, X, [0.1, -1.0], 1.0)
    with pytest.raises(ConfigError, match=r"\(2, 2\)"):
        matern52_kernel(X, np.zeros((2, 3)), [0.1, 0.1], 1.0)
    with pytest.raises(ConfigError, match="signal_var"):
        se_kernel(X, X, [0.1, 0.1], 0.0)


# ---- hyperparameters ------------------------------------------------------------------------


def test_hyperparameters_json_round_trip() -> None:
    hp = GPHyperparameters((0.3, 1.2), 0.8, 1e-3)
    back = GPHyperparameters.from_dict(json.loads(json.dumps(hp.to_dict())))
    assert back == hp
    assert GPHyperparameters.from_log_params(hp.to_log_params()).lengthscales == pytest.approx(
        hp.lengthscales
    )


@pytest.mark.parametrize(
    "data",
    [
        {"lengthscales": [0.3], "signal_var": 1.0},
        {"lengthscales": [0.3, -1.0], "signal_var": 1.0, "noise_var": 0.1},
        {"lengthscales": [], "signal_var": 1.0, "noise_var": 0.1},
        {"lengthscales": [0.3], "signal_var": float("nan"), "noise_var": 0.1},
        {"lengthscales": [0.3], "signal_var": 1.0, "noise_var": "x"},
    ],
)
def test_hyperparameters_reject_bad_dicts(data: dict) -> None:
    with pytest.raises(ConfigError):
        GPHyperparameters.from_dict(data)


# ---- marginal likelihood --------------------------------------------------------------------


@pytest.mark.parametrize("kind", list(KernelKind))
def test_mll_value_and_gradient(kind: KernelKind) -> None:
    rng = np.random.default_rng(1)
    X = rng.random((7, 2))
    y = rng.normal(size=7)
    noise = rng.uniform(0.01, 0.3, size=7)
    hp = GPHyperparameters((0.4, 0.9), 1.3, 0.05)
    K = kernel_matrix(kind, X, X, np.array(hp.lengthscales), hp.signal_var)
    Ky = K + np.diag(noise) + hp.noise_var * np.eye(7)
    expected = multivariate_normal(mean=np.zeros(7), cov=Ky).logpdf(y)
    assert log_marginal_likelihood(X, y, noise, hp, kind) == pytest.approx(expected, rel=1e-12)

    def value(theta: np.ndarray) -> float:
        return log_marginal_likelihood(X, y, noise, GPHyperparameters.from_log_params(theta), kind)

    def grad(theta: np.ndarray) -> np.ndarray:
        hp_t = GPHyperparameters.from_log_params(theta)
        return log_marginal_likelihood(X, y, noise, hp_t, kind, return_grad=True)[1]

    for theta in (hp.to_log_params(), np.log([0.08, 3.0, 0.2, 1e-4])):
        g = grad(theta)
        assert check_grad(value, grad, theta, epsilon=1e-6) < 1e-5 * max(1.0, np.linalg.norm(g))


def test_mll_raises_when_not_positive_definite() -> None:
    X = np.array([[0.1], [0.2]])
    hp = GPHyperparameters((0.3,), 1.0, 1e-6)
    with pytest.raises(EstimatorError):
        log_marginal_likelihood(X, np.zeros(2), np.array([-5.0, -5.0]), hp)


# ---- posterior ------------------------------------------------------------------------------


def _textbook_posterior(X, y, noise, hp, Xs):
    """R&W eq. 2.25–2.26 on standardised targets, by direct solves (SE kernel)."""
    ym, ystd = y.mean(), y.std()
    ys = (y - ym) / ystd
    (ls,), sv = hp.lengthscales, hp.signal_var

    def k(a, b):
        return sv * np.exp(-((a[:, None, 0] - b[None, :, 0]) ** 2) / (2 * ls**2))

    Ky = k(X, X) + np.diag(noise / ystd**2) + hp.noise_var * np.eye(len(y))
    Ks = k(Xs, X)
    mean = ym + ystd * Ks @ np.linalg.solve(Ky, ys)
    var = ystd**2 * (sv - np.sum(Ks * np.linalg.solve(Ky, Ks.T).T, axis=1))
    return mean, var


def test_posterior_matches_textbook_formulas() -> None:
    X = np.array([[0.1], [0.5], [0.9]])
    y = np.array([310.0, 290.0, 305.0])
    noise = np.array([4.0, 9.0, 25.0])
    hp = GPHyperparameters((0.3,), 1.2, 1e-3)
    Xs = np.array([[0.0], [0.3], [0.5], [0.77], [1.0]])
    gp = GaussianProcess(KernelKind.SE).fit(
        X, y, noise, rng=np.random.default_rng(0), init=hp, optimize=False
    )
    mean, var = gp.predict(Xs)
    ref_mean, ref_var = _textbook_posterior(X, y, noise, hp, Xs)
    np.testing.assert_allclose(mean, ref_mean, rtol=1e-12)
    np.testing.assert_allclose(var, ref_var, rtol=1e-10)
    assert gp.hyperparameters == hp and gp.n_obs == 3
    np.testing.assert_array_equal(gp.X, X)
    np.testing.assert_array_equal(gp.y, y)


def test_noisier_observation_pulls_the_mean_less() -> None:
    X = np.array([[0.1], [0.5], [0.9]])
    y = np.array([1.0, 3.0, 2.0])
    hp = GPHyperparameters((0.3,), 1.0, 1e-4)
    x_mid = np.array([[0.5]])
    rng = np.random.default_rng(0)
    gaps = []
    for mid_noise in (0.01, 0.1, 1.0):
        noise = np.array([0.01, mid_noise, 0.01])
        gp = GaussianProcess(KernelKind.MATERN52).fit(X, y, noise, rng=rng, init=hp, optimize=False)
        gaps.append(abs(float(gp.predict(x_mid)[0][0]) - 3.0))
    assert gaps[0] < gaps[1] < gaps[2]


def test_predict_with_grad_matches_finite_differences() -> None:
    rng = np.random.default_rng(3)
    X = rng.random((15, 3))
    y = np.sum(X**2, axis=1) * 50 + 300
    gp = GaussianProcess().fit(X, y, np.full(15, 2.0), rng=rng)
    x0 = rng.random(3)
    mean, var, dmean, dvar = gp.predict_with_grad(x0[None, :])
    m_ref, v_ref = gp.predict(x0[None, :])
    np.testing.assert_allclose([mean[0], var[0]], [m_ref[0], v_ref[0]], rtol=1e-10)
    num_m = approx_fprime(x0, lambda u: gp.predict(u[None, :])[0][0], 1e-7)
    num_v = approx_fprime(x0, lambda u: gp.predict(u[None, :])[1][0], 1e-7)
    np.testing.assert_allclose(dmean[0], num_m, rtol=1e-4, atol=1e-4)
    np.testing.assert_allclose(dvar[0], num_v, rtol=1e-4, atol=1e-4)


# ---- fitting --------------------------------------------------------------------------------


@pytest.mark.parametrize("kind", list(KernelKind))
def test_fit_on_eight_points_in_6d_is_sensible(kind: KernelKind) -> None:
    X = qmc.Sobol(6, seed=3).random_base2(3)
    y = _smooth6(X)
    gp = GaussianProcess(kind).fit(X, y, rng=np.random.default_rng(0))
    hp = gp.hyperparameters
    assert all(0.1 <= ls <= 5.0 for ls in hp.lengthscales)
    assert 0.05 <= hp.signal_var <= 20.0
    mean, var = gp.predict(X)
    assert np.max(np.abs(mean - y)) < 0.05 * np.ptp(y)  # interpolates (nearly noise-free data)
    Xt = np.random.default_rng(1).random((200, 6))
    m_t, v_t = gp.predict(Xt)
    assert np.all(v_t > np.max(var))  # less certain away from the data
    rmse = np.sqrt(np.mean((m_t - _smooth6(Xt)) ** 2))
    assert rmse < 0.8 * np.std(_smooth6(Xt))  # better than guessing the mean


def test_fit_with_more_data_predicts_well_and_warm_starts() -> None:
    X = qmc.Sobol(6, seed=5).random_base2(5)
    y = 300.0 + 40.0 * _smooth6(X)
    noise = np.full(len(y), 1.0)
    gp = GaussianProcess().fit(X, y, noise, rng=np.random.default_rng(0))
    Xt = np.random.default_rng(2).random((200, 6))
    truth = 300.0 + 40.0 * _smooth6(Xt)
    mean, var = gp.predict(Xt)
    assert np.sqrt(np.mean((mean - truth) ** 2)) < 0.3 * np.std(truth)
    assert np.mean(np.abs(mean - truth) < 3 * np.sqrt(var)) > 0.8
    lml = gp.log_marginal_likelihood()
    warm = GaussianProcess().fit(
        X, y, noise, rng=np.random.default_rng(1), init=gp.hyperparameters
    )
    assert warm.log_marginal_likelihood() == pytest.approx(lml, abs=0.05)


def test_fit_is_deterministic_for_a_seed() -> None:
    X = np.random.default_rng(7).random((10, 2))
    y = np.sin(4 * X[:, 0]) + X[:, 1]
    a = GaussianProcess().fit(X, y, rng=np.random.default_rng(9)).hyperparameters
    b = GaussianProcess().fit(X, y, rng=np.random.default_rng(9)).hyperparameters
    assert a == b


def test_single_point_and_constant_targets() -> None:
    rng = np.random.default_rng(0)
    gp = GaussianProcess().fit(np.array([[0.5, 0.5]]), np.array([400.0]), np.array([25.0]), rng=rng)
    mean, var = gp.predict(np.array([[0.5, 0.5], [0.0, 1.0]]))
    assert np.all(np.isfinite(mean)) and np.all(var > 0.0)
    assert abs(mean[0] - 400.0) < abs(mean[1] - 400.0) + 1e-9 or var[1] > var[0]
    assert gp.y_std == pytest.approx(5.0)  # falls back to √mean(noise_var)
    gp.fit(rng.random((5, 2)), np.full(5, 3.0), rng=rng)
    mean, var = gp.predict(rng.random((4, 2)))
    np.testing.assert_allclose(mean, 3.0, atol=1e-6)
    assert np.all(np.isfinite(var))


def test_near_duplicate_points_need_jitter_but_fit() -> None:
    X = np.full((20, 1), 0.5) + np.linspace(0, 1e-9, 20)[:, None]
    y = np.linspace(0.0, 1e-3, 20)
    hp = GPHyperparameters((2.0,), 1.0, 1e-12)
    gp = GaussianProcess(KernelKind.SE, noise_var_bounds=(1e-12, 1.0)).fit(
        X, y, rng=np.random.default_rng(0), init=hp, optimize=False
    )
    mean, var = gp.predict(np.array([[0.5], [0.9]]))
    assert np.all(np.isfinite(mean)) and np.all(var > 0.0)


def test_feature_map_hook() -> None:
    rng = np.random.default_rng(0)
    X = rng.random((12, 2))
    y = np.sin(5 * X[:, 0])
    gp = GaussianProcess(feature_map=lambda U: U[:, :1]).fit(X, y, rng=rng)
    assert gp.hyperparameters.dim == 1
    m1, v1 = gp.predict(np.array([[0.3, 0.0], [0.3, 1.0]]))
    assert m1[0] == pytest.approx(m1[1]) and v1[0] == pytest.approx(v1[1])
    with pytest.raises(ConfigError, match="feature_map"):
        gp.predict_with_grad(np.array([[0.3, 0.0]]))
    with pytest.raises(ConfigError, match="feature_map"):
        GaussianProcess(feature_map=lambda U: U[:3]).fit(X, y, rng=rng)


# ---- validation -----------------------------------------------------------------------------


def test_input_validation_names_the_offending_row() -> None:
    gp = GaussianProcess()
    rng = np.random.default_rng(0)
    X = np.random.default_rng(1).random((4, 2))
    y = np.arange(4.0)
    with pytest.raises(MeasurementError, match=r"y\[2\]"):
        gp.fit(X, np.array([0.0, 1.0, np.nan, 2.0]), rng=rng)
    with pytest.raises(MeasurementError, match=r"noise_var\[1\]"):
        gp.fit(X, y, np.array([1.0, 0.0, 1.0, 1.0]), rng=rng)
    with pytest.raises(MeasurementError, match=r"noise_var\[3\]"):
        gp.fit(X, y, np.array([1.0, 1.0, 1.0, np.inf]), rng=rng)
    bad = X.copy()
    bad[3, 1] = np.inf
    with pytest.raises(ConfigError, match="row 3"):
        gp.fit(bad, y, rng=rng)
    bad[3, 1] = 1.7
    with pytest.raises(ConfigError, match=r"row 3.*unit cube"):
        gp.fit(bad, y, rng=rng)
    with pytest.raises(ConfigError, match="y must have shape"):
        gp.fit(X, y[:3], rng=rng)
    with pytest.raises(ConfigError, match="noise_var must have shape"):
        gp.fit(X, y, np.ones(3), rng=rng)
    with pytest.raises(ConfigError, match="init has 3"):
        gp.fit(X, y, rng=rng, init=GPHyperparameters((0.5, 0.5, 0.5), 1.0, 0.01))


def test_unfitted_gp_and_bad_constructor_arguments() -> None:
    gp = GaussianProcess()
    assert gp.n_obs == 0 and not gp.is_fitted
    with pytest.raises(OptimizerStateError):
        gp.predict(np.zeros((1, 2)))
    with pytest.raises(OptimizerStateError):
        _ = gp.hyperparameters
    with pytest.raises(ConfigError, match="lengthscale_bounds"):
        GaussianProcess(lengthscale_bounds=(1.0, 0.5))
    with pytest.raises(ConfigError, match="n_restarts"):
        GaussianProcess(n_restarts=-1)
    with pytest.raises(ConfigError, match="kernel"):
        GaussianProcess("se")  # type: ignore[arg-type]
    fitted = GaussianProcess().fit(np.array([[0.1, 0.2]]), np.array([1.0]), rng=np.random.default_rng(0))
    with pytest.raises(ConfigError, match=r"\(m, 2\)"):
        fitted.predict(np.zeros((1, 3)))
