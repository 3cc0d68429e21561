"""One simulated HIL session with the Antonova 2016 options: fast prior, feature kernel, constant-K stopping.

Shared by the study script (:mod:`bridge.bench.thesis_study`, docs/results_thesis.md §2–4) and the
``adaptive-*`` methods of ``hilbo bench hil`` (:mod:`bridge.bench.hil`). The protocol is that of
:func:`bridge.sim.core.run_insim` (a warm-up, the exploration bout of E × N breaths, a second
warm-up, optimisation until the session ends, all on the wearer's breath clock); a session with
the default :class:`Arm` is the same session as ``hilbo sim`` / the ``adaptive`` method.

The optimizer does not (yet) take a feature map or a constant-K rule, so :class:`StudyOptimizer`
overrides three private methods of :class:`HILOptimizer` (``_fit_gp``, ``_propose``, ``_rule``)
— measurement scaffolding, to be replaced by optimizer options. The simulated wearer has no
"new day" option either; the breath stream of day 2 is reseeded by replacing its private
generator. Both are marked where they happen. The simulated wearer's landscape does not change
between days, so a prior from day 1 is a best case (a real wearer adapts and drifts).
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from bridge.sim.core import SimConfig, check_optimisation_ran
from bridge.sim.devices import SimulatedWearer
from hilbo_core import HILOptimizer, brockway_watts, presets
from hilbo_core.acquisition import maximize_ei
from hilbo_core.errors import ConfigError
from hilbo_core.features import ProfileFeatureMap, with_raw
from hilbo_core.gp import GaussianProcess
from hilbo_core.optimizer import BreathStep, Evaluation, OptimizerConfig, Phase, PriorObservation
from hilbo_core.protocol import SessionProtocol, SessionProtocolConfig, drive
from hilbo_core.stopping import FixedIntervalRule, SigmaScaledRule, StoppingRule

__all__ = ["FEATURE_KINDS", "Arm", "StudyOptimizer", "run_session"]

FEATURE_KINDS = ("profile", "profile+raw")
"""Feature kernels of :class:`Arm`: profile features only, or profile features and raw parameters."""

_DAY_STREAM = 100_000  # the optimizer seed of day d > 1 is seed + 100000 (any fixed offset would do)


class StudyOptimizer(HILOptimizer):
    """HILOptimizer with a feature map and/or a constant-K stopping rule (study scaffolding).

    Overrides private methods of the parent; the wiring the optimizer needs instead:
    ``GaussianProcess(kernel, feature_map=fm)`` in ``_fit_gp`` and
    ``predict_grad=None if fm else gp.predict_with_grad`` in ``_propose``;
    ``SigmaScaledRule.constant(k, N)`` in ``_rule``.
    """

    def __init__(self, *args: Any, feature_map: Callable[[np.ndarray], np.ndarray] | None = None,
                 stopping_k: float | None = None, **kwargs: Any) -> None:
        self._feature_map = feature_map
        self._stopping_k = stopping_k
        super().__init__(*args, **kwargs)

    def _fit_gp(self, rng: np.random.Generator, *, store: bool) -> GaussianProcess:
        if self._feature_map is None:
            return super()._fit_gp(rng, store=store)
        U, y, v = self._training_set()
        gp = GaussianProcess(self.config.kernel, feature_map=self._feature_map)
        gp.fit(U, y, v, rng=rng, init=self._hyp)
        if store:
            self._hyp = gp.hyperparameters
        return gp

    def _propose(self) -> np.ndarray:
        if self._feature_map is None:
            return super()._propose()
        # The parent's proposal with finite-difference EI refinement (φ has no Jacobian).
        gp = self._fit_gp(self._rng, store=True)
        self._incumbent = self._gp_best(gp)
        best_observed = min(e.mean for e in self._evaluations)
        A_u, b_u = self.space.unit_constraints()
        cand = self.space.sample_unit(self.config.n_candidates, self._rng)
        u, _ = maximize_ei(gp.predict, best_observed, candidates=cand, A_ub=A_u, b_ub=b_u,
                           rng=self._rng, xi=self.config.xi, n_local=self.config.n_local,
                           predict_grad=None)
        x = self.space.from_unit(np.clip(u, 0.0, 1.0))
        return x if self.space.is_feasible(x) else self.space.from_unit(cand[0])

    def _rule(self) -> StoppingRule:
        if self._stopping_k is None or self._thresholds is None:
            return super()._rule()
        if self.config.stopping.value == "fixed":
            return FixedIntervalRule(self.config.max_breaths)
        return SigmaScaledRule.constant(self._stopping_k, self.config.max_breaths)


@dataclass(frozen=True)
class Arm:
    """One way of running a session.

    Attributes:
        name: Label.
        n_explore: Exploration points E.
        feature: None (raw parameters), ``"profile"`` or ``"profile+raw"`` (:data:`FEATURE_KINDS`).
        stopping_k: Constant K of the σ-scaled rule (in σ, >= 0), or None for Algorithm 2's schedule.
        window: Algorithm 2's window W (when ``stopping_k`` is None).
        prior: The session is given prior observations (bookkeeping: pass them to
            :func:`run_session`).
        day: 1 for the first session (the default breath stream and optimizer seed), 2 or more
            for a later "day" of the same wearer (a fresh breath stream and optimizer seed).
    """

    name: str
    n_explore: int = OptimizerConfig.n_explore
    feature: str | None = None
    stopping_k: float | None = None
    window: int = OptimizerConfig.window
    prior: bool = False
    day: int = 1

    def __post_init__(self) -> None:
        if self.feature is not None and self.feature not in FEATURE_KINDS:
            raise ConfigError(f"feature={self.feature!r}; expected None or one of {list(FEATURE_KINDS)}")
        if self.stopping_k is not None and not (np.isfinite(self.stopping_k) and self.stopping_k >= 0):
            raise ConfigError(f"stopping_k={self.stopping_k!r}; expected a constant K >= 0 (in σ) or None")
        if isinstance(self.day, bool) or not isinstance(self.day, int) or self.day < 1:
            raise ConfigError(f"day={self.day!r}; expected an integer >= 1")


def run_session(seed: int, arm: Arm, *, minutes: float = 60.0, preset: str = "hip_6d",
                priors: Sequence[PriorObservation] = (),
                max_breaths: int = OptimizerConfig.max_breaths,
                warmup_s: float = SessionProtocolConfig.warmup_s) -> dict[str, Any]:
    """One simulated session (the protocol of :func:`bridge.sim.core.run_insim`).

    Args:
        seed: The simulated wearer (subject) and, on day 1, the optimizer's seed.
        arm: How the session is run.
        minutes: Session length on the breath clock, warm-ups included.
        preset: Parameter-space preset.
        priors: Prior observations given to the optimizer before the session starts.
        max_breaths: N.
        warmup_s: Each of the two unassisted warm-ups (s).

    Returns:
        ``regret_trace`` ([t_end_s, regret_w] after every evaluation), ``recommendations``
        ([t_end_s, params] after every evaluation: :meth:`HILOptimizer.best`), ``evaluations``,
        ``trajectories`` (breaths [t_s, W] of every evaluation that ran N breaths), the wearer's
        ``optimum_w`` and ``baseline_w``, ``n_early_stops``, ``n_evaluations_bout2``,
        ``assisted_s`` (time on settings), ``bout2_s`` (first to last optimisation breath),
        ``session_s`` (the session clock at the end), ``walking``
        (:class:`~hilbo_core.protocol.WalkingTime`), ``n_priors`` and ``wall_s``.

    Raises:
        ConfigError: The minutes end before the optimisation bout begins.
    """
    wall0 = time.perf_counter()
    space = presets.preset(preset)
    wearer = SimulatedWearer(space, seed=seed)
    opt_seed = seed if arm.day == 1 else seed + _DAY_STREAM * (arm.day - 1)
    if arm.day != 1:
        # Scaffolding: a "new day" of the same subject = a fresh breath-noise stream (the wearer
        # has no option for it; its subject and landscape stay those of ``seed``).
        wearer._breath_rng = np.random.default_rng([seed, arm.day])
    fm = None
    if arm.feature is not None:
        prof = ProfileFeatureMap(space, n_reference=256, seed=0)
        fm = prof if arm.feature == "profile" else with_raw(prof, space.dim)
    opt = StudyOptimizer(space, n_explore=arm.n_explore, max_breaths=max_breaths, window=arm.window,
                         seed=opt_seed, prior_observations=list(priors), feature_map=fm,
                         stopping_k=arm.stopping_k,
                         stopping="adaptive")  # the Antonova 2016 studies are of Kim et al. 2019's rule
    _, opt_cost = wearer.true_optimum
    # The protocol of run_insim for the seed's rule (Kim et al. 2019's walking protocol): the
    # minutes are the whole session, no pause between the bouts.
    plan = SimConfig(minutes=minutes, n_explore=arm.n_explore, max_breaths=max_breaths, warmup_s=warmup_s,
                     stopping="adaptive", protocol="seed")
    protocol = SessionProtocol(plan.protocol_config(), t_start_s=wearer.t_s)
    trace: list[list[float]] = []
    recommendations: list[list[Any]] = []
    trajectories: list[list[list[float]]] = []
    breaths: list[list[float]] = []
    assisted_s = 0.0
    bout2_start = bout2_end = None

    def next_breath() -> tuple[float, float]:
        b = wearer.next_breath()
        return b.t_s, float(brockway_watts(b.vo2_ml_min, b.vco2_ml_min))

    def apply_setting(params: Mapping[str, float] | None, t_s: float) -> None:
        if params is None:
            wearer.apply_profiles((), t_s)
        else:
            wearer.apply_params(params, t_s)
        breaths.clear()

    def on_measure(step: BreathStep, t_setting_s: float, watts: float) -> None:
        breaths.append([t_setting_s, watts])

    def on_evaluation(ev: Evaluation, t0: float, t_end: float) -> None:
        nonlocal assisted_s, bout2_start, bout2_end
        assisted_s += t_end - t0
        if ev.phase == Phase.OPTIMIZATION.value:
            bout2_start = t0 if bout2_start is None else bout2_start
            bout2_end = t_end
        if len(breaths) == max_breaths:
            trajectories.append(list(breaths))
        best_params, _, _ = opt.best()
        trace.append([t_end, wearer.true_cost_w(best_params) - opt_cost])
        recommendations.append([t_end, best_params])

    drive(protocol, opt, next_breath, apply_setting, on_measure=on_measure, on_evaluation=on_evaluation)
    check_optimisation_ran(protocol, minutes)
    evaluations = [e.to_json() for e in opt.evaluations]
    return {
        "seed": seed, "arm": asdict(arm), "regret_trace": trace, "recommendations": recommendations,
        "evaluations": evaluations, "trajectories": trajectories,
        "optimum_w": opt_cost, "baseline_w": wearer.baseline_cost_w,
        "n_early_stops": sum(e.stopped_early for e in opt.evaluations),
        "n_evaluations_bout2": sum(e["phase"] == "optimization" for e in evaluations),
        "assisted_s": assisted_s,
        "bout2_s": 0.0 if bout2_start is None or bout2_end is None else bout2_end - bout2_start,
        "session_s": wearer.t_s, "walking": protocol.walking.to_json(), "n_priors": len(priors),
        "wall_s": time.perf_counter() - wall0,
    }
