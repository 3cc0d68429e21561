"""Stop statistics + regret of BO sessions on a simulated wearer (the sound rule's stop targets).

usage: stats.py NAME STOPPING A_FLOOR MIN_DECISION_S N_SUBJECTS [DRIFT REMEASURE BETA ACCEPT_Z FIRST_SEED
                WEARER SPACE]

(FIRST_SEED 1, WEARER realistic, SPACE hip_6d by default)
"""
import json
import sys

import numpy as np

import bridge.sim.core as insim
from bridge.bench.common import blas_threads
from bridge.sim.core import SimConfig, run_insim
from hilbo_core.presets import preset
from virtual_hw.wearer import make_wearer

blas_threads(1)
name, stopping = sys.argv[1], sys.argv[2]
a_floor, min_s, n = float(sys.argv[3]), float(sys.argv[4]), int(sys.argv[5])
_orig = insim.HILOptimizer
drift = float(sys.argv[6]) if len(sys.argv) > 6 and sys.argv[6] != "none" else None
remeasure = float(sys.argv[7]) if len(sys.argv) > 7 and sys.argv[7] != "none" else None
beta = float(sys.argv[8]) if len(sys.argv) > 8 else 1.0
# ACCEPT_Z: a number, or none (off); absent: the optimizer's default (3 since 2026-12-05, off before)
accept = {"accept_z": None if sys.argv[9] == "none" else float(sys.argv[9])} if len(sys.argv) > 9 else {}
first = int(sys.argv[10]) if len(sys.argv) > 10 else 1
wearer_kind = sys.argv[11] if len(sys.argv) > 11 else "realistic"
space = sys.argv[12] if len(sys.argv) > 12 else "hip_6d"
if stopping == "sound":
    insim.HILOptimizer = lambda space, **kw: _orig(space, a_floor=a_floor, min_decision_s=min_s,
                                                   drift_hours=drift, remeasure_best_s=remeasure,
                                                   recommend_beta=beta, **accept, **kw)
rows, regrets, r20, r30 = [], [], [], []
for seed in range(first, first + n):
    judge = make_wearer(wearer_kind, preset(space), seed=seed)
    _, opt_cost = judge.true_optimum
    red = judge.baseline_cost_w - opt_cost
    trace = []

    def on_eval(rec, opt, trace=trace, judge=judge, opt_cost=opt_cost):
        ev = rec.evaluation
        if ev.phase == "optimization" and opt.incumbent is not None:
            rows.append((ev.breaths, ev.duration_s, ev.reason == "threshold", ev.reason == "decided",
                         judge.true_cost_w(ev.params), judge.true_cost_w(opt.incumbent[0])))
        trace.append((rec.t_end, judge.true_cost_w(opt.best()[0]) - opt_cost))

    run_insim(SimConfig(minutes=60, seed=seed, preset=space, stopping=stopping, refit="at_proposal",
                        wearer=wearer_kind),
              on_evaluation=on_eval)
    regrets.append(100 * trace[-1][1] / red)
    for lst, t_min in ((r20, 20), (r30, 30)):
        before = [r for t, r in trace if t <= 60.0 * t_min]
        lst.append(100 * before[-1] / red if before else np.nan)
a = np.array(rows, dtype=float)
better = a[:, 4] < a[:, 5]
res = {"name": name, "subjects": n, "opt_evaluations": len(a),
       "mean_breaths": round(float(a[:, 0].mean()), 1),
       "pct_end_within_30s": round(100 * float((a[:, 1] < 30).mean()), 1),
       "pct_early": round(100 * float(a[:, 2].mean()), 1),
       "pct_decided": round(100 * float(a[:, 3].mean()), 1),
       "truly_better": int(better.sum()),
       "pct_truly_better_rejected": round(100 * float(a[better, 2].mean()), 1) if better.any() else None,
       "median_regret_pct_20min": round(float(np.nanmedian(r20)), 1),
       "median_regret_pct_30min": round(float(np.nanmedian(r30)), 1),
       "median_regret_pct_final": round(float(np.median(regrets)), 1),
       # per subject (first, first + 1, ...), for paired comparisons between rules
       "regret_pct_20min": [round(float(v), 2) for v in r20],
       "regret_pct_30min": [round(float(v), 2) for v in r30],
       "regret_pct_final": [round(float(v), 2) for v in regrets]}
sys.stdout.write(json.dumps(res) + "\n")
