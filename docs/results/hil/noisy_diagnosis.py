"""Why a ``sound`` session on the noisy wearer ends above 50 % regret: one line per subject.

Re-runs the default (``sound``; ``--method``: another BO method of ``hilbo bench hil``) session
of each chosen subject exactly as ``hilbo bench hil`` does (same seed, same wearer, same
protocol) and prints, as one JSON line per subject:

* the landscape: ``family``, ``reduction_w`` (unassisted minus optimum), the share of random
  feasible settings below 30 % / 50 % regret (``share_lt30``, ``share_lt50``) and their median
  regret (``random_median_pct``);
* the measurements: the median SD of a full evaluation's estimate (``full_sd_w``), ``snr`` =
  reduction / that SD, the estimates' z against the true cost (``z_median``, ``z_sd``; a
  calibrated estimator has SD ≈ 1), and how much of the estimates' error is the wearer's slow
  drift and adaptation (``drift_share``: 1 − var(error − drift part) / var(error), the drift
  part being the true cost times the drift-and-adaptation factor minus 1 at the evaluation's end);
* the search: the optimisation proposals' median true regret (``proposals_median_pct``, against
  ``random_median_pct``) and their median distance from the domain's centre in the unit cube
  (``proposals_centre_dist``, random feasible settings: ``random_centre_dist``); the best setting
  ever measured (``best_measured_pct``);
* the recommendation at 30 and 60 min (``rec30_pct``, ``rec60_pct``) and the GP's fitted
  hyperparameters at the end (``lengthscales``, ``signal_var``, ``noise_var``; standardised
  units; the length-scale prior's median is √d/4 = 0.61 in 6-D).

``--variant`` runs the same subjects on the noisy wearer with one error source removed
(``nodrift``: drift SD 0; ``nooutlier``: no outlier breaths; ``cv10``: the default wearer's
breath CV of 8-12 % with the noisy wearer's 3 % outliers): the landscape and every other draw of
the subject are the same, so the change in ``rec60_pct`` is that error source's doing.

Usage::

    python docs/results/hil/noisy_diagnosis.py 9 43 45 48 [--variant nodrift]
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from typing import Any

import numpy as np

from bridge.bench.hil import _BO_VARIANTS
from bridge.sim import core
from bridge.sim.core import SimConfig, run_insim
from hilbo_core.presets import preset
from virtual_hw.wearer import NOISY_BREATH_CV, NOISY_OUTLIER_FRAC
from virtual_hw.wearer_realistic import RealisticWearer, RealisticWearerConfig

SPACE = "hip_6d"
NOISY: dict[str, Any] = {"noise_cv": NOISY_BREATH_CV, "outlier_frac": NOISY_OUTLIER_FRAC}
VARIANTS: dict[str, dict[str, Any]] = {
    "noisy": NOISY,
    "nodrift": {**NOISY, "drift_sd": (0.0, 0.0)},
    "nooutlier": {**NOISY, "outlier_frac": (0.0, 0.0)},
    "cv10": {"outlier_frac": NOISY_OUTLIER_FRAC},
}
N_RANDOM = 1500  # random feasible settings for the landscape's shares and medians


def diagnose(seed: int, variant: str, method: str = "sound") -> dict[str, Any]:
    """One subject's session and its diagnosis (see the module docstring for the keys)."""
    space = preset(SPACE)
    config = RealisticWearerConfig(**VARIANTS[variant])
    # Every wearer of the session is this variant's (the subject's draws do not depend on the
    # ranges' values, only on their count, so the landscape is the noisy wearer's).
    core.make_wearer = lambda _kind, sp, seed, **_kw: RealisticWearer(sp, seed=seed, config=config)
    judge = RealisticWearer(space, seed=seed, config=config)
    x_opt, c_opt = judge.true_optimum
    reduction = judge.baseline_cost_w - c_opt

    def regret_pct(params: dict[str, float]) -> float:
        return 100.0 * (judge.true_cost_w(params) - c_opt) / reduction

    rng = np.random.default_rng([seed, 0xD1A6])
    U = space.sample_unit(N_RANDOM, rng)
    rand = np.array([regret_pct(space.to_dict(space.from_unit(u))) for u in U])

    recs: list[tuple[float, dict[str, float]]] = []
    hyp: list[Any] = []

    def on_eval(rec: Any, opt: Any) -> None:
        recs.append((rec.t_end, opt.best()[0]))
        hyp.append(opt._hyp)  # the last fitted hyperparameters (diagnosis only)

    stopping, protocol, options, protocol_options = _BO_VARIANTS[method]
    summary = run_insim(SimConfig(minutes=60, seed=seed, preset=SPACE, stopping=stopping,
                                  refit="at_proposal", wearer="noisy", protocol=protocol,
                                  options=options, protocol_options=protocol_options),
                        on_evaluation=on_eval)
    evals = [e for e in summary["evaluations"] if e["reason"] != "budget"]
    full = [e for e in evals if not e["stopped_early"]]
    err = np.array([e["mean"] - judge.true_cost_w(e["params"]) for e in full])
    drift = np.array([judge.true_cost_w(e["params"])
                      * (judge.drift_factor(e["t_end"]) * judge.adaptation_factor(e["t_end"]) - 1.0)
                      for e in full])
    sd = np.array([math.sqrt(e["var"]) for e in full])
    proposals = [e for e in evals if e["phase"] == "optimization"]
    centre = [float(np.linalg.norm(space.to_unit(space.from_dict(e["params"])) - 0.5))
              for e in proposals]
    rec30 = [p for t, p in recs if t <= 1800.0]
    last = hyp[-1]
    return {
        "seed": seed, "variant": variant, "method": method, "family": judge.family.value,
        "reduction_w": round(reduction, 1),
        "share_lt30": round(float(np.mean(rand < 30.0)), 3),
        "share_lt50": round(float(np.mean(rand < 50.0)), 3),
        "random_median_pct": round(float(np.median(rand)), 1),
        "full_sd_w": round(float(np.median(sd)), 1),
        "snr": round(reduction / float(np.median(sd)), 2),
        "z_median": round(float(np.median(err / sd)), 2),
        "z_sd": round(float(np.std(err / sd)), 2),
        "drift_share": round(1.0 - float(np.var(err - drift) / np.var(err)), 2),
        "proposals_median_pct": round(float(np.median([regret_pct(e["params"]) for e in proposals])), 1),
        "proposals_centre_dist": round(float(np.median(centre)), 2),
        "random_centre_dist": round(float(np.median(np.linalg.norm(U - 0.5, axis=1))), 2),
        "best_measured_pct": round(min(regret_pct(e["params"]) for e in evals), 1),
        "rec30_pct": round(regret_pct(rec30[-1]), 1) if rec30 else None,
        "rec60_pct": round(regret_pct(recs[-1][1]), 1),
        "optimum_unit": [round(float(v), 2) for v in space.to_unit(space.from_dict(x_opt))],
        "n_evaluations": len(evals), "n_early_stops": sum(e["stopped_early"] for e in evals),
        "lengthscales": None if last is None else [round(v, 2) for v in last.lengthscales],
        "signal_var": None if last is None else round(last.signal_var, 2),
        "noise_var": None if last is None else round(last.noise_var, 3),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("seeds", nargs="+", type=int, help="subject seeds")
    parser.add_argument("--variant", choices=sorted(VARIANTS), default="noisy")
    parser.add_argument("--method", choices=sorted(_BO_VARIANTS), default="sound",
                        help="the BO method of hilbo bench hil to re-run (default: sound)")
    args = parser.parse_args()
    for seed in args.seeds:
        sys.stdout.write(json.dumps(diagnose(seed, args.variant, args.method)) + "\n")
        sys.stdout.flush()


if __name__ == "__main__":
    main()
