"""Offline tuning of the sound rule's constants (bridge.bench.tune_sound)."""

from __future__ import annotations

import numpy as np
import pytest

from bridge.bench.tune_sound import (
    SoundReplay,
    TuneSoundConfig,
    realistic_trajectories,
    sound_cost,
    tune_sound,
)
from bridge.bench.tune_stopping import BreathTrace
from hilbo_core.errors import ConfigError
from hilbo_core.presets import hip_6d

N = 4
TIMES = [np.array([10.0, 20.0, 40.0, 60.0])] * 3


def _replay(truth=None) -> SoundReplay:
    # Trace 0 looks 100 W worse than trace 1's final from breath 0; trace 2 ends 50 W below 1.
    traces = [BreathTrace(np.array([500.0, 500.0, 500.0, 500.0]), np.full(N, 50.0)),
              BreathTrace(np.array([400.0, 400.0, 400.0, 400.0]), np.full(N, 50.0)),
              BreathTrace(np.array([450.0, 420.0, 380.0, 350.0]), np.full(N, 50.0))]
    return SoundReplay(traces, TIMES, np.zeros((3, N)), truth)


def test_steps_respect_the_time_floor_and_the_threshold_floor() -> None:
    r = _replay()
    # Against incumbent 1 (400 W, σ = 10): trace 0 is 10 σ worse; the first breath at >= 30 s
    # is breath 2 (40 s), so it stops after 3 breaths; against incumbent 2 (350 W) likewise.
    np.testing.assert_array_equal(r.steps(0, 30.0, 1.0), [4, 3, 3])
    # With no time floor it stops after breath 0.
    np.testing.assert_array_equal(r.steps(0, 0.0, 1.0), [4, 1, 1])
    # Trace 2 against incumbent 1: 450 − 400 = 5 σ at breath 0, 2 σ at 1, −2 σ at 2. With
    # min_decision 15 s the only chance is breath 1 (z = 2): stops if a_floor < 2.
    assert r.steps(2, 15.0, 1.0)[1] == 2
    assert r.steps(2, 15.0, 2.5)[1] == N


def test_stats_count_rejected_better_candidates_by_truth() -> None:
    # By truth trace 2 (340 W) beats 1 (400 W) and 0 (500 W); 1 beats 0.
    r = _replay(truth=[500.0, 400.0, 340.0])
    st = r.stats(15.0, 1.0)
    # Better pairs: (1,0), (2,0), (2,1). Trace 2 is stopped against 1 after breath 1: rejected.
    # Trace 1 vs 0: 400 − 500 < 0, never stopped; trace 2 vs 0: never worse by > 1 σ. 1 of 3.
    assert st["n_better"] == 3 and st["rejected_better"] == pytest.approx(1 / 3)
    # Steps: 0→[1: 2 breaths (20 s), 2: 2], 1→[0: 4, 2: 2 (z = 5 at 20 s)], 2→[0: 4, 1: 2].
    assert st["mean_breaths"] == pytest.approx((2 + 2 + 4 + 2 + 4 + 2) / 6)
    # Ended within 30 s: the four 2-breath evaluations (20 s).
    assert st["ended_30s"] == pytest.approx(4 / 6)


def test_stats_give_the_counts_behind_the_rates() -> None:
    r = _replay(truth=[500.0, 400.0, 340.0])
    st = r.stats(15.0, 1.0)
    assert st["n_pairs"] == 6 and st["breaths_total"] == 16 and st["n_early"] == 4
    assert st["n_ended_30s"] == 4 and st["n_rejected_better"] == 1
    # Truly better, and its final estimate above the incumbent's final: none here (2 ends at
    # 350 < 400 < 500; 1 at 400 < 500).
    assert st["n_better_above_at_n"] == 0
    assert r.stats(15.0, 1.0, js=[2])["n_pairs"] == 2


def test_accept_stop_ends_decided_evaluations_without_rejecting_them() -> None:
    r = _replay(truth=[500.0, 400.0, 340.0])
    # Trace 1 (400 W) against incumbent 0 (500 W): 100 W better, σ = 10, so −10 σ from breath
    # 0; with accept_z 3 and no time floor it ends after one breath, and it is no rejection.
    steps, rejected = r.outcomes(1, 0.0, 1.0, accept_z=3.0)
    assert steps[0] == 1 and not rejected[0]
    # Without the accept stop it runs to N.
    assert r.steps(1, 0.0, 1.0)[0] == N
    # The time floor holds for accept stops too: the first breath at >= 30 s is breath 2.
    assert r.steps(1, 30.0, 1.0, accept_z=3.0)[0] == 3
    # A rejection stays a rejection: trace 0 against 1 is stopped at breath 0 by the threshold.
    steps, rejected = r.outcomes(0, 0.0, 1.0, accept_z=3.0)
    assert steps[1] == 1 and rejected[1]
    st = r.stats(15.0, 1.0, accept_z=3.0)
    # Pair (2, 1): at 20 s trace 2 is 2 σ worse — rejected as before; accept stops add none.
    assert st["n_rejected_better"] == 1 and st["n_early"] > r.stats(15.0, 1.0)["n_early"]


def test_cost_penalises_only_the_excess() -> None:
    cfg = TuneSoundConfig(penalty=10.0)
    ok = {"breath_fraction": 0.7, "rejected_better": 0.10, "ended_30s": 0.05}
    assert sound_cost(ok, cfg) == pytest.approx(0.7)
    bad = ok | {"rejected_better": 0.15, "ended_30s": 0.07}
    assert sound_cost(bad, cfg) == pytest.approx(0.7 + 10 * 0.05 + 10 * 0.02)


def test_tune_sound_on_realistic_trajectories_meets_the_targets_offline() -> None:
    trajs, truth = realistic_trajectories(hip_6d(), seed=7, n_settings=12, n_max=20)
    assert len(trajs) == 12 and all(t.shape == (20, 2) for t in trajs)
    assert np.all(np.diff(trajs[0][:, 0]) > 0) and trajs[0][0, 0] > 0
    cfg = TuneSoundConfig(n_max=20, n_real=6, n_resamples=1, grid_min_decision_s=(30.0, 60.0),
                          grid_a_floor=(0.5, 1.0))
    res = tune_sound(trajs, cfg, truth=truth)
    assert res["n_trajectories"] == 12 and len(res["grid"]) == 4
    lo, hi = cfg.min_decision_bounds
    assert lo <= res["recommended"]["min_decision_s"] <= hi
    # A decision at >= 30 s can never end an evaluation within 30 s.
    assert all(g["ended_30s"] == 0.0 for g in res["grid"])
    assert res["grid_best"]["cost"] == min(g["cost"] for g in res["grid"])


@pytest.mark.parametrize("kw", [{"n_max": 1}, {"penalty": -1.0}, {"a_floor_bounds": (1.0, 0.5)},
                                {"min_decision_bounds": (-5.0, 10.0)}])
def test_bad_config(kw) -> None:
    with pytest.raises(ConfigError):
        TuneSoundConfig(**kw)


def test_too_few_trajectories() -> None:
    with pytest.raises(ConfigError, match="trajectories"):
        tune_sound([np.column_stack([np.arange(1.0, 46.0), np.full(45, 300.0)])] * 2)
