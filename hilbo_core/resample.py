"""BO-RESAMPLE (Antonova 2016 §4.2, Algorithm 1): Bayesian optimisation of optimal-stopping policies
with off-policy re-evaluation of stored trajectories.

An optimal-stopping policy watches a sequence of observations o_1, o_2, … and decides before each
step whether to halt; its cost is a function of the observations up to where it halted. A
trajectory collected with a policy that halted after ``t`` steps therefore also tells what any
other policy would have got *if that policy halts at some step t' <= t on the same observations*:
replay the stored prefix and ask the new policy at every step (:func:`replay_halt_step`). A
policy that would continue beyond ``t`` cannot be evaluated on that trajectory.

Algorithm 1 (Antonova 2016 §4.2)::

    for j = 1 … J:
        π_j ← NextBOPoint(GP);  τ_j ← ExecuteInRealWorld(π_j);  UpdateGP(GetObjectVal(τ_j))
        for k = 1 … K:                                   # K resamples per real evaluation
            π_k ← NextBOPoint(GP)
            τ_k ← SelectRandLimited(τ_1 … τ_j)           # each trajectory reused a bounded number of times
            τ'_k ← SimulatePolicyExec(π_k, τ_k);  UpdateGP(GetObjectVal(τ'_k))

Details Antonova 2016 leaves open, as implemented here:

* ``SelectRandLimited`` draws uniformly among the stored trajectories that have been resampled
  fewer than ``max_reuse`` times *and* can evaluate π_k (the new policy halts within the stored
  prefix); the prose says resampling goes on "until we have used all prior trajectories at most a
  bounded number of times or until we reach a point that we cannot evaluate given the existing
  prior data". When no trajectory qualifies, resampling stops for this round and π_k — proposed
  by the unchanged GP — becomes the next real evaluation.
* The real execution itself does not count as a reuse of its trajectory.
* The GP's hyperparameters are refitted (maximum a-posteriori, warm-started) after every real
  evaluation; a resampled value only conditions the GP on one more point with the hyperparameters
  kept, which is exact GP conditioning and keeps K resamples cheap.
* The recommendation after each real evaluation is the evaluated policy (real or simulated) with
  the lowest GP posterior mean (as Kim et al. 2019 §III.2 recommends the GP's estimated minimum).

Costs are minimised (Antonova 2016's tutoring objective is f(π) = 1 − R(π)). Everything problem-specific
is a callable: ``execute`` (the real world), ``halt`` (the policy class) and ``objective``. With
``n_resamples = 0`` the loop is plain BO, so both arms of a comparison share one code path.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any

import numpy as np

from hilbo_core.acquisition import maximize_ei
from hilbo_core.errors import ConfigError, MeasurementError
from hilbo_core.gp import GaussianProcess, GPHyperparameters, KernelKind
from hilbo_core.space import DesignKind, ParameterSpace

__all__ = [
    "ExecuteFn",
    "HaltRule",
    "ObjectiveFn",
    "PolicyEvaluation",
    "ResampleConfig",
    "ResampleRun",
    "Trajectory",
    "TrajectoryStore",
    "bo_resample",
    "replay_halt_step",
    "simulate_policy_exec",
]

HaltRule = Callable[[Mapping[str, float], Sequence[Any], Mapping[str, Any]], bool]
"""``halt(policy_params, observations_so_far, context) -> bool``: stop before the next step?"""
ObjectiveFn = Callable[[Sequence[Any], int, Mapping[str, Any], Mapping[str, float]], float]
"""``objective(observations, halt_step, context, params) -> cost`` of halting after ``halt_step``
steps. Algorithm 1's GetObjectVal needs only the trajectory; ``params`` is there for episodes
that pose several stopping decisions at once (e.g. one breath trace against several incumbents,
``bridge.bench.tune_stopping``), whose cost the policy's own decisions determine."""
ExecuteFn = Callable[[dict[str, float], np.random.Generator], "Trajectory"]
"""``execute(policy_params, rng) -> Trajectory``: run the policy in the real world."""


@dataclass(frozen=True)
class Trajectory:
    """Observations collected by running a policy until it halted.

    Attributes:
        observations: o_1 … o_L (any objects; the halt rule and objective interpret them). A
            policy halting after ``s`` steps has seen ``observations[:s]``; the objective may also
            read later entries up to ``halt_step`` (e.g. the tutor's assessment answer, o_{t+1}).
        halt_step: Steps the collecting policy took before halting, 0 <= halt_step <= L. Every
            policy that halts after at most this many steps can be replayed on the trajectory.
        context: Fixed facts of the episode that are not observations (read-only), e.g. the
            incumbent a metabolic estimate is compared with.
    """

    observations: tuple[Any, ...]
    halt_step: int
    context: Mapping[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        obs = tuple(self.observations)
        object.__setattr__(self, "observations", obs)
        h = self.halt_step
        if isinstance(h, bool) or not isinstance(h, int | np.integer) or not 0 <= h <= len(obs):
            raise ConfigError(
                f"halt_step={h!r}; expected an integer in [0, {len(obs)}] (the number of observations)"
            )
        object.__setattr__(self, "halt_step", int(h))
        object.__setattr__(self, "context", MappingProxyType(dict(self.context)))


def replay_halt_step(halt: HaltRule, params: Mapping[str, float], trajectory: Trajectory) -> int | None:
    """Where a policy would halt on a stored trajectory (off-policy replay, Antonova 2016 §4.2).

    Asks ``halt`` after 0, 1, … observations of the stored prefix.

    Args:
        halt: The policy class's decision rule.
        params: The policy to replay.
        trajectory: The stored episode.

    Returns:
        The first s <= ``trajectory.halt_step`` at which the policy halts, or None when it would
        continue beyond the stored data (it cannot be evaluated on this trajectory).
    """
    obs = trajectory.observations
    for s in range(trajectory.halt_step + 1):
        if halt(params, obs[:s], trajectory.context):
            return s
    return None


def simulate_policy_exec(halt: HaltRule, objective: ObjectiveFn, params: Mapping[str, float],
                         trajectory: Trajectory) -> tuple[int, float] | None:
    """SimulatePolicyExec of Algorithm 1: (halt step, cost) of a policy on a stored trajectory.

    Returns:
        None when the policy cannot be evaluated on the trajectory (see :func:`replay_halt_step`).
    """
    s = replay_halt_step(halt, params, trajectory)
    if s is None:
        return None
    return s, _check_cost(objective(trajectory.observations, s, trajectory.context, params))


def _check_cost(value: float) -> float:
    cost = float(value)
    if not math.isfinite(cost):
        raise MeasurementError(f"objective returned {value!r}; expected a finite cost")
    return cost


class TrajectoryStore:
    """The trajectories collected so far, with how often each was resampled.

    Args:
        max_reuse: Resamples allowed per trajectory (Antonova 2016's experiments: 10).
    """

    def __init__(self, max_reuse: int) -> None:
        if isinstance(max_reuse, bool) or not isinstance(max_reuse, int) or max_reuse < 0:
            raise ConfigError(f"max_reuse={max_reuse!r}; expected an integer >= 0")
        self._max_reuse = max_reuse
        self._trajectories: list[Trajectory] = []
        self._uses: list[int] = []

    @property
    def max_reuse(self) -> int:
        """Resamples allowed per trajectory."""
        return self._max_reuse

    def __len__(self) -> int:
        return len(self._trajectories)

    def __getitem__(self, index: int) -> Trajectory:
        return self._trajectories[index]

    def add(self, trajectory: Trajectory) -> int:
        """Store a trajectory; returns its index."""
        if not isinstance(trajectory, Trajectory):
            raise ConfigError(f"expected a Trajectory, got {type(trajectory).__name__}")
        self._trajectories.append(trajectory)
        self._uses.append(0)
        return len(self._trajectories) - 1

    def uses(self, index: int) -> int:
        """How often trajectory ``index`` has been resampled."""
        return self._uses[index]

    @property
    def all_uses(self) -> tuple[int, ...]:
        """Resample counts of every trajectory, by index."""
        return tuple(self._uses)

    def available(self) -> list[int]:
        """Indices that may still be resampled."""
        return [i for i, u in enumerate(self._uses) if u < self._max_reuse]

    def select_limited(self, halt: HaltRule, params: Mapping[str, float],
                       rng: np.random.Generator) -> tuple[int, int] | None:
        """SelectRandLimited + replay: a random reusable trajectory that can evaluate ``params``.

        Tries the reusable trajectories in random order and takes the first on which the policy
        halts within the stored prefix; that trajectory's use count goes up by one.

        Returns:
            (trajectory index, halt step), or None when no reusable trajectory can evaluate it.
        """
        avail = self.available()
        for i in rng.permutation(len(avail)):
            idx = avail[int(i)]
            s = replay_halt_step(halt, params, self._trajectories[idx])
            if s is not None:
                self._uses[idx] += 1
                return idx, s
        return None


@dataclass(frozen=True)
class ResampleConfig:
    """Options of :func:`bo_resample`.

    Attributes:
        n_resamples: K, simulated evaluations after each real one (0 = plain BO).
        max_reuse: Resamples allowed per stored trajectory (Antonova 2016 §4.4 uses 10).
        n_init: Real evaluations on a space-filling design before the GP proposes (>= 1).
        kernel: GP kernel.
        n_candidates: Feasible Sobol candidates per EI maximisation.
        n_local: Candidates refined locally per EI maximisation.
        n_restarts: Random restarts of the hyperparameter fit.
        xi: EI's ξ (Kim et al. 2019 §II.B convention).
    """

    n_resamples: int = 10
    max_reuse: int = 10
    n_init: int = 2
    kernel: KernelKind = KernelKind.MATERN52
    n_candidates: int = 256
    n_local: int = 1
    n_restarts: int = 1
    xi: float = 0.0

    def __post_init__(self) -> None:
        for name, low in (("n_resamples", 0), ("max_reuse", 0), ("n_init", 1),
                          ("n_candidates", 1), ("n_local", 0), ("n_restarts", 0)):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < low:
                raise ConfigError(f"ResampleConfig.{name}={v!r}; expected an integer >= {low}")
        try:
            object.__setattr__(self, "kernel", KernelKind(self.kernel))
        except ValueError as err:
            raise ConfigError(f"ResampleConfig.kernel={self.kernel!r}; expected one of "
                              f"{[k.value for k in KernelKind]}") from err
        if not math.isfinite(self.xi):
            raise ConfigError(f"ResampleConfig.xi={self.xi!r}; expected a finite number")


@dataclass(frozen=True)
class PolicyEvaluation:
    """One evaluation the GP was told about.

    Attributes:
        params: The policy.
        cost: Its cost on the trajectory.
        simulated: True for an off-policy resample, False for a real execution.
        trajectory: Index of the trajectory in the store.
        halt_step: Where the policy halted on it.
        n_real: Real evaluations done when this one was made (1-based).
    """

    params: dict[str, float]
    cost: float
    simulated: bool
    trajectory: int
    halt_step: int
    n_real: int

    def to_json(self) -> dict[str, Any]:
        """JSON-able form."""
        return {"params": self.params, "cost": self.cost, "simulated": self.simulated,
                "trajectory": self.trajectory, "halt_step": self.halt_step, "n_real": self.n_real}


@dataclass(frozen=True)
class ResampleRun:
    """What :func:`bo_resample` did.

    Attributes:
        evaluations: Every evaluation in order (real and simulated).
        recommendations: The recommended policy after each real evaluation (its resamples
            included), one per real evaluation.
        trajectory_uses: Final resample count of every stored trajectory.
        hyperparameters: The last GP hyperparameters.
    """

    evaluations: tuple[PolicyEvaluation, ...]
    recommendations: tuple[dict[str, float], ...]
    trajectory_uses: tuple[int, ...]
    hyperparameters: GPHyperparameters | None

    @property
    def n_real(self) -> int:
        """Real evaluations."""
        return sum(not e.simulated for e in self.evaluations)

    @property
    def n_simulated(self) -> int:
        """Off-policy resamples."""
        return sum(e.simulated for e in self.evaluations)


class _Surrogate:
    """The GP over policy parameters, refitted or just conditioned as Algorithm 1 needs."""

    def __init__(self, space: ParameterSpace, cfg: ResampleConfig) -> None:
        self.space = space
        self.cfg = cfg
        self.U: list[np.ndarray] = []
        self.y: list[float] = []
        self.hyp: GPHyperparameters | None = None
        self.gp: GaussianProcess | None = None

    def add(self, x: np.ndarray, cost: float, rng: np.random.Generator, *, refit: bool) -> None:
        self.U.append(self.space.to_unit(x))
        self.y.append(cost)
        gp = GaussianProcess(self.cfg.kernel, n_restarts=self.cfg.n_restarts)
        optimize = refit or self.hyp is None
        gp.fit(np.array(self.U), np.array(self.y), None, rng=rng, init=self.hyp, optimize=optimize)
        self.hyp = gp.hyperparameters
        self.gp = gp

    def propose(self, rng: np.random.Generator) -> np.ndarray:
        gp = self.gp
        if gp is None:
            raise ConfigError("internal: propose() before any observation")
        A_u, b_u = self.space.unit_constraints()
        cand = self.space.sample_unit(self.cfg.n_candidates, rng)
        u, _ = maximize_ei(gp.predict, float(min(self.y)), candidates=cand, A_ub=A_u, b_ub=b_u,
                           rng=rng, xi=self.cfg.xi, n_local=self.cfg.n_local,
                           predict_grad=gp.predict_with_grad)
        x = self.space.from_unit(np.clip(u, 0.0, 1.0))
        return x if self.space.is_feasible(x) else self.space.from_unit(cand[0])

    def recommend(self) -> np.ndarray:
        if self.gp is None:
            raise ConfigError("internal: recommend() before any observation")
        U = np.array(self.U)
        mean, _ = self.gp.predict(U)
        return self.space.from_unit(U[int(np.argmin(mean))])


def bo_resample(
    space: ParameterSpace,
    execute: ExecuteFn,
    halt: HaltRule,
    objective: ObjectiveFn,
    *,
    n_real: int,
    rng: np.random.Generator,
    config: ResampleConfig | None = None,
    prior_trajectories: Sequence[Trajectory] = (),
    on_real: Callable[[int, ResampleRun], None] | None = None,
) -> ResampleRun:
    """Run Algorithm 1 of Antonova 2016 §4.2 for ``n_real`` real evaluations.

    Args:
        space: The policy-parameter space.
        execute: Runs a policy in the real world and returns its trajectory.
        halt: The policy class's decision rule (used to replay stored trajectories).
        objective: Cost of a trajectory halted at a step (minimised).
        n_real: J, the number of real evaluations (>= 1).
        rng: The only source of randomness (design, candidates, trajectory selection; ``execute``
            receives it too).
        config: K, the reuse bound and the BO options.
        prior_trajectories: Trajectories collected beforehand (e.g. recorded sessions); they can
            be resampled like the real ones from the start.
        on_real: Called after every real evaluation's resamples with (j, the run so far).

    Returns:
        The evaluations, the recommendation after each real evaluation and the reuse counts.

    Raises:
        ConfigError: Bad arguments, or ``execute`` returned something other than a Trajectory.
        MeasurementError: The objective returned a non-finite cost.
    """
    cfg = ResampleConfig() if config is None else config
    if isinstance(n_real, bool) or not isinstance(n_real, int) or n_real < 1:
        raise ConfigError(f"n_real={n_real!r}; expected an integer >= 1 (real evaluations)")
    store = TrajectoryStore(cfg.max_reuse)
    for traj in prior_trajectories:
        store.add(traj)
    model = _Surrogate(space, cfg)
    # The design BO-RESAMPLE was measured with (the Antonova 2016 method stays what it was).
    design = space.design(min(cfg.n_init, n_real), rng, kind=DesignKind.MAXIMIN)
    evaluations: list[PolicyEvaluation] = []
    recommendations: list[dict[str, float]] = []
    pending: np.ndarray | None = None

    def snapshot() -> ResampleRun:
        return ResampleRun(tuple(evaluations), tuple(recommendations), store.all_uses, model.hyp)

    for j in range(n_real):
        if j < len(design):
            x = design[j]
        elif pending is not None:
            x = pending  # proposed by the GP as it still is (resampling could not evaluate it)
        else:
            x = model.propose(rng)
        pending = None
        params = space.to_dict(x)
        traj = execute(dict(params), rng)
        if not isinstance(traj, Trajectory):
            raise ConfigError(f"execute must return a Trajectory, got {type(traj).__name__}")
        idx = store.add(traj)
        cost = _check_cost(objective(traj.observations, traj.halt_step, traj.context, params))
        evaluations.append(PolicyEvaluation(params, cost, False, idx, traj.halt_step, j + 1))
        model.add(x, cost, rng, refit=True)
        for _ in range(cfg.n_resamples):
            xk = model.propose(rng)
            pk = space.to_dict(xk)
            picked = store.select_limited(halt, pk, rng)
            if picked is None:
                pending = xk
                break
            i, s = picked
            tk = store[i]
            ck = _check_cost(objective(tk.observations, s, tk.context, pk))
            evaluations.append(PolicyEvaluation(pk, ck, True, i, s, j + 1))
            model.add(xk, ck, rng, refit=False)
        recommendations.append(space.to_dict(model.recommend()))
        if on_real is not None:
            on_real(j + 1, snapshot())
    return snapshot()
