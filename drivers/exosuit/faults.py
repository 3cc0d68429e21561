"""The exosuit's fault bits: names, meaning, what clears each, and who may resume after it
(PROTOCOL.md, "Faults" and "Who resumes after a fault").

DeviceStatus carries eight fault bits (:class:`~drivers.exosuit.codec.DeviceFault`). Every fault
is *latched*: it stays set after its cause is gone, so a transient fault is never missed, until
the bridge clears it with a ClearFaults request — which the device honours only once the cause is
gone — except FaultBusError, which the node clears itself once it is error-active again. This
module turns a bitmask into the words an operator needs: ``describe_faults(0x10)`` is
``("heartbeat_lost (cleared by the bridge once the bridge heartbeat is back for 100 ms)",)``
rather than ``faults [16, 16]``.

Each bit also has a :class:`FaultRecovery` class, the one table the bridge enforces: a fault of
class ``PERSON`` (the emergency stop first of all) keeps assistance off until a person at the PC
resumes after its cause is gone, and the bridge never sends a ClearFaults for it on its own.
Releasing an emergency stop must not restart the machine (ISO 13850 and IEC 60204-1 on
resetting an emergency stop): only a separate, deliberate action of a person may.
"""

from __future__ import annotations

import enum
import types
from collections.abc import Mapping
from dataclasses import dataclass

from drivers.exosuit.codec import DeviceFault

__all__ = [
    "CLEARABLE_FAULTS",
    "FAULT_INFO",
    "HEARTBEAT_CLEAR_S",
    "PERSON_FAULTS",
    "POLICY_CLEARABLE_FAULTS",
    "FaultInfo",
    "FaultRecovery",
    "describe_faults",
    "fault_names",
    "faults_text",
    "recovery_of",
]

#: How long the bridge heartbeat must have been back (its counter and its liveness advancing, no
#: watchdog expiry) before a device clears FaultHeartbeatLost on request: one watchdog period
#: (5 heartbeats of 20 ms), so a bridge that is still stalling every few hundred ms cannot clear
#: it between two stalls.
HEARTBEAT_CLEAR_S = 0.100


class FaultRecovery(enum.Enum):
    """Who may end the pause that a fault caused (PROTOCOL.md, "Who resumes after a fault").

    Ordered from the least to the most strict: a pause with several causes takes the strictest.
    """

    #: A transient condition of the link or the drive that the device itself judges gone (the
    #: heartbeat back for 100 ms, the motor cooled): the resume policy of a headless run may
    #: clear it and resume.
    POLICY = "policy"
    #: A person at the PC must resume (``r``) after its cause is gone: the emergency stop (a
    #: person pressed it), a force above the hardware limit or a tripped motor current (the
    #: wearer or the suit may need looking at), a sensor that failed (the controller cannot
    #: track a profile without it). The bridge never clears it unless that person asks.
    PERSON = "person"
    #: The session cannot go on (the bridge's own CAN bus failed, the resume budget is spent):
    #: assistance off and the session ends; ``hilbo run --resume`` continues it.
    END = "end"

    @property
    def rank(self) -> int:
        """0 (policy) < 1 (person) < 2 (end): the strictest cause of a pause decides."""
        return _RANK[self]


_RANK = {FaultRecovery.POLICY: 0, FaultRecovery.PERSON: 1, FaultRecovery.END: 2}


@dataclass(frozen=True)
class FaultInfo:
    """One fault bit.

    Attributes:
        fault: the bit.
        name: its name in logs and on screen (the DBC signal without ``Fault``, snake case).
        meaning: what the device detected.
        clears: what clears it, in words for the operator.
        recovery: who may resume after it (:class:`FaultRecovery`).
        by_request: whether a ClearFaults request clears it (once the cause is gone).
    """

    fault: DeviceFault
    name: str
    meaning: str
    clears: str
    recovery: FaultRecovery
    by_request: bool = True


FAULT_INFO: Mapping[DeviceFault, FaultInfo] = types.MappingProxyType({
    info.fault: info for info in (
        FaultInfo(DeviceFault.OVERCURRENT, "overcurrent", "motor current limit tripped",
                  "cleared by the bridge once the motor current is back under its limit",
                  FaultRecovery.PERSON),
        FaultInfo(DeviceFault.OVERTEMPERATURE, "overtemperature", "motor or driver too hot",
                  "cleared by the bridge once motor and driver have cooled below their limit",
                  FaultRecovery.POLICY),
        FaultInfo(DeviceFault.FORCE_SENSOR, "force_sensor", "load cell implausible or missing",
                  "cleared by the bridge once the load cell reads plausibly again",
                  FaultRecovery.PERSON),
        FaultInfo(DeviceFault.ENCODER, "encoder", "motor encoder or gait sensor (IMU) error",
                  "cleared by the bridge once the encoder and the gait sensor work again",
                  FaultRecovery.PERSON),
        FaultInfo(DeviceFault.HEARTBEAT_LOST, "heartbeat_lost",
                  "the bridge heartbeat was lost for 100 ms, or its liveness counter stood "
                  "still for 1 s (a hung bridge)",
                  "cleared by the bridge once the bridge heartbeat is back for "
                  f"{HEARTBEAT_CLEAR_S * 1e3:.0f} ms", FaultRecovery.POLICY),
        FaultInfo(DeviceFault.FORCE_LIMIT, "force_limit",
                  "measured force above the hardware force limit",
                  "cleared by the bridge once the measured force is back under the limit",
                  FaultRecovery.PERSON),
        FaultInfo(DeviceFault.BUS_ERROR, "bus_error", "the node was error passive or bus-off",
                  "clears itself once the node is error-active again (not by the bridge)",
                  FaultRecovery.POLICY, by_request=False),
        FaultInfo(DeviceFault.EMERGENCY_STOP, "emergency_stop",
                  "the hardware emergency stop is pressed",
                  "cleared by the bridge, when the operator resumes, once the emergency stop is "
                  "released", FaultRecovery.PERSON),
    )
})

#: The faults a ClearFaults request can clear (once their cause is gone): all but FaultBusError.
#: The bridge asks for these only when a person at the PC resumes.
CLEARABLE_FAULTS = DeviceFault(sum(int(f) for f, i in FAULT_INFO.items() if i.by_request))
#: The faults the bridge may clear by itself (before a push, by the resume policy).
POLICY_CLEARABLE_FAULTS = DeviceFault(sum(
    int(f) for f, i in FAULT_INFO.items() if i.by_request and i.recovery is FaultRecovery.POLICY))
#: The faults after which only a person at the PC may resume.
PERSON_FAULTS = DeviceFault(sum(
    int(f) for f, i in FAULT_INFO.items() if i.recovery is FaultRecovery.PERSON))


def recovery_of(faults: DeviceFault | int) -> FaultRecovery | None:
    """The strictest recovery class among the set bits (None when no bit is set).

    A bit the protocol does not define counts as ``PERSON``: nobody knows what it means, so
    nothing may clear it by itself.

    Raises:
        ValueError: ``faults`` is negative or not an integer.
    """
    bits = _bits(faults)
    worst: FaultRecovery | None = None
    for k in range(bits.bit_length()):
        if bits >> k & 1:
            info = FAULT_INFO.get(DeviceFault(1 << k)) if k < 8 else None
            rec = info.recovery if info is not None else FaultRecovery.PERSON
            if worst is None or rec.rank > worst.rank:
                worst = rec
    return worst


def _bits(faults: DeviceFault | int) -> int:
    if isinstance(faults, bool) or not isinstance(faults, int) or faults < 0:
        raise ValueError(f"faults = {faults!r}; expected a DeviceFault or a non-negative int")
    return int(faults)


def fault_names(faults: DeviceFault | int) -> tuple[str, ...]:
    """The names of the set bits, lowest bit first (``0x30`` → ``("heartbeat_lost",
    "force_limit")``); a bit the protocol does not define is named ``bit<k>``.

    Raises:
        ValueError: ``faults`` is negative or not an integer.
    """
    bits = _bits(faults)
    out = []
    for k in range(bits.bit_length()):
        if bits >> k & 1:
            info = FAULT_INFO.get(DeviceFault(1 << k)) if k < 8 else None
            out.append(info.name if info is not None else f"bit{k}")
    return tuple(out)


def describe_faults(faults: DeviceFault | int) -> tuple[str, ...]:
    """Each set bit as ``"name (what clears it)"``, lowest bit first.

    Raises:
        ValueError: ``faults`` is negative or not an integer.
    """
    bits = _bits(faults)
    out = []
    for k in range(bits.bit_length()):
        if bits >> k & 1:
            info = FAULT_INFO.get(DeviceFault(1 << k)) if k < 8 else None
            out.append(f"{info.name} ({info.clears})" if info is not None
                       else f"bit{k} (not defined by the protocol)")
    return tuple(out)


def faults_text(faults: DeviceFault | int) -> str:
    """One line for the operator: ``"none"`` or the :func:`describe_faults` items joined."""
    described = describe_faults(faults)
    return "; ".join(described) if described else "none"
