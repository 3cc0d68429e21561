"""Calibration of the sound rule's two sides in whole sessions: the incumbent and the candidate.

usage: incumbent_bias.py N_SUBJECTS WEARER SPACE [FIRST_SEED]

For every optimisation-phase evaluation of 60-minute `sound` sessions (the defaults) it takes the
last stop decision and compares, against the wearer's true cost at the evaluation's end:

* the incumbent (μ*, σ*²): the GP posterior at x* (z = (μ* − true(x*)) / σ*);
* the candidate's estimate as the rule saw it (the data-only estimate × the GP predictive) and
  the data-only estimate alone (z against true(x_t));

and, for the truly better candidates the threshold rejected, by how much they were better (% of
the incumbent's true cost). Prints one JSON line.
"""
import json
import sys

import numpy as np

import bridge.sim.core as insim
from bridge.bench.common import blas_threads
from bridge.sim.core import SimConfig, run_insim
from hilbo_core import stopping
from hilbo_core.presets import preset
from virtual_hw.wearer import make_wearer

blas_threads(1)
n, wearer_kind, space = int(sys.argv[1]), sys.argv[2], sys.argv[3]
first = int(sys.argv[4]) if len(sys.argv) > 4 else 1

last: dict[str, tuple[float, ...]] = {}
_decide = stopping.SoundRule.decide
_candidate = insim.HILOptimizer._candidate_estimate


def decide(self, i, mean, var, best_mean, best_var, t_s=None):
    last["rule"] = (mean, var, best_mean, best_var)
    return _decide(self, i, mean, var, best_mean, best_var, t_s=t_s)


def candidate(self, mean, var):
    last["data"] = self._estimator.data_only()
    return _candidate(self, mean, var)


stopping.SoundRule.decide = decide
insim.HILOptimizer._candidate_estimate = candidate
inc_z, fused_z, data_z, margins = [], [], [], []
n_better = 0
for seed in range(first, first + n):
    judge = make_wearer(wearer_kind, preset(space), seed=seed)

    def on_eval(rec, opt, judge=judge):
        global n_better
        ev = rec.evaluation
        if ev.phase == "optimization" and opt.incumbent is not None and "rule" in last:
            mean, var, best_mean, best_var = last["rule"]
            true_c = judge.true_cost_w(ev.params, rec.t_end)
            true_i = judge.true_cost_w(opt.incumbent[0], rec.t_end)
            inc_z.append((best_mean - true_i) / np.sqrt(best_var))
            fused_z.append((mean - true_c) / np.sqrt(var))
            d_mean, d_var = last.get("data", (mean, var))
            data_z.append((d_mean - true_c) / np.sqrt(d_var))
            if true_c < true_i:
                n_better += 1
                if ev.reason == "threshold":
                    margins.append(100.0 * (true_i - true_c) / true_i)
        last.clear()

    run_insim(SimConfig(minutes=60, seed=seed, preset=space, stopping="sound", refit="at_proposal",
                        wearer=wearer_kind), on_evaluation=on_eval)


def summary(z: list[float]) -> dict[str, float]:
    a = np.asarray(z)
    return {"mean": round(float(a.mean()), 2), "sd": round(float(a.std(ddof=1)), 2)}


sys.stdout.write(json.dumps({
    "wearer": wearer_kind, "space": space, "subjects": n, "evaluations": len(inc_z),
    "incumbent_z": summary(inc_z), "candidate_as_seen_z": summary(fused_z),
    "candidate_data_only_z": summary(data_z), "truly_better": n_better,
    "rejected_truly_better": len(margins),
    "rejected_margin_pct_median": round(float(np.median(margins)), 2) if margins else None,
    "rejected_margin_pct_max": round(float(np.max(margins)), 2) if margins else None}) + "\n")
