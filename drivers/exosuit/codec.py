"""Codecs of the exosuit CAN messages: frozen dataclasses encoded and decoded by cantools.

The message set is defined once, in ``hilbo_exosuit.dbc`` next to this module (identifiers,
layouts, scaling, ranges, enumerations, comments). Every dataclass here maps one-to-one to a DBC
message and goes through :mod:`cantools` in both directions, so the wire format cannot drift from
the DBC that engineers load into ``cantools monitor`` or any other CAN tool.

Decoding is strict: a frame with an unknown identifier, the wrong length, an extended/remote/
error/FD frame, a value outside the DBC range or an enumeration value the DBC does not name raises
:class:`~drivers.errors.DecodeError` with a short ``reason`` (one of :data:`DECODE_REASONS`), which
the endpoint counts. Encoding is strict too: a value outside the DBC range, NaN or an unknown
actuator raises :class:`EncodeError`.

Sequences, timing and the device's obligations: ``drivers/PROTOCOL.md``.
"""

from __future__ import annotations

import enum
import functools
import importlib.resources
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any, ClassVar, TypeAlias

import can
import cantools
from cantools.database.can import Database
from cantools.database.can import Message as DbcMessage
from cantools.database.namedsignalvalue import NamedSignalValue

from drivers.errors import DecodeError, DriverError

__all__ = [
    "ASSISTANCE_OFF_ID",
    "DBC_FILENAME",
    "DECODE_REASONS",
    "HEARTBEAT_SEQUENCE_LEN",
    "N_ACTUATORS",
    "AssistanceOff",
    "AssistanceOffReason",
    "BridgeHeartbeat",
    "BridgeState",
    "ClearFaults",
    "ClearFaultsAck",
    "DeviceFault",
    "DeviceMode",
    "DeviceStatus",
    "EncodeError",
    "ExosuitMessage",
    "ForceFeedback",
    "NackReason",
    "ProfileAck",
    "ProfileCommit",
    "ProfileSegment",
    "database",
    "decode_frame",
    "frame_id",
    "heartbeat_sequence",
]

DBC_FILENAME = "hilbo_exosuit.dbc"

#: Number of actuators the message set addresses (one identifier per actuator and message).
N_ACTUATORS = 2

#: Identifier of AssistanceOff. A device must act on this identifier whatever the payload.
ASSISTANCE_OFF_ID = 0x010

#: Every ``DecodeError.reason`` that :func:`decode_frame` raises.
DECODE_REASONS = (
    "unknown_id",
    "extended_id",
    "remote_frame",
    "error_frame",
    "fd_frame",
    "bad_length",
    "bad_value",
)


class EncodeError(DriverError, ValueError):
    """A value cannot be put on the wire (out of the DBC range, NaN, unknown actuator...)."""


@functools.cache
def database() -> Database:
    """The exosuit message set, loaded (once) from the DBC file shipped in this package.

    Returns:
        The cantools CAN database (strict: overlapping signals would fail to load).
    """
    text = importlib.resources.files(__package__).joinpath(DBC_FILENAME).read_text("utf-8")
    db = cantools.database.load_string(text, database_format="dbc", strict=True)
    if not isinstance(db, Database):  # load_string may also return a diagnostics database
        raise TypeError(f"{DBC_FILENAME} did not load as a CAN database")
    return db


def frame_id(message_name: str) -> int:
    """CAN identifier of a DBC message, e.g. ``frame_id("ProfileAck") == 0x7A0``."""
    return database().get_message_by_name(message_name).frame_id


# --- enumerations (names equal the DBC value tables, upper-cased; a test checks it) -------------


class BridgeState(enum.IntEnum):
    """BridgeHeartbeat.State: the device may assist only while the bridge is RUNNING."""

    IDLE = 0
    RUNNING = 1
    PAUSED = 2
    SHUTDOWN = 3


class DeviceMode(enum.IntEnum):
    """DeviceStatus.Mode."""

    OFF = 0
    ASSIST = 1
    TRANSPARENT = 2
    ASSISTANCE_OFF = 3
    FAULT = 4


class DeviceFault(enum.IntFlag):
    """DeviceStatus fault bits (one 1-bit DBC signal each, bits 8..15 of the frame)."""

    OVERCURRENT = 1 << 0
    OVERTEMPERATURE = 1 << 1
    FORCE_SENSOR = 1 << 2
    ENCODER = 1 << 3
    HEARTBEAT_LOST = 1 << 4
    FORCE_LIMIT = 1 << 5
    BUS_ERROR = 1 << 6
    EMERGENCY_STOP = 1 << 7


_FAULT_SIGNALS: Mapping[DeviceFault, str] = {
    DeviceFault.OVERCURRENT: "FaultOvercurrent",
    DeviceFault.OVERTEMPERATURE: "FaultOvertemperature",
    DeviceFault.FORCE_SENSOR: "FaultForceSensor",
    DeviceFault.ENCODER: "FaultEncoder",
    DeviceFault.HEARTBEAT_LOST: "FaultHeartbeatLost",
    DeviceFault.FORCE_LIMIT: "FaultForceLimit",
    DeviceFault.BUS_ERROR: "FaultBusError",
    DeviceFault.EMERGENCY_STOP: "FaultEmergencyStop",
}


class NackReason(enum.IntEnum):
    """ProfileAck.Reason; NONE exactly when the commit was acked."""

    NONE = 0
    BAD_CRC = 1
    BAD_LENGTH = 2
    OUT_OF_LIMITS = 3
    MISSING_SEGMENT = 4
    BUSY = 5
    BAD_VERSION = 6


class AssistanceOffReason(enum.IntEnum):
    """AssistanceOff.Reason (logged by the device; the action is the same for all)."""

    OPERATOR_STOP = 1
    DEVICE_HEARTBEAT_LOST = 2
    BUS_ERROR = 3
    LIMIT_VIOLATION = 4
    SESSION_END = 5
    INTERNAL_ERROR = 6


# --- shared encode/decode through cantools ------------------------------------------------------

_Value: TypeAlias = "int | float | NamedSignalValue"


def _message(name: str) -> DbcMessage:
    try:
        return database().get_message_by_name(name)
    except KeyError as err:
        raise EncodeError(f"no message {name!r} in {DBC_FILENAME}") from err


def _encode(name: str, values: Mapping[str, Any]) -> can.Message:
    """Encode physical values (enums as ints, sentinels as DBC choice names) into a frame."""
    message = _message(name)
    for signal, value in values.items():
        if isinstance(value, float) and not math.isfinite(value):
            raise EncodeError(f"{name}.{signal} must be finite, got {value!r}")
    try:
        data = message.encode(dict(values), scaling=True, strict=True)
    except (cantools.database.EncodeError, KeyError, TypeError, ValueError) as err:
        raise EncodeError(f"cannot encode {name} {dict(values)!r}: {err}") from err
    return can.Message(arbitration_id=message.frame_id, data=data, is_extended_id=False)


def _decode(message: DbcMessage, frame: can.Message) -> dict[str, _Value]:
    """Decode and range-check one frame whose identifier is known to map to ``message``.

    Returns physical values, except that a raw value named in the DBC value table comes back as
    the cantools ``NamedSignalValue`` (enumerations and sentinels such as GaitPhase 255).
    """
    data = bytes(frame.data)
    if len(data) != message.length:
        raise DecodeError(
            "bad_length",
            f"{message.name} (0x{message.frame_id:03X}) needs {message.length} bytes, "
            f"got {len(data)}",
        )
    raw = message.decode(data, decode_choices=False, scaling=False, allow_truncated=False)
    out: dict[str, _Value] = {}
    for signal in message.signals:
        value = int(raw[signal.name])
        choices = signal.choices or {}
        if value in choices:
            choice = choices[value]
            out[signal.name] = (
                choice if isinstance(choice, NamedSignalValue) else NamedSignalValue(value, choice)
            )
            continue
        scaled = signal.conversion.raw_to_scaled(value, decode_choices=False)
        lo, hi = signal.minimum, signal.maximum
        # raw·scale is inexact in binary (32767 × 0.1 = 3276.7000000000003): allow what cantools'
        # own encoder allows, a millionth of one step.
        tol = abs(signal.scale) * 1e-6
        if (lo is not None and scaled < lo - tol) or (hi is not None and scaled > hi + tol):
            raise DecodeError(
                "bad_value",
                f"{message.name}.{signal.name} = {scaled} (raw {value}) outside [{lo}, {hi}]",
            )
        out[signal.name] = scaled
    return out


def _enum(kind: type[enum.IntEnum], value: _Value, where: str) -> Any:
    try:
        return kind(int(value.value if isinstance(value, NamedSignalValue) else value))
    except ValueError as err:
        raise DecodeError("bad_value", f"{where} = {value!r} is not a {kind.__name__}") from err


def _gait_phase(value: _Value) -> float | None:
    # GaitPhase 255 is the DBC's "unknown" sentinel (not walking, no gait event yet).
    return None if isinstance(value, NamedSignalValue) else float(value)


def _actuator_name(base: str, actuator: int) -> str:
    if not isinstance(actuator, int) or not 0 <= actuator < N_ACTUATORS:
        raise EncodeError(f"{base}: actuator must be 0..{N_ACTUATORS - 1}, got {actuator!r}")
    return f"{base}{actuator}"


# --- messages -------------------------------------------------------------------------------------


@dataclass(frozen=True)
class AssistanceOff:
    """Safe-state command (bridge → device), identifier 0x010: wins arbitration over everything.

    Attributes:
        reason: why the bridge commanded the safe state.
    """

    reason: AssistanceOffReason
    MESSAGE: ClassVar[str] = "AssistanceOff"

    def to_frame(self) -> can.Message:
        """Encode as a CAN frame."""
        return _encode(self.MESSAGE, {"Reason": int(self.reason)})

    @classmethod
    def from_frame(cls, frame: can.Message) -> AssistanceOff:
        """Decode a frame (raises DecodeError)."""
        v = _decode(_message(cls.MESSAGE), frame)
        return cls(_enum(AssistanceOffReason, v["Reason"], "AssistanceOff.Reason"))


@dataclass(frozen=True)
class BridgeHeartbeat:
    """Bridge heartbeat (bridge → device), every 20 ms, from a cyclic sender (PROTOCOL.md,
    "Heartbeats and their timeouts").

    Attributes:
        counter: 0..255, incremented by one per frame (mod 256) by the cyclic sender itself,
            which cycles through the :func:`heartbeat_sequence` of 256 frames.
        state: the bridge session state.
        liveness: 0..255, the application liveness counter: the bridge's event loop advances it
            (every 200 ms) and hands the cyclic sender new frames; the device's slower liveness
            watchdog (1 s) sees a hung bridge whose cyclic sender still runs.
    """

    counter: int
    state: BridgeState
    liveness: int = 0
    MESSAGE: ClassVar[str] = "BridgeHeartbeat"

    def to_frame(self) -> can.Message:
        """Encode as a CAN frame."""
        return _encode(self.MESSAGE, {"Counter": self.counter, "State": int(self.state),
                                      "Liveness": self.liveness})

    @classmethod
    def from_frame(cls, frame: can.Message) -> BridgeHeartbeat:
        """Decode a frame (raises DecodeError)."""
        v = _decode(_message(cls.MESSAGE), frame)
        return cls(int(v["Counter"]), _enum(BridgeState, v["State"], "BridgeHeartbeat.State"),
                   int(v["Liveness"]))


#: Frames in one cycle of the heartbeat's cyclic sender: one per Counter value, so the counter
#: advances by one on every frame without user space (256 is also the kernel broadcast
#: manager's largest sequence, MAX_NFRAMES).
HEARTBEAT_SEQUENCE_LEN = 256


def heartbeat_sequence(state: BridgeState, liveness: int) -> tuple[can.Message, ...]:
    """The frames a cyclic sender cycles through: Counter 0..255 with this state and liveness.

    Args:
        state: the bridge state to announce.
        liveness: the application liveness counter, 0..255.

    Returns:
        :data:`HEARTBEAT_SEQUENCE_LEN` frames, Counter = index.

    Raises:
        EncodeError: ``liveness`` outside 0..255 or ``state`` not a BridgeState.
    """
    first = BridgeHeartbeat(0, BridgeState(state), liveness).to_frame()
    # 256 cantools encodes take ~4 ms of the event loop at every liveness update; Counter is a
    # whole byte (checked against the DBC here), so the other frames differ from the first in
    # that byte alone.
    counter = _message(BridgeHeartbeat.MESSAGE).get_signal_by_name("Counter")
    if counter.start % 8 or counter.length != 8 or counter.byte_order != "little_endian":
        raise EncodeError("BridgeHeartbeat.Counter is not a whole byte in the DBC")
    at, data = counter.start // 8, bytearray(first.data)
    frames = []
    for k in range(HEARTBEAT_SEQUENCE_LEN):
        data[at] = k
        frames.append(can.Message(arbitration_id=first.arbitration_id, data=bytes(data),
                                  is_extended_id=False))
    return tuple(frames)


@dataclass(frozen=True)
class ForceFeedback:
    """Desired vs measured force of one actuator at the controller's rate (1 kHz).

    Attributes:
        actuator: 0 or 1 (identifier 0x110 + actuator).
        desired_force_n: desired force of the active profile, 0..6553.5 N, 0.1 N resolution.
        measured_force_n: measured cable force, -3276.8..3276.7 N, 0.1 N resolution.
        gait_phase_pct: gait phase in % of the gait cycle (0.5 % resolution), None if unknown.
        counter: 0..255, incremented per frame.
    """

    actuator: int
    desired_force_n: float
    measured_force_n: float
    gait_phase_pct: float | None
    counter: int
    BASE: ClassVar[str] = "ForceFeedback"

    def to_frame(self) -> can.Message:
        """Encode as a CAN frame."""
        return _encode(
            _actuator_name(self.BASE, self.actuator),
            {
                "DesiredForce": self.desired_force_n,
                "MeasuredForce": self.measured_force_n,
                "GaitPhase": "unknown" if self.gait_phase_pct is None else self.gait_phase_pct,
                "Counter": self.counter,
            },
        )

    @classmethod
    def from_frame(cls, frame: can.Message) -> ForceFeedback:
        """Decode a frame (raises DecodeError)."""
        actuator = frame.arbitration_id - frame_id("ForceFeedback0")
        v = _decode(_message(_actuator_name(cls.BASE, actuator)), frame)
        return cls(
            actuator=actuator,
            desired_force_n=float(v["DesiredForce"]),
            measured_force_n=float(v["MeasuredForce"]),
            gait_phase_pct=_gait_phase(v["GaitPhase"]),
            counter=int(v["Counter"]),
        )


@dataclass(frozen=True)
class DeviceStatus:
    """Status and device heartbeat of one actuator, every 20 ms.

    Attributes:
        actuator: 0 or 1 (identifier 0x120 + actuator).
        mode: operating mode.
        faults: active fault bits.
        gait_phase_pct: gait phase in % of the gait cycle (0.5 % resolution), None if unknown.
        profile_version_active: version of the table being executed, 0 = none.
        profile_version_pending: version waiting for the next gait-cycle boundary, 0 = none.
        counter: 0..255, incremented per frame.
    """

    actuator: int
    mode: DeviceMode
    faults: DeviceFault
    gait_phase_pct: float | None
    profile_version_active: int
    profile_version_pending: int
    counter: int
    BASE: ClassVar[str] = "DeviceStatus"

    def to_frame(self) -> can.Message:
        """Encode as a CAN frame."""
        values: dict[str, Any] = {
            "Mode": int(self.mode),
            "GaitPhase": "unknown" if self.gait_phase_pct is None else self.gait_phase_pct,
            "ProfileVersionActive": self.profile_version_active,
            "ProfileVersionPending": self.profile_version_pending,
            "Counter": self.counter,
        }
        if int(self.faults) & ~0xFF:
            raise EncodeError(f"DeviceStatus.faults = {int(self.faults):#x}; only bits 0..7 exist")
        faults = DeviceFault(self.faults)
        for bit, signal in _FAULT_SIGNALS.items():
            values[signal] = int(bit in faults)
        return _encode(_actuator_name(self.BASE, self.actuator), values)

    @classmethod
    def from_frame(cls, frame: can.Message) -> DeviceStatus:
        """Decode a frame (raises DecodeError)."""
        actuator = frame.arbitration_id - frame_id("DeviceStatus0")
        v = _decode(_message(_actuator_name(cls.BASE, actuator)), frame)
        faults = DeviceFault(0)
        for bit, signal in _FAULT_SIGNALS.items():
            if int(v[signal]):
                faults |= bit
        return cls(
            actuator=actuator,
            mode=_enum(DeviceMode, v["Mode"], "DeviceStatus.Mode"),
            faults=faults,
            gait_phase_pct=_gait_phase(v["GaitPhase"]),
            profile_version_active=int(v["ProfileVersionActive"]),
            profile_version_pending=int(v["ProfileVersionPending"]),
            counter=int(v["Counter"]),
        )


@dataclass(frozen=True)
class ProfileSegment:
    """Three consecutive points of a force-profile table (bridge → device).

    Attributes:
        version: profile version 1..255.
        index: segment number 0..255; carries points 3·index .. 3·index+2.
        forces_n: the three forces in newtons (0..6553.5 N, 0.1 N resolution); points past the
            end of the table are padding (0.0).
    """

    version: int
    index: int
    forces_n: tuple[float, float, float]
    MESSAGE: ClassVar[str] = "ProfileSegment"

    def to_frame(self) -> can.Message:
        """Encode as a CAN frame."""
        if len(self.forces_n) != 3:
            raise EncodeError(f"ProfileSegment needs 3 forces, got {len(self.forces_n)}")
        f0, f1, f2 = self.forces_n
        return _encode(
            self.MESSAGE,
            {"Version": self.version, "Index": self.index, "Force0": f0, "Force1": f1,
             "Force2": f2},
        )

    @classmethod
    def from_frame(cls, frame: can.Message) -> ProfileSegment:
        """Decode a frame (raises DecodeError)."""
        v = _decode(_message(cls.MESSAGE), frame)
        return cls(
            version=int(v["Version"]),
            index=int(v["Index"]),
            forces_n=(float(v["Force0"]), float(v["Force1"]), float(v["Force2"])),
        )


@dataclass(frozen=True)
class ProfileCommit:
    """End of a profile transfer (bridge → device): length and CRC-32 of the table.

    Attributes:
        version: profile version 1..255.
        n_points: number of points in the table, 2..768.
        crc32: zlib.crc32 of the raw points, 2 bytes little-endian each (see profile.py).
    """

    version: int
    n_points: int
    crc32: int
    MESSAGE: ClassVar[str] = "ProfileCommit"

    def to_frame(self) -> can.Message:
        """Encode as a CAN frame."""
        return _encode(
            self.MESSAGE,
            {"Version": self.version, "NumPoints": self.n_points, "Crc32": self.crc32},
        )

    @classmethod
    def from_frame(cls, frame: can.Message) -> ProfileCommit:
        """Decode a frame (raises DecodeError)."""
        v = _decode(_message(cls.MESSAGE), frame)
        return cls(int(v["Version"]), int(v["NumPoints"]), int(v["Crc32"]))


@dataclass(frozen=True)
class ProfileAck:
    """The device's answer to a commit (device → bridge).

    Attributes:
        version: version of the commit being answered.
        accepted: True for ack (then ``reason`` is NONE), False for nack.
        reason: why the commit was refused.
        detail: reason-specific detail (first missing segment, first offending point, the
            device's maximum number of points), 0 otherwise.
    """

    version: int
    accepted: bool
    reason: NackReason = NackReason.NONE
    detail: int = 0
    MESSAGE: ClassVar[str] = "ProfileAck"

    def __post_init__(self) -> None:
        if self.accepted != (self.reason == NackReason.NONE):
            raise EncodeError(
                f"ProfileAck: reason must be NONE exactly when accepted; got "
                f"accepted={self.accepted}, reason={NackReason(self.reason).name}"
            )

    @classmethod
    def ack(cls, version: int) -> ProfileAck:
        """An ack of ``version``."""
        return cls(version, True)

    @classmethod
    def nack(cls, version: int, reason: NackReason, detail: int = 0) -> ProfileAck:
        """A nack of ``version`` with a reason (not NONE) and an optional detail."""
        return cls(version, False, reason, detail)

    def to_frame(self) -> can.Message:
        """Encode as a CAN frame."""
        return _encode(
            self.MESSAGE,
            {"Version": self.version, "Result": 0 if self.accepted else 1,
             "Reason": int(self.reason), "Detail": self.detail},
        )

    @classmethod
    def from_frame(cls, frame: can.Message) -> ProfileAck:
        """Decode a frame (raises DecodeError; also for an ack with a reason, a nack without)."""
        v = _decode(_message(cls.MESSAGE), frame)
        accepted = _enum(_AckResult, v["Result"], "ProfileAck.Result") == _AckResult.ACK
        reason = _enum(NackReason, v["Reason"], "ProfileAck.Reason")
        try:
            return cls(int(v["Version"]), accepted, reason, int(v["Detail"]))
        except EncodeError as err:
            raise DecodeError("bad_value", str(err)) from err


def _fault_bits(value: object, where: str) -> DeviceFault:
    try:
        bits = int(value)  # type: ignore[call-overload]
    except (TypeError, ValueError) as err:
        raise EncodeError(f"{where} = {value!r}; expected fault bits 0..0xFF") from err
    if isinstance(value, bool) or not 0 <= bits <= 0xFF:
        raise EncodeError(f"{where} = {value!r}; expected fault bits 0..0xFF (DeviceFault)")
    return DeviceFault(bits)


@dataclass(frozen=True)
class ClearFaults:
    """Fault-clear request (bridge → device), identifier 0x790, sent while no push runs.

    The device clears each fault in ``mask`` only if its cause is gone and answers with a
    :class:`ClearFaultsAck` per addressed actuator (PROTOCOL.md, "Clearing a latched fault").

    Attributes:
        sequence: 0..255, echoed in the answers.
        mask: the fault bits to clear (0 only asks for the answer).
        actuator: 0 or 1, or None for every actuator of the device (``all`` on the wire).
    """

    sequence: int
    mask: DeviceFault
    actuator: int | None = None
    MESSAGE: ClassVar[str] = "ClearFaults"

    def to_frame(self) -> can.Message:
        """Encode as a CAN frame."""
        if self.actuator is not None:
            _actuator_name(self.MESSAGE, self.actuator)  # 0..N_ACTUATORS-1 or EncodeError
        return _encode(self.MESSAGE, {
            "Sequence": self.sequence,
            "Actuator": "all" if self.actuator is None else self.actuator,
            "Mask": int(_fault_bits(self.mask, "ClearFaults.mask")),
        })

    @classmethod
    def from_frame(cls, frame: can.Message) -> ClearFaults:
        """Decode a frame (raises DecodeError)."""
        v = _decode(_message(cls.MESSAGE), frame)
        target = v["Actuator"]
        actuator = None if isinstance(target, NamedSignalValue) else int(target)
        return cls(int(v["Sequence"]), DeviceFault(int(v["Mask"])), actuator)


@dataclass(frozen=True)
class ClearFaultsAck:
    """One actuator's answer to a :class:`ClearFaults` (device → bridge), 0x791 + actuator.

    Attributes:
        actuator: 0 or 1.
        sequence: the sequence of the request answered.
        cleared: the fault bits this request cleared.
        held: every fault bit still set after the request (0: the actuator is fault-free).
    """

    actuator: int
    sequence: int
    cleared: DeviceFault
    held: DeviceFault
    BASE: ClassVar[str] = "ClearFaultsAck"

    def to_frame(self) -> can.Message:
        """Encode as a CAN frame."""
        return _encode(_actuator_name(self.BASE, self.actuator), {
            "Sequence": self.sequence,
            "Cleared": int(_fault_bits(self.cleared, "ClearFaultsAck.cleared")),
            "Held": int(_fault_bits(self.held, "ClearFaultsAck.held")),
        })

    @classmethod
    def from_frame(cls, frame: can.Message) -> ClearFaultsAck:
        """Decode a frame (raises DecodeError)."""
        actuator = frame.arbitration_id - frame_id("ClearFaultsAck0")
        v = _decode(_message(_actuator_name(cls.BASE, actuator)), frame)
        return cls(actuator, int(v["Sequence"]), DeviceFault(int(v["Cleared"])),
                   DeviceFault(int(v["Held"])))


class _AckResult(enum.IntEnum):
    ACK = 0
    NACK = 1


ExosuitMessage: TypeAlias = (
    AssistanceOff
    | BridgeHeartbeat
    | ForceFeedback
    | DeviceStatus
    | ProfileSegment
    | ProfileCommit
    | ProfileAck
    | ClearFaults
    | ClearFaultsAck
)


@functools.cache
def _decoders() -> Mapping[int, Callable[[can.Message], ExosuitMessage]]:
    table: dict[int, Callable[[can.Message], ExosuitMessage]] = {
        frame_id(cls.MESSAGE): cls.from_frame
        for cls in (AssistanceOff, BridgeHeartbeat, ProfileSegment, ProfileCommit, ProfileAck,
                    ClearFaults)
    }
    for actuator in range(N_ACTUATORS):
        table[frame_id(f"ForceFeedback{actuator}")] = ForceFeedback.from_frame
        table[frame_id(f"DeviceStatus{actuator}")] = DeviceStatus.from_frame
        table[frame_id(f"ClearFaultsAck{actuator}")] = ClearFaultsAck.from_frame
    if ASSISTANCE_OFF_ID not in table:
        raise RuntimeError(f"{DBC_FILENAME} does not define 0x{ASSISTANCE_OFF_ID:03X}")
    return table


def decode_frame(frame: can.Message) -> ExosuitMessage:
    """Decode any frame of the exosuit message set.

    Args:
        frame: a received python-can message.

    Returns:
        The decoded message dataclass.

    Raises:
        DecodeError: with ``reason`` in :data:`DECODE_REASONS`; nothing else for any input.
    """
    if frame.is_error_frame:
        raise DecodeError("error_frame", f"error frame 0x{frame.arbitration_id:X}")
    if frame.is_remote_frame:
        raise DecodeError("remote_frame", f"remote frame 0x{frame.arbitration_id:X}")
    if frame.is_fd:
        raise DecodeError("fd_frame", f"CAN FD frame 0x{frame.arbitration_id:X}")
    if frame.is_extended_id:
        raise DecodeError("extended_id", f"29-bit identifier 0x{frame.arbitration_id:08X}")
    decoder = _decoders().get(frame.arbitration_id)
    if decoder is None:
        raise DecodeError("unknown_id", f"0x{frame.arbitration_id:03X}")
    return decoder(frame)
