"""Correlated observation errors: the GP's ``noise_corr`` and the optimizer's ``drift_corr_s``."""

from __future__ import annotations

import numpy as np
import pytest

from hilbo_core.errors import ConfigError, MeasurementError
from hilbo_core.estimation import TransitionEstimator
from hilbo_core.gp import GaussianProcess, GPHyperparameters, KernelKind, kernel_matrix
from hilbo_core.optimizer import HILOptimizer, OptimizerConfig
from hilbo_core.presets import hip_6d

HYP = GPHyperparameters(lengthscales=(0.3, 0.3), signal_var=1.0, noise_var=1e-4)


def _data(n: int = 8) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(3)
    X = rng.uniform(0.0, 1.0, (n, 2))
    y = 400.0 + 30.0 * np.sin(4.0 * X[:, 0]) + rng.normal(0.0, 5.0, n)
    v = rng.uniform(20.0, 60.0, n)
    t = np.arange(n) * 90.0
    R = np.exp(-0.5 * ((t[:, None] - t[None, :]) / 180.0) ** 2) * 0.6
    np.fill_diagonal(R, 1.0)
    return X, y, v, R


def _fit(X, y, v, R=None) -> GaussianProcess:
    return GaussianProcess(KernelKind.MATERN52).fit(X, y, v, rng=np.random.default_rng(0), init=HYP,
                                                   optimize=False, noise_corr=R)


def test_an_identity_correlation_is_the_independent_model() -> None:
    X, y, v, _ = _data()
    Xs = np.random.default_rng(1).uniform(0.0, 1.0, (5, 2))
    m0, v0 = _fit(X, y, v).predict(Xs)
    m1, v1 = _fit(X, y, v, np.eye(len(y))).predict(Xs)
    np.testing.assert_allclose(m1, m0, rtol=1e-12)
    np.testing.assert_allclose(v1, v0, rtol=1e-10)


def test_the_posterior_with_correlated_errors_matches_the_textbook_formula() -> None:
    # R&W eq. 2.25-2.26 with K_y = K + S R S + sigma_n^2 I, in standardised units.
    X, y, v, R = _data()
    gp = _fit(X, y, v, R)
    Xs = np.random.default_rng(2).uniform(0.0, 1.0, (4, 2))
    mean, var = gp.predict(Xs)
    ym, ys = y.mean(), y.std()
    s = np.sqrt(v) / ys
    Ky = kernel_matrix(KernelKind.MATERN52, X, X, np.array(HYP.lengthscales), HYP.signal_var)
    Ky = Ky + R * np.outer(s, s) + HYP.noise_var * np.eye(len(y))
    Ks = kernel_matrix(KernelKind.MATERN52, Xs, X, np.array(HYP.lengthscales), HYP.signal_var)
    ref_mean = ym + ys * Ks @ np.linalg.solve(Ky, (y - ym) / ys)
    ref_var = ys**2 * (HYP.signal_var - np.einsum("ij,ji->i", Ks, np.linalg.solve(Ky, Ks.T)))
    np.testing.assert_allclose(mean, ref_mean, rtol=1e-10)
    np.testing.assert_allclose(var, ref_var, rtol=1e-8)
    # and the fit's likelihood is the one of that covariance
    ref_ll = -0.5 * ((y - ym) / ys) @ np.linalg.solve(Ky, (y - ym) / ys) \
        - 0.5 * np.linalg.slogdet(Ky)[1] - 0.5 * len(y) * np.log(2 * np.pi)
    assert gp.log_marginal_likelihood() == pytest.approx(ref_ll, rel=1e-10)


def test_a_shared_offset_is_recovered_as_the_error_and_left_out_of_f() -> None:
    # Two far-apart settings, each measured early (t = 0, 90 s) and again late (t = 1800, 1890
    # s) when every reading is 20 W high; the late errors are fully correlated with each other.
    X = np.array([[0.1, 0.1], [0.9, 0.9], [0.1, 0.1], [0.9, 0.9]])
    y = np.array([400.0, 430.0, 420.0, 450.0])
    v = np.full(4, 101.0)
    drift_sd = 10.0
    t = np.array([0.0, 90.0, 1800.0, 1890.0])
    rho = np.exp(-0.5 * ((t[:, None] - t[None, :]) / 180.0) ** 2)
    C = rho * drift_sd**2
    np.fill_diagonal(C, v)
    R = C / v[0]
    gp = _fit(X, y, v, R)
    late = gp.predict_error(np.array([[drift_sd**2 * rho[3, j] for j in range(4)]]))[0]
    early = gp.predict_error(np.array([[drift_sd**2 * rho[0, j] for j in range(4)]]))[0]
    assert late - early > 10.0  # the 20 W step is mostly drift, not the settings
    independent, var_ind = _fit(X, y, v).predict(X[:2])
    correlated, var_cor = gp.predict(X[:2])
    # With the step explained as a shared error, each setting's cost is known better and their
    # 30 W difference is shrunk less than by the independent model.
    assert np.all(var_cor < var_ind)
    assert correlated[1] - correlated[0] == pytest.approx(30.0, abs=1.0)
    assert independent[1] - independent[0] < correlated[1] - correlated[0]


@pytest.mark.parametrize("R, match", [
    (np.ones((3, 3)), "shape"),
    (np.array([[1.0, 0.5], [0.4, 1.0]]), "symmetric"),
    (np.array([[1.0, 1.5], [1.5, 1.0]]), r"\[-1, 1\]"),
    (np.array([[0.5, 0.2], [0.2, 1.0]]), "unit diagonal"),
])
def test_a_bad_correlation_matrix_is_refused(R, match) -> None:
    X, y, v, _ = _data(2)
    with pytest.raises(ConfigError, match=match):
        _fit(X, y, v, R)


def test_noise_corr_needs_the_variances() -> None:
    X, y, _, R = _data(3)
    with pytest.raises(ConfigError, match="noise_corr needs noise_var"):
        GaussianProcess().fit(X, y, None, rng=np.random.default_rng(0), noise_corr=R[:3, :3])


@pytest.mark.parametrize("value", [0.0, -5.0, float("inf"), True, "180"])
def test_a_bad_drift_corr_s_is_refused_with_its_value(value) -> None:
    with pytest.raises(ConfigError, match="drift_corr_s"):
        OptimizerConfig(drift_corr_s=value)


def test_drift_corr_s_round_trips_and_defaults_to_off() -> None:
    assert OptimizerConfig().drift_corr_s is None
    assert OptimizerConfig.from_json(OptimizerConfig(drift_corr_s=180.0).to_json()).drift_corr_s == 180.0


def test_the_transition_estimator_reports_its_model_error_share() -> None:
    est = TransitionEstimator()
    est.start_from(400.0, 40.0**2)
    rng = np.random.default_rng(0)
    for i in range(30):
        est.update(3.0 * (i + 1), 400.0 * (1.0 + 0.1 * rng.standard_normal()))
    mean, var = est.data_only()
    share = est.model_error_var()
    assert share == pytest.approx((est.config.model_error_rel * mean) ** 2)
    assert 0.0 < share < var


SPACE = hip_6d()


def _told(drift_corr_s: float | None, late_offset_w: float) -> HILOptimizer:
    """Eight settings of 90 s each, the last four read ``late_offset_w`` high (a drift)."""
    opt = HILOptimizer(SPACE, n_explore=2, seed=0, n_candidates=128, drift_corr_s=drift_corr_s)
    rng = np.random.default_rng(5)
    for i, u in enumerate(SPACE.sample_unit(8, rng)):
        truth = 400.0 + 40.0 * float(u[0])
        opt.tell(SPACE.to_dict(SPACE.from_unit(u)), truth + (late_offset_w if i >= 4 else 0.0),
                 15.0**2, duration_s=90.0, drift_var=12.0**2)
    return opt


def test_the_stop_decision_sees_the_drift_inferred_now() -> None:
    opt = _told(180.0, 25.0)
    opt.ask()
    assert opt._drift_now_w > 5.0  # the late readings' shared 25 W
    m_inc, _ = opt._incumbent_stats()
    assert opt.incumbent is not None
    assert m_inc == pytest.approx(opt.incumbent[1] + opt._drift_now_w)
    off = _told(None, 25.0)
    off.ask()
    assert off._drift_now_w == 0.0


def test_the_drift_state_survives_a_resume() -> None:
    opt = _told(180.0, 25.0)
    opt.ask()
    back = HILOptimizer.from_json(opt.to_json(), estimator_factory=None)
    assert back._drift_now_w == opt._drift_now_w
    assert [e.drift_var for e in back.evaluations] == [12.0**2] * 8


def test_tell_refuses_a_drift_share_above_the_variance() -> None:
    opt = HILOptimizer(SPACE, n_explore=2, seed=0)
    with pytest.raises(MeasurementError, match="drift_var"):
        opt.tell(SPACE.to_dict(SPACE.from_unit(np.full(6, 0.5))), 400.0, 100.0, drift_var=200.0)
