"""The knowledge gradient (hilbo_core/knowledge_gradient.py) and OptimizerConfig.acquisition."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hilbo_core.errors import ConfigError
from hilbo_core.knowledge_gradient import knowledge_gradient, knowledge_gradient_min
from hilbo_core.metabolic import GaussianProductEstimator
from hilbo_core.optimizer import AcquisitionKind, HILOptimizer, OptimizerConfig
from hilbo_core.presets import hip_6d

PHI0 = 1.0 / math.sqrt(2.0 * math.pi)


@pytest.mark.parametrize("a, b, expected", [
    ([0.0, 0.0], [0.0, 1.0], PHI0),  # E[max(0, Z)] = φ(0)
    ([0.0, 0.0], [-1.0, 1.0], 2.0 * PHI0),  # E|Z| = √(2/π)
    ([0.0, 0.0, 0.0], [-1.0, 0.0, 1.0], 2.0 * PHI0),  # the flat line never tops the envelope
    ([1.0, 0.0], [0.0, 0.0], 0.0),  # nothing can move
    ([5.0], [3.0], 0.0),  # one line: its mean
    ([0.0, -1.0], [0.0, 1.0], 1.0 * (-1.0 * 0.15865525393145707 + 0.24197072451914337)),  # f(-1)
])
def test_reference_values(a, b, expected) -> None:
    assert knowledge_gradient(np.array([a]), np.array([b]))[0] == pytest.approx(expected, abs=1e-12)


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), k=st.integers(1, 12))
def test_it_is_the_expected_maximum_of_the_lines(seed: int, k: int) -> None:
    rng = np.random.default_rng(seed)
    a = rng.normal(0.0, 1.0, k)
    b = rng.normal(0.0, 1.0, k)
    b[rng.uniform(size=k) < 0.2] = b[0]  # some equal slopes
    z = rng.standard_normal(200_000)
    mc = np.max(a[:, None] + b[:, None] * z, axis=0)
    got = knowledge_gradient(a[None, :], b[None, :])[0]
    assert got >= 0.0
    tol = 5.0 * float(np.std(mc)) / math.sqrt(z.size) + 1e-12
    assert got == pytest.approx(float(np.mean(mc)) - a.max(), abs=tol)


def test_a_noisier_measurement_is_worth_less() -> None:
    mean_ref = np.array([400.0, 410.0, 420.0])
    cov = np.array([[5.0], [2.0], [1.0]])
    values = [knowledge_gradient_min(mean_ref, cov, np.array([405.0]), np.array([100.0]), n)[0]
              for n in (1.0, 100.0, 1e4, 1e8)]
    assert values == sorted(values, reverse=True)
    assert values[-1] < 1e-3 * values[0]


def test_bad_shapes_and_variances_are_refused() -> None:
    with pytest.raises(ConfigError, match="cov_ref"):
        knowledge_gradient_min(np.zeros(3), np.zeros((2, 1)), np.zeros(1), np.ones(1), 1.0)
    with pytest.raises(ConfigError, match="noise_var > 0"):
        knowledge_gradient_min(np.zeros(1), np.zeros((1, 1)), np.zeros(1), np.ones(1), 0.0)
    with pytest.raises(ConfigError, match="finite"):
        knowledge_gradient(np.array([[np.nan]]), np.array([[1.0]]))


def test_acquisition_round_trips_defaults_to_ei_and_refuses_unknown_names() -> None:
    assert OptimizerConfig().acquisition is AcquisitionKind.EI
    cfg = OptimizerConfig(acquisition="kg")
    assert cfg.acquisition is AcquisitionKind.KG
    assert OptimizerConfig.from_json(cfg.to_json()).acquisition is AcquisitionKind.KG
    with pytest.raises(ConfigError, match="acquisition='ucb'"):
        OptimizerConfig(acquisition="ucb")


SPACE = hip_6d()


def _product() -> GaussianProductEstimator:
    return GaussianProductEstimator(400.0, 200.0**2, 40.0**2)


def _told(acquisition: str, seed: int) -> HILOptimizer:
    opt = HILOptimizer(SPACE, estimator_factory=_product, n_explore=2, seed=seed, n_candidates=128,
                       acquisition=acquisition)
    rng = np.random.default_rng(seed + 1)
    for u in SPACE.sample_unit(9, rng):
        opt.tell(SPACE.to_dict(SPACE.from_unit(u)), float(rng.uniform(360.0, 460.0)), 10.0**2,
                 breaths=45)
    return opt


@pytest.mark.parametrize("seed", range(3))
def test_kg_proposals_are_feasible_and_differ_from_ei(seed: int) -> None:
    kg, ei = _told("kg", seed).ask(), _told("ei", seed).ask()
    assert SPACE.is_feasible(kg)
    assert kg != ei


def test_measured_settings_are_kg_candidates() -> None:
    # With no new candidates at all, the knowledge gradient picks one of the measured settings.
    opt = _told("kg", 0)
    gp = opt._fit_gp(np.random.default_rng(0), store=False)
    u = opt._maximize_kg(gp, np.empty((0, SPACE.dim)))
    assert any(np.allclose(u, v) for v in opt._evaluation_units())


def _told_for(acquisition: str, duration_s: float, **options) -> HILOptimizer:
    """Nine settings told, each ``duration_s`` long on the optimizer's clock."""
    opt = HILOptimizer(SPACE, estimator_factory=_product, n_explore=2, seed=4, n_candidates=128,
                       acquisition=acquisition, **options)
    rng = np.random.default_rng(7)
    for u in SPACE.sample_unit(9, rng):
        opt.tell(SPACE.to_dict(SPACE.from_unit(u)), float(rng.uniform(360.0, 460.0)), 10.0**2,
                 breaths=45, duration_s=duration_s)
    return opt


def test_ei_then_kg_is_ei_before_kg_from_s_and_kg_global_after() -> None:
    # 9 settings of 100 s: the clock is at 900 s
    assert _told_for("ei-then-kg", 100.0, kg_from_s=1000.0).ask() == _told_for("ei", 100.0).ask()
    assert (_told_for("ei-then-kg", 100.0, kg_from_s=900.0).ask()
            == _told_for("kg-global", 100.0).ask())
    assert _told_for("kg-global", 100.0).ask() != _told_for("ei", 100.0).ask()


@pytest.mark.parametrize("value", [0.0, -1.0, float("nan"), True, "1620"])
def test_a_bad_kg_from_s_is_refused_with_its_value(value) -> None:
    with pytest.raises(ConfigError, match="kg_from_s"):
        OptimizerConfig(kg_from_s=value)
