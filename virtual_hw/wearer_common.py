"""What the two simulated wearers share: constants, the assistance score and the checks.

:mod:`virtual_hw.wearer` (the legacy single-window wearer and the factory that chooses a wearer)
and :mod:`virtual_hw.wearer_realistic` both build on these pieces; they live here so that neither
wearer module imports the other at import time. The model, its equations and the sources of the
population constants are described in :mod:`virtual_hw.wearer`.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.optimize import minimize

from hilbo_core.errors import ConfigError, MeasurementError
from hilbo_core.profiles import PROFILE_BUILDERS, ForceProfile
from hilbo_core.space import ParameterSpace

__all__ = [
    "ANKLE_PRIOR",
    "HIP_PRIOR",
    "ActuatorPrior",
    "AssistWindow",
    "assistance_score",
    "check_profiles",
    "check_subject_args",
    "check_time",
    "find_optimum",
    "saturate_penalty",
    "timing_window",
]

# Brockway (1987): P[W] = 16.58·VO2[ml/s] + 4.51·VCO2[ml/s].
_BROCKWAY_O2 = 16.58
_BROCKWAY_CO2 = 4.51
_S_PER_MIN = 60.0
_G = 9.81  # m/s², to turn body-weight fractions into newtons
# Physiological guards on the per-breath draws (≈ 5 SD of the default noise), so a freak draw
# can never produce a negative gas exchange or an impossible RER.
_MIN_NOISE_FACTOR = 0.2
_RER_LIMITS = (0.7, 1.1)
# A single breaths_until() call generating more breaths than this is a caller bug (a time in ms
# instead of s, say), not a session: refuse rather than allocate forever.
_MAX_BREATHS_PER_CALL = 1_000_000


# ---------------------------------------------------------------------------- pure functions
def timing_window(gait_pct: np.ndarray, centre_pct: float, width_pct: float) -> np.ndarray:
    """Circular Gaussian weight over the gait cycle.

    Args:
        gait_pct: Gait-cycle positions in %, shape (n,).
        centre_pct: Centre of the window in %.
        width_pct: Standard deviation of the window in % (> 0).

    Returns:
        ``exp(-d² / (2 width²))``, shape (n,), with ``d`` the signed distance to the centre on the
        100 % cycle (so a window near 0 % wraps to 100 %).

    Raises:
        ConfigError: ``width_pct`` is not a positive finite number.
    """
    if not (math.isfinite(width_pct) and width_pct > 0.0):
        raise ConfigError(f"width_pct={width_pct!r} must be a positive number of % gait cycle")
    g = np.asarray(gait_pct, dtype=float)
    d = np.mod(g - centre_pct + 50.0, 100.0) - 50.0
    return np.exp(-0.5 * (d / width_pct) ** 2)


def assistance_score(
    gait_pct: np.ndarray, force_n: np.ndarray, centre_pct: float, width_pct: float,
    ideal_force_n: float,
) -> float:
    """How well one actuator's force table matches the subject's useful window (module docstring).

    ``φ = (2 <f, w> / F - <f, f> / F²) / <w, w>`` with trapezoidal integrals over the table's own
    grid. ``φ = 1`` for ``f = F·w``, 0 for ``f = 0`` (and for ``f = 2F·w``), negative for force
    at the wrong time.

    Args:
        gait_pct: Gait-cycle positions in %, shape (n,), increasing.
        force_n: Applied force in N, shape (n,); negative values are clipped to 0 (a cable can
            only pull).
        centre_pct, width_pct: The window (:func:`timing_window`).
        ideal_force_n: The force ``F`` that fully offloads the muscles at the window centre (> 0).

    Returns:
        The dimensionless score φ (unbounded below).

    Raises:
        ConfigError: ``ideal_force_n`` or ``width_pct`` is not positive.
    """
    if not (math.isfinite(ideal_force_n) and ideal_force_n > 0.0):
        raise ConfigError(f"ideal_force_n={ideal_force_n!r} must be a positive force in N")
    g = np.asarray(gait_pct, dtype=float)
    f = np.clip(np.asarray(force_n, dtype=float), 0.0, None)
    w = timing_window(g, centre_pct, width_pct)
    ww = float(np.trapezoid(w * w, g))
    fw = float(np.trapezoid(f * w, g))
    ff = float(np.trapezoid(f * f, g))
    return (2.0 * fw / ideal_force_n - ff / ideal_force_n**2) / ww


def saturate_penalty(score: float, cap: float) -> float:
    """``S(φ)``: identity for ``φ >= 0``, ``-cap·tanh(-φ/cap)`` below (C¹ at 0, bounded by -cap)."""
    if score >= 0.0:
        return score
    return -cap * math.tanh(-score / cap)


def check_time(name: str, t_s: float) -> float:
    """``t_s`` as a float, refusing anything but a finite time >= 0 s.

    Raises:
        MeasurementError: Not a number, not finite, or negative (names ``name``).
    """
    try:
        t = float(t_s)
    except (TypeError, ValueError) as err:
        raise MeasurementError(f"{name}={t_s!r} is not a time in seconds") from err
    if not math.isfinite(t) or t < 0.0:
        raise MeasurementError(f"{name}={t_s!r} must be a finite time >= 0 s")
    return t


def check_profiles(profiles: Sequence[ForceProfile] | ForceProfile,
                   known: Mapping[str, Any]) -> tuple[ForceProfile, ...]:
    """The applied tables as a tuple, at most one per actuator, each an actuator in ``known``.

    Raises:
        ConfigError: Not ForceProfiles, an actuator twice, or an unknown actuator.
    """
    if isinstance(profiles, ForceProfile):
        profiles = (profiles,)
    try:
        profs = tuple(profiles)
    except TypeError as err:
        raise ConfigError(f"profiles must be a sequence of ForceProfile, got {profiles!r}") from err
    seen: set[str] = set()
    for p in profs:
        if not isinstance(p, ForceProfile):
            raise ConfigError(f"expected ForceProfile values, got {type(p).__name__}")
        if p.actuator not in known:
            raise ConfigError(
                f"no model for actuator {p.actuator!r}; this wearer knows {sorted(known)}"
            )
        if p.actuator in seen:
            raise ConfigError(f"actuator {p.actuator!r} appears twice in the applied profiles")
        seen.add(p.actuator)
    return profs


def check_subject_args(space: ParameterSpace, seed: int, body_mass_kg: float) -> None:
    """Validate a wearer's space, seed and body mass.

    Raises:
        ConfigError: Not a ParameterSpace or one without a force-profile builder, a seed that is
            not a non-negative integer, or a body mass outside [20, 250] kg.
    """
    if not isinstance(space, ParameterSpace):
        raise ConfigError(f"space must be a ParameterSpace, got {type(space).__name__}")
    if space.name not in PROFILE_BUILDERS:
        raise ConfigError(
            f"space {space.name!r} has no force-profile builder; known: "
            f"{sorted(PROFILE_BUILDERS)}"
        )
    if isinstance(seed, bool) or not isinstance(seed, int | np.integer) or seed < 0:
        raise ConfigError(f"seed={seed!r} must be a non-negative integer")
    if isinstance(body_mass_kg, bool) or not isinstance(body_mass_kg, int | float) or not (
        20.0 <= body_mass_kg <= 250.0
    ):
        raise ConfigError(f"body_mass_kg={body_mass_kg!r} must be a number in [20, 250] kg")


def find_optimum(space: ParameterSpace, cost_unit: Callable[[np.ndarray], float],
                 search_ss: np.random.SeedSequence, n_candidates: int,
                 n_starts: int) -> tuple[dict[str, float], float]:
    """``(params, cost)`` of the best feasible point of ``cost_unit`` over the unit cube.

    Scrambled-Sobol feasible candidates (``n_candidates``), then SLSQP in the unit cube under the
    space's linear constraints from the ``n_starts`` best of them; the best feasible result wins
    (a candidate itself if refinement never improves on it).

    Args:
        space: The parameter space (its constraints and unit-cube map).
        cost_unit: Cost of a unit-cube point, shape (d,) -> float.
        search_ss: Seeds the candidates (deterministic for a subject).
        n_candidates: Candidate points.
        n_starts: SLSQP starts from the best candidates.
    """
    rng = np.random.default_rng(search_ss)
    cand = space.sample_unit(n_candidates, rng)
    costs = np.array([cost_unit(u) for u in cand])
    order = np.argsort(costs)
    best_u, best_c = cand[order[0]], float(costs[order[0]])
    A_u, b_u = space.unit_constraints()
    constraints = (
        [{"type": "ineq", "fun": lambda u: b_u - A_u @ u, "jac": lambda u: -A_u}]
        if len(b_u) else []
    )
    for i in order[:n_starts]:
        # eps: the tables are sampled at 1 %GC, so the cost is only piecewise smooth at the
        # 1e-8 scale of the default finite-difference step; 1e-6 sees the smooth trend.
        res = minimize(cost_unit, cand[i], method="SLSQP",
                       bounds=[(0.0, 1.0)] * space.dim, constraints=constraints,
                       options={"ftol": 1e-10, "maxiter": 100, "eps": 1e-6})
        u = np.clip(res.x, 0.0, 1.0)
        if not space.feasible_mask(space.from_unit(u)[None, :])[0]:
            continue
        c = cost_unit(u)
        if c < best_c:
            best_u, best_c = u, c
    return space.to_dict(space.from_unit(best_u)), best_c


# ---------------------------------------------------------------------------- configuration
def _check_range(owner: str, name: str, rng: tuple[float, float], lo: float, hi: float) -> None:
    try:
        a, b = (float(v) for v in rng)
    except (TypeError, ValueError) as err:
        raise ConfigError(f"{owner}.{name}={rng!r} must be a (low, high) pair of numbers") from err
    if not (math.isfinite(a) and math.isfinite(b) and lo <= a <= b <= hi):
        raise ConfigError(
            f"{owner}.{name}={rng!r} must satisfy {lo:g} <= low <= high <= {hi:g}"
        )


def _check_value(owner: str, name: str, value: float, lo: float, hi: float) -> None:
    if isinstance(value, bool) or not isinstance(value, int | float) or not (
        math.isfinite(value) and lo <= value <= hi
    ):
        raise ConfigError(f"{owner}.{name}={value!r} must be a number in [{lo:g}, {hi:g}]")


@dataclass(frozen=True)
class ActuatorPrior:
    """Population ranges of one actuator's useful window (drawn uniformly per subject).

    Attributes:
        actuator: The load path, as in ``ForceProfile.actuator`` (``"hip"``, ``"ankle"``).
        centre_pct: Range of the window centre, % gait cycle (in that actuator's convention).
        width_pct: Range of the window's standard deviation, % gait cycle.
        ideal_force_bw: Range of the ideal peak force, as a fraction of body weight.
        max_benefit_frac: Range of β, the largest fractional saving of the unassisted cost.
    """

    actuator: str
    centre_pct: tuple[float, float]
    width_pct: tuple[float, float]
    ideal_force_bw: tuple[float, float]
    max_benefit_frac: tuple[float, float]

    def __post_init__(self) -> None:
        owner = f"ActuatorPrior({self.actuator!r})"
        if not isinstance(self.actuator, str) or not self.actuator:
            raise ConfigError(f"ActuatorPrior.actuator={self.actuator!r} must be a non-empty name")
        _check_range(owner, "centre_pct", self.centre_pct, 0.0, 100.0)
        _check_range(owner, "width_pct", self.width_pct, 0.5, 50.0)
        _check_range(owner, "ideal_force_bw", self.ideal_force_bw, 1e-3, 5.0)
        _check_range(owner, "max_benefit_frac", self.max_benefit_frac, 0.0, 0.6)


HIP_PRIOR = ActuatorPrior("hip", (20.0, 28.0), (7.0, 11.0), (0.22, 0.32), (0.10, 0.20))
ANKLE_PRIOR = ActuatorPrior("ankle", (52.0, 60.0), (5.0, 8.0), (0.50, 0.75), (0.05, 0.10))


@dataclass(frozen=True)
class AssistWindow:
    """One subject's useful window for one actuator (drawn from an :class:`ActuatorPrior`).

    Attributes:
        actuator: Load path name.
        centre_pct: Window centre, % gait cycle.
        width_pct: Window standard deviation, % gait cycle.
        ideal_force_n: Force that fully offloads the muscles at the centre, N.
        max_benefit_frac: β, the largest fractional saving of the unassisted cost.
    """

    actuator: str
    centre_pct: float
    width_pct: float
    ideal_force_n: float
    max_benefit_frac: float
