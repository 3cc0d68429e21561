"""The realistic simulated wearer: noise, outliers, dynamics, adaptation, families."""

from __future__ import annotations

import itertools
import json
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hilbo_core.errors import ConfigError, MeasurementError
from hilbo_core.presets import hip_6d, hip_ankle_4d
from hilbo_core.profiles import ForceProfile
from virtual_hw.wearer import SimulatedWearer, WearerKind, make_wearer
from virtual_hw.wearer_realistic import (
    Bump,
    BumpLandscape,
    LandscapeFamily,
    RealisticWearer,
    RealisticWearerConfig,
    adaptation_factor,
    bump_score,
    profile_moments,
)

SPACES = {"hip_6d": hip_6d(), "hip_ankle_4d": hip_ankle_4d()}
GRID = np.linspace(0.0, 100.0, 101)
SEEDS = st.integers(min_value=0, max_value=100_000)
N_STEADY = 2000  # breaths of unassisted walking for the noise statistics (≈ 1.1-1.9 h)


def steady_residuals(w: RealisticWearer, n: int = N_STEADY) -> tuple[np.ndarray, np.ndarray]:
    """Breath times and relative errors ``P / m(t) - 1`` of ``n`` unassisted breaths."""
    breaths = [w.next_breath() for _ in range(n)]
    t = np.array([b.t_s for b in breaths])
    r = np.array([b.watts / w.metabolic_rate_w(b.t_s) - 1.0 for b in breaths])
    return t, r


def robust_sd(x: np.ndarray) -> float:
    return float(1.4826 * np.median(np.abs(x - np.median(x))))


def acf(x: np.ndarray, lag: int) -> float:
    x = x - x.mean()
    return float(np.dot(x[:-lag], x[lag:]) / np.dot(x, x))


@pytest.fixture(scope="module")
def optimised() -> dict[tuple[str, int], RealisticWearer]:
    """Wearers whose true optimum is computed once for the whole module (40 seeds per space)."""
    out = {}
    for name, space in SPACES.items():
        for seed in range(40):
            w = RealisticWearer(space, seed)
            _ = w.true_optimum
            out[(name, seed)] = w
    return out


# ---------------------------------------------------------------------------- breath noise
@given(seed=SEEDS)
@settings(max_examples=12, deadline=None)
def test_steady_state_noise_cv_is_the_persons_8_to_12_percent(seed: int) -> None:
    w = RealisticWearer(hip_6d(), seed)
    assert 0.08 <= w.noise_cv <= 0.12
    _, r = steady_residuals(w)
    # The core (robust SD, blind to the outliers) is the drawn CV; the raw CV includes the
    # outliers and stays near the real recordings' median of about 11 %.
    assert robust_sd(r) == pytest.approx(w.noise_cv, abs=0.012)
    assert 0.075 <= float(np.std(r)) <= 0.17


def test_median_raw_cv_over_subjects_is_near_the_real_datas_11_percent() -> None:
    cvs = [float(np.std(steady_residuals(RealisticWearer(hip_6d(), s), 1000)[1])) for s in range(20)]
    assert 0.095 <= float(np.median(cvs)) <= 0.125


@given(seed=SEEDS)
@settings(max_examples=12, deadline=None)
def test_outliers_are_a_few_percent_and_heavy_tailed(seed: int) -> None:
    w = RealisticWearer(hip_6d(), seed)
    assert 0.01 <= w.outlier_frac <= 0.04
    _, r = steady_residuals(w)
    frac = w.n_outliers / N_STEADY
    # Binomial: 4 SD of the count around the drawn share.
    assert abs(frac - w.outlier_frac) <= 4.0 * math.sqrt(w.outlier_frac / N_STEADY) + 1e-3
    # Only outliers go beyond 5 core SDs (a Gaussian's 6e-7), and never past the clip.
    assert float(np.mean(np.abs(r) > 5.0 * w.noise_cv)) <= frac + 1e-12
    assert float(r.min()) >= 0.2 - 1.0 - 1e-12 and float(r.max()) <= 3.0 - 1.0 + 1e-12


def test_outliers_make_the_breaths_heavy_tailed() -> None:
    far, share = [], []
    for s in range(20):
        w = RealisticWearer(hip_6d(), s)
        _, r = steady_residuals(w)
        z = (r - r.mean()) / r.std()
        assert float(np.mean(z**4)) > 3.5  # kurtosis; a Gaussian's is 3 (SD ≈ 0.11 at 2000 breaths)
        far.append(float(np.mean(np.abs(r) > 4.0 * w.noise_cv)))
        share.append(w.outlier_frac)
    # Pooled: beyond 4 core SDs ≈ 0.3 of the outliers (0.3·t_3 beyond 0.4), a Gaussian 6e-5.
    assert 0.15 * np.mean(share) <= np.mean(far) <= np.mean(share)


def test_without_outliers_the_noise_is_gaussian_with_the_drawn_sd() -> None:
    cfg = RealisticWearerConfig(outlier_frac=(0.0, 0.0))
    w = RealisticWearer(hip_6d(), 7, cfg)
    _, r = steady_residuals(w)
    assert w.n_outliers == 0
    assert float(np.std(r)) == pytest.approx(w.noise_cv, rel=0.08)
    assert float(np.mean(np.abs(r) > 4.0 * w.noise_cv)) < 0.002


@given(seed=SEEDS)
@settings(max_examples=12, deadline=None)
def test_autocorrelation_beyond_3_s_is_below_0_15(seed: int) -> None:
    w = RealisticWearer(hip_6d(), seed)
    t, r = steady_residuals(w)
    mean_dt = float(np.mean(np.diff(t)))
    lags = [k for k in range(1, 8) if k * mean_dt > 3.0]
    assert lags and lags[0] <= 2  # at most two breaths span 3 s (breaths every 2-3.5 s)
    for k in lags:
        assert abs(acf(r, k)) < 0.15, (k, acf(r, k))


# ---------------------------------------------------------------------------- breath timing
@given(seed=SEEDS)
@settings(max_examples=12, deadline=None)
def test_breaths_come_every_2_to_3_5_s_with_jitter(seed: int) -> None:
    w = RealisticWearer(hip_6d(), seed)
    assert 2.0 <= w.breath_interval_mean_s <= 3.5
    t = np.array([w.next_breath().t_s for _ in range(600)])
    dt = np.diff(np.concatenate([[0.0], t]))
    assert float(dt.mean()) == pytest.approx(w.breath_interval_mean_s, rel=0.04)
    assert float(dt.std() / dt.mean()) >= 0.05  # irregular, not a metronome
    assert dt.min() >= 0.5 * w.breath_interval_mean_s - 1e-12
    assert dt.max() <= 2.0 * w.breath_interval_mean_s + 1e-12


def test_breath_rates_span_the_walking_range_over_subjects() -> None:
    means = [RealisticWearer(hip_6d(), s).breath_interval_mean_s for s in range(40)]
    assert min(means) < 2.3 and max(means) > 3.2  # ≈ 17-30 breaths/min


# ---------------------------------------------------------------------------- dynamics
def test_tau_is_per_person_in_14_to_55_s_log_uniform() -> None:
    taus = [RealisticWearer(hip_6d(), s).tau_s for s in range(40)]
    assert all(14.0 <= tau <= 55.0 for tau in taus)
    assert min(taus) < 18.0 and max(taus) > 45.0  # a 16 s walker and a 50 s one both occur
    assert 20.0 <= float(np.median(taus)) <= 36.0  # log-uniform: median √(14·55) ≈ 28 s


def test_the_steady_state_drifts_about_1_percent_per_minute_and_is_smooth() -> None:
    slopes, sds = [], []
    for seed in range(20):
        w = RealisticWearer(hip_6d(), seed)
        assert 0.015 <= w.drift_sd <= 0.035
        t = np.arange(0.0, 3600.0, 10.0)
        d = np.array([w.drift_factor(float(x)) for x in t]) - 1.0
        sds.append(float(np.std(d)) / w.drift_sd)
        slopes.append(float(np.sqrt(np.mean((np.diff(d) / 10.0 * 60.0) ** 2))))
        # It is the body's rate: metabolic_rate_w carries it, the same at every call.
        assert w.metabolic_rate_w(600.0) == pytest.approx(w.baseline_cost_w * w.drift_factor(600.0)
                                                          * w.adaptation_factor(600.0), rel=2e-3)
    assert 0.5 <= float(np.median(sds)) <= 1.5  # the drawn SD, give or take an hour's sampling
    assert 0.006 <= float(np.median(slopes)) <= 0.02  # RMS rate ≈ 1.3 %/min: about ±1 %/min
    assert RealisticWearer(hip_6d(), 3, RealisticWearerConfig.noiseless()).drift_factor(900.0) == 1.0


def test_a_partial_first_breath_after_a_change_and_every_other_breath_unchanged() -> None:
    space = hip_6d()
    x = space.to_dict(space.from_unit(np.full(6, 0.5)))
    always = RealisticWearer(space, 5, RealisticWearerConfig(first_breath_p=(1.0, 1.0)))
    never = RealisticWearer(space, 5, RealisticWearerConfig(first_breath_p=(0.0, 0.0)))
    runs = []
    for w in (always, never):
        before = w.breaths_until(100.0)
        t_change = w.t_s
        w.apply_params(x, t_change)
        runs.append((before + w.breaths_until(200.0), t_change))
    (ba, t_change), (bn, _) = runs
    a = np.array([r.watts for r in ba])
    n = np.array([r.watts for r in bn])
    assert [r.t_s for r in ba] == [r.t_s for r in bn]
    changed = np.flatnonzero(a != n)
    # Only the first breath after the change, and it is 20-60 % of the level.
    first = next(i for i, r in enumerate(ba) if r.t_s > t_change)
    assert changed.tolist() == [first] and always.n_partial_first_breaths == 1
    assert 0.2 <= a[first] / always.metabolic_rate_w(ba[first].t_s) <= 0.6
    assert never.n_partial_first_breaths == 0


@given(seed=SEEDS)
@settings(max_examples=15, deadline=None)
def test_a_step_relaxes_first_order_with_the_persons_tau(seed: int) -> None:
    w = RealisticWearer(hip_6d(), seed, RealisticWearerConfig.noiseless())
    x = hip_6d().to_dict(hip_6d().from_unit(np.full(6, 0.5)))
    t0 = 300.0
    w.breaths_until(t0)
    target = w.apply_params(x, t0)
    m0 = w.baseline_cost_w
    assert w.metabolic_rate_w(t0) == pytest.approx(m0, rel=1e-12)
    for k in (0.5, 1.0, 3.0):
        expected = target + (m0 - target) * math.exp(-k)
        assert w.metabolic_rate_w(t0 + k * w.tau_s) == pytest.approx(expected, rel=1e-9)
    # Noiseless breaths report exactly m(t).
    for b in w.breaths_until(t0 + 120.0):
        assert b.watts == pytest.approx(w.metabolic_rate_w(b.t_s), rel=1e-12)


@given(seed=SEEDS, gaps=st.lists(st.floats(min_value=0.5, max_value=200.0), min_size=2, max_size=6),
       points=st.lists(st.lists(st.floats(0.0, 1.0), min_size=6, max_size=6), min_size=6, max_size=6))
@settings(max_examples=25, deadline=None)
def test_each_transition_starts_where_the_body_is_no_jump_at_a_change(
        seed: int, gaps: list[float], points: list[list[float]]) -> None:
    space = hip_6d()
    w = RealisticWearer(space, seed)
    rng = np.random.default_rng(seed)
    feasible = space.sample_unit(len(gaps), rng)
    t = 100.0
    w.breaths_until(t)
    for gap, u in zip(gaps, feasible, strict=False):
        before = w.metabolic_rate_w(t)
        w.apply_params(space.to_dict(space.from_unit(u)), t)
        # The new transition starts from the rate the body was at (the previous setting's
        # transition, not its steady state, nor a reset), and the rate is continuous.
        assert w.metabolic_rate_w(t) == pytest.approx(before, rel=1e-12)
        assert w.metabolic_rate_w(t + 1e-6) == pytest.approx(before, rel=1e-6)
        t += gap
        w.breaths_until(t)


def test_a_quick_switch_starts_mid_transition() -> None:
    space = hip_6d()
    w = RealisticWearer(space, 3, RealisticWearerConfig.noiseless())
    lo = space.to_dict(space.from_unit(np.array([0.1, 0.4, 0.6, 1.0, 0.5, 0.5])))
    w.apply_params(lo, 0.0)
    c_lo = w.steady_state_cost_w
    t1 = 0.5 * w.tau_s
    mid = w.metabolic_rate_w(t1)
    assert abs(mid - c_lo) > 0.3 * abs(w.baseline_cost_w - c_lo)  # far from steady at t1
    w.breaths_until(t1)
    w.apply_profiles((), t1)
    assert w.metabolic_rate_w(t1) == pytest.approx(mid, rel=1e-12)
    expected = w.baseline_cost_w + (mid - w.baseline_cost_w) * math.exp(-1.0)
    assert w.metabolic_rate_w(t1 + w.tau_s) == pytest.approx(expected, rel=1e-9)


def test_standing_relaxes_to_the_standing_level_and_walking_starts_from_there() -> None:
    space = hip_6d()
    w = RealisticWearer(space, 5, RealisticWearerConfig.noiseless(), body_mass_kg=80.0)
    x = space.to_dict(space.from_unit(np.full(6, 0.5)))
    w.apply_params(x, 0.0)
    t1 = 600.0
    w.breaths_until(t1)
    walking = w.metabolic_rate_w(t1)
    assert w.stand(t1) == w.standing_cost_w == pytest.approx(1.5 * 80.0)
    assert w.applied_profiles == () and w.steady_state_cost_w == w.standing_cost_w
    assert w.metabolic_rate_w(t1) == pytest.approx(walking, rel=1e-12)  # no jump
    expected = w.standing_cost_w + (walking - w.standing_cost_w) * math.exp(-1.0)
    assert w.metabolic_rate_w(t1 + w.tau_s) == pytest.approx(expected, rel=1e-9)
    # Standing is a large step: walking costs 3-4x more.
    assert 3.0 < w.true_cost_w(x) / w.standing_cost_w < 4.5
    t2 = t1 + 10.0 * w.tau_s
    w.breaths_until(t2)
    assert w.metabolic_rate_w(t2) == pytest.approx(w.standing_cost_w, rel=1e-3)
    w.apply_params(x, t2)
    assert w.metabolic_rate_w(t2 + w.tau_s) == pytest.approx(
        w.true_cost_w(x) + (w.metabolic_rate_w(t2) - w.true_cost_w(x)) * math.exp(-1.0), rel=1e-9)
    with pytest.raises(MeasurementError, match="goes backwards"):
        w.stand(t1)


# ---------------------------------------------------------------------------- adaptation
def test_adaptation_factor_is_1_at_0_and_1_minus_alpha_after_an_hour() -> None:
    assert adaptation_factor(0.0, 0.02, 1500.0) == 1.0
    assert adaptation_factor(3600.0, 0.02, 1500.0) == pytest.approx(0.98, abs=1e-15)
    values = [adaptation_factor(t, 0.02, 1500.0) for t in np.linspace(0, 3600, 50)]
    assert all(a >= b for a, b in itertools.pairwise(values))  # only ever falls


def test_every_settings_cost_falls_0_to_3_percent_over_the_hour_per_person() -> None:
    space = hip_6d()
    x = space.to_dict(space.from_unit(np.full(6, 0.5)))
    drops = []
    for s in range(40):
        w = RealisticWearer(space, s)
        drop = 1.0 - w.true_cost_w(x, 3600.0) / w.true_cost_w(x)
        assert drop == pytest.approx(w.adaptation_frac, abs=1e-12)
        assert 1.0 - w.adaptation_factor(3600.0) == pytest.approx(drop, abs=1e-12)
        drops.append(drop)
    assert all(0.0 <= d <= 0.03 for d in drops)
    assert min(drops) < 0.005 and max(drops) > 0.025


@given(seed=SEEDS)
@settings(max_examples=10, deadline=None)
def test_the_body_follows_the_adaptation_at_steady_state(seed: int) -> None:
    w = RealisticWearer(hip_6d(), seed, RealisticWearerConfig.noiseless(adaptation_frac=(0.03, 0.03)))
    w.breaths_until(3600.0)
    # Unassisted for an hour: the rate tracks the falling target with a lag of ≈ τ/T of it.
    assert w.metabolic_rate_w(3600.0) == pytest.approx(0.97 * w.baseline_cost_w, rel=2e-3)
    assert w.metabolic_rate_w(3600.0) < w.metabolic_rate_w(600.0) < w.baseline_cost_w


# ---------------------------------------------------------------------------- landscapes
def test_moments_of_a_rectangle() -> None:
    f = np.where((GRID >= 20.0) & (GRID <= 40.0), 100.0, 0.0)
    mu, sigma, q = profile_moments(GRID, f)
    assert mu == pytest.approx(30.0)
    # 20 %GC wide (its edges are 1 %GC ramps on the table's grid).
    assert sigma == pytest.approx(20.0 / math.sqrt(12.0), rel=0.06)
    assert q == pytest.approx(100.0, rel=0.06)  # ∫f²/∫f of a rectangle (trapezoid ends)
    assert profile_moments(GRID, np.zeros_like(GRID)) == (0.0, 0.0, 0.0)
    assert profile_moments(GRID, -f) == (0.0, 0.0, 0.0)  # a cable cannot push


def test_bump_score_is_1_at_the_primary_bumps_centre_and_0_without_force() -> None:
    f = np.where((GRID >= 20.0) & (GRID <= 40.0), 100.0, 0.0)
    mu, sigma, q = profile_moments(GRID, f)
    main = Bump(mu, sigma, 4.0, 2.0, 0.5, 1.0, q)
    far = Bump(mu + 40.0, sigma, 4.0, 2.0, 0.0, 0.6, q)
    land = BumpLandscape("hip", (main, far), 0.15, 0.2)
    assert bump_score(GRID, f, land) == pytest.approx(1.0, abs=1e-6)
    assert bump_score(GRID, np.zeros_like(GRID), land) == 0.0
    late = np.where((GRID >= 85.0) & (GRID <= 99.0), 100.0, 0.0)
    assert bump_score(GRID, late, land) < 0.0  # force at the wrong time costs
    # Half or twice the ideal force scores less, gently (r·e^{1-r}).
    assert bump_score(GRID, 0.5 * f, land) == pytest.approx(0.5 * math.exp(0.5), abs=1e-6)
    assert bump_score(GRID, 2.0 * f, land) == pytest.approx(2.0 * math.exp(-1.0), abs=1e-6)


@pytest.mark.parametrize("space_name", sorted(SPACES))
def test_two_landscape_families_over_seeds_with_5_to_25_percent_reduction(
        space_name: str, optimised: dict[tuple[str, int], RealisticWearer]) -> None:
    wearers = [w for (name, _), w in optimised.items() if name == space_name]
    families = {w.family for w in wearers}
    assert families == {LandscapeFamily.WINDOW, LandscapeFamily.BUMPS}
    rng = np.random.default_rng(0)
    space = SPACES[space_name]
    for w in wearers:
        params, cost = w.true_optimum
        reduction = 1.0 - cost / w.baseline_cost_w
        assert 0.05 <= reduction <= 0.25, (w.seed, w.family, reduction)
        assert w.true_cost_w(params) == pytest.approx(cost, rel=1e-12)
        assert space.feasible_mask(space.from_dict(params)[None, :])[0]
        others = [w.true_cost_w(space.to_dict(x)) for x in space.from_unit(space.sample_unit(64, rng))]
        assert cost <= min(others) + 1e-9
        assert w.cost_of_profiles(()) == w.baseline_cost_w
        assert json.loads(json.dumps(w.subject))["family"] == w.family.value


def test_the_families_put_the_optimum_in_different_places(
        optimised: dict[tuple[str, int], RealisticWearer]) -> None:
    # The same person (seed) under the other family: a different landscape, not a rescaling.
    w = optimised[("hip_6d", 0)]
    other = (LandscapeFamily.WINDOW if w.family is LandscapeFamily.BUMPS else LandscapeFamily.BUMPS)
    twin = RealisticWearer(hip_6d(), 0, RealisticWearerConfig(
        p_bumps=1.0 if other is LandscapeFamily.BUMPS else 0.0))
    assert twin.family is other
    a = hip_6d().from_dict(w.true_optimum[0])
    b = hip_6d().from_dict(twin.true_optimum[0])
    assert float(np.max(np.abs(hip_6d().to_unit(a) - hip_6d().to_unit(b)))) > 0.05


# ---------------------------------------------------------------------------- determinism & API
@given(seed=SEEDS)
@settings(max_examples=10, deadline=None)
def test_same_seed_same_subject_and_breaths(seed: int) -> None:
    space = hip_6d()
    x = space.to_dict(space.from_unit(np.full(6, 0.4)))

    def run() -> tuple[dict, list]:
        w = RealisticWearer(space, seed)
        out = w.breaths_until(200.0)
        w.apply_params(x, w.t_s)
        out += w.breaths_until(400.0)
        return w.subject, out

    assert run() == run()
    assert RealisticWearer(space, seed).subject != RealisticWearer(space, seed + 1).subject


def test_make_wearer_picks_the_kind_and_realistic_is_the_default_choice() -> None:
    space = hip_6d()
    assert isinstance(make_wearer("realistic", space, 1), RealisticWearer)
    assert isinstance(make_wearer(WearerKind.LEGACY, space, 1), SimulatedWearer)
    legacy = make_wearer("legacy", space, 1)
    assert legacy.breaths_until(30.0) == SimulatedWearer(space, 1).breaths_until(30.0)
    with pytest.raises(ConfigError, match=r"wearer='human'; expected one of realistic, noisy, slow, legacy"):
        make_wearer("human", space, 1)


def test_truth_at_a_time_is_the_unadapted_truth_times_the_adaptation() -> None:
    space = hip_ankle_4d()
    w = RealisticWearer(space, 5)
    x = space.to_dict(space.from_unit(np.full(4, 0.3)))
    assert w.true_cost_w(x, 1800.0) == pytest.approx(w.true_cost_w(x) * w.adaptation_factor(1800.0))
    with pytest.raises(MeasurementError, match=r"t_s=-1\.0"):
        w.true_cost_w(x, -1.0)
    # The legacy wearer answers the same questions and does not adapt.
    legacy = SimulatedWearer(space, 5)
    assert legacy.adaptation_factor(3600.0) == 1.0
    assert legacy.true_cost_w(x, 3600.0) == legacy.true_cost_w(x)


@pytest.mark.parametrize(("overrides", "message"), [
    ({"tau_s": (60.0, 30.0)}, "tau_s"),
    ({"noise_cv": (0.1, 0.9)}, "noise_cv"),
    ({"outlier_frac": (-0.1, 0.1)}, "outlier_frac"),
    ({"adaptation_tau_s": (100.0, 2000.0)}, "adaptation_tau_s"),
    ({"p_bumps": 1.5}, "p_bumps"),
    ({"bumps": ()}, "windows and bumps must cover the same actuators"),
])
def test_config_refuses_bad_values_by_name(overrides: dict, message: str) -> None:
    with pytest.raises(ConfigError, match=message):
        RealisticWearerConfig(**overrides)


def test_bad_inputs_are_refused() -> None:
    space = hip_6d()
    with pytest.raises(ConfigError, match="seed=-1"):
        RealisticWearer(space, -1)
    with pytest.raises(ConfigError, match="config must be a RealisticWearerConfig"):
        RealisticWearer(space, 1, config=object())  # type: ignore[arg-type]
    w = RealisticWearer(space, 1)
    w.breaths_until(50.0)
    with pytest.raises(MeasurementError, match="goes backwards"):
        w.apply_profiles((), 10.0)
    with pytest.raises(MeasurementError, match="goes backwards"):
        w.breaths_until(10.0)
    with pytest.raises(MeasurementError, match="times must be in seconds"):
        w.breaths_until(1e9)
    with pytest.raises(ConfigError, match="no model for actuator 'knee'"):
        w.apply_profiles((ForceProfile("knee", GRID, np.zeros_like(GRID)),), 60.0)


def test_steps_to_and_from_standing_have_a_phase_i_and_walking_steps_do_not() -> None:
    space = hip_6d()
    cfg = RealisticWearerConfig.noiseless(phase1_s=(15.0, 15.0), phase1_share=(0.2, 0.2))
    w = RealisticWearer(space, 5, cfg)
    x = space.to_dict(space.from_unit(np.full(6, 0.5)))
    y = space.to_dict(space.from_unit(np.full(6, 0.3)))
    w.apply_params(x, 0.0)  # walking to walking: first-order
    m0, c = w.metabolic_rate_w(0.0), w.steady_state_cost_w
    assert w.metabolic_rate_w(w.tau_s) == pytest.approx(c + (m0 - c) * math.exp(-1.0), rel=1e-9)
    t1 = 600.0
    walking = w.metabolic_rate_w(t1)
    w.stand(t1)
    stand = w.standing_cost_w
    left = 1.0 - 0.2 * (1.0 - math.exp(-4.0))  # the share of the step still to come after δ
    assert w.metabolic_rate_w(t1) == pytest.approx(walking, rel=1e-12)  # no jump
    assert w.metabolic_rate_w(t1 + 15.0) == pytest.approx(stand + (walking - stand) * left, rel=1e-9)
    assert w.metabolic_rate_w(t1 + 15.0 + w.tau_s) == pytest.approx(
        stand + (walking - stand) * left * math.exp(-1.0), rel=1e-9)
    t2 = t1 + 600.0
    low = w.metabolic_rate_w(t2)
    w.apply_params(y, t2)  # from standing: phase I again
    c_y = w.steady_state_cost_w
    assert w.metabolic_rate_w(t2 + 15.0) == pytest.approx(c_y + (low - c_y) * left, rel=1e-9)
    t3 = t2 + 600.0
    m3 = w.metabolic_rate_w(t3)
    w.apply_params(x, t3)  # the next walking setting: first-order again
    assert w.metabolic_rate_w(t3 + w.tau_s) == pytest.approx(c + (m3 - c) * math.exp(-1.0), rel=1e-9)
    assert w.subject["phase1_s"] == 15.0 and w.subject["phase1_share"] == 0.2
    # A stand and a walk at the same instant replace each other: a walking step, first-order.
    t4 = t3 + 600.0
    m4 = w.metabolic_rate_w(t4)
    w.stand(t4)
    w.apply_params(y, t4)
    assert w.metabolic_rate_w(t4 + w.tau_s) == pytest.approx(c_y + (m4 - c_y) * math.exp(-1.0), rel=1e-9)
