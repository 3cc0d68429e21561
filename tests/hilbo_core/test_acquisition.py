"""Tests for hilbo_core.acquisition: stable EI (Kim et al. 2019 §II.B) and its constrained maximiser."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.stats import norm

from hilbo_core.acquisition import (
    expected_improvement,
    log_expected_improvement,
    maximize_ei,
)
from hilbo_core.errors import ConfigError, EstimatorError, InfeasibleError
from hilbo_core.gp import GaussianProcess


def _series_log_h(z: float, terms: int = 30) -> float:
    """log(zΦ(z) + φ(z)) from the asymptotic series φ(z)/z² Σ_k (−1)^k (2k+1)!!/z^{2k}.

    For |z| >= 12 the 30-term truncation error is below 1e-22 (relative), so this is a
    high-precision reference independent of the implementation's branches.
    """
    total, term = [], 1.0
    for k in range(terms):
        total.append(term)
        term *= -(2 * k + 3) / (z * z)
    return -0.5 * z * z - 0.5 * math.log(2 * math.pi) - 2 * math.log(abs(z)) + math.log(
        math.fsum(total)
    )


# ---- expected_improvement / log_expected_improvement ----------------------------------------


def test_reference_value_matches_botorch() -> None:
    # botorch's test for maximisation: mean −0.5, sd 1, best 0 → 0.19780; mirrored here.
    assert float(expected_improvement(0.5, 1.0, 0.0)) == pytest.approx(0.19780, abs=5e-6)
    assert float(log_expected_improvement(0.5, 1.0, 0.0)) == pytest.approx(
        math.log(0.19779655740130608), rel=1e-12
    )


def test_matches_closed_form_on_grid() -> None:
    mean = np.linspace(-3.0, 3.0, 41)[:, None]
    std = np.array([0.5, 1.0, 2.0, 7.0])[None, :]
    best = 0.25
    z = (best - mean) / std
    expected = std * (z * norm.cdf(z) + norm.pdf(z))
    got = expected_improvement(mean, std, best)
    assert got.shape == (41, 4)
    np.testing.assert_allclose(got, expected, rtol=1e-11, atol=0.0)
    np.testing.assert_allclose(
        log_expected_improvement(mean, std, best), np.log(expected), rtol=1e-11
    )


@pytest.mark.parametrize("z", [-12.0, -20.0, -30.0, -39.9, -40.0, -40.1, -55.0, -1e3, -1e6])
def test_log_ei_tail_matches_asymptotic_reference(z: float) -> None:
    std, best = 2.0, 10.0
    mean = best - z * std
    got = float(log_expected_improvement(mean, std, best))
    assert math.isfinite(got)
    assert got == pytest.approx(math.log(std) + _series_log_h(z), rel=1e-12)


def test_ei_far_tail_positive_and_never_negative() -> None:
    # mean = best + 30 σ: EI ≈ 1.6e-199, far below what zΦ + φ can resolve directly.
    ei = float(expected_improvement(30.0, 1.0, 0.0))
    assert ei > 0.0
    assert ei == pytest.approx(math.exp(_series_log_h(-30.0)), rel=1e-11)
    # mean = best + 40 σ: the true EI (~2.5e-352 σ) is below float64's smallest subnormal unless
    # σ is huge; EI underflows to 0 but log EI stays exact.
    assert float(expected_improvement(40.0, 1.0, 0.0)) == 0.0
    big = 1e40  # scaling σ makes the same z representable
    ei_big = float(expected_improvement(40.0 * big, big, 0.0))
    assert 0.0 < ei_big < 1e-300
    z = -np.logspace(-3, 8, 400)
    ei = expected_improvement(-z, 1.0, 0.0)
    log_ei = log_expected_improvement(-z, 1.0, 0.0)
    assert np.all(ei >= 0.0) and not np.any(np.isnan(ei))
    assert np.all(np.isfinite(log_ei))
    assert np.all(np.diff(log_ei) < 0.0)  # strictly decreasing as z → −∞


@pytest.mark.parametrize("z0", [-1.0, -40.0])
def test_log_ei_continuous_at_branch_switches(z0: float) -> None:
    zs = np.array([np.nextafter(z0, -np.inf), z0, np.nextafter(z0, np.inf)])
    vals = log_expected_improvement(-zs, 1.0, 0.0)
    np.testing.assert_allclose(vals, vals[1], rtol=1e-12)


def test_zero_std_is_improvement_of_the_mean() -> None:
    got = expected_improvement(np.array([1.0, 3.0, 2.0]), 0.0, 2.0, xi=0.5)
    np.testing.assert_array_equal(got, [1.5, 0.0, 0.5])
    log_got = log_expected_improvement(np.array([1.0, 3.0]), 0.0, 2.0)
    assert log_got[0] == pytest.approx(0.0) and log_got[1] == -np.inf


def test_xi_sign_follows_the_seed() -> None:
    # z = (best − μ + ξ)/σ: ξ > 0 is the same as lowering the mean by ξ, so EI grows.
    mean, std, best = np.array([0.2, 1.0]), np.array([0.3, 0.7]), 0.5
    np.testing.assert_allclose(
        expected_improvement(mean, std, best, xi=0.1),
        expected_improvement(mean - 0.1, std, best),
        rtol=1e-14,
    )
    assert np.all(expected_improvement(mean, std, best, xi=0.1) > expected_improvement(
        mean, std, best
    ))
    assert np.all(expected_improvement(mean, std, best, xi=-0.1) < expected_improvement(
        mean, std, best
    ))


@pytest.mark.parametrize(
    ("mean", "std"), [(np.nan, 1.0), (0.0, -1.0), (np.inf, 1.0), (0.0, np.nan)]
)
def test_invalid_inputs_raise(mean: float, std: float) -> None:
    with pytest.raises(ConfigError):
        expected_improvement(mean, std, 0.0)
    with pytest.raises(ConfigError):
        log_expected_improvement(mean, std, 0.0)


finite = st.floats(-1e6, 1e6, allow_nan=False, allow_infinity=False)


@given(mean=finite, std=st.floats(1e-6, 1e4), best=finite, dm=st.floats(1e-3, 10.0))
@settings(max_examples=200, deadline=None)
def test_ei_properties(mean: float, std: float, best: float, dm: float) -> None:
    ei = float(expected_improvement(mean, std, best))
    log_ei = float(log_expected_improvement(mean, std, best))
    assert ei >= 0.0 and math.isfinite(ei)
    assert math.isfinite(log_ei)
    # Jensen: E[max(best − f, 0)] >= max(best − E f, 0).
    assert ei >= max(best - mean, 0.0) * (1.0 - 1e-12)
    if ei > 1e-280:
        assert math.exp(log_ei) == pytest.approx(ei, rel=1e-9)
    # Worse mean, no more improvement.
    assert float(log_expected_improvement(mean + dm, std, best)) <= log_ei


# ---- maximize_ei ----------------------------------------------------------------------------


def _quadratic_model(center: np.ndarray):
    """mean = 10‖u − c‖², var = 0.05 + 0.5 Σ sin²(3u): smooth, with analytic gradients."""

    def predict(U: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return 10.0 * np.sum((U - center) ** 2, axis=1), 0.05 + 0.5 * np.sum(
            np.sin(3.0 * U) ** 2, axis=1
        )

    def predict_grad(U: np.ndarray):
        mean, var = predict(U)
        return mean, var, 20.0 * (U - center), 3.0 * np.sin(6.0 * U) * 0.5

    return predict, predict_grad


@st.composite
def constrained_problems(draw):
    d = draw(st.integers(1, 4))
    k = draw(st.integers(0, 3))
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    A = rng.normal(size=(k, d))
    anchor = rng.random(d)
    b = A @ anchor + rng.exponential(0.1, size=k)  # anchor is feasible, the set may be thin
    pool = rng.random((150, d))
    cands = np.vstack([anchor, pool[np.all(pool @ A.T <= b, axis=1)]])
    center = rng.uniform(-0.3, 1.3, size=d)  # the unconstrained optimum may be infeasible
    best = draw(st.floats(-1.0, 5.0))
    return A, b, cands, center, best, draw(st.booleans())


@given(problem=constrained_problems(), seed=st.integers(0, 1000))
@settings(max_examples=60, deadline=None)
def test_maximize_ei_returns_feasible_point_at_least_as_good(problem, seed) -> None:
    A, b, cands, center, best, use_grad = problem
    predict, predict_grad = _quadratic_model(center)
    u, ei = maximize_ei(
        predict,
        best,
        candidates=cands,
        A_ub=A,
        b_ub=b,
        rng=np.random.default_rng(seed),
        predict_grad=predict_grad if use_grad else None,
    )
    assert u.shape == (cands.shape[1],)
    assert np.all(u >= 0.0) and np.all(u <= 1.0)
    assert np.all(A @ u <= b + 1e-9)
    mean, var = predict(cands)
    best_candidate = float(np.max(expected_improvement(mean, np.sqrt(var), best)))
    assert ei >= best_candidate * (1.0 - 1e-12)
    m, v = predict(u[None, :])
    assert ei == pytest.approx(float(expected_improvement(m, np.sqrt(v), best)[0]), rel=1e-12)


def test_refinement_finds_the_constrained_optimum() -> None:
    # Constant variance: EI is maximised where the mean is lowest, i.e. at the projection of the
    # centre (0.8, 0.8) onto u0 + u1 <= 1, which is (0.5, 0.5).
    center = np.array([0.8, 0.8])

    def predict(U: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return np.sum((U - center) ** 2, axis=1), np.full(U.shape[0], 0.01)

    rng = np.random.default_rng(4)
    pool = rng.random((64, 2))
    A, b = np.array([[1.0, 1.0]]), np.array([1.0])
    cands = pool[pool.sum(axis=1) <= 1.0]
    u, ei = maximize_ei(predict, 0.2, candidates=cands, A_ub=A, b_ub=b, rng=rng)
    np.testing.assert_allclose(u, [0.5, 0.5], atol=1e-4)
    assert A @ u <= b + 1e-9
    mean, var = predict(cands)
    assert ei > np.max(expected_improvement(mean, np.sqrt(var), 0.2))


def test_analytic_and_numeric_gradients_agree() -> None:
    predict, predict_grad = _quadratic_model(np.array([0.3, 0.9, 0.5]))
    cands = np.random.default_rng(0).random((200, 3))
    kwargs = {"candidates": cands, "A_ub": None, "b_ub": None}
    u1, ei1 = maximize_ei(predict, 1.0, rng=np.random.default_rng(1), **kwargs)
    u2, ei2 = maximize_ei(
        predict, 1.0, rng=np.random.default_rng(1), predict_grad=predict_grad, **kwargs
    )
    np.testing.assert_allclose(u1, u2, atol=1e-4)
    assert ei1 == pytest.approx(ei2, rel=1e-6)


def test_n_local_zero_returns_the_best_candidate() -> None:
    predict, _ = _quadratic_model(np.array([0.5, 0.5]))
    cands = np.random.default_rng(2).random((50, 2))
    u, ei = maximize_ei(
        predict, 1.0, candidates=cands, A_ub=np.zeros((0, 2)), b_ub=np.zeros(0),
        rng=np.random.default_rng(0), n_local=0,
    )
    mean, var = predict(cands)
    all_ei = expected_improvement(mean, np.sqrt(var), 1.0)
    np.testing.assert_array_equal(u, cands[np.argmax(all_ei)])
    assert ei == pytest.approx(np.max(all_ei), rel=1e-14)


def test_with_a_fitted_gp() -> None:
    rng = np.random.default_rng(5)
    X = rng.random((12, 3))
    y = np.sum((X - 0.4) ** 2, axis=1)
    gp = GaussianProcess().fit(X, y, np.full(12, 1e-4), rng=rng)
    cands = rng.random((500, 3))
    A, b = np.array([[1.0, -1.0, 0.0]]), np.array([0.0])  # u0 <= u1
    cands = cands[cands @ A[0] <= 0.0]
    u, ei = maximize_ei(
        gp.predict, float(y.min()), candidates=cands, A_ub=A, b_ub=b, rng=rng,
        predict_grad=gp.predict_with_grad,
    )
    assert u[0] <= u[1] + 1e-9 and np.all((u >= 0.0) & (u <= 1.0))
    mean, var = gp.predict(cands)
    assert ei >= np.max(expected_improvement(mean, np.sqrt(var), float(y.min())))


def test_infeasible_candidate_is_rejected() -> None:
    predict, _ = _quadratic_model(np.array([0.5]))
    with pytest.raises(InfeasibleError, match="row 1"):
        maximize_ei(
            predict, 0.0, candidates=np.array([[0.2], [0.9]]), A_ub=np.array([[1.0]]),
            b_ub=np.array([0.5]), rng=np.random.default_rng(0),
        )
    with pytest.raises(InfeasibleError, match="row 0"):
        maximize_ei(
            predict, 0.0, candidates=np.array([[1.5]]), A_ub=None, b_ub=None,
            rng=np.random.default_rng(0),
        )


def test_bad_arguments_raise() -> None:
    predict, _ = _quadratic_model(np.array([0.5]))
    cands = np.array([[0.2]])
    rng = np.random.default_rng(0)
    with pytest.raises(ConfigError, match="b_ub"):
        maximize_ei(predict, 0.0, candidates=cands, A_ub=np.ones((2, 1)), b_ub=np.ones(1), rng=rng)
    with pytest.raises(ConfigError, match="n_local"):
        maximize_ei(predict, 0.0, candidates=cands, A_ub=None, b_ub=None, rng=rng, n_local=-1)
    with pytest.raises(ConfigError, match="candidates"):
        maximize_ei(predict, 0.0, candidates=np.zeros((0, 1)), A_ub=None, b_ub=None, rng=rng)
    with pytest.raises(EstimatorError):
        maximize_ei(
            lambda U: (np.full(len(U), np.nan), np.ones(len(U))), 0.0,
            candidates=cands, A_ub=None, b_ub=None, rng=rng,
        )
