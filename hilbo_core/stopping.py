"""Stopping rules for the metabolic estimate of one setting (Kim et al. 2019 §II.D, Algorithms 1 and 2).

After every measurement i of a setting x_t the optimizer compares the estimate
``N(μ_xt, σ²_xt)`` with the best setting so far ``N(μ_x*, σ²_x*)``: with ``μ = μ_xt − μ_x*`` and
``σ² = σ²_xt + σ²_x*`` it stops as soon as ``μ > A_i·σ`` (the setting is confidently worse), or
after the N-th measurement. :func:`threshold_schedule` computes the schedule A from the
exploration traces (Algorithm 2); :class:`SigmaScaledRule` applies it (Algorithm 1, lines 13–20);
:class:`FixedIntervalRule` never stops early (the fixed-interval baseline). :class:`SoundRule`
(the optimizer's rule) is the σ-scaled rule made safe: no decision before
``min_decision_s`` in the setting, and a threshold floored at ``a_floor`` ≥ 0, so a candidate that
looks at least as good as the incumbent is never stopped; with ``boundary_s`` (the optimizer's
default) its reject and accept boundaries are sequential ones, strict early and relaxing to their
late levels as the evidence grows (O'Brien–Fleming-shaped), instead of a fixed clock.

Indices are 0-based: ``A[i]`` belongs to the (i+1)-th measurement, and ``i == N−1`` is the last.
"""

from __future__ import annotations

import enum
import math
import operator
from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np
import numpy.typing as npt

from hilbo_core.errors import ConfigError, MeasurementError

__all__ = [
    "FixedIntervalRule",
    "SigmaScaledRule",
    "SoundRule",
    "StopDecision",
    "StopReason",
    "StoppingRule",
    "threshold_schedule",
]


def _as_index(value: object, name: str) -> int:
    """An integer (not bool) argument, else ConfigError."""
    if isinstance(value, bool):
        raise ConfigError(f"{name}={value!r} must be an integer, not a bool")
    try:
        return operator.index(value)  # type: ignore[arg-type]
    except TypeError as err:
        raise ConfigError(f"{name}={value!r} must be an integer") from err


def _check_traces(name: str, arr: npt.NDArray[np.float64], positive: bool) -> None:
    """Raise MeasurementError naming the first non-finite (or non-positive) entry of ``arr``."""
    bad = ~np.isfinite(arr)
    if positive:
        bad |= ~(arr > 0.0)
    if bad.any():
        r, c = (int(k) for k in np.argwhere(bad)[0])
        what = "a finite variance > 0" if positive else "finite"
        raise MeasurementError(f"{name}[{r}, {c}]={float(arr[r, c])!r} must be {what}")


def threshold_schedule(
    M: npt.ArrayLike,  # Kim et al. 2019's name for the matrix of means
    S: npt.ArrayLike,  # Kim et al. 2019's Σ
    window: int,
) -> npt.NDArray[np.float64]:
    """Threshold schedule A from exploration traces (Kim et al. 2019 Algorithm 2).

    Each exploration point is treated as if its own final estimate were the best so far:
    ``X_ij = (M_ij − M_iN) / sqrt(S_ij + S_iN)``, and ``A_i`` is the largest X over all rows and
    over the columns ``i−W ≤ c ≤ i+W`` (clipped to the array) — the most risk-averse threshold
    near measurement i. ``A[N−1] ≥ 0`` always, because column N−1 of X is zero.

    Args:
        M: Shape (n_explore, N): mean of the estimate after each measurement of each
            exploration point.
        S: Shape (n_explore, N): the matching variances (> 0).
        window: W ≥ 0, in measurements (Kim et al. 2019's simulations use 2).

    Returns:
        A, shape (N,).

    Raises:
        ConfigError: Bad shapes or window.
        MeasurementError: A non-finite mean, or a variance that is not finite and positive.
    """
    w = _as_index(window, "window")
    if w < 0:
        raise ConfigError(f"window={window!r} must be >= 0 measurements")
    means = np.asarray(M, dtype=float)
    variances = np.asarray(S, dtype=float)
    if means.ndim != 2 or means.shape[0] < 1 or means.shape[1] < 1:
        raise ConfigError(f"M must have shape (n_explore >= 1, N >= 1), got {means.shape}")
    if variances.shape != means.shape:
        raise ConfigError(f"S must have the shape of M {means.shape}, got {variances.shape}")
    _check_traces("M", means, positive=False)
    _check_traces("S", variances, positive=True)

    # Algorithm 2, lines 4–10: standardised distance of every trace point from its final value.
    x = (means - means[:, -1:]) / np.sqrt(variances + variances[:, -1:])
    # Lines 11–13: max over rows, then a sliding max over columns i−W..i+W. A window wider than
    # N−1 already covers every column, so clip it (keeps the padding small for any W).
    col_max = x.max(axis=0)
    n = col_max.shape[0]
    w = min(w, n - 1)
    padded = np.pad(col_max, w, mode="constant", constant_values=-np.inf)
    return np.lib.stride_tricks.sliding_window_view(padded, 2 * w + 1).max(axis=1)


class StopReason(enum.Enum):
    """Why a rule decided as it did after a measurement."""

    CONTINUE = "continue"
    THRESHOLD = "threshold"
    MAX_MEASUREMENTS = "max_measurements"
    DECIDED = "decided"  # the sound rule's accept stop: confidently better, not a rejection


@dataclass(frozen=True)
class StopDecision:
    """A stopping rule's decision after one measurement.

    Attributes:
        stop: True to stop measuring this setting now.
        reason: CONTINUE, THRESHOLD (confidently worse than the best), MAX_MEASUREMENTS or
            DECIDED (confidently better: the sound rule's ``accept_z``).
        index: 0-based measurement index i within the evaluation.
        z: μ/σ, the standardised difference from the best setting (positive = worse).
        threshold: A_i used at this index, or None for a rule without thresholds.
    """

    stop: bool
    reason: StopReason
    index: int
    z: float
    threshold: float | None


@runtime_checkable
class StoppingRule(Protocol):
    """A rule deciding after every measurement whether to stop evaluating a setting."""

    @property
    def n_max(self) -> int:
        """N, the maximum number of measurements per setting."""
        ...

    def decide(
        self, i: int, mean: float, var: float, best_mean: float, best_var: float
    ) -> StopDecision:
        """Decision after measurement ``i`` (0-based) given the current and best estimates."""
        ...


def _difference(
    i: int, n_max: int, mean: float, var: float, best_mean: float, best_var: float
) -> tuple[int, float, float]:
    """Validate a decide() call; return (i, μ, σ) of the difference to the best (§II.D)."""
    idx = _as_index(i, "i")
    if not 0 <= idx < n_max:
        raise ConfigError(f"measurement index i={i!r} must be in [0, {n_max - 1}]")
    values = {"mean": mean, "var": var, "best_mean": best_mean, "best_var": best_var}
    for name, value in values.items():
        v = float(value)
        if not math.isfinite(v):
            raise MeasurementError(f"{name}={value!r} must be finite")
        if name.endswith("var") and v < 0.0:
            raise MeasurementError(f"{name}={value!r} must be a variance >= 0")
    sigma_sq = float(var) + float(best_var)
    if sigma_sq <= 0.0:
        raise MeasurementError(
            f"var={var!r} + best_var={best_var!r} must be > 0 for a σ-scaled comparison"
        )
    return idx, float(mean) - float(best_mean), math.sqrt(sigma_sq)


class SigmaScaledRule:
    """σ-scaled offset rule with a threshold schedule (Kim et al. 2019 §II.D, Algorithm 1 l. 13–20).

    After measurement i, with ``μ = mean − best_mean`` and ``σ² = var + best_var``, stop with
    THRESHOLD if ``μ > A[i]·σ``; at the last index ``i == N−1`` the evaluation is complete and the
    reason is MAX_MEASUREMENTS (so a stop counts as *early* exactly when its reason is THRESHOLD).

    Args:
        thresholds: A, shape (N,), N ≥ 1, finite (e.g. from :func:`threshold_schedule`).

    Raises:
        ConfigError: Wrong shape, empty, or non-finite thresholds.
    """

    def __init__(self, thresholds: npt.ArrayLike) -> None:
        a = np.array(thresholds, dtype=float)  # a private copy the caller cannot mutate
        if a.ndim != 1 or a.shape[0] < 1:
            raise ConfigError(f"thresholds must have shape (N >= 1,), got {a.shape}")
        if not np.isfinite(a).all():
            k = int(np.flatnonzero(~np.isfinite(a))[0])
            raise ConfigError(f"thresholds[{k}]={a[k]!r} must be finite")
        a.flags.writeable = False
        self._thresholds = a

    @classmethod
    def constant(cls, k: float, n_max: int) -> SigmaScaledRule:
        """The σ-scaled offset with a single K for every measurement (Kim et al. 2019 §II.D).

        Args:
            k: The offset K in units of σ (finite).
            n_max: N ≥ 1.
        """
        n = _as_index(n_max, "n_max")
        if n < 1:
            raise ConfigError(f"n_max={n_max!r} must be >= 1")
        if not math.isfinite(float(k)):
            raise ConfigError(f"k={k!r} must be finite")
        return cls(np.full(n, float(k)))

    @property
    def n_max(self) -> int:
        """N, the length of the threshold schedule."""
        return int(self._thresholds.shape[0])

    @property
    def thresholds(self) -> npt.NDArray[np.float64]:
        """The schedule A, shape (N,) (read-only)."""
        return self._thresholds

    def decide(
        self, i: int, mean: float, var: float, best_mean: float, best_var: float
    ) -> StopDecision:
        """Decide after measurement ``i`` (0-based).

        Args:
            i: Measurement index within the evaluation, 0 ≤ i < N.
            mean: Current estimate's mean.
            var: Current estimate's variance (≥ 0).
            best_mean: Mean of the best setting so far.
            best_var: Its variance (≥ 0); ``var + best_var`` must be > 0.

        Raises:
            ConfigError: ``i`` out of range or not an integer.
            MeasurementError: Non-finite input or a negative/zero total variance.
        """
        idx, mu, sigma = _difference(i, self.n_max, mean, var, best_mean, best_var)
        a_i = float(self._thresholds[idx])
        z = mu / sigma
        if idx == self.n_max - 1:
            return StopDecision(True, StopReason.MAX_MEASUREMENTS, idx, z, a_i)
        # Compare μ > A_i·σ as Kim et al. 2019 write it (not z > A_i) so boundary cases are exact.
        if mu > a_i * sigma:
            return StopDecision(True, StopReason.THRESHOLD, idx, z, a_i)
        return StopDecision(False, StopReason.CONTINUE, idx, z, a_i)


class FixedIntervalRule:
    """Never stops early: MAX_MEASUREMENTS after measurement ``n_max − 1`` (the baseline).

    Args:
        n_max: N ≥ 1 measurements per setting.

    Raises:
        ConfigError: ``n_max`` is not an integer ≥ 1.
    """

    def __init__(self, n_max: int) -> None:
        n = _as_index(n_max, "n_max")
        if n < 1:
            raise ConfigError(f"n_max={n_max!r} must be >= 1")
        self._n_max = n

    @property
    def n_max(self) -> int:
        """N, the number of measurements per setting."""
        return self._n_max

    def decide(
        self, i: int, mean: float, var: float, best_mean: float, best_var: float
    ) -> StopDecision:
        """Decide after measurement ``i``; z is reported for logging, threshold is None.

        Raises:
            ConfigError: ``i`` out of range or not an integer.
            MeasurementError: Non-finite input or a negative/zero total variance.
        """
        idx, mu, sigma = _difference(i, self._n_max, mean, var, best_mean, best_var)
        if idx == self._n_max - 1:
            return StopDecision(True, StopReason.MAX_MEASUREMENTS, idx, mu / sigma, None)
        return StopDecision(False, StopReason.CONTINUE, idx, mu / sigma, None)


class SoundRule:
    """The σ-scaled rule with a time floor, a threshold floor and, optionally, a sequential boundary.

    After measurement i at ``t_s`` seconds into the setting, with ``μ = mean − best_mean`` and
    ``σ² = var + best_var``: no decision while ``t_s < min_decision_s``; after that, stop with
    THRESHOLD if ``μ > max(A_i, a_floor·s(t))·σ``; MAX_MEASUREMENTS at ``i == N−1``. Without
    ``boundary_s`` the scale is ``s(t) = 1`` (a fixed clock: the floor rule); with it,
    ``s(t) = sqrt(max(1, boundary_s / t))`` (the sequential boundary, below). Why the floors:

    * **Time.** The first breaths of a setting are dominated by the previous setting: with the
      first-order response of τ (the estimator's prior: median 25 s, 95 % in 11–55 s, Poole &
      Jones 2012, Compr Physiol 2:933; ≈ 42 s for the whole metabolic response to a walking
      step, Selinger & Donelan 2014, J Appl Physiol 117:1406) the previous level still makes up
      e^{−t/τ} of the signal: 30 % at 30 s for τ = 25 s, 49 % for τ = 42 s. Before ~30 s the
      breaths say more about where the body came from than where it is going, so no σ can make
      a decision there trustworthy: ``min_decision_s`` is a hard floor (60 s for the floor rule,
      ≈ 1.5 τ at 42 s; 30 s with the sequential boundary, which guards 30–60 s itself). It also
      makes "≤ 5 % of evaluations end within 30 s" hold by construction (only budget ends can).
    * **Threshold.** Algorithm 2's A_i can be negative (its median at breath 1 was measured
      at −0.29), which stops candidates that look *better* than the incumbent. With a floor
      ``a_floor ≥ 0`` a stop always needs ``μ > 0`` (and by a margin of ``a_floor``·s(t)·σ), so a
      candidate whose estimate is at or below the incumbent's is never rejected.
    * **Sequential boundary** (``boundary_s``). The rule tests after every breath; the error of
      a repeated test accumulates, so early looks need a stricter bound than late ones. The
      group-sequential answer is a boundary that is constant on the score scale ``z·sqrt(I)``
      (I: the information so far, as a fraction of the information at which the late level
      applies): O'Brien & Fleming 1979 (Biometrics 35:549), the shape of Lan & DeMets 1983's
      (Biometrika 70:659) O'Brien–Fleming-type α-spending; Jennison & Turnbull 2000
      (*Group Sequential Methods*, ch. 2 and 7). With information growing like the time in
      the setting, the boundary on z is ``level·sqrt(boundary_s / t)`` until ``boundary_s`` and
      the late ``level`` after it: 1.41·level at 30 s, 1.15·level at 45 s. For a Brownian score
      the reflection principle bounds the chance of ever crossing such a boundary before
      ``boundary_s`` by twice the chance of crossing the late level at one look (2·(1 − Φ(level))
      at zero true difference), where a constant bound looked at every breath has no such
      bound. The margin in watts, ``level·s(t)·σ_t``, is wide early twice over: σ_t itself
      still carries the estimator's transition and model-error terms. After ``boundary_s`` the
      σ is dominated by terms that persist from breath to breath (the incumbent's error, the
      steady state's drift), so the late looks are strongly correlated and the constant late
      level is what the floor rule already used. So a rejection before the old 60 s clock
      needs a candidate decisively worse, and the decision time follows the evidence.

    Optionally (``accept_z``; with the sequential boundary it is scaled by ``s(t)`` too) the rule
    also ends an evaluation whose comparison is already decided the other way: after
    ``min_decision_s``, stop with DECIDED if ``μ < −accept_z·s(t)·σ`` — the candidate is better
    than the incumbent by ``accept_z`` standard deviations, so more breaths would rarely change
    that it beats the incumbent. It is not a rejection: its estimate goes to the GP like any
    other (with its wider variance).

    Args:
        thresholds: A, shape (N,), finite (Algorithm 2's schedule, or a constant).
        min_decision_s: No decision before this many seconds in the setting (≥ 0).
        a_floor: Lower bound of every threshold, in σ (finite, ≥ 0): the reject boundary's late
            level.
        accept_z: Accept-stop margin in σ (finite, ≥ 0): the accept boundary's late level; or
            None (default) for no accept stop.
        boundary_s: Seconds in the setting at which the sequential boundaries reach their late
            levels (finite, > 0), or None (default) for the floor rule's fixed clock.

    Raises:
        ConfigError: Bad thresholds, a negative or non-finite ``min_decision_s``, ``a_floor`` or
            ``accept_z``, or a ``boundary_s`` that is not a finite number > 0.
    """

    def __init__(self, thresholds: npt.ArrayLike, *, min_decision_s: float = 60.0,
                 a_floor: float = 1.0, accept_z: float | None = None,
                 boundary_s: float | None = None) -> None:
        base = SigmaScaledRule(thresholds)  # validates the schedule
        checks: list[tuple[str, object, bool]] = [("min_decision_s", min_decision_s, False),
                                                  ("a_floor", a_floor, False)]
        if accept_z is not None:
            checks.append(("accept_z", accept_z, False))
        if boundary_s is not None:
            checks.append(("boundary_s", boundary_s, True))
        for name, value, positive in checks:
            if isinstance(value, bool) or not isinstance(value, int | float | np.integer | np.floating) \
                    or not (math.isfinite(value) and (value > 0.0 if positive else value >= 0.0)):
                raise ConfigError(f"{name}={value!r}; expected a finite number {'>' if positive else '>='} 0")
        a = np.maximum(base.thresholds, float(a_floor))
        a.flags.writeable = False
        self._raw = base.thresholds
        self._thresholds = a
        self._boundary_s = None if boundary_s is None else float(boundary_s)
        self._min_decision_s = float(min_decision_s)
        self._a_floor = float(a_floor)
        self._accept_z = None if accept_z is None else float(accept_z)

    @property
    def n_max(self) -> int:
        """N, the length of the threshold schedule."""
        return int(self._thresholds.shape[0])

    @property
    def thresholds(self) -> npt.NDArray[np.float64]:
        """The floored schedule max(A, a_floor), shape (N,) (read-only)."""
        return self._thresholds

    @property
    def min_decision_s(self) -> float:
        """Seconds in the setting before the first threshold decision."""
        return self._min_decision_s

    @property
    def a_floor(self) -> float:
        """The threshold floor, in σ."""
        return self._a_floor

    @property
    def accept_z(self) -> float | None:
        """The accept-stop margin in σ, or None (no accept stop)."""
        return self._accept_z

    @property
    def boundary_s(self) -> float | None:
        """Seconds at which the sequential boundaries reach their late levels, or None."""
        return self._boundary_s

    def scale(self, t_s: float) -> float:
        """The boundaries' factor ``s(t) = sqrt(max(1, boundary_s / t))`` at ``t_s`` (1 without
        ``boundary_s``; +inf at t = 0 with it: no look at time 0 can decide)."""
        if self._boundary_s is None or t_s >= self._boundary_s:
            return 1.0
        return math.inf if t_s <= 0.0 else math.sqrt(self._boundary_s / t_s)

    def decide(
        self, i: int, mean: float, var: float, best_mean: float, best_var: float,
        t_s: float | None = None,
    ) -> StopDecision:
        """Decide after measurement ``i`` (0-based), taken ``t_s`` seconds into the setting.

        Args:
            i: Measurement index within the evaluation, 0 ≤ i < N.
            mean: Current estimate's mean.
            var: Current estimate's variance (≥ 0).
            best_mean: The incumbent's mean (the GP posterior at x*).
            best_var: Its variance (≥ 0); ``var + best_var`` must be > 0.
            t_s: Time of the measurement since the setting began (s, finite, ≥ 0); required.

        Raises:
            ConfigError: ``i`` out of range or not an integer; ``t_s`` missing or invalid.
            MeasurementError: Non-finite input or a negative/zero total variance.
        """
        idx, mu, sigma = _difference(i, self.n_max, mean, var, best_mean, best_var)
        if t_s is None or isinstance(t_s, bool) or not math.isfinite(float(t_s)) or float(t_s) < 0.0:
            raise ConfigError(f"t_s={t_s!r}; the sound rule needs the finite time >= 0 s of the "
                              "measurement since the setting began")
        t = float(t_s)
        k = self.scale(t)
        # The reject threshold: Algorithm 2's A_i, at least the floor scaled by the boundary
        # (infinite at t = 0 with a boundary, where 0·inf would be undefined).
        a_i = math.inf if math.isinf(k) else max(float(self._raw[idx]), self._a_floor * k)
        z = mu / sigma
        if idx == self.n_max - 1:
            return StopDecision(True, StopReason.MAX_MEASUREMENTS, idx, z, a_i)
        if t < self._min_decision_s or math.isinf(k):
            return StopDecision(False, StopReason.CONTINUE, idx, z, a_i)
        if mu > a_i * sigma:
            return StopDecision(True, StopReason.THRESHOLD, idx, z, a_i)
        if self._accept_z is not None and mu < -self._accept_z * k * sigma:
            return StopDecision(True, StopReason.DECIDED, idx, z, a_i)
        return StopDecision(False, StopReason.CONTINUE, idx, z, a_i)
