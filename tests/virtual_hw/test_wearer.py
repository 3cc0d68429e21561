"""The simulated wearer: landscape, true optimum, first-order dynamics and breaths."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hilbo_core.errors import ConfigError, InfeasibleError, MeasurementError
from hilbo_core.presets import hip_6d, hip_ankle_4d
from hilbo_core.profiles import ForceProfile
from virtual_hw.wearer import (
    ActuatorPrior,
    SimulatedWearer,
    WearerConfig,
    assistance_score,
    relaxed_rate_w,
    saturate_penalty,
    timing_window,
)

SPACES = {"hip_6d": hip_6d(), "hip_ankle_4d": hip_ankle_4d()}
GRID = np.linspace(0.0, 100.0, 101)


@pytest.fixture(scope="module")
def optimised() -> dict[tuple[str, int], SimulatedWearer]:
    """Wearers whose true optimum is computed once for the whole module."""
    out = {}
    for name, space in SPACES.items():
        for seed in range(4):
            w = SimulatedWearer(space, seed)
            _ = w.true_optimum
            out[(name, seed)] = w
    return out


# ---------------------------------------------------------------------------- pure functions
@pytest.mark.parametrize(("scale", "expected"), [(0.0, 0.0), (0.5, 0.75), (1.0, 1.0), (2.0, 0.0)])
def test_score_of_scaled_ideal_profile_is_2a_minus_a_squared(scale: float, expected: float) -> None:
    # f = a·F·w gives φ = 2a - a² exactly (the integrals are the same trapezoid sums).
    w = timing_window(GRID, 25.0, 9.0)
    score = assistance_score(GRID, scale * 180.0 * w, 25.0, 9.0, 180.0)
    assert score == pytest.approx(expected, abs=1e-12)


def test_score_penalises_force_outside_the_window_and_ignores_negative_force() -> None:
    late = np.where((GRID > 70) & (GRID < 90), 150.0, 0.0)
    assert assistance_score(GRID, late, 25.0, 8.0, 180.0) < -0.5
    assert assistance_score(GRID, -late, 25.0, 8.0, 180.0) == 0.0  # a cable cannot push


def test_window_and_score_refuse_non_positive_scales() -> None:
    with pytest.raises(ConfigError, match="width_pct"):
        timing_window(GRID, 25.0, 0.0)
    with pytest.raises(ConfigError, match="ideal_force_n"):
        assistance_score(GRID, np.zeros(101), 25.0, 8.0, -1.0)


def test_window_wraps_around_the_cycle() -> None:
    w = timing_window(np.array([0.0, 5.0, 95.0, 50.0]), 0.0, 5.0)
    assert w[0] == 1.0
    assert w[1] == pytest.approx(math.exp(-0.5)) and w[2] == pytest.approx(math.exp(-0.5))
    assert w[3] < 1e-10


def test_saturation_is_identity_above_zero_and_bounded_below() -> None:
    assert saturate_penalty(0.3, 0.5) == 0.3
    assert saturate_penalty(-1e-6, 0.5) == pytest.approx(-1e-6, rel=1e-6)  # C¹ at zero
    assert saturate_penalty(-100.0, 0.5) == pytest.approx(-0.5)
    assert saturate_penalty(-0.5, 0.5) == pytest.approx(-0.5 * math.tanh(1.0))


def test_relaxation_reference_value() -> None:
    # One time constant after the change, 1 - 1/e ≈ 63.2 % of the step is done.
    m = relaxed_rate_w(100.0 + 40.0, 100.0, 400.0, 340.0, 40.0)
    assert m == pytest.approx(340.0 + 60.0 * math.exp(-1.0))
    assert (400.0 - m) / 60.0 == pytest.approx(0.6321, abs=1e-4)


# ---------------------------------------------------------------------------- the subject
def test_same_seed_same_subject_and_breaths_different_seed_different_subject() -> None:
    space = SPACES["hip_ankle_4d"]
    x = space.to_dict(np.array([25.0, 45.0, 35.0, 55.0]))

    def session(seed: int) -> tuple[dict, list[tuple[float, ...]]]:
        w = SimulatedWearer(space, seed)
        b = w.breaths_until(120.0)
        w.apply_params(x, 121.0)
        b += w.breaths_until(300.0)
        return w.subject, [(r.t_s, r.vo2_ml_min, r.vco2_ml_min, r.rer, r.hr_bpm) for r in b]

    s1, b1 = session(7)
    s2, b2 = session(7)
    s3, b3 = session(8)
    assert s1 == s2 and b1 == b2
    assert s1 != s3 and b1[:5] != b3[:5]
    json.dumps(s1)  # JSON-able for summary.json
    assert {"tau_s", "unassisted_cost_w", "windows"} <= set(s1)
    assert {"centre_pct", "width_pct", "ideal_force_n"} <= set(s1["windows"]["hip"])


def test_different_seeds_have_different_optima(optimised) -> None:
    for name in SPACES:
        optima = [optimised[(name, s)].true_optimum[0] for s in range(4)]
        vecs = np.array([SPACES[name].from_dict(p) for p in optima])
        spread = np.ptp(SPACES[name].to_unit(vecs), axis=0)
        assert spread.max() > 0.05, name


def test_noise_level_does_not_change_who_the_subject_is() -> None:
    a = SimulatedWearer(SPACES["hip_6d"], 3)
    b = SimulatedWearer(SPACES["hip_6d"], 3, WearerConfig.noiseless())
    assert a.windows == b.windows and a.baseline_cost_w == b.baseline_cost_w


@pytest.mark.parametrize("name", list(SPACES))
@pytest.mark.parametrize("seed", range(4))
def test_true_optimum_is_feasible_and_a_realistic_reduction(optimised, name: str, seed: int) -> None:
    w = optimised[(name, seed)]
    params, cost = w.true_optimum
    assert SPACES[name].is_feasible(params)
    assert w.true_cost_w(params) == pytest.approx(cost)
    reduction = 1.0 - cost / w.baseline_cost_w
    assert 0.05 <= reduction <= 0.25
    assert 300.0 <= w.baseline_cost_w <= 450.0  # 75 kg walking at 1.25 m/s


@pytest.mark.parametrize("name", list(SPACES))
def test_true_optimum_beats_4096_random_feasible_points(optimised, name: str) -> None:
    space = SPACES[name]
    w = optimised[(name, 0)]
    xs = space.from_unit(space.sample_unit(4096, np.random.default_rng(2024)))
    best_random = min(w.true_cost_w(space.to_dict(x)) for x in xs)
    assert w.true_optimum[1] <= best_random


def test_optimum_is_interior_in_force_and_timing(optimised) -> None:
    for seed in range(4):
        p = optimised[("hip_6d", seed)].true_optimum[0]
        assert 60.0 < p["F_p"] < 245.0 and 16.0 < p["t_p"] < 39.0


def test_node_ratios_matter_less_than_timing_and_peak_force(optimised) -> None:
    space = SPACES["hip_6d"]
    for seed in range(4):
        w = optimised[("hip_6d", seed)]
        x0 = space.from_dict(w.true_optimum[0])
        spread = {}
        for j, name in enumerate(space.names):
            costs = []
            for v in np.linspace(space.lower[j], space.upper[j], 17):
                x = x0.copy()
                x[j] = v
                if space.feasible_mask(x[None, :])[0]:
                    costs.append(w.true_cost_w(space.to_dict(x)))
            spread[name] = max(costs) - min(costs)
        assert max(spread["F_r"], spread["F_f"]) < 0.5 * spread["F_p"], (seed, spread)
        assert max(spread["F_r"], spread["F_f"]) < spread["t_p"], (seed, spread)


# ---------------------------------------------------------------------------- no / lost assistance
def test_no_assistance_and_zero_tables_give_the_baseline() -> None:
    w = SimulatedWearer(SPACES["hip_ankle_4d"], 1)
    zero = (ForceProfile("hip", GRID, np.zeros(101)), ForceProfile("ankle", GRID, np.zeros(101)))
    assert w.cost_of_profiles(()) == w.baseline_cost_w
    assert w.cost_of_profiles(zero) == w.baseline_cost_w
    assert w.metabolic_rate_w(0.0) == w.baseline_cost_w


def test_a_lost_profile_shows_in_the_metabolic_rate(optimised) -> None:
    w = SimulatedWearer(SPACES["hip_ankle_4d"], 2, WearerConfig.noiseless())
    params, c_opt = optimised[("hip_ankle_4d", 2)].true_optimum
    hip_only = w.profiles_for(params)[:1]  # the ankle table was lost on the way
    assert w.apply_profiles(hip_only, 0.0) > c_opt + 1.0
    w.apply_params(params, 10.0)
    assert w.steady_state_cost_w == pytest.approx(c_opt)
    w.apply_profiles((), 600.0)  # assistance off: back to baseline
    assert w.metabolic_rate_w(600.0 + 10 * w.tau_s) == pytest.approx(w.baseline_cost_w, rel=1e-4)


# ---------------------------------------------------------------------------- dynamics
def test_step_response_reaches_63_percent_after_tau(optimised) -> None:
    w = SimulatedWearer(SPACES["hip_6d"], 0)
    params, c_opt = optimised[("hip_6d", 0)].true_optimum
    w.breaths_until(60.0)
    m0 = w.metabolic_rate_w(60.0)
    w.apply_params(params, 60.0)
    done = (m0 - w.metabolic_rate_w(60.0 + w.tau_s)) / (m0 - c_opt)
    assert done == pytest.approx(1.0 - math.exp(-1.0), abs=1e-9)
    assert 30.0 <= w.tau_s <= 50.0


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**31), t_change=st.floats(0.0, 500.0), dt=st.floats(0.0, 2000.0))
def test_rate_moves_monotonically_from_old_to_new_state(seed: int, t_change: float,
                                                        dt: float) -> None:
    space = SPACES["hip_ankle_4d"]
    w = SimulatedWearer(space, seed)
    x = space.from_unit(space.sample_unit(1, np.random.default_rng(seed))[0])
    m0 = w.metabolic_rate_w(t_change)
    c = w.apply_params(space.to_dict(x), t_change)
    m1 = w.metabolic_rate_w(t_change + dt)
    m2 = w.metabolic_rate_w(t_change + dt + 1.0)
    lo, hi = min(m0, c), max(m0, c)
    assert lo - 1e-9 <= m1 <= hi + 1e-9
    assert abs(m2 - c) <= abs(m1 - c) + 1e-9
    assert w.metabolic_rate_w(t_change / 2) == m0  # history before the change is unchanged


@pytest.mark.parametrize("seed", range(5))
def test_noisy_breaths_average_to_the_steady_state(optimised, seed: int) -> None:
    # Seed §III.1's ground truth: the mean of the last 2 minutes of a 6-minute hold.
    w = SimulatedWearer(SPACES["hip_ankle_4d"], seed)
    params = optimised[("hip_ankle_4d", seed % 4)].true_optimum[0]
    c = w.apply_params(params, 0.0)
    watts = np.array([b.watts for b in w.breaths_until(360.0) if b.t_s >= 240.0])
    assert len(watts) > 30
    assert np.mean(watts) == pytest.approx(c, rel=0.05)
    # Breath-by-breath scatter is realistic: roughly 10-15 % of the level.
    assert 0.06 < np.std(watts) / c < 0.22


# ---------------------------------------------------------------------------- breaths
def test_breath_intervals_are_irregular_around_three_seconds() -> None:
    w = SimulatedWearer(SPACES["hip_6d"], 4)
    t = np.array([b.t_s for b in w.breaths_until(3600.0)])
    dt = np.diff(np.concatenate([[0.0], t]))
    assert 1050 <= len(t) <= 1350  # 18-22 breaths/min for an hour
    assert np.mean(dt) == pytest.approx(w.subject["breath_interval_mean_s"], rel=0.05)
    assert 2.6 < np.mean(dt) < 3.4
    assert np.all(dt >= 1.0) and np.std(dt) / np.mean(dt) > 0.15
    assert w.t_s == t[-1] and w.n_breaths == len(t)


def test_noiseless_breaths_obey_brockway_and_equal_the_rate() -> None:
    space = SPACES["hip_6d"]
    w = SimulatedWearer(space, 5, WearerConfig.noiseless())
    w.apply_params(space.to_dict(np.array([5.0, 25.0, 45.0, 180.0, 0.5, 0.5])), 0.0)
    for b in w.breaths_until(300.0):
        assert b.watts == pytest.approx(w.metabolic_rate_w(b.t_s), rel=1e-12)
        assert b.rer == pytest.approx(b.vco2_ml_min / b.vo2_ml_min)
        assert 0.85 <= b.rer <= 0.90
        assert b.is_finite() and 60 < b.hr_bpm < 140 and 15 < b.ve_l_min < 45
        # Brockway by hand: P = (16.58·VO2 + 4.51·VCO2) / 60 with gases in ml/min.
        assert (16.58 * b.vo2_ml_min + 4.51 * b.vco2_ml_min) / 60 == pytest.approx(b.watts)


def test_noisy_breaths_are_physiological() -> None:
    w = SimulatedWearer(SPACES["hip_6d"], 6)
    breaths = w.breaths_until(1200.0)
    vo2 = np.array([b.vo2_ml_min for b in breaths])
    rer = np.array([b.rer for b in breaths])
    assert np.all(vo2 > 0) and 900 < np.mean(vo2) < 1400
    assert 80 < np.std(vo2) < 300  # a few hundred ml/min at most
    assert 0.83 < np.mean(rer) < 0.92 and np.all((rer >= 0.7) & (rer <= 1.1))
    # Some breath-to-breath correlation (AR(1) ρ = 0.3).
    e = vo2 / np.mean(vo2) - 1
    assert 0.1 < np.corrcoef(e[:-1], e[1:])[0, 1] < 0.5


def test_a_60_minute_session_breathes_through_40_settings() -> None:
    # How fast it runs is `hilbo bench perf`'s business: a timed assertion fails on a busy machine.
    space = SPACES["hip_6d"]
    w = SimulatedWearer(space, 9)
    xs = space.from_unit(space.sample_unit(40, np.random.default_rng(0)))
    n = 0
    for k, x in enumerate(xs):
        n += len(w.breaths_until(90.0 * k))
        w.apply_params(space.to_dict(x), 90.0 * k)
    n += len(w.breaths_until(3600.0))
    assert n > 1000


@pytest.mark.parametrize("name", list(SPACES))
def test_true_optimum_is_feasible_and_beats_unassisted(name: str) -> None:
    # Its speed (0.1-0.4 s on one core) is not a test's business: a busy machine took 3 s.
    w = SimulatedWearer(SPACES[name], 11)
    params, cost = w.true_optimum
    assert SPACES[name].is_feasible(params)
    assert cost == pytest.approx(w.true_cost_w(params)) and cost < w.baseline_cost_w


# ---------------------------------------------------------------------------- bad input
def test_bad_times_are_refused() -> None:
    w = SimulatedWearer(SPACES["hip_ankle_4d"], 0)
    for bad in (float("nan"), float("inf"), -1.0, "soon"):
        with pytest.raises(MeasurementError):
            w.breaths_until(bad)  # type: ignore[arg-type]
        with pytest.raises(MeasurementError):
            w.metabolic_rate_w(bad)  # type: ignore[arg-type]
    w.breaths_until(60.0)
    with pytest.raises(MeasurementError, match="backwards"):
        w.breaths_until(w.t_s - 1.0)
    with pytest.raises(MeasurementError, match="backwards"):
        w.apply_profiles((), w.t_s - 0.5)
    with pytest.raises(MeasurementError):
        w.breaths_until(1e12)  # a time in the wrong unit, not a session


def test_bad_settings_and_profiles_are_refused() -> None:
    space = SPACES["hip_6d"]
    w = SimulatedWearer(space, 0)
    ok = {"t_on": 5.0, "t_p": 25.0, "t_off": 45.0, "F_p": 180.0, "F_r": 0.5, "F_f": 0.5}
    with pytest.raises(InfeasibleError, match="F_p"):
        w.true_cost_w({**ok, "F_p": 400.0})
    with pytest.raises(InfeasibleError, match="t_on"):
        w.apply_params({**ok, "t_on": 20.0}, 1.0)
    with pytest.raises(ConfigError):
        w.true_cost_w({**ok, "F_q": 1.0})
    knee = ForceProfile("knee", GRID, np.zeros(101))
    with pytest.raises(ConfigError, match="knee"):
        w.cost_of_profiles((knee,))
    hip = w.profiles_for(ok)[0]
    with pytest.raises(ConfigError, match="twice"):
        w.apply_profiles((hip, hip), 1.0)
    with pytest.raises(ConfigError):
        w.cost_of_profiles([np.zeros(101)])  # type: ignore[list-item]
    assert w.steady_state_cost_w == w.baseline_cost_w  # nothing was applied


@pytest.mark.parametrize(
    "kwargs",
    [
        {"tau_s": (50.0, 30.0)},
        {"tau_s": (float("nan"), 40.0)},
        {"noise_frac": (0.1, 0.9)},
        {"noise_ar1": 1.0},
        {"breath_interval_cv": -0.1},
        {"min_breath_interval_s": 5.0},
        {"rer": (0.5, 0.9)},
        {"penalty_cap": 0.0},
        {"n_optimum_starts": 0},
        {"report_hr": "yes"},
        {"actuators": (ActuatorPrior("hip", (20, 28), (7, 11), (0.2, 0.3), (0.1, 0.2)),) * 2},
    ],
)
def test_bad_config_is_refused(kwargs: dict) -> None:
    with pytest.raises(ConfigError):
        WearerConfig(**kwargs)


def test_bad_constructor_arguments_are_refused() -> None:
    with pytest.raises(ConfigError, match="seed"):
        SimulatedWearer(SPACES["hip_6d"], -1)
    with pytest.raises(ConfigError, match="body_mass_kg"):
        SimulatedWearer(SPACES["hip_6d"], 0, body_mass_kg=5.0)
    with pytest.raises(ConfigError, match="builder"):
        from hilbo_core.space import Parameter, ParameterSpace

        SimulatedWearer(ParameterSpace([Parameter("a", 0.0, 1.0)], name="toy"), 0)
    with pytest.raises(ConfigError, match="ActuatorPrior"):
        ActuatorPrior("hip", (20, 28), (7, 11), (0.2, 0.3), (0.1, 0.9))
