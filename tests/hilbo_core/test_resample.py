"""Tests for hilbo_core.resample: BO-RESAMPLE (Antonova 2016 §4.2, Algorithm 1)."""

from __future__ import annotations

import numpy as np
import pytest

from hilbo_core.errors import ConfigError, MeasurementError
from hilbo_core.resample import (
    ResampleConfig,
    Trajectory,
    TrajectoryStore,
    bo_resample,
    replay_halt_step,
    simulate_policy_exec,
)
from hilbo_core.studies.tutor import FIG9_STUDENTS, TutorProblem, afm_space


def _count_halt(params, history, context) -> bool:
    """Stop once ``c`` successes were seen (or at the end of the horizon)."""
    return sum(history) >= params["c"] or len(history) >= context.get("horizon", 99)


def _objective(obs, s, context, params) -> float:
    return float(s) - 10.0 * float(obs[s])


def test_trajectory_validation() -> None:
    with pytest.raises(ConfigError, match="halt_step"):
        Trajectory((True, False), 3)
    with pytest.raises(ConfigError, match="halt_step"):
        Trajectory((True,), -1)
    t = Trajectory([1, 0], 1, {"a": 1})
    assert t.observations == (1, 0)
    with pytest.raises(TypeError):
        t.context["a"] = 2  # read-only


def test_replay_halt_step_hand_made() -> None:
    traj = Trajectory((False, True, True, False, True), 4)
    assert replay_halt_step(_count_halt, {"c": 0}, traj) == 0
    assert replay_halt_step(_count_halt, {"c": 1}, traj) == 2  # after [F, T]
    assert replay_halt_step(_count_halt, {"c": 2}, traj) == 3  # after [F, T, T]
    assert replay_halt_step(_count_halt, {"c": 3}, traj) is None  # would need a 4th step's data
    assert simulate_policy_exec(_count_halt, _objective, {"c": 1}, traj) == (2, 2.0 - 10.0)
    assert simulate_policy_exec(_count_halt, _objective, {"c": 3}, traj) is None


def test_store_select_limited_respects_reuse_and_feasibility() -> None:
    store = TrajectoryStore(max_reuse=2)
    short = store.add(Trajectory((True, True), 1))  # can only evaluate policies stopping at <= 1
    long = store.add(Trajectory((False, False, False, True, True), 4))
    rng = np.random.default_rng(0)
    # c = 3 needs three successes within a stored prefix; neither trajectory has them.
    assert store.select_limited(_count_halt, {"c": 3}, rng) is None
    assert store.all_uses == (0, 0)
    # c = 1: "short" halts at 1, "long" at 4. Four picks, at most 2 each, then nothing.
    picks = [store.select_limited(_count_halt, {"c": 1}, rng) for _ in range(5)]
    assert picks[4] is None
    assert sorted(p[0] for p in picks[:4]) == [short, short, long, long]
    assert {p for p in picks[:4]} == {(short, 1), (long, 4)}
    assert store.all_uses == (2, 2)
    assert store.available() == []


def test_store_validation() -> None:
    with pytest.raises(ConfigError, match="max_reuse"):
        TrajectoryStore(-1)
    with pytest.raises(ConfigError, match="Trajectory"):
        TrajectoryStore(1).add(("not", "a", "trajectory"))  # type: ignore[arg-type]


def _tutor_run(k: int, reuse: int, n_real: int, seed: int):
    prob = TutorProblem(FIG9_STUDENTS, 10)
    cfg = ResampleConfig(n_resamples=k, max_reuse=reuse, n_candidates=64, n_local=0)
    return bo_resample(afm_space(), prob.execute, prob.halt, prob.objective, n_real=n_real,
                       rng=np.random.default_rng(seed), config=cfg)


def test_bo_resample_counts_are_bounded() -> None:
    run = _tutor_run(k=3, reuse=2, n_real=6, seed=1)
    assert run.n_real == 6
    assert len(run.recommendations) == 6
    assert run.n_simulated <= 3 * 6  # at most K per real evaluation
    assert max(run.trajectory_uses) <= 2  # each trajectory reused a bounded number of times
    assert run.n_simulated == sum(run.trajectory_uses)
    per_round = np.bincount([e.n_real for e in run.evaluations if e.simulated], minlength=7)
    assert per_round.max() <= 3
    assert run.n_simulated > 0
    for e in run.evaluations:
        assert 0.0 <= e.cost <= 1.0
        assert e.trajectory < 6


def test_plain_bo_has_no_resamples_and_is_deterministic() -> None:
    a = _tutor_run(k=0, reuse=10, n_real=5, seed=3)
    b = _tutor_run(k=0, reuse=10, n_real=5, seed=3)
    assert a.n_simulated == 0 and a.trajectory_uses == (0,) * 5
    assert [e.params for e in a.evaluations] == [e.params for e in b.evaluations]
    assert a.recommendations == b.recommendations


def test_resampled_costs_are_replays_of_stored_trajectories() -> None:
    store: list[Trajectory] = []
    prob = TutorProblem(FIG9_STUDENTS, 10)

    def execute(params, rng):
        traj = prob.execute(params, rng)
        store.append(traj)
        return traj

    run = bo_resample(afm_space(), execute, prob.halt, prob.objective, n_real=4,
                      rng=np.random.default_rng(7),
                      config=ResampleConfig(n_resamples=4, max_reuse=3, n_candidates=64, n_local=0))
    for e in run.evaluations:
        traj = store[e.trajectory]
        if e.simulated:
            assert replay_halt_step(prob.halt, e.params, traj) == e.halt_step
        else:
            assert e.halt_step == traj.halt_step
        assert e.cost == pytest.approx(prob.objective(traj.observations, e.halt_step, {}))


def test_prior_trajectories_can_be_resampled_from_the_start() -> None:
    prob = TutorProblem(FIG9_STUDENTS, 10)
    full = Trajectory(tuple([False] * 10 + [True]), 10)  # a full curriculum evaluates any policy
    run = bo_resample(afm_space(), prob.execute, prob.halt, prob.objective, n_real=1,
                      rng=np.random.default_rng(0), prior_trajectories=[full],
                      config=ResampleConfig(n_resamples=5, max_reuse=5, n_init=1,
                                            n_candidates=64, n_local=0))
    assert run.trajectory_uses[0] >= 1


def test_bad_arguments() -> None:
    prob = TutorProblem(FIG9_STUDENTS, 10)
    with pytest.raises(ConfigError, match="n_real"):
        bo_resample(afm_space(), prob.execute, prob.halt, prob.objective, n_real=0,
                    rng=np.random.default_rng(0))
    with pytest.raises(ConfigError, match="n_resamples"):
        ResampleConfig(n_resamples=-1)
    with pytest.raises(ConfigError, match="Trajectory"):
        bo_resample(afm_space(), lambda p, r: [True], prob.halt, prob.objective, n_real=1,
                    rng=np.random.default_rng(0))
    with pytest.raises(MeasurementError, match="finite"):
        bo_resample(afm_space(), prob.execute, prob.halt, lambda o, s, c, p: float("nan"), n_real=1,
                    rng=np.random.default_rng(0))
