"""``hilbo tune-stopping LOG.mcap…``: tune the estimator stopping rule offline with BO-RESAMPLE.

The σ-scaled offset rule of Kim et al. 2019 §II.D is itself an optimal-stopping policy: after breath i
of a setting it stops when ``μ_i − μ* > A_i·σ_i`` (σ_i² = var_i + σ*²). Its hyperparameter is
either a constant K (``A_i = K``; family ``k``) or Algorithm 2's window W (``A`` = the threshold
schedule of the given traces with window W; family ``window``). Every full-length breath
trajectory — an exploration bout, or an optimisation-phase evaluation that ran all N breaths —
can replay *any* rule that stops at or before N (Antonova 2016 §4.2), so BO-RESAMPLE
(:func:`hilbo_core.resample.bo_resample`) can search the hyperparameter with few "real"
episodes and many off-policy resamples.

An **episode** is one full-length trajectory j (drawn in random order, as a new evaluation's
breaths would arrive) compared, as the optimizer compares a new setting with its best one, with
every other trajectory k as the incumbent: the rule watches j's running UKF estimate (Kim et al. 2019
§II.C) against k's final estimate (μ*, σ*²) and stops after s_k breaths. Its cost, in units of
one full evaluation's walking time, is the mean over k of

    s_k / N  +  λ · I(s_k < N and μ_N(j) <= μ_N(k))

— the breaths used, plus λ for every *wrong early stop*: a setting stopped early although its
full-length estimate was no worse than the incumbent's (the error Algorithm 2 is built to avoid;
its own construction admits none on its exploration traces). λ (``--error-weight``, default 2)
says how many evaluations' time a wrongly discarded setting is worth; the tuned value depends
on it. Averaging over the incumbents inside an episode (rather than drawing one incumbent per
episode) keeps a single wrong stop from dominating the GP's view of a rule. Because every stored
trajectory is full length, every rule can be replayed on it; BO-RESAMPLE's bound on reuse is
what keeps the resampled episodes from being the same few trajectories over and over.

Besides the BO-RESAMPLE recommendation the result reports an exhaustive evaluation of a grid of
hyperparameters on *all* ordered pairs (cheap offline, and a check of what BO found) and the
same numbers for Algorithm 2's schedule with the session's window (W = 2 by default). Algorithm
2's schedules (the reference and the ``window`` family) are always out of sample: trajectory j is
judged with the schedule built from ``n_explore`` = 6 *other* trajectories, as a session builds it
from its own exploration bout and then applies it to new settings.

Logs are read with :func:`bridge.log.reader.read_log`: the ``/estimator`` channel holds every breath
the optimizer consumed (``t_setting_s``, ``watts``) by evaluation, ``/observations`` how many
breaths each evaluation kept.
"""

from __future__ import annotations

import argparse
import enum
import json
import logging
import math
import os
import sys
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from bridge.argtypes import nonnegative, nonnegative_int, positive_int, two_or_more
from bridge.bench.traces import BreathTrace, breath_traces, exploration_groups, threshold_schedules
from hilbo_core.errors import ConfigError
from hilbo_core.metabolic import Estimator, MetabolicUKF
from hilbo_core.resample import ResampleConfig, Trajectory, bo_resample
from hilbo_core.space import Parameter, ParameterSpace

if TYPE_CHECKING:
    from bridge.log.records import Evaluation

__all__ = [
    "BreathTrace",
    "StoppingFamily",
    "TuneStoppingConfig",
    "add_tune_stopping_parser",
    "breath_traces",
    "evaluate_schedule",
    "evaluations_from_log",
    "trajectories_from_log",
    "tune_stopping",
]

logger = logging.getLogger(__name__)


class StoppingFamily(enum.Enum):
    """Which hyperparameter of the σ-scaled rule is tuned."""

    CONSTANT_K = "k"  # A_i = K for every breath
    WINDOW = "window"  # A = Algorithm 2's schedule (threshold_schedule) with window W


@dataclass(frozen=True)
class TuneStoppingConfig:
    """Options of :func:`tune_stopping`.

    Attributes:
        family: :class:`StoppingFamily`.
        n_max: N, breaths of a full evaluation; shorter trajectories are skipped, longer ones cut.
        k_bounds: Search interval of K (in σ).
        max_window: Largest W searched (window family).
        error_weight: λ, the cost of a wrong early stop in evaluations' time.
        reference_window: W of Algorithm 2's schedule reported for comparison.
        n_explore: Traces behind each Algorithm 2 schedule: trace j is judged with the schedule
            of ``n_explore`` other traces (a session's exploration bout), never its own.
        n_real: Real episodes of BO-RESAMPLE.
        n_resamples: K of BO-RESAMPLE (resamples per real episode). Keep it below
            ``max_reuse``: with K >= max_reuse the older trajectories are soon used up and every
            resample of a round falls on the newest one, which the GP then sees K times over.
        max_reuse: Resamples allowed per trajectory.
        n_grid: Grid size of the exhaustive check (K family).
        seed: Seeds episodes and BO.
    """

    family: StoppingFamily = StoppingFamily.CONSTANT_K
    n_max: int = 45
    k_bounds: tuple[float, float] = (0.0, 4.0)
    max_window: int = 10
    error_weight: float = 2.0
    reference_window: int = 2
    n_explore: int = 6
    n_real: int = 60
    n_resamples: int = 3
    max_reuse: int = 5
    n_grid: int = 41
    seed: int = 0

    def __post_init__(self) -> None:
        try:
            object.__setattr__(self, "family", StoppingFamily(self.family))
        except ValueError as err:
            raise ConfigError(f"family={self.family!r}; expected one of "
                              f"{[f.value for f in StoppingFamily]}") from err
        for name, low in (("n_max", 2), ("max_window", 0), ("reference_window", 0), ("n_explore", 1),
                          ("n_real", 1), ("n_resamples", 0), ("max_reuse", 0), ("n_grid", 2),
                          ("seed", 0)):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < low:
                raise ConfigError(f"{name}={v!r}; expected an integer >= {low}")
        lo, hi = (float(b) for b in self.k_bounds)
        if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
            raise ConfigError(f"k_bounds={self.k_bounds!r}; expected finite low < high")
        if not (math.isfinite(self.error_weight) and self.error_weight >= 0):
            raise ConfigError(f"error_weight={self.error_weight!r}; expected a number >= 0")


def _stop_step(trace: BreathTrace, thresholds: np.ndarray, mu_star: float, var_star: float) -> int:
    """Breaths used by the σ-scaled rule on a trace against an incumbent (N if never early)."""
    sigma = np.sqrt(trace.vars + var_star)
    hits = np.flatnonzero(trace.means[:-1] - mu_star > thresholds[:-1] * sigma[:-1])
    return int(hits[0]) + 1 if hits.size else len(trace.means)


def evaluate_schedule(traces: Sequence[BreathTrace], thresholds: np.ndarray,
                      error_weight: float) -> dict[str, float]:
    """Exhaustive cost of a threshold schedule over every ordered pair (j, k ≠ j) of traces.

    Args:
        traces: Full-length traces.
        thresholds: One schedule (N,), or one per trace (n, N) (row j is used for trace j).
        error_weight: λ.

    Returns:
        ``{"cost", "breath_fraction", "early_stop_rate", "wrong_stop_rate"}`` (means over pairs;
        the wrong-stop rate is per pair, not per early stop).
    """
    n = len(traces)
    if n < 2:
        raise ConfigError(f"need at least 2 full-length trajectories, got {n}")
    N = len(traces[0].means)
    A = np.broadcast_to(np.asarray(thresholds, dtype=float), (n, N))
    used, early, wrong = [], [], []
    for j, tj in enumerate(traces):
        for k, tk in enumerate(traces):
            if j == k:
                continue
            s = _stop_step(tj, A[j], tk.final_mean, tk.final_var)
            used.append(s / N)
            early.append(s < N)
            wrong.append(s < N and tj.final_mean <= tk.final_mean)
    bf = float(np.mean(used))
    wr = float(np.mean(wrong))
    return {"cost": bf + error_weight * wr, "breath_fraction": bf,
            "early_stop_rate": float(np.mean(early)), "wrong_stop_rate": wr}


def _thresholds_fn(cfg: TuneStoppingConfig, traces: Sequence[BreathTrace], groups: np.ndarray
                   ) -> tuple[ParameterSpace, Callable[[Mapping[str, float]], np.ndarray]]:
    """The search space and params → per-trace threshold schedules (n, N)."""
    N = cfg.n_max
    n = len(traces)
    if cfg.family is StoppingFamily.CONSTANT_K:
        space = ParameterSpace([Parameter("k", *cfg.k_bounds, "σ", "constant threshold K")],
                               name="stopping_k")
        return space, lambda p: np.full((n, N), float(p["k"]))
    w_max = min(cfg.max_window, N - 1)
    schedules = [threshold_schedules(traces, w, groups) for w in range(w_max + 1)]
    space = ParameterSpace([Parameter("window", -0.5, w_max + 0.5, "breaths", "Algorithm 2 window W")],
                           name="stopping_window")
    return space, lambda p: schedules[int(np.clip(round(p["window"]), 0, w_max))]


def tune_stopping(trajectories: Sequence[Any], config: TuneStoppingConfig | None = None, *,
                  sources: Sequence[str] | None = None,
                  estimator_factory: Callable[[], Estimator] = MetabolicUKF) -> dict[str, Any]:
    """Tune K or W of the σ-scaled stopping rule with BO-RESAMPLE (module docstring).

    Args:
        trajectories: Per-evaluation breath arrays (n, 2) of ``(t_s since the setting began, W)``.
        config: Options.
        sources: Labels of the trajectories.
        estimator_factory: The estimator whose running estimate the rule watches.

    Returns:
        A JSON-able dict: the recommendation, its exhaustive cost, Algorithm 2's, the grid, the
        BO-RESAMPLE evaluations and counts.

    Raises:
        ConfigError: Fewer than 3 full-length trajectories.
        MeasurementError: A malformed trajectory.
    """
    cfg = TuneStoppingConfig() if config is None else config
    traces, skipped = breath_traces(trajectories, cfg.n_max, estimator_factory, sources)
    if len(traces) < 3:
        raise ConfigError(
            f"need at least 3 trajectories of >= {cfg.n_max} breaths, got {len(traces)} "
            f"({skipped} shorter ones skipped)"
        )
    groups = exploration_groups(len(traces), cfg.n_explore, cfg.seed)
    space, thresholds = _thresholds_fn(cfg, traces, groups)
    N = cfg.n_max
    lam = cfg.error_weight
    pool = [tuple(zip(t.means.tolist(), t.vars.tolist(), strict=True)) for t in traces]
    finals = np.array([[t.final_mean, t.final_var] for t in traces])
    order: list[int] = []

    def execute(params: dict[str, float], rng: np.random.Generator) -> Trajectory:
        # The next trajectory, in a random order without replacement (reshuffled when used up),
        # as a new evaluation's breaths would arrive.
        if not order:
            order.extend(int(i) for i in rng.permutation(len(traces)))
        j = order.pop()
        return Trajectory(pool[j], N, {"trace": j})

    def stop_steps(params: Mapping[str, float], j: int) -> np.ndarray:
        others = np.arange(len(traces)) != j
        a = thresholds(params)[j]
        return np.array([_stop_step(traces[j], a, m, v) for m, v in finals[others]])

    def halt(params: Mapping[str, float], prefix: Sequence[Any], ctx: Mapping[str, Any]) -> bool:
        # The episode is over once the rule has stopped against every incumbent (at N at the latest).
        return len(prefix) >= int(stop_steps(params, ctx["trace"]).max())

    def objective(obs: Sequence[Any], s: int, ctx: Mapping[str, Any], params: Mapping[str, float]) -> float:
        j = ctx["trace"]
        steps = stop_steps(params, j)
        others = np.arange(len(traces)) != j
        wrong = (steps < N) & (traces[j].final_mean <= finals[others, 0])
        return float(np.mean(steps / N + lam * wrong))

    rcfg = ResampleConfig(n_resamples=cfg.n_resamples, max_reuse=cfg.max_reuse, n_init=2,
                          n_candidates=128, n_local=1)
    run = bo_resample(space, execute, halt, objective, n_real=cfg.n_real,
                      rng=np.random.default_rng(cfg.seed), config=rcfg)
    best = run.recommendations[-1]
    if cfg.family is StoppingFamily.CONSTANT_K:
        grid_values = np.linspace(cfg.k_bounds[0], cfg.k_bounds[1], cfg.n_grid).tolist()
        key = "k"
    else:
        grid_values = list(range(min(cfg.max_window, N - 1) + 1))
        key = "window"
    grid = [{key: v, **evaluate_schedule(traces, thresholds({key: v}), lam)} for v in grid_values]
    alg2 = threshold_schedules(traces, min(cfg.reference_window, N - 1), groups)
    if key == "window":
        recommended: dict[str, float] = {key: int(np.clip(round(best[key]), 0, min(cfg.max_window, N - 1)))}
    else:
        recommended = {key: best[key]}
    return {
        "config": asdict(cfg) | {"family": cfg.family.value},
        "n_trajectories": len(traces),
        "n_skipped_short": skipped,
        "recommended": recommended,
        "recommended_exhaustive": evaluate_schedule(traces, thresholds(best), lam),
        "grid_best": min(grid, key=lambda g: g["cost"]),
        "algorithm2": {"window": cfg.reference_window, **evaluate_schedule(traces, alg2, lam)},
        "never_stop": evaluate_schedule(traces, np.full(N, np.inf), lam),
        "grid": grid,
        "bo_resample": {"n_real": run.n_real, "n_simulated": run.n_simulated,
                        "max_trajectory_uses": max(run.trajectory_uses, default=0),
                        "recommendations": run.recommendations,
                        "evaluations": [e.to_json() for e in run.evaluations]},
    }


# --------------------------------------------------------------------------------------------
# Log adapters (bridge.log.reader)
# --------------------------------------------------------------------------------------------


def evaluations_from_log(path: str | os.PathLike[str]) -> list[dict[str, Any]]:
    """The completed evaluations of a session log (``/observations``), as plain dicts.

    Suitable for :func:`hilbo_core.priors.priors_from_evaluations` (a previous session's prior).
    """
    import msgspec

    from bridge.log import Topic
    from bridge.log.reader import read_log

    records = read_log(path, topics=[Topic.OBSERVATIONS]).records(Topic.OBSERVATIONS)
    return [msgspec.to_builtins(r) for r in records]


def collect_trajectories(paths: Sequence[str | os.PathLike[str]]
                         ) -> tuple[list[np.ndarray], list[Evaluation], list[str], list[str]]:
    """Every completed evaluation of the given logs, each once.

    A session's evaluation is counted once however many files hold it: a resumed session's logs
    share its id, and ``hilbo log recover`` writes a copy beside the cut log (a shell glob
    catches both). A validation walk (``hilbo validate``) is left out: its conditions are no
    optimisation's candidates, and its unassisted one applies no setting.

    Returns:
        (trajectories, their ``/observations`` records, their sources ``file:evaluation k``,
        notes on what was left out).
    """
    from bridge.log import Topic
    from bridge.log.reader import read_log

    trajs: list[np.ndarray] = []
    evs: list[Evaluation] = []
    sources: list[str] = []
    notes: list[str] = []
    seen: set[tuple[str, int]] = set()
    for path in paths:
        head = read_log(path, topics=[Topic.EVENTS])
        if any(e.kind == "validation_plan" for e in head.records(Topic.EVENTS)):
            notes.append(f"{Path(path).name}: a validation walk, left out")
            continue
        sid = head.session_id or str(path)
        t, e = trajectories_from_log(path)
        dup = 0
        for traj, ev in zip(t, e, strict=True):
            if (sid, ev.index) in seen:
                dup += 1
                continue
            seen.add((sid, ev.index))
            trajs.append(traj)
            evs.append(ev)
            sources.append(f"{Path(path).name}:evaluation {ev.index}")
        if dup:
            notes.append(f"{Path(path).name}: {dup} evaluation(s) of session {sid} already read from "
                         "another file (a recovered copy or a second listing), counted once")
    return trajs, evs, sources, notes


def trajectories_from_log(path: str | os.PathLike[str]) -> tuple[list[np.ndarray], list[Evaluation]]:
    """Breath trajectories ``(t_setting_s, watts)`` of every completed evaluation of a log.

    The breaths come from ``/estimator`` (what the optimizer consumed). An evaluation index that
    was cancelled and asked again restarts at breath 0, so the breaths after its last restart are
    used, and only as many as ``/observations`` says the evaluation kept.

    Returns:
        (trajectories, their ``/observations`` records), in evaluation order.
    """
    from bridge.log import Topic
    from bridge.log.reader import read_log

    log = read_log(path, topics=[Topic.ESTIMATOR, Topic.OBSERVATIONS])
    by_index: dict[int, list[tuple[float, float]]] = {}
    for est in log.records(Topic.ESTIMATOR):
        if est.breath == 0:
            by_index[est.index] = []
        by_index.setdefault(est.index, []).append((est.t_setting_s, est.watts))
    trajs, evs = [], []
    for ev in log.records(Topic.OBSERVATIONS):
        breaths = by_index.get(ev.index, [])
        n = ev.breaths or len(breaths)
        if len(breaths) >= n > 0:
            trajs.append(np.array(breaths[:n], dtype=float))
            evs.append(ev)
    return trajs, evs


def _n_max_from(evs: Iterable[Evaluation]) -> int | None:
    full = [e.breaths for e in evs if e.reason == "max_measurements"]
    return max(set(full), key=full.count) if full else None


def _cmd_tune_stopping(args: argparse.Namespace) -> int:
    from rich.console import Console

    from bridge.config import check_out_dir

    console = Console(stderr=True, markup=False, highlight=False, soft_wrap=True)
    if args.out and Path(args.out).is_dir():  # refused before the tuning, not after it
        raise ConfigError(f"--out {args.out!r} is a directory; expected the name of the JSON file "
                          "to write (e.g. tuned.json)")
    if args.out:
        check_out_dir(Path(args.out).parent, "--out's folder")
    trajs, evs, sources, notes = collect_trajectories(args.logs)
    for note in notes:
        console.print(f"hilbo tune-stopping: note: {note}")
    n_max = args.n_max if args.n_max is not None else (_n_max_from(evs) or 45)
    if args.family == SOUND_FAMILY:
        return _tune_sound_cmd(args, console, trajs, n_max)
    cfg = TuneStoppingConfig(family=StoppingFamily(args.family), n_max=n_max,
                             error_weight=args.error_weight, n_real=args.real,
                             n_resamples=args.resamples, max_reuse=args.max_reuse, seed=args.seed,
                             reference_window=args.window)
    console.print(f"hilbo tune-stopping: {len(trajs)} evaluations from {len(args.logs)} log(s), N = {n_max}")
    result = tune_stopping(trajs, cfg, sources=sources)
    rec = result["recommended_exhaustive"]
    alg2 = result["algorithm2"]
    bo = result["bo_resample"]
    console.print(f"{result['n_trajectories']} full-length trajectories "
                  f"({result['n_skipped_short']} shorter skipped); BO-RESAMPLE: {bo['n_real']} real + "
                  f"{bo['n_simulated']} resampled episodes")
    for label, r in ((f"recommended {result['recommended']}", rec),
                     (f"Algorithm 2 (W = {alg2['window']})", alg2)):
        console.print(f"{label}: cost {r['cost']:.3f} (breaths {100 * r['breath_fraction']:.0f} %, "
                      f"wrong stops {100 * r['wrong_stop_rate']:.1f} % of pairs)")
    if rec["cost"] > alg2["cost"]:
        console.print(f"hilbo tune-stopping: warning: the recommendation's cost on these data "
                      f"({rec['cost']:.3f}) is above Algorithm 2's ({alg2['cost']:.3f}): BO-RESAMPLE's "
                      f"episodes did not find better constants in {result['n_trajectories']} "
                      "trajectories; keep the current rule or give more sessions")
    _write_result(args, result)
    return 0


# The sound rule (hilbo's default) is tuned by bridge.bench.tune_sound: its two constants, not K or W.
SOUND_FAMILY = "sound"


def _tune_sound_cmd(args: argparse.Namespace, console: Any, trajs: list[np.ndarray], n_max: int) -> int:
    """``--family sound``: the sound rule's ``min_decision_s`` and ``a_floor`` (tune_sound)."""
    from bridge.bench.tune_sound import TuneSoundConfig, tune_sound

    cfg = TuneSoundConfig(n_max=n_max, window=args.window, n_real=args.real, n_resamples=args.resamples,
                          max_reuse=args.max_reuse, seed=args.seed)
    console.print(f"hilbo tune-stopping --family sound: {len(trajs)} evaluations from {len(args.logs)} "
                  f"log(s), N = {n_max}")
    result = tune_sound(trajs, cfg)
    for label, key in (("BO-RESAMPLE's recommendation", "recommended_stats"),
                       ("the grid's best", "grid_best")):
        r = result[key]
        consts = result["recommended"] if key == "recommended_stats" else r
        console.print(f"{label}: no decision before {consts['min_decision_s']:.0f} s, floor "
                      f"{consts['a_floor']:.2f} σ: {r['mean_breaths']:.1f} breaths, "
                      f"{100 * r['rejected_better']:.1f} % of better candidates rejected, "
                      f"{100 * r['ended_30s']:.1f} % ended within 30 s (cost {r['cost']:.3f})")
    console.print("(BO-RESAMPLE's episodes penalise each trajectory's own rates, which pulls it towards "
                  "conservative floors; the grid's best minimises the pooled cost)")
    _write_result(args, result)
    return 0


def _write_result(args: argparse.Namespace, result: dict[str, Any]) -> None:
    text = json.dumps(result, indent=2) + "\n"
    if args.out:
        out = Path(args.out)
        out.parent.mkdir(parents=True, exist_ok=True)
        tmp = out.with_suffix(out.suffix + ".tmp")
        tmp.write_text(text)
        os.replace(tmp, out)
        sys.stdout.write(f"{out}\n")
    else:
        sys.stdout.write(text)


def add_tune_stopping_parser(subparsers: Any) -> argparse.ArgumentParser:
    """Add ``tune-stopping`` to the ``hilbo`` subcommands; returns its parser."""
    p = subparsers.add_parser(
        "tune-stopping", help="tune the stopping rule's constants offline with BO-RESAMPLE",
        description="Replay the full-length breath trajectories of session logs and tune the "
                    "σ-scaled stopping rule (constant K, or Algorithm 2's window W; compared with "
                    "Algorithm 2's schedule) or the sound rule's time and threshold floors (--family "
                    "sound; with an exhaustive grid beside it) with BO-RESAMPLE (Antonova 2016 §4.2).")
    p.add_argument("logs", nargs="+", metavar="LOG.mcap", help="session logs")
    p.add_argument("--family", choices=[*(f.value for f in StoppingFamily), SOUND_FAMILY], default="k",
                   help="tune a constant K (default), the window W, or the sound rule's "
                        "min_decision_s and a_floor on its fixed clock, as sound-floor (sound)")
    p.add_argument("--n-max", type=two_or_more, default=None,
                   help="N, breaths of a full evaluation (default: from the logs, else 45)")
    p.add_argument("--error-weight", type=nonnegative, default=2.0,
                   help="λ: cost of a wrong early stop in evaluations' time (default 2; not for "
                        "sound, whose cost is the project's targets for the rule)")
    p.add_argument("--window", type=nonnegative_int, default=2,
                   help="W of the Algorithm 2 reference (default 2)")
    p.add_argument("--real", type=positive_int, default=60, help="real episodes (default 60)")
    p.add_argument("--resamples", type=nonnegative_int, default=3,
                   help="resamples per real episode (default 3)")
    p.add_argument("--max-reuse", type=nonnegative_int, default=5,
                   help="resamples per trajectory (default 5)")
    p.add_argument("--seed", type=nonnegative_int, default=0, help="seed (default 0)")
    p.add_argument("--out", default=None, help="write the JSON result here (default: stdout)")
    p.set_defaults(func=_cmd_tune_stopping)
    return p
