"""stop_stats.py with the estimator's data-only variance multiplied by VSCALE (a diagnostic).

usage: VSCALE=1.5 variance_scale.py NAME STOPPING A_FLOOR MIN_DECISION_S N_SUBJECTS [... as stop_stats.py]

Every variance the sound rule and the GP take from the breath estimator (the data-only
(mean, var) of :meth:`~hilbo_core.estimation.TransitionEstimator.data_only`: the candidate's side
of the rule and the GP's observations, so the GP-posterior incumbent too) is multiplied by
VSCALE; nothing else changes. It asks how much of the sound rule's wrong rejections on a wearer
come from an estimator σ that is too small there (docs/results.md, "Whole sessions against CMA-ES").
"""
import os
import runpy
import sys
from pathlib import Path

from hilbo_core import estimation

VS = float(os.environ.get("VSCALE", "1"))
_data_only = estimation.TransitionEstimator.data_only


def data_only(self: estimation.TransitionEstimator) -> tuple[float, float]:
    mean, var = _data_only(self)
    return mean, VS * var


estimation.TransitionEstimator.data_only = data_only  # type: ignore[method-assign]
sys.argv = ["stop_stats.py", *sys.argv[1:]]
runpy.run_path(str(Path(__file__).with_name("stop_stats.py")), run_name="__main__")
