"""The virtual exosuit: the device side of the exosuit CAN protocol, on any python-can bus.

:class:`VirtualExosuit` is an asyncio CAN node that behaves like the exosuit's motor-driver layer
as ``drivers/PROTOCOL.md`` specifies it ("What the device must do"), so the bridge can be tested,
demonstrated and benchmarked without hardware:

* **DeviceStatus** of every actuator every 20 ms (mode, fault bits, gait phase, active and
  pending profile version, counter): the device heartbeat.
* **Gait.** The wearer walks from the moment the node opens: strides of about 1.1 s
  (:class:`GaitConfig`) with stride-to-stride variability, seeded. Each actuator has its own
  gait-cycle boundary (0 %GC), a fixed fraction of the stride after the reference leg's (see
  "Joints" below).
* **Profile reception.** Segments go into the receive buffer of a
  :class:`~drivers.exosuit.profile.ProfileAssembler`; a commit is checked in the protocol's order
  (busy, bad_version, bad_length, missing_segment, bad_crc, out_of_limits against this device's
  own :class:`DeviceLimits`) and answered at once with a ProfileAck. An acked table goes to the
  back buffer (``ProfileVersionPending``); each actuator switches to it atomically at its own
  next gait-cycle boundary, never mid-table, and then reports it in ``ProfileVersionActive``.
* **Applied profiles.** Whenever what the wearer actually receives changes — every actuator
  assisting with one new table, or assistance stopping — ``on_applied(profiles, t_s)`` is called
  with the simulated time of the gait-cycle boundary of the last actuator to switch (or of the
  stop). ``profiles`` is a tuple of :class:`~hilbo_core.profiles.ForceProfile`, one per joint,
  ``()`` for no assistance; ``hilbo sim`` wires ``on_applied=cart.on_profile_applied`` so the
  simulated wearer feels what the device applies, not what the bridge intended. A device in
  another process is followed from the bus with :class:`AppliedProfileListener`.
* **ForceFeedback** of every actuator at the controller's rate (``feedback_hz``; 1 kHz on the
  real device, lower in tests): the desired force of the active table at the current gait phase
  and a measured force that follows it through a first-order lag plus sensor noise
  (:class:`TrackingConfig`), within about 5 % of the peak.
* **Safe state.** Identifier 0x010 with *any* payload (seen on the raw frame, before decoding),
  100 ms without a bridge heartbeat whose counter advanced, or a heartbeat announcing ``paused``
  or ``shutdown`` (or anything but ``running`` while assisting) ramp every actuator to zero at
  once (Mode = assistance_off, latched; a lost heartbeat also sets FaultHeartbeatLost until a
  ClearFaults clears it, with Mode = assistance_off as PROTOCOL.md's heartbeat sequence shows; Mode =
  fault is reserved for the hardware faults, here the bus error after a bus-off). The latch
  clears only when a commit is acked while the bridge heartbeat is fresh and ``running`` and no
  fault bit is set; assistance restarts at the next gait-cycle boundary. A bridge that is still
  ``idle`` (session not started) does not latch the device: its tables are taken and switched,
  but the device stays transparent (zero force) and starts assisting at the first boundary after
  the bridge turns ``running``.
* **Clearing faults** (PROTOCOL.md, "Clearing a latched fault"). Fault bits are latched: while
  any is set, commits are nacked ``busy``. A ClearFaults request clears FaultHeartbeatLost only
  once the bridge heartbeat has been back (advancing, without a watchdog expiry) for
  ``heartbeat_clear_s``, and a hardware fault only once its cause (an injected window, below)
  is over; the device answers with ClearFaultsAck (what it cleared, what it still holds) for
  each addressed actuator. FaultBusError clears itself after ``bus_error_hold_s``. The device's
  faults are the node's: a request addressed to either actuator clears them for both.
* **Faults** for the bridge's reliability tests (:data:`EXOSUIT_FAULTS`, in the shared syntax of
  :mod:`virtual_hw.faults`, ``--fault`` on the command line): ``drop-status@T+D`` stops the
  device heartbeat (DeviceStatus); ``bus-off@T+D`` makes the node deaf and mute, then reports
  FaultBusError with Mode = fault (commits nacked ``busy``) for ``bus_error_hold_s`` and leaves
  it in assistance-off; ``nack-<reason>@TxN`` or ``@T+D`` (``nack-bad-crc``, ``nack-busy``,
  ``nack-out-of-limits``, ...) nacks the next N commits or every commit in a window;
  ``wrong-dlc``, ``unknown-id`` and ``garbage`` (``@TxN`` or ``@T+D``) transmit malformed frames
  at ``malformed_rate_hz``; ``overcurrent``, ``overtemperature``, ``force-sensor``, ``encoder``,
  ``force-limit`` and ``emergency-stop`` (``@T+D``) are hardware faults whose cause lasts the
  window: the bit latches at its start (Mode = fault, assistance off) and can be cleared only
  after its end.

Joints and the two-table convention
-----------------------------------
``joints`` names the load path of each actuator, in actuator order. A profile push carries ONE
table of ``n`` points; the device splits it into one equal chunk per *distinct* joint, in order of
first appearance, and each actuator executes its joint's chunk. The layout is the protocol's,
defined once in :mod:`drivers.exosuit.profile` (:func:`~drivers.exosuit.profile.table_order`,
:func:`~drivers.exosuit.profile.pack_tables`, :func:`~drivers.exosuit.profile.unpack_tables`)
and in PROTOCOL.md:

* hip suit, ``joints=("hip", "hip")`` (:data:`SUIT_JOINTS` ``["hip_6d"]``): one 101-point table,
  executed by both legs; ``on_applied`` gets ``(ForceProfile("hip", ...),)``.
* hip + ankle suit, ``joints=("hip", "ankle")`` (``["hip_ankle_4d"]``): the concatenation
  ``[hip 101 points, ankle 101 points]`` (``n = 202``); actuator 0 executes the hip half and
  actuator 1 the ankle half; ``on_applied`` gets ``(hip, ankle)`` profiles, as
  :func:`~hilbo_core.profiles.build_profile` returns them. A table whose length is not a multiple
  of the number of joints is nacked ``bad_length``.

Each actuator's 0 %GC is its own gait event (PROTOCOL.md §"What the device must do" 4): maximum
hip flexion for the hip, heel strike for the ankle. The second leg of a joint is half a stride
after the first; heel strike comes 15 % of a stride after maximum hip flexion (maximum hip flexion
is at ≈ 85 %GC from heel strike in healthy walking; Winter, *Biomechanics and Motor Control of
Human Movement*), so ``PHASE_OFFSETS = {"hip": 0.0, "ankle": 0.15}``.

Clocks
------
Two time bases, as DESIGN.md prescribes ("wall clock is used only by watchdogs"): the gait, the
table switches, the force dynamics, the fault windows and the times given to ``on_applied`` run
on the simulated clock (``clock.now()``, ``await clock.sleep_until(t)``; :mod:`virtual_hw.clock`)
so a session at any speed sees the same ordering of events; the bus-level periods and watchdogs
(DeviceStatus every 20 ms, ForceFeedback at ``feedback_hz``, the 100 ms bridge-heartbeat
watchdog, malformed-frame rates) run on the event loop's monotonic clock, because the bridge's
own heartbeat and watchdogs do. A firmware watchdog never stalls, a Python process on a busy host
does: when the watchdog fires more than one heartbeat period late (this process's own event loop
was stalled), it waits up to three more periods for heartbeats still queued in the receive path
before it declares the bridge lost.
"""

from __future__ import annotations

import asyncio
import bisect
import collections
import contextlib
import logging
import math
import types
from collections.abc import Callable, Coroutine, Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Protocol

import can
import numpy as np

from drivers.exosuit.codec import (
    ASSISTANCE_OFF_ID,
    N_ACTUATORS,
    BridgeHeartbeat,
    BridgeState,
    ClearFaults,
    ClearFaultsAck,
    DeviceFault,
    DeviceMode,
    DeviceStatus,
    EncodeError,
    ForceFeedback,
    NackReason,
    ProfileAck,
    ProfileCommit,
    ProfileSegment,
    database,
    frame_id,
)
from drivers.exosuit.endpoint import CanBusConfig, CanEndpoint, Subscription
from drivers.exosuit.faults import FAULT_INFO, HEARTBEAT_CLEAR_S
from drivers.exosuit.profile import (
    MAX_FORCE_ON_WIRE_N,
    MAX_PROFILE_POINTS,
    MIN_PROFILE_POINTS,
    ProfileAssembler,
    forces_to_raw,
    profile_crc32,
    raw_to_forces,
    segment_count,
    table_order,
    unpack_tables,
)
from hilbo_core.profiles import ForceProfile
from virtual_hw.clock import SimClock
from virtual_hw.errors import VirtualConfigError, VirtualHwError
from virtual_hw.faults import FaultCatalog, FaultKind, FaultSchedule, FaultShape, FaultSpec

__all__ = [
    "DEFAULT_FEEDBACK_HZ",
    "EXOSUIT_FAULTS",
    "HARDWARE_FAULTS",
    "HEARTBEAT_TIMEOUT_S",
    "LIVENESS_TIMEOUT_S",
    "MALFORMED_FAULTS",
    "NACK_FAULTS",
    "PHASE_OFFSETS",
    "STATUS_PERIOD_S",
    "SUIT_JOINTS",
    "AppliedProfileListener",
    "AppliedTable",
    "DeviceLimits",
    "GaitConfig",
    "GaitModel",
    "TrackingConfig",
    "VirtualExosuit",
    "applied_profile_feed",
    "split_table",
]

log = logging.getLogger(__name__)

#: DeviceStatus period per actuator (PROTOCOL.md: the device heartbeat, every 20 ms).
STATUS_PERIOD_S = 0.020
#: Bridge-heartbeat bus watchdog: 5 periods of 20 ms without an advanced counter (PROTOCOL.md).
HEARTBEAT_TIMEOUT_S = 0.100
#: Bridge liveness watchdog: the heartbeat's Liveness unchanged this long means the bridge
#: process is hung although its cyclic sender still runs (PROTOCOL.md).
LIVENESS_TIMEOUT_S = 1.0
#: The force controller's rate on the real device (ForceFeedback per actuator).
DEFAULT_FEEDBACK_HZ = 1000.0
#: Joints per actuator for the parameter-space presets (see the module docstring).
SUIT_JOINTS: Mapping[str, tuple[str, ...]] = types.MappingProxyType({
    "hip_6d": ("hip", "hip"),
    "hip_ankle_4d": ("hip", "ankle"),
})
#: Where each joint's 0 %GC lies in the stride of the reference leg, as a fraction of the stride.
PHASE_OFFSETS: Mapping[str, float] = types.MappingProxyType({"hip": 0.0, "ankle": 0.15})
# The second actuator of a joint (the other leg) is half a stride later.
_OTHER_LEG_OFFSET = 0.5
# A device never transmits the bridge's identifiers, even as "garbage".
_BRIDGE_IDS = frozenset(
    frame_id(name)
    for name in ("AssistanceOff", "BridgeHeartbeat", "ProfileCommit", "ProfileSegment",
                 "ClearFaults")
)
# How many acked tables the listener keeps while it waits for them to become active.
_LISTENER_KEEP = 8
# A watchdog callback this late means the device's own event loop stalled (one heartbeat period).
_STALL_GRACE_S = 0.020
# ...and the watchdog waits for the receive path at most this many times in a row.
_MAX_DEFERRALS = 3
# How far a periodic loop may fall behind before it skips ticks instead of catching up.
_MAX_LAG_S = 0.010
# ForceFeedback.MeasuredForce range on the wire (signed 16 bit of 0.1 N).
_MEASURED_RANGE_N = (-3276.8, 3276.7)


# ------------------------------------------------------------------------------ configuration


def _check_number(owner: str, name: str, value: object, lo: float, hi: float,
                  *, lo_open: bool = False) -> float:
    ok = isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)
    if ok:
        v = float(value)  # type: ignore[arg-type]
        ok = (v > lo if lo_open else v >= lo) and v <= hi
    if not ok:
        bracket = "(" if lo_open else "["
        raise VirtualConfigError(f"{owner}.{name}={value!r}; expected a number in {bracket}{lo:g}, {hi:g}]")
    return float(value)  # type: ignore[arg-type]


@dataclass(frozen=True)
class DeviceLimits:
    """The device's own hardware limits, enforced on every table it receives (nack
    ``out_of_limits``), whatever the bridge already clipped.

    Attributes:
        max_force_n: largest force of any point, N (default 600 N, ≈ 60 % of the body weight
            of a 100 kg wearer, Kim et al. 2019's largest ankle assistance).
        max_slope_n_per_pct: largest change of force per % gait cycle between neighbouring points
            (N/%GC); the step allowed between neighbours of an ``m``-point table is
            ``max_slope_n_per_pct · 100 / (m − 1)``. The default, 80 N/%GC (≈ 7 kN/s at a 1.1 s
            stride), passes every feasible preset profile (the steepest, the hip+ankle preset's
            ankle ramp, is 60 % BW over 10 %GC ≈ 59 N/%GC at 100 kg).
        max_points: longest table accepted (≤ 768); longer commits are nacked ``bad_length``.

    Raises:
        VirtualConfigError: a limit outside its range.
    """

    max_force_n: float = 600.0
    max_slope_n_per_pct: float = 80.0
    max_points: int = MAX_PROFILE_POINTS

    def __post_init__(self) -> None:
        _check_number("DeviceLimits", "max_force_n", self.max_force_n, 0.0, 6553.5, lo_open=True)
        _check_number("DeviceLimits", "max_slope_n_per_pct", self.max_slope_n_per_pct, 0.0, 1e5,
                      lo_open=True)
        if isinstance(self.max_points, bool) or not isinstance(self.max_points, int) or not (
            MIN_PROFILE_POINTS <= self.max_points <= MAX_PROFILE_POINTS
        ):
            raise VirtualConfigError(
                f"DeviceLimits.max_points={self.max_points!r}; expected an integer "
                f"{MIN_PROFILE_POINTS}..{MAX_PROFILE_POINTS}"
            )


@dataclass(frozen=True)
class GaitConfig:
    """Stride timing of the simulated walk.

    Stride ``k`` lasts ``stride_s · (1 + e_k)`` with ``e_k`` an AR(1) series of stationary SD
    ``stride_cv`` and lag-one correlation ``stride_ar1``, clipped at ±4 SD. Healthy adults
    walking at a steady speed show stride-time CVs of about 1.5–3 % with persistent (positively
    correlated) fluctuations (Hausdorff et al., J Appl Physiol 1995 and 1996); 1.1 s is a typical
    stride at Kim et al. 2019's 1.25 m/s treadmill speed.

    Attributes:
        stride_s: mean stride time, s.
        stride_cv: stride-to-stride coefficient of variation.
        stride_ar1: lag-one correlation of consecutive stride deviations.
    """

    stride_s: float = 1.1
    stride_cv: float = 0.025
    stride_ar1: float = 0.5

    def __post_init__(self) -> None:
        _check_number("GaitConfig", "stride_s", self.stride_s, 0.2, 5.0)
        _check_number("GaitConfig", "stride_cv", self.stride_cv, 0.0, 0.2)
        _check_number("GaitConfig", "stride_ar1", self.stride_ar1, 0.0, 0.95)


@dataclass(frozen=True)
class TrackingConfig:
    """How the measured cable force follows the desired one.

    The measured force is the desired force through a first-order lag of time constant
    ``lag_s`` (the closed-loop response of a force controller with the known profile as
    feed-forward) plus white sensor noise of SD ``noise_n``. With a ramp of slope ``s`` the lag
    error settles at ``s·lag_s``: 2 ms keeps it under 5 % of the peak for every feasible preset
    profile (the steepest, an ankle ramp of ≈ 4 kN/s to ≈ 440 N, lags by ≈ 8 N, 2 %), and a
    stop reaches cable slack (< 5 N) from 600 N in ≈ 10 ms, inside PROTOCOL.md's 50 ms.

    Attributes:
        lag_s: first-order time constant, s (simulated clock).
        noise_n: SD of the load-cell noise, N.
    """

    lag_s: float = 0.002
    noise_n: float = 0.8

    def __post_init__(self) -> None:
        _check_number("TrackingConfig", "lag_s", self.lag_s, 0.0, 1.0, lo_open=True)
        _check_number("TrackingConfig", "noise_n", self.noise_n, 0.0, 100.0)


# ------------------------------------------------------------------------------ faults

#: Nack reasons a ``nack-*`` fault can inject (every reason but NONE), by fault kind name.
NACK_FAULTS: Mapping[str, NackReason] = types.MappingProxyType({
    "nack-" + r.name.lower().replace("_", "-"): r for r in NackReason if r != NackReason.NONE
})
#: Hardware faults a window fault injects: the cause lasts the window, the bit stays latched
#: until a ClearFaults after it (fault kind name -> bit).
HARDWARE_FAULTS: Mapping[str, DeviceFault] = types.MappingProxyType({
    FAULT_INFO[bit].name.replace("_", "-"): bit
    for bit in (DeviceFault.OVERCURRENT, DeviceFault.OVERTEMPERATURE, DeviceFault.FORCE_SENSOR,
                DeviceFault.ENCODER, DeviceFault.FORCE_LIMIT, DeviceFault.EMERGENCY_STOP)
})
#: Malformed-frame fault kinds (:meth:`VirtualExosuit._malformed_frame`).
MALFORMED_FAULTS = ("wrong-dlc", "unknown-id", "garbage")

#: The faults a virtual exosuit can inject (syntax: :mod:`virtual_hw.faults`; times are simulated
#: seconds, so a fault hits the same protocol step at every speed).
EXOSUIT_FAULTS = FaultCatalog("virtual exosuit", (
    FaultKind("drop-status", FaultShape.WINDOW,
              "send no DeviceStatus (the device heartbeat); feedback continues"),
    FaultKind("bus-off", FaultShape.WINDOW,
              "bus-off: receive and transmit nothing; on recovery FaultBusError, Mode=fault, "
              "busy nacks and assistance off for bus_error_hold_s"),
    *(FaultKind(name, FaultShape.EVENTS, f"nack commits with reason {reason.name.lower()}")
      for name, reason in NACK_FAULTS.items()),
    *(FaultKind(name, FaultShape.WINDOW,
                f"{FAULT_INFO[bit].meaning} for the window: "
                f"Fault{''.join(w.capitalize() for w in FAULT_INFO[bit].name.split('_'))} latches "
                "(Mode=fault, assistance off); a ClearFaults clears it only after the window")
      for name, bit in HARDWARE_FAULTS.items()),
    FaultKind("wrong-dlc", FaultShape.EVENTS,
              "transmit DeviceStatus/ForceFeedback frames of a wrong length, at malformed_rate_hz"),
    FaultKind("unknown-id", FaultShape.EVENTS,
              "transmit frames with identifiers the DBC does not define, at malformed_rate_hz"),
    FaultKind("garbage", FaultShape.EVENTS,
              "transmit random identifiers (never the bridge's), lengths and bytes, at "
              "malformed_rate_hz"),
))


# ------------------------------------------------------------------------------ gait


class GaitModel:
    """Seeded stride sequence and the gait phase of each actuator (pure; no clock, no I/O).

    Reference boundaries ``b_k`` (maximum hip flexion of the reference leg) are generated lazily
    and kept, so any time at or after the start can be queried, and the sequence depends only on
    the seeded stream and the gait config, not on when it is queried. Actuator ``a`` with
    stride fraction ``o_a`` has its boundaries at
    ``β_k = b_k + o_a·(b_{k+1} − b_k)``; its phase runs linearly from 0 to 100 % between
    consecutive boundaries.

    Args:
        offsets: stride fraction of each actuator's 0 %GC, each in [0, 1).
        config: stride statistics.
        rng: the random stream of the strides (the first draw sets the initial phase).
        t0_s: the simulated time at which walking is observed to start.
    """

    def __init__(self, offsets: Sequence[float], config: GaitConfig, rng: np.random.Generator,
                 t0_s: float) -> None:
        self.offsets = tuple(float(o) for o in offsets)
        if not self.offsets or not all(0.0 <= o < 1.0 for o in self.offsets):
            raise VirtualConfigError(f"gait offsets {offsets!r}; expected fractions in [0, 1)")
        self.config = config
        self._rng = rng
        self._e = 0.0
        first = self._draw_stride(first=True)
        start = float(t0_s) - float(rng.uniform(0.0, 1.0)) * first
        self._b = [start, start + first]

    def _draw_stride(self, *, first: bool = False) -> float:
        cfg = self.config
        rho = 0.0 if first else cfg.stride_ar1
        xi = float(self._rng.standard_normal())
        self._e = rho * self._e + math.sqrt(1.0 - rho * rho) * cfg.stride_cv * xi
        e = min(max(self._e, -4.0 * cfg.stride_cv), 4.0 * cfg.stride_cv)
        return cfg.stride_s * (1.0 + e)

    def _cover(self, t_s: float) -> None:
        while self._b[-1] <= t_s:
            self._b.append(self._b[-1] + self._draw_stride())

    def _cover_index(self, k: int) -> None:
        while len(self._b) <= k:
            self._b.append(self._b[-1] + self._draw_stride())

    def _interval(self, t_s: float) -> int:
        """Index k with b_k <= t < b_{k+1}."""
        if t_s < self._b[0]:
            raise VirtualConfigError(f"gait time {t_s!r} s is before the walk started ({self._b[0]!r} s)")
        self._cover(t_s)
        return bisect.bisect_right(self._b, t_s) - 1

    def _boundary(self, actuator: int, k: int) -> float:
        """Boundary of ``actuator`` in reference stride ``k`` (k = -1: the stride before b_0)."""
        o = self.offsets[actuator]
        if k < 0:
            first = self._b[1] - self._b[0]
            return self._b[0] - first + o * first
        self._cover_index(k + 1)
        return self._b[k] + o * (self._b[k + 1] - self._b[k])

    def cycle(self, actuator: int, t_s: float) -> tuple[float, float]:
        """``(start, end)`` of the gait cycle of ``actuator`` that contains ``t_s``, s."""
        k = self._interval(t_s)
        start = self._boundary(actuator, k)
        if t_s >= start:
            return start, self._boundary(actuator, k + 1)
        return self._boundary(actuator, k - 1), start

    def phase_pct(self, actuator: int, t_s: float) -> float:
        """Gait phase of ``actuator`` at ``t_s``, in [0, 100) %GC (exactly 0 at a boundary)."""
        start, end = self.cycle(actuator, t_s)
        return 100.0 * (t_s - start) / (end - start)

    def stride_at(self, actuator: int, t_s: float) -> float:
        """Duration of the gait cycle of ``actuator`` that contains ``t_s``, s."""
        start, end = self.cycle(actuator, t_s)
        return end - start

    def next_boundary(self, actuator: int, after_s: float) -> float:
        """The first gait-cycle boundary (0 %GC) of ``actuator`` strictly after ``after_s``."""
        k = self._interval(after_s)
        while (t := self._boundary(actuator, k)) <= after_s:
            k += 1
        return t


def _joint_offsets(joints: Sequence[str]) -> tuple[float, ...]:
    seen: collections.Counter[str] = collections.Counter()
    out = []
    for joint in joints:
        if joint not in PHASE_OFFSETS:
            raise VirtualConfigError(f"joint {joint!r}; expected one of {', '.join(PHASE_OFFSETS)}")
        out.append((PHASE_OFFSETS[joint] + _OTHER_LEG_OFFSET * seen[joint]) % 1.0)
        seen[joint] += 1
    return tuple(out)


# ------------------------------------------------------------------------------ tables


@dataclass(frozen=True)
class AppliedTable:
    """A committed table as the device holds it.

    Attributes:
        version: profile version 1..255.
        forces_raw: the whole table as received, raw 0.1 N counts (bit for bit what was
            committed).
        profiles: the table split per joint (see :func:`split_table`).
    """

    version: int
    forces_raw: tuple[int, ...]
    profiles: tuple[ForceProfile, ...]

    def table_for(self, joint: str) -> ForceProfile:
        """The profile of one joint."""
        for p in self.profiles:
            if p.actuator == joint:
                return p
        raise KeyError(joint)


def _distinct(joints: Sequence[str]) -> tuple[str, ...]:
    try:
        return table_order(joints)
    except EncodeError as err:
        raise VirtualConfigError(str(err)) from err


def split_table(forces_raw: Sequence[int], joints: Sequence[str]) -> tuple[ForceProfile, ...]:
    """Split a received table into one ForceProfile per distinct joint (module docstring).

    Args:
        forces_raw: the table, raw 0.1 N counts, shape (n,).
        joints: joint of each actuator, in actuator order (``("hip", "hip")``,
            ``("hip", "ankle")``).

    Returns:
        One profile per distinct joint in order of first appearance, each over 0..100 %GC with
        ``n / len(distinct joints)`` points (:func:`~drivers.exosuit.profile.unpack_tables`).

    Raises:
        VirtualConfigError: ``n`` is not a multiple of the number of joints, or a chunk has fewer than
            2 points.
    """
    names = _distinct(joints)
    try:
        chunks = unpack_tables(np.asarray(raw_to_forces(forces_raw), dtype=float), len(names))
    except EncodeError as err:
        raise VirtualConfigError(f"{err} for joints {names}") from err
    grid = np.linspace(0.0, 100.0, chunks[0].size)
    return tuple(ForceProfile(name, grid, chunk) for name, chunk in zip(names, chunks, strict=True))


def _first_slope_violation(forces_raw: Sequence[int], n_tables: int,
                           max_slope_n_per_pct: float) -> int | None:
    """Index of the first point whose step from its neighbour in the same table is too steep."""
    chunks = unpack_tables(np.asarray(raw_to_forces(forces_raw), dtype=float), n_tables)
    m = chunks[0].size
    max_step = max_slope_n_per_pct * 100.0 / (m - 1)
    for i, chunk in enumerate(chunks):
        bad = np.flatnonzero(np.abs(np.diff(chunk)) > max_step)
        if bad.size:
            return i * m + int(bad[0]) + 1
    return None


# ------------------------------------------------------------------------------ the bus tap


class _TapBus(can.BusABC):
    """A python-can bus that wraps another and shows every received frame to the device first.

    The device must act on identifier 0x010 whatever its payload (PROTOCOL.md), and the endpoint
    only delivers frames that decode; the tap sees them raw. It also makes the node deaf while
    it is bus-off. ``on_frame`` runs in whatever thread python-can receives in.
    """

    def __init__(self, inner: can.BusABC, on_frame: Callable[[can.Message], bool]) -> None:
        self._inner = inner
        self._on_frame = on_frame
        self.channel_info = f"tap:{inner.channel_info}"
        super().__init__(channel=getattr(inner, "channel", None))
        self._can_protocol = inner.protocol

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        msg = self._inner.recv(timeout)
        if msg is not None and not self._on_frame(msg):
            return None, True
        return msg, True

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        self._inner.send(msg, timeout)

    def fileno(self) -> int:
        return self._inner.fileno()

    def shutdown(self) -> None:
        super().shutdown()
        self._inner.shutdown()


def _interface_name(bus: can.BusABC) -> str:
    for name, (module, cls) in can.interfaces.BACKENDS.items():
        if type(bus).__name__ == cls and type(bus).__module__ == module:
            return name
    return "virtual"  # only used for CanBusConfig validation and log lines


# ------------------------------------------------------------------------------ tracking


class _Tracker:
    """First-order lag of the measured force behind the desired one (TrackingConfig)."""

    def __init__(self, config: TrackingConfig, t0_s: float) -> None:
        self.config = config
        self.t_s = t0_s
        self.measured_n = 0.0

    def advance(self, t_s: float, desired_now_n: float, desired_then_n: float,
                slope_n_per_s: float) -> float:
        """Advance to ``t_s`` and return the (noise-free) measured force.

        Exact for a desired force that is a ramp of slope ``slope_n_per_s`` between the last
        time and ``t_s`` (``desired_then_n`` is that ramp's value at the last time):
        ``e(t) = −sτ + (e₀ + sτ)·exp(−Δt/τ)`` with ``e = measured − desired``.
        """
        dt = t_s - self.t_s
        if dt <= 0.0:
            return self.measured_n
        tau = self.config.lag_s
        e0 = self.measured_n - desired_then_n
        lag = slope_n_per_s * tau
        self.measured_n = desired_now_n - lag + (e0 + lag) * math.exp(-dt / tau)
        self.t_s = t_s
        return self.measured_n


# ------------------------------------------------------------------------------ the device


class _Watchdog:
    """One watchdog of the bridge heartbeat on the device's event loop (wall clock).

    :meth:`feed` (an advanced counter) re-arms it for ``timeout_s``; when it expires, ``on_lost``
    is called with it and it stays lost until the next feed. A firmware watchdog never stalls, a
    Python process on a busy host does: when the callback runs more than one heartbeat period
    late (this process's own loop was stalled), it waits up to :data:`_MAX_DEFERRALS` more
    periods for frames still queued in the receive path before it declares the bridge lost.
    """

    def __init__(self, name: str, on_lost: Callable[[_Watchdog], None],
                 stats: collections.Counter[str]) -> None:
        self.name = name
        self._on_lost = on_lost
        self._stats = stats
        self.fresh = False
        self.back_since = math.inf  # loop time since which it has been fed without expiring
        self._timer: asyncio.TimerHandle | None = None
        self._deadline = math.inf
        self._deferrals = 0

    def feed(self, loop: asyncio.AbstractEventLoop, timeout_s: float) -> None:
        now = loop.time()
        if not self.fresh:  # back after a loss (or the first frame)
            self.back_since = now
        self.fresh = True
        if self._timer is not None:
            self._timer.cancel()
        self._deadline = now + timeout_s
        self._deferrals = 0
        self._timer = loop.call_at(self._deadline, self._expire, loop)

    def cancel(self) -> None:
        if self._timer is not None:
            self._timer.cancel()
            self._timer = None

    def _expire(self, loop: asyncio.AbstractEventLoop) -> None:
        self._timer = None
        now = loop.time()
        if now - self._deadline > _STALL_GRACE_S and self._deferrals < _MAX_DEFERRALS:
            self._deferrals += 1
            self._stats["watchdog_deferred"] += 1
            self._deadline = now + _STALL_GRACE_S
            self._timer = loop.call_at(self._deadline, self._expire, loop)
            return
        self.fresh = False
        self.back_since = math.inf
        self._on_lost(self)


class VirtualExosuit:
    """A simulated exosuit node (see the module docstring for everything it does).

    Use as ``async with VirtualExosuit(config, clock, ...) as exo:``; :meth:`wait` returns when a
    task of the device fails (and raises its error); leaving the context stops every task,
    closes the bus and re-raises the first task error.

    On a :class:`~virtual_hw.clock.VirtualClock` the gait and fault tasks are clock participants
    (time waits for them at every gait-cycle boundary they act on); the bus-level loops run on
    the event loop's clock and only read the simulated time.

    Args:
        bus: a :class:`~drivers.exosuit.endpoint.CanBusConfig` to open, or an open python-can
            bus (the device takes it over and shuts it down on exit).
        clock: the simulated clock.
        n_actuators: 1 or 2.
        joints: joint of each actuator (default all ``"hip"``); see the module docstring.
        limits: the device's hardware limits.
        seed: seeds the strides, the sensor noise and the malformed frames.
        faults: faults to inject (:data:`EXOSUIT_FAULTS` specs, as text or
            :class:`~virtual_hw.faults.FaultSpec`).
        on_applied: called with ``(profiles, t_s)`` whenever the applied assistance changes.
        feedback_hz: ForceFeedback rate per actuator (wall clock); 0 disables feedback.
        status_period_s: DeviceStatus period (wall clock).
        heartbeat_timeout_s: bridge-heartbeat bus watchdog: no frame with an advanced
            Counter for this long (wall clock).
        liveness_timeout_s: bridge liveness watchdog: the heartbeat's Liveness unchanged for
            this long (wall clock).
        heartbeat_clear_s: how long the bridge heartbeat must have been back before a
            ClearFaults clears FaultHeartbeatLost (wall clock).
        malformed_rate_hz: malformed frames per wall second while such a fault is on.
        bus_error_hold_s: how long FaultBusError and Mode = fault last after a bus-off
            (simulated s).
        gait: stride statistics.
        tracking: force-tracking model.

    Raises:
        VirtualConfigError: a bad argument (FaultSpecError for a bad fault spec).
    """

    def __init__(
        self,
        bus: CanBusConfig | can.BusABC,
        clock: SimClock,
        *,
        n_actuators: int = N_ACTUATORS,
        joints: Sequence[str] | None = None,
        limits: DeviceLimits | None = None,
        seed: int = 0,
        faults: Iterable[str | FaultSpec] = (),
        on_applied: Callable[[tuple[ForceProfile, ...], float], object] | None = None,
        feedback_hz: float = DEFAULT_FEEDBACK_HZ,
        status_period_s: float = STATUS_PERIOD_S,
        heartbeat_timeout_s: float = HEARTBEAT_TIMEOUT_S,
        liveness_timeout_s: float = LIVENESS_TIMEOUT_S,
        heartbeat_clear_s: float = HEARTBEAT_CLEAR_S,
        malformed_rate_hz: float = 50.0,
        bus_error_hold_s: float = 0.5,
        gait: GaitConfig | None = None,
        tracking: TrackingConfig | None = None,
    ) -> None:
        if isinstance(n_actuators, bool) or n_actuators not in range(1, N_ACTUATORS + 1):
            raise VirtualConfigError(f"n_actuators={n_actuators!r}; expected 1..{N_ACTUATORS}")
        joints = tuple(joints) if joints is not None else ("hip",) * n_actuators
        if len(joints) != n_actuators:
            raise VirtualConfigError(
                f"joints={joints!r}; expected one joint per actuator ({n_actuators})"
            )
        self._offsets = _joint_offsets(joints)
        if not isinstance(bus, CanBusConfig | can.BusABC):
            raise VirtualConfigError(f"bus must be a CanBusConfig or a python-can bus, got {bus!r}")
        self._bus_arg = bus
        self.clock = clock
        self.n_actuators = n_actuators
        self.joints = joints
        self.limits = DeviceLimits() if limits is None else limits
        if not isinstance(self.limits, DeviceLimits):
            raise VirtualConfigError(f"limits must be DeviceLimits, got {limits!r}")
        self.seed = int(seed)
        self.faults = FaultSchedule(EXOSUIT_FAULTS, faults)
        self.on_applied = on_applied
        self.feedback_hz = _check_number("VirtualExosuit", "feedback_hz", feedback_hz, 0.0, 10_000.0)
        self.status_period_s = _check_number("VirtualExosuit", "status_period_s", status_period_s,
                                             0.0, 10.0, lo_open=True)
        self.heartbeat_timeout_s = _check_number(
            "VirtualExosuit", "heartbeat_timeout_s", heartbeat_timeout_s, 0.0, 60.0, lo_open=True)
        self.liveness_timeout_s = _check_number(
            "VirtualExosuit", "liveness_timeout_s", liveness_timeout_s, 0.0, 600.0, lo_open=True)
        self.heartbeat_clear_s = _check_number(
            "VirtualExosuit", "heartbeat_clear_s", heartbeat_clear_s, 0.0, 60.0)
        self.malformed_rate_hz = _check_number(
            "VirtualExosuit", "malformed_rate_hz", malformed_rate_hz, 0.0, 10_000.0, lo_open=True)
        self.bus_error_hold_s = _check_number(
            "VirtualExosuit", "bus_error_hold_s", bus_error_hold_s, 0.0, 3600.0)
        self.gait_config = GaitConfig() if gait is None else gait
        self.tracking_config = TrackingConfig() if tracking is None else tracking
        gait_ss, noise_ss, fault_ss = np.random.SeedSequence(self.seed).spawn(3)
        self._gait_rng = np.random.default_rng(gait_ss)
        self._noise_rng = np.random.default_rng(noise_ss)
        self._fault_rng = np.random.default_rng(fault_ss)
        self._n_tables = len(_distinct(joints))
        self._bus_off_ends = sorted(
            e for s in self.faults.specs if s.kind == "bus-off" and (e := s.end_s) is not None
        )
        self._hw_fault_starts = sorted(
            (s.start_s, HARDWARE_FAULTS[s.kind]) for s in self.faults.specs
            if s.kind in HARDWARE_FAULTS
        )

        self._endpoint: CanEndpoint | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._tasks: list[asyncio.Task[None]] = []
        self._error: BaseException | None = None
        self._failed: asyncio.Event | None = None
        self._gait_wake: asyncio.Event | None = None
        self.gait_model: GaitModel | None = None
        self._assembler = ProfileAssembler(max_force_n=self.limits.max_force_n, max_step_n=None,
                                           max_points=self.limits.max_points)
        self._pending: AppliedTable | None = None
        self._pending_t = -math.inf
        self._active: list[AppliedTable | None] = [None] * n_actuators
        self._assist = [False] * n_actuators
        self._latched = False
        self._latch_faults = DeviceFault(0)  # FaultHeartbeatLost
        self._hw_faults = DeviceFault(0)  # FaultBusError while it lasts (clears itself)
        self._hw_latched = DeviceFault(0)  # hardware faults, until a ClearFaults after the cause
        self._hb_state: BridgeState | None = None
        self._hb_counter: int | None = None
        self._hb_liveness: int | None = None
        # The bus watchdog (Counter advancing) and the liveness watchdog (Liveness advancing).
        self._stats: collections.Counter[str] = collections.Counter()
        self._bus_watch = _Watchdog("heartbeat", self._on_heartbeat_lost, self._stats)
        self._live_watch = _Watchdog("liveness", self._on_heartbeat_lost, self._stats)
        self._can_assist_now = False
        self._arm_t = -math.inf
        self._reported: AppliedTable | None = None
        self._status_counter = [0] * n_actuators
        self._feedback_counter = [0] * n_actuators
        self._trackers: list[_Tracker] = []
        self._applied_log: list[tuple[int | None, float]] = []

    # ------------------------------------------------------------------ lifecycle

    async def __aenter__(self) -> VirtualExosuit:
        await self.open()
        return self

    async def __aexit__(self, exc_type: object, exc: object, tb: object) -> None:
        error = await self.close()
        if error is not None and exc is None:
            raise error

    async def open(self) -> None:
        """Open the bus and start the device's tasks.

        Raises:
            TransportError: the bus could not be opened.
            DriverConfigError: python-can rejects the interface or its options
                (:class:`drivers.errors.DriverConfigError`).
            VirtualConfigError: already open.
        """
        if self._endpoint is not None:
            raise VirtualConfigError("the virtual exosuit is already open")
        loop = asyncio.get_running_loop()
        self._loop = loop
        self._failed = asyncio.Event()
        self._gait_wake = asyncio.Event()
        t0 = self.clock.now()
        self.gait_model = GaitModel(self._offsets, self.gait_config, self._gait_rng, t0)
        self._trackers = [_Tracker(self.tracking_config, t0) for _ in range(self.n_actuators)]
        if isinstance(self._bus_arg, CanBusConfig):
            config = self._bus_arg

            def factory(**kwargs: Any) -> can.BusABC:
                return _TapBus(can.Bus(**kwargs), self._tap)
        else:
            given = self._bus_arg
            config = CanBusConfig(_interface_name(given), str(given.channel_info), None)

            def factory(**_: Any) -> can.BusABC:
                return _TapBus(given, self._tap)

        endpoint = CanEndpoint(config, bus_factory=factory)
        await endpoint.open()
        self._endpoint = endpoint
        subscription = endpoint.subscribe(BridgeHeartbeat, ProfileSegment, ProfileCommit,
                                          ClearFaults, maxsize=4096)
        self._start(self._receive_loop(subscription), "exosuit-rx")
        self._start(self._status_loop(), "exosuit-status")
        if self.feedback_hz > 0:
            self._start(self._feedback_loop(), "exosuit-feedback")
        self._start(self._gait_loop(), "exosuit-gait")
        self._start(self._watch_endpoint(endpoint), "exosuit-bus")
        if self._bus_off_ends:
            self._start(self._bus_error_loop(), "exosuit-bus-error")
        if self._hw_fault_starts:
            self._start(self._hardware_fault_loop(), "exosuit-hardware-faults")
        if any(s.kind in MALFORMED_FAULTS for s in self.faults.specs):
            self._start(self._malformed_loop(), "exosuit-malformed")
        log.info("virtual exosuit open on %s:%s (%d actuators, joints %s, faults %s)",
                 config.interface, config.channel, self.n_actuators, self.joints,
                 [str(s) for s in self.faults.specs])

    async def close(self) -> BaseException | None:
        """Stop every task and close the bus (idempotent).

        Returns:
            The first error a task of the device failed with, if any.
        """
        tasks, self._tasks = self._tasks, []
        for task in tasks:
            task.cancel()
        # A task that failed has its error recorded (_on_task_done -> _fail, returned below);
        # awaiting it here must not raise it before the bus is closed (it leaked the bus's
        # receive thread).
        await asyncio.gather(*tasks, return_exceptions=True)
        self._bus_watch.cancel()
        self._live_watch.cancel()
        if self._endpoint is not None:
            endpoint, self._endpoint = self._endpoint, None
            await endpoint.close()
        return self._error

    def _start(self, coro: Coroutine[Any, Any, None], name: str) -> None:
        task = asyncio.get_running_loop().create_task(coro, name=name)
        task.add_done_callback(self._on_task_done)
        self._tasks.append(task)

    def _on_task_done(self, task: asyncio.Task[None]) -> None:
        if task.cancelled():
            return
        exc = task.exception()
        if exc is not None:
            self._fail(exc)

    def _fail(self, exc: BaseException) -> None:
        if self._error is None:
            log.error("virtual exosuit failed: %r", exc)
            self._error = exc
        if self._failed is not None:
            self._failed.set()

    async def wait(self) -> None:
        """Wait until a task of the device fails, then raise its error."""
        if self._failed is None:
            raise VirtualConfigError("the virtual exosuit is not open")
        await self._failed.wait()
        if self._error is not None:
            raise self._error

    @property
    def endpoint(self) -> CanEndpoint:
        """The device's CAN endpoint (its counters show what it could not decode)."""
        if self._endpoint is None:
            raise VirtualConfigError("the virtual exosuit is not open")
        return self._endpoint

    # ------------------------------------------------------------------ observation

    @property
    def stats(self) -> Mapping[str, int]:
        """Counts of what the device did: ``commits``, ``acks``, ``nack_<reason>``,
        ``switches``, ``assistance_off``, ``assistance_off_received``, ``heartbeat_lost``,
        ``liveness_lost``, ``watchdog_deferred``, ``clear_requests``, ``cleared_<fault>``,
        ``held_<fault>``, ``hardware_fault``, ``bus_off_dropped``, ``bus_off_recovered``,
        ``status_sent``, ``feedback_sent``, ``malformed_sent`` and ``malformed_<kind>``."""
        return types.MappingProxyType(self._stats)

    @property
    def applied_log(self) -> tuple[tuple[int | None, float], ...]:
        """Every ``on_applied`` report as ``(version, or None for no assistance; t_s)``."""
        return tuple(self._applied_log)

    def active_table(self, actuator: int) -> AppliedTable | None:
        """The table ``actuator`` executes (None before its first switch)."""
        return self._active[actuator]

    @property
    def pending_table(self) -> AppliedTable | None:
        """The committed table waiting for the next gait-cycle boundary."""
        return self._pending

    def mode(self, actuator: int) -> DeviceMode:
        """The operating mode reported for ``actuator``."""
        if self._hw_faults or self._hw_latched:
            return DeviceMode.FAULT
        if self._latched:
            return DeviceMode.ASSISTANCE_OFF
        return DeviceMode.ASSIST if self._assist[actuator] else DeviceMode.TRANSPARENT

    def fault_bits(self) -> DeviceFault:
        """The fault bits reported in DeviceStatus."""
        return self._hw_faults | self._hw_latched | self._latch_faults

    def bus_off(self) -> bool:
        """Whether an injected bus-off is on now (the node neither receives nor transmits)."""
        return self.faults.active("bus-off", self.clock.now())

    # ------------------------------------------------------------------ receive

    def _tap(self, frame: can.Message) -> bool:
        """Every received frame, raw, in python-can's receive thread; False drops it."""
        if self.bus_off():
            self._stats["bus_off_dropped"] += 1
            return False
        if (frame.arbitration_id == ASSISTANCE_OFF_ID and not frame.is_extended_id
                and not frame.is_error_frame and self._loop is not None):
            # Act on the identifier whatever the payload (PROTOCOL.md); the endpoint counts a
            # malformed one as bad and never delivers it.
            self._loop.call_soon_threadsafe(self._on_assistance_off_frame)
        return True

    def _on_assistance_off_frame(self) -> None:
        try:
            self._stats["assistance_off_received"] += 1
            self._go_off("AssistanceOff")
        except Exception as err:  # surfaced through wait()/close(), not swallowed
            self._fail(err)

    async def _receive_loop(self, subscription: Subscription) -> None:
        async for message in subscription:
            if isinstance(message, BridgeHeartbeat):
                self._on_heartbeat(message)
            elif isinstance(message, ProfileSegment):
                self._assembler.on_segment(message)
            elif isinstance(message, ProfileCommit):
                await self._on_commit(message)
            elif isinstance(message, ClearFaults):
                await self._on_clear_faults(message)

    def _on_heartbeat(self, hb: BridgeHeartbeat) -> None:
        advanced = hb.counter != self._hb_counter
        live = hb.liveness != self._hb_liveness
        self._hb_counter, self._hb_liveness, self._hb_state = hb.counter, hb.liveness, hb.state
        loop = asyncio.get_running_loop()
        if advanced:
            self._bus_watch.feed(loop, self.heartbeat_timeout_s)
        if live:
            self._live_watch.feed(loop, self.liveness_timeout_s)
        stop = hb.state in (BridgeState.PAUSED, BridgeState.SHUTDOWN) or (
            hb.state != BridgeState.RUNNING and any(self._assist)
        )
        if stop and not self._latched:
            self._go_off(f"bridge state {hb.state.name.lower()}")
        self._update_arming()

    @property
    def _hb_fresh(self) -> bool:
        """Both watchdogs of the bridge heartbeat are satisfied."""
        return self._bus_watch.fresh and self._live_watch.fresh

    def _on_heartbeat_lost(self, watchdog: _Watchdog) -> None:
        """A watchdog expired: assistance off, FaultHeartbeatLost latched (either watchdog: a
        lost link and a hung bridge are the same fault class, ``policy``; faults.py)."""
        try:
            self._stats[f"{watchdog.name}_lost"] += 1
            self._latch_faults |= DeviceFault.HEARTBEAT_LOST
            self._go_off(f"bridge {watchdog.name} lost")
        except Exception as err:  # surfaced through wait()/close(), not swallowed
            self._fail(err)

    def _can_assist(self) -> bool:
        return (not self._latched and not self.fault_bits() and self._hb_fresh
                and self._hb_state == BridgeState.RUNNING)

    def _update_arming(self) -> None:
        ok = self._can_assist()
        if ok and not self._can_assist_now:
            self._arm_t = self.clock.now()
            if self._gait_wake is not None:
                self._gait_wake.set()
        self._can_assist_now = ok

    def _go_off(self, why: str) -> None:
        """Enter the latched safe state at once (desired force zero from now on)."""
        if not self._latched:
            log.info("virtual exosuit: assistance off (%s)", why)
            self._stats["assistance_off"] += 1
        self._latched = True
        self._assist = [False] * self.n_actuators
        self._update_arming()
        self._report_applied(self.clock.now())

    def _injected_nack(self, t_s: float) -> NackReason | None:
        for name, reason in NACK_FAULTS.items():
            if self.faults.take(name, t_s):
                return reason
        return None

    async def _on_commit(self, commit: ProfileCommit) -> None:
        now = self.clock.now()
        self._stats["commits"] += 1
        self._assembler.busy = bool(self.fault_bits())  # a latched fault must be cleared first
        injected = self._injected_nack(now)
        table: tuple[float, ...] | None
        if injected is not None:
            detail = self.limits.max_points if injected == NackReason.BAD_LENGTH else 0
            ack, table = ProfileAck.nack(commit.version, injected, detail), None
        elif (commit.version != 0 and not self._assembler.busy
              and MIN_PROFILE_POINTS <= commit.n_points <= self.limits.max_points
              and commit.n_points % self._n_tables):
            # Checked before the segments so that the protocol's order of checks holds.
            ack, table = ProfileAck.nack(commit.version, NackReason.BAD_LENGTH,
                                         self.limits.max_points), None
        else:
            ack, table = self._assembler.on_commit(commit)
            if table is not None:
                bad = _first_slope_violation(forces_to_raw(table), self._n_tables,
                                             self.limits.max_slope_n_per_pct)
                if bad is not None:
                    ack, table = ProfileAck.nack(commit.version, NackReason.OUT_OF_LIMITS, bad), None
        if not self.bus_off():
            await self.endpoint.send(ack)
        if table is None:
            self._stats[f"nack_{ack.reason.name.lower()}"] += 1
            log.info("virtual exosuit: nack v%d %s (detail %d)", commit.version,
                     ack.reason.name, ack.detail)
            return
        self._stats["acks"] += 1
        raw = forces_to_raw(table)
        self._accept(AppliedTable(commit.version, raw, split_table(raw, self.joints)), now)

    def _accept(self, table: AppliedTable, now: float) -> None:
        """An acked table: to the back buffer, unless every actuator already runs exactly it."""

        def same(t: AppliedTable | None) -> bool:
            return t is not None and t.version == table.version and t.forces_raw == table.forces_raw

        if self._pending is not None and same(self._pending):
            pass  # a repeated commit of the pending table: keep it and its commit time
        elif self._pending is None and all(same(t) for t in self._active):
            pass  # a repeated commit of the active table (its ack was lost)
        else:
            self._pending, self._pending_t = table, now
        if (self._latched and self._hb_fresh and self._hb_state == BridgeState.RUNNING
                and not self.fault_bits()):
            log.info("virtual exosuit: latch cleared by the ack of v%d", table.version)
            self._latched = False
        self._update_arming()
        if self._gait_wake is not None:
            self._gait_wake.set()

    def heartbeat_back_s(self) -> float:
        """How long the bridge heartbeat has been back (advancing, no watchdog expiry), wall s;
        0 while it is lost."""
        if not self._hb_fresh or self._loop is None:
            return 0.0
        back_since = max(self._bus_watch.back_since, self._live_watch.back_since)
        return max(0.0, self._loop.time() - back_since)

    def _cause_present(self, bit: DeviceFault, t_s: float) -> bool:
        """Whether the cause of a latched fault is still there (so a request cannot clear it)."""
        if bit == DeviceFault.HEARTBEAT_LOST:
            return self.heartbeat_back_s() < self.heartbeat_clear_s
        return any(self.faults.active(name, t_s) for name, b in HARDWARE_FAULTS.items()
                   if b == bit)

    async def _on_clear_faults(self, request: ClearFaults) -> None:
        """Clear the requested latched faults whose cause is gone; answer per actuator."""
        self._stats["clear_requests"] += 1
        now = self.clock.now()
        cleared = DeviceFault(0)
        for bit in DeviceFault(request.mask):
            latched = (self._latch_faults if bit == DeviceFault.HEARTBEAT_LOST
                       else self._hw_latched)
            if bit in latched and not self._cause_present(bit, now):
                cleared |= bit
        self._latch_faults &= ~cleared
        self._hw_latched &= ~cleared
        held = self.fault_bits()
        for bit in cleared:
            self._stats[f"cleared_{FAULT_INFO[bit].name}"] += 1
        for bit in held & DeviceFault(request.mask):
            self._stats[f"held_{FAULT_INFO[bit].name}"] += 1
        log.info("virtual exosuit: clear faults %#04x: cleared %#04x, still held %#04x",
                 int(request.mask), int(cleared), int(held))
        self._update_arming()
        actuators = range(self.n_actuators) if request.actuator is None else (
            [request.actuator] if request.actuator < self.n_actuators else [])
        if self.bus_off():
            return
        for a in actuators:
            await self.endpoint.send(ClearFaultsAck(a, request.sequence, cleared, held))

    async def _watch_endpoint(self, endpoint: CanEndpoint) -> None:
        raise await endpoint.wait_failed()

    # ------------------------------------------------------------------ gait boundaries

    def _needs_boundary(self) -> bool:
        if self._pending is not None:
            return True
        return self._can_assist() and any(
            t is not None and not a for t, a in zip(self._active, self._assist, strict=True)
        )

    async def _gait_loop(self) -> None:
        wake, gait = self._gait_wake, self.gait_model
        if wake is None or gait is None:
            raise RuntimeError("gait loop started before open()")
        with self.clock.participant("virtual-exosuit gait") as me:
            t_from = self.clock.now()
            while True:
                if not self._needs_boundary():
                    wake.clear()
                    with me.idle():
                        await wake.wait()
                    t_from = max(t_from, self.clock.now())
                    continue
                # The earliest boundary of any actuator: work that appears while we sleep only
                # concerns later boundaries (it is time-stamped and checked in _on_boundary).
                t_b, actuator = min(
                    (gait.next_boundary(a, t_from), a) for a in range(self.n_actuators)
                )
                await me.sleep_until(t_b)
                t_from = t_b
                self._on_boundary(actuator, t_b)

    def _on_boundary(self, a: int, t_b: float) -> None:
        pending = self._pending
        if pending is not None and self._active[a] is not pending and self._pending_t < t_b:
            self._active[a] = pending
            self._stats["switches"] += 1
            log.debug("actuator %d switched to v%d at t=%.3f s", a, pending.version, t_b)
            if all(t is pending for t in self._active):
                self._pending = None
        if (self._can_assist() and self._active[a] is not None and not self._assist[a]
                and self._arm_t < t_b):
            self._assist[a] = True
        self._report_applied(t_b)

    def _report_applied(self, t_s: float) -> None:
        if not any(self._assist):
            key: AppliedTable | None = None
        elif all(self._assist) and all(t is self._active[0] for t in self._active):
            key = self._active[0]
        else:
            return  # mid-transition: some actuators have not switched yet
        if key is self._reported:
            return
        self._reported = key
        self._applied_log.append((None if key is None else key.version, t_s))
        if self.on_applied is not None:
            self.on_applied(() if key is None else key.profiles, t_s)

    # ------------------------------------------------------------------ transmit

    def _desired(self, a: int, t_s: float) -> tuple[float, float]:
        """Desired force (N) of actuator ``a`` at ``t_s`` and its rate of change (N/s)."""
        table = self._active[a]
        if not self._assist[a] or table is None or self.gait_model is None:
            return 0.0, 0.0
        profile = table.table_for(self.joints[a])
        phase = self.gait_model.phase_pct(a, t_s)
        g, f = profile.gait_pct, profile.force_n
        k = min(int(np.searchsorted(g, phase, side="right")) - 1, len(g) - 2)
        slope_per_pct = (f[k + 1] - f[k]) / (g[k + 1] - g[k])  # linear interpolation (PROTOCOL.md)
        value = f[k] + slope_per_pct * (phase - g[k])
        return float(value), float(slope_per_pct * 100.0 / self.gait_model.stride_at(a, t_s))

    def status(self, a: int) -> DeviceStatus:
        """The DeviceStatus of actuator ``a`` now (without advancing its counter)."""
        if self.gait_model is None:
            raise VirtualConfigError("the virtual exosuit is not open")
        pending, active = self._pending, self._active[a]
        return DeviceStatus(
            actuator=a,
            mode=self.mode(a),
            faults=self.fault_bits(),
            gait_phase_pct=self.gait_model.phase_pct(a, self.clock.now()),
            profile_version_active=0 if active is None else active.version,
            profile_version_pending=0 if pending is None or active is pending else pending.version,
            counter=self._status_counter[a],
        )

    async def _status_loop(self) -> None:
        loop = asyncio.get_running_loop()
        next_t = loop.time()
        while True:
            now = self.clock.now()
            if not (self.faults.active("drop-status", now) or self.bus_off()):
                for a in range(self.n_actuators):
                    status = self.status(a)
                    self._status_counter[a] = (self._status_counter[a] + 1) % 256
                    await self.endpoint.send(status)
                    self._stats["status_sent"] += 1
            next_t = _next_tick(loop, next_t, self.status_period_s)
            await asyncio.sleep(max(0.0, next_t - loop.time()))

    def feedback_sample(self, a: int) -> tuple[float, float, float]:
        """Advance actuator ``a``'s force model to now: ``(desired_n, measured_n, phase_pct)``.

        ``measured_n`` includes the sensor noise (one draw per call).
        """
        gait = self.gait_model
        if gait is None:
            raise VirtualConfigError("the virtual exosuit is not open")
        now = self.clock.now()
        tracker = self._trackers[a]
        desired, slope = self._desired(a, now)
        then = desired - slope * (now - tracker.t_s)  # the same ramp at the tracker's last time
        measured = tracker.advance(now, desired, then, slope)
        noisy = measured + self.tracking_config.noise_n * float(self._noise_rng.standard_normal())
        return desired, noisy, gait.phase_pct(a, now)

    async def _feedback_loop(self) -> None:
        loop = asyncio.get_running_loop()
        period = 1.0 / self.feedback_hz
        next_t = loop.time()
        while True:
            if not self.bus_off():
                for a in range(self.n_actuators):
                    desired, measured, phase = self.feedback_sample(a)
                    frame = ForceFeedback(
                        actuator=a,
                        desired_force_n=min(max(desired, 0.0), MAX_FORCE_ON_WIRE_N),
                        measured_force_n=min(max(measured, _MEASURED_RANGE_N[0]),
                                             _MEASURED_RANGE_N[1]),
                        gait_phase_pct=phase,
                        counter=self._feedback_counter[a],
                    )
                    self._feedback_counter[a] = (self._feedback_counter[a] + 1) % 256
                    await self.endpoint.send(frame)
                    self._stats["feedback_sent"] += 1
            next_t = _next_tick(loop, next_t, period)
            await asyncio.sleep(max(0.0, next_t - loop.time()))

    # ------------------------------------------------------------------ faults

    async def _bus_error_loop(self) -> None:
        """After each bus-off: FaultBusError, Mode = fault and assistance off for the hold."""
        with self.clock.participant("virtual-exosuit bus-off") as me:
            for end_s in self._bus_off_ends:
                await me.sleep_until(end_s)
                if self.bus_off():
                    continue  # another bus-off window still covers this instant
                self._stats["bus_off_recovered"] += 1
                self._hw_faults |= DeviceFault.BUS_ERROR
                self._go_off("recovered from bus-off")
                await me.sleep_until(end_s + self.bus_error_hold_s)
                self._hw_faults &= ~DeviceFault.BUS_ERROR
                self._update_arming()

    async def _hardware_fault_loop(self) -> None:
        """At the start of each hardware-fault window: latch its bit and go to assistance-off."""
        with self.clock.participant("virtual-exosuit hardware faults") as me:
            for start_s, bit in self._hw_fault_starts:
                await me.sleep_until(start_s)
                self._stats["hardware_fault"] += 1
                self._hw_latched |= bit
                self._go_off(f"hardware fault {FAULT_INFO[bit].name}")

    def _malformed_frame(self, kind: str) -> can.Message:
        """One malformed frame of a MALFORMED_FAULTS kind."""
        rng = self._fault_rng
        if kind == "wrong-dlc":
            base = ("DeviceStatus", "ForceFeedback")[int(rng.integers(2))]
            ident = frame_id(f"{base}{int(rng.integers(self.n_actuators))}")
            length = int(rng.choice([n for n in range(9) if n != 6]))  # both are 6 bytes long
            return can.Message(arbitration_id=ident, is_extended_id=False, data=rng.bytes(length))
        if kind == "unknown-id":
            known = {m.frame_id for m in database().messages}
            while True:
                ident = int(rng.integers(0x080, 0x800))
                if ident not in known:
                    return can.Message(arbitration_id=ident, is_extended_id=False,
                                       data=rng.bytes(int(rng.integers(9))))
        while True:  # garbage
            ident = int(rng.integers(0, 0x800))
            if ident not in _BRIDGE_IDS:
                return can.Message(arbitration_id=ident, is_extended_id=False,
                                   data=rng.bytes(int(rng.integers(9))))

    async def _malformed_loop(self) -> None:
        """At ``malformed_rate_hz`` (wall clock), one frame per malformed fault that is on."""
        loop = asyncio.get_running_loop()
        period = 1.0 / self.malformed_rate_hz
        next_t = loop.time()
        while True:
            now = self.clock.now()
            if not self.bus_off():
                for kind in MALFORMED_FAULTS:
                    if self.faults.take(kind, now):
                        await self.endpoint.send(self._malformed_frame(kind))
                        self._stats["malformed_sent"] += 1
                        self._stats[f"malformed_{kind}"] += 1
            next_t = _next_tick(loop, next_t, period)
            await asyncio.sleep(max(0.0, next_t - loop.time()))


def _next_tick(loop: asyncio.AbstractEventLoop, next_t: float, period: float) -> float:
    """The next tick of a periodic loop.

    Ticks missed by less than ``_MAX_LAG_S`` (asyncio wakes up to a millisecond late) are sent
    back to back, so the average rate holds; after a longer stall the loop resynchronises
    instead of bursting.
    """
    next_t += period
    if next_t < loop.time() - max(_MAX_LAG_S, period):
        next_t = loop.time()
    return next_t


# ------------------------------------------------------------------------------ listener


class AppliedProfileListener:
    """Follows, from the bus, which profile a virtual exosuit in another process applies.

    A subscriber of a :class:`~drivers.exosuit.endpoint.CanEndpoint` on the same bus as the
    bridge and the device: it reassembles every pushed table from the bridge's ProfileSegment
    frames, keeps those whose commit CRC matches and that the device acked, and watches the
    device's DeviceStatus frames. When every actuator reports Mode = assist with one version
    active, it calls ``on_applied(profiles, t_s)`` with that version's tables (split per joint as
    the device does, :func:`split_table`); when no actuator assists any more, it calls
    ``on_applied((), t_s)``. ``t_s`` is the listener's simulated clock, moved back to the gait
    boundary the device's reported gait phase implies (never before the previous status frame, so
    it errs late by at most one status period, plus however late this process handles the frame
    on a busy PC).

    The endpoint must be the listener's own node (the virtual cart's process has one): a CAN
    node does not receive the frames it sends itself, so an endpoint that also pushes the
    profiles would never see the segments. A table pushed before the listener started is not
    known; that device state is counted (``unknown_version``) and not reported.

    Use ``async with AppliedProfileListener(endpoint, clock, on_applied=...)`` (a task runs
    inside; leaving the block re-raises its error), or ``await listener.run()``.

    Args:
        endpoint: an open endpoint on the device's bus.
        clock: the simulated clock shared with the device (same speed and epoch).
        on_applied: called with ``(profiles, t_s)`` when the applied assistance changes.
        n_actuators: actuators of the device (1 or 2).
        joints: joint of each actuator, as given to the device.
        stride_s: mean stride, to turn the reported gait phase into time.
    """

    def __init__(
        self,
        endpoint: CanEndpoint,
        clock: SimClock,
        *,
        on_applied: Callable[[tuple[ForceProfile, ...], float], object],
        n_actuators: int = N_ACTUATORS,
        joints: Sequence[str] | None = None,
        stride_s: float = GaitConfig().stride_s,
    ) -> None:
        if isinstance(n_actuators, bool) or n_actuators not in range(1, N_ACTUATORS + 1):
            raise VirtualConfigError(f"n_actuators={n_actuators!r}; expected 1..{N_ACTUATORS}")
        self.joints = tuple(joints) if joints is not None else ("hip",) * n_actuators
        if len(self.joints) != n_actuators:
            raise VirtualConfigError(f"joints={self.joints!r}; expected one per actuator ({n_actuators})")
        _joint_offsets(self.joints)
        self.endpoint = endpoint
        self.clock = clock
        self.on_applied = on_applied
        self.n_actuators = n_actuators
        self.stride_s = _check_number("AppliedProfileListener", "stride_s", stride_s, 0.2, 5.0)
        # One receive buffer, like the device's: a segment of another version starts it over.
        self._receiving: int | None = None
        self._segments: dict[int, tuple[float, float, float]] = {}
        self._candidates: dict[int, AppliedTable] = {}
        self._accepted: dict[int, AppliedTable] = {}
        self._status: list[DeviceStatus | None] = [None] * n_actuators
        self._status_t: list[float] = [-math.inf] * n_actuators
        self._applied: int | None = None
        self._unknown: set[int] = set()
        self._last_t = -math.inf
        self._task: asyncio.Task[None] | None = None
        self.counters: collections.Counter[str] = collections.Counter()
        #: Every report as ``(version or None, t_s)``.
        self.reports: list[tuple[int | None, float]] = []

    async def __aenter__(self) -> AppliedProfileListener:
        self._task = asyncio.get_running_loop().create_task(self.run(), name="applied-listener")
        return self

    async def __aexit__(self, exc_type: object, exc: object, tb: object) -> None:
        task, self._task = self._task, None
        if task is None:
            return
        if task.done():
            if exc is None:
                task.result()  # re-raise the listener's error
            return
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task

    async def run(self) -> None:
        """Follow the bus until cancelled (raises TransportError if the bus fails)."""
        with self.endpoint.subscribe(ProfileSegment, ProfileCommit, ProfileAck, DeviceStatus,
                                     maxsize=4096) as sub:
            async for message in sub:
                self.handle(message)

    def handle(self, message: object) -> None:
        """Process one decoded message (exposed so a caller with its own receive loop can feed
        the listener)."""
        if isinstance(message, ProfileSegment):
            if message.version != self._receiving:
                self._receiving, self._segments = message.version, {}
            self._segments[message.index] = message.forces_n
        elif isinstance(message, ProfileCommit):
            self._on_commit(message)
        elif isinstance(message, ProfileAck):
            if message.accepted and message.version in self._candidates:
                self._accepted[message.version] = self._candidates[message.version]
                while len(self._accepted) > _LISTENER_KEEP:
                    del self._accepted[next(iter(self._accepted))]
            elif message.accepted:
                self.counters["ack_without_table"] += 1
        elif isinstance(message, DeviceStatus) and message.actuator < self.n_actuators:
            self._on_status(message)

    def _on_commit(self, commit: ProfileCommit) -> None:
        parts = self._segments if commit.version == self._receiving else {}
        needed = segment_count(commit.n_points)
        if any(i not in parts for i in range(needed)):
            self.counters["incomplete_transfer"] += 1
            return
        try:
            raw = forces_to_raw([f for i in range(needed) for f in parts[i]])[:commit.n_points]
            if profile_crc32(raw) != commit.crc32:
                self.counters["bad_crc"] += 1
                return
            profiles = split_table(raw, self.joints)
        except (VirtualHwError, ValueError) as err:
            self.counters["unusable_table"] += 1
            log.warning("listener: table v%d unusable: %s", commit.version, err)
            return
        self._candidates[commit.version] = AppliedTable(commit.version, raw, profiles)
        while len(self._candidates) > _LISTENER_KEEP:
            del self._candidates[next(iter(self._candidates))]

    def _on_status(self, status: DeviceStatus) -> None:
        now = self.clock.now()
        a = status.actuator
        previous_t = self._status_t[a]
        self._status[a] = status
        self._status_t[a] = now
        if any(s is None for s in self._status):
            return
        states = [s for s in self._status if s is not None]
        assisting = [s.mode == DeviceMode.ASSIST for s in states]
        if not any(assisting):
            version: int | None = None
            t_s = now
        elif all(assisting) and len({s.profile_version_active for s in states}) == 1:
            version = states[0].profile_version_active
            # The switch happened at this actuator's last boundary, phase·stride ago, but not
            # before its previous status frame (which did not show it yet).
            back = (status.gait_phase_pct or 0.0) / 100.0 * self.stride_s
            t_s = max(now - back, previous_t)
        else:
            return
        if version == self._applied:
            return
        t_s = max(t_s, self._last_t)
        if version is None:
            profiles: tuple[ForceProfile, ...] = ()
        elif version in self._accepted:
            profiles = self._accepted[version].profiles
        else:
            if version not in self._unknown:  # once per version, not every 20 ms
                self._unknown.add(version)
                self.counters["unknown_version"] += 1
                log.warning("listener: device applies v%d, whose table was not seen on the bus",
                            version)
            return
        self._applied = version
        self._last_t = t_s
        self.reports.append((version, t_s))
        self.on_applied(profiles, t_s)


class _ProfileSink(Protocol):
    """What :func:`applied_profile_feed` needs of a virtual cart."""

    clock: SimClock

    def on_profile_applied(self, profiles: Sequence[ForceProfile], t_sim: float | None = None) -> object:
        """The exosuit applies ``profiles`` from ``t_sim`` on."""
        ...


def applied_profile_feed(
    config: CanBusConfig,
    *,
    joints: Sequence[str] = SUIT_JOINTS["hip_6d"],
    stride_s: float = GaitConfig().stride_s,
) -> Callable[[_ProfileSink], Coroutine[Any, Any, None]]:
    """A virtual cart's profile feed from a virtual exosuit in another process.

    The returned coroutine function opens its own endpoint on ``config`` and runs an
    :class:`AppliedProfileListener` that calls ``cart.on_profile_applied(profiles, t)`` on the
    cart's clock, until cancelled (``virtual_hw.cli_cart.ProfileFeed``).

    Args:
        config: the bus the bridge and the exosuit share.
        joints: the exosuit's joints per actuator (:data:`SUIT_JOINTS` of the preset).
        stride_s: mean stride of the exosuit's gait, to date switches from its gait phase.
    """
    joints = tuple(joints)

    async def feed(cart: _ProfileSink) -> None:
        async with CanEndpoint(config) as endpoint:
            listener = AppliedProfileListener(endpoint, cart.clock, on_applied=cart.on_profile_applied,
                                              n_actuators=len(joints), joints=joints,
                                              stride_s=stride_s)
            await listener.run()

    return feed
