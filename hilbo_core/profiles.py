"""Force profiles: assistance parameters -> a table of force over 0-100 % of the gait cycle.

Pure functions. The bridge uses them to build what it sends to the exosuit; the virtual exosuit
uses the same code to check what it receives, so the two can never disagree on the shape.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass

import numpy as np
from scipy.interpolate import CubicSpline

from hilbo_core.errors import ConfigError, InfeasibleError

__all__ = [
    "PROFILE_BUILDERS",
    "PROFILE_DOMAINS",
    "Domain",
    "ForceProfile",
    "build_profile",
    "hip_ankle_profiles",
    "hip_spline_profile",
]

N_POINTS = 101  # one point per % of the gait cycle, 0..100 inclusive


@dataclass(frozen=True)
class ForceProfile:
    """Desired force of one actuator over one gait cycle.

    Attributes:
        actuator: Which load path it drives (``"hip"``, ``"ankle"``).
        gait_pct: Gait-cycle positions in %, shape (n,), increasing from 0 to 100.
        force_n: Desired force in N at each position, shape (n,), all >= 0.
    """

    actuator: str
    gait_pct: np.ndarray
    force_n: np.ndarray

    def __post_init__(self) -> None:
        # Copies: freezing the table must not freeze the caller's arrays.
        g = np.array(self.gait_pct, dtype=float)
        f = np.array(self.force_n, dtype=float)
        if g.shape != f.shape or g.ndim != 1 or len(g) < 2:
            raise ConfigError(f"profile tables must be 1-D of equal length, got {g.shape} and {f.shape}")
        if not (np.all(np.isfinite(f)) and np.all(np.isfinite(g))):
            raise InfeasibleError(f"profile {self.actuator!r} contains a non-finite value")
        g.setflags(write=False)
        f.setflags(write=False)
        object.__setattr__(self, "gait_pct", g)
        object.__setattr__(self, "force_n", f)

    @property
    def peak_n(self) -> float:
        """Largest desired force in N."""
        return float(self.force_n.max())

    def to_json(self) -> dict:
        """JSON-able form (used by the log)."""
        return {"actuator": self.actuator, "gait_pct": self.gait_pct.tolist(),
                "force_n": self.force_n.tolist()}


def _grid(n_points: int) -> np.ndarray:
    if n_points < 2:
        raise ConfigError(f"a profile needs at least 2 points, got {n_points}")
    return np.linspace(0.0, 100.0, n_points)


def hip_spline_profile(
    t_on: float, t_p: float, t_off: float, F_p: float, F_r: float, F_f: float,
    n_points: int = N_POINTS,
) -> ForceProfile:
    """Hip-extension force: two cubic splines (Kim et al. 2019 §IV.A.2, Fig. 3a).

    The rising spline passes through onset (t_on, 0), the rising node
    ((t_on + t_p)/2, F_r·F_p) and the peak (t_p, F_p); the falling spline through the peak, the
    falling node ((t_p + t_off)/2, F_f·F_p) and the offset (t_off, 0). Both are clamped with zero
    slope at their ends so the force starts, peaks and ends smoothly; outside [t_on, t_off] the
    force is zero. The result is clipped to [0, F_p] because a cubic through a high node can
    overshoot slightly, and the peak force is a hardware limit, not a suggestion.

    Args:
        t_on, t_p, t_off: Onset, peak and offset timings in % gait cycle, t_on < t_p < t_off.
        F_p: Peak force in N (> 0).
        F_r, F_f: Rising and falling node forces as ratios of F_p, in (0, 1).
        n_points: Table length over 0..100 %.

    Returns:
        The hip ForceProfile.
    """
    vals = {"t_on": t_on, "t_p": t_p, "t_off": t_off, "F_p": F_p, "F_r": F_r, "F_f": F_f}
    for k, v in vals.items():
        if not math.isfinite(v):
            raise InfeasibleError(f"hip profile parameter {k}={v!r} is not finite")
    if not 0.0 <= t_on < t_p < t_off <= 100.0:
        raise InfeasibleError(
            f"hip timings must satisfy 0 <= t_on < t_p < t_off <= 100, got {t_on}, {t_p}, {t_off}"
        )
    if F_p <= 0 or not (0 < F_r < 1 and 0 < F_f < 1):
        raise InfeasibleError(f"need F_p > 0 and node ratios in (0, 1), got {F_p}, {F_r}, {F_f}")
    g = _grid(n_points)
    force = np.zeros_like(g)
    rise = CubicSpline([t_on, 0.5 * (t_on + t_p), t_p], [0.0, F_r * F_p, F_p], bc_type="clamped")
    fall = CubicSpline([t_p, 0.5 * (t_p + t_off), t_off], [F_p, F_f * F_p, 0.0], bc_type="clamped")
    m_rise = (g >= t_on) & (g <= t_p)
    m_fall = (g > t_p) & (g <= t_off)
    force[m_rise] = rise(g[m_rise])
    force[m_fall] = fall(g[m_fall])
    return ForceProfile("hip", g, np.clip(force, 0.0, F_p))


def hip_ankle_profiles(
    params: Mapping[str, float], body_mass_kg: float = 75.0, n_points: int = N_POINTS,
) -> tuple[ForceProfile, ForceProfile]:
    """Hip and ankle force tables for the multi-joint preset (Kim et al. 2019 §IV.B, Fig. 3b).

    Hip: a piecewise-sinusoidal extension force rising from 0 %GC to ``hip_t_peak`` and falling
    to zero at ``hip_t_offset``, peak fixed at 40 % of body weight. Ankle: Kim et al. 2019 drive the
    ankle with a piecewise-linear *position* profile under force-based position control and a
    target peak force of 60 % body weight; this table is the force that profile is meant to
    produce: zero until ``ankle_t1``, a linear ramp to the peak at ``ankle_t2``, held until
    ``ankle_t3``, and released linearly over 10 %GC.

    Args:
        params: Values of hip_t_peak, hip_t_offset, ankle_t1, ankle_t2 and (derived) ankle_t3.
        body_mass_kg: The wearer's mass; sets the peak forces (g = 9.81 m/s²).
        n_points: Table length over 0..100 %.
    """
    try:
        tp, toff = float(params["hip_t_peak"]), float(params["hip_t_offset"])
        t1, t2 = float(params["ankle_t1"]), float(params["ankle_t2"])
    except KeyError as err:
        raise ConfigError(f"hip_ankle profile needs parameter {err.args[0]!r}") from err
    t3 = float(params.get("ankle_t3", t2 + 10.0))
    if not (0 < tp < toff <= 100 and 0 <= t1 < t2 <= t3 < 100):
        raise InfeasibleError(
            f"need 0 < hip_t_peak < hip_t_offset <= 100 and 0 <= ankle_t1 < ankle_t2 <= ankle_t3 < 100, "
            f"got {tp}, {toff}, {t1}, {t2}, {t3}"
        )
    if not 20.0 <= body_mass_kg <= 250.0:
        raise ConfigError(f"body_mass_kg={body_mass_kg} is outside [20, 250] kg")
    g = _grid(n_points)
    weight_n = 9.81 * body_mass_kg
    hip_peak = 0.40 * weight_n
    hip = np.zeros_like(g)
    up = g <= tp
    hip[up] = hip_peak * 0.5 * (1 - np.cos(np.pi * g[up] / tp))
    down = (g > tp) & (g <= toff)
    hip[down] = hip_peak * 0.5 * (1 + np.cos(np.pi * (g[down] - tp) / (toff - tp)))
    ankle_peak = 0.60 * weight_n
    ankle = np.interp(g, [0, t1, t2, t3, min(t3 + 10.0, 100.0)], [0, 0, ankle_peak, ankle_peak, 0])
    return ForceProfile("hip", g, hip), ForceProfile("ankle", g, ankle)


def _hip_6d(params: Mapping[str, float], **_: object) -> tuple[ForceProfile, ...]:
    names = ("t_on", "t_p", "t_off", "F_p", "F_r", "F_f")
    missing = [k for k in names if k not in params]
    if missing:
        raise ConfigError(f"hip_6d profile needs parameter(s) {missing}")
    return (hip_spline_profile(**{k: float(params[k]) for k in names}),)


def _hip_ankle_4d(params: Mapping[str, float], **kw: object) -> tuple[ForceProfile, ...]:
    return hip_ankle_profiles(params, **kw)  # type: ignore[arg-type]


PROFILE_BUILDERS: dict[str, Callable[..., tuple[ForceProfile, ...]]] = {
    "hip_6d": _hip_6d,
    "hip_ankle_4d": _hip_ankle_4d,
}


@dataclass(frozen=True)
class Domain:
    """The values one builder parameter may take on its own (the builders' checks above; the
    orderings between parameters are the space's constraints)."""

    low: float
    high: float
    low_open: bool = False
    high_open: bool = False

    def contains(self, lower: float, upper: float) -> bool:
        """Whether the whole range [lower, upper] is inside the domain."""
        lo_ok = lower > self.low if self.low_open else lower >= self.low
        hi_ok = upper < self.high if self.high_open else upper <= self.high
        return lo_ok and hi_ok

    def text(self, name: str) -> str:
        """E.g. ``0 < F_p`` or ``0 <= t_on < 100``."""
        lo = "" if math.isinf(self.low) else f"{self.low:g} {'<' if self.low_open else '<='} "
        hi = "" if math.isinf(self.high) else f" {'<' if self.high_open else '<='} {self.high:g}"
        return f"{lo}{name}{hi}"


PROFILE_DOMAINS: dict[str, dict[str, Domain]] = {
    # hip_spline_profile: 0 <= t_on < t_p < t_off <= 100, F_p > 0, node ratios in (0, 1).
    "hip_6d": {"t_on": Domain(0.0, 100.0, high_open=True), "t_p": Domain(0.0, 100.0, True, True),
               "t_off": Domain(0.0, 100.0, low_open=True), "F_p": Domain(0.0, math.inf, True, True),
               "F_r": Domain(0.0, 1.0, True, True), "F_f": Domain(0.0, 1.0, True, True)},
    # hip_ankle_profiles: 0 < hip_t_peak < hip_t_offset <= 100, 0 <= ankle_t1 < ankle_t2 <= ankle_t3 < 100
    # with ankle_t3 = ankle_t2 + 10 unless given.
    "hip_ankle_4d": {"hip_t_peak": Domain(0.0, 100.0, True, True),
                     "hip_t_offset": Domain(0.0, 100.0, low_open=True),
                     "ankle_t1": Domain(0.0, 100.0, high_open=True),
                     "ankle_t2": Domain(0.0, 90.0, True, True)},
}
"""Per builder, the values each parameter may take on its own: a [space] whose range leaves them
builds no profile there (checked when a config is loaded)."""


def build_profile(space_name: str, params: Mapping[str, float], **kwargs: object) -> tuple[ForceProfile, ...]:
    """The actuator profiles for a point of a preset space.

    Args:
        space_name: Preset name (``ParameterSpace.name``).
        params: The point, as ``ParameterSpace.to_dict`` returns it.
        **kwargs: Builder options (e.g. ``body_mass_kg`` for ``hip_ankle_4d``).
    """
    try:
        builder = PROFILE_BUILDERS[space_name]
    except KeyError as err:
        raise ConfigError(
            f"no force-profile builder for space {space_name!r}; known: {sorted(PROFILE_BUILDERS)}"
        ) from err
    return builder(params, **kwargs)
