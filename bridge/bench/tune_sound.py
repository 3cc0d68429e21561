"""Tune the sound stopping rule's constants offline with BO-RESAMPLE.

:class:`~hilbo_core.stopping.SoundRule` has two constants: ``min_decision_s`` (no decision
before this many seconds in a setting) and ``a_floor`` (the floor of Algorithm 2's thresholds, in
σ). The project's targets for the rule are constraints, not a trade-off weight: use as few breaths as possible
while rejecting ≤ 10 % of truly better candidates and ending ≤ 5 % of evaluations within 30 s.
The tuner therefore minimises a *penalised* cost (:func:`sound_cost`)::

    breaths / N  +  penalty · (max(0, rejected_better − 0.10) + max(0, ended_30s − 0.05))

on off-policy replays of full-length breath trajectories (Antonova 2016 §4.2, as
:mod:`bridge.bench.tune_stopping` does for K and W): trajectory j's running estimate is compared
with every other trajectory k's final estimate as the incumbent. "Truly better" is j's true cost
below k's when the trajectories come from a simulated wearer (``truth``), else j's final estimate
at most k's. Algorithm 2's schedule of trajectory j is built from ``n_explore`` *other*
trajectories (a session's exploration bout), as in ``tune_stopping``.

What the replay leaves out: in a session the sound rule watches the data-only estimate fused with
the GP's predictive at x_t, and the incumbent is the GP posterior at x*; offline both are the
estimator's data-only estimates. The tuned constants are therefore checked in whole sessions on
held-out subjects (docs/results.md, "Stopping on pairs" and its git history).

:func:`realistic_trajectories` draws the training trajectories from the realistic wearer
(:class:`bridge.sim.devices.RealisticWearerConfig`): random feasible settings, one after another,
N breaths each, so every trajectory starts from the previous setting's level as a session's would.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from bridge.bench.traces import BreathTrace, breath_traces, exploration_groups, threshold_schedules
from hilbo_core.errors import ConfigError
from hilbo_core.estimation import TransitionEstimator
from hilbo_core.metabolic import Estimator, brockway_watts
from hilbo_core.resample import ResampleConfig, Trajectory, bo_resample
from hilbo_core.space import Parameter, ParameterSpace

__all__ = ["SoundReplay", "TuneSoundConfig", "realistic_trajectories", "sound_cost", "tune_sound"]


@dataclass(frozen=True)
class TuneSoundConfig:
    """Options of :func:`tune_sound`.

    Attributes:
        n_max: N, breaths of a full evaluation.
        window: Algorithm 2's window W of the schedule the floor applies to.
        n_explore: Trajectories behind each trajectory's Algorithm 2 schedule.
        min_decision_bounds: Search interval of ``min_decision_s`` (s).
        a_floor_bounds: Search interval of ``a_floor`` (σ).
        max_rejected_better: Target fraction of truly better candidates stopped early.
        max_ended_30s: Target fraction of evaluations that end within 30 s.
        penalty: Weight of a target's excess, in evaluations' time per unit fraction.
        n_real: BO-RESAMPLE's real episodes.
        n_resamples: Resamples per real episode.
        max_reuse: Resamples allowed per trajectory.
        grid_min_decision_s: ``min_decision_s`` values of the exhaustive check.
        grid_a_floor: ``a_floor`` values of the exhaustive check.
        seed: Seeds episodes and BO.
    """

    n_max: int = 45
    window: int = 2
    n_explore: int = 6
    min_decision_bounds: tuple[float, float] = (20.0, 120.0)
    a_floor_bounds: tuple[float, float] = (0.0, 2.0)
    max_rejected_better: float = 0.10
    max_ended_30s: float = 0.05
    penalty: float = 10.0
    n_real: int = 40
    n_resamples: int = 3
    max_reuse: int = 5
    grid_min_decision_s: tuple[float, ...] = (30.0, 45.0, 60.0, 75.0, 90.0)
    grid_a_floor: tuple[float, ...] = (0.0, 0.25, 0.5, 0.75, 1.0, 1.25, 1.5)
    seed: int = 0

    def __post_init__(self) -> None:
        for name, low in (("n_max", 2), ("window", 0), ("n_explore", 1), ("n_real", 1),
                          ("n_resamples", 0), ("max_reuse", 0), ("seed", 0)):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < low:
                raise ConfigError(f"{name}={v!r}; expected an integer >= {low}")
        for name in ("min_decision_bounds", "a_floor_bounds"):
            lo, hi = (float(b) for b in getattr(self, name))
            if not (math.isfinite(lo) and math.isfinite(hi) and 0.0 <= lo < hi):
                raise ConfigError(f"{name}={getattr(self, name)!r}; expected finite 0 <= low < high")
        for name in ("max_rejected_better", "max_ended_30s", "penalty"):
            v = float(getattr(self, name))
            if not (math.isfinite(v) and v >= 0.0):
                raise ConfigError(f"{name}={v!r}; expected a finite number >= 0")


class SoundReplay:
    """The sound rule replayed on every ordered pair of full-length traces.

    Args:
        traces: Full-length running estimates (:func:`bridge.bench.traces.breath_traces`).
        times: Per trace, the breath times since the setting began (s), shape (N,).
        schedules: Algorithm 2's schedule per trace, shape (n, N).
        truth: True cost per trace (W), or None to judge "better" by the final estimates.
        pairs: Which ordered pairs count, ``pairs[j, k]`` for candidate j against incumbent k,
            shape (n, n) (the diagonal is never used), or None for every pair.
    """

    def __init__(self, traces: Sequence[BreathTrace], times: Sequence[np.ndarray], schedules: np.ndarray,
                 truth: Sequence[float] | None = None, pairs: np.ndarray | None = None) -> None:
        if len(traces) < 2 or len(times) != len(traces) or len(schedules) != len(traces):
            raise ConfigError(f"need >= 2 traces with one time array and schedule each, got "
                              f"{len(traces)}, {len(times)}, {len(schedules)}")
        self.means = np.array([t.means for t in traces])
        self.vars = np.array([t.vars for t in traces])
        self.times = np.array([np.asarray(t, dtype=float) for t in times])
        self.schedules = np.asarray(schedules, dtype=float)
        finals = self.means[:, -1] if truth is None else np.asarray(truth, dtype=float)
        if finals.shape != (len(traces),):
            raise ConfigError(f"truth has shape {finals.shape}; expected ({len(traces)},)")
        n = len(traces)
        # better[j, k]: candidate j is truly better than incumbent k (the diagonal is never used).
        self.better = finals[:, None] < finals[None, :] if truth is not None \
            else finals[:, None] <= finals[None, :]
        self.n, self.N = n, self.means.shape[1]
        self.pairs = np.ones((n, n), dtype=bool) if pairs is None else np.asarray(pairs, dtype=bool)
        if self.pairs.shape != (n, n):
            raise ConfigError(f"pairs has shape {self.pairs.shape}; expected ({n}, {n})")

    def outcomes(self, j: int, min_decision_s: float, a_floor: float, accept_z: float | None = None,
                 boundary_s: float | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Trajectory j against every incumbent k: (breaths used, N if never stopped; whether
        the stop was a rejection by the threshold), both shape (n,).

        With ``accept_z`` the rule also ends an evaluation the other way once μ < −accept_z·σ
        (:class:`~hilbo_core.stopping.SoundRule`'s DECIDED stop; not a rejection). With
        ``boundary_s`` both margins are scaled by SoundRule's sequential factor
        sqrt(max(1, boundary_s / t)).
        """
        t = self.times[j][None, :-1]
        late = t >= min_decision_s
        scale = np.ones_like(t)
        if boundary_s is not None:
            with np.errstate(divide="ignore"):
                scale = np.sqrt(np.maximum(1.0, boundary_s / t))
            late &= np.isfinite(scale)
        floor = a_floor * scale if math.isfinite(a_floor) else np.full_like(t, a_floor)
        a = np.maximum(self.schedules[j][None, :-1], floor)
        mu = self.means[j][None, :-1] - self.means[:, -1][:, None]
        sigma = np.sqrt(self.vars[j][None, :-1] + self.vars[:, -1][:, None])
        reject = (mu > a * sigma) & late
        hit = (reject | ((mu < -accept_z * scale * sigma) & late)) if accept_z is not None else reject
        stopped = hit.any(axis=1)
        first = np.where(stopped, hit.argmax(axis=1) + 1, self.N)
        rejected = stopped & reject[np.arange(self.n), np.where(stopped, first - 1, 0)]
        return first, rejected

    def steps(self, j: int, min_decision_s: float, a_floor: float, accept_z: float | None = None,
              boundary_s: float | None = None) -> np.ndarray:
        """Breaths trajectory j uses against every incumbent k (N if never stopped), shape (n,)."""
        return self.outcomes(j, min_decision_s, a_floor, accept_z, boundary_s)[0]

    def stats(self, min_decision_s: float, a_floor: float, js: Sequence[int] | None = None,
              accept_z: float | None = None, boundary_s: float | None = None) -> dict[str, float]:
        """Pooled replay statistics over the pairs (j, k ≠ j, ``pairs[j, k]``) for j in ``js``
        (default all).

        ``a_floor`` may be ``-inf`` (Algorithm 2's schedule unfloored: Kim et al. 2019's rule, with
        ``min_decision_s`` 0). Rates, and the counts behind them (``n_pairs``,
        ``breaths_total``, ``n_early`` (every stop before N, rejections and accept stops),
        ``n_ended_30s``, ``n_better``, ``n_rejected_better``, ``n_better_above_at_n``: truly
        better candidates whose N-breath estimate is above the incumbent's, the measurement's
        own error) so that replays can be pooled.
        """
        used, end30, rej, nbetter, above = [], [], 0, 0, 0
        final = self.means[:, -1]
        for j in (range(self.n) if js is None else js):
            steps, rejected = self.outcomes(j, min_decision_s, a_floor, accept_z, boundary_s)
            keep = self.pairs[j].copy()
            keep[j] = False
            s = steps[keep]
            b = self.better[j][keep]
            used.append(s)
            end30.append(self.times[j][s - 1] < 30.0)
            rej += int((rejected[keep] & b).sum())
            nbetter += int(b.sum())
            above += int((b & (final[j] > final[keep])).sum())
        u = np.concatenate(used)
        if u.size == 0:
            raise ConfigError("no pair to replay: every pair was filtered out")
        n_end30 = int(np.concatenate(end30).sum())
        return {"mean_breaths": float(u.mean()), "breath_fraction": float(u.mean() / self.N),
                "early_stop_rate": float((u < self.N).mean()),
                "ended_30s": n_end30 / u.size,
                "rejected_better": rej / nbetter if nbetter else 0.0, "n_better": nbetter,
                "n_pairs": int(u.size), "breaths_total": int(u.sum()), "n_early": int((u < self.N).sum()),
                "n_ended_30s": n_end30, "n_rejected_better": rej, "n_better_above_at_n": above}


def sound_cost(stats: Mapping[str, float], config: TuneSoundConfig) -> float:
    """The penalised cost of replay statistics (module docstring)."""
    return (float(stats["breath_fraction"])
            + config.penalty * max(0.0, float(stats["rejected_better"]) - config.max_rejected_better)
            + config.penalty * max(0.0, float(stats["ended_30s"]) - config.max_ended_30s))


def tune_sound(trajectories: Sequence[Any], config: TuneSoundConfig | None = None, *,
               truth: Sequence[float] | None = None,
               estimator_factory: Callable[[], Estimator] = TransitionEstimator) -> dict[str, Any]:
    """Tune ``min_decision_s`` and ``a_floor`` with BO-RESAMPLE on the penalised cost.

    Args:
        trajectories: Per-evaluation breath arrays (n, 2) of ``(t_s since the setting began, W)``,
            each at least N breaths long.
        config: Options.
        truth: True cost of each trajectory's setting (W), or None.
        estimator_factory: The estimator the rule watches (default the optimizer's default).

    An episode's cost applies the penalty to that one trajectory's rates; since max(0, ·) is
    convex, the mean over episodes overstates the penalty of the pooled rates and pulls
    BO-RESAMPLE towards conservative constants (measured: docs/results.md's git history,
    "Tuning the sound rule's two constants offline"), so compare its recommendation with
    ``grid_best``, the pooled cost's minimum on the grid.

    Returns:
        JSON-able: ``recommended`` (BO-RESAMPLE's), its pooled ``recommended_stats``, the
        exhaustive ``grid`` with ``grid_best`` and the BO-RESAMPLE counts.

    Raises:
        ConfigError: Fewer than 3 trajectories of N breaths, or a short one when ``truth`` is given.
    """
    cfg = TuneSoundConfig() if config is None else config
    N = cfg.n_max
    traces, skipped = breath_traces(trajectories, N, estimator_factory)
    if len(traces) < 3 or (truth is not None and skipped):
        with_truth = " (all of them, with truth given)" if truth is not None else ""
        raise ConfigError(f"need >= 3 trajectories of >= {N} breaths{with_truth}, "
                          f"got {len(traces)} ({skipped} shorter)")
    times = [np.asarray(t, dtype=float)[:N, 0] for t in trajectories if len(t) >= N]
    groups = exploration_groups(len(traces), cfg.n_explore, cfg.seed)
    replay = SoundReplay(traces, times, threshold_schedules(traces, min(cfg.window, N - 1), groups), truth)
    space = ParameterSpace([Parameter("min_decision_s", *cfg.min_decision_bounds, "s", "no decision before"),
                            Parameter("a_floor", *cfg.a_floor_bounds, "σ", "threshold floor")],
                           name="sound_rule")
    order: list[int] = []

    def execute(params: dict[str, float], rng: np.random.Generator) -> Trajectory:
        if not order:
            order.extend(int(i) for i in rng.permutation(replay.n))
        j = order.pop()
        return Trajectory(tuple(range(N)), N, {"trace": j})

    def halt(params: Mapping[str, float], prefix: Sequence[Any], ctx: Mapping[str, Any]) -> bool:
        s = replay.steps(ctx["trace"], params["min_decision_s"], params["a_floor"])
        return len(prefix) >= int(np.delete(s, ctx["trace"]).max())

    def objective(obs: Sequence[Any], s: int, ctx: Mapping[str, Any], params: Mapping[str, float]) -> float:
        return sound_cost(replay.stats(params["min_decision_s"], params["a_floor"], [ctx["trace"]]), cfg)

    rcfg = ResampleConfig(n_resamples=cfg.n_resamples, max_reuse=cfg.max_reuse, n_init=4,
                          n_candidates=256, n_local=1)
    run = bo_resample(space, execute, halt, objective, n_real=cfg.n_real,
                      rng=np.random.default_rng(cfg.seed), config=rcfg)
    best = {k: float(v) for k, v in run.recommendations[-1].items()}
    grid = []
    for m in cfg.grid_min_decision_s:
        for a in cfg.grid_a_floor:
            st = replay.stats(m, a)
            grid.append({"min_decision_s": m, "a_floor": a, "cost": sound_cost(st, cfg), **st})
    rec_stats = replay.stats(best["min_decision_s"], best["a_floor"])
    return {
        "config": asdict(cfg), "n_trajectories": replay.n, "recommended": best,
        "recommended_stats": rec_stats | {"cost": sound_cost(rec_stats, cfg)},
        "grid_best": min(grid, key=lambda g: g["cost"]), "grid": grid,
        "bo_resample": {"n_real": run.n_real, "n_simulated": run.n_simulated},
    }


def realistic_trajectories(space: ParameterSpace, seed: int, n_settings: int, n_max: int = 45
                           ) -> tuple[list[np.ndarray], list[float]]:
    """Full-length breath trajectories of random settings on one realistic wearer.

    Args:
        space: The parameter space (e.g. ``preset("hip_6d")``).
        seed: The wearer (subject) seed; also seeds the settings.
        n_settings: Settings, applied one after another (each starts from the previous level).
        n_max: Breaths per setting.

    Returns:
        (trajectories of ``(t_s since the setting began, W)``, true cost of each setting in W).
    """
    from bridge.sim.devices import make_wearer

    wearer = make_wearer("realistic", space, seed=seed)
    rng = np.random.default_rng([seed, 0x50D])
    xs = space.from_unit(space.sample_unit(n_settings, rng))
    trajs, truth = [], []
    t_last = float(wearer.t_s)
    for x in xs:
        params = space.to_dict(x)
        wearer.apply_params(params, t_last)
        rows = []
        for _ in range(n_max):
            b = wearer.next_breath()
            rows.append((b.t_s - t_last, float(brockway_watts(b.vo2_ml_min, b.vco2_ml_min))))
        t_last = b.t_s
        trajs.append(np.array(rows))
        truth.append(float(wearer.true_cost_w(params)))
    return trajs, truth
