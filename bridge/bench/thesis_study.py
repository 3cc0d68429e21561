"""Simulated-wearer study of the Antonova 2016 methods in whole HIL sessions (docs/results_thesis.md).

Three questions, each answered with paired sessions on the same simulated wearers
(:class:`bridge.sim.devices.SimulatedWearer`) under the protocol of :func:`bridge.sim.core.run_insim`
(3-min warm-up, exploration bout of E × N breaths, 3-min warm-up, optimisation until the session
ends), measuring the true regret of the recommendation (:meth:`HILOptimizer.best`) at fixed
minutes of walking:

1. **Fast prior** (Antonova 2016 §3.3): a second session of the same wearer, on another "day" (a fresh
   breath-noise stream, another optimizer seed), with or without the first session's evaluations
   as prior observations (:func:`hilbo_core.priors.priors_from_evaluations`, default inflation),
   and with the exploration bout cut to 3 points when the prior is there.
2. **Feature kernels** (§3.4.2): the GP on raw parameters (baseline), on profile features only
   (:class:`hilbo_core.features.ProfileFeatureMap`), and on both (:func:`hilbo_core.features.with_raw`).
3. **Tuned stopping** (Antonova 2016 §4.2): a constant-K σ-scaled rule with K tuned offline by
   ``tune_stopping`` on *other* wearers' full-length trajectories vs Algorithm 2's schedule.

The sessions themselves (the optimizer scaffolding for feature maps and constant-K stopping,
the "new day" of a wearer) are :mod:`bridge.bench.thesis_session`, shared with the ``adaptive-*``
methods of ``hilbo bench hil``.

The simulated wearer's landscape does not change between sessions, so the prior experiment is a
best case for priors from a previous session (a real wearer adapts and drifts between days).
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys
import time
from collections.abc import Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from bridge.bench.hil import regret_at
from bridge.bench.thesis_session import Arm, StudyOptimizer, run_session
from bridge.bench.tune_stopping import TuneStoppingConfig, tune_stopping
from hilbo_core import presets
from hilbo_core.optimizer import PriorObservation
from hilbo_core.priors import priors_from_evaluations

__all__ = ["Arm", "StudyOptimizer", "main", "run_session", "run_study"]

logger = logging.getLogger(__name__)

_MINUTE_GRID = (20.0, 30.0, 40.0, 50.0, 60.0)


@dataclass(frozen=True)
class _Job:
    seed: int
    arm: Arm
    minutes: float
    priors: tuple[PriorObservation, ...] = field(default=())


def _run_job(job: _Job) -> dict[str, Any]:
    return run_session(job.seed, job.arm, minutes=job.minutes, priors=job.priors)


def _map(jobs: Sequence[_Job], workers: int) -> list[dict[str, Any]]:
    if workers > 1:
        with ProcessPoolExecutor(max_workers=workers) as pool:
            return list(pool.map(_run_job, jobs))
    out = []
    for job in jobs:
        out.append(_run_job(job))
        logger.info("session seed %d arm %s: %.1f s", job.seed, job.arm.name, out[-1]["wall_s"])
    return out


def run_study(test_seeds: Sequence[int], train_seeds: Sequence[int], *, minutes: float = 60.0,
              workers: int = 1, studies: Sequence[str] = ("prior", "feature", "stopping"),
              error_weight: float = 2.0, k_bo_wearers: int = 3) -> dict[str, Any]:
    """Run the three studies (module docstring); returns per-arm regrets on the minute grid.

    ``k_bo_wearers`` limits the BO-RESAMPLE-tuned K arm to the first test wearers.
    """
    wall0 = time.perf_counter()
    base = Arm("alg2_raw")
    sessions: dict[str, list[dict[str, Any]]] = {}
    sessions[base.name] = _map([_Job(s, base, minutes) for s in test_seeds], workers)
    extra: dict[str, Any] = {}
    if "feature" in studies:
        for arm in (Arm("profile", feature="profile"), Arm("profile+raw", feature="profile+raw")):
            sessions[arm.name] = _map([_Job(s, arm, minutes) for s in test_seeds], workers)
    if "stopping" in studies:
        train = _map([_Job(s, base, minutes) for s in train_seeds], workers)
        trajs = [np.array(t) for r in train for t in r["trajectories"]]
        extra["tuning"] = {}
        for family in ("k", "window"):
            tuned = tune_stopping(trajs, TuneStoppingConfig(family=family, error_weight=error_weight))
            extra["tuning"][family] = {k2: v for k2, v in tuned.items() if k2 != "bo_resample"} | {
                "bo_resample_counts": {
                    "n_real": tuned["bo_resample"]["n_real"],
                    "n_simulated": tuned["bo_resample"]["n_simulated"],
                    "max_trajectory_uses": tuned["bo_resample"]["max_trajectory_uses"]}}
        k_bo = float(extra["tuning"]["k"]["recommended"]["k"])
        k_grid = float(extra["tuning"]["k"]["grid_best"]["k"])
        w_bo = int(extra["tuning"]["window"]["recommended"]["window"])
        for name, arm, seeds in (
                ("k_grid", Arm(f"k_grid={k_grid:.2f}", stopping_k=k_grid), test_seeds),
                ("w_bo", Arm(f"w_bo={w_bo}", window=w_bo), test_seeds),
                # A small K stops after a breath or two: hundreds of evaluations, each GP fit
                # O(n³), so this arm runs on fewer wearers.
                ("k_bo", Arm(f"k_bo={k_bo:.2f}", stopping_k=k_bo), test_seeds[:k_bo_wearers])):
            if seeds:
                sessions[name] = _map([_Job(s, arm, minutes) for s in seeds], workers)
    if "prior" in studies:
        day2 = Arm("day2_none", day=2)
        with_prior = Arm("day2_prior", day=2, prior=True)
        short = Arm("day2_prior_e3", day=2, prior=True, n_explore=3)
        space = presets.hip_6d()
        jobs_none, jobs_prior, jobs_short = [], [], []
        for r in sessions[base.name]:
            pri = tuple(priors_from_evaluations(space, r["evaluations"], label=f"day1 seed {r['seed']}"))
            jobs_none.append(_Job(r["seed"], day2, minutes))
            jobs_prior.append(_Job(r["seed"], with_prior, minutes, pri))
            jobs_short.append(_Job(r["seed"], short, minutes, pri))
        sessions[day2.name] = _map(jobs_none, workers)
        sessions[with_prior.name] = _map(jobs_prior, workers)
        sessions[short.name] = _map(jobs_short, workers)
    summary: dict[str, Any] = {}
    for name, rows in sessions.items():
        grid = {}
        for m in _MINUTE_GRID:
            if m > minutes:
                continue
            vals = np.array([regret_at(r["regret_trace"], m * 60.0) for r in rows])
            span = np.array([r["baseline_w"] - r["optimum_w"] for r in rows])
            pct = 100.0 * vals / span
            grid[f"{m:g}"] = {"regret_w_mean": float(np.nanmean(vals)),
                              "regret_w_median": float(np.nanmedian(vals)),
                              "regret_pct_mean": float(np.nanmean(pct)), "values_w": vals.tolist()}
        summary[name] = {"arm": rows[0]["arm"], "seeds": [r["seed"] for r in rows], "regret_at_min": grid,
                         "n_early_stops_mean": float(np.mean([r["n_early_stops"] for r in rows])),
                         "n_evaluations_mean": float(np.mean([len(r["evaluations"]) for r in rows])),
                         "wall_s_mean": float(np.mean([r["wall_s"] for r in rows]))}
    return {"test_seeds": list(test_seeds), "train_seeds": list(train_seeds), "minutes": minutes,
            "summary": summary, **extra, "wall_time_s": time.perf_counter() - wall0}


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m bridge.bench.thesis_study --out FILE [--test 201-210] [--train 101-110]``."""
    p = argparse.ArgumentParser(prog="python -m bridge.bench.thesis_study",
                                description=__doc__.splitlines()[0])
    p.add_argument("--test", default="201-210", help="test wearer seeds a-b (default 201-210)")
    p.add_argument("--train", default="101-110", help="training wearer seeds a-b (default 101-110)")
    p.add_argument("--minutes", type=float, default=60.0)
    p.add_argument("--workers", type=int, default=1)
    p.add_argument("--studies", nargs="+", default=["prior", "feature", "stopping"])
    p.add_argument("--error-weight", type=float, default=2.0)
    p.add_argument("--k-bo-wearers", type=int, default=3)
    p.add_argument("--out", required=True)
    a = p.parse_args(argv)

    def seeds(text: str) -> list[int]:
        lo, _, hi = text.partition("-")
        return list(range(int(lo), int(hi or lo) + 1))

    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(message)s")
    result = run_study(seeds(a.test), seeds(a.train), minutes=a.minutes, workers=a.workers,
                       studies=a.studies, error_weight=a.error_weight, k_bo_wearers=a.k_bo_wearers)
    out = Path(a.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_suffix(".tmp")
    tmp.write_text(json.dumps(result, indent=2) + "\n")
    os.replace(tmp, out)
    sys.stdout.write(f"{out}\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
