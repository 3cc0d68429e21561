"""``hilbo bench hil``: whole simulated HIL sessions on simulated wearers, four methods.

Every session is one subject (a simulated wearer's seed: the realistic wearer of
:class:`~bridge.sim.devices.RealisticWearerConfig` by default, the legacy
:class:`~bridge.sim.devices.SimulatedWearer` with ``wearer="legacy"``, :attr:`HilProtocol.wearer`) walking a
session of ``minutes`` on the wearer's breath clock (default 60, like Kim et al. 2019's protocol,
§IV.A.3): a 3-minute unassisted warm-up, a first bout, a second 3-minute warm-up and a second
bout until the session ends. The methods:

* ``sound`` — BO with the default sound stopping rule and recommendation.
* ``adaptive`` / ``fixed`` — Bayesian optimisation with / without the estimator stopping process,
  exactly as ``hilbo sim`` runs it (:func:`bridge.sim.core.run_insim`): bout 1 is the exploration
  (6 points × N = 45 breaths, ≈ 14 min), bout 2 the optimisation until the session ends (≈ 40
  min). The recommendation after every evaluation is :meth:`HILOptimizer.best`.
* ``cmaes`` — CMA-ES as HIL studies run it (the ``cma`` package): generations of 8 conditions of
  2 minutes each, every condition's cost the UKF estimate (Kim et al. 2019 §II.C) from that condition's
  breaths; bout 1 is the first generation. CMA-ES searches the unit cube (``bounds=[0, 1]``, cma's
  own boundary transformation); the linear constraints (e.g. ``t_on <= t_p − 15``) are handled
  by *projection with a penalty*: an infeasible sample is walked as its Euclidean projection onto
  the feasible polytope (so the wearer only ever gets a feasible setting), and CMA-ES is told the
  measured cost plus ``penalty_w · ||x − proj(x)||²`` (unit-cube distance), which pulls the
  distribution back into the feasible set without discarding the measurement. Its recommendation
  is the distribution mean (projected), updated after every complete generation; a generation
  cut short by the end of the session does not count.
* ``adaptive-ahead`` — ``adaptive`` with the GP hyperparameters fitted *ahead*, as ``hilbo run``
  and ``hilbo sim`` do by default (``[protocol] refit = "ahead"``): on the completed evaluations
  while the next setting is measured, so every proposal uses hyperparameters one evaluation old
  (``HILOptimizer`` with ``refit_lag`` 1). Not run by default; paired with ``adaptive``, it
  measures what that costs.
* ``random`` — uniform random feasible settings (rejection sampling), 2-minute conditions, the
  same UKF estimate; recommendation: the lowest estimate so far. Bout 1 is its first 8 conditions.

The Antonova 2016 methods (:data:`THESIS_METHODS`, not run by default) are BO sessions of
:func:`bridge.bench.thesis_session.run_session` — the same protocol and recommendation as
``adaptive``, with one thing changed:

* ``adaptive-day2`` — a second "day" of the same wearer (a fresh breath-noise stream and
  optimizer seed) without a prior: the control of the two prior methods.
* ``adaptive-prior`` — day 2 with the day-1 session's evaluations (the ``adaptive`` session of
  the same subject, run again inside the task) as fast-prior observations
  (:func:`hilbo_core.priors.priors_from_evaluations`, ``previous_session`` inflation:
  var = 2·σ² + (10 W)²), Antonova 2016 §3.3. ``adaptive-prior-e3``: the same with an exploration bout
  of 3 points instead of E.
* ``adaptive-features`` — the GP's kernel over [raw parameters, profile features]
  (:class:`hilbo_core.features.ProfileFeatureMap` via :func:`~hilbo_core.features.with_raw`),
  Antonova 2016 §3.4.2; ``adaptive-features-only`` over the profile features alone. 15–30× slower
  per session (finite-difference EI refinement).
* ``adaptive-tuned-k`` — the σ-scaled rule with a constant threshold K (A_i = K) instead of
  Algorithm 2's schedule; K is given (:attr:`HilTask.stopping_k`), e.g. tuned offline by
  BO-RESAMPLE on other wearers' full-length trajectories (:func:`tune_constant_k`, what
  ``hilbo bench hil --tuned-k bo`` does before the sessions).

The simulated wearer's landscape is the same on both days, so the prior methods measure a best
case for a previous session's prior.

The metric is the *true* (noiseless) steady-state cost of the recommended setting minus the
subject's true optimum (W, and % of the optimum's reduction from unassisted walking), on a grid
of minutes walked (session clock, warm-ups included, so every method walks the same time). A
grid point is ``None`` until every session of that method has made a recommendation.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import cma
import numpy as np
from scipy.optimize import linprog, minimize

from bridge.bench.common import blas_threads, markdown_table, round_sig
from bridge.bench.methods import DEFAULT_HIL_METHODS, HIL_METHODS, PRIOR_METHODS, THESIS_METHODS
from bridge.bench.thesis_session import Arm, run_session
from bridge.sim.core import SimConfig, SimEvaluation, run_insim
from bridge.sim.devices import RealisticWearerConfig, WearerConfig, WearerKind, make_wearer, wearer_kind
from hilbo_core.errors import ConfigError, InfeasibleError
from hilbo_core.metabolic import MetabolicUKF
from hilbo_core.optimizer import HILOptimizer, OptimizerConfig
from hilbo_core.presets import PRESETS, preset
from hilbo_core.priors import priors_from_evaluations
from hilbo_core.protocol import (
    ActionKind,
    ProtocolKind,
    SessionPhase,
    SessionProtocol,
    SessionProtocolConfig,
    protocol_preset,
)
from hilbo_core.space import ParameterSpace

__all__ = [
    "ABLATION_METHODS",
    "DEFAULT_HIL_METHODS",
    "HIL_METHODS",
    "PRIOR_METHODS",
    "THESIS_METHODS",
    "HilProtocol",
    "HilTask",
    "check_methods_for_wearer",
    "hil_comparisons",
    "hil_table",
    "load_sessions",
    "project_feasible",
    "run_hil_task",
    "run_training_session",
    "summarize_hil",
    "tune_constant_k",
]

_PRIOR_E3 = 3  # exploration points of adaptive-prior-e3 (docs/results_thesis.md §2)
_BO_METHODS = ("sound", "adaptive", "fixed")
# How each BO method runs in run_insim: (stopping rule, walking protocol, optimizer options,
# protocol options). The seed's rules keep the seed's protocol (Kim et al. 2019 §IV.A.3); the
# default "sound" runs hilbo's default (the fast protocol). The "sound-..." methods are the
# ablations of the default (not run by default), each one change away from its neighbour:
_BO_VARIANTS: dict[str, tuple[str, str, tuple[tuple[str, Any], ...], tuple[tuple[str, Any], ...]]] = {
    "sound": ("sound", "fast", (), ()),
    "adaptive": ("adaptive", "seed", (), ()),
    "fixed": ("fixed", "seed", (), ()),
    "adaptive-ahead": ("adaptive", "seed", (), ()),
    # the default before the fast protocol: the seed's protocol, the best measured setting
    "sound-seed": ("sound", "seed", (("recommend", "posterior"),), ()),
    # + the recommendation over the whole feasible set
    "sound-seed-global": ("sound", "seed", (), ()),
    # + its confirmation in the last 4 minutes
    "sound-seed-confirm": ("sound", "seed", (), (("confirm_s", 240.0),)),
    # the fast protocol without the confirmation
    "sound-fast-noconfirm": ("sound", "fast", (), (("confirm_s", None),)),
    # the fast protocol's other candidates: 6 or 4 exploration settings of N breaths; 6 ended
    # once their SD is 4 % of the estimate; 6 with EI against the lowest posterior mean
    "sound-e6": ("sound", "fast", (("n_explore", 6),), (("n_explore", 6),)),
    "sound-e4": ("sound", "fast", (("n_explore", 4),), (("n_explore", 4),)),
    "sound-explore-sd": ("sound", "fast", (("n_explore", 6), ("explore_rel_sd", 0.04)),
                         (("n_explore", 6),)),
    "sound-nei": ("sound", "fast", (("n_explore", 6), ("ei_best", "posterior")), (("n_explore", 6),)),
    # the default before the sequential boundaries: no decision before a fixed 60 s, accept at 3 σ
    "sound-floor": ("sound-floor", "fast", (("accept_z", 3.0),), ()),
    # EI's candidates in a box of half-width 0.25 / 0.4 (unit cube) around the incumbent
    "sound-tr25": ("sound", "fast", (("trust_region", 0.25),), ()),
    "sound-tr40": ("sound", "fast", (("trust_region", 0.4),), ()),
    # the same box for every other proposal, the whole feasible set for the others
    "sound-tr40-alt": ("sound", "fast", (("trust_region", 0.4), ("trust_region_alternate", True)), ()),
    # the estimator's model error correlated in time (the drift shared by nearby settings)
    "sound-drift": ("sound", "fast", (("drift_corr_s", 180.0),), ()),
    # the knowledge gradient in place of EI
    "sound-kg": ("sound", "fast", (("acquisition", "kg"),), ()),
    "sound-kg-global": ("sound", "fast", (("acquisition", "kg-global"),), ()),
    # EI for the first half of the hour, then the knowledge gradient
    "sound-ei-kg": ("sound", "fast", (("acquisition", "ei-then-kg"),), ()),
    # the default before the pessimistic prior mean: the GP's mean at the observations' average
    "sound-mean0": ("sound", "fast", (("prior_mean_sd", 0.0),), ()),
    # The GP's predictive as the plain product in the stop decision (before the cap).
    "sound-prior-full": ("sound", "fast", (("gp_prior_max_share", 1.0),), ()),
}
ABLATION_METHODS: tuple[str, ...] = tuple(m for m in _BO_VARIANTS if m.startswith("sound-"))
"""The default's ablations (``--methods sound-seed,...``)."""
_CMA_STREAM = 0xC3A
_RANDOM_STREAM = 0x5A3D


@dataclass(frozen=True)
class HilProtocol:
    """The session protocol shared by every method.

    Attributes:
        minutes: Session length on the breath clock, warm-ups included.
        warmup_s: Each of the two unassisted warm-ups (s).
        n_explore: BO exploration points (bout 1); None (default): each method's protocol's
            (``sound``: the fast protocol's 3; the seed's rules and the Antonova 2016 methods: 6,
            :attr:`explore_points`).
        max_breaths: BO's N.
        window: Algorithm 2's W.
        condition_s: CMA-ES and random-search condition length (s).
        popsize: CMA-ES generation size (conditions per generation).
        sigma0: CMA-ES initial step size in the unit cube.
        penalty_w: CMA-ES constraint penalty in W per squared unit-cube distance.
        bout1_conditions: CMA-ES / random-search conditions before the second warm-up.
        grid_min: Spacing of the minutes grid of the summary.
        wearer: The simulated wearer (:class:`bridge.sim.devices.WearerKind` value): ``realistic``
            (default) or ``legacy``. Regret is scored on the same kind's unadapted landscape
            (:class:`bridge.sim.devices.RealisticWearerConfig`, "Truth and regret").
    """

    minutes: float = 60.0
    warmup_s: float = SessionProtocolConfig.warmup_s
    n_explore: int | None = None
    max_breaths: int = OptimizerConfig.max_breaths
    window: int = OptimizerConfig.window
    condition_s: float = 120.0
    popsize: int = 8
    sigma0: float = 0.25
    penalty_w: float = 500.0
    bout1_conditions: int = 8
    grid_min: float = 1.0
    wearer: str = WearerKind.REALISTIC.value

    def __post_init__(self) -> None:
        wearer_kind(self.wearer)  # raises ConfigError naming the value and the choices
        for name, low in (("n_explore", 1), ("max_breaths", 2), ("window", 0), ("popsize", 2),
                          ("bout1_conditions", 0)):
            v = getattr(self, name)
            if name == "n_explore" and v is None:
                continue
            if isinstance(v, bool) or not isinstance(v, int) or v < low:
                raise ConfigError(f"{name}={v!r}; expected an integer >= {low}")
        for name in ("minutes", "condition_s", "sigma0", "grid_min"):
            v = getattr(self, name)
            if not (isinstance(v, int | float) and math.isfinite(v) and v > 0):
                raise ConfigError(f"{name}={v!r}; expected a positive number")
        for name in ("warmup_s", "penalty_w"):
            v = getattr(self, name)
            if not (isinstance(v, int | float) and math.isfinite(v) and v >= 0):
                raise ConfigError(f"{name}={v!r}; expected a number >= 0")
        if self.minutes > 600:
            raise ConfigError(f"minutes={self.minutes!r}; expected at most 600")
        session_s = self.minutes * 60.0
        # The exploration bout at the slowest mean breathing of the wearer population.
        slowest_s = (WearerConfig().breath_interval_s[1] if self.wearer == WearerKind.LEGACY.value
                     else RealisticWearerConfig().breath_interval_s[1])
        explore_s = self.explore_points * self.max_breaths * slowest_s
        if 2 * self.warmup_s + explore_s >= session_s:
            raise ConfigError(
                f"minutes={self.minutes:g} is too short: the warm-ups ({2 * self.warmup_s / 60:g} min) "
                f"and the BO exploration ({self.explore_points} × {self.max_breaths} breaths, up to "
                f"{explore_s / 60:.1f} min) leave no optimisation time; give minutes > "
                f"{math.ceil((2 * self.warmup_s + explore_s) / 60)}"
            )
        if 2 * self.warmup_s + (self.bout1_conditions + 1) * self.condition_s > session_s:
            raise ConfigError(
                f"minutes={self.minutes:g} is too short for the warm-ups and "
                f"{self.bout1_conditions + 1} conditions of {self.condition_s:g} s"
            )

    @property
    def explore_points(self) -> int:
        """``n_explore``, else the seed protocol's (the most any method explores)."""
        if self.n_explore is not None:
            return self.n_explore
        return int(protocol_preset(ProtocolKind.SEED)[1]["n_explore"])

    def to_json(self) -> dict[str, Any]:
        """JSON-able form."""
        return asdict(self)


@dataclass(frozen=True)
class HilTask:
    """One session: a method on one subject in one space (picklable).

    Attributes:
        method: One of :data:`HIL_METHODS`.
        space: A preset name.
        seed: The subject (simulated wearer) seed.
        protocol: The session protocol.
        stopping_k: The constant K (in σ, >= 0) of ``adaptive-tuned-k``; None for every other method.
    """

    method: str
    space: str
    seed: int
    protocol: HilProtocol = field(default_factory=HilProtocol)
    stopping_k: float | None = None

    def key(self) -> tuple[str, str, int]:
        """Identity of the session within a run."""
        return (self.method, self.space, self.seed)

    def __post_init__(self) -> None:
        if self.method not in HIL_METHODS:
            raise ConfigError(f"unknown method {self.method!r}; choose from {list(HIL_METHODS)}")
        if self.space not in PRESETS:
            raise ConfigError(f"unknown space {self.space!r}; choose from {sorted(PRESETS)}")
        if isinstance(self.seed, bool) or not isinstance(self.seed, int) or self.seed < 0:
            raise ConfigError(f"seed={self.seed!r}; expected an integer >= 0")
        if self.method == "adaptive-tuned-k":
            k = self.stopping_k
            if isinstance(k, bool) or not isinstance(k, int | float) or not (math.isfinite(k) and k >= 0):
                raise ConfigError(f"adaptive-tuned-k needs stopping_k = a constant K >= 0 (in σ), got {k!r}")
        elif self.stopping_k is not None:
            raise ConfigError(f"stopping_k={self.stopping_k!r} is only for adaptive-tuned-k, "
                              f"not {self.method!r}")
        check_methods_for_wearer([self.method], self.protocol.wearer)


def check_methods_for_wearer(methods: Iterable[str], wearer: str) -> None:
    """Refuse the Antonova 2016 methods on any wearer but the legacy one.

    :func:`bridge.bench.thesis_session.run_session` builds the legacy wearer itself; scoring its sessions
    on another wearer's landscape would be meaningless.

    Raises:
        ConfigError: A method of :data:`THESIS_METHODS` with ``wearer`` other than ``legacy``.
    """
    bad = [m for m in methods if m in THESIS_METHODS]
    if bad and wearer != WearerKind.LEGACY.value:
        raise ConfigError(f"method(s) {', '.join(bad)} run on the legacy wearer only "
                          f"(bridge/bench/thesis_session.py), not wearer={wearer!r}; use --wearer legacy")


# --------------------------------------------------------------------------------------------
# Constraint handling for CMA-ES
# --------------------------------------------------------------------------------------------


def project_feasible(v: np.ndarray, A: np.ndarray, b: np.ndarray, tol: float = 1e-9) -> np.ndarray:
    """Euclidean projection of v onto ``P = {u : A u <= b, 0 <= u <= 1}``.

    Args:
        v: Point, shape (d,).
        A: Constraint matrix, shape (m, d) (m may be 0).
        b: Right-hand sides, shape (m,).
        tol: Constraint tolerance of the result.

    Returns:
        The nearest point of P, shape (d,).

    Raises:
        InfeasibleError: The solver returned a point outside P (it should not for a non-empty P).
    """
    v = np.asarray(v, dtype=float)
    u = np.clip(v, 0.0, 1.0)
    # The box projection is the answer whenever it already satisfies A u <= b (P ⊂ box).
    if len(b) == 0 or np.all(A @ u <= b + tol):
        return u
    res = minimize(lambda w: 0.5 * float(np.sum((w - v) ** 2)), u, jac=lambda w: w - v,
                   method="SLSQP", bounds=[(0.0, 1.0)] * len(u),
                   constraints=[{"type": "ineq", "fun": lambda w: b - A @ w, "jac": lambda w: -A}],
                   options={"ftol": 1e-14, "maxiter": 200})
    w = np.clip(res.x, 0.0, 1.0)
    if np.any(A @ w > b + tol):
        # SLSQP can stop a hair outside P at a degenerate vertex (seen: 9e-9 over a row of norm
        # 35 after "Iteration limit reached"). Step towards a strictly interior point just far
        # enough to satisfy every row: the distance grows by the violation only.
        w = _pull_inside(w, A, b)
    if np.any(A @ w > b + tol):
        raise InfeasibleError(f"projection of {v.tolist()} failed: {res.message}")
    return w


def _pull_inside(w: np.ndarray, A: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The point of the segment from w to P's Chebyshev centre c nearest w that satisfies A u <= b."""
    d = A.shape[1]
    norms = np.linalg.norm(A, axis=1)
    # max s  s.t.  A u + s·|a_i| <= b,  s <= u <= 1 - s  (the centre of the largest inscribed ball)
    A_ub = np.vstack([np.hstack([A, norms[:, None]]),
                      np.hstack([-np.eye(d), np.ones((d, 1))]),
                      np.hstack([np.eye(d), np.ones((d, 1))])])
    b_ub = np.concatenate([b, np.zeros(d), np.ones(d)])
    cost = np.zeros(d + 1)
    cost[-1] = -1.0
    lp = linprog(cost, A_ub=A_ub, b_ub=b_ub, bounds=[(None, None)] * d + [(0.0, 1.0)], method="highs")
    if not lp.success or lp.x[-1] <= 0:
        return w
    c = lp.x[:d]
    over = A @ w - b
    gap = A @ w - A @ c  # > 0 wherever w violates (A c < b there)
    t = float(np.max(np.where(over > 0, over / np.maximum(gap, 1e-300), 0.0)))
    return w + min(1.0, t * (1 + 1e-6) + 1e-15) * (c - w)


# --------------------------------------------------------------------------------------------
# Sessions
# --------------------------------------------------------------------------------------------


class _Session:
    """Fixed-length conditions on a simulated wearer (CMA-ES, random search).

    The walking protocol is every method's (:class:`~hilbo_core.protocol.SessionProtocol`): a
    warm-up, bout 1 of ``bout1_conditions`` conditions, a second warm-up, bout 2 until the
    minutes are walked (within one breath). A condition that cannot end by then is walked but not
    counted (:meth:`condition` returns None): a generation cut short does not update CMA-ES, and
    random search recommends from complete conditions only.
    """

    def __init__(self, space: ParameterSpace, seed: int, proto: HilProtocol) -> None:
        self.space = space
        self.wearer = make_wearer(proto.wearer, space, seed=seed)
        self.proto = proto
        self.protocol = SessionProtocol(SessionProtocolConfig(
            warmup_s=proto.warmup_s, n_explore=proto.bout1_conditions, session_s=proto.minutes * 60.0,
            budget_s=None, pause_between_bouts=False), t_start_s=self.wearer.t_s)
        self._act = self.protocol.start()
        self.n_conditions = 0
        self.assisted_s = 0.0
        self.bout2_conditions = 0
        self.bout2_start_s = math.nan
        self.last_end_s = math.nan

    def has_time(self) -> bool:
        """The session has not ended: another condition starts."""
        return not self.protocol.ended

    def condition(self, params: Mapping[str, float]) -> tuple[float, float] | None:
        """Walk one condition; returns (UKF mean of the steady-state cost in W, end time in s), or
        None when the session ends first (it has then walked to its end)."""
        w, p, cond_s = self.wearer, self.protocol, self.proto.condition_s
        act = self._act
        while act.kind is not ActionKind.PROPOSE:  # the warm-ups (drive() without an optimizer)
            if act.kind is ActionKind.END:
                return None
            if act.kind is ActionKind.WARM_UP and act.starts:
                w.apply_profiles((), w.t_s)
            act = p.on_breath(w.next_breath().t_s)
        t0 = w.t_s
        w.apply_params(params, t0)
        p.on_setting_applied(t0)
        t_end = p.t_end_s
        fits = t_end is None or t0 + cond_s <= t_end
        ukf = MetabolicUKF()
        while True:
            breath = w.next_breath()
            act = p.on_breath(breath.t_s)
            t = act.t_setting_s if act.t_setting_s is not None else breath.t_s - t0
            ukf.update(t, breath.watts)
            if act.final or (fits and t >= cond_s):
                break
        if not (fits and t >= cond_s):
            self._act = p.on_setting_dropped()
            return None
        if p.phase is SessionPhase.OPTIMIZATION:
            self.bout2_conditions += 1
            if self.bout2_conditions == 1:
                self.bout2_start_s = t0
        self._act = p.on_evaluation_done()
        self.n_conditions += 1
        self.assisted_s += breath.t_s - t0
        self.last_end_s = breath.t_s
        return ukf.mean, breath.t_s


def _run_bo(task: HilTask) -> dict[str, Any]:
    proto = task.protocol
    trace: list[tuple[float, dict[str, float]]] = []

    def on_eval(rec: SimEvaluation, opt: HILOptimizer) -> None:
        trace.append((rec.t_end, opt.best()[0]))

    stopping, protocol, options, protocol_options = _BO_VARIANTS[task.method]
    summary = run_insim(
        SimConfig(minutes=proto.minutes, seed=task.seed, preset=task.space, n_explore=proto.n_explore,
                  max_breaths=proto.max_breaths, window=proto.window, warmup_s=proto.warmup_s,
                  stopping=stopping, refit="ahead" if task.method == "adaptive-ahead" else "at_proposal",
                  wearer=proto.wearer, protocol=protocol, options=options,
                  protocol_options=protocol_options),
        on_evaluation=on_eval,
    )
    evals = summary["evaluations"]
    opt_evals = [e for e in evals if e["phase"] == "optimization"]
    bout2_start = opt_evals[0]["t_start"] if opt_evals else math.nan
    return {
        "trace": trace,
        "n_evaluations": summary["n_evaluations"],
        "n_evaluations_bout2": len(opt_evals),
        "early_stops": summary["n_early_stops"],
        "assisted_s": sum(e["t_end"] - e["t_start"] for e in evals),
        "bout2_s": (evals[-1]["t_end"] - bout2_start) if opt_evals else 0.0,
        "session_s": summary["session_minutes"] * 60.0,
        "t_first_proposal_s": summary["t_first_proposal_s"],
        # The final recommendation's reported estimate against its true cost at the end, in its
        # reported SDs (the confirmation's own measurement when there is one).
        "reported_z": (summary["best_mean"] - summary["true_cost_of_best_at_end"])
        / math.sqrt(summary["best_var"]),
        "confirmed": bool(summary["confirmation"] and summary["confirmation"]["n_evaluations"]),
    }


def _run_cmaes(task: HilTask) -> dict[str, Any]:
    proto = task.protocol
    space = preset(task.space)
    session = _Session(space, task.seed, proto)
    A, b = space.unit_constraints()
    rng = np.random.default_rng([task.seed, _CMA_STREAM])
    x0 = space.sample_unit(256, rng).mean(axis=0)  # centre of the (convex) feasible set
    es = cma.CMAEvolutionStrategy(x0, proto.sigma0, {
        "popsize": proto.popsize, "bounds": [0.0, 1.0],
        # Our own generator instead of numpy's global one: the run depends on the task alone.
        "seed": math.nan, "randn": lambda lam, n: rng.standard_normal((lam, n)),
        "verbose": -9, "verb_log": 0, "verb_disp": 0, "tolfun": 0.0, "tolx": 0.0,
        "tolfunhist": 0.0, "tolstagnation": 10**9, "tolflatfitness": 10**9,
    })
    trace: list[tuple[float, dict[str, float]]] = []
    t_end = 0.0
    while session.has_time():
        X = es.ask()
        fitness = []
        for x in X:
            xf = project_feasible(np.asarray(x), A, b)
            done = session.condition(space.to_dict(space.from_unit(xf)))
            if done is None:
                break
            cost, t_end = done
            fitness.append(cost + proto.penalty_w * float(np.sum((np.asarray(x) - xf) ** 2)))
        if len(fitness) < len(X):
            break  # the session ended mid-generation: CMA-ES cannot update on a part
        es.tell(X, fitness)
        mean = project_feasible(np.asarray(es.result.xfavorite), A, b)
        trace.append((t_end, space.to_dict(space.from_unit(mean))))
    return _fixed_condition_result(session, trace)


def _run_random(task: HilTask) -> dict[str, Any]:
    proto = task.protocol
    space = preset(task.space)
    session = _Session(space, task.seed, proto)
    A, b = space.unit_constraints()
    rng = np.random.default_rng([task.seed, _RANDOM_STREAM])
    trace: list[tuple[float, dict[str, float]]] = []
    best = math.inf
    while session.has_time():
        while True:  # uniform on the feasible set by rejection
            u = rng.uniform(size=space.dim)
            if len(b) == 0 or np.all(A @ u <= b):
                break
        params = space.to_dict(space.from_unit(u))
        done = session.condition(params)
        if done is None:
            break
        cost, t_end = done
        if cost < best:
            best = cost
            trace.append((t_end, params))
        else:
            trace.append((t_end, trace[-1][1]))
    return _fixed_condition_result(session, trace)


def _thesis_arm(task: HilTask) -> Arm:
    proto, m = task.protocol, task.method
    base = {"n_explore": proto.explore_points, "window": proto.window}
    return {
        "adaptive-day2": lambda: Arm(m, day=2, **base),
        "adaptive-prior": lambda: Arm(m, day=2, prior=True, **base),
        "adaptive-prior-e3": lambda: Arm(m, day=2, prior=True, **(base | {"n_explore": _PRIOR_E3})),
        "adaptive-features": lambda: Arm(m, feature="profile+raw", **base),
        "adaptive-features-only": lambda: Arm(m, feature="profile", **base),
        "adaptive-tuned-k": lambda: Arm(m, stopping_k=task.stopping_k, **base),
    }[m]()


def _session_kwargs(task: HilTask) -> dict[str, Any]:
    proto = task.protocol
    return {"minutes": proto.minutes, "preset": task.space, "max_breaths": proto.max_breaths,
            "warmup_s": proto.warmup_s}


def _run_thesis(task: HilTask) -> dict[str, Any]:
    arm = _thesis_arm(task)
    kwargs = _session_kwargs(task)
    extra: dict[str, Any] = {}
    priors: list[Any] = []
    if arm.prior:
        # Day 1: the `adaptive` session of this subject (same protocol, seed, breath stream).
        day1 = run_session(task.seed, Arm("day1", n_explore=task.protocol.explore_points,
                                          window=task.protocol.window), **kwargs)
        priors = priors_from_evaluations(preset(task.space), day1["evaluations"],
                                         label=f"day1 seed {task.seed}")
        extra = {"day1_wall_s": day1["wall_s"], "day1_final_regret_w": day1["regret_trace"][-1][1],
                 "day1_n_evaluations": len(day1["evaluations"])}
    r = run_session(task.seed, arm, priors=priors, **kwargs)
    return {
        "trace": [(t, params) for t, params in r["recommendations"]],
        "n_evaluations": len(r["evaluations"]),
        "n_evaluations_bout2": r["n_evaluations_bout2"],
        "early_stops": r["n_early_stops"],
        "assisted_s": r["assisted_s"],
        "bout2_s": r["bout2_s"],
        "session_s": r["session_s"],
        "n_explore": arm.n_explore,
        "n_priors": r["n_priors"],
        "stopping_k": task.stopping_k,
        **extra,
    }


def run_training_session(task: HilTask) -> list[list[list[float]]]:
    """An ``adaptive`` session of a training wearer; returns its full-length breath trajectories.

    Each trajectory is the ``[t_s since the setting began, W]`` of every breath of an evaluation
    that ran all N breaths (the exploration bout and optimisation evaluations that were not
    stopped early): what :func:`tune_constant_k` replays. Picklable, for an executor.
    """
    blas_threads(1)
    proto = task.protocol
    r = run_session(task.seed, Arm("train", n_explore=proto.explore_points, window=proto.window),
                    **_session_kwargs(task))
    return r["trajectories"]


def tune_constant_k(trajectories: Sequence[Sequence[Sequence[float]]], protocol: HilProtocol, *,
                    pick: str = "bo", error_weight: float = 2.0, n_real: int = 60,
                    seed: int = 0) -> dict[str, Any]:
    """Tune the constant K of the σ-scaled rule offline (:func:`bridge.bench.tune_stopping.tune_stopping`).

    BO-RESAMPLE (Antonova 2016 §4.2) over K on the trajectories' replays, as ``hilbo tune-stopping``
    does on logs; the cost of a rule is the breaths it uses plus ``error_weight`` evaluations for
    every wrong early stop (docs/results_thesis.md §4).

    Args:
        trajectories: Full-length breath trajectories ``[[t_s, W], ...]`` of training wearers.
        protocol: Gives N (``max_breaths``), E and Algorithm 2's W for the reference.
        pick: ``"bo"`` — BO-RESAMPLE's recommendation; ``"grid"`` — the best K of the exhaustive
            41-point grid on all trajectory pairs.
        error_weight: λ, in evaluations' time.
        n_real: BO-RESAMPLE's real episodes.
        seed: Seeds the episodes and BO.

    Returns:
        JSON-able: ``k`` (the K to use), ``pick``, ``n_trajectories``, ``recommended`` (BO's K),
        ``recommended_exhaustive``, ``grid_best``, ``algorithm2`` and ``never_stop`` (offline
        costs), ``bo_resample_counts``.

    Raises:
        ConfigError: Unknown ``pick``, or fewer than 3 full-length trajectories.
    """
    from bridge.bench.tune_stopping import TuneStoppingConfig, tune_stopping

    if pick not in ("bo", "grid"):
        raise ConfigError(f"pick={pick!r}; expected 'bo' (BO-RESAMPLE) or 'grid' (exhaustive grid)")
    N = protocol.max_breaths
    cfg = TuneStoppingConfig(family="k", n_max=N, error_weight=error_weight,
                             reference_window=min(protocol.window, N - 1), n_explore=protocol.explore_points,
                             n_real=n_real, seed=seed)
    tuned = tune_stopping([np.asarray(t, dtype=float) for t in trajectories], cfg)
    k = tuned["recommended"]["k"] if pick == "bo" else tuned["grid_best"]["k"]
    bo = tuned["bo_resample"]
    return {
        "k": float(k), "pick": pick, "error_weight": error_weight, "n_real": n_real,
        "n_trajectories": tuned["n_trajectories"], "recommended": tuned["recommended"],
        "recommended_exhaustive": tuned["recommended_exhaustive"], "grid_best": tuned["grid_best"],
        "algorithm2": tuned["algorithm2"], "never_stop": tuned["never_stop"],
        "bo_resample_counts": {"n_real": bo["n_real"], "n_simulated": bo["n_simulated"],
                               "max_trajectory_uses": bo["max_trajectory_uses"]},
    }


def _fixed_condition_result(session: _Session, trace: list[tuple[float, dict[str, float]]]) -> dict[str, Any]:
    return {
        "trace": trace,
        "n_evaluations": session.n_conditions,
        "n_evaluations_bout2": session.bout2_conditions,
        "early_stops": 0,
        "assisted_s": session.assisted_s,
        "bout2_s": session.last_end_s - session.bout2_start_s if session.bout2_conditions else 0.0,
        "session_s": session.wearer.t_s,
        "walking": session.protocol.walking.to_json(),
    }


def run_hil_task(task: HilTask) -> dict[str, Any]:
    """Run one session (in a worker) and score its recommendations against the true landscape.

    Returns:
        JSON-able dict: ``method``, ``space``, ``seed``; ``trace`` — ``[t_s, regret_w]`` after
        every recommendation; ``baseline_cost_w``, ``optimum_cost_w``; ``final_regret_w`` and
        ``final_regret_pct`` (% of the optimum's reduction from unassisted walking);
        ``n_evaluations``, ``n_evaluations_bout2``, ``early_stops``; ``assisted_s`` (time on
        conditions), ``bout2_s``; ``evaluations_per_hour`` (conditions per hour of assisted
        walking, warm-ups excluded); ``wall_s``. The Antonova 2016 methods add ``n_explore``,
        ``n_priors``, ``stopping_k``, and for the prior methods ``day1_wall_s`` (included in
        ``wall_s``), ``day1_final_regret_w`` and ``day1_n_evaluations``.
    """
    blas_threads(1)  # wherever it runs: see bridge.bench.common.blas_threads
    t0 = time.perf_counter()
    runner = {**dict.fromkeys(_BO_VARIANTS, _run_bo),
              "cmaes": _run_cmaes, "random": _run_random,
              **dict.fromkeys(THESIS_METHODS, _run_thesis)}[task.method]
    out = runner(task)
    # The true landscape of the same subject (same seed); the optimum is found numerically.
    judge = make_wearer(task.protocol.wearer, preset(task.space), seed=task.seed)
    _, opt_cost = judge.true_optimum
    baseline = judge.baseline_cost_w
    reduction = max(baseline - opt_cost, 1e-9)
    trace = [(t, judge.true_cost_w(p) - opt_cost) for t, p in out.pop("trace")]
    final = trace[-1][1] if trace else math.nan
    return {
        "method": task.method, "space": task.space, "seed": task.seed,
        "trace": [[t, r] for t, r in trace],
        "baseline_cost_w": baseline, "optimum_cost_w": opt_cost,
        "final_regret_w": final, "final_regret_pct": 100.0 * final / reduction,
        "evaluations_per_hour": out["n_evaluations"] / max(out["assisted_s"] / 3600.0, 1e-9),
        **out,
        "wall_s": time.perf_counter() - t0,
    }


def load_sessions(path: Path, protocol: HilProtocol) -> dict[tuple[str, str, int], dict[str, Any]]:
    """Finished sessions of ``sessions.jsonl`` run under ``protocol``, by :meth:`HilTask.key`.

    Lines of other protocols are skipped; a truncated last line (a killed run) is ignored.
    """
    out: dict[tuple[str, str, int], dict[str, Any]] = {}
    if not path.exists():
        return out
    want = protocol.to_json()
    for line in path.read_text().splitlines():
        try:
            rec = json.loads(line)
        except json.JSONDecodeError:
            continue
        if rec.get("protocol") == want:
            out[(rec["method"], rec["space"], int(rec["seed"]))] = rec
    return out


def regret_at(trace: Sequence[Sequence[float]], t_s: float) -> float:
    """Regret of the latest recommendation made by ``t_s`` (NaN before the first)."""
    value = math.nan
    for t, r in trace:
        if t <= t_s:
            value = r
        else:
            break
    return value


def summarize_hil(results: Iterable[Mapping[str, Any]], spaces: Sequence[str], methods: Sequence[str],
                  protocol: HilProtocol) -> list[dict[str, Any]]:
    """One entry per method × space: regret quantiles on the minutes grid and rates.

    Each entry: ``method``, ``space``, ``n_sessions``, ``minutes``, ``regret_w_median``,
    ``regret_w_p75``, ``regret_pct_median`` (None until every session has a recommendation),
    ``final_regret_w_median``/``_p75``/``_mean``, ``final_regret_pct_median``,
    ``baseline_cost_w_median`` and ``optimum_reduction_w_median`` (unassisted cost minus optimum),
    ``evaluations_per_hour`` (mean over sessions), ``evaluations_bout2_mean``,
    ``early_stops_mean``, ``session_wall_s_mean``.
    """
    by: dict[tuple[str, str], list[Mapping[str, Any]]] = {}
    for r in results:
        by.setdefault((r["method"], r["space"]), []).append(r)
    n_grid = math.floor(protocol.minutes / protocol.grid_min + 1e-9)
    minutes = [round(k * protocol.grid_min, 6) for k in range(n_grid + 1)]
    out: list[dict[str, Any]] = []
    for space in spaces:
        for method in methods:
            rs = sorted(by.get((method, space), []), key=lambda r: r["seed"])
            if not rs:
                continue
            R = np.array([[regret_at(r["trace"], m * 60.0) for m in minutes] for r in rs])
            red = np.array([r["baseline_cost_w"] - r["optimum_cost_w"] for r in rs])
            complete = ~np.isnan(R).any(axis=0)
            with np.errstate(invalid="ignore"):
                med = np.where(complete, np.median(R, axis=0), np.nan)
                p75 = np.where(complete, np.percentile(R, 75, axis=0), np.nan)
                pct = np.where(complete, np.median(100.0 * R / red[:, None], axis=0), np.nan)
            fin = np.array([r["final_regret_w"] for r in rs])
            fin_pct = np.array([r["final_regret_pct"] for r in rs])
            out.append(round_sig({
                "method": method, "space": space, "n_sessions": len(rs), "minutes": minutes,
                "regret_w_median": med, "regret_w_p75": p75, "regret_pct_median": pct,
                "final_regret_w_median": float(np.median(fin)),
                "final_regret_w_p75": float(np.percentile(fin, 75)),
                "final_regret_w_mean": float(np.mean(fin)),
                "final_regret_pct_median": float(np.median(fin_pct)),
                "baseline_cost_w_median": float(np.median([r["baseline_cost_w"] for r in rs])),
                "optimum_reduction_w_median": float(np.median(red)),
                "evaluations_per_hour": float(np.mean([r["evaluations_per_hour"] for r in rs])),
                "evaluations_bout2_mean": float(np.mean([r["n_evaluations_bout2"] for r in rs])),
                "bout2_min_mean": float(np.mean([r["bout2_s"] for r in rs])) / 60.0,
                "early_stops_mean": float(np.mean([r["early_stops"] for r in rs])),
                "session_wall_s_mean": float(np.mean([r["wall_s"] for r in rs])),
            }))
    return out


def _comparison_pairs(methods: Sequence[str]) -> list[tuple[str, str]]:
    """(method, baseline) pairs: every method against the first; against ``adaptive`` too when it
    is not first; the prior methods against ``adaptive-day2`` (their control) when it ran."""
    pairs: list[tuple[str, str]] = []
    baselines = [methods[0]]
    if "adaptive" in methods and methods[0] != "adaptive":
        baselines.append("adaptive")
    for base in baselines:
        pairs += [(m, base) for m in methods if m != base and (m, base) not in pairs]
    if "adaptive-day2" in methods:
        pairs += [(m, "adaptive-day2") for m in PRIOR_METHODS
                  if m in methods and (m, "adaptive-day2") not in pairs]
    return pairs


def hil_comparisons(results: Iterable[Mapping[str, Any]], spaces: Sequence[str],
                    methods: Sequence[str], *,
                    at_minutes: Sequence[float] = (20.0, 30.0, 40.0)) -> list[dict[str, Any]]:
    """Paired per-subject differences of regret, method − baseline, at the end and at equal minutes.

    The pairs: every method after the first against the first; every method against
    ``adaptive`` as well when it ran but is not first; ``adaptive-prior``/``-e3`` against
    ``adaptive-day2`` (the same day without the prior) when it ran. For each pair and space, over
    the subjects both ran: the median, mean and standard error of ``final_regret_w(method) −
    final_regret_w(baseline)`` and the fraction of subjects where the method ended lower; and
    the same mean, SE and fraction of the regret at each of ``at_minutes`` of the session clock
    (``regret_diff_w_mean_at`` etc., aligned with ``at_minutes``; None where a session has no
    recommendation yet).
    """
    results = list(results)
    final = {(r["method"], r["space"], r["seed"]): r["final_regret_w"] for r in results}
    traces = {(r["method"], r["space"], r["seed"]): r.get("trace") for r in results}
    out = []
    for space in spaces:
        for method, base in _comparison_pairs(methods):
            seeds = sorted(k[2] for k in final if k[0] == method and k[1] == space
                           and (base, space, k[2]) in final)
            if not seeds:
                continue
            d = np.array([final[(method, space, s)] - final[(base, space, s)] for s in seeds])
            mean_at, se_at, lower_at = [], [], []
            for m in at_minutes:
                if any(traces[(x, space, s)] is None for x in (method, base) for s in seeds):
                    dm = np.array([np.nan])
                else:
                    dm = np.array([regret_at(traces[(method, space, s)], m * 60.0)
                                   - regret_at(traces[(base, space, s)], m * 60.0) for s in seeds])
                ok = dm[np.isfinite(dm)]
                complete = len(ok) == len(seeds)
                mean_at.append(float(ok.mean()) if complete else None)
                se_at.append(float(ok.std(ddof=1) / math.sqrt(len(ok))) if complete and len(ok) > 1 else None)
                lower_at.append(float(np.mean(ok < 0)) if complete else None)
            out.append(round_sig({
                "space": space, "method": method, "baseline": base, "n_subjects": len(seeds),
                "final_regret_diff_w_median": float(np.median(d)),
                "final_regret_diff_w_mean": float(d.mean()),
                "final_regret_diff_w_se": float(d.std(ddof=1) / math.sqrt(len(d))) if len(d) > 1 else None,
                "frac_lower": float(np.mean(d < 0)),
                "at_minutes": [float(m) for m in at_minutes],
                "regret_diff_w_mean_at": mean_at, "regret_diff_w_se_at": se_at, "frac_lower_at": lower_at,
            }))
    return out


def hil_table(entries: Sequence[Mapping[str, Any]],
              at_minutes: Sequence[float] = (20, 30, 40, 50, 60),
              comparisons: Sequence[Mapping[str, Any]] = ()) -> str:
    """Markdown: median regret (W) at a few session minutes, final regret, rates; then the
    paired differences of :func:`hil_comparisons`."""
    header = ["space", "method", "sessions"] + [f"median regret @{m:g} min (W)" for m in at_minutes] + [
        "final regret median / p75 (W)", "final regret median (% of reduction)",
        "evaluations / h", "bout-2 evaluations", "early stops"]
    rows = []
    for e in entries:
        cells = []
        for m in at_minutes:
            v = None
            if m in e["minutes"]:
                v = e["regret_w_median"][e["minutes"].index(m)]
            cells.append("–" if v is None else f"{v:.1f}")
        rows.append([e["space"], e["method"], e["n_sessions"], *cells,
                     f"{e['final_regret_w_median']:.1f} / {e['final_regret_w_p75']:.1f}",
                     f"{e['final_regret_pct_median']:.1f} %", f"{e['evaluations_per_hour']:.1f}",
                     f"{e['evaluations_bout2_mean']:.1f}", f"{e['early_stops_mean']:.1f}"])
    out = markdown_table(header, rows)
    if comparisons:
        at = list(comparisons[0].get("at_minutes") or [])

        def mean_se(mean: float | None, se: float | None) -> str:
            return "–" if mean is None else f"{mean:.1f}" + ("" if se is None else f" ± {se:.1f}")

        crow = []
        for c in comparisons:
            cells = []
            for i in range(len(at)):
                mean = c.get("regret_diff_w_mean_at", [None] * len(at))[i]
                se = c.get("regret_diff_w_se_at", [None] * len(at))[i]
                lower = c.get("frac_lower_at", [None] * len(at))[i]
                cells.append(mean_se(mean, se) + ("" if lower is None else f" ({100 * lower:.0f} %)"))
            crow.append([c["space"], f"{c['method']} − {c['baseline']}", c["n_subjects"], *cells,
                         f"{c['final_regret_diff_w_median']:.1f}",
                         mean_se(c["final_regret_diff_w_mean"], c["final_regret_diff_w_se"]),
                         f"{100 * c['frac_lower']:.0f} %"])
        out += "\n" + markdown_table(
            ["space", "paired difference of regret", "subjects",
             *[f"@{m:g} min: mean ± SE (W) (% lower)" for m in at],
             "final: median (W)", "final: mean ± SE (W)", "subjects where the method ended lower"], crow)
    return out
