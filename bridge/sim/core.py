"""In-process simulated session: HILOptimizer driven breath by breath by the simulated wearer.

This is what ``hilbo sim`` runs until the asyncio bridge drives the virtual devices over real
transports. The protocol follows Kim et al. 2019 §IV.A.3: a first bout with a warm-up and the
exploration points, then a second bout with a warm-up and Bayesian optimisation until the
session's minutes are used up. Time is the wearer's breath clock, so a 60-minute session runs
as fast as the computer allows (``speed="max"``) or paced at a multiple of real time.

The loop is :func:`hilbo_core.protocol.drive` (the one :class:`~hilbo_core.protocol.SessionProtocol`
loop of the simulations): ``minutes`` is the whole session, both bouts and both warm-ups, in
walking time; the session ends at the first breath at or past it (it overruns by less than one
breath), and the evaluation running then is closed with its breaths (reason ``"budget"``).
"""

from __future__ import annotations

import logging
import math
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

from hilbo_core import HILOptimizer, brockway_watts, fit_hyperparameters, presets
from hilbo_core.errors import ConfigError
from hilbo_core.optimizer import BreathStep, Evaluation, OptimizerConfig
from hilbo_core.protocol import ProtocolKind, SessionProtocol, SessionProtocolConfig, drive, protocol_preset
from virtual_hw.wearer import WearerKind, make_wearer, wearer_kind

__all__ = ["SimConfig", "SimEvaluation", "check_optimisation_ran", "run_insim"]

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class SimConfig:
    """A simulated session.

    Attributes:
        minutes: Whole session length in minutes of walking (both bouts, warm-ups included).
        seed: Seeds the wearer (the subject) and the optimizer.
        speed: ``None`` for as fast as possible, else the real-time factor (1 = real time).
        preset: Parameter-space preset name.
        n_explore: Exploration points; None: the protocol's (fast 3, seed 6).
        max_breaths: N, the maximum breaths per evaluation.
        window: Algorithm 2's window W.
        warmup_s: Warm-up at the start of each bout, without assistance (seed: 3 min).
        stopping: ``"sound"`` (the default rule), ``"sound-floor"`` (it on a fixed 60 s clock, the
            earlier default), ``"adaptive"`` (Kim et al. 2019's Algorithm 1/2) or ``"fixed"``.
        refit: ``"at_proposal"`` (GP hyperparameters refitted in every proposal) or ``"ahead"``
            (as the bridge does by default: fitted on the completed evaluations while the next
            setting is measured, ``refit_lag`` 1).
        wearer: The simulated wearer (:class:`virtual_hw.wearer.WearerKind` value): ``realistic``
            (default), ``noisy`` or ``legacy``.
        protocol: The walking protocol (:class:`hilbo_core.protocol.ProtocolKind` value):
            ``fast`` (one warm-up, 3 exploration settings, the recommendation confirmed in the
            last minutes) or ``seed`` (Kim et al. 2019's); None (default): ``fast`` with the
            sound rule, ``seed`` with the seed's rules (as ``[protocol] protocol``).
        options: Further :class:`~hilbo_core.optimizer.OptimizerConfig` fields (benchmark
            variants), applied after the protocol's.
        protocol_options: Further :class:`~hilbo_core.protocol.SessionProtocolConfig` fields
            (benchmark variants), applied after the protocol's.
    """

    minutes: float = 60.0
    seed: int = 1
    speed: float | None = None
    preset: str = "hip_6d"
    n_explore: int | None = None
    max_breaths: int = OptimizerConfig.max_breaths
    window: int = OptimizerConfig.window
    warmup_s: float = SessionProtocolConfig.warmup_s
    stopping: str = "sound"
    refit: str = "at_proposal"
    wearer: str = WearerKind.REALISTIC.value
    protocol: str | None = None
    options: tuple[tuple[str, Any], ...] = ()
    protocol_options: tuple[tuple[str, Any], ...] = ()

    def __post_init__(self) -> None:
        wearer_kind(self.wearer)  # raises ConfigError naming the value and the choices
        if self.protocol is not None:
            protocol_preset(self.protocol)  # the same for the protocol's name
        if not (math.isfinite(self.minutes) and 0 < self.minutes <= 600):
            raise ConfigError(f"minutes={self.minutes!r}; expected a number in (0, 600]")
        if self.speed is not None and not (math.isfinite(self.speed) and self.speed > 0):
            raise ConfigError(f"speed={self.speed!r}; expected 'max' or a positive factor")
        if not (math.isfinite(self.warmup_s) and self.warmup_s >= 0):
            raise ConfigError(f"warmup_s={self.warmup_s!r}; expected >= 0 s")
        if self.refit not in ("at_proposal", "ahead"):
            raise ConfigError(f"refit={self.refit!r}; expected 'at_proposal' or 'ahead'")

    def protocol_config(self) -> SessionProtocolConfig:
        """The session's protocol: ``minutes`` of walking in all, no pause between the bouts."""
        named, _ = protocol_preset(self.walking_protocol)
        fields: dict[str, Any] = {
            **named, "warmup_s": self.warmup_s, "max_breaths": self.max_breaths,
            "session_s": self.minutes * 60.0, "budget_s": None, "pause_between_bouts": False,
            "n_explore": self.explore_points, **dict(self.protocol_options)}
        return SessionProtocolConfig(**fields)

    @property
    def walking_protocol(self) -> ProtocolKind:
        """``protocol``, else ``fast`` with the sound rule and ``seed`` with the seed's rules."""
        if self.protocol is not None:
            return ProtocolKind(self.protocol)
        return ProtocolKind.FAST if self.stopping in ("sound", "sound-floor") else ProtocolKind.SEED

    @property
    def budget_min(self) -> float:
        """The minutes the session leaves for optimisation (:func:`optimisation_minutes`)."""
        return optimisation_minutes(self.minutes, self.walking_protocol, self.explore_points,
                                    self.max_breaths, self.warmup_s)

    @property
    def explore_points(self) -> int:
        """``n_explore``, else the protocol's."""
        if self.n_explore is not None:
            return self.n_explore
        return int(protocol_preset(self.walking_protocol)[1]["n_explore"])

    def optimizer_config(self) -> OptimizerConfig:
        """The session's optimizer: no budget of its own (the protocol ends the session)."""
        fields: dict[str, Any] = {
            **protocol_preset(self.walking_protocol)[1], "n_explore": self.explore_points,
            "max_breaths": self.max_breaths, "window": self.window, "stopping": self.stopping,
            "seed": self.seed, "refit_lag": 1 if self.refit == "ahead" else 0, **dict(self.options)}
        return OptimizerConfig(**fields)


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


_MEAN_BREATH_S = 3.0  # the simulated wearers' mean breath interval, for the estimate below


def optimisation_minutes(minutes: float, protocol: ProtocolKind, n_explore: int, max_breaths: int,
                         warmup_s: float) -> float:
    """What a simulated session of ``minutes`` leaves for optimisation after its warm-ups and its
    exploration bout (about ``n_explore``·N breaths of ~3 s), in minutes; checked before a
    simulation starts (:func:`check_optimisation_ran` says it afterwards, exactly).

    Raises:
        ConfigError: Less than a minute is left.
    """
    named, _ = protocol_preset(protocol)
    explore_s = n_explore * max_breaths * _MEAN_BREATH_S
    warm_ups = 2 if named["pause_between_bouts"] or named["warmup_without_pause"] else 1
    left_s = minutes * 60.0 - warm_ups * warmup_s - explore_s
    if left_s < 60.0:
        need = math.ceil((warm_ups * warmup_s + explore_s + 60.0) / 60.0)
        raise ConfigError(
            f"minutes={minutes:g} leaves {max(left_s, 0) / 60:.1f} min for optimisation after "
            f"the warm-ups and the exploration bout (~{explore_s / 60:.0f} min); give at least "
            f"{need} minutes"
        )
    return left_s / 60.0


def check_optimisation_ran(protocol: SessionProtocol, minutes: float) -> None:
    """Raise when the session's minutes ended before the optimisation bout could begin.

    Raises:
        ConfigError: The session is too short for the warm-ups and the exploration bout.
    """
    if not protocol.optimization_started:
        raise ConfigError(
            f"minutes={minutes:g} leaves no time for optimisation: the warm-ups and the exploration "
            f"bout ({protocol.n_explored} of {protocol.config.n_explore} settings measured) used "
            f"all {protocol.walking.session_s / 60:.1f} min; give more minutes"
        )


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
    # No budget of the optimizer's own: the protocol ends the session on walking time.
    opt = HILOptimizer(space, config=cfg.optimizer_config())
    protocol = SessionProtocol(cfg.protocol_config(), t_start_s=wearer.t_s)
    clock = _Clock(cfg.speed)
    records: list[SimEvaluation] = []
    n_breaths = 0

    def next_breath() -> tuple[float, float]:
        breath = wearer.next_breath()
        clock.wait_until(breath.t_s)
        return breath.t_s, brockway_watts(breath.vo2_ml_min, breath.vco2_ml_min)

    def apply_setting(params: Mapping[str, float] | None, t_s: float) -> None:
        if params is None:
            wearer.apply_profiles((), t_s)
        else:
            wearer.apply_params(params, t_s)

    def on_propose(params: dict[str, float]) -> None:
        if cfg.refit == "ahead":  # what the bridge's worker does while this setting is measured
            fit = opt.hyperparameter_fit()
            if fit is not None:
                opt.apply_hyperparameters(fit, fit_hyperparameters(fit))

    def on_measure(step: BreathStep, t_setting_s: float, watts: float) -> None:
        nonlocal n_breaths
        n_breaths += 1

    def record(ev: Evaluation, t_start: float, t_end: float) -> None:
        rec = SimEvaluation(ev, t_start, t_end)
        records.append(rec)
        if on_evaluation is not None:
            on_evaluation(rec, opt)

    drive(protocol, opt, next_breath, apply_setting, on_propose=on_propose, on_measure=on_measure,
          on_evaluation=record)
    check_optimisation_ran(protocol, cfg.minutes)

    best_params, best_mean, best_var = opt.best()
    opt_params, opt_cost = wearer.true_optimum
    true_best = wearer.true_cost_w(best_params)
    baseline = wearer.baseline_cost_w
    conf = opt.confirmation
    return {
        "n_evaluations": len(records),
        "n_early_stops": sum(r.evaluation.stopped_early for r in records),
        "n_breaths": n_breaths,
        "evaluations": [r.to_json() for r in records],
        "best_params": best_params,
        "best_mean": best_mean,
        "best_var": best_var,
        # The recommendation's cost on the breath clock at the end (adaptation included): what
        # its reported estimate (best_mean, measured in the confirmation) is an estimate of.
        "true_cost_of_best_at_end": wearer.true_cost_w(best_params, wearer.t_s),
        "confirmation": None if conf is None else conf.to_json(),
        "t_first_proposal_s": next((r.t_start for r in records if r.evaluation.phase == "optimization"),
                                   None),
        "true_optimum": {"params": opt_params, "cost_w": opt_cost},
        "true_cost_of_best": true_best,
        "regret_w": true_best - opt_cost,
        "regret_pct_of_reduction": 100.0 * (true_best - opt_cost) / max(baseline - opt_cost, 1e-9),
        "baseline_cost_w": baseline,
        "subject": wearer.subject,
        "session_minutes": wearer.t_s / 60.0,
        "walking": protocol.walking.to_json(),
        "end_reason": None if protocol.end_reason is None else protocol.end_reason.value,
        "thresholds": None if opt.thresholds is None else opt.thresholds.tolist(),
        "config": {"minutes": cfg.minutes, "seed": cfg.seed, "preset": cfg.preset,
                   "n_explore": cfg.explore_points, "max_breaths": cfg.max_breaths,
                   "window": cfg.window, "warmup_s": cfg.warmup_s, "stopping": cfg.stopping,
                   "wearer": cfg.wearer, "protocol": cfg.walking_protocol.value,
                   "speed": "max" if cfg.speed is None else cfg.speed},
        "wall_time_s": time.perf_counter() - wall0,
    }
