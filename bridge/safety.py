"""The limits layer: the one gate between the optimizer and the CAN bus.

The wearer is a person, so whatever the optimizer proposes — NaN, infinity, a point outside the
space, or a perfectly feasible setting whose force table happens to exceed what the hardware may
do — nothing reaches the exosuit unless it passes the checks here (shared/DESIGN.md, "Safety
invariants"). Everything in this module is pure and synchronous: no I/O, no clock, no asyncio.

Pieces:

- :class:`ProfileLimits` / :class:`ActuatorLimits`: the hardware limits of the ``[limits]``
  config table (force, assistance window, rate of change, step of the peak between profiles,
  table grid), optionally per actuator.
- :func:`check_params`: the setting against its space (bounds, linear constraints, finiteness,
  consistency of derived parameters).
- :func:`check_profile`: force tables against the limits; returns a :class:`LimitVerdict` that
  lists *every* violation (actuator, index, %GC, value, limit), never raises for bad data.
- :class:`SafeProfileGate`: ``admit(params)`` builds the tables with
  :func:`hilbo_core.profiles.build_profile`, checks everything and returns an
  :class:`AdmittedProfile` — the only thing the bridge may push — or raises
  :class:`~bridge.errors.UnsafeProfileError`. An ``AdmittedProfile`` cannot be made anywhere
  else (its constructor wants a module-private token), so nothing bypasses the gate.

Decisions (documented because they are safety policy, not implementation detail):

- **Reject, never clip.** A table that violates any limit — force, window, slope (rate of
  change) or the step of the peak from the last acknowledged profile — is rejected as a whole.
  Clipping would send the wearer a profile the optimizer never proposed and then attribute the
  measured cost to the proposal. On rejection nothing is sent; the device keeps executing the
  last acknowledged (in-limits) profile. The bridge then cancels the setting
  (``HILOptimizer.cancel_current()``, its breaths count against nothing), logs an event with the
  verdict, and asks again. Because ``ask()`` repeats an exploration point after a cancel and the
  GP may propose a similar point again, :attr:`SafeProfileGate.rejections_exhausted` tells the
  bridge when ``limits.max_consecutive_rejections`` proposals in a row were refused: it must
  then command assistance-off, pause the session and tell the operator (the config's limits and
  space disagree; ``hilbo config check`` shows how much of the space the limits refuse).
- **Peak step.** ``max_peak_change_n`` bounds the change of an actuator's peak force between the
  profile the device last *acknowledged* and the next one. The first profile of a session, and
  the first after assistance-off (:meth:`SafeProfileGate.assistance_off`), have no baseline: the
  wearer comes from slack, and only ``max_force_n`` bounds them. An all-zero table (zero-force
  tracking, :meth:`SafeProfileGate.admit_zero_force`) is slack too, so it is no baseline either,
  and a step *to* an all-zero table is never a peak-change violation: it is what the device does
  at once on AssistanceOff (drivers/PROTOCOL.md, "Assistance-off (safe state)").
- **Rate of change** is the table's slope in N per %GC between neighbouring points, including the
  seam from 100 % back to 0 % of the next cycle (treated as one grid step: the device wraps the
  table every stride, so a jump there is as real as one mid-table).
- **Zero force.** The assistance window ``[min_onset_pct, max_offset_pct]`` is where a table may
  be non-zero; a point counts as zero when it quantises to 0 on the wire (below half the 0.1 N
  resolution of drivers/PROTOCOL.md).
- **Grid.** Tables must have exactly ``n_points`` points at ``100·k/(n−1)`` %GC, the grid the
  device assumes (PROTOCOL.md, "Force profile tables").
"""

from __future__ import annotations

import enum
import math
import weakref
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, fields
from types import MappingProxyType
from typing import Any, NamedTuple

import numpy as np

from bridge.errors import BridgeConfigError, UnsafeProfileError
from drivers.exosuit.profile import (
    FORCE_RESOLUTION_N,
    MAX_FORCE_ON_WIRE_N,
    MAX_PROFILE_POINTS,
    MIN_PROFILE_POINTS,
)
from hilbo_core.profiles import ForceProfile, build_profile
from hilbo_core.space import ParameterSpace

__all__ = [
    "ACTUATOR_LIMIT_RANGES",
    "ActuatorLimits",
    "AdmittedProfile",
    "LimitVerdict",
    "PreflightReport",
    "ProfileLimits",
    "SafeProfileGate",
    "Violation",
    "ViolationKind",
    "check_params",
    "check_profile",
    "make_actuator_limits",
    "preflight",
]

#: A force below this quantises to a raw 0 on the wire (half the DBC's 0.1 N resolution).
ZERO_FORCE_N = FORCE_RESOLUTION_N / 2
# Tolerance on the gait grid (%GC): tables are built with np.linspace, so only round-off differs.
_GRID_TOL_PCT = 1e-6
# Tolerance on a derived parameter the caller passed vs the one recomputed from the space.
_DERIVED_TOL = 1e-9


class ViolationKind(enum.Enum):
    """What was wrong."""

    PARAMS = "params"  # the setting is outside its space (bounds, constraints, NaN, unknown keys)
    BUILD = "build"  # the force-profile builder refused the setting
    NO_PROFILE = "no_profile"  # no tables, or something that is not a force table
    DUPLICATE_ACTUATOR = "duplicate_actuator"  # two tables for one actuator
    LENGTH = "length"  # not 1-D, lengths differ, or not limits.n_points points
    NON_FINITE = "non_finite"  # NaN or infinity in a table
    GRID = "grid"  # gait positions are not 100·k/(n−1) %GC
    NEGATIVE_FORCE = "negative_force"  # a cable cannot push
    MAX_FORCE = "max_force"  # above max_force_n
    ONSET = "onset"  # force before min_onset_pct
    OFFSET = "offset"  # force after max_offset_pct
    SLOPE = "slope"  # |ΔF/Δ%GC| above max_slope_n_per_pct
    PEAK_CHANGE = "peak_change"  # peak moved more than max_peak_change_n from the acknowledged one


@dataclass(frozen=True)
class Violation:
    """One broken limit.

    Attributes:
        kind: What was wrong.
        message: Human-readable, naming the actuator, the position, the value and the limit.
        actuator: The actuator's table, when the violation is in one.
        index: Table index of the (first or worst) offending point.
        gait_pct: Its position in %GC.
        value: The offending value (N, N/%GC, %GC... as the kind says).
        limit: The limit it broke, in the same unit.
    """

    kind: ViolationKind
    message: str
    actuator: str | None = None
    index: int | None = None
    gait_pct: float | None = None
    value: float | None = None
    limit: float | None = None

    def to_json(self) -> dict[str, Any]:
        """JSON-able form (non-finite values as strings, e.g. ``"nan"``)."""
        return {
            "kind": self.kind.value,
            "message": self.message,
            "actuator": self.actuator,
            "index": self.index,
            "gait_pct": _json_float(self.gait_pct),
            "value": _json_float(self.value),
            "limit": _json_float(self.limit),
        }


@dataclass(frozen=True)
class LimitVerdict:
    """The outcome of a check: ``ok`` when there is no violation.

    Attributes:
        violations: Every violation found, in check order.
    """

    violations: tuple[Violation, ...] = ()

    @property
    def ok(self) -> bool:
        """True when nothing is violated."""
        return not self.violations

    @property
    def kinds(self) -> frozenset[ViolationKind]:
        """The kinds of violation present."""
        return frozenset(v.kind for v in self.violations)

    def describe(self) -> str:
        """One line per violation (``"within limits"`` when there is none)."""
        if self.ok:
            return "within limits"
        return "; ".join(v.message for v in self.violations)

    def to_json(self) -> dict[str, Any]:
        """JSON-able form (for the log's events)."""
        return {"ok": self.ok, "violations": [v.to_json() for v in self.violations]}


#: Allowed range of every per-actuator limit: key -> (low, high, low is open).
ACTUATOR_LIMIT_RANGES: Mapping[str, tuple[float, float, bool]] = MappingProxyType({
    "max_force_n": (0.0, MAX_FORCE_ON_WIRE_N, True),
    "min_onset_pct": (0.0, 100.0, False),
    "max_offset_pct": (0.0, 100.0, False),
    "max_slope_n_per_pct": (0.0, MAX_FORCE_ON_WIRE_N, True),
    "max_peak_change_n": (0.0, MAX_FORCE_ON_WIRE_N, True),
})


def _check_limit_value(key: str, value: object, where: str) -> float:
    lo, hi, lo_open = ACTUATOR_LIMIT_RANGES[key]
    expected = f"a finite number in {'(' if lo_open else '['}{lo:g}, {hi:g}]"
    if isinstance(value, bool) or not isinstance(value, int | float | np.floating | np.integer):
        raise BridgeConfigError(f"{where}.{key} = {value!r}: expected {expected}")
    v = float(value)
    if not math.isfinite(v) or (v <= lo if lo_open else v < lo) or v > hi:
        raise BridgeConfigError(f"{where}.{key} = {value!r}: expected {expected}")
    return v


def _check_actuator_values(values: Mapping[str, object], where: str) -> dict[str, float]:
    out = {k: _check_limit_value(k, v, where) for k, v in values.items()}
    if out["min_onset_pct"] >= out["max_offset_pct"]:
        raise BridgeConfigError(
            f"{where}.min_onset_pct = {out['min_onset_pct']:g} must be below "
            f"{where}.max_offset_pct = {out['max_offset_pct']:g} (the assistance window in %GC)"
        )
    return out


@dataclass(frozen=True)
class ActuatorLimits:
    """Hardware limits of one actuator's force table.

    Defaults fit Kim et al. 2019's hip exosuit (Kim et al. 2019 §IV.A.2: peak force 50–250 N, offset at most
    55 %GC_MHF): every profile of the ``hip_6d`` preset passes them (its steepest table, 250 N
    reached in 15 %GC, rises at 31 N/%GC), with a margin.

    Attributes:
        max_force_n: Largest force anywhere in the table (N), 0 < x ≤ 6553.5 (the wire's range).
        min_onset_pct: Earliest %GC at which the force may be non-zero.
        max_offset_pct: Latest %GC at which the force may be non-zero.
        max_slope_n_per_pct: Largest |ΔF| between neighbouring points per %GC between them (N/%GC).
        max_peak_change_n: Largest change of the peak force from the last acknowledged profile (N).
    """

    max_force_n: float = 250.0
    min_onset_pct: float = 0.0
    max_offset_pct: float = 60.0
    max_slope_n_per_pct: float = 40.0
    max_peak_change_n: float = 250.0

    def __post_init__(self) -> None:
        checked = _check_actuator_values({f.name: getattr(self, f.name) for f in fields(self)}, "limits")
        for k, v in checked.items():
            object.__setattr__(self, k, v)

    def to_json(self) -> dict[str, float]:
        """JSON-able form."""
        return {f.name: getattr(self, f.name) for f in fields(self)}


def make_actuator_limits(where: str, **values: object) -> ActuatorLimits:
    """Build :class:`ActuatorLimits`, naming ``where`` (e.g. ``limits.actuators.ankle``) in errors.

    Raises:
        BridgeConfigError: A value out of range, or an empty assistance window.
    """
    unknown = sorted(set(values) - set(ACTUATOR_LIMIT_RANGES))
    if unknown:
        raise BridgeConfigError(
            f"{where}: unknown limit(s) {unknown}; allowed: {sorted(ACTUATOR_LIMIT_RANGES)}"
        )
    merged = ActuatorLimits().to_json()
    merged.update(values)  # type: ignore[arg-type]
    return ActuatorLimits(**_check_actuator_values(merged, where))


@dataclass(frozen=True)
class ProfileLimits:
    """The ``[limits]`` table: what no profile may exceed.

    The five per-actuator limits given at top level apply to every actuator; ``actuators`` holds
    complete :class:`ActuatorLimits` for actuators that differ (the config loader fills the keys an
    override does not give from the top level).

    Attributes:
        max_force_n, min_onset_pct, max_offset_pct, max_slope_n_per_pct, max_peak_change_n:
            See :class:`ActuatorLimits`.
        n_points: Required table length (2..768; the hip profile uses 101, 1 %GC steps).
        max_consecutive_rejections: After this many rejected proposals in a row the bridge
            commands assistance-off and pauses for the operator (>= 1).
        actuators: Per-actuator overrides, ``{actuator name: ActuatorLimits}``.
    """

    max_force_n: float = 250.0
    min_onset_pct: float = 0.0
    max_offset_pct: float = 60.0
    max_slope_n_per_pct: float = 40.0
    max_peak_change_n: float = 250.0
    n_points: int = 101
    max_consecutive_rejections: int = 3
    actuators: Mapping[str, ActuatorLimits] = field(default_factory=dict)

    def __post_init__(self) -> None:
        base = make_actuator_limits("limits", **self._base_values())
        for k, v in base.to_json().items():
            object.__setattr__(self, k, v)
        n = self.n_points
        if isinstance(n, bool) or not isinstance(n, int) or not MIN_PROFILE_POINTS <= n <= MAX_PROFILE_POINTS:
            raise BridgeConfigError(
                f"limits.n_points = {n!r}: expected an integer in "
                f"[{MIN_PROFILE_POINTS}, {MAX_PROFILE_POINTS}] (the wire's table lengths)"
            )
        m = self.max_consecutive_rejections
        if isinstance(m, bool) or not isinstance(m, int) or not 1 <= m <= 100:
            raise BridgeConfigError(
                f"limits.max_consecutive_rejections = {m!r}: expected an integer in [1, 100]"
            )
        if not isinstance(self.actuators, Mapping):
            raise BridgeConfigError(
                f"limits.actuators = {self.actuators!r}: expected a table of actuator tables"
            )
        for name, lim in self.actuators.items():
            if not isinstance(name, str) or not name:
                raise BridgeConfigError(
                    f"limits.actuators: actuator name {name!r} must be a non-empty string"
                )
            if not isinstance(lim, ActuatorLimits):
                raise BridgeConfigError(f"limits.actuators.{name} = {lim!r}: expected ActuatorLimits")
        object.__setattr__(self, "actuators", MappingProxyType(dict(self.actuators)))

    def _base_values(self) -> dict[str, object]:
        return {k: getattr(self, k) for k in ACTUATOR_LIMIT_RANGES}

    @property
    def default(self) -> ActuatorLimits:
        """The limits of an actuator without an override."""
        return ActuatorLimits(**self._base_values())  # type: ignore[arg-type]

    def for_actuator(self, name: str) -> ActuatorLimits:
        """The limits that apply to actuator ``name``."""
        return self.actuators.get(name) or self.default

    def to_json(self) -> dict[str, Any]:
        """JSON-able form."""
        out: dict[str, Any] = dict(self._base_values())
        out["n_points"] = self.n_points
        out["max_consecutive_rejections"] = self.max_consecutive_rejections
        out["actuators"] = {k: v.to_json() for k, v in self.actuators.items()}
        return out


# --------------------------------------------------------------------------------------------
# Checks
# --------------------------------------------------------------------------------------------


class _Table(NamedTuple):
    actuator: str
    gait_pct: np.ndarray
    force_n: np.ndarray


def _json_float(x: float | None) -> float | str | None:
    if x is None or math.isfinite(x):
        return x
    return str(x)


def _snapshot(profiles: object, out: list[Violation]) -> list[_Table]:
    """Private read-only copies of the tables, so what is checked is what is kept and sent."""
    if isinstance(profiles, str | bytes) or not isinstance(profiles, Sequence) or not profiles:
        out.append(Violation(ViolationKind.NO_PROFILE,
                             f"expected a non-empty sequence of force profiles, got {profiles!r:.80}"))
        return []
    tables: list[_Table] = []
    seen: set[str] = set()
    for i, p in enumerate(profiles):
        actuator = getattr(p, "actuator", None)
        if not isinstance(actuator, str) or not actuator:
            out.append(Violation(ViolationKind.NO_PROFILE,
                                 f"profile {i} has no actuator name (got {actuator!r:.40})"))
            continue
        try:
            g = np.array(p.gait_pct, dtype=float)
            f = np.array(p.force_n, dtype=float)
        except (AttributeError, TypeError, ValueError) as err:
            out.append(Violation(ViolationKind.NO_PROFILE,
                                 f"{actuator}: not a numeric force table ({err})", actuator))
            continue
        if actuator in seen:
            out.append(Violation(ViolationKind.DUPLICATE_ACTUATOR,
                                 f"{actuator}: two tables for the same actuator", actuator))
            continue
        seen.add(actuator)
        g.setflags(write=False)
        f.setflags(write=False)
        tables.append(_Table(actuator, g, f))
    return tables


def _check_table(t: _Table, lim: ActuatorLimits, n_points: int,
                 previous_peak_n: float | None) -> list[Violation]:
    a, g, f = t
    out: list[Violation] = []
    if g.ndim != 1 or f.ndim != 1 or g.shape != f.shape or len(f) != n_points:
        out.append(Violation(ViolationKind.LENGTH,
                             f"{a}: table of shape {f.shape} on a grid of shape {g.shape}; "
                             f"expected {n_points} points (limits.n_points)",
                             a, value=float(f.size), limit=float(n_points)))
        return out  # nothing below is meaningful on a malformed table
    bad = ~(np.isfinite(f) & np.isfinite(g))
    if bad.any():
        i = int(np.argmax(bad))
        out.append(Violation(ViolationKind.NON_FINITE,
                             f"{a}: non-finite value at {int(bad.sum())} point(s), first at index {i} "
                             f"(gait {g[i]!r} %GC, force {f[i]!r} N)",
                             a, i, float(g[i]), float(f[i])))
        return out
    expected = np.linspace(0.0, 100.0, n_points)
    off = np.abs(g - expected) > _GRID_TOL_PCT
    if off.any():
        i = int(np.argmax(off))
        out.append(Violation(ViolationKind.GRID,
                             f"{a}: point {i} is at {g[i]:g} %GC; the grid is 100·k/(n−1), "
                             f"i.e. {expected[i]:g} %GC", a, i, float(g[i]), float(g[i]), float(expected[i])))
        return out
    if (f < 0).any():
        i = int(np.argmin(f))
        out.append(Violation(ViolationKind.NEGATIVE_FORCE,
                             f"{a}: force {f[i]:g} N < 0 at {g[i]:g} %GC (index {i})",
                             a, i, float(g[i]), float(f[i]), 0.0))
    if (f > lim.max_force_n).any():
        i = int(np.argmax(f))
        out.append(Violation(ViolationKind.MAX_FORCE,
                             f"{a}: force {f[i]:g} N at {g[i]:g} %GC (index {i}) exceeds "
                             f"max_force_n = {lim.max_force_n:g} N",
                             a, i, float(g[i]), float(f[i]), lim.max_force_n))
    active = f >= ZERO_FORCE_N
    early = active & (g < lim.min_onset_pct)
    if early.any():
        i = int(np.argmax(early))
        out.append(Violation(ViolationKind.ONSET,
                             f"{a}: force {f[i]:g} N at {g[i]:g} %GC (index {i}), before "
                             f"min_onset_pct = {lim.min_onset_pct:g} %GC",
                             a, i, float(g[i]), float(g[i]), lim.min_onset_pct))
    late = active & (g > lim.max_offset_pct)
    if late.any():
        i = int(np.argmax(late))
        out.append(Violation(ViolationKind.OFFSET,
                             f"{a}: force {f[i]:g} N at {g[i]:g} %GC (index {i}), after "
                             f"max_offset_pct = {lim.max_offset_pct:g} %GC",
                             a, i, float(g[i]), float(g[i]), lim.max_offset_pct))
    step_pct = float(g[1] - g[0])
    # Neighbouring points, then the seam 100 % -> 0 % of the next stride as one more grid step.
    slopes = np.append(np.abs(np.diff(f)) / np.diff(g), abs(float(f[0] - f[-1])) / step_pct)
    if (slopes > lim.max_slope_n_per_pct).any():
        i = int(np.argmax(slopes))
        where = (f"between {g[i]:g} and {g[i + 1]:g} %GC (index {i}→{i + 1})" if i < len(f) - 1
                 else "across the seam 100 % → 0 % of the next stride")
        out.append(Violation(ViolationKind.SLOPE,
                             f"{a}: slope {slopes[i]:.4g} N/%GC {where} exceeds "
                             f"max_slope_n_per_pct = {lim.max_slope_n_per_pct:g} N/%GC",
                             a, i, float(g[i]), float(slopes[i]), lim.max_slope_n_per_pct))
    if previous_peak_n is not None and bool((f >= ZERO_FORCE_N).any()):
        i = int(np.argmax(f))
        change = abs(float(f[i]) - previous_peak_n)
        if not change <= lim.max_peak_change_n:  # `not <=`: a NaN baseline is a violation too
            out.append(Violation(ViolationKind.PEAK_CHANGE,
                                 f"{a}: peak {f[i]:g} N changes by {change:g} N from the acknowledged "
                                 f"{previous_peak_n:g} N; max_peak_change_n = {lim.max_peak_change_n:g} N",
                                 a, i, float(g[i]), change, lim.max_peak_change_n))
    return out


def _previous_peaks(previous: Sequence[ForceProfile] | None) -> dict[str, float]:
    if previous is None:
        return {}
    peaks: dict[str, float] = {}
    for p in previous:
        f = np.asarray(p.force_n, dtype=float)
        peak = float(np.max(f)) if f.size and np.all(np.isfinite(f)) else math.nan
        if not peak < ZERO_FORCE_N:  # an all-zero table is slack: no baseline (module docstring)
            peaks[p.actuator] = peak
    return peaks


def check_profile(
    profiles: Sequence[ForceProfile],
    limits: ProfileLimits,
    previous: Sequence[ForceProfile] | None = None,
) -> LimitVerdict:
    """Check force tables against the hardware limits.

    Never raises for bad data: every problem becomes a :class:`Violation`. Checked per table, in
    this order: length (``limits.n_points``), finiteness, the grid ``100·k/(n−1)`` %GC (a table
    failing one of these is not checked further), negative force, ``max_force_n``, force outside
    ``[min_onset_pct, max_offset_pct]``, slope (seam included), and the change of the peak from
    ``previous`` (matched by actuator; an actuator absent from ``previous``, or all zero there, has
    no baseline, and an all-zero table is never a peak change: module docstring, "Peak step").

    Args:
        profiles: The tables to send, one per actuator.
        limits: The configured limits.
        previous: The tables the device last acknowledged, or None (session start, or after
            assistance-off: no peak-change baseline).

    Returns:
        The verdict; ``verdict.ok`` when every table is within every limit.
    """
    violations: list[Violation] = []
    tables = _snapshot(profiles, violations)
    peaks = _previous_peaks(previous)
    for t in tables:
        violations.extend(_check_table(t, limits.for_actuator(t.actuator), limits.n_points,
                                       peaks.get(t.actuator)))
    return LimitVerdict(tuple(violations))


def _canonical_params(space: ParameterSpace, params: object) -> tuple[dict[str, float] | None, LimitVerdict]:
    """The setting checked against its space, with derived parameters recomputed."""
    try:
        if isinstance(params, Mapping):
            vec = space.check(params)
        else:
            vec = space.check(np.asarray(params, dtype=float).reshape(-1))
    except (ValueError, TypeError) as err:  # InfeasibleError and ConfigError are ValueErrors
        return None, LimitVerdict((Violation(ViolationKind.PARAMS, f"setting {params!r:.200}: {err}"),))
    full = space.to_dict(vec)
    if isinstance(params, Mapping):
        for d in space.derived:
            if d.name in params:
                try:
                    given = float(params[d.name])
                except (TypeError, ValueError):
                    given = math.nan
                if not abs(given - full[d.name]) <= _DERIVED_TOL * (1.0 + abs(full[d.name])):
                    msg = (f"derived parameter {d.name} = {params[d.name]!r} disagrees with "
                           f"{d.text or d.name} = {full[d.name]:g}")
                    return None, LimitVerdict((Violation(ViolationKind.PARAMS, msg, value=given,
                                                         limit=full[d.name]),))
    return full, LimitVerdict()


def check_params(
    space: ParameterSpace, params: Mapping[str, float] | Sequence[float] | np.ndarray,
) -> LimitVerdict:
    """Check a setting against its space: names, finiteness, bounds, linear constraints.

    Derived parameters may be given; they must equal what the space computes (the profile
    builder may read them, so a stale or NaN derived value must not slip through).

    Returns:
        ``ok``, or one PARAMS violation naming the first problem (as ``space.check`` reports it).
    """
    return _canonical_params(space, params)[1]


# --------------------------------------------------------------------------------------------
# The gate
# --------------------------------------------------------------------------------------------

_ADMIT_TOKEN = object()  # only this module can make an AdmittedProfile


class AdmittedProfile:
    """A setting and its force tables that passed every check of a :class:`SafeProfileGate`.

    The only thing the bridge may push over CAN. Made only by :meth:`SafeProfileGate.admit`;
    immutable (tables are read-only arrays).

    Attributes:
        params: The setting, derived parameters recomputed by the space (read-only mapping).
        profiles: One :class:`ForceProfile` per actuator.
        serial: The gate's count of admitted profiles, 1-based.
    """

    __slots__ = ("__weakref__", "_params", "_profiles", "_serial")

    def __init__(self, token: object, params: Mapping[str, float],
                 profiles: tuple[ForceProfile, ...], serial: int) -> None:
        if token is not _ADMIT_TOKEN:
            raise TypeError("AdmittedProfile is made only by SafeProfileGate.admit(); "
                            "nothing may bypass the limits")
        object.__setattr__(self, "_params", MappingProxyType(dict(params)))
        object.__setattr__(self, "_profiles", tuple(profiles))
        object.__setattr__(self, "_serial", int(serial))

    def __setattr__(self, name: str, value: object) -> None:
        raise AttributeError(f"AdmittedProfile is immutable (tried to set {name!r})")

    def __delattr__(self, name: str) -> None:
        raise AttributeError(f"AdmittedProfile is immutable (tried to delete {name!r})")

    def __reduce__(self) -> Any:
        # A copy or an unpickled object would be an AdmittedProfile no gate checked.
        raise TypeError("an AdmittedProfile cannot be copied or pickled; admit the setting again")

    def __repr__(self) -> str:
        peaks = ", ".join(f"{p.actuator} {p.peak_n:.1f} N" for p in self._profiles)
        return f"AdmittedProfile(serial={self._serial}, peaks: {peaks})"

    @property
    def params(self) -> Mapping[str, float]:
        """The setting (derived parameters included)."""
        return self._params

    @property
    def profiles(self) -> tuple[ForceProfile, ...]:
        """The tables, one per actuator."""
        return self._profiles

    @property
    def serial(self) -> int:
        """1-based count of profiles the gate admitted."""
        return self._serial

    def forces_n(self, actuator: str) -> np.ndarray:
        """The read-only force table (N) of ``actuator``, shape (n_points,)."""
        for p in self._profiles:
            if p.actuator == actuator:
                return p.force_n
        raise KeyError(f"no table for actuator {actuator!r}; have {[p.actuator for p in self._profiles]}")

    def to_json(self) -> dict[str, Any]:
        """JSON-able form (for the log's ``profiles sent`` channel)."""
        return {"serial": self._serial, "params": dict(self._params),
                "profiles": [p.to_json() for p in self._profiles]}


ProfileBuilder = Callable[[Mapping[str, float]], Sequence[ForceProfile]]


class SafeProfileGate:
    """Admits settings whose force tables are within the limits; remembers what the device acked.

    Args:
        space: The parameter space the optimizer searches; ``space.name`` picks the builder.
        limits: The hardware limits.
        body_mass_kg: Passed to the builder (``hip_ankle_4d`` scales its forces by it).
        builder: ``params -> tables``; default :func:`hilbo_core.profiles.build_profile` for
            ``space.name`` (tests inject others).

    Typical use in the bridge::

        try:
            admitted = gate.admit(opt.ask())
        except UnsafeProfileError as err:
            log_event("profile_rejected", err.verdict.to_json()); opt.cancel_current()
            if gate.rejections_exhausted: assistance_off_and_pause()
        else:
            result = await endpoint.push_profile(admitted.forces_n("hip"), version)
            gate.acknowledge(admitted)           # only after the device's ack
    """

    def __init__(self, space: ParameterSpace, limits: ProfileLimits, *,
                 body_mass_kg: float | None = None, builder: ProfileBuilder | None = None) -> None:
        if not isinstance(space, ParameterSpace):
            raise BridgeConfigError(f"space must be a ParameterSpace, got {type(space).__name__}")
        if not isinstance(limits, ProfileLimits):
            raise BridgeConfigError(f"limits must be ProfileLimits, got {type(limits).__name__}")
        self.space = space
        self.limits = limits
        if builder is None:
            kwargs: dict[str, object] = {} if body_mass_kg is None else {"body_mass_kg": float(body_mass_kg)}

            def builder(params: Mapping[str, float]) -> Sequence[ForceProfile]:
                return build_profile(space.name, params, **kwargs)

        self._builder: ProfileBuilder = builder
        self._acknowledged: AdmittedProfile | None = None
        self._issued: weakref.WeakSet[AdmittedProfile] = weakref.WeakSet()
        self._serial = 0
        self._consecutive_rejections = 0
        self.rejected_count = 0

    @property
    def acknowledged(self) -> AdmittedProfile | None:
        """The profile the device last acknowledged (None at start and after assistance-off)."""
        return self._acknowledged

    @property
    def admitted_count(self) -> int:
        """Profiles admitted so far."""
        return self._serial

    @property
    def consecutive_rejections(self) -> int:
        """Rejections since the last admitted profile."""
        return self._consecutive_rejections

    @property
    def rejections_exhausted(self) -> bool:
        """``limits.max_consecutive_rejections`` proposals in a row were refused: pause for the operator."""
        return self._consecutive_rejections >= self.limits.max_consecutive_rejections

    def _evaluate(self, params: object, *, zero_force: bool = False
                  ) -> tuple[LimitVerdict, dict[str, float] | None, list[_Table]]:
        full, verdict = _canonical_params(self.space, params)
        if full is None:
            return verdict, None, []
        try:
            built = self._builder(MappingProxyType(full))
            if zero_force:
                built = [ForceProfile(p.actuator, p.gait_pct, np.zeros(np.shape(p.force_n))) for p in built]
        except Exception as err:  # any builder failure means "send nothing"; it is reported
            return LimitVerdict((Violation(ViolationKind.BUILD,
                                           f"the profile builder refused {full}: "
                                           f"{type(err).__name__}: {err}"),)), None, []
        prev = None if self._acknowledged is None else self._acknowledged.profiles
        violations: list[Violation] = []
        tables = _snapshot(built, violations)
        peaks = _previous_peaks(prev)
        for t in tables:
            violations.extend(_check_table(t, self.limits.for_actuator(t.actuator), self.limits.n_points,
                                           peaks.get(t.actuator)))
        return LimitVerdict(tuple(violations)), full, tables

    def verdict(self, params: object) -> LimitVerdict:
        """Check a setting against the space and the limits without admitting or counting it.

        A dry run (status displays, :func:`preflight`); the baseline is the acknowledged profile.
        """
        return self._evaluate(params)[0]

    def admit(self, params: Mapping[str, float]) -> AdmittedProfile:
        """Build and check the tables of a setting; the result is the only thing the bridge may push.

        Raises:
            UnsafeProfileError: The setting is outside its space, the builder refused it, or a
                table breaks a limit; ``err.verdict`` lists every violation. Nothing is clipped.
        """
        return self._admit(params, zero_force=False)

    def admit_zero_force(self, params: Mapping[str, float]) -> AdmittedProfile:
        """The tables of ``params`` with every force 0 N, through the same checks as :meth:`admit`.

        Zero-force tracking: the suit worn and actuated, its force controller running and tracking
        0 N, so the wearer feels the suit's mass and what the tracking leaves, but no assistance.
        drivers/PROTOCOL.md has no command for it (Mode ``transparent`` is only the device's state
        before its first profile), so it is a profile like any other: the same actuators and grid
        as the setting's tables, every point 0 N. It differs from assistance-off, where the device
        ramps to slack and stops following a table. The setting itself must still be feasible (it
        names the tables' actuators and grid; ``params`` of the result is it).

        Raises:
            UnsafeProfileError: As :meth:`admit` (the setting is outside its space, or the builder
                refused it); an all-zero table itself is within every limit.
        """
        return self._admit(params, zero_force=True)

    def _admit(self, params: Mapping[str, float], *, zero_force: bool) -> AdmittedProfile:
        verdict, full, tables = self._evaluate(params, zero_force=zero_force)
        if not verdict.ok or full is None:
            self._consecutive_rejections += 1
            self.rejected_count += 1
            raise UnsafeProfileError(f"setting rejected by the hardware limits: {verdict.describe()}",
                                     verdict, params)
        # The tables kept are the read-only snapshots that were checked, not the builder's objects.
        profiles = tuple(ForceProfile(t.actuator, t.gait_pct, t.force_n) for t in tables)
        self._serial += 1
        self._consecutive_rejections = 0
        admitted = AdmittedProfile(_ADMIT_TOKEN, full, profiles, self._serial)
        self._issued.add(admitted)
        return admitted

    def acknowledge(self, admitted: AdmittedProfile) -> None:
        """Record that the device acknowledged ``admitted``: it becomes the peak-change baseline.

        Raises:
            UnsafeProfileError: ``admitted`` was not issued by this gate's :meth:`admit`.
        """
        if not isinstance(admitted, AdmittedProfile) or admitted not in self._issued:
            raise UnsafeProfileError(
                f"{admitted!r:.80} was not admitted by this gate; refusing it as a baseline",
                LimitVerdict((Violation(ViolationKind.NO_PROFILE, "not admitted by this gate"),)),
            )
        self._acknowledged = admitted

    def assistance_off(self) -> None:
        """The device was commanded to slack: the next profile has no peak-change baseline."""
        self._acknowledged = None


# --------------------------------------------------------------------------------------------
# Pre-flight: how much of the space do the limits refuse?
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class PreflightReport:
    """How many sampled feasible settings the limits refuse (no peak-change baseline).

    Attributes:
        n_checked: Settings sampled (scrambled Sobol, feasible).
        n_rejected: Of those, refused.
        by_kind: Refusals by violation kind (a setting may count under several).
        example: The first refusal's description, or None.
    """

    n_checked: int
    n_rejected: int
    by_kind: Mapping[str, int]
    example: str | None

    def to_json(self) -> dict[str, Any]:
        """JSON-able form."""
        return {"n_checked": self.n_checked, "n_rejected": self.n_rejected,
                "by_kind": dict(self.by_kind), "example": self.example}


def preflight(space: ParameterSpace, limits: ProfileLimits, *, body_mass_kg: float | None = None,
              n: int = 256, seed: int = 0, builder: ProfileBuilder | None = None) -> PreflightReport:
    """Check ``n`` feasible settings of the space against the limits, without a baseline.

    A space whose settings the limits often refuse makes a session stall (every refusal cancels
    the setting), so ``hilbo config check`` reports this before anyone walks.
    """
    gate = SafeProfileGate(space, limits, body_mass_kg=body_mass_kg, builder=builder)
    points = space.from_unit(space.sample_unit(n, np.random.default_rng(seed)))
    by_kind: dict[str, int] = {}
    rejected = 0
    example: str | None = None
    for x in points:
        verdict = gate.verdict(space.to_dict(x))
        if not verdict.ok:
            rejected += 1
            example = example or verdict.describe()
            for k in verdict.kinds:
                by_kind[k.value] = by_kind.get(k.value, 0) + 1
    return PreflightReport(len(points), rejected, MappingProxyType(by_kind), example)
