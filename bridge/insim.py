"""In-process simulated session: HILOptimizer driven breath by breath by the simulated wearer.

This is what ``hilbo sim`` runs until the asyncio bridge drives the virtual devices over real
transports. The protocol follows seed 000 §IV.A.3: a first bout with a warm-up and the
exploration points, then a second bout with a warm-up and Bayesian optimisation until the
session's minutes are used up. Time is the wearer's breath clock, so a 60-minute session runs
as fast as the computer allows (``speed="max"``) or paced at a multiple of real time.
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from hilbo_core import HILOptimizer, brockway_watts, fit_hyperparameters, presets
from hilbo_core.errors import ConfigError
from hilbo_core.optimizer import Evaluation
from virtual_hw.wearer import WearerKind, make_wearer, wearer_kind

__all__ = ["SimConfig", "SimEvaluation", "run_insim"]

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class SimConfig:
    """A simulated session.

    Attributes:
        minutes: Whole session length in minutes of walking (both bouts, warm-ups included).
        seed: Seeds the wearer (the subject) and the optimizer.
        speed: ``None`` for as fast as possible, else the real-time factor (1 = real time).
        preset: Parameter-space preset name.
        n_explore: Exploration points.
        max_breaths: N, the maximum breaths per evaluation.
        window: Algorithm 2's window W.
        warmup_s: Warm-up at the start of each bout, without assistance (seed: 3 min).
        stopping: ``"adaptive"`` or ``"fixed"``.
        refit: ``"at_proposal"`` (GP hyperparameters refitted in every proposal) or ``"ahead"``
            (as the bridge does by default: fitted on the completed evaluations while the next
            setting is measured, ``refit_lag`` 1).
        wearer: The simulated wearer (:class:`virtual_hw.wearer.WearerKind` value): ``realistic``
            (default) or ``legacy``.
    """

    minutes: float = 60.0
    seed: int = 1
    speed: float | None = None
    preset: str = "hip_6d"
    n_explore: int = 6
    max_breaths: int = 45
    window: int = 2
    warmup_s: float = 180.0
    stopping: str = "adaptive"
    refit: str = "at_proposal"
    wearer: str = WearerKind.REALISTIC.value

    def __post_init__(self) -> None:
        wearer_kind(self.wearer)  # raises ConfigError naming the value and the choices
        if not (math.isfinite(self.minutes) and 0 < self.minutes <= 600):
            raise ConfigError(f"minutes={self.minutes!r}; expected a number in (0, 600]")
        if self.speed is not None and not (math.isfinite(self.speed) and self.speed > 0):
            raise ConfigError(f"speed={self.speed!r}; expected 'max' or a positive factor")
        if not (math.isfinite(self.warmup_s) and self.warmup_s >= 0):
            raise ConfigError(f"warmup_s={self.warmup_s!r}; expected >= 0 s")
        if self.refit not in ("at_proposal", "ahead"):
            raise ConfigError(f"refit={self.refit!r}; expected 'at_proposal' or 'ahead'")


@dataclass(frozen=True)
class SimEvaluation:
    """An evaluation with its place on the session clock (seconds since the session began)."""

    evaluation: Evaluation
    t_start: float
    t_end: float

    def to_json(self) -> dict[str, Any]:
        """The summary.json entry."""
        e = self.evaluation
        return {"index": e.index, "params": e.params, "mean": e.mean, "var": e.var,
                "breaths": e.breaths, "stopped_early": e.stopped_early, "reason": e.reason,
                "phase": e.phase, "t_start": self.t_start, "t_end": self.t_end}


class _Clock:
    """Paces the loop at ``speed`` × real time (or not at all) against breath time."""

    def __init__(self, speed: float | None) -> None:
        self.speed = speed
        self._wall0 = time.monotonic()
        self._sim0: float | None = None

    def wait_until(self, t_sim: float) -> None:
        if self.speed is None:
            return
        if self._sim0 is None:
            self._sim0 = t_sim
        due = self._wall0 + (t_sim - self._sim0) / self.speed
        delay = due - time.monotonic()
        if delay > 0:
            time.sleep(delay)


def run_insim(
    cfg: SimConfig, on_evaluation: Callable[[SimEvaluation, HILOptimizer], None] | None = None,
) -> dict[str, Any]:
    """Run a whole simulated session and return the summary (the summary.json content).

    Args:
        cfg: The session.
        on_evaluation: Called after every completed evaluation (progress display).

    Raises:
        ConfigError: The session is too short for the warm-ups and the exploration bout.
    """
    wall0 = time.perf_counter()
    space = presets.preset(cfg.preset)
    wearer = make_wearer(cfg.wearer, space, seed=cfg.seed)
    opt = HILOptimizer(space, n_explore=cfg.n_explore, max_breaths=cfg.max_breaths,
                       window=cfg.window, stopping=cfg.stopping, seed=cfg.seed,
                       refit_lag=1 if cfg.refit == "ahead" else 0)
    clock = _Clock(cfg.speed)
    session_s = cfg.minutes * 60.0
    records: list[SimEvaluation] = []
    n_breaths = 0

    def warm_up(until_s: float) -> None:
        wearer.apply_profiles((), wearer.t_s)
        while wearer.t_s < until_s:
            clock.wait_until(wearer.next_breath().t_s)

    warm_up(cfg.warmup_s)
    optimisation_started = False
    while not opt.done:
        if not optimisation_started and len(opt.evaluations) == cfg.n_explore:
            # Second bout: warm-up, then the rest of the session is the optimisation budget.
            warm_up(wearer.t_s + cfg.warmup_s)
            remaining = session_s - wearer.t_s
            if remaining <= 0:
                raise ConfigError(
                    f"minutes={cfg.minutes:g} leaves no time for optimisation after the warm-ups "
                    f"and exploration ({wearer.t_s / 60:.1f} min); give more minutes"
                )
            opt.set_budget(budget_s=remaining, budget_breaths=None)
            optimisation_started = True
        params = opt.ask()
        if cfg.refit == "ahead":  # what the bridge's worker does while this setting is measured
            fit = opt.hyperparameter_fit()
            if fit is not None:
                opt.apply_hyperparameters(fit, fit_hyperparameters(fit))
        t0 = wearer.t_s
        wearer.apply_params(params, t0)
        while True:
            breath = wearer.next_breath()
            clock.wait_until(breath.t_s)
            n_breaths += 1
            step = opt.observe_breath(breath.t_s - t0, brockway_watts(breath.vo2_ml_min, breath.vco2_ml_min))
            if step.stop:
                break
        assert step.evaluation is not None
        rec = SimEvaluation(step.evaluation, t0, breath.t_s)
        records.append(rec)
        if on_evaluation is not None:
            on_evaluation(rec, opt)

    best_params, best_mean, best_var = opt.best()
    opt_params, opt_cost = wearer.true_optimum
    true_best = wearer.true_cost_w(best_params)
    baseline = wearer.baseline_cost_w
    return {
        "n_evaluations": len(records),
        "n_early_stops": sum(r.evaluation.stopped_early for r in records),
        "n_breaths": n_breaths,
        "evaluations": [r.to_json() for r in records],
        "best_params": best_params,
        "best_mean": best_mean,
        "best_var": best_var,
        "true_optimum": {"params": opt_params, "cost_w": opt_cost},
        "true_cost_of_best": true_best,
        "regret_w": true_best - opt_cost,
        "regret_pct_of_reduction": 100.0 * (true_best - opt_cost) / max(baseline - opt_cost, 1e-9),
        "baseline_cost_w": baseline,
        "subject": wearer.subject,
        "session_minutes": wearer.t_s / 60.0,
        "thresholds": None if opt.thresholds is None else opt.thresholds.tolist(),
        "config": {"minutes": cfg.minutes, "seed": cfg.seed, "preset": cfg.preset,
                   "n_explore": cfg.n_explore, "max_breaths": cfg.max_breaths,
                   "window": cfg.window, "warmup_s": cfg.warmup_s, "stopping": cfg.stopping,
                   "wearer": cfg.wearer,
                   "speed": "max" if cfg.speed is None else cfg.speed},
        "wall_time_s": time.perf_counter() - wall0,
    }
