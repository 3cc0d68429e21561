"""``hilbo bench tutor``: the tutoring study of Antonova 2016 §4.1/§4.4 (Figs. 7 and 9).

Simulated BKT students are taught by the AFM threshold policy (β1, β2, β3); the cost of a policy
on one student is f = 1 − R(π) (Antonova 2016 §4.1). Three ways of choosing the policy are compared
after every student, over many repetitions:

* ``bo`` — direct policy search by Bayesian optimisation, one real evaluation per student;
* ``bo_resample`` — BO-RESAMPLE (Algorithm 1 of §4.2): after each student, up to K off-policy
  re-evaluations of stored trajectories, each trajectory resampled at most ``max_reuse`` times;
* ``fit_threshold`` — fit the AFM model (β1, β2) by maximum likelihood to the students seen so
  far, then pick β3 among 20 thresholds by the fitted model's predicted reward (Fig. 7). Its data
  are the students' whole answer sequences (each given the full curriculum), the most a model fit
  could get.

Within a repetition every method meets the *same* students in the same order (common random
numbers: a student is a pre-drawn answer sequence, and a policy only decides how much of it is
used). The plotted value is the exact expected cost 1 − E[R] over the student population of the
policy each method recommends after n students (:func:`hilbo_core.studies.tutor.expected_reward`), so the
curves carry no evaluation noise. Reference lines: the best AFM threshold policy (brute force
over its effective "stop at the c-th correct answer" form) and the best BKT threshold policy with
the students' true parameters (exact, over a grid of 48 thresholds).

Not implemented: MBOA (Antonova 2016 ref. [31]), the third curve of Fig. 9.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import os
import sys
import time
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from bridge.argtypes import nonnegative_int, positive_int, two_or_more
from hilbo_core.errors import ConfigError
from hilbo_core.resample import ResampleConfig, Trajectory, bo_resample
from hilbo_core.studies.tutor import (
    FIG7_STUDENTS,
    FIG9_STUDENTS,
    AFMPolicy,
    BKTParams,
    TutorProblem,
    afm_space,
    best_count_policy,
    bkt_threshold_expected_reward,
    draw_students,
    expected_reward,
    fit_then_threshold,
    run_policy,
)

__all__ = [
    "FIGURES",
    "METHODS",
    "TutorBenchConfig",
    "add_tutor_bench_parser",
    "bkt_threshold_reference",
    "run_tutor_bench",
    "run_tutor_repetition",
]

logger = logging.getLogger(__name__)

FIGURES: dict[str, BKTParams] = {"fig7": FIG7_STUDENTS, "fig9": FIG9_STUDENTS}
"""The student populations of Antonova 2016 Fig. 7 and Fig. 9."""
METHODS = ("bo", "bo_resample", "fit_threshold")
# Thresholds tried for the reference "best BKT threshold policy".
_REFERENCE_THRESHOLDS = np.linspace(0.05, 0.99, 48)


@dataclass(frozen=True)
class TutorBenchConfig:
    """One ``hilbo bench tutor`` run.

    Attributes:
        figures: Which student populations (keys of :data:`FIGURES`).
        students: Students per repetition (Antonova 2016: 30).
        repetitions: Independent repetitions per method.
        resamples: K of BO-RESAMPLE (resamples per real evaluation).
        max_reuse: Resamples allowed per stored trajectory (Antonova 2016: 10).
        t_max: Curriculum length.
        seed: Base seed; repetition r of figure f uses SeedSequence([seed, f, r]).
        workers: Processes (1 = in this process).
        n_init: Design points before BO proposes.
    """

    figures: tuple[str, ...] = ("fig7", "fig9")
    students: int = 30
    repetitions: int = 30
    resamples: int = 10
    max_reuse: int = 10
    t_max: int = 20
    seed: int = 0
    workers: int = 1
    n_init: int = 2

    def __post_init__(self) -> None:
        unknown = [f for f in self.figures if f not in FIGURES]
        if unknown or not self.figures:
            raise ConfigError(f"figures={list(self.figures)}; choose from {sorted(FIGURES)}")
        for name, low in (("students", 2), ("repetitions", 1), ("resamples", 0), ("max_reuse", 0),
                          ("t_max", 1), ("seed", 0), ("workers", 1), ("n_init", 1)):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < low:
                raise ConfigError(f"{name}={v!r}; expected an integer >= {low}")


class _StudentStream:
    """The students of one repetition, in order; ``execute`` teaches the next one."""

    def __init__(self, answers: np.ndarray, t_max: int) -> None:
        self.answers = answers
        self.t_max = t_max
        self.next = 0

    def execute(self, params: dict[str, float], rng: np.random.Generator) -> Trajectory:
        if self.next >= len(self.answers):
            raise ConfigError(f"ran out of students after {self.next}")
        a = self.answers[self.next]
        self.next += 1
        t, _ = run_policy(AFMPolicy.from_params(params), a, self.t_max)
        return Trajectory(tuple(bool(o) for o in a[: t + 1]), t)


def run_tutor_repetition(figure: str, rep: int, cfg: TutorBenchConfig) -> dict[str, Any]:
    """One repetition of every method on one student population.

    Returns:
        ``{"costs": {method: [1 − E[R] after n students, n = 1 … students]}, "resample": {...}}``.
    """
    bkt = FIGURES[figure]
    fig_index = sorted(FIGURES).index(figure)
    students_ss, bo_ss, rs_ss = np.random.SeedSequence([cfg.seed, fig_index, rep]).spawn(3)
    answers = draw_students(bkt, cfg.t_max, cfg.students, np.random.default_rng(students_ss))
    problem = TutorProblem(bkt, cfg.t_max)
    space = afm_space()

    def true_cost(params: dict[str, float]) -> float:
        return 1.0 - expected_reward(AFMPolicy.from_params(params), bkt, cfg.t_max)

    costs: dict[str, list[float]] = {}
    extra: dict[str, Any] = {}
    for method, k, ss in (("bo", 0, bo_ss), ("bo_resample", cfg.resamples, rs_ss)):
        stream = _StudentStream(answers, cfg.t_max)
        rcfg = ResampleConfig(n_resamples=k, max_reuse=cfg.max_reuse, n_init=cfg.n_init)
        run = bo_resample(space, stream.execute, problem.halt, problem.objective,
                          n_real=cfg.students, rng=np.random.default_rng(ss), config=rcfg)
        costs[method] = [true_cost(p) for p in run.recommendations]
        extra[method] = {"n_simulated": run.n_simulated,
                         "max_trajectory_uses": max(run.trajectory_uses, default=0),
                         "final_policy": run.recommendations[-1]}
    fit_costs = []
    for n in range(1, cfg.students + 1):
        policy = fit_then_threshold(answers[:n], cfg.t_max)
        fit_costs.append(1.0 - expected_reward(policy, bkt, cfg.t_max))
    costs["fit_threshold"] = fit_costs
    extra["fit_threshold"] = {"final_policy": asdict(policy)}
    return {"figure": figure, "rep": rep, "costs": costs, "details": extra}


def bkt_threshold_reference(bkt: BKTParams, t_max: int) -> tuple[float, float]:
    """Best BKT threshold policy with the students' true parameters: (threshold, 1 − E[R]).

    Exact expectations (:func:`hilbo_core.studies.tutor.bkt_threshold_expected_reward`) over a fixed
    grid of thresholds.
    """
    values = [(float(thr), 1.0 - bkt_threshold_expected_reward(bkt, float(thr), t_max))
              for thr in _REFERENCE_THRESHOLDS]
    return min(values, key=lambda v: v[1])


def _summarise(values: np.ndarray) -> dict[str, list[float]]:
    """Mean and 95 % normal confidence half-width per column of (reps, students)."""
    mean = values.mean(axis=0)
    half = 1.96 * values.std(axis=0, ddof=1) / math.sqrt(values.shape[0]) if values.shape[0] > 1 \
        else np.zeros_like(mean)
    return {"mean": mean.tolist(), "ci95": half.tolist()}


def _run_job(job: tuple[str, int, TutorBenchConfig]) -> dict[str, Any]:
    figure, rep, cfg = job
    return run_tutor_repetition(figure, rep, cfg)


def run_tutor_bench(cfg: TutorBenchConfig, out_dir: Path | None = None, *,
                    progress: Callable[[int, int, float], None] | None = None) -> dict[str, Any]:
    """Run the bench; write ``results.json`` and one plot per figure into ``out_dir`` if given.

    Args:
        cfg: The bench's options.
        out_dir: Where to write, or None.
        progress: Called after every repetition with (done, total, wall seconds so far).

    Returns:
        The results dict (what ``results.json`` holds).
    """
    wall0 = time.perf_counter()
    jobs = [(f, r, cfg) for f in cfg.figures for r in range(cfg.repetitions)]
    by_job: dict[int, dict[str, Any]] = {}

    def finished(i: int, result: dict[str, Any]) -> None:
        by_job[i] = result
        logger.info("tutor bench %s rep %d done", jobs[i][0], jobs[i][1])
        if progress is not None:
            progress(len(by_job), len(jobs), time.perf_counter() - wall0)

    if cfg.workers > 1:
        pool = ProcessPoolExecutor(max_workers=cfg.workers)
        try:
            futures = {pool.submit(_run_job, job): i for i, job in enumerate(jobs)}
            for fut in as_completed(futures):  # progress as repetitions finish, in any order
                finished(futures[fut], fut.result())
        finally:
            # Ctrl-C or a failed repetition: the queued ones are not started.
            pool.shutdown(wait=True, cancel_futures=True)
    else:
        for i, job in enumerate(jobs):
            finished(i, _run_job(job))
    reps = [by_job[i] for i in range(len(jobs))]  # the jobs' order, whatever order they ended in
    results: dict[str, Any] = {"config": asdict(cfg) | {"figures": list(cfg.figures)}, "figures": {}}
    for figure in cfg.figures:
        bkt = FIGURES[figure]
        rows = [r for r in reps if r["figure"] == figure]
        c_best, r_best = best_count_policy(bkt, cfg.t_max)
        thr, bkt_cost = bkt_threshold_reference(bkt, cfg.t_max)
        fig: dict[str, Any] = {
            "students": bkt.to_json(),
            "best_afm_cost": 1.0 - r_best,
            "best_afm_stop_at_correct": c_best,
            "best_bkt_threshold": thr,
            "best_bkt_threshold_cost": bkt_cost,
            "methods": {},
        }
        for method in METHODS:
            values = np.array([r["costs"][method] for r in rows])
            s = _summarise(values)
            fig["methods"][method] = {
                **s,
                "final_mean": float(values[:, -1].mean()),
                "final_ci95": s["ci95"][-1],
                "final_values": values[:, -1].tolist(),
                "frac_reps_at_best_afm": float(np.mean(values[:, -1] <= 1.0 - r_best + 1e-12)),
            }
            if method != "fit_threshold":
                fig["methods"][method]["n_simulated_mean"] = float(
                    np.mean([r["details"][method]["n_simulated"] for r in rows]))
                fig["methods"][method]["max_trajectory_uses"] = int(
                    max(r["details"][method]["max_trajectory_uses"] for r in rows))
        results["figures"][figure] = fig
    results["wall_time_s"] = time.perf_counter() - wall0
    if out_dir is not None:
        out_dir.mkdir(parents=True, exist_ok=True)
        tmp = out_dir / "results.json.tmp"
        tmp.write_text(json.dumps(results, indent=2) + "\n")
        os.replace(tmp, out_dir / "results.json")
        for figure in cfg.figures:
            _plot(results["figures"][figure], figure, cfg, out_dir / f"tutor_{figure}.png")
    return results


_LABELS = {"bo": "BO", "bo_resample": "BO-RESAMPLE", "fit_threshold": "AFM fit + threshold"}


def _plot(fig: dict[str, Any], figure: str, cfg: TutorBenchConfig, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    n = np.arange(1, cfg.students + 1)
    f, ax = plt.subplots(figsize=(6.4, 4.2))
    for method in METHODS:
        m = np.array(fig["methods"][method]["mean"])
        h = np.array(fig["methods"][method]["ci95"])
        label = _LABELS[method] + (f" (K={cfg.resamples})" if method == "bo_resample" else "")
        ax.plot(n, m, label=label)
        ax.fill_between(n, m - h, m + h, alpha=0.2)
    ax.axhline(fig["best_afm_cost"], color="k", ls="--", lw=1, label="best AFM threshold policy")
    ax.axhline(fig["best_bkt_threshold_cost"], color="grey", ls=":", lw=1,
               label="best BKT threshold (true params)")
    s = fig["students"]
    ax.set_title(f"{figure}: BKT pk={s['p_know']:g} pl={s['p_learn']:g} pg={s['p_guess']:g} "
                 f"ps={s['p_slip']:g}, t_max={cfg.t_max}", fontsize=9)
    ax.set_xlabel("students (real policy evaluations)")
    ax.set_ylabel("1 − E[R] of recommended policy")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    f.tight_layout()
    f.savefig(path, dpi=120)
    plt.close(f)


def _cmd_bench_tutor(args: argparse.Namespace) -> int:
    from rich.console import Console

    from bridge.bench.common import choices, options

    console = Console(markup=False, highlight=False, soft_wrap=True)  # the results: stdout
    err = Console(stderr=True, markup=False, highlight=False, soft_wrap=True)  # progress
    with options():  # a bad value on the command line: exit status 2
        figures = choices(",".join(args.figures), FIGURES, "figure", ())
        cfg = TutorBenchConfig(figures=tuple(figures), students=args.students,
                               repetitions=args.reps, resamples=args.resamples,
                               max_reuse=args.max_reuse, t_max=args.t_max, seed=args.seed,
                               workers=args.workers)
    out = Path(args.out)
    console.print(f"hilbo bench tutor: {cfg.repetitions} repetitions × {cfg.students} students, "
                  f"K={cfg.resamples}, reuse ≤ {cfg.max_reuse}, t_max={cfg.t_max}")

    def progress(done: int, total: int, wall_s: float) -> None:
        err.print(f"  {done}/{total} repetitions, {wall_s:.0f} s")

    results = run_tutor_bench(cfg, out, progress=None if args.no_progress else progress)
    for figure, fig in results["figures"].items():
        console.print(f"{figure}: best AFM policy 1−E[R] = {fig['best_afm_cost']:.4f}; "
                      f"best BKT threshold {fig['best_bkt_threshold_cost']:.4f}")
        for method, m in fig["methods"].items():
            console.print(f"  {_LABELS[method]:22s} after {cfg.students} students: "
                          f"{m['final_mean']:.4f} ± {m['final_ci95']:.4f}  "
                          f"(at best AFM in {100 * m['frac_reps_at_best_afm']:.0f} % of reps)")
    console.print(f"wall time {results['wall_time_s']:.0f} s; results in {out / 'results.json'}")
    sys.stdout.write(f"{out / 'results.json'}\n")
    return 0


def add_tutor_bench_parser(bench_subparsers: Any) -> argparse.ArgumentParser:
    """Add ``tutor`` to the ``hilbo bench`` subcommands.

    Args:
        bench_subparsers: What ``bench_parser.add_subparsers()`` returned.

    Returns:
        The ``tutor`` parser (its ``func`` default runs the bench and returns the exit code).
    """
    p = bench_subparsers.add_parser(
        "tutor", help="tutoring study of Antonova 2016 (BO vs BO-RESAMPLE vs fit-then-threshold)",
        description="Simulated BKT students taught by the AFM threshold policy (Antonova 2016 §4.1, "
                    "§4.4): BO, BO-RESAMPLE and model-fit-then-threshold after every student; "
                    "writes results.json and tutor_fig7.png / tutor_fig9.png.")
    p.add_argument("--figures", nargs="+", default=["fig7", "fig9"], metavar="FIG",
                   help=f"student populations, from {','.join(sorted(FIGURES))} (separated by spaces "
                        "or commas; default both)")
    p.add_argument("--students", type=two_or_more, default=30, help="students per repetition (default 30)")
    p.add_argument("--reps", type=positive_int, default=30, help="repetitions (default 30)")
    p.add_argument("--resamples", type=nonnegative_int, default=10, help="K of BO-RESAMPLE (default 10)")
    p.add_argument("--max-reuse", type=nonnegative_int, default=10,
                   help="resamples allowed per stored trajectory (default 10)")
    p.add_argument("--t-max", type=positive_int, default=20, help="curriculum length (default 20)")
    p.add_argument("--seed", type=nonnegative_int, default=0, help="base seed (default 0)")
    p.add_argument("--workers", type=positive_int, default=1, help="processes (default 1)")
    p.add_argument("--out", default="runs/bench_tutor",
                   help="output directory (default runs/bench_tutor)")
    p.add_argument("--no-progress", action="store_true", help="no progress lines")
    p.set_defaults(func=_cmd_bench_tutor)
    return p

