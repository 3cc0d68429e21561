"""bridge.bench.hil: constraint projection, sessions of every method at toy size, the summary."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from bridge.bench.hil import (
    HilProtocol,
    HilTask,
    hil_table,
    project_feasible,
    regret_at,
    run_hil_task,
    summarize_hil,
)
from hilbo_core.errors import ConfigError
from hilbo_core.presets import hip_6d

TOY = HilProtocol(minutes=5.5, warmup_s=30.0, n_explore=2, max_breaths=5, condition_s=30.0, popsize=4,
                  bout1_conditions=4, grid_min=0.5)
A_HIP, B_HIP = hip_6d().unit_constraints()


def test_projection_reference_values() -> None:
    A, b = np.array([[1.0, -1.0]]), np.array([0.0])  # u0 <= u1
    np.testing.assert_allclose(project_feasible(np.array([0.8, 0.2]), A, b), [0.5, 0.5], atol=1e-8)
    np.testing.assert_array_equal(project_feasible(np.array([0.2, 0.8]), A, b), [0.2, 0.8])
    # Outside the box only: clipping is the projection.
    np.testing.assert_array_equal(project_feasible(np.array([-0.5, 1.5]), A, b), [0.0, 1.0])
    np.testing.assert_array_equal(project_feasible(np.array([1.5, -1.0]), np.zeros((0, 2)), np.zeros(0)),
                                  [1.0, 0.0])


@settings(max_examples=40, deadline=None)
@given(st.lists(st.floats(-0.5, 1.5), min_size=6, max_size=6))
@example([0.0, 1e-9, 0.0, 0.0, 0.0, 1.5])  # SLSQP stopped 9e-9 outside here ("Iteration limit reached")
def test_projection_is_feasible_and_no_farther_than_any_feasible_point(v: list[float]) -> None:
    v_arr = np.array(v)
    p = project_feasible(v_arr, A_HIP, B_HIP)
    assert np.all(A_HIP @ p <= B_HIP + 1e-9) and np.all((p >= 0) & (p <= 1))
    others = hip_6d().sample_unit(64, np.random.default_rng(0))
    assert np.linalg.norm(p - v_arr) <= np.linalg.norm(others - v_arr, axis=1).min() + 1e-7


def test_regret_at_takes_the_latest_recommendation() -> None:
    trace = [[60.0, 10.0], [120.0, 4.0], [300.0, 6.0]]
    assert math.isnan(regret_at(trace, 59.0))
    assert regret_at(trace, 60.0) == 10.0 and regret_at(trace, 299.0) == 4.0 and regret_at(trace, 1e4) == 6.0


def test_summary_quantiles_by_hand_and_none_until_every_session_recommends() -> None:
    proto = HilProtocol(minutes=20.0, warmup_s=0.0, n_explore=1, max_breaths=2, grid_min=5.0)
    base = {"method": "random", "space": "hip_6d", "baseline_cost_w": 400.0, "optimum_cost_w": 300.0,
            "evaluations_per_hour": 30.0, "n_evaluations_bout2": 5, "bout2_s": 600.0, "early_stops": 0,
            "wall_s": 1.0}
    rs = [base | {"seed": 1, "trace": [[200.0, 10.0], [700.0, 2.0]], "final_regret_w": 2.0,
                  "final_regret_pct": 2.0},
          base | {"seed": 2, "trace": [[400.0, 30.0]], "final_regret_w": 30.0, "final_regret_pct": 30.0},
          base | {"seed": 3, "trace": [[100.0, 20.0]], "final_regret_w": 20.0, "final_regret_pct": 20.0}]
    (e,) = summarize_hil(rs, ["hip_6d"], ["random"], proto)
    assert e["minutes"] == [0.0, 5.0, 10.0, 15.0, 20.0]
    # minute 5 (300 s): seed 2 has no recommendation yet -> None
    assert e["regret_w_median"][:2] == [None, None]
    assert e["regret_w_median"][2:] == [20.0, 20.0, 20.0]  # median of (2, 30, 20)
    assert e["regret_w_p75"][2] == 25.0  # 75th percentile of (2, 20, 30), linear interpolation
    assert e["regret_pct_median"][2] == 20.0 and e["final_regret_w_median"] == 20.0
    assert e["n_sessions"] == 3 and e["evaluations_per_hour"] == 30.0
    assert "| hip_6d | random | 3 |" in hil_table([e], at_minutes=(10,))


def test_protocol_rejects_a_session_shorter_than_warmups_and_exploration() -> None:
    with pytest.raises(ConfigError, match="minutes=15 is too short"):
        HilProtocol(minutes=15.0)
    with pytest.raises(ConfigError, match="unknown method 'bayes'"):
        HilTask("bayes", "hip_6d", 1)
    with pytest.raises(ConfigError, match="unknown space 'knee'"):
        HilTask("cmaes", "knee", 1)


def test_adaptive_ahead_is_adaptive_with_its_own_fits() -> None:
    ahead = run_hil_task(HilTask("adaptive-ahead", "hip_ankle_4d", 2, TOY))
    plain = run_hil_task(HilTask("adaptive", "hip_ankle_4d", 2, TOY))
    assert ahead["method"] == "adaptive-ahead"
    # The same exploration bout (the design does not depend on the hyperparameters).
    assert ahead["trace"][:TOY.n_explore] == plain["trace"][:TOY.n_explore]
    assert ahead["n_evaluations"] > TOY.n_explore and ahead["early_stops"] >= 0


@pytest.mark.parametrize("space", ["hip_6d", "hip_ankle_4d"])
def test_cmaes_and_random_sessions_use_whole_conditions_within_the_session(space: str) -> None:
    for method in ("cmaes", "random"):
        r = run_hil_task(HilTask(method, space, 3, TOY))
        assert r["n_evaluations"] == 8 and r["n_evaluations_bout2"] == 4
        # Every method walks the whole session (session time is walking time): to the
        # first breath at or past its minutes; the condition that cannot end by then is not counted.
        assert TOY.minutes * 60.0 <= r["session_s"] <= TOY.minutes * 60.0 + 10.0
        assert r["walking"]["session_s"] == pytest.approx(r["session_s"])
        assert r["assisted_s"] >= 8 * TOY.condition_s
        times = [t for t, _ in r["trace"]]
        assert times == sorted(times) and all(math.isfinite(g) for _, g in r["trace"])
        # CMA-ES recommends once per complete generation; random search after every condition.
        assert len(r["trace"]) == (2 if method == "cmaes" else 8)
        assert r["baseline_cost_w"] > r["optimum_cost_w"]
        assert r["final_regret_pct"] == pytest.approx(
            100 * r["final_regret_w"] / (r["baseline_cost_w"] - r["optimum_cost_w"]))


def test_sessions_are_deterministic_per_seed() -> None:
    a = run_hil_task(HilTask("cmaes", "hip_ankle_4d", 4, TOY))
    b = run_hil_task(HilTask("cmaes", "hip_ankle_4d", 4, TOY))
    strip = lambda r: {k: v for k, v in r.items() if k != "wall_s"}  # noqa: E731
    assert strip(a) == strip(b)


@pytest.mark.slow  # two whole (toy) BO sessions through run_insim: ~5 s on a busy 2-core machine
def test_bo_sessions_run_through_insim_and_stopping_buys_evaluations() -> None:
    fixed = run_hil_task(HilTask("fixed", "hip_ankle_4d", 2, TOY))
    adaptive = run_hil_task(HilTask("adaptive", "hip_ankle_4d", 2, TOY))
    for r in (fixed, adaptive):
        assert r["session_s"] <= TOY.minutes * 60.0 + 10.0  # the last breath may overrun a little
        assert len(r["trace"]) == r["n_evaluations"] and r["n_evaluations"] > TOY.n_explore
    assert fixed["early_stops"] == 0
    assert adaptive["n_evaluations"] >= fixed["n_evaluations"]


def test_the_default_walks_the_fast_protocol_and_its_ablation_the_seeds() -> None:
    # Same subject: the default (fast protocol) proposes its first optimisation setting one
    # warm-up earlier than its ablation on the seed's protocol, and confirms its recommendation.
    fast = run_hil_task(HilTask("sound", "hip_6d", 3, TOY))
    seed = run_hil_task(HilTask("sound-seed", "hip_6d", 3, TOY))
    assert fast["t_first_proposal_s"] <= seed["t_first_proposal_s"] - TOY.warmup_s + 3.5
    assert fast["confirmed"] and not seed["confirmed"]
    for r in (fast, seed):
        assert math.isfinite(r["reported_z"])
