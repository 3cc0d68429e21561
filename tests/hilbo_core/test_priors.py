"""Tests for hilbo_core.priors: fast-prior observations with inflated noise (Antonova 2016 §3.3)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from hilbo_core import HILOptimizer, presets
from hilbo_core.errors import ConfigError
from hilbo_core.priors import (
    DEFAULT_PRIOR_NOISE,
    PriorNoise,
    PriorSource,
    inflate_variance,
    priors_from_evaluations,
    priors_from_rows,
)

HIP = {"t_on": 5.0, "t_p": 25.0, "t_off": 45.0, "F_p": 150.0, "F_r": 0.5, "F_f": 0.5}


def _row(**over):
    row = {k: str(v) for k, v in HIP.items()}
    row.update({"mean": "380.5", "var": "25"})
    row.update(over)
    return row


@given(var=st.floats(1e-6, 1e6), factor=st.floats(1.0, 100.0), extra=st.floats(0.0, 1e4))
def test_inflate_variance_formula(var: float, factor: float, extra: float) -> None:
    out = inflate_variance(var, PriorNoise(factor, extra))
    assert out == pytest.approx(factor * var + extra)
    assert out >= var  # a prior is never trusted more than its source


def test_prior_noise_validation() -> None:
    with pytest.raises(ConfigError, match="factor"):
        PriorNoise(factor=0.5)
    with pytest.raises(ConfigError, match="extra_var_w2"):
        PriorNoise(extra_var_w2=-1.0)
    with pytest.raises(ConfigError, match="var_w2"):
        inflate_variance(0.0, PriorNoise())
    assert set(DEFAULT_PRIOR_NOISE) == set(PriorSource)


def test_rows_with_var_sd_and_default() -> None:
    space = presets.hip_6d()
    rows = [_row(), _row(var="", sd="4"), {**_row(), "var": ""}, _row(subject="S3")]
    noise = PriorNoise(factor=2.0, extra_var_w2=10.0)
    out = priors_from_rows(space, rows, noise=noise, default_var_w2=9.0)
    assert [p.var for p in out] == pytest.approx([2 * 25 + 10, 2 * 16 + 10, 2 * 9 + 10, 2 * 25 + 10])
    assert out[0].mean == pytest.approx(380.5)
    assert out[0].params == pytest.approx(HIP)
    assert out[2].source == "population:row 2"


def test_relative_table_scaled_by_baseline() -> None:
    space = presets.hip_6d()
    out = priors_from_rows(space, [_row(mean="0.9", var="0.0004")], baseline_w=400.0,
                           noise=PriorNoise(1.0, 0.0))
    assert out[0].mean == pytest.approx(360.0)
    assert out[0].var == pytest.approx(0.0004 * 400.0**2)


def test_derived_parameters_may_be_present() -> None:
    space = presets.hip_ankle_4d()
    row = {"hip_t_peak": 25, "hip_t_offset": 45, "ankle_t1": 35, "ankle_t2": 55, "ankle_t3": 99,
           "mean": 350, "sd": 5}
    out = priors_from_rows(space, [row])
    assert out[0].params["ankle_t3"] == pytest.approx(65.0)  # recomputed, not the table's 99


@pytest.mark.parametrize(
    ("bad", "match"),
    [
        (_row(t_on="24", t_p="30"), "row 1.*t_on <= t_p - 15"),  # violates a constraint
        (_row(F_p="400"), "row 1.*F_p"),  # outside the bounds
        (_row(mean="nan"), "row 1 mean"),
        (_row(var="0"), "row 1 var"),
        (_row(var="-4"), "row 1 var"),
        (_row(F_r="abc"), "row 1 parameter F_r"),
        (_row(bogus="1"), "row 1: unknown column"),
        ({k: v for k, v in _row().items() if k != "mean"}, "row 1: missing the cost column"),
        ({k: v for k, v in _row().items() if k != "t_off"}, "row 1.*missing parameter"),
    ],
)
def test_bad_rows_name_the_row(bad: dict, match: str) -> None:
    with pytest.raises(ConfigError, match=match):
        priors_from_rows(presets.hip_6d(), [_row(), bad])


def test_row_without_uncertainty_needs_default() -> None:
    with pytest.raises(ConfigError, match="row 0: neither"):
        priors_from_rows(presets.hip_6d(), [{**HIP, "mean": 300}])


def test_evaluations_of_a_previous_session() -> None:
    space = presets.hip_6d()
    evs = [
        {"params": HIP, "mean": 390.0, "var": 30.0, "breaths": 45, "stopped_early": False},
        {"params": {**HIP, "F_p": 200.0}, "mean": 420.0, "var": 80.0, "stopped_early": True},
    ]
    out = priors_from_evaluations(space, evs, label="day1.mcap")
    noise = DEFAULT_PRIOR_NOISE[PriorSource.PREVIOUS_SESSION]
    expected = [inflate_variance(30.0, noise), inflate_variance(80.0, noise)]
    assert [p.var for p in out] == pytest.approx(expected)
    assert out[1].source == "day1.mcap:previous_session:evaluation 1"
    kept = priors_from_evaluations(space, evs, skip_early_stopped=True)
    assert len(kept) == 1 and kept[0].mean == 390.0
    # They are accepted by the optimizer and enter its GP training set.
    opt = HILOptimizer(space, prior_observations=out, seed=1)
    assert len(opt.to_json()["priors"]) == 2


@pytest.mark.parametrize(
    ("bad", "match"),
    [
        ({"params": HIP, "mean": float("nan"), "var": 3.0}, "evaluation 1 mean"),
        ({"params": HIP, "mean": 300.0, "var": 0.0}, "evaluation 1 var"),
        ({"params": HIP, "mean": 300.0}, r"evaluation 1: missing key\(s\) \['var'\]"),
        ({"params": {**HIP, "t_off": 70.0}, "mean": 300.0, "var": 3.0}, "evaluation 1.*t_off"),
        ({"params": [1, 2], "mean": 300.0, "var": 3.0}, "evaluation 1: params"),
    ],
)
def test_bad_evaluations_name_the_index(bad: dict, match: str) -> None:
    good = {"params": HIP, "mean": 300.0, "var": 3.0}
    with pytest.raises(ConfigError, match=match):
        priors_from_evaluations(presets.hip_6d(), [good, bad])


def test_unknown_source() -> None:
    with pytest.raises(ConfigError, match="prior source"):
        priors_from_evaluations(presets.hip_6d(), [], source="gossip")


def test_prior_pulls_the_gp_towards_it() -> None:
    """A fast prior at a point makes the GP's prediction there move towards the prior value."""
    from hilbo_core.gp import GaussianProcess

    space = presets.hip_6d()
    rng = np.random.default_rng(0)
    X = space.sample_unit(8, rng)
    y = 400.0 + 20.0 * rng.standard_normal(8)
    x0 = space.to_unit(space.from_dict(HIP))
    prior = priors_from_rows(space, [_row(mean="300", var="4")], noise=PriorNoise(4.0, 0.0))[0]
    gp0 = GaussianProcess().fit(X, y, np.full(8, 4.0), rng=np.random.default_rng(1))
    gp1 = GaussianProcess().fit(np.vstack([X, x0]), np.r_[y, prior.mean], np.r_[np.full(8, 4.0), prior.var],
                                rng=np.random.default_rng(1))
    m0 = gp0.predict(x0[None, :])[0][0]
    m1 = gp1.predict(x0[None, :])[0][0]
    assert abs(m1 - 300.0) < abs(m0 - 300.0)
