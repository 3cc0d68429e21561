"""The tutoring simulation of Antonova 2016 §4.1, §4.3 and §4.4: BKT students, AFM threshold policy, R(π).

An instructional policy decides, before every practice item, whether to stop teaching a skill.
When it stops after ``t`` practice items the student answers one more item, the assessment, and
the policy earns (Antonova 2016 §4.1)

    R(π) = I(o_{t+1} = correct) · (t_max − t) / (t_max + 1),

so a good policy gives enough practice for a correct assessment but no more. ``t_max`` is the
length of the curriculum: a policy that has not stopped after ``t_max`` items is stopped there
(and earns 0). Antonova 2016 does not print ``t_max``; :data:`DEFAULT_T_MAX` is our choice.

**Students** follow Bayesian Knowledge Tracing (§4.3, Corbett & Anderson 1994): a hidden state
"learned"/"not learned", learned at the start with ``p_know``; an item is answered correctly with
``1 − p_slip`` when learned and ``p_guess`` when not; after every item a not-learned student
learns with ``p_learn``; no forgetting. The assessment item is answered by the same process, so a
student is fully described by the answers it *would* give to items 1 … t_max + 1
(:func:`draw_student`), and any policy's outcome is a function of a prefix of that sequence
(:func:`run_policy`). This is the structure BO-RESAMPLE exploits (Antonova 2016 §4.2).

**Policies.** The AFM threshold policy of §4.1 predicts the next item with the additive factors
model ``p = 1 / (1 + exp(−(β1 + β2·n_c)))`` (``n_c`` = correct answers so far) and halts when
``p > β3``; its parameters are ``(β1, β2, β3)``. Students are BKT and the policy is AFM: the
deliberate model mismatch of §4.1/§4.4. Because ``p`` depends on the history only through
``n_c``, its expected reward is computed *exactly* by a dynamic programme over
``(t, n_c, learned)`` (:func:`expected_reward`), which the benchmarks use as the true value of a
recommended policy. The 5-parameter BKT threshold policy of §4.3 (halt when the BKT posterior of
"learned" exceeds a threshold) is :func:`bkt_threshold_halt`.

**Model fit, then threshold** (§4.1, Fig. 7): fit (β1, β2) by maximum likelihood
(:func:`fit_afm`), then pick β3 among 20 thresholds on [0, 1] by the policy's expected reward
*under the fitted AFM model* (:func:`afm_model_expected_reward`), i.e. plan with the model.

Everything is pure and seeded: randomness only through the ``np.random.Generator`` passed in.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.optimize import minimize
from scipy.special import expit, log_expit

from hilbo_core.errors import ConfigError, EstimatorError
from hilbo_core.resample import Trajectory
from hilbo_core.space import Parameter, ParameterSpace

__all__ = [
    "DEFAULT_T_MAX",
    "FIG7_STUDENTS",
    "FIG9_STUDENTS",
    "AFMPolicy",
    "BKTParams",
    "HaltFn",
    "TutorProblem",
    "afm_model_expected_reward",
    "afm_space",
    "best_count_policy",
    "bkt_posterior",
    "bkt_threshold_expected_reward",
    "bkt_threshold_halt",
    "draw_student",
    "draw_students",
    "expected_reward",
    "fit_afm",
    "fit_then_threshold",
    "p_correct",
    "reward",
    "run_policy",
]

DEFAULT_T_MAX = 20
"""Curriculum length t_max (practice items before a forced stop). Our choice (Antonova 2016 omits it):
with 20 items both populations of Figs. 7 and 9 have an interior optimum in the AFM class (stop
at the 2nd correct answer); with 10 the best policy is the trivial "stop at the 1st correct"."""

HaltFn = Callable[[Sequence[bool]], bool]
"""A stopping policy: answers seen so far (oldest first) → True to stop now."""

# The AFM fit's weak Gaussian prior on (β1, β2): with a handful of students the likelihood is
# often separable (e.g. every answer after the first correct one is correct) and the plain MLE
# runs off to infinity; N(0, 10²) keeps it finite while moving a well-determined fit by < 1 %.
_AFM_PRIOR_SD = 10.0
# The 20 thresholds of the fit-then-threshold baseline (Antonova 2016 §4.1: "discretizing [0, 1]
# into 20 discrete thresholds"): the midpoints of 20 equal bins.
_N_THRESHOLDS = 20


@dataclass(frozen=True)
class BKTParams:
    """Bayesian Knowledge Tracing parameters (Antonova 2016 §4.3, Fig. 8), all probabilities.

    Attributes:
        p_know: P(learned before the first item), ``pk``.
        p_learn: P(not learned → learned) after each item, ``pl``.
        p_guess: P(correct | not learned), ``pg``.
        p_slip: P(wrong | learned), ``ps``.
    """

    p_know: float
    p_learn: float
    p_guess: float
    p_slip: float

    def __post_init__(self) -> None:
        for name in ("p_know", "p_learn", "p_guess", "p_slip"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int | float) or not (
                math.isfinite(value) and 0.0 <= value <= 1.0
            ):
                raise ConfigError(f"BKTParams.{name}={value!r}; expected a probability in [0, 1]")
            object.__setattr__(self, name, float(value))

    def to_json(self) -> dict[str, float]:
        """``{"p_know": …, "p_learn": …, "p_guess": …, "p_slip": …}``."""
        return {"p_know": self.p_know, "p_learn": self.p_learn, "p_guess": self.p_guess,
                "p_slip": self.p_slip}


FIG7_STUDENTS = BKTParams(p_know=0.18, p_learn=0.2, p_guess=0.2, p_slip=0.1)
"""The simulated students of Antonova 2016 Fig. 7."""
FIG9_STUDENTS = BKTParams(p_know=0.05, p_learn=0.05, p_guess=0.05, p_slip=0.05)
"""The simulated students of Antonova 2016 Fig. 9."""


def _check_t_max(t_max: int) -> int:
    if isinstance(t_max, bool) or not isinstance(t_max, int | np.integer) or t_max < 1:
        raise ConfigError(f"t_max={t_max!r}; expected an integer >= 1 (practice items)")
    return int(t_max)


# --------------------------------------------------------------------------------------------
# BKT
# --------------------------------------------------------------------------------------------


def p_correct(p_learned: float, bkt: BKTParams) -> float:
    """P(next answer correct) = P(L)(1 − ps) + (1 − P(L)) pg (BKT)."""
    return p_learned * (1.0 - bkt.p_slip) + (1.0 - p_learned) * bkt.p_guess


def bkt_posterior(p_learned: float, correct: bool, bkt: BKTParams) -> float:
    """One BKT knowledge-tracing step: condition on an answer, then allow learning.

    P(L | correct) = P(L)(1 − ps) / [P(L)(1 − ps) + (1 − P(L)) pg],
    P(L | wrong)   = P(L) ps / [P(L) ps + (1 − P(L))(1 − pg)],
    P(L_next)      = P(L | o) + (1 − P(L | o)) pl.

    Args:
        p_learned: P(learned) before the answer, in [0, 1].
        correct: The answer.
        bkt: Model parameters.

    Returns:
        P(learned) before the next item.

    Raises:
        ConfigError: ``p_learned`` is not a probability.
        EstimatorError: The answer has probability 0 under the model (e.g. a wrong answer with
            ``p_slip = 0`` from a surely learned student).
    """
    if not (math.isfinite(p_learned) and 0.0 <= p_learned <= 1.0):
        raise ConfigError(f"p_learned={p_learned!r}; expected a probability in [0, 1]")
    if correct:
        num = p_learned * (1.0 - bkt.p_slip)
        den = num + (1.0 - p_learned) * bkt.p_guess
    else:
        num = p_learned * bkt.p_slip
        den = num + (1.0 - p_learned) * (1.0 - bkt.p_guess)
    if den <= 0.0:
        raise EstimatorError(
            f"a {'correct' if correct else 'wrong'} answer has probability 0 under {bkt} "
            f"with P(learned)={p_learned!r}"
        )
    post = num / den
    return post + (1.0 - post) * bkt.p_learn


def bkt_threshold_halt(bkt: BKTParams, threshold: float) -> HaltFn:
    """The 5-parameter BKT threshold policy of Antonova 2016 §4.3: halt when P(learned) > threshold.

    Args:
        bkt: The policy's student model (not necessarily the students' true one).
        threshold: Mastery threshold in [0, 1].

    Returns:
        A :data:`HaltFn` that traces the answers seen so far with :func:`bkt_posterior`.
    """
    if not (math.isfinite(threshold) and 0.0 <= threshold <= 1.0):
        raise ConfigError(f"threshold={threshold!r}; expected a probability in [0, 1]")

    def halt(history: Sequence[bool]) -> bool:
        p = bkt.p_know
        for o in history:
            p = bkt_posterior(p, bool(o), bkt)
        return p > threshold

    return halt


def draw_student(bkt: BKTParams, t_max: int, rng: np.random.Generator) -> np.ndarray:
    """The answers one BKT student would give to items 1 … t_max + 1 (practice, then assessment).

    Item k is answered from the state after k − 1 learning opportunities; learning happens after
    each answer (BKT's order).

    Args:
        bkt: The students' parameters.
        t_max: Curriculum length (>= 1).
        rng: Source of the student.

    Returns:
        Bool array, shape (t_max + 1,): True = correct.
    """
    return draw_students(bkt, t_max, 1, rng)[0]


def draw_students(bkt: BKTParams, t_max: int, n: int, rng: np.random.Generator) -> np.ndarray:
    """``n`` independent students at once: bool array of shape (n, t_max + 1) (see :func:`draw_student`)."""
    t_max = _check_t_max(t_max)
    if isinstance(n, bool) or not isinstance(n, int | np.integer) or n < 1:
        raise ConfigError(f"n={n!r}; expected an integer >= 1 (students)")
    # Fixed draw order (initial state, answers, learning) so a seed always gives the same class.
    known0 = rng.random(n) < bkt.p_know
    u_answer = rng.random((n, t_max + 1))
    u_learn = rng.random((n, t_max + 1))
    learned_at = np.where(u_learn < bkt.p_learn, 1, 0)
    # known before item k (0-based) = known0 or learned after one of the items 0 … k−1.
    learned_before = np.zeros((n, t_max + 1), dtype=bool)
    learned_before[:, 1:] = np.cumsum(learned_at[:, :-1], axis=1) > 0
    known = known0[:, None] | learned_before
    p = np.where(known, 1.0 - bkt.p_slip, bkt.p_guess)
    return u_answer < p


# --------------------------------------------------------------------------------------------
# Reward and policies
# --------------------------------------------------------------------------------------------


def reward(n_practice: int, assessment_correct: bool, t_max: int) -> float:
    """R(π) of Antonova 2016 §4.1: ``I(o_{t+1} = c) · (t_max − t) / (t_max + 1)``.

    Args:
        n_practice: t, the practice items given (0 … t_max).
        assessment_correct: o_{t+1} = correct.
        t_max: Curriculum length.
    """
    t_max = _check_t_max(t_max)
    if isinstance(n_practice, bool) or not 0 <= int(n_practice) <= t_max:
        raise ConfigError(f"n_practice={n_practice!r}; expected an integer in [0, {t_max}]")
    return (t_max - int(n_practice)) / (t_max + 1) if assessment_correct else 0.0


def run_policy(halt: HaltFn, answers: Sequence[bool], t_max: int) -> tuple[int, float]:
    """Teach one student: ask ``halt`` before every item; stop at ``t_max`` at the latest.

    Args:
        halt: The policy.
        answers: The student's answers to items 1 … (at least t + 1), e.g. :func:`draw_student`.
        t_max: Curriculum length.

    Returns:
        (t, R): practice items given and the reward.

    Raises:
        ConfigError: ``answers`` is too short for where the policy stops.
    """
    t_max = _check_t_max(t_max)
    seq = [bool(a) for a in answers]
    t = 0
    while t < t_max and not halt(seq[:t]):
        t += 1
    if t >= len(seq):
        raise ConfigError(f"the policy stopped after {t} items but only {len(seq)} answers were given")
    return t, reward(t, seq[t], t_max)


@dataclass(frozen=True)
class AFMPolicy:
    """The AFM threshold policy of Antonova 2016 §4.1.

    Predicts P(next correct) = σ(β1 + β2·n_c) from the number of correct answers so far and
    halts when that exceeds β3.

    Attributes:
        beta1: Intercept β1 (logit of a novice's success).
        beta2: Learning rate per correct answer β2.
        beta3: Threshold β3 on the predicted probability.
    """

    beta1: float
    beta2: float
    beta3: float

    def __post_init__(self) -> None:
        for name in ("beta1", "beta2", "beta3"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int | float | np.floating) or not (
                math.isfinite(value)
            ):
                raise ConfigError(f"AFMPolicy.{name}={value!r}; expected a finite number")
            object.__setattr__(self, name, float(value))

    @classmethod
    def from_params(cls, params: dict[str, float] | Sequence[float]) -> AFMPolicy:
        """From ``{"beta1", "beta2", "beta3"}`` or a length-3 sequence."""
        if isinstance(params, dict):
            try:
                return cls(params["beta1"], params["beta2"], params["beta3"])
            except KeyError as err:
                raise ConfigError(f"AFM policy parameters lack {err.args[0]!r}") from err
        values = list(params)
        if len(values) != 3:
            raise ConfigError(f"expected (beta1, beta2, beta3), got {values!r}")
        return cls(*values)

    def predict(self, n_correct: int) -> float:
        """σ(β1 + β2·n_c)."""
        return float(expit(self.beta1 + self.beta2 * n_correct))

    def halts_at(self, n_correct: int) -> bool:
        """The decision given n_c correct answers so far."""
        return self.predict(n_correct) > self.beta3

    def __call__(self, history: Sequence[bool]) -> bool:
        """The policy as a :data:`HaltFn`."""
        return self.halts_at(int(sum(bool(o) for o in history)))


def afm_space(beta1: tuple[float, float] = (-3.0, 3.0), beta2: tuple[float, float] = (-1.0, 3.0),
              beta3: tuple[float, float] = (0.0, 1.0)) -> ParameterSpace:
    """The policy-search space of (β1, β2, β3). Bounds are our choice (Antonova 2016 gives none)."""
    return ParameterSpace(
        [
            Parameter("beta1", *beta1, "logit", "AFM intercept"),
            Parameter("beta2", *beta2, "logit per correct answer", "AFM learning rate"),
            Parameter("beta3", *beta3, "probability", "stopping threshold"),
        ],
        name="afm_threshold",
    )


# --------------------------------------------------------------------------------------------
# Exact expectations (dynamic programmes over (t, n_c, learned))
# --------------------------------------------------------------------------------------------


def _count_halt_table(halt_count: Callable[[int, int], bool], t_max: int) -> np.ndarray:
    table = np.zeros((t_max + 1, t_max + 1), dtype=bool)
    for t in range(t_max + 1):
        for n_c in range(t + 1):
            table[t, n_c] = t == t_max or bool(halt_count(t, n_c))
    return table


def expected_reward(policy: AFMPolicy | Callable[[int, int], bool], bkt: BKTParams, t_max: int) -> float:
    """Exact E[R] of a policy that depends on the history only through (t, n_c), for BKT students.

    Forward dynamic programme over the probability mass of (n_c, learned) after t items.

    Args:
        policy: An :class:`AFMPolicy`, or ``halt(t, n_c) -> bool``.
        bkt: The students.
        t_max: Curriculum length.

    Returns:
        E[R] in [0, t_max / (t_max + 1)].
    """
    t_max = _check_t_max(t_max)
    if isinstance(policy, AFMPolicy):
        afm = policy

        def halt_count(t: int, n_c: int) -> bool:
            return afm.halts_at(n_c)
    else:
        halt_count = policy
    halt = _count_halt_table(halt_count, t_max)
    q = np.array([bkt.p_guess, 1.0 - bkt.p_slip])  # P(correct | learned = 0, 1)
    mass = np.zeros((t_max + 1, 2))  # mass[n_c, learned] after t items (n_c <= t)
    mass[0] = (1.0 - bkt.p_know, bkt.p_know)
    total = 0.0
    for t in range(t_max + 1):
        stop_rows = np.flatnonzero(halt[t, : t + 1])
        if stop_rows.size:
            total += float(np.sum(mass[stop_rows] @ q)) * (t_max - t) / (t_max + 1)
            mass[stop_rows] = 0.0
        if t == t_max:
            break
        nxt = np.zeros_like(mass)
        right = mass * q  # answered correctly
        wrong = mass * (1.0 - q)
        nxt[1:] += right[:-1]
        nxt += wrong
        # Learning after the item: not learned → learned with p_learn.
        learn = nxt[:, 0] * bkt.p_learn
        nxt[:, 0] -= learn
        nxt[:, 1] += learn
        mass = nxt
    return total


def best_count_policy(bkt: BKTParams, t_max: int) -> tuple[int | None, float]:
    """The best policy of the AFM class by brute force (Antonova 2016 §4.1's offline analysis).

    An AFM threshold policy halts as soon as n_c reaches some count c (or at the start, or
    never), so the class is exactly "stop at the c-th correct answer", c = 0 … t_max, or never.

    Returns:
        (c, E[R]) of the best such policy; c is None for "never stop before t_max".
    """
    t_max = _check_t_max(t_max)
    best: tuple[int | None, float] = (None, expected_reward(lambda t, n: False, bkt, t_max))
    for c in range(t_max + 1):
        value = expected_reward(lambda t, n, c=c: n >= c, bkt, t_max)
        if value > best[1]:
            best = (c, value)
    return best


def bkt_threshold_expected_reward(bkt: BKTParams, threshold: float, t_max: int) -> float:
    """Exact E[R] of the BKT threshold policy whose model is the students' true one.

    When the policy's BKT parameters are the students', its belief P(learned | history) is the
    true posterior, so the next answer is correct with :func:`p_correct` of it. A forward
    programme over (t, belief) — histories with the same belief merged — gives the expectation
    without sampling.

    Args:
        bkt: The students (and the policy's model).
        threshold: Halt when the belief exceeds it.
        t_max: Curriculum length.
    """
    t_max = _check_t_max(t_max)
    if not (math.isfinite(threshold) and 0.0 <= threshold <= 1.0):
        raise ConfigError(f"threshold={threshold!r}; expected a probability in [0, 1]")
    level: dict[float, float] = {bkt.p_know: 1.0}  # belief -> probability of reaching it
    total = 0.0
    for t in range(t_max + 1):
        nxt: dict[float, float] = {}
        for belief, prob in level.items():
            pc = p_correct(belief, bkt)
            if t == t_max or belief > threshold:
                total += prob * pc * (t_max - t) / (t_max + 1)
                continue
            for correct, p_obs in ((True, pc), (False, 1.0 - pc)):
                if p_obs <= 0.0:
                    continue
                b = round(bkt_posterior(belief, correct, bkt), 12)
                nxt[b] = nxt.get(b, 0.0) + prob * p_obs
        level = nxt
    return total


def afm_model_expected_reward(policy: AFMPolicy, beta1: float, beta2: float, t_max: int) -> float:
    """E[R] of ``policy`` if students answered as the AFM model (β1, β2) says (planning model).

    Item k is correct with σ(β1 + β2·n_c); dynamic programme over n_c.
    """
    t_max = _check_t_max(t_max)
    mass = np.zeros(t_max + 2)
    mass[0] = 1.0
    n = np.arange(t_max + 2)
    p = expit(beta1 + beta2 * n)
    halts = np.array([policy.halts_at(int(k)) for k in n])
    total = 0.0
    for t in range(t_max + 1):
        stop = halts.copy() if t < t_max else np.ones_like(halts)
        total += float(np.sum(mass[stop] * p[stop])) * (t_max - t) / (t_max + 1)
        mass = np.where(stop, 0.0, mass)
        if t == t_max:
            break
        nxt = mass * (1.0 - p)
        nxt[1:] += (mass * p)[:-1]
        mass = nxt
    return total


# --------------------------------------------------------------------------------------------
# Model fit, then threshold (Antonova 2016 §4.1, Fig. 7)
# --------------------------------------------------------------------------------------------


def fit_afm(answer_sequences: Sequence[Sequence[bool]]) -> tuple[float, float]:
    """Maximum-likelihood AFM parameters (β1, β2) from observed answer sequences.

    Every answer (practice and assessment) is a Bernoulli observation with
    P(correct) = σ(β1 + β2·n_c), n_c the correct answers before it in the same sequence. A weak
    N(0, 10²) prior on each β keeps separable data finite (see ``_AFM_PRIOR_SD``).

    Args:
        answer_sequences: One bool sequence per student.

    Returns:
        (β1, β2).

    Raises:
        ConfigError: No answers at all.
        EstimatorError: The optimiser did not converge to finite values.
    """
    n_c: list[np.ndarray] = []
    obs: list[np.ndarray] = []
    for seq in answer_sequences:
        a = np.asarray([bool(o) for o in seq], dtype=bool)
        if a.size == 0:
            continue
        n_c.append(np.concatenate([[0], np.cumsum(a)[:-1]]))
        obs.append(a)
    if not obs:
        raise ConfigError("fit_afm needs at least one answer")
    x = np.concatenate(n_c).astype(float)
    y = np.concatenate(obs).astype(float)

    def neg_log_post(beta: np.ndarray) -> tuple[float, np.ndarray]:
        z = beta[0] + beta[1] * x
        ll = float(np.sum(y * log_expit(z) + (1.0 - y) * log_expit(-z)))
        r = y - expit(z)
        grad = np.array([np.sum(r), np.sum(r * x)]) - beta / _AFM_PRIOR_SD**2
        return -(ll - 0.5 * float(beta @ beta) / _AFM_PRIOR_SD**2), -grad

    res = minimize(neg_log_post, np.zeros(2), jac=True, method="BFGS")
    beta = np.asarray(res.x, dtype=float)
    if not np.all(np.isfinite(beta)):
        raise EstimatorError(f"AFM fit did not converge: {res.message}")
    return float(beta[0]), float(beta[1])


def fit_then_threshold(answer_sequences: Sequence[Sequence[bool]], t_max: int,
                       n_thresholds: int = _N_THRESHOLDS) -> AFMPolicy:
    """The model-fit-then-threshold baseline of Antonova 2016 §4.1 (Fig. 7).

    Fit (β1, β2) by :func:`fit_afm`, then evaluate ``n_thresholds`` thresholds (midpoints of equal
    bins of [0, 1]) by their expected reward under the fitted model and keep the best (the first
    on ties).
    """
    t_max = _check_t_max(t_max)
    if isinstance(n_thresholds, bool) or not isinstance(n_thresholds, int) or n_thresholds < 1:
        raise ConfigError(f"n_thresholds={n_thresholds!r}; expected an integer >= 1")
    b1, b2 = fit_afm(answer_sequences)
    thresholds = (np.arange(n_thresholds) + 0.5) / n_thresholds
    values = [afm_model_expected_reward(AFMPolicy(b1, b2, b3), b1, b2, t_max) for b3 in thresholds]
    return AFMPolicy(b1, b2, float(thresholds[int(np.argmax(values))]))


# --------------------------------------------------------------------------------------------
# The tutoring problem for BO-RESAMPLE (Antonova 2016 §4.4)
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class TutorProblem:
    """The callables :func:`hilbo_core.resample.bo_resample` needs for the tutoring study.

    A real evaluation teaches one new BKT student with the AFM policy; its trajectory is the
    answers o_1 … o_{t+1} (practice and assessment) with ``halt_step = t``. The cost is
    f(π) = 1 − R(π) (Antonova 2016 Fig. 7/9: "set up optimization as loss minimization").

    Attributes:
        bkt: The students.
        t_max: Curriculum length.
    """

    bkt: BKTParams
    t_max: int = DEFAULT_T_MAX

    def __post_init__(self) -> None:
        object.__setattr__(self, "t_max", _check_t_max(self.t_max))

    def halt(self, params: Mapping[str, float], history: Sequence[Any], context: Mapping[str, Any]) -> bool:
        """AFM decision before the next item, forced at ``t_max``."""
        return len(history) >= self.t_max or AFMPolicy.from_params(dict(params))(history)

    def objective(self, observations: Sequence[Any], halt_step: int, context: Mapping[str, Any],
                  params: Mapping[str, float] | None = None) -> float:
        """1 − R for a stop after ``halt_step`` items (``observations[halt_step]`` is the assessment)."""
        return 1.0 - reward(halt_step, bool(observations[halt_step]), self.t_max)

    def execute(self, params: dict[str, float], rng: np.random.Generator) -> Trajectory:
        """Teach one new student (drawn from ``rng``) with the policy."""
        answers = draw_student(self.bkt, self.t_max, rng)
        policy = AFMPolicy.from_params(params)
        t, _ = run_policy(policy, answers, self.t_max)
        return Trajectory(tuple(bool(a) for a in answers[: t + 1]), t)

    def true_cost(self, params: Mapping[str, float]) -> float:
        """Exact 1 − E[R] of a policy over the student population (:func:`expected_reward`)."""
        return 1.0 - expected_reward(AFMPolicy.from_params(dict(params)), self.bkt, self.t_max)
