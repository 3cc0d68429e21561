"""Async CAN endpoint of the exosuit protocol on python-can.

One :class:`CanEndpoint` owns one python-can bus, built from a frozen :class:`CanBusConfig`
(``socketcan``, ``pcan``, ``kvaser``, ``slcan``, ``virtual``, ``remote``... all through
``can.Bus``). Received frames arrive through python-can's asyncio machinery — a ``can.Notifier``
bound to the running loop feeding a ``can.AsyncBufferedReader`` — and one receive task decodes
them (:func:`~drivers.exosuit.codec.decode_frame`) and hands the messages to subscriptions
(bounded queues, oldest dropped and counted when a consumer falls behind, so the 2 kHz feedback
can never block the endpoint). Frames that do not decode are counted by reason in
:attr:`CanEndpoint.counters` and never stop it.

Bridge-side helpers: :meth:`CanEndpoint.push_profile` (segments, paced; commit; ack with a
timeout; bounded retries), a heartbeat task (:meth:`CanEndpoint.start_heartbeat`) and
:meth:`CanEndpoint.send_assistance_off`. A bus failure (receive or transmit) is recorded once in
:attr:`CanEndpoint.error`, wakes :meth:`CanEndpoint.wait_failed` and makes every subscription and
pending push raise :class:`~drivers.errors.TransportError`: the bridge's supervisor reacts with
assistance-off and a pause. The protocol itself is in ``drivers/PROTOCOL.md``.
"""

from __future__ import annotations

import asyncio
import collections
import contextlib
import enum
import errno
import functools
import logging
import math
import threading
import time
import types
from collections.abc import AsyncIterator, Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, NamedTuple

import can
import numpy as np

from drivers.errors import (
    DecodeError,
    DriverConfigError,
    DriverError,
    ProfilePushAborted,
    ProfilePushError,
    TransportError,
)
from drivers.exosuit.codec import (
    N_ACTUATORS,
    AssistanceOff,
    AssistanceOffReason,
    BridgeHeartbeat,
    BridgeState,
    ClearFaults,
    ClearFaultsAck,
    DeviceFault,
    ExosuitMessage,
    NackReason,
    ProfileAck,
    decode_frame,
    heartbeat_sequence,
)
from drivers.exosuit.faults import CLEARABLE_FAULTS, describe_faults, fault_names
from drivers.exosuit.profile import ProfileTransfer, pack_tables

__all__ = [
    "DEFAULT_ACK_TIMEOUT_S",
    "DEFAULT_PACE_S",
    "DEFAULT_RETRIES",
    "HEARTBEAT_PERIOD_S",
    "HEARTBEAT_WATCHDOG_S",
    "INTERFACE_OPTIONS",
    "LIVENESS_PERIOD_S",
    "LIVENESS_WATCHDOG_S",
    "NATIVE_CYCLIC_INTERFACES",
    "OTHER_BRIDGE_LISTEN_S",
    "RETRYABLE_NACKS",
    "CanBusConfig",
    "CanEndpoint",
    "ClearFaultsResult",
    "ProfileNackError",
    "PushPermit",
    "PushResult",
    "PushStage",
    "Stamped",
    "Subscription",
]

log = logging.getLogger(__name__)

#: Bridge heartbeat period (the device's watchdog is 5 periods, 100 ms).
HEARTBEAT_PERIOD_S = 0.020
#: The device's bus watchdog on the bridge heartbeat (PROTOCOL.md): 100 ms without a frame with
#: an advanced Counter latches ``heartbeat_lost``. The frames come from a cyclic sender (the
#: kernel's broadcast manager, or a sender thread), so a stall of the event loop does not trip it.
HEARTBEAT_WATCHDOG_S = 0.100
#: How long :meth:`CanEndpoint.check_no_other_bridge` listens for another bridge's heartbeat
#: before this one starts its own: five heartbeat periods, so a bridge already driving the bus
#: has sent several frames even if a few are late.
OTHER_BRIDGE_LISTEN_S = 5 * HEARTBEAT_PERIOD_S
#: How often the event loop advances the heartbeat's Liveness counter (and hands the cyclic
#: sender new frames): 5 updates per liveness watchdog, so 4 may come late or be lost.
LIVENESS_PERIOD_S = 0.200
#: The device's liveness watchdog (PROTOCOL.md): Liveness unchanged for 1 s latches
#: ``heartbeat_lost``. Longer than the worst event-loop stalls seen on a busy lab PC (0.1-0.7 s),
#: and about one stride (1.1 s), during which the device keeps executing a table it checked and
#: acknowledged itself.
LIVENESS_WATCHDOG_S = 1.0
#: Interfaces whose python-can bus has a native cyclic sender that cycles through a sequence of
#: frames and updates them in place (``modify_data``): SocketCAN's kernel broadcast manager.
#: Every other bus gets python-can's thread-based cyclic sender in this process
#: (``can.broadcastmanager.ThreadBasedCyclicSendTask``; python-can-remote's own periodic task
#: sends one frame per identifier and its ``modify_data`` does not work).
NATIVE_CYCLIC_INTERFACES = frozenset({"socketcan"})
#: Gap between profile segments: one 135-bit frame per 1 ms is 13.5 % of a 1 Mbit/s bus while a
#: push lasts (34 ms for 101 points), and an AssistanceOff queued behind segments is on the wire
#: within 2.69 ms in the worst case (PROTOCOL.md, "Bus budget"; drivers/exosuit/busload.py).
DEFAULT_PACE_S = 0.001
#: How long to wait for the ack after the commit (the device answers within 10 ms).
DEFAULT_ACK_TIMEOUT_S = 0.25
#: Transfer attempts after the first one.
DEFAULT_RETRIES = 3
#: Nack reasons worth re-sending the same table for; the others would be refused again.
RETRYABLE_NACKS = frozenset({NackReason.BAD_CRC, NackReason.MISSING_SEGMENT, NackReason.BUSY})

#: Interface options (``can.Bus`` keyword arguments besides interface/channel/bitrate) accepted
#: per interface, from the python-can 4.6 and python-can-remote signatures. Interfaces not listed
#: here are passed through unchecked.
INTERFACE_OPTIONS: Mapping[str, frozenset[str]] = types.MappingProxyType({
    "socketcan": frozenset({
        "receive_own_messages", "local_loopback", "fd", "can_filters", "ignore_rx_error_frames",
    }),
    "virtual": frozenset({
        "receive_own_messages", "rx_queue_size", "preserve_timestamps", "protocol",
        "can_filters",
    }),
    "slcan": frozenset({
        "tty_baudrate", "sleep_after_open", "rtscts", "listen_only", "timeout", "timing",
        "can_filters",
    }),
    "pcan": frozenset({
        "device_id", "state", "timing", "receive_own_messages", "fd", "auto_reset", "f_clock",
        "f_clock_mhz", "nom_brp", "nom_tseg1", "nom_tseg2", "nom_sjw", "data_brp",
        "data_tseg1", "data_tseg2", "data_sjw", "can_filters",
    }),
    "kvaser": frozenset({
        "accept_virtual", "tseg1", "tseg2", "sjw", "no_samp", "driver_mode", "single_handle",
        "receive_own_messages", "fd", "fd_non_iso", "exclusive", "override_exclusive",
        "data_bitrate", "no_init_access", "timing", "can_filters",
    }),
    "remote": frozenset({"can_filters", "receive_own_messages", "ssl_context"}),
})

# Interfaces whose bitrate is set outside python-can (socketcan: ``ip link ... bitrate``) or is
# meaningless (virtual); the configured bitrate is then not passed to ``can.Bus`` (``remote``
# gets it and passes it on to its server).
_NO_BITRATE = frozenset({"socketcan", "virtual"})


@dataclass(frozen=True)
class CanBusConfig:
    """Which CAN bus to open.

    Attributes:
        interface: python-can interface name (``socketcan``, ``pcan``, ``kvaser``, ``slcan``,
            ``virtual``, ``remote``, ...).
        channel: interface channel (``can0``/``vcan0``, ``PCAN_USBBUS1``, ``0``, ``/dev/ttyACM0``,
            a virtual channel name, ``ws://host:54701/``).
        bitrate: nominal bitrate in bit/s (not passed for socketcan, whose bitrate is set with
            ``ip link``, nor for virtual).
        options: further ``can.Bus`` keyword arguments; for the interfaces in
            :data:`INTERFACE_OPTIONS` only the keys listed there.

    Raises:
        DriverConfigError: unknown interface, empty channel, bad bitrate or unknown option.
    """

    interface: str
    channel: str | int
    bitrate: int | None = 1_000_000
    options: Mapping[str, Any] = field(default_factory=dict)

    _KEYS = ("interface", "channel", "bitrate", "options")

    def __post_init__(self) -> None:
        if not isinstance(self.interface, str) or self.interface not in can.VALID_INTERFACES:
            raise DriverConfigError(
                f"can.interface = {self.interface!r}; expected one of "
                f"{', '.join(sorted(can.VALID_INTERFACES))}"
            )
        if isinstance(self.channel, bool) or not isinstance(self.channel, (str, int)) or (
            isinstance(self.channel, str) and not self.channel
        ):
            raise DriverConfigError(
                f"can.channel = {self.channel!r}; expected a non-empty string or an integer"
            )
        if self.bitrate is not None and (
            isinstance(self.bitrate, bool) or not isinstance(self.bitrate, int)
            or not 10_000 <= self.bitrate <= 8_000_000
        ):
            raise DriverConfigError(
                f"can.bitrate = {self.bitrate!r}; expected an integer 10000..8000000 bit/s or None"
            )
        allowed = INTERFACE_OPTIONS.get(self.interface)
        unknown = sorted(set(self.options) - allowed) if allowed is not None else []
        if unknown:
            raise DriverConfigError(
                f"can option(s) {', '.join(unknown)} not known for interface "
                f"{self.interface!r}; expected some of {', '.join(sorted(allowed or ()))}"
            )
        object.__setattr__(self, "options", types.MappingProxyType(dict(self.options)))

    @classmethod
    def from_mapping(cls, mapping: Mapping[str, Any]) -> CanBusConfig:
        """Build from a config table, e.g. TOML ``[can]``.

        ``interface`` and ``channel`` are required, ``bitrate`` optional; every other key is an
        interface option (``fd = true``, ``tty_baudrate = 115200``...), or goes in ``options``.

        Raises:
            DriverConfigError: a required key is missing or a key is unknown.
        """
        missing = [k for k in ("interface", "channel") if k not in mapping]
        if missing:
            raise DriverConfigError(f"can: missing key(s) {', '.join(missing)}")
        nested = mapping.get("options", {})
        if not isinstance(nested, Mapping):
            raise DriverConfigError(f"can.options must be a table, got {nested!r}")
        options = {k: v for k, v in mapping.items() if k not in cls._KEYS}
        options.update(nested)
        return cls(
            interface=mapping["interface"],
            channel=mapping["channel"],
            bitrate=mapping.get("bitrate", 1_000_000),
            options=options,
        )

    def bus_kwargs(self) -> dict[str, Any]:
        """Keyword arguments for ``can.Bus``."""
        kwargs: dict[str, Any] = {"interface": self.interface, "channel": self.channel}
        if self.bitrate is not None and self.interface not in _NO_BITRATE:
            kwargs["bitrate"] = self.bitrate
        kwargs.update(self.options)
        return kwargs


class PushStage(enum.StrEnum):
    """The steps of a profile push at which :meth:`CanEndpoint.push_profile` asks ``permit``.

    The values are plain strings (``"first_segment"``, ``"commit"``), so a permit callable may
    compare its argument with either the enum or the string.
    """

    FIRST_SEGMENT = "first_segment"
    """Right before the first segment of an attempt is sent."""
    COMMIT = "commit"
    """Right before the commit of an attempt is sent (nothing is awaited in between)."""


#: ``permit(stage) -> bool``: whether the push may send the next step (see push_profile).
PushPermit = Callable[[str], bool]


@dataclass(frozen=True)
class PushResult:
    """Outcome of an acknowledged profile push.

    Attributes:
        version: the profile version acked.
        n_points: points in the table.
        crc32: CRC-32 of the table as sent.
        attempts: transfers sent (1 = first try).
        elapsed_s: loop time from the first segment to the ack.
        nacks: reasons of the nacks received before the ack.
        timeouts: attempts that got no matching ack in time.
    """

    version: int
    n_points: int
    crc32: int
    attempts: int
    elapsed_s: float
    nacks: tuple[NackReason, ...] = ()
    timeouts: int = 0


@dataclass(frozen=True)
class ClearFaultsResult:
    """Outcome of :meth:`CanEndpoint.clear_faults`.

    Attributes:
        sequence: the request's sequence number.
        mask: the faults asked to be cleared.
        answers: each answering actuator's :class:`~drivers.exosuit.codec.ClearFaultsAck`.
        missing: addressed actuators that did not answer within the timeout.
    """

    sequence: int
    mask: DeviceFault
    answers: Mapping[int, ClearFaultsAck]
    missing: tuple[int, ...] = ()

    @property
    def cleared(self) -> DeviceFault:
        """Faults cleared on any actuator."""
        out = DeviceFault(0)
        for a in self.answers.values():
            out |= a.cleared
        return out

    @property
    def held(self) -> DeviceFault:
        """Faults still set on any answering actuator."""
        out = DeviceFault(0)
        for a in self.answers.values():
            out |= a.held
        return out

    @property
    def ok(self) -> bool:
        """Every addressed actuator answered and none holds a fault any more."""
        return not self.missing and not self.held

    def describe(self) -> str:
        """One line for the operator, e.g. ``"cleared heartbeat_lost; still held: force_limit
        (cleared by the bridge once the measured force is back under the limit)"``."""
        parts = [f"cleared {', '.join(fault_names(self.cleared))}" if self.cleared
                 else "cleared nothing"]
        if self.held:
            parts.append(f"still held: {'; '.join(describe_faults(self.held))}")
        if self.missing:
            parts.append(f"no answer from actuator(s) {', '.join(map(str, self.missing))}")
        return "; ".join(parts)


class ProfileNackError(ProfilePushError):
    """The device refused a profile (after the retries, or at once for a non-retryable reason).

    Attributes:
        version: the profile version.
        reason: the last nack reason.
        detail: the nack's detail field.
        attempts: transfers sent.
    """

    def __init__(self, version: int, reason: NackReason, detail: int, attempts: int) -> None:
        self.version = version
        self.reason = reason
        self.detail = detail
        self.attempts = attempts
        super().__init__(
            f"profile version {version} refused by the device: {reason.name.lower()} "
            f"(detail {detail}) after {attempts} attempt(s)"
        )


class Stamped(NamedTuple):
    """A received message with the frame's receive timestamp (seconds, the bus's clock)."""

    t_s: float
    message: ExosuitMessage


_FAILED = object()  # queued into subscriptions when the bus fails


class Subscription:
    """A bounded queue of decoded messages of chosen kinds.

    Iterate with ``async for``, or ``await sub.get()``. When the queue is full the oldest item is
    dropped (counted as ``subscriber_overflow`` in the endpoint's counters). Use as a context
    manager, or call :meth:`close`, to stop receiving.
    """

    def __init__(
        self,
        endpoint: CanEndpoint,
        kinds: tuple[type, ...],
        maxsize: int,
        timestamps: bool,
    ) -> None:
        self._endpoint = endpoint
        self.kinds = kinds
        self.timestamps = timestamps
        self._queue: asyncio.Queue[Any] = asyncio.Queue(maxsize=maxsize)

    def accepts(self, message: ExosuitMessage) -> bool:
        """Whether ``message`` is of one of the subscribed kinds (all when none given)."""
        return not self.kinds or isinstance(message, self.kinds)

    def _put(self, item: Any) -> bool:
        dropped = False
        if self._queue.full():
            self._queue.get_nowait()
            dropped = True
        self._queue.put_nowait(item)
        return dropped

    async def get(self) -> Any:
        """The next message (a :class:`Stamped` when subscribed with ``timestamps=True``).

        Raises:
            TransportError: the bus failed.
        """
        item = await self._queue.get()
        if item is _FAILED:
            self._queue.put_nowait(_FAILED)  # keep failing for later calls too
            raise TransportError(f"CAN bus failed: {self._endpoint.error}")
        return item

    def get_nowait(self) -> Any:
        """The next message if one is queued (raises asyncio.QueueEmpty otherwise)."""
        item = self._queue.get_nowait()
        if item is _FAILED:
            self._queue.put_nowait(_FAILED)
            raise TransportError(f"CAN bus failed: {self._endpoint.error}")
        return item

    def qsize(self) -> int:
        """Number of queued items."""
        return self._queue.qsize()

    def close(self) -> None:
        """Stop receiving (idempotent)."""
        self._endpoint._unsubscribe(self)

    def __enter__(self) -> Subscription:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __aiter__(self) -> AsyncIterator[Any]:
        return self

    async def __anext__(self) -> Any:
        return await self.get()


class _PushAcks(Subscription):
    """The answers a running push accepts: filled by the endpoint's answer accounting only."""

    def __init__(self, endpoint: CanEndpoint) -> None:
        super().__init__(endpoint, (ProfileAck,), 64, False)

    def accepts(self, message: ExosuitMessage) -> bool:
        """Never through the ordinary dispatch (the accounting puts accepted answers in)."""
        return False


class _ErrorListener(can.Listener):
    """Receives python-can's reader errors (from the Notifier, in the loop thread)."""

    def __init__(self, on_error: Callable[[Exception], None]) -> None:
        self._on_error_cb = on_error

    def on_message_received(self, msg: can.Message) -> None:
        """Messages go to the AsyncBufferedReader; nothing to do here."""

    def on_error(self, exc: Exception) -> None:
        """Forward the reader's exception to the endpoint."""
        self._on_error_cb(exc)


class _LoopNotifier(can.Notifier):
    """A Notifier whose file-descriptor reader reports a failing ``recv`` to the listeners.

    python-can's loop-bound reader (``loop.add_reader`` on ``bus.fileno()``) lets an exception
    from ``bus.recv`` escape into the event loop's exception handler, where it is only logged and
    repeats on every readiness event. Here it goes to ``Listener.on_error`` like the threaded
    reader's errors, and the fd is no longer watched.
    """

    def _on_message_available(self, bus: can.BusABC) -> None:
        try:
            super()._on_message_available(bus)
        except Exception as err:  # forwarded to on_error, not swallowed
            self.exception = err
            if self._loop is not None:
                # Best effort: stop watching the fd. The error itself goes on to on_error below.
                with contextlib.suppress(ValueError, OSError, can.CanError):
                    self._loop.remove_reader(bus.fileno())
            self._on_error(err)


class _CyclicErrors:
    """``on_error`` of the heartbeat's sender thread (python-can calls it in that thread).

    A full transmit queue is retried (counted ``send_retry``) until it has lasted
    ``timeout_s``; then, or on any other error, the endpoint is marked failed in its event loop
    and the sender stops.
    """

    def __init__(self, endpoint: CanEndpoint, loop: asyncio.AbstractEventLoop, timeout_s: float,
                 period_s: float) -> None:
        self._endpoint = endpoint
        self._loop = loop
        self._timeout_s = timeout_s
        self._period_s = period_s
        self._first: float | None = None
        self._last = -math.inf

    def __call__(self, exc: Exception) -> bool:
        now = time.monotonic()
        if now - self._last > 2 * self._period_s + 0.05:  # frames went out in between
            self._first = now
        self._last = now
        first = now if self._first is None else self._first
        retry = isinstance(exc, can.CanOperationError) and now - first < self._timeout_s
        with contextlib.suppress(RuntimeError):  # the loop is closed: nobody to tell
            if retry:
                self._loop.call_soon_threadsafe(self._endpoint._count, "send_retry")
            else:
                err = TransportError(f"CAN send of the bridge heartbeat failed: {exc}")
                err.__cause__ = exc
                self._loop.call_soon_threadsafe(self._endpoint._on_bus_error, err)
        return retry


#: errno values of a SocketCAN interface that is not there: the kernel has no CAN support
#: (EAFNOSUPPORT), no such interface (ENODEV), or it is down (ENETDOWN).
_SOCKETCAN_MISSING = frozenset({errno.EAFNOSUPPORT, errno.ENODEV, errno.ENETDOWN})


def _socketcan_hint(config: CanBusConfig, err: BaseException) -> str:
    """What to do when a SocketCAN interface is missing or down ('' for any other failure)."""
    if config.interface != "socketcan":
        return ""
    codes = {getattr(e, "errno", None) or getattr(e, "error_code", None)
             for e in (err, err.__cause__, err.__context__) if e is not None}
    if not codes & _SOCKETCAN_MISSING:
        return ""
    return (f"; is {config.channel} up? `ip link show {config.channel}` says; for a dry run on the "
            "virtual exosuit `hilbo vcan-setup | sudo sh` creates vcan0 (a kernel without vcan: "
            "[can] interface = \"remote\" or \"virtual\", docs/simulation.md)")


class CanEndpoint:
    """Async endpoint of the exosuit protocol on one python-can bus.

    Use ``async with CanEndpoint(config) as ep:``. Inside: :meth:`subscribe` to decoded
    messages, :meth:`send`, :meth:`push_profile`, :meth:`start_heartbeat`,
    :meth:`send_assistance_off`. The endpoint is not thread-safe: use it from one event loop.

    Args:
        config: which bus to open.
        bus_factory: builds the bus from ``config.bus_kwargs()`` (default ``can.Bus``).
        send_timeout_s: how long :meth:`send` keeps retrying a full transmit queue.
        notifier_timeout_s: receive-thread poll period for buses without a file descriptor
            (also the bound on how long :meth:`close` waits for that thread).
    """

    def __init__(
        self,
        config: CanBusConfig,
        *,
        bus_factory: Callable[..., can.BusABC] = can.Bus,
        send_timeout_s: float = 0.05,
        notifier_timeout_s: float = 0.05,
    ) -> None:
        if not isinstance(config, CanBusConfig):
            raise DriverConfigError(f"config must be a CanBusConfig, got {type(config).__name__}")
        self.config = config
        self._bus_factory = bus_factory
        self._send_timeout_s = float(send_timeout_s)
        self._notifier_timeout_s = float(notifier_timeout_s)
        self._bus: can.BusABC | None = None
        self._notifier: can.Notifier | None = None
        self._reader: can.AsyncBufferedReader | None = None
        self._rx_task: asyncio.Task[None] | None = None
        self._hb_task: asyncio.Task[None] | None = None
        self._hb_cyclic: can.broadcastmanager.CyclicSendTaskABC | None = None
        self._hb_liveness = 0
        # Held around every transmit when a sender thread shares the bus with this loop.
        self._send_lock = threading.Lock()
        self._clear_sequence = 0
        # Answer accounting of the latest push (version, commits sent, answers accepted), and
        # the queue of the push waiting for an answer (PROTOCOL.md, "Transfer, commit, ack").
        self._ack_version: int | None = None
        self._ack_commits = 0
        self._ack_answers = 0
        self._push_acks: Subscription | None = None
        self._subs: list[Subscription] = []
        self._counters: collections.Counter[str] = collections.Counter()
        self._received: collections.Counter[str] = collections.Counter()
        self._error: BaseException | None = None
        self._failed: asyncio.Event | None = None
        self._push_lock: asyncio.Lock | None = None
        self._bridge_state = BridgeState.IDLE

    @property
    def bridge_state(self) -> BridgeState:
        """State announced in the bridge heartbeat; the device assists only while RUNNING.

        Setting it hands the cyclic sender new frames at once (the next heartbeat carries it).
        """
        return self._bridge_state

    @bridge_state.setter
    def bridge_state(self, state: BridgeState) -> None:
        self._bridge_state = BridgeState(state)
        if self._hb_cyclic is not None:
            self._modify_heartbeat()

    # --- lifecycle --------------------------------------------------------------------------

    async def __aenter__(self) -> CanEndpoint:
        await self.open()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.close()

    @property
    def is_open(self) -> bool:
        """Whether the bus is open."""
        return self._bus is not None

    async def open(self) -> None:
        """Open the bus and start receiving.

        Raises:
            DriverConfigError: python-can rejects the interface or its options.
            TransportError: the bus could not be opened.
        """
        if self._bus is not None:
            raise DriverError("endpoint is already open")
        loop = asyncio.get_running_loop()
        kwargs = self.config.bus_kwargs()
        try:
            # Opening may block (an slcan adapter sleeps after opening its port).
            bus = await asyncio.to_thread(self._bus_factory, **kwargs)
        except can.CanInterfaceNotImplementedError as err:
            raise DriverConfigError(
                f"CAN interface {self.config.interface!r} is not usable here: {err}"
            ) from err
        except (can.CanError, OSError, ValueError, TypeError, ImportError) as err:
            raise TransportError(
                f"cannot open CAN bus {self.config.interface}:{self.config.channel}: {err}"
                f"{_socketcan_hint(self.config, err)}"
            ) from err
        self._error = None
        self._failed = asyncio.Event()
        self._push_lock = asyncio.Lock()
        self._reader = can.AsyncBufferedReader()
        try:
            self._notifier = _LoopNotifier(
                bus,
                [self._reader, _ErrorListener(self._on_bus_error)],
                timeout=self._notifier_timeout_s,
                loop=loop,
            )
        except (ValueError, can.CanError, OSError) as err:  # e.g. bus already has a Notifier
            bus.shutdown()
            raise TransportError(f"cannot receive from CAN bus {self.config.channel}: {err}") from err
        self._bus = bus
        self._rx_task = loop.create_task(self._receive_loop(), name="can-endpoint-rx")
        self._rx_task.add_done_callback(self._on_task_done)
        log.info("CAN endpoint open on %s:%s", self.config.interface, self.config.channel)

    async def close(self) -> None:
        """Stop the heartbeat and the receiver, and shut the bus down (idempotent)."""
        await self.stop_heartbeat()
        if self._rx_task is not None:
            self._rx_task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._rx_task
            self._rx_task = None
        if self._notifier is not None:
            self._notifier.stop(timeout=self._notifier_timeout_s + 1.0)
            self._notifier = None
        if self._bus is not None:
            bus, self._bus = self._bus, None
            try:
                bus.shutdown()
            except (can.CanError, OSError) as err:
                log.warning("CAN bus shutdown failed: %s", err)

    # --- receive ----------------------------------------------------------------------------

    @property
    def counters(self) -> Mapping[str, int]:
        """Frames that did not decode, by reason (``unknown_id``, ``bad_length``, ``bad_value``,
        ``extended_id``, ``remote_frame``, ``error_frame``, ``fd_frame``), plus
        ``subscriber_overflow``, ``send_retry``, ``heartbeat_overrun`` (a liveness update of
        the heartbeat more than one liveness period late: the event loop was blocked; the
        heartbeat frames themselves went on), ``clear_ack_stale`` and
        the profile answers this endpoint rejected (once it has pushed a profile):
        ``ack_before_commit`` (an answer of the version being pushed before its first commit was
        sent), ``ack_repeated`` (an answer beyond one per commit sent, e.g. a second ack of the
        same commit) and ``ack_stale`` (an answer of another version than the latest push's)."""
        return types.MappingProxyType(self._counters)

    @property
    def received(self) -> Mapping[str, int]:
        """Decoded frames, by message class name."""
        return types.MappingProxyType(self._received)

    @property
    def error(self) -> BaseException | None:
        """The bus failure, once one happened."""
        return self._error

    async def wait_failed(self) -> BaseException:
        """Wait until the bus fails; returns the error (for the bridge's supervisor)."""
        if self._failed is None:
            raise DriverError("endpoint is not open")
        await self._failed.wait()
        if self._error is None:
            raise DriverError("endpoint failure flagged without an error")
        return self._error

    def subscribe(
        self, *kinds: type, maxsize: int = 1024, timestamps: bool = False
    ) -> Subscription:
        """Receive decoded messages of the given classes (all messages if none given).

        Args:
            kinds: message classes, e.g. ``ProfileAck, DeviceStatus``.
            maxsize: queue bound; the oldest item is dropped when it is full.
            timestamps: deliver :class:`Stamped` (t_s, message) instead of bare messages.
        """
        if maxsize < 1:
            raise DriverConfigError(f"subscription maxsize must be >= 1, got {maxsize}")
        sub = Subscription(self, tuple(kinds), maxsize, timestamps)
        if self._error is not None:
            sub._put(_FAILED)
        self._subs.append(sub)
        return sub

    def _unsubscribe(self, sub: Subscription) -> None:
        with contextlib.suppress(ValueError):
            self._subs.remove(sub)

    async def _receive_loop(self) -> None:
        reader = self._reader
        if reader is None:
            raise DriverError("receive loop started without a reader")
        while True:
            frame = await reader.get_message()
            self._dispatch(frame)

    def _dispatch(self, frame: can.Message) -> None:
        try:
            message = decode_frame(frame)
        except DecodeError as err:
            self._counters[err.reason] += 1
            log.debug("undecodable frame counted as %s: %s", err.reason, err)
            return
        self._received[type(message).__name__] += 1
        if (isinstance(message, BridgeHeartbeat) and self._hb_cyclic is not None
                and self._foreign(frame)):
            # Two bridges driving one exosuit push conflicting profiles and accept each other's
            # acks (their versions count alike), and one's pause turns the device off under the
            # other: neither may go on (DESIGN.md, safety invariants: a bus error pauses).
            self._on_bus_error(TransportError(
                "another bridge is sending heartbeats on this bus: two sessions must never drive "
                "one exosuit; stop the other hilbo run (or validate) before starting this one"))
        if isinstance(message, ProfileAck) and self._answers_push(message) and (
            self._push_acks is not None
        ):
            self._push_acks._put(message)
        stamped: Stamped | None = None
        for sub in self._subs:
            if sub.accepts(message):
                if sub.timestamps:
                    stamped = stamped or Stamped(float(frame.timestamp), message)
                    item: Any = stamped
                else:
                    item = message
                if sub._put(item):
                    self._counters["subscriber_overflow"] += 1

    def _foreign(self, frame: can.Message) -> bool:
        """Whether a received bridge frame was sent by another node, not echoed from this one.

        python-can delivers this bus's own frames only with ``receive_own_messages``, and then
        marks them ``is_rx = False`` (SocketCAN, virtual); a bus configured to echo them whose
        interface cannot mark them (python-can-remote) cannot tell, so nothing is judged there.
        """
        if not frame.is_rx:
            return False
        if self.config.options.get("receive_own_messages"):
            return self.config.interface in ("socketcan", "virtual")
        return True

    async def check_no_other_bridge(self, listen_s: float = OTHER_BRIDGE_LISTEN_S) -> None:
        """Refuse a bus on which another bridge is already sending its heartbeat.

        Call it after :meth:`open` and before :meth:`start_heartbeat`: it listens for
        ``listen_s`` (the other bridge sends a heartbeat every 20 ms) and counts the
        BridgeHeartbeat frames received since :meth:`open`, which before this endpoint sends its
        own can only be another bridge's. Once this one's heartbeat runs, a foreign heartbeat fails the bus
        (:meth:`wait_failed`) instead.

        Raises:
            TransportError: another bridge's heartbeat was received; or the bus has failed.
            DriverConfigError: ``listen_s`` is not a finite number > 0.
            DriverError: the endpoint is not open, or its own heartbeat already runs.
        """
        if not (isinstance(listen_s, int | float) and math.isfinite(listen_s) and listen_s > 0):
            raise DriverConfigError(f"listen_s={listen_s!r}; expected a finite number of seconds > 0")
        self._check_usable()
        if self._hb_cyclic is not None:
            raise DriverError("check_no_other_bridge() after start_heartbeat(): this bridge's own "
                              "heartbeat would be counted")
        await asyncio.sleep(listen_s)
        self._check_usable()
        seen = self._received["BridgeHeartbeat"]  # since open(); none of them ours yet
        if seen:
            raise TransportError(
                f"another bridge is already driving the exosuit on {self.config.interface} "
                f"{self.config.channel!r} ({seen} of its heartbeats in {listen_s * 1e3:.0f} ms): "
                "two sessions must never drive one exosuit; stop the other hilbo run (or "
                "validate) first, or check [can] channel")

    def _answers_push(self, ack: ProfileAck) -> bool:
        """Whether ``ack`` answers a commit of the latest push; counts the answers it rejects.

        Each commit sent earns one answer: an answer of the push's version before its first
        commit left, one beyond the number of commits sent, or one of another version is
        rejected (never completes a push) and counted. An endpoint that never pushed (a
        listener, the device's own) judges nothing.
        """
        if self._ack_version is None:
            return False
        if ack.version != self._ack_version:
            reason = "ack_stale"
        elif self._ack_commits == 0:
            reason = "ack_before_commit"
        elif self._ack_answers >= self._ack_commits:
            reason = "ack_repeated"
        else:
            self._ack_answers += 1
            return True
        self._counters[reason] += 1
        # debug, like undecodable frames: a misbehaving device must not flood the log; the
        # counters are what the bridge logs.
        log.debug("profile answer %s rejected: %s (push v%d, %d commit(s), %d answer(s))",
                  ack, reason, self._ack_version, self._ack_commits, self._ack_answers)
        return False

    def _on_bus_error(self, exc: BaseException) -> None:
        if self._error is not None:
            return
        log.error("CAN bus failed: %s", exc)
        self._error = exc
        if self._failed is not None:
            self._failed.set()
        for sub in self._subs:
            sub._put(_FAILED)

    def _count(self, name: str) -> None:
        self._counters[name] += 1

    def _on_task_done(self, task: asyncio.Task[None]) -> None:
        if task.cancelled():
            return
        exc = task.exception()
        if exc is not None:
            self._on_bus_error(exc)

    # --- transmit ---------------------------------------------------------------------------

    def _check_usable(self) -> can.BusABC:
        if self._bus is None:
            raise DriverError("endpoint is not open")
        if self._error is not None:
            raise TransportError(f"CAN bus failed: {self._error}")
        return self._bus

    def send_nowait(self, message: ExosuitMessage | can.Message) -> None:
        """Transmit one message now (one attempt).

        Raises:
            EncodeError: the message does not encode.
            TransportError: the bus refused the frame or has failed.
        """
        bus = self._check_usable()
        frame = message if isinstance(message, can.Message) else message.to_frame()
        try:
            with self._send_lock:
                bus.send(frame, timeout=0)
        except can.CanError as err:
            raise TransportError(f"CAN send of 0x{frame.arbitration_id:03X} failed: {err}") from err

    async def send(self, message: ExosuitMessage | can.Message) -> None:
        """Transmit one message, retrying a full transmit queue for up to ``send_timeout_s``.

        Raises:
            EncodeError: the message does not encode.
            TransportError: still refused at the deadline, or the bus has failed.
        """
        await self._send(message)

    async def _send(self, message: ExosuitMessage | can.Message,
                    before_try: Callable[[], None] | None = None) -> None:
        """:meth:`send`, calling ``before_try()`` right before every transmit attempt (a
        retry after a full queue included), with nothing awaited in between."""
        bus = self._check_usable()
        frame = message if isinstance(message, can.Message) else message.to_frame()
        loop = asyncio.get_running_loop()
        deadline = loop.time() + self._send_timeout_s
        while True:
            if before_try is not None:
                before_try()
            try:
                with self._send_lock:
                    bus.send(frame, timeout=0)
                return
            except can.CanOperationError as err:
                # Typically ENOBUFS / "Transmit buffer full": the adapter queue is busy.
                if loop.time() >= deadline:
                    raise TransportError(
                        f"CAN send of 0x{frame.arbitration_id:03X} failed for "
                        f"{self._send_timeout_s} s: {err}"
                    ) from err
                self._counters["send_retry"] += 1
                await asyncio.sleep(0.001)
            except can.CanError as err:
                raise TransportError(
                    f"CAN send of 0x{frame.arbitration_id:03X} failed: {err}"
                ) from err

    async def send_assistance_off(self, reason: AssistanceOffReason) -> None:
        """Command the safe state at once and announce PAUSED in the heartbeat (if RUNNING).

        The heartbeat's state keeps the device off afterwards, so a lost AssistanceOff frame is
        corrected within one heartbeat period.
        """
        if self.bridge_state == BridgeState.RUNNING:
            self.bridge_state = BridgeState.PAUSED
        await self.send(AssistanceOff(AssistanceOffReason(reason)))

    async def clear_faults(
        self,
        mask: DeviceFault | int = CLEARABLE_FAULTS,
        actuator: int | None = None,
        *,
        timeout_s: float = DEFAULT_ACK_TIMEOUT_S,
        n_actuators: int = N_ACTUATORS,
    ) -> ClearFaultsResult:
        """Ask the device to clear latched faults, and wait for its answers.

        Sends one ClearFaults (PROTOCOL.md, "Clearing a latched fault") and waits up to
        ``timeout_s`` for the ClearFaultsAck of every addressed actuator with this request's
        sequence; answers to earlier requests are ignored and counted (``clear_ack_stale``).
        The device clears a fault only once its cause is gone and never restarts assistance by
        itself: it assists again only after a new profile commit is acked while the heartbeat
        says RUNNING. The request is serialised with :meth:`push_profile` (it waits for a
        running push and holds pushes back until it is answered), so it never lands among the
        segments.

        Args:
            mask: the faults to clear (default every fault a request can clear); 0 only asks
                for the answer.
            actuator: 0 or 1, or None for every actuator.
            timeout_s: how long to wait for the answers (s).
            n_actuators: actuators the device has (the answers awaited when ``actuator`` is
                None).

        Returns:
            A :class:`ClearFaultsResult` (``ok`` when nothing is held and every actuator
            answered; ``missing`` lists those that did not).

        Raises:
            DriverConfigError: bad timeout or actuator count.
            EncodeError: bad mask or actuator.
            TransportError: the bus failed.
        """
        if not timeout_s > 0 or isinstance(n_actuators, bool) or n_actuators not in range(
            1, N_ACTUATORS + 1
        ):
            raise DriverConfigError(
                f"clear_faults: expected timeout_s > 0 and n_actuators 1..{N_ACTUATORS}; got "
                f"timeout_s={timeout_s}, n_actuators={n_actuators}"
            )
        sequence = self._clear_sequence
        request = ClearFaults(sequence, mask, actuator)  # type: ignore[arg-type]
        frame = request.to_frame()  # validates mask and actuator before anything is sent
        expected = set(range(n_actuators)) if actuator is None else {actuator}
        self._check_usable()
        if self._push_lock is None:
            raise DriverError("endpoint is not open")
        loop = asyncio.get_running_loop()
        async with self._push_lock:
            self._clear_sequence = (sequence + 1) % 256
            answers: dict[int, ClearFaultsAck] = {}
            with self.subscribe(ClearFaultsAck) as sub:
                await self.send(frame)
                deadline = loop.time() + timeout_s
                while expected - answers.keys():
                    remaining = deadline - loop.time()
                    if remaining <= 0:
                        break
                    try:
                        async with asyncio.timeout(remaining):
                            answer = await sub.get()
                    except TimeoutError:
                        break
                    if answer.sequence != sequence or answer.actuator not in expected:
                        self._counters["clear_ack_stale"] += 1
                        continue
                    answers[answer.actuator] = answer
        result = ClearFaultsResult(sequence, DeviceFault(int(request.mask)),
                                   types.MappingProxyType(answers),
                                   tuple(sorted(expected - answers.keys())))
        log.info("clear faults %s: %s", fault_names(request.mask) or "(query)", result.describe())
        return result

    # --- heartbeat --------------------------------------------------------------------------

    def start_heartbeat(
        self, period_s: float = HEARTBEAT_PERIOD_S, *, liveness_period_s: float = LIVENESS_PERIOD_S
    ) -> asyncio.Task[None]:
        """Start the bridge heartbeat (or return its running liveness task).

        Two layers (PROTOCOL.md, "Heartbeats and their timeouts"):

        * a **cyclic sender** sends BridgeHeartbeat every ``period_s``, cycling through the 256
          frames of :func:`~drivers.exosuit.codec.heartbeat_sequence` so that Counter advances
          on every frame: python-can ``send_periodic`` on SocketCAN (the kernel's broadcast
          manager), python-can's thread-based cyclic sender elsewhere
          (:data:`NATIVE_CYCLIC_INTERFACES`). A busy or stalled event loop does not delay it.
        * a **liveness task** of this event loop advances Liveness every ``liveness_period_s``
          and hands the sender the new frames (``modify_data``); a hung bridge stops advancing
          it, and the device's liveness watchdog (1 s) turns assistance off.

        A send failure of either ends the task and marks the endpoint failed
        (:meth:`wait_failed`).

        Returns:
            The liveness task.
        """
        if not period_s > 0 or not liveness_period_s > 0:
            raise DriverConfigError(
                f"heartbeat period_s and liveness_period_s must be > 0, got {period_s}, "
                f"{liveness_period_s}")
        bus = self._check_usable()
        if self._hb_task is not None and not self._hb_task.done():
            return self._hb_task
        loop = asyncio.get_running_loop()
        frames = heartbeat_sequence(self._bridge_state, self._hb_liveness)
        try:
            if self.config.interface in NATIVE_CYCLIC_INTERFACES:
                self._hb_cyclic = bus.send_periodic(frames, period_s)
            else:
                self._hb_cyclic = can.broadcastmanager.ThreadBasedCyclicSendTask(
                    bus, self._send_lock, frames, period_s,
                    on_error=_CyclicErrors(self, loop, self._send_timeout_s, period_s))
        except (can.CanError, OSError, ValueError) as err:
            raise TransportError(f"cannot start the bridge heartbeat: {err}") from err
        task = loop.create_task(self._liveness_loop(liveness_period_s),
                                name="can-endpoint-heartbeat")
        task.add_done_callback(self._on_task_done)
        self._hb_task = task
        return task

    async def stop_heartbeat(self) -> None:
        """Stop the liveness task and the cyclic sender (idempotent)."""
        task, self._hb_task = self._hb_task, None
        if task is not None and not task.done():
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task
        cyclic, self._hb_cyclic = self._hb_cyclic, None
        if cyclic is not None:
            with contextlib.suppress(can.CanError, OSError, ValueError):
                cyclic.stop()  # a failed bus may refuse the request; it sends nothing either way
            thread = getattr(cyclic, "thread", None)
            if isinstance(thread, threading.Thread) and thread is not threading.current_thread():
                await asyncio.to_thread(thread.join, 1.0)

    def _modify_heartbeat(self) -> None:
        """Hand the cyclic sender the frames of the current state and liveness."""
        cyclic = self._hb_cyclic
        if not isinstance(cyclic, can.ModifiableCyclicTaskABC):
            raise DriverError(f"the heartbeat's cyclic sender {cyclic!r} cannot be updated")
        try:
            cyclic.modify_data(heartbeat_sequence(self._bridge_state, self._hb_liveness))
        except (can.CanError, OSError) as err:
            raise TransportError(f"cannot update the bridge heartbeat: {err}") from err

    async def _liveness_loop(self, period_s: float) -> None:
        loop = asyncio.get_running_loop()
        next_t = loop.time()
        while True:
            self._check_usable()
            self._hb_liveness = (self._hb_liveness + 1) % 256
            self._modify_heartbeat()
            next_t += period_s
            delay = next_t - loop.time()
            if delay < 0:  # the loop was blocked for more than a period: resynchronise
                self._counters["heartbeat_overrun"] += 1
                next_t, delay = loop.time(), 0.0
            if self._failed is None:
                raise DriverError("endpoint is not open")
            # Sleep, but end at once when the bus fails (the sender thread reports it).
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(delay):
                    await self._failed.wait()

    # --- profile push -----------------------------------------------------------------------

    async def push_profile(
        self,
        forces_n: Sequence[float] | np.ndarray,
        version: int,
        *,
        timeout_s: float = DEFAULT_ACK_TIMEOUT_S,
        retries: int = DEFAULT_RETRIES,
        pace_s: float = DEFAULT_PACE_S,
        permit: PushPermit | None = None,
    ) -> PushResult:
        """Send a force-profile table, commit it and wait for the device's ack.

        Each attempt sends every segment (``pace_s`` apart), then the commit, then waits up to
        ``timeout_s`` for a ProfileAck of this version. A timeout or a retryable nack
        (:data:`RETRYABLE_NACKS`; after BUSY the endpoint first waits ``timeout_s``) starts the
        next attempt, up to ``retries`` more; other nacks fail at once. Pushes are serialised.

        ``permit`` lets the caller (the bridge's supervisor) stop a push at the last moment: it
        is called with :attr:`PushStage.FIRST_SEGMENT` right before the first segment of every
        attempt and with :attr:`PushStage.COMMIT` right before every commit, synchronously,
        with no await between its True and the frame going to the bus (if the transmit queue
        is full, it is asked again before each retry of that frame). When it returns False
        the push sends nothing more (in particular not that commit) and raises
        :class:`~drivers.errors.ProfilePushAborted`. An exception it raises propagates the same
        way, unchanged.

        Args:
            forces_n: the table, shape (n,), 2 ≤ n ≤ 768, newtons over 0..100 % gait cycle (a
                multi-actuator table is built with :func:`~drivers.exosuit.profile.pack_tables`).
            version: profile version 1..255.
            timeout_s: ack timeout per attempt (s).
            retries: attempts after the first.
            pace_s: gap between segments (s); 0 sends them back to back.
            permit: ``permit(stage) -> bool``, asked before each attempt's first segment and
                before each commit; None always permits.

        Returns:
            A :class:`PushResult`.

        Raises:
            EncodeError: the table or version cannot be encoded (nothing is sent).
            ProfilePushAborted: ``permit`` returned False (the refused step was not sent).
            ProfileNackError: nacked with a non-retryable reason, or the last attempt nacked.
            ProfilePushError: no ack after all attempts.
            TransportError: the bus failed.
        """
        if not timeout_s > 0 or not pace_s >= 0 or not (isinstance(retries, int) and retries >= 0):
            raise DriverConfigError(
                f"push_profile: expected timeout_s > 0, pace_s >= 0, integer retries >= 0; got "
                f"timeout_s={timeout_s}, pace_s={pace_s}, retries={retries}"
            )
        if permit is not None and not callable(permit):
            raise DriverConfigError(
                f"push_profile: permit must be a callable permit(stage) -> bool or None, got "
                f"{permit!r}"
            )
        transfer = ProfileTransfer.from_forces(forces_n, version)
        segments = [s.to_frame() for s in transfer.segments()]
        commit = transfer.commit().to_frame()
        self._check_usable()
        if self._push_lock is None:
            raise DriverError("endpoint is not open")
        loop = asyncio.get_running_loop()
        async with self._push_lock:
            t0 = loop.time()
            nacks: list[NackReason] = []
            timeouts = 0
            last: ProfileAck | None = None
            commits_sent = 0

            def check(stage: PushStage, attempt: int) -> None:
                if permit is not None and not permit(stage):
                    log.info("profile v%d: push aborted before the %s (attempt %d)",
                             version, stage.value, attempt)
                    raise ProfilePushAborted(version, stage.value, attempt, commits_sent)

            # A new push supersedes the earlier ones: their late answers are stale from now on,
            # and nothing answers this one before its first commit is on the bus.
            self._ack_version, self._ack_commits, self._ack_answers = version, 0, 0
            acks = _PushAcks(self)
            self._subs.append(acks)
            if self._error is not None:
                acks._put(_FAILED)
            self._push_acks = acks
            try:
                for attempt in range(1, retries + 2):
                    # Paced against deadlines (frame k at start + k·pace_s), not by sleeping pace_s
                    # after each send: on a busy event loop every sleep overshoots (measured: a
                    # 2 ms sleep took 2.65 ms beside 2 kHz of feedback), which summed to +20 ms
                    # per push. A late frame never sends the next closer than pace_s / 2.
                    start = loop.time()
                    sent_at = -math.inf
                    for k, frame in enumerate([*segments, commit]):
                        if k and pace_s > 0:
                            due = max(start + k * pace_s, sent_at + 0.5 * pace_s)
                            delay = due - loop.time()
                            if delay > 0:
                                await asyncio.sleep(delay)
                        # Asked after the pacing sleep (and again before a transmit retry), so
                        # nothing is awaited between the permission and the frame reaching the
                        # bus.
                        stage = (PushStage.COMMIT if frame is commit
                                 else PushStage.FIRST_SEGMENT if k == 0 else None)
                        await self._send(frame, None if stage is None
                                         else functools.partial(check, stage, attempt))
                        if frame is commit:
                            # Counted before anything is awaited: an answer dispatched from
                            # now on may answer this commit.
                            self._ack_commits += 1
                            commits_sent += 1
                        sent_at = loop.time()
                    ack = await self._await_ack(acks, version, loop.time() + timeout_s)
                    if ack is None:
                        timeouts += 1
                        log.warning("profile v%d: no ack within %.3f s (attempt %d)",
                                    version, timeout_s, attempt)
                        continue
                    if ack.accepted:
                        return PushResult(
                            version=version, n_points=transfer.n_points, crc32=transfer.crc32,
                            attempts=attempt, elapsed_s=loop.time() - t0, nacks=tuple(nacks),
                            timeouts=timeouts,
                        )
                    last = ack
                    nacks.append(ack.reason)
                    log.warning("profile v%d nacked: %s (detail %d, attempt %d)",
                                version, ack.reason.name, ack.detail, attempt)
                    if ack.reason not in RETRYABLE_NACKS:
                        raise ProfileNackError(version, ack.reason, ack.detail, attempt)
                    if ack.reason == NackReason.BUSY:
                        await asyncio.sleep(timeout_s)
            finally:
                self._push_acks = None
                acks.close()
            if last is not None:
                raise ProfileNackError(version, last.reason, last.detail, retries + 1)
            raise ProfilePushError(
                f"profile version {version}: no ack after {retries + 1} attempt(s) of "
                f"{timeout_s} s each"
            )

    async def push_tables(
        self,
        tables: Sequence[Sequence[float] | np.ndarray],
        version: int,
        *,
        timeout_s: float = DEFAULT_ACK_TIMEOUT_S,
        retries: int = DEFAULT_RETRIES,
        pace_s: float = DEFAULT_PACE_S,
        permit: PushPermit | None = None,
    ) -> PushResult:
        """Push one table per joint of a multi-actuator device as one profile.

        The tables are packed with :func:`~drivers.exosuit.profile.pack_tables` (the layout of
        PROTOCOL.md, "Force profile tables") and sent with :meth:`push_profile`, whose
        arguments and errors apply.

        Args:
            tables: ``k`` tables in the device's table order, each shape ``(m,)``, newtons.
            version: profile version 1..255.
            timeout_s: ack timeout per attempt (s).
            retries: attempts after the first.
            pace_s: gap between segments (s).
            permit: see :meth:`push_profile`.
        """
        return await self.push_profile(pack_tables(tables), version, timeout_s=timeout_s,
                                       retries=retries, pace_s=pace_s, permit=permit)

    async def _await_ack(
        self, acks: Subscription, version: int, deadline: float
    ) -> ProfileAck | None:
        loop = asyncio.get_running_loop()
        while True:
            remaining = deadline - loop.time()
            if remaining <= 0:
                return None
            try:
                # asyncio.timeout: 3.11's wait_for can swallow a cancellation of the push.
                async with asyncio.timeout(remaining):
                    ack = await acks.get()
            except TimeoutError:
                return None
            if ack.version == version:  # always: only accepted answers are queued
                return ack
