"""hilbo_core.studies.tutor: BKT students, the AFM threshold policy, R(π) (Antonova 2016 §4.1-4.4)."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hilbo_core.errors import ConfigError
from hilbo_core.resample import replay_halt_step
from hilbo_core.studies.tutor import (
    FIG7_STUDENTS,
    FIG9_STUDENTS,
    AFMPolicy,
    BKTParams,
    TutorProblem,
    afm_model_expected_reward,
    afm_space,
    best_count_policy,
    bkt_posterior,
    bkt_threshold_expected_reward,
    bkt_threshold_halt,
    draw_students,
    expected_reward,
    fit_afm,
    fit_then_threshold,
    p_correct,
    reward,
    run_policy,
)

BKT = BKTParams(p_know=0.18, p_learn=0.2, p_guess=0.2, p_slip=0.1)


def _enumerate_expected_reward(halt, bkt: BKTParams, t_max: int) -> float:
    """Brute force over every hidden path: initial state, learning events and answers."""
    total = 0.0
    n = t_max + 1
    for known0 in (False, True):
        p0 = bkt.p_know if known0 else 1.0 - bkt.p_know
        for learn in itertools.product((False, True), repeat=n):
            p_learn_path = p0
            known = known0
            states = []
            for k in range(n):
                states.append(known)
                if known:
                    # No forgetting and nothing left to learn: only learn[k] = False is a path.
                    p_learn_path *= 0.0 if learn[k] else 1.0
                else:
                    p_learn_path *= bkt.p_learn if learn[k] else 1.0 - bkt.p_learn
                    known = learn[k]
            if p_learn_path == 0.0:
                continue
            for answers in itertools.product((False, True), repeat=n):
                p = p_learn_path
                for s, a in zip(states, answers, strict=True):
                    q = 1.0 - bkt.p_slip if s else bkt.p_guess
                    p *= q if a else 1.0 - q
                total += p * run_policy(halt, answers, t_max)[1]
    return total


# ---- BKT --------------------------------------------------------------------------------------


def test_bkt_update_equations_by_hand() -> None:
    # Correct: 0.18·0.9 / (0.18·0.9 + 0.82·0.2) = 0.162 / 0.326, then + (1 − ·)·0.2.
    post = 0.162 / 0.326
    assert bkt_posterior(0.18, True, BKT) == pytest.approx(post + (1 - post) * 0.2, rel=1e-12)
    # Wrong: 0.18·0.1 / (0.18·0.1 + 0.82·0.8) = 0.018 / 0.674.
    post = 0.018 / 0.674
    assert bkt_posterior(0.18, False, BKT) == pytest.approx(post + (1 - post) * 0.2, rel=1e-12)
    assert p_correct(0.18, BKT) == pytest.approx(0.326)


def test_bkt_params_validated() -> None:
    with pytest.raises(ConfigError, match="p_slip"):
        BKTParams(0.1, 0.1, 0.1, 1.5)
    with pytest.raises(ConfigError, match="p_know"):
        BKTParams(float("nan"), 0.1, 0.1, 0.1)


def test_draw_students_first_answer_frequency() -> None:
    answers = draw_students(BKT, 5, 40000, np.random.default_rng(3))
    assert answers.shape == (40000, 6)
    p = 0.326
    assert abs(answers[:, 0].mean() - p) < 4 * math.sqrt(p * (1 - p) / 40000)
    # Learning only ever helps: later items are answered correctly more often.
    assert answers[:, 5].mean() > answers[:, 0].mean() + 0.2


def test_draw_students_is_seeded() -> None:
    a = draw_students(FIG9_STUDENTS, 10, 7, np.random.default_rng(5))
    b = draw_students(FIG9_STUDENTS, 10, 7, np.random.default_rng(5))
    assert np.array_equal(a, b)


# ---- reward and policies ----------------------------------------------------------------------


def test_reward_definition() -> None:
    assert reward(3, True, 20) == pytest.approx(17 / 21)
    assert reward(3, False, 20) == 0.0
    assert reward(20, True, 20) == 0.0
    assert reward(0, True, 20) == pytest.approx(20 / 21)
    with pytest.raises(ConfigError, match="n_practice"):
        reward(21, True, 20)


def test_run_policy_hand_made_student() -> None:
    answers = [False, True, False, True, True, False] + [True] * 20

    def stop_at_two_correct(h):
        return sum(h) >= 2

    t, r = run_policy(stop_at_two_correct, answers, 20)
    assert t == 4  # after [F, T, F, T]
    assert r == pytest.approx(16 / 21)  # answers[4] is correct
    t, r = run_policy(lambda h: False, answers, 3)
    assert (t, r) == (3, 0.0)  # forced stop at t_max earns nothing


def test_afm_policy_thresholds() -> None:
    pol = AFMPolicy(-1.0, 1.0, 0.6)  # σ(−1)=0.27, σ(0)=0.5, σ(1)=0.73
    assert [pol.halts_at(n) for n in range(3)] == [False, False, True]
    assert pol([True, False, True]) and not pol([True, False])
    assert AFMPolicy.from_params({"beta1": -1, "beta2": 1, "beta3": 0.6}) == pol
    with pytest.raises(ConfigError, match="beta3"):
        AFMPolicy.from_params({"beta1": 0, "beta2": 1})
    assert afm_space().names == ("beta1", "beta2", "beta3")


@pytest.mark.parametrize("bkt", [BKT, FIG9_STUDENTS, BKTParams(0.3, 0.5, 0.25, 0.2)])
@pytest.mark.parametrize("c", [0, 1, 2, None])
def test_expected_reward_matches_brute_force(bkt: BKTParams, c: int | None) -> None:
    t_max = 3
    pol = (lambda t, n: False) if c is None else (lambda t, n: n >= c)
    exact = expected_reward(pol, bkt, t_max)

    def halt(h):
        return c is not None and sum(h) >= c

    assert exact == pytest.approx(_enumerate_expected_reward(halt, bkt, t_max), abs=1e-12)


def test_expected_reward_closed_form_t_max_1() -> None:
    # Halting at once: the assessment is item 1, correct with p_correct(pk); R = 1/2.
    assert expected_reward(lambda t, n: True, BKT, 1) == pytest.approx(0.326 / 2)
    assert expected_reward(lambda t, n: False, BKT, 1) == 0.0


def test_expected_reward_agrees_with_simulation() -> None:
    pol = AFMPolicy(-1.0, 1.2, 0.6)
    answers = draw_students(FIG7_STUDENTS, 20, 20000, np.random.default_rng(1))
    mc = np.array([run_policy(pol, a, 20)[1] for a in answers])
    exact = expected_reward(pol, FIG7_STUDENTS, 20)
    assert abs(mc.mean() - exact) < 4 * mc.std() / math.sqrt(len(mc))


def test_best_count_policy_is_best() -> None:
    c, value = best_count_policy(FIG9_STUDENTS, 20)
    assert c == 2
    for k in range(21):
        assert expected_reward(lambda t, n, k=k: n >= k, FIG9_STUDENTS, 20) <= value + 1e-15


def test_bkt_threshold_expected_reward_matches_brute_force() -> None:
    for thr in (0.3, 0.6, 0.9):
        exact = bkt_threshold_expected_reward(BKT, thr, 3)
        brute = _enumerate_expected_reward(bkt_threshold_halt(BKT, thr), BKT, 3)
        assert exact == pytest.approx(brute, abs=1e-12)


# ---- model fit then threshold ----------------------------------------------------------------


def test_fit_afm_recovers_generating_parameters() -> None:
    rng = np.random.default_rng(0)
    b1, b2 = -1.0, 0.8
    seqs = []
    for _ in range(3000):
        n_c, seq = 0, []
        for _ in range(8):
            ok = bool(rng.random() < 1 / (1 + math.exp(-(b1 + b2 * n_c))))
            seq.append(ok)
            n_c += ok
        seqs.append(seq)
    f1, f2 = fit_afm(seqs)
    assert f1 == pytest.approx(b1, abs=0.08)
    assert f2 == pytest.approx(b2, abs=0.05)


def test_fit_afm_separable_data_stays_finite() -> None:
    b1, b2 = fit_afm([[True] * 5, [True] * 3])
    assert math.isfinite(b1) and math.isfinite(b2) and b1 > 1.0
    with pytest.raises(ConfigError):
        fit_afm([[], []])


def test_afm_model_expected_reward_closed_form() -> None:
    # t_max = 1, halting at once: R = σ(β1)·1/2.
    pol = AFMPolicy(0.3, 1.0, 0.0)
    expected = 1 / (1 + math.exp(-0.3)) / 2
    assert afm_model_expected_reward(pol, 0.3, 1.0, 1) == pytest.approx(expected)


def test_fit_then_threshold_picks_a_grid_threshold() -> None:
    answers = draw_students(FIG7_STUDENTS, 20, 30, np.random.default_rng(2))
    pol = fit_then_threshold(answers, 20)
    grid = (np.arange(20) + 0.5) / 20
    assert np.min(np.abs(grid - pol.beta3)) < 1e-12
    b1, b2 = fit_afm(answers)
    best = max(afm_model_expected_reward(AFMPolicy(b1, b2, t), b1, b2, 20) for t in grid)
    assert afm_model_expected_reward(pol, b1, b2, 20) == pytest.approx(best)


# ---- the BO-RESAMPLE problem ------------------------------------------------------------------


def test_tutor_problem_trajectory_and_objective() -> None:
    prob = TutorProblem(FIG7_STUDENTS, 20)
    params = {"beta1": -1.0, "beta2": 1.0, "beta3": 0.6}
    traj = prob.execute(params, np.random.default_rng(4))
    t = traj.halt_step
    assert len(traj.observations) == t + 1
    assert prob.objective(traj.observations, t, {}) == pytest.approx(
        1 - reward(t, traj.observations[t], 20))
    exact = expected_reward(AFMPolicy(-1, 1, 0.6), FIG7_STUDENTS, 20)
    assert prob.true_cost(params) == pytest.approx(1 - exact)


@settings(max_examples=60, deadline=None)
@given(answers=st.lists(st.booleans(), min_size=11, max_size=11),
       c_behaviour=st.integers(0, 10), c_new=st.integers(0, 10))
def test_off_policy_replay_equals_on_policy(answers: list[bool], c_behaviour: int, c_new: int) -> None:
    """Replaying a stored trajectory gives exactly what running the new policy would have."""
    t_max = 10
    prob = TutorProblem(BKT, t_max)

    def params(c: int) -> dict[str, float]:
        # β1 + β2 n_c > logit(0.5) = 0  ⇔  n_c > c − 0.5  ⇔  n_c >= c.
        return {"beta1": 0.5 - c, "beta2": 1.0, "beta3": 0.5}

    t_b, _ = run_policy(AFMPolicy.from_params(params(c_behaviour)), answers, t_max)
    from hilbo_core.resample import Trajectory

    stored = Trajectory(tuple(answers[: t_b + 1]), t_b)
    s = replay_halt_step(prob.halt, params(c_new), stored)
    t_new, r_new = run_policy(AFMPolicy.from_params(params(c_new)), answers, t_max)
    if t_new <= t_b:
        assert s == t_new
        assert prob.objective(stored.observations, s, {}) == pytest.approx(1 - r_new)
    else:
        assert s is None
