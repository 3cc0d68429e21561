"""MeasurementNoisePool and PooledNoiseEstimator: the measurement variance learnt from the run."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hilbo_core.errors import ConfigError, MeasurementError
from hilbo_core.metabolic import (
    GaussianProductEstimator,
    MeasurementNoisePool,
    PooledNoiseEstimator,
    divide_gaussian,
)


def test_pool_reference_values() -> None:
    pool = MeasurementNoisePool(2.0, prior_dof=4.0)
    # Prior only: s² = σ_z², used as s²·ν/(ν − 2) = 2·4/2.
    assert (pool.dof, pool.scale_var, pool.meas_var) == (4.0, 2.0, 4.0)
    est = PooledNoiseEstimator(0.0, 100.0, pool)
    for i, z in enumerate((1.0, 3.0, 5.0)):
        est.update(float(i), z)
    # Σ(z − z̄)² = 4 + 0 + 4 = 8 on 2 degrees of freedom: s² = (4·2 + 8)/(4 + 2) = 8/3.
    assert pool.dof == 6.0
    assert pool.scale_var == pytest.approx(8.0 / 3.0)
    assert pool.meas_var == pytest.approx(8.0 / 3.0 * 6.0 / 4.0)


def test_estimator_is_the_gaussian_product_at_the_pools_variance() -> None:
    rng = np.random.default_rng(7)
    pool = MeasurementNoisePool(3.0, prior_dof=1e12)  # so heavy the variance cannot move
    pooled = PooledNoiseEstimator(5.0, 9.0, pool)
    plain = GaussianProductEstimator(5.0, 9.0, pool.meas_var)
    assert (pooled.mean, pooled.var, pooled.n_updates) == (5.0, 9.0, 0)
    for i, z in enumerate(rng.normal(8.0, 2.0, size=25)):
        got = pooled.update(float(i), float(z))
        want = plain.update(float(i), float(z))
        assert got == pytest.approx(want, rel=1e-9)
    assert pooled.data_only() == pytest.approx(plain.data_only(), rel=1e-9)
    assert (pooled.n_updates, pooled.last_t) == (25, 24.0)


def test_data_only_is_the_measurements_mean_with_the_pools_variance_over_n() -> None:
    pool = MeasurementNoisePool(1.0)
    est = PooledNoiseEstimator(0.0, 4.0, pool)
    assert est.data_only() == divide_gaussian(0.0, 4.0, 0.0, 4.0)  # no data: uninformative
    for i, z in enumerate((2.0, 4.0, 9.0)):
        est.update(float(i), z)
    mean, var = est.data_only()
    assert mean == pytest.approx(5.0)
    assert var == pytest.approx(pool.meas_var / 3.0)


@settings(max_examples=50, deadline=None)
@given(st.lists(st.lists(st.floats(-1e3, 1e3), min_size=1, max_size=12), min_size=1, max_size=6),
       st.randoms(use_true_random=False))
def test_pool_sums_each_settings_squares_about_its_own_mean(settings_z: list[list[float]], order) -> None:
    # However the settings' measurements interleave, the pool holds Σ_settings Σ (z − z̄)² on
    # Σ (n − 1) degrees of freedom.
    prior_dof, assumed = 5.0, 2.0
    pool = MeasurementNoisePool(assumed, prior_dof=prior_dof)
    ests = [PooledNoiseEstimator(0.0, 1.0, pool) for _ in settings_z]
    queue = [(k, i) for k, zs in enumerate(settings_z) for i in range(len(zs))]
    order.shuffle(queue)
    queue.sort(key=lambda ki: ki[1])  # within a setting, in order (times increase)
    for k, i in queue:
        ests[k].update(float(i), settings_z[k][i])
    ss = sum(float(np.sum((np.array(zs) - np.mean(zs)) ** 2)) for zs in settings_z)
    dof = sum(len(zs) - 1 for zs in settings_z)
    assert pool.dof == prior_dof + dof
    assert pool.scale_var == pytest.approx((prior_dof * assumed + ss) / (prior_dof + dof), rel=1e-6, abs=1e-6)


@pytest.mark.parametrize("assumed_over_true", [0.1, 10.0])
def test_a_wrong_assumption_is_learnt_within_an_exploration(assumed_over_true: float) -> None:
    # Kim et al. 2019's exploration: 6 settings × 45 measurements of variance 1, estimator told 0.1 or 10.
    rng = np.random.default_rng([3, int(assumed_over_true * 10)])
    pool = MeasurementNoisePool(assumed_over_true)
    for level in rng.uniform(-5.0, 5.0, size=6):
        est = PooledNoiseEstimator(0.0, 25.0, pool)
        for i in range(45):
            est.update(float(i), level + float(rng.normal()))
    assert pool.meas_var == pytest.approx(1.0, rel=0.2)
    # ... and a new setting's single measurement gets the learnt variance, not the assumption.
    est = PooledNoiseEstimator(0.0, 25.0, pool)
    est.update(0.0, 1.0)
    assert est.var == pytest.approx(1.0 / (1.0 / 25.0 + 1.0 / pool.meas_var))


def test_an_estimate_reads_the_variance_learnt_since_it_was_last_updated() -> None:
    pool = MeasurementNoisePool(1.0)
    first = PooledNoiseEstimator(0.0, 100.0, pool)
    first.update(0.0, 3.0)
    before = first.var
    other = PooledNoiseEstimator(0.0, 100.0, pool)
    for i, z in enumerate((-20.0, 20.0, -20.0, 20.0)):  # very noisy: the pool's variance grows
        other.update(float(i), z)
    assert first.var > 10.0 * before
    assert first.mean == pytest.approx(3.0 * 100.0 / (100.0 + pool.meas_var))


def test_bad_input_is_named_and_leaves_estimate_and_pool_unchanged() -> None:
    with pytest.raises(ConfigError, match=r"assumed_var=0\.0"):
        MeasurementNoisePool(0.0)
    with pytest.raises(ConfigError, match="prior_dof=2"):
        MeasurementNoisePool(1.0, prior_dof=2)
    with pytest.raises(ConfigError, match="prior_var=-1"):
        PooledNoiseEstimator(0.0, -1.0, MeasurementNoisePool(1.0))
    with pytest.raises(ConfigError, match="prior_mean=inf"):
        PooledNoiseEstimator(math.inf, 1.0, MeasurementNoisePool(1.0))
    pool = MeasurementNoisePool(1.0)
    est = PooledNoiseEstimator(0.0, 1.0, pool)
    est.update(1.0, 2.0)
    est.update(2.0, 5.0)
    before = (est.mean, est.var, est.n_updates, pool.dof, pool.scale_var)
    with pytest.raises(MeasurementError, match="value=nan"):
        est.update(3.0, math.nan)
    with pytest.raises(MeasurementError, match=r"t_s=2\.0"):
        est.update(2.0, 1.0)
    assert (est.mean, est.var, est.n_updates, pool.dof, pool.scale_var) == before
