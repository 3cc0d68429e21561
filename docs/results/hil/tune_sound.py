"""Tune the sound rule's min_decision_s and a_floor by BO-RESAMPLE on realistic-wearer trajectories.

usage: tune_sound.py FIRST_SEED N_WEARERS N_SETTINGS OUT.json [N_REAL]
(training wearers FIRST_SEED .. FIRST_SEED+N_WEARERS-1; keep them apart from the report subjects)
"""
import json
import sys

from bridge.bench.common import blas_threads
from bridge.bench.tune_sound import TuneSoundConfig, realistic_trajectories, tune_sound
from hilbo_core.presets import preset

blas_threads(1)
first, n_wearers, n_settings, out = int(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3]), sys.argv[4]
trajs, truth = [], []
for seed in range(first, first + n_wearers):
    t, c = realistic_trajectories(preset("hip_6d"), seed, n_settings)
    trajs += t
    truth += c
n_real = int(sys.argv[5]) if len(sys.argv) > 5 else TuneSoundConfig.n_real
res = tune_sound(trajs, TuneSoundConfig(n_real=n_real), truth=truth)
res["train_seeds"] = [first, first + n_wearers - 1]
with open(out, "w") as fh:
    json.dump(res, fh, indent=1)
g = {(r["min_decision_s"], r["a_floor"]): r for r in res["grid"]}
sys.stdout.write(json.dumps({"recommended": res["recommended"], "stats": res["recommended_stats"],
                             "grid_best": res["grid_best"], "default_60_1.0": g[(60.0, 1.0)]}) + "\n")
