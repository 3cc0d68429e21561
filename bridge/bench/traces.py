"""Full-length breath traces and Algorithm 2's schedules: what the stopping-rule tuners share.

:mod:`bridge.bench.tune_stopping` (the σ-scaled rule's K or W), :mod:`bridge.bench.tune_sound`
(the sound rule's constants) and :mod:`bridge.bench.pairs` all replay the running estimate of
evaluations that ran every breath (Antonova 2016 §4.2: a full-length trajectory can replay any
rule that stops at or before its end). This module holds those replays so that the tuners need
not import each other.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from hilbo_core.errors import MeasurementError
from hilbo_core.metabolic import Estimator, MetabolicUKF
from hilbo_core.stopping import threshold_schedule

__all__ = ["BreathTrace", "breath_traces", "exploration_groups", "threshold_schedules"]


@dataclass(frozen=True)
class BreathTrace:
    """The running estimate of one full-length evaluation.

    Attributes:
        means: Estimated steady-state cost after each breath (W), shape (N,).
        vars: Its variance (W²), shape (N,).
        source: Where the breaths came from.
    """

    means: np.ndarray
    vars: np.ndarray
    source: str = ""

    @property
    def final_mean(self) -> float:
        """μ_N."""
        return float(self.means[-1])

    @property
    def final_var(self) -> float:
        """σ_N²."""
        return float(self.vars[-1])


def breath_traces(trajectories: Sequence[Any], n_max: int,
                  estimator_factory: Callable[[], Estimator] = MetabolicUKF,
                  sources: Sequence[str] | None = None) -> tuple[list[BreathTrace], int]:
    """Run the estimator over breath trajectories.

    Args:
        trajectories: Each an array-like of shape (n, 2): per breath ``(t_s, watts)`` with
            ``t_s`` the time since the setting began.
        n_max: N; trajectories with fewer breaths are skipped, longer ones use their first N.
        estimator_factory: A fresh estimator per trajectory (default the UKF of Kim et al. 2019 §II.C).
        sources: Labels of the trajectories (for errors and the result).

    Returns:
        (traces, number of trajectories skipped as too short).

    Raises:
        MeasurementError: A trajectory with non-finite values or times that do not increase
            (naming its index).
    """
    traces: list[BreathTrace] = []
    skipped = 0
    for i, traj in enumerate(trajectories):
        label = sources[i] if sources is not None else f"trajectory {i}"
        a = np.asarray(traj, dtype=float)
        if a.ndim != 2 or a.shape[1] != 2:
            raise MeasurementError(f"{label}: expected shape (n, 2) of (t_s, watts), got {a.shape}")
        if a.shape[0] < n_max:
            skipped += 1
            continue
        a = a[:n_max]
        if not np.all(np.isfinite(a)):
            raise MeasurementError(f"{label}: contains non-finite breaths")
        est = estimator_factory()
        means, variances = np.empty(n_max), np.empty(n_max)
        try:
            for b, (t, w) in enumerate(a):
                means[b], variances[b] = est.update(float(t), float(w))
        except MeasurementError as err:
            raise MeasurementError(f"{label}, breath {b}: {err}") from err
        traces.append(BreathTrace(means, variances, label))
    return traces, skipped


def exploration_groups(n: int, size: int, seed: int) -> np.ndarray:
    """For each trace j, ``size`` other traces standing in for its session's exploration bout."""
    rng = np.random.default_rng([seed, 0x57])
    size = min(size, n - 1)
    return np.array([rng.choice(np.delete(np.arange(n), j), size, replace=False) for j in range(n)])


def threshold_schedules(traces: Sequence[BreathTrace], window: int, groups: np.ndarray) -> np.ndarray:
    """Algorithm 2's schedule for each trace j from its group's traces: (n, N)."""
    M = np.array([t.means for t in traces])
    S = np.array([t.vars for t in traces])
    return np.array([threshold_schedule(M[g], S[g], window) for g in groups])
