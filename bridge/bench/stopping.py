"""``hilbo bench stopping``: Kim et al. 2019 §III.2's simulation study, campaign and summary.

One *trial* is :func:`hilbo_core.studies.benchmarks.stopping_trial` for one (function, noise, method,
seed). A campaign runs ``trials`` seeds for every function × noise level × method; the methods
of one trial share the seed, hence the exploration design, the exploration measurements and x_0,
so methods are compared pairwise on the same trials (as Kim et al. 2019 compare them).

Every finished trial is appended to ``OUT/trials.jsonl`` as it completes, so an interrupted
campaign continues with ``--resume`` and a campaign can be grown by re-running with more
trials. The summary (``results.json``), the Markdown table and one PNG per function (the layout
of Kim et al. 2019's Fig. 2) are written from all trials of the campaign at the end.

``refit_growth`` (``--refit-growth``) is :class:`~hilbo_core.optimizer.OptimizerConfig`'s option
of the same name, applied identically to every method of the campaign; it is part of a trial's
identity (a trial of one growth factor is never resumed or merged into a campaign of another), and
trials recorded before the option existed count as 1.0 (they refitted at every proposal).

Reference methods (:data:`PEER_METHODS`, the strongest off-the-shelf peers): Optuna's TPE
sampler with the Wilcoxon (``tpe-wilcoxon``) or the successive-halving pruner (``tpe-halving``),
in the same harness: the
same exploration (design points, measurements and hence x_0 as the BO methods of the trial; they
enter the study as completed trials), then every Optuna trial is a setting measured breath by
breath with the harness's Gaussian-product measurements, each measurement reported as an
intermediate value so that the pruner can stop the setting early, until the same
``budget`` of measurements is spent (a setting running when it ends is closed with the estimate it
has, as the BO methods' is). The recommendation x_t is the completed setting with the lowest
estimate (pruned settings have no final value). Optuna is the optional extra ``peers``
(``pip install hilbo[peers]``), imported only when such a method runs.
"""

from __future__ import annotations

import json
import logging
import math
import time
import warnings
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from bridge.bench.common import blas_threads, markdown_table, round_sig
from bridge.bench.executors import keep_freed_memory
from hilbo_core.errors import ConfigError, OptimizerStateError
from hilbo_core.optimizer import OptimizerConfig, Phase
from hilbo_core.studies.benchmarks import (
    _NOISE_STREAM,  # the trial's measurement stream: peers must measure what the BO methods measure
    FUNCTIONS,
    MEASUREMENT_INTERVAL_S,
    METHODS,
    NOISE_LEVELS,
    NoiseModel,
    StoppingMethod,
    StoppingProtocol,
    check_noise,
    estimator_factory,
    measure,
    resolve_function,
    resolve_method,
    stopping_trial,
    study_optimizer,
    y_metric,
)

__all__ = [
    "PEER_METHODS",
    "PeerMethod",
    "StoppingCampaign",
    "StoppingTask",
    "against_peers",
    "load_trials",
    "peer_trial",
    "run_stopping_task",
    "stopping_table",
    "summarize_stopping",
]

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class PeerMethod:
    """An Optuna reference method of the stopping benchmark.

    Attributes:
        name: Identifier on the command line and in results.
        description: One line for tables.
        pruner: ``"wilcoxon"`` or ``"halving"``.
    """

    name: str
    description: str
    pruner: str


PEER_METHODS: Mapping[str, PeerMethod] = {
    "tpe-wilcoxon": PeerMethod(
        "tpe-wilcoxon", "Optuna TPE, Wilcoxon pruner (p 0.1) on the single measurements", "wilcoxon"),
    "tpe-halving": PeerMethod(
        "tpe-halving", "Optuna TPE, successive-halving pruner (rungs 1, 4, 16 measurements) on the "
        "running estimate", "halving"),
}
"""Optuna TPE + pruner peers, by name; they need the ``peers`` extra."""

_PEERS_HINT = "pip install hilbo[peers]"
# Wilcoxon pruner: Optuna's default p threshold; the test compares the new setting's single
# measurements with the best setting's at the same breath indices (the pruner's intended use:
# one step = one independent evaluation of the same objective).
_WILCOXON_P = 0.1
# Successive halving: rungs at 1, 4, 16 measurements (Optuna's default reduction factor 4);
# min_resource is fixed, not "auto", because the exploration trials are added, not run.
_HALVING_MIN_RESOURCE = 1
_HALVING_REDUCTION = 4


def _import_optuna() -> Any:
    try:
        import optuna
    except ImportError as err:
        raise ConfigError(
            f"the Optuna reference methods {sorted(PEER_METHODS)} need Optuna: {_PEERS_HINT}"
        ) from err
    return optuna


def peer_trial(function: str, noise: float, method: str, seed: int,
               protocol: StoppingProtocol | None = None) -> dict[str, Any]:
    """One trial of an Optuna peer in the harness of :func:`hilbo_core.studies.benchmarks.stopping_trial`.

    Same trial identity and output fields as ``stopping_trial`` (``y`` on the same measurement
    grid, normalised by the same x_0), plus ``pruned`` (settings the pruner stopped).

    Raises:
        ConfigError: Unknown function, method, bad noise, seed, or Optuna not installed.
    """
    if method not in PEER_METHODS:
        raise ConfigError(f"unknown peer method {method!r}; choose one of {sorted(PEER_METHODS)}")
    peer = PEER_METHODS[method]
    fn = resolve_function(function)
    level = check_noise(noise)
    proto = protocol or StoppingProtocol()
    if isinstance(seed, bool) or not isinstance(seed, int | np.integer) or seed < 0:
        raise ConfigError(f"seed={seed!r}; expected an integer >= 0")
    optuna = _import_optuna()
    prior_var = fn.prior_std**2
    true_var = level * prior_var if proto.noise_model is NoiseModel.MATCHED else prior_var
    # One factory per trial: exploration and every Optuna setting share its noise pool.
    estimator = estimator_factory(fn, level, proto.noise_estimate)
    rng = np.random.default_rng([int(seed), _NOISE_STREAM])

    # Exploration exactly as stopping_trial runs it (same optimizer seed, design, noise stream):
    # the same points, the same measurements, the same x_0.
    explorer = study_optimizer(fn, proto, int(seed), estimator)
    explored: list[tuple[dict[str, float], float, list[float]]] = []
    while len(explorer.evaluations) < proto.n_explore:
        params = explorer.ask()
        f_true = fn.value(params)
        zs: list[float] = []
        i = 0
        while True:
            i += 1
            z = measure(f_true, true_var, rng)
            zs.append(z)
            step = explorer.observe(i * MEASUREMENT_INTERVAL_S, z)
            if step.stop:
                break
        if step.phase is not Phase.EXPLORATION or step.evaluation is None:
            raise OptimizerStateError("internal: exploration did not end where expected")
        explored.append((step.evaluation.params, step.evaluation.mean, zs))
    x0 = explorer.best()[0]
    f_x0 = fn.value(x0)

    names = [f"x{i + 1}" for i in range(fn.dim)]
    dists = {n: optuna.distributions.FloatDistribution(lo, hi)
             for n, lo, hi in zip(names, fn.lower, fn.upper, strict=True)}
    with warnings.catch_warnings():
        # WilcoxonPruner is marked experimental in some Optuna versions; the benchmark pins
        # its behaviour by its own tests, so the warning says nothing to the user here.
        warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)
        if peer.pruner == "wilcoxon":
            pruner = optuna.pruners.WilcoxonPruner(p_threshold=_WILCOXON_P)
        else:
            pruner = optuna.pruners.SuccessiveHalvingPruner(
                min_resource=_HALVING_MIN_RESOURCE, reduction_factor=_HALVING_REDUCTION)
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    study = optuna.create_study(direction="minimize", pruner=pruner,
                                sampler=optuna.samplers.TPESampler(seed=int(seed)))
    # The running estimates of the exploration settings are the explorer's traces (estimating
    # them again would add their measurements to the trial's noise pool a second time).
    running, _ = explorer.exploration_traces
    for (params, mean, zs), trace in zip(explored, running, strict=True):
        inter = [float(z) for z in zs] if peer.pruner == "wilcoxon" else [float(m) for m in trace]
        study.add_trial(optuna.trial.create_trial(
            params={n: float(params[n]) for n in names}, distributions=dists, value=float(mean),
            intermediate_values=dict(enumerate(inter))))

    y = np.full(proto.budget + 1, np.nan)
    y[0] = 1.0
    rec = x0
    t = evaluations = pruned = 0
    while t < proto.budget:
        trial = study.ask(dists)
        params = {n: float(trial.params[n]) for n in names}
        f_true = fn.value(params)
        est = estimator()
        state = optuna.trial.TrialState.COMPLETE
        mean = math.nan
        for i in range(proto.max_breaths):
            z = measure(f_true, true_var, rng)
            mean, _ = est.update(float(i + 1), z)
            t += 1
            y[t] = y[t - 1]
            trial.report(z if peer.pruner == "wilcoxon" else float(mean), i)
            if t >= proto.budget:
                break  # the budget ends this setting with the estimate it has
            if i < proto.max_breaths - 1 and trial.should_prune():
                state = optuna.trial.TrialState.PRUNED
                break
        evaluations += 1
        if state is optuna.trial.TrialState.PRUNED:
            pruned += 1
            study.tell(trial, state=state)
        else:
            study.tell(trial, float(mean))
        best = study.best_trial
        rec = {n: float(best.params[n]) for n in names}
        y[t] = float(y_metric(fn.value(rec), f_x0, fn.f_min))
    return {
        "function": fn.name, "noise": level, "method": method, "seed": int(seed),
        "y": y.tolist(), "evaluations": evaluations, "early_stops": pruned, "pruned": pruned,
        "measurements": t, "f_x0": f_x0, "f_final": fn.value(rec), "x0": x0, "x_final": rec,
    }


@dataclass(frozen=True)
class StoppingTask:
    """One trial of one method (picklable; everything the worker needs)."""

    function: str
    noise: float
    method: str
    seed: int
    protocol: StoppingProtocol = field(default_factory=StoppingProtocol)
    refit_growth: float = 1.0

    def key(self) -> tuple[str, float, str, int]:
        """Identity of the trial within a campaign."""
        return (self.function, self.noise, self.method, self.seed)


def _with_refit_growth(method: str, refit_growth: float) -> StoppingMethod:
    """The registered method with ``refit_growth`` added to its optimizer options."""
    base = resolve_method(method)
    return StoppingMethod(base.name, base.description, {**base.options, "refit_growth": refit_growth})


def run_stopping_task(task: StoppingTask) -> dict[str, Any]:
    """Run one trial (in a worker); the result of :func:`stopping_trial` plus ``wall_s``,
    ``protocol`` and ``refit_growth``."""
    blas_threads(1)  # wherever it runs: see bridge.bench.common.blas_threads
    keep_freed_memory()  # no page faults for the same big arrays again (see there)
    t0 = time.perf_counter()
    if task.method in PEER_METHODS:
        result = peer_trial(task.function, task.noise, task.method, task.seed, task.protocol)
    else:
        result = stopping_trial(task.function, task.noise,
                                _with_refit_growth(task.method, task.refit_growth), task.seed,
                                task.protocol)
    result["wall_s"] = time.perf_counter() - t0
    result["protocol"] = task.protocol.to_json()
    result["refit_growth"] = task.refit_growth
    return result


@dataclass(frozen=True)
class StoppingCampaign:
    """Which trials a ``bench stopping`` run consists of; validated before any work starts.

    Attributes:
        functions: Names in :data:`hilbo_core.studies.benchmarks.FUNCTIONS`.
        noises: σ_z²/σ̃² factors (Kim et al. 2019's: 0.1, 1, 10).
        methods: Names in :data:`hilbo_core.studies.benchmarks.METHODS` or :data:`PEER_METHODS`.
        trials: Trials per function × noise (>= 1); trial k uses seed ``seed + k``.
        seed: Seed of the first trial (>= 0).
        protocol: The study's protocol.
        refit_growth: ``OptimizerConfig.refit_growth`` of every method (finite, >= 1; 1.0 refits
            the GP hyperparameters at every proposal).
    """

    functions: tuple[str, ...] = tuple(FUNCTIONS)
    noises: tuple[float, ...] = NOISE_LEVELS
    methods: tuple[str, ...] = ("fixed", "adaptive")
    trials: int = 100
    seed: int = 0
    protocol: StoppingProtocol = field(default_factory=StoppingProtocol)
    refit_growth: float = 1.0

    def __post_init__(self) -> None:
        for name in ("trials", "seed"):
            value = getattr(self, name)
            low = 1 if name == "trials" else 0
            if isinstance(value, bool) or not isinstance(value, int) or value < low:
                raise ConfigError(f"{name}={value!r}; expected an integer >= {low}")
        if not self.functions or not self.methods or not self.noises:
            raise ConfigError("a campaign needs at least one function, one noise level and one method")
        for f in self.functions:
            resolve_function(f)
        for m in self.methods:
            if m not in PEER_METHODS:
                try:
                    resolve_method(m)
                except ConfigError as err:
                    raise ConfigError(f"unknown method {m!r}; choose one of "
                                      f"{sorted({**METHODS, **PEER_METHODS})}") from err
        if any(m in PEER_METHODS for m in self.methods):
            _import_optuna()  # before any work: the clear message, not a failed worker
        object.__setattr__(self, "noises", tuple(check_noise(n) for n in self.noises))
        for what, values in (("function", self.functions), ("method", self.methods),
                             ("noise level", self.noises)):
            if len(set(values)) != len(values):
                raise ConfigError(f"a {what} is listed twice in {list(values)}")
        # The optimizer's own validation, so the message is the same as everywhere else.
        object.__setattr__(self, "refit_growth", OptimizerConfig(refit_growth=self.refit_growth).refit_growth)

    def tasks(self) -> list[StoppingTask]:
        """All trials, trial-major: an interrupted campaign has covered every setting evenly."""
        return [StoppingTask(f, n, m, self.seed + k, self.protocol, self.refit_growth)
                for k in range(self.trials) for f in self.functions for n in self.noises
                for m in self.methods]

    def to_json(self) -> dict[str, Any]:
        """JSON-able form."""
        return {"functions": list(self.functions), "noises": list(self.noises),
                "methods": list(self.methods), "trials": self.trials, "seed": self.seed,
                "protocol": self.protocol.to_json(), "refit_growth": self.refit_growth}


def load_trials(path: Path, protocol: StoppingProtocol, refit_growth: float = 1.0,
                ) -> dict[tuple[str, float, str, int], dict[str, Any]]:
    """Finished trials of ``trials.jsonl`` run under ``protocol`` and ``refit_growth``, by
    :meth:`StoppingTask.key`.

    Lines of other protocols or growth factors are skipped (a line without ``refit_growth`` was
    written before the option existed and refitted at every proposal: 1.0; one without the
    protocol's ``noise_estimate`` used Kim et al. 2019's estimator); a truncated last line
    (a killed run) is ignored.
    """
    out: dict[tuple[str, float, str, int], dict[str, Any]] = {}
    if not path.exists():
        return out
    want = protocol.to_json()
    for n, line in enumerate(path.read_text().splitlines(), start=1):
        if not line.strip():
            continue
        try:
            rec = json.loads(line)
        except json.JSONDecodeError:
            logger.warning("%s:%d: unreadable line skipped (interrupted write?)", path, n)
            continue
        # A line without noise_estimate was written before the option existed: Kim et al. 2019's.
        proto = {"noise_estimate": "seed", **rec.get("protocol", {})}
        if proto != want or float(rec.get("refit_growth", 1.0)) != refit_growth:
            continue
        out[(rec["function"], float(rec["noise"]), rec["method"], int(rec["seed"]))] = rec
    return out


def _mean_se(values: np.ndarray, axis: int = 0) -> tuple[np.ndarray, np.ndarray]:
    n = values.shape[axis]
    mean = values.mean(axis=axis)
    se = values.std(axis=axis, ddof=1) / math.sqrt(n) if n > 1 else np.full_like(mean, np.nan)
    return mean, se


def summarize_stopping(results: Iterable[Mapping[str, Any]], campaign: StoppingCampaign,
                       grid_step: int = 1, paired: bool = True) -> dict[str, Any]:
    """Aggregate trials into one entry per method × function × noise (and paired comparisons).

    Args:
        results: Trial results (:func:`run_stopping_task`) of this campaign.
        campaign: The campaign (gives the order and the expected trial count).
        grid_step: Keep y_t every ``grid_step`` measurements (the last one always).
        paired: Summarise, per function × noise, only the seeds every method finished (the
            default; ``n_trials_run`` still counts all of a method's trials).

    Returns:
        ``{"settings": [...], "comparisons": [...]}``. A setting holds ``method``,
        ``function``, ``noise``, ``refit_growth`` (the campaign's), ``n_trials``, ``t``
        (measurement counts), ``y_mean``, ``y_se`` (on ``t``), ``y_final_mean``/``_se``
        (t = budget), ``y_avg_mean``/``_se`` (y averaged over all t: the anytime performance),
        ``evaluations_mean``, ``early_stops_mean``, ``trial_wall_s_mean``. A comparison holds,
        per function × noise and method other than the first, the paired difference of y_final
        and of y_avg (method − first method) over the shared seeds, with its SE and the
        fraction of trials where the method ended lower.
    """
    if isinstance(grid_step, bool) or not isinstance(grid_step, int) or grid_step < 1:
        raise ConfigError(f"grid_step={grid_step!r}; expected an integer >= 1")
    groups: dict[tuple[str, str, float], dict[int, Mapping[str, Any]]] = {}
    for r in results:
        groups.setdefault((r["method"], r["function"], float(r["noise"])), {})[int(r["seed"])] = r
    budget = campaign.protocol.budget
    t_grid = list(range(0, budget + 1, grid_step))
    if t_grid[-1] != budget:
        t_grid.append(budget)
    settings: list[dict[str, Any]] = []
    comparisons: list[dict[str, Any]] = []
    for f in campaign.functions:
        for noise in campaign.noises:
            per_method = {m: groups.get((m, f, noise), {}) for m in campaign.methods}
            shared = set.intersection(*(set(t) for t in per_method.values()))
            for method in campaign.methods:
                ran = per_method[method]
                # Paired design: a method's curve uses only the trials every method finished,
                # so all curves of a panel start from the same x_0s.
                trials = {k: v for k, v in ran.items() if k in shared} if paired else ran
                if not trials:
                    continue
                Y = np.array([trials[s]["y"] for s in sorted(trials)], dtype=float)
                y_mean, y_se = _mean_se(Y[:, t_grid])
                fin_m, fin_se = _mean_se(Y[:, -1])
                avg_m, avg_se = _mean_se(Y.mean(axis=1))
                settings.append({
                    "method": method, "function": f, "noise": noise, "refit_growth": campaign.refit_growth,
                    "n_trials": len(trials),
                    "n_trials_run": len(ran),
                    "t": t_grid, "y_mean": y_mean, "y_se": y_se,
                    "y_final_mean": fin_m, "y_final_se": fin_se,
                    "y_avg_mean": avg_m, "y_avg_se": avg_se,
                    "y_final_median": float(np.median(Y[:, -1])),
                    "evaluations_mean": float(np.mean([trials[s]["evaluations"] for s in trials])),
                    "early_stops_mean": float(np.mean([trials[s]["early_stops"] for s in trials])),
                    "trial_wall_s_mean": float(np.mean([trials[s].get("wall_s", math.nan) for s in trials])),
                })
            base = campaign.methods[0]
            base_trials = groups.get((base, f, noise), {})
            for method in campaign.methods[1:]:
                trials = groups.get((method, f, noise), {})
                seeds = sorted(set(trials) & set(base_trials))
                if not seeds:
                    continue
                ym = np.array([trials[s]["y"] for s in seeds], dtype=float)
                yb = np.array([base_trials[s]["y"] for s in seeds], dtype=float)
                d_fin = ym[:, -1] - yb[:, -1]
                d_avg = ym.mean(axis=1) - yb.mean(axis=1)
                fm, fse = _mean_se(d_fin)
                am, ase = _mean_se(d_avg)
                comparisons.append({
                    "function": f, "noise": noise, "method": method, "baseline": base,
                    "n_pairs": len(seeds),
                    "y_final_diff_mean": fm, "y_final_diff_se": fse,
                    "y_avg_diff_mean": am, "y_avg_diff_se": ase,
                    "frac_final_lower": float(np.mean(d_fin < 0)),
                    "frac_final_tied": float(np.mean(d_fin == 0)),
                })
    return {"settings": round_sig(settings), "comparisons": round_sig(comparisons),
            "against_peers": against_peers(settings)}


def against_peers(settings: Sequence[Mapping[str, Any]]) -> dict[str, Any]:
    """Which hilbo methods end below the better Optuna peer, setting by setting (mean y_T).

    The statistic is the mean over trials of y_T, y at the end of the optimisation phase (t =
    budget): Kim et al. 2019 §III.2 define y_t by the recommendation x_t, and what a study has
    at its end is x_T (Fig. 2's curves end there). A setting (function × noise) counts for a
    method when its mean y_T is strictly below the lower of the peers' mean y_T.

    Args:
        settings: The ``settings`` of :func:`summarize_stopping`.

    Returns:
        ``{"settings": [{function, noise, best_peer, best_peer_y_final, below: {method: bool}}],
        "count": {method: settings below}, "n_settings": settings with a peer}``; empty counts
        when the campaign ran no peer.
    """
    by_setting: dict[tuple[str, float], dict[str, float]] = {}
    for st in settings:
        key = (st["function"], float(st["noise"]))
        by_setting.setdefault(key, {})[st["method"]] = float(st["y_final_mean"])
    rows: list[dict[str, Any]] = []
    count: dict[str, int] = {}
    for (f, noise), ys in by_setting.items():
        peers = {m: y for m, y in ys.items() if m in PEER_METHODS}
        if not peers:
            continue
        best = min(peers, key=lambda m: peers[m])
        below = {m: y < peers[best] for m, y in ys.items() if m not in PEER_METHODS}
        for m, ok in below.items():
            count[m] = count.get(m, 0) + int(ok)
        rows.append({"function": f, "noise": noise, "best_peer": best, "best_peer_y_final": peers[best],
                     "below": below})
    return {"settings": rows, "count": count, "n_settings": len(rows)}


def _pm(mean: Any, se: Any, digits: int = 3) -> str:
    if mean is None:
        return "–"
    if se is None:
        return f"{mean:.{digits}f}"
    return f"{mean:.{digits}f} ± {se:.{digits}f}"


def stopping_table(summary: Mapping[str, Any]) -> str:
    """Markdown: per function × noise × method, y_final and y averaged over t (mean ± SE),
    evaluations and early stops; then the paired differences against the first method."""
    rows = []
    for s in summary["settings"]:
        rows.append([s["function"], f"{s['noise']:g}", s["method"], s["n_trials"],
                     _pm(s["y_final_mean"], s["y_final_se"]), f"{s['y_final_median']:.3f}",
                     _pm(s["y_avg_mean"], s["y_avg_se"]),
                     f"{s['evaluations_mean']:.1f}", f"{s['early_stops_mean']:.1f}",
                     "–" if s["trial_wall_s_mean"] is None else f"{s['trial_wall_s_mean']:.1f}"])
    out = markdown_table(
        ["function", "σ_z²/σ̃²", "method", "trials", "y_final (mean ± SE)", "y_final median",
         "mean y_t over t", "evaluations", "early stops", "s / trial"], rows)
    comp = summary.get("comparisons") or []
    if comp:
        crow = [[c["function"], f"{c['noise']:g}", f"{c['method']} − {c['baseline']}", c["n_pairs"],
                 _pm(c["y_final_diff_mean"], c["y_final_diff_se"]),
                 _pm(c["y_avg_diff_mean"], c["y_avg_diff_se"]),
                 f"{100 * c['frac_final_lower']:.0f} %"]
                for c in comp]
        out += "\n" + markdown_table(
            ["function", "σ_z²/σ̃²", "paired difference", "pairs", "Δ y_final (mean ± SE)",
             "Δ mean y_t (mean ± SE)", "trials ending lower"], crow)
    peers = summary.get("against_peers") or {}
    if peers.get("n_settings"):
        prow = [[m, f"{k} of {peers['n_settings']}"] for m, k in peers["count"].items()]
        out += "\n" + markdown_table(["method", "mean y_T below the better TPE + pruner"], prow)
    return out


def run_campaign(campaign: StoppingCampaign, executor: Any, out_dir: Path, *, resume: bool = False,
                 on_result: Callable[[int, dict[str, Any]], None] | None = None,
                 ) -> tuple[list[dict[str, Any]], float]:
    """Run (or finish) a campaign; every trial is appended to ``out_dir/trials.jsonl``.

    Returns:
        (all results of the campaign in task order, wall time of this run in s).
    """
    tasks = campaign.tasks()
    path = out_dir / "trials.jsonl"
    out_dir.mkdir(parents=True, exist_ok=True)
    done = load_trials(path, campaign.protocol, campaign.refit_growth) if resume else {}
    if not resume and path.exists():
        path.unlink()  # a fresh campaign; --resume keeps what is there
    todo = [t for t in tasks if t.key() not in done]
    logger.info("stopping campaign: %d trials, %d already done, %d to run on %s",
                len(tasks), len(tasks) - len(todo), len(todo), getattr(executor, "name", executor))
    # The summary is computed from what trials.jsonl holds, so that --summarize-only gives the
    # same numbers to the last digit.
    written: dict[int, dict[str, Any]] = {}
    with path.open("a") as fh:

        def record(i: int, result: dict[str, Any]) -> None:
            written[i] = round_sig(result, 10)
            fh.write(json.dumps(written[i]) + "\n")
            fh.flush()
            if on_result is not None:
                on_result(i, result)

        t0 = time.perf_counter()
        executor.map(run_stopping_task, todo, label="stopping trials", on_result=record)
        wall = time.perf_counter() - t0
    for i, t in enumerate(todo):
        done[t.key()] = written[i]
    return [done[t.key()] for t in tasks], wall


def method_descriptions(methods: Sequence[str]) -> dict[str, str]:
    """One line per method, for results.json."""
    return {m: (PEER_METHODS[m] if m in PEER_METHODS else METHODS[m]).description for m in methods}


def function_descriptions(functions: Sequence[str]) -> dict[str, Any]:
    """Table I rows of the functions, for results.json."""
    out = {}
    for f in functions:
        fn = FUNCTIONS[f]
        out[f] = {"dim": fn.dim, "lower": list(fn.lower), "upper": list(fn.upper), "f_min": fn.f_min,
                  "prior_mean": fn.prior_mean, "prior_std": fn.prior_std}
    return out
