"""Tests of hilbo_core.metabolic: Brockway, the metabolic UKF and the Gaussian-product model."""

from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from hilbo_core.errors import ConfigError, EstimatorError, MeasurementError
from hilbo_core.metabolic import (
    Estimator,
    GaussianProductEstimator,
    MetabolicUKF,
    UKFConfig,
    brockway_watts,
)
from hilbo_core.types import BreathRecord

# ---------------------------------------------------------------- Brockway


def test_brockway_hand_computed() -> None:
    # 1200 ml/min = 20 ml/s O2 -> 331.6 W; 1000 ml/min = 16.666.. ml/s CO2 -> 75.1666.. W.
    assert brockway_watts(1200.0, 1000.0) == pytest.approx(406.766666667, rel=1e-12)
    assert isinstance(brockway_watts(1200.0, 1000.0), float)


def test_brockway_matches_breath_record() -> None:
    rec = BreathRecord(t_s=1.0, vo2_ml_min=1500.0, vco2_ml_min=1300.0)
    assert brockway_watts(1500.0, 1300.0) == pytest.approx(rec.watts, rel=1e-12)


def test_brockway_arrays_and_broadcast() -> None:
    vo2 = np.array([0.0, 600.0, 1200.0])
    out = brockway_watts(vo2, 1000.0)
    assert isinstance(out, np.ndarray)
    expected = np.array([75.1666666667, 165.8 + 75.1666666667, 331.6 + 75.1666666667])
    np.testing.assert_allclose(out, expected, rtol=1e-10)
    grid = brockway_watts(vo2[:, None], np.array([[0.0, 60.0]]))
    assert grid.shape == (3, 2)
    np.testing.assert_allclose(grid[:, 1] - grid[:, 0], 4.51)


@pytest.mark.parametrize("bad", [math.nan, math.inf, -1.0])
def test_brockway_rejects_bad_values(bad: float) -> None:
    with pytest.raises(MeasurementError, match="vo2_ml_min"):
        brockway_watts(bad, 1000.0)
    with pytest.raises(MeasurementError, match="vco2_ml_min"):
        brockway_watts(np.array([1000.0, 1100.0]), np.array([900.0, bad]))


def test_brockway_rejects_shape_mismatch() -> None:
    with pytest.raises(MeasurementError, match="broadcast"):
        brockway_watts(np.ones(3), np.ones(2))


# ---------------------------------------------------------------- UKF

C_TRUE_W, C0_TRUE_W, TAU_TRUE_S = 400.0, 300.0, 40.0


def _breaths(seed: int, t_end_s: float, noise_rel: float = 0.10) -> list[tuple[float, float]]:
    """First-order step response sampled every ~3 s (jitter ±1 s) with noise ∝ the level."""
    rng = np.random.default_rng(seed)
    out, t = [], 0.0
    while t <= t_end_s:
        m = C_TRUE_W * (1.0 - math.exp(-t / TAU_TRUE_S)) + C0_TRUE_W * math.exp(-t / TAU_TRUE_S)
        out.append((t, m + rng.normal(0.0, noise_rel * m)))
        t += 3.0 + rng.uniform(-1.0, 1.0)
    return out


def _run(seed: int) -> tuple[MetabolicUKF, dict[float, tuple[float, float]]]:
    """Run 5 minutes of breaths; snapshot (mean, var) after the first breath, 2 min and 5 min."""
    ukf = MetabolicUKF()
    snaps: dict[float, tuple[float, float]] = {}
    for t, w in _breaths(seed, 300.0):
        mean, var = ukf.update(t, w)
        if ukf.n_updates == 1:
            snaps[0.0] = (mean, var)
        if t <= 120.0:
            snaps[120.0] = (mean, var)
        snaps[300.0] = (mean, var)
    return ukf, snaps


def test_ukf_recovers_steady_state_cost() -> None:
    seeds = range(20)
    errs_2min, errs_5min = [], []
    for seed in seeds:
        _, snaps = _run(seed)
        for t_end, errs in ((120.0, errs_2min), (300.0, errs_5min)):
            mean, var = snaps[t_end]
            errs.append(mean / C_TRUE_W - 1.0)
            # The reported variance is honest (if anything conservative) at every seed.
            assert abs(mean - C_TRUE_W) < 3.0 * math.sqrt(var), (seed, t_end, mean, var)
        # Variance shrinks overall: first breath > 2 min > 5 min.
        assert snaps[0.0][1] > snaps[120.0][1] > snaps[300.0][1], (seed, snaps)
    # 2 min of 10 %-noise breaths with unknown τ0, τ: a few percent on average (a single seed
    # can be ~2σ ≈ 8 % off — a batch least-squares fit of the same model does no better).
    assert float(np.mean(np.abs(errs_2min))) < 0.05
    # After 5 minutes every seed is within 5 % (Kim et al. 2019 §III.1 reports ~1 % on real data).
    assert max(abs(e) for e in errs_5min) < 0.05


def test_ukf_first_breath_sets_prior() -> None:
    cfg = UKFConfig()
    ukf = MetabolicUKF(cfg)
    assert ukf.n_updates == 0 and ukf.last_t is None
    with pytest.raises(EstimatorError, match="first breath"):
        _ = ukf.mean
    mean, var = ukf.update(2.5, 320.0)
    assert (mean, var) == (320.0, pytest.approx((cfg.c_rel_std * 320.0) ** 2))
    assert (ukf.mean, ukf.var, ukf.n_updates, ukf.last_t) == (mean, var, 1, 2.5)


def _snapshot(ukf: MetabolicUKF) -> str:
    return json.dumps(ukf.state_dict(), sort_keys=True)


@pytest.mark.parametrize(
    ("t_s", "watts", "match"),
    [
        (20.0, math.nan, "watts=nan"),
        (20.0, math.inf, "watts=inf"),
        (20.0, 0.0, "watts=0.0"),
        (20.0, -5.0, "watts=-5.0"),
        (20.0, 6000.0, "watts=6000.0"),
        (math.nan, 300.0, "t_s=nan"),
        (-1.0, 300.0, "t_s=-1.0"),
        ("soon", 300.0, "t_s='soon' is not a number"),
        (20.0, None, "watts=None is not a number"),
        (9.0, 300.0, "strictly after"),  # same time as the last breath
        (4.0, 300.0, "strictly after"),  # earlier than the last breath
    ],
)
def test_ukf_rejects_bad_input_and_keeps_state(t_s: float, watts: float, match: str) -> None:
    ukf = MetabolicUKF()
    for t, w in [(0.0, 300.0), (3.0, 310.0), (6.0, 330.0), (9.0, 320.0)]:
        ukf.update(t, w)
    before = (ukf.mean, ukf.var, ukf.n_updates, ukf.last_t, _snapshot(ukf))
    with pytest.raises(MeasurementError, match=match):
        ukf.update(t_s, watts)
    assert (ukf.mean, ukf.var, ukf.n_updates, ukf.last_t, _snapshot(ukf)) == before
    ukf.update(12.0, 330.0)  # still usable
    assert ukf.n_updates == 5


def test_ukf_numerical_failure_raises_and_restores() -> None:
    ukf = MetabolicUKF()
    ukf.update(0.0, 300.0)
    ukf.update(3.0, 310.0)
    ukf._ukf.P = -np.eye(4)  # white-box: force a covariance that is not positive definite
    before = _snapshot(ukf)
    with pytest.raises(EstimatorError, match="positive definite") as info:
        ukf.update(6.0, 320.0)
    assert info.value.__cause__ is not None
    assert _snapshot(ukf) == before and ukf.n_updates == 2


def test_ukf_state_dict_is_json() -> None:
    ukf = MetabolicUKF()
    assert ukf.state_dict()["x"] is None
    for t, w in _breaths(3, 30.0):
        ukf.update(t, w)
    state = json.loads(json.dumps(ukf.state_dict()))
    assert state["n_updates"] == ukf.n_updates
    assert state["x"][1] == ukf.mean and state["P"][1][1] == ukf.var
    assert state["config"]["tau_init_s"] == 40.0


def test_estimators_satisfy_protocol() -> None:
    estimators: list[Estimator] = [MetabolicUKF(), GaussianProductEstimator(300.0, 1e4, 1e3)]
    for est in estimators:
        mean, var = est.update(0.0, 310.0)
        assert (est.mean, est.var, est.n_updates) == (mean, var, 1)
        assert var > 0.0


@pytest.mark.parametrize(
    ("field", "value"),
    [
        ("tau_init_s", 0.0),
        ("tau0_init_s", -40.0),
        ("meas_noise_rel", math.nan),
        ("alpha", 1.5),
        ("kappa", -4.0),
        ("process_rel_std_per_sqrt_s", -1e-3),
        ("max_watts", True),
    ],
)
def test_ukf_config_validation(field: str, value: float) -> None:
    with pytest.raises(ConfigError, match=f"UKFConfig.{field}="):
        UKFConfig(**{field: value})


def test_ukf_config_is_frozen() -> None:
    with pytest.raises(dataclasses.FrozenInstanceError):
        UKFConfig().alpha = 0.5  # type: ignore[misc]


# ---------------------------------------------------------------- Gaussian product


@given(
    n=st.integers(min_value=1, max_value=50),
    prior_var=st.floats(min_value=1e-3, max_value=1e3),
    meas_var=st.floats(min_value=1e-3, max_value=1e3),
    seed=st.integers(min_value=0, max_value=2**32 - 1),
)
def test_gaussian_product_closed_form(n: int, prior_var: float, meas_var: float, seed: int) -> None:
    zs = np.random.default_rng(seed).normal(5.0, 2.0, size=n)
    est = GaussianProductEstimator(1.0, prior_var, meas_var)
    for i, z in enumerate(zs):
        est.update(float(i), float(z))
    # n products of Gaussians with the same measurement variance r:
    # var_n = 1/(1/v0 + n/r), mean_n = var_n·(m0/v0 + Σz/r).
    var_n = 1.0 / (1.0 / prior_var + n / meas_var)
    mean_n = var_n * (1.0 / prior_var + zs.sum() / meas_var)
    assert est.var == pytest.approx(var_n, rel=1e-9)
    assert est.mean == pytest.approx(mean_n, rel=1e-9, abs=1e-9)
    assert est.n_updates == n


def test_gaussian_product_single_update_by_hand() -> None:
    est = GaussianProductEstimator(prior_mean=10.0, prior_var=4.0, meas_var=12.0)
    assert (est.mean, est.var, est.n_updates) == (10.0, 4.0, 0)
    # var' = 1/(1/4 + 1/12) = 3; mean' = 3·(10/4 + 14/12) = 11.
    assert est.update(0.0, 14.0) == (pytest.approx(11.0), pytest.approx(3.0))


def test_gaussian_product_bad_input() -> None:
    est = GaussianProductEstimator(0.0, 1.0, 1.0)
    est.update(1.0, -3.0)  # negative measurements are fine (e.g. Hartmann-6)
    before = (est.mean, est.var, est.n_updates)
    with pytest.raises(MeasurementError, match="value=nan"):
        est.update(2.0, math.nan)
    with pytest.raises(MeasurementError, match="strictly after"):
        est.update(1.0, 0.0)
    assert (est.mean, est.var, est.n_updates) == before
    with pytest.raises(ConfigError, match="prior_var"):
        GaussianProductEstimator(0.0, 0.0, 1.0)
    with pytest.raises(ConfigError, match="meas_var"):
        GaussianProductEstimator(0.0, 1.0, -1.0)
    with pytest.raises(ConfigError, match="prior_mean"):
        GaussianProductEstimator(math.inf, 1.0, 1.0)
