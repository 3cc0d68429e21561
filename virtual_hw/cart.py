"""The virtual metabolic cart: the simulated wearer's breaths over serial, TCP or UDP.

A :class:`VirtualCart` stands in for a breath-by-breath gas analyser. It asks the simulated
wearer (a :class:`~virtual_hw.wearer.Wearer`, realistic or legacy:
:func:`~virtual_hw.wearer.make_wearer`) for every breath at that breath's simulated time and
writes it in one of the wire formats of ``drivers/cart/FORMAT.md`` — our hilbo-line (with a
sequence number and CRC-16) or a vendor-like CSV (:data:`VIRTUAL_CSV_MAPPING`) — over

* **serial**: a pseudo-terminal it creates (``os.openpty``). The bridge opens it with pyserial
  through a *stable symlink* (:attr:`VirtualCart.serial_path`, e.g.
  ``/tmp/hilbo-vcart-k2j/cart.tty``) that the cart re-points to a fresh pty after a simulated
  unplug, like a udev ``/dev/serial/by-id`` link when a USB adapter re-enumerates. A pty has
  no notion of a connection, so "a client is attached" means "someone has the slave open"
  (Linux reports ``POLLHUP`` on the master otherwise); lines written with nobody attached are
  lost, as from a real cart talking to an unplugged cable.
* **TCP**: a server on ``host`` (default 127.0.0.1; port 0 picks a free port, see
  :attr:`VirtualCart.port`) sending every line to every connected client, at most
  ``max_clients`` of them; a client that falls ``max_buffer_bytes`` behind or does not drain
  within ``drain_timeout_s`` is dropped so one stuck reader cannot stall the cart.
* **UDP**: one datagram per line to ``host:port`` (the bridge's receiving socket).

**Timing.** The cart wakes on a grid of ``emit_period_s`` simulated seconds (and at every fault
boundary) and writes each breath that has ended by then, so a breath reaches the wire at most
``emit_period_s`` after its time (real carts, too, report a breath after it ends). The records
carry the wearer's exact breath times. The grid is the same at every clock speed, so the order
of events is too.

**Assistance.** The wearer feels what the exosuit *applies*, not what the bridge intended:
:meth:`VirtualCart.on_profile_applied` is called by the virtual exosuit in-process (or by a
listener for the exosuit's applied-profile status on CAN), so a lost or refused profile shows
up in the metabolic data as it would in a lab.

**Faults** (:data:`CART_FAULTS`; syntax in :mod:`virtual_hw.faults`), all in simulated seconds:

=================  ======  ============================================================
``disconnect``     window  the link goes down: TCP clients are closed and the port stops
                           listening, the pty is closed (its symlink removed), UDP datagrams
                           are not sent. Breaths keep being measured and numbered, so a
                           reader sees the gap as missing sequence numbers; TCP and serial
                           clients must reconnect when the link is back.
``stall``          window  the analyser stalls: breaths ending in the window are never
                           reported (no sequence number used); later ones carry their
                           correct times, so a reader sees a time gap without missing seqs.
``garbage``        events  a line of random bytes before the breath (a ``garbage`` reject).
``duplicate``      events  the breath's line is sent twice (a ``duplicate`` reject).
``out-of-order``   events  the breath is held back and sent after the next one (an
                           ``out_of_order`` reject of the held breath).
``nan``            events  the breath is reported with VO2 and VCO2 NaN (well formed, valid
                           CRC: a ``non_finite`` reject).
``malformed``      events  the breath's line is corrupted: a digit of VO2 changed after the
                           CRC was computed (``bad_checksum``), or for CSV the row cut after
                           the time (``field_count``).
=================  ======  ============================================================

Window faults are judged at the cart's tick (``disconnect``) or at the breath's time
(``stall``); events faults hit the first COUNT breaths whose time is at or after START, or every
breath in ``+DURATION``. Every breath the wearer produced is recorded in
:attr:`VirtualCart.history` with its :class:`BreathFate` and the number of clients it reached,
so a test can check exactly what a reader should have accepted.

Use::

    clock = VirtualClock()
    cart = VirtualCart(wearer, clock, link=CartLink(LinkKind.TCP), end_s=3600)
    async with cart:
        config = cart.client_config()        # drivers.cart.CartConfig for the reader
        ...                                  # the bridge reads; the exosuit calls on_profile_applied
        await cart.wait()                    # until end_s (raises if the cart failed)
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import logging
import math
import os
import select
import shutil
import struct
import tempfile
from abc import ABC, abstractmethod
from collections import Counter, deque
from collections.abc import Callable, Coroutine, Iterable, Sequence
from dataclasses import dataclass
from enum import StrEnum
from pathlib import Path
from types import TracebackType
from typing import Any, Self

import numpy as np

from drivers.cart import (
    CartConfig,
    CartFormat,
    CsvMapping,
    SerialOptions,
    TcpOptions,
    TimeFormat,
    UdpOptions,
    encode_csv_header,
    encode_csv_row,
    encode_line,
)
from drivers.cart.validate import SEQ_MODULUS
from hilbo_core.profiles import ForceProfile
from hilbo_core.types import BreathRecord
from virtual_hw.clock import Participant, SimClock
from virtual_hw.errors import ClockError, VirtualConfigError
from virtual_hw.faults import FaultCatalog, FaultKind, FaultSchedule, FaultShape, FaultSpec
from virtual_hw.wearer import Wearer

__all__ = [
    "CART_FAULTS",
    "VIRTUAL_CSV_MAPPING",
    "BreathFate",
    "CartFault",
    "CartLink",
    "EmittedBreath",
    "LinkKind",
    "VirtualCart",
]

_log = logging.getLogger(__name__)

# A pty client that appears (open(2) clears POLLHUP) is not ready yet: pyserial's open() then
# configures the port (tcsetattr) and flushes its input queue (tcflush), eating any line written
# in between. The cart marks a fresh pty with a sentinel speed (B50) and waits until the opener
# has set its own (Linux reports the slave's termios on the master); where the master can be put
# in packet mode (TIOCPKT, Linux) it then waits for the opener's flush itself, which the master
# reads as a TIOCPKT_FLUSHREAD packet, so a reader descheduled between the two calls loses
# nothing. Without packet mode, or for a reader that never flushes, it writes _PTY_ATTACH_GRACE_S
# after the speed changed, or after _CLOSE_TIMEOUT_S. Lines are delayed, never lost.
_PTY_ATTACH_GRACE_S = 0.02
_PTY_POLL_S = 0.01  # wall period of "is anyone attached yet?" while waiting for a client
_PTY_EMPTY_POLLS = 3  # empty looks at the reader's queue, _PTY_POLL_S apart, before a close
_CLOSE_TIMEOUT_S = 1.0  # wall bound on a graceful TCP close before aborting


class CartFault(StrEnum):
    """The faults the virtual cart can inject (module docstring)."""

    DISCONNECT = "disconnect"
    STALL = "stall"
    GARBAGE = "garbage"
    DUPLICATE = "duplicate"
    OUT_OF_ORDER = "out-of-order"
    NAN = "nan"
    MALFORMED = "malformed"


CART_FAULTS = FaultCatalog(
    "virtual cart",
    (
        FaultKind(CartFault.DISCONNECT.value, FaultShape.WINDOW,
                  "link down (TCP/serial clients closed and must reconnect; UDP not sent)"),
        FaultKind(CartFault.STALL.value, FaultShape.WINDOW,
                  "no breaths reported, then later breaths with correct times"),
        FaultKind(CartFault.GARBAGE.value, FaultShape.EVENTS, "a line of random bytes before a breath"),
        FaultKind(CartFault.DUPLICATE.value, FaultShape.EVENTS, "a breath sent twice"),
        FaultKind(CartFault.OUT_OF_ORDER.value, FaultShape.EVENTS, "a breath sent after the next one"),
        FaultKind(CartFault.NAN.value, FaultShape.EVENTS, "a breath reported with NaN VO2/VCO2"),
        FaultKind(CartFault.MALFORMED.value, FaultShape.EVENTS,
                  "a corrupted line (bad checksum; CSV: row cut short)"),
    ),
)
"""The virtual cart's fault catalog (``--fault`` specs are parsed against it)."""

VIRTUAL_CSV_MAPPING = CsvMapping(
    time_column="t",
    time_format=TimeFormat.HMS,
    vo2_column="VO2",
    vco2_column="VCO2",
    ve_column="VE",
    rer_column="R",
    hr_column="HR",
)
"""The vendor-like CSV the virtual cart writes with ``fmt="csv"`` (COSMED-style names, clock
time ``h:mm:ss.ffffff``, gases in ml/min). The reader's ``[cart.csv]`` table must match it::

    [cart.csv]
    time_column = "t"
    time_format = "hh:mm:ss"
    vo2_column = "VO2"
    vco2_column = "VCO2"
    ve_column = "VE"
    rer_column = "R"
    hr_column = "HR"
"""


class LinkKind(StrEnum):
    """How the cart talks to the bridge."""

    SERIAL = "serial"
    TCP = "tcp"
    UDP = "udp"


@dataclass(frozen=True)
class CartLink:
    """Where the virtual cart writes its lines.

    Attributes:
        kind: :class:`LinkKind`.
        host: TCP: address to listen on; UDP: address to send to. Unused for serial.
        port: TCP: port to listen on (0 = any free port); UDP: destination port (required).
        max_clients: TCP: connections served at once; more are closed at once.
        max_buffer_bytes: TCP: a client with more unsent bytes than this is dropped.
        drain_timeout_s: Wall seconds a TCP client or the pty may take to accept a line
            before it is dropped (TCP) or the line is (pty).
        csv_header_every: UDP + CSV: repeat the header every this many lines, so a receiver
            that starts late learns the columns (the CSV parser skips repeated headers).

    Raises:
        VirtualConfigError: A bad value, named.
    """

    kind: LinkKind = LinkKind.TCP
    host: str = "127.0.0.1"
    port: int = 0
    max_clients: int = 8
    max_buffer_bytes: int = 1 << 20
    drain_timeout_s: float = 5.0
    csv_header_every: int = 32

    def __post_init__(self) -> None:
        try:
            object.__setattr__(self, "kind", LinkKind(self.kind))
        except ValueError as err:
            raise VirtualConfigError(
                f"link kind {self.kind!r}: expected one of {[k.value for k in LinkKind]}"
            ) from err
        if not isinstance(self.host, str) or not self.host:
            raise VirtualConfigError(f"host={self.host!r}: expected an address such as '127.0.0.1'")
        lo = 1 if self.kind is LinkKind.UDP else 0
        if isinstance(self.port, bool) or not isinstance(self.port, int) or not lo <= self.port <= 65535:
            raise VirtualConfigError(
                f"port={self.port!r}: expected an integer in [{lo}, 65535]"
                + (" (UDP needs the receiver's port)" if self.kind is LinkKind.UDP else "")
            )
        for name in ("max_clients", "max_buffer_bytes", "csv_header_every"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise VirtualConfigError(f"{name}={value!r}: expected an integer >= 1")
        d = self.drain_timeout_s
        if isinstance(d, bool) or not isinstance(d, int | float) or not (math.isfinite(d) and d > 0):
            raise VirtualConfigError(f"drain_timeout_s={d!r}: expected a finite number of seconds > 0")


class BreathFate(StrEnum):
    """What happened to one breath of the wearer on its way out of the cart."""

    SENT = "sent"
    """Written once, intact."""
    DUPLICATED = "duplicated"
    """Written intact, then once more (the copy is a ``duplicate`` reject)."""
    REORDERED = "reordered"
    """Written intact but after the next breath (an ``out_of_order`` reject)."""
    NAN = "nan"
    """Written with NaN gases (a ``non_finite`` reject)."""
    MALFORMED = "malformed"
    """Written corrupted (``bad_checksum``, or ``field_count`` for CSV)."""
    STALLED = "stalled"
    """Never written: the analyser stalled (no sequence number used)."""


_READABLE_FATES = frozenset({BreathFate.SENT, BreathFate.DUPLICATED})


@dataclass(frozen=True)
class EmittedBreath:
    """One breath of the wearer and what the cart did with it (:attr:`VirtualCart.history`).

    Attributes:
        record: The breath as the wearer breathed it (the true values).
        seq: The hilbo-line sequence number it used, or None when it was never written.
        fate: :class:`BreathFate`.
        clients: How many clients its line reached (0: lost — link down, nobody connected).
        t_sent_s: Simulated time at which it was written (or dropped).
    """

    record: BreathRecord
    seq: int | None
    fate: BreathFate
    clients: int
    t_sent_s: float

    @property
    def readable(self) -> bool:
        """True when a connected reader must accept this breath (intact and delivered)."""
        return self.fate in _READABLE_FATES and self.clients > 0


Spawn = Callable[[Coroutine[Any, Any, None], str], "asyncio.Task[None]"]


# ------------------------------------------------------------------------------- endpoints
class _Endpoint(ABC):
    """One link kind: open/close, down/up for the disconnect fault, and sending lines."""

    def __init__(self, link: CartLink, greeting: bytes | None, spawn: Spawn, stats: Counter[str]) -> None:
        self.link = link
        self.greeting = greeting
        self._spawn = spawn
        self.stats = stats
        self.up = False

    @abstractmethod
    async def open(self) -> None:
        """Create the link (bind, listen, make the pty)."""

    @abstractmethod
    async def close(self) -> None:
        """Release everything; idempotent."""

    @abstractmethod
    async def take_down(self) -> None:
        """Disconnect fault begins."""

    @abstractmethod
    async def bring_up(self) -> None:
        """Disconnect fault ends."""

    @abstractmethod
    async def send(self, data: bytes) -> int:
        """Write one line (or a garbage line) to every client; return how many it reached."""

    @abstractmethod
    async def wait_for_client(self) -> None:
        """Return once a client is attached (at once for UDP)."""

    @abstractmethod
    def address_line(self) -> str:
        """The machine-readable address, e.g. ``tcp 127.0.0.1 40123``."""


class _TcpServer(_Endpoint):
    def __init__(self, link: CartLink, greeting: bytes | None, spawn: Spawn, stats: Counter[str]) -> None:
        super().__init__(link, greeting, spawn, stats)
        self._server: asyncio.Server | None = None
        self._clients: list[asyncio.StreamWriter] = []
        self._has_client = asyncio.Event()
        self.port = link.port

    async def open(self) -> None:
        await self._listen()

    async def _listen(self) -> None:
        # The same port after a disconnect fault (SO_REUSEADDR is asyncio's default on POSIX).
        self._server = await asyncio.start_server(self._on_connect, self.link.host, self.port)
        self.port = int(self._server.sockets[0].getsockname()[1])
        self.up = True

    def _on_connect(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        peer = writer.get_extra_info("peername")
        if not self.up or len(self._clients) >= self.link.max_clients:
            self.stats["clients_refused"] += 1
            _log.warning("virtual cart: refusing TCP client %s (%d connected, max %d)",
                         peer, len(self._clients), self.link.max_clients)
            writer.transport.abort()
            return
        self._clients.append(writer)
        self.stats["clients_accepted"] += 1
        self._has_client.set()
        _log.info("virtual cart: TCP client %s connected", peer)
        if self.greeting is not None:
            writer.write(self.greeting)
        self._spawn(self._watch(reader, writer), f"virtual-cart tcp client {peer}")

    async def _watch(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        """Notice a client that hangs up; whatever it sends is read and ignored."""
        try:
            while await reader.read(4096):
                pass
        except OSError as err:
            _log.info("virtual cart: TCP client read ended: %s", err)
        finally:
            self._forget(writer)

    def _forget(self, writer: asyncio.StreamWriter, *, abort: bool = False) -> None:
        if writer in self._clients:
            self._clients.remove(writer)
            self.stats["clients_gone"] += 1
        if not self._clients:
            self._has_client.clear()
        if abort:
            writer.transport.abort()
        elif not writer.is_closing():
            writer.close()

    async def send(self, data: bytes) -> int:
        if not self.up:
            return 0
        reached: list[asyncio.StreamWriter] = []
        for writer in list(self._clients):
            if writer.is_closing():
                self._forget(writer)
                continue
            writer.write(data)
            if writer.transport.get_write_buffer_size() > self.link.max_buffer_bytes:
                self.stats["clients_too_slow"] += 1
                _log.warning("virtual cart: dropping a TCP client %d bytes behind",
                             writer.transport.get_write_buffer_size())
                self._forget(writer, abort=True)
                continue
            reached.append(writer)
        for writer in reached:
            try:
                async with asyncio.timeout(self.link.drain_timeout_s):
                    await writer.drain()
            except (TimeoutError, OSError) as err:
                self.stats["clients_too_slow"] += 1
                _log.warning("virtual cart: dropping a TCP client that does not drain: %r", err)
                self._forget(writer, abort=True)
        return len(reached)

    async def wait_for_client(self) -> None:
        await self._has_client.wait()

    async def take_down(self) -> None:
        self.up = False
        server, self._server = self._server, None
        if server is not None:
            server.close()
        clients, self._clients = self._clients, []
        self._has_client.clear()
        for writer in clients:
            writer.close()  # a graceful close: lines already written still arrive
        for writer in clients:
            try:
                async with asyncio.timeout(_CLOSE_TIMEOUT_S):
                    await writer.wait_closed()
            except (TimeoutError, OSError) as err:
                _log.debug("virtual cart: TCP close: %r", err)
                writer.transport.abort()
        if server is not None:
            await server.wait_closed()

    async def bring_up(self) -> None:
        await self._listen()

    async def close(self) -> None:
        await self.take_down()

    def address_line(self) -> str:
        return f"tcp {self.link.host} {self.port}"


class _UdpProtocol(asyncio.DatagramProtocol):
    def __init__(self, stats: Counter[str]) -> None:
        self.stats = stats

    def error_received(self, exc: Exception) -> None:
        # ICMP "port unreachable" while the receiver is not bound: like sending into the void.
        self.stats["udp_errors"] += 1
        _log.debug("virtual cart: UDP send error: %s", exc)


class _UdpSender(_Endpoint):
    def __init__(self, link: CartLink, greeting: bytes | None, spawn: Spawn, stats: Counter[str]) -> None:
        super().__init__(link, greeting, spawn, stats)
        self._transport: asyncio.DatagramTransport | None = None
        self._since_header = 0

    async def open(self) -> None:
        loop = asyncio.get_running_loop()
        self._transport, _ = await loop.create_datagram_endpoint(
            lambda: _UdpProtocol(self.stats), remote_addr=(self.link.host, self.link.port)
        )
        self.up = True

    async def send(self, data: bytes) -> int:
        if not self.up or self._transport is None:
            return 0
        if self.greeting is not None:
            if self._since_header == 0:
                self._transport.sendto(self.greeting)
            self._since_header = (self._since_header + 1) % self.link.csv_header_every
        self._transport.sendto(data)
        return 1

    async def wait_for_client(self) -> None:
        return None  # datagrams have no connection to wait for

    async def take_down(self) -> None:
        self.up = False

    async def bring_up(self) -> None:
        self.up = True
        self._since_header = 0

    async def close(self) -> None:
        self.up = False
        transport, self._transport = self._transport, None
        if transport is not None:
            transport.close()

    def address_line(self) -> str:
        return f"udp {self.link.host} {self.link.port}"


class _PtyEndpoint(_Endpoint):
    def __init__(self, link: CartLink, greeting: bytes | None, spawn: Spawn, stats: Counter[str]) -> None:
        super().__init__(link, greeting, spawn, stats)
        if not hasattr(os, "openpty"):
            raise VirtualConfigError("the serial virtual cart needs POSIX pseudo-terminals (os.openpty)")
        self._dir: Path | None = None
        self._master: int | None = None
        self._attached = False
        self._packet_mode = False
        self.device = ""

    @property
    def path(self) -> Path:
        if self._dir is None:
            raise VirtualConfigError("the serial virtual cart is not open yet: no device path")
        return self._dir / "cart.tty"

    async def open(self) -> None:
        self._dir = Path(tempfile.mkdtemp(prefix="hilbo-vcart-"))
        self._new_pty()

    def _new_pty(self) -> None:
        import tty  # POSIX only, like os.openpty

        master, slave = os.openpty()
        try:
            tty.setraw(slave)  # no echo, no CR/LF translation, even for a reader that sets nothing
            self.device = os.ttyname(slave)
        finally:
            os.close(slave)  # nobody holds the slave: POLLHUP on the master until a client opens it
        _set_sentinel_speed(master)
        os.set_blocking(master, False)
        self._packet_mode = _set_packet_mode(master)
        self._master = master
        self._attached = False
        tmp = self.path.with_suffix(".new")
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
        tmp.symlink_to(self.device)
        tmp.replace(self.path)  # atomic re-point: a reader never sees a missing link here
        self.up = True
        _log.info("virtual cart: serial on %s -> %s", self.path, self.device)

    def _poll_attached(self) -> bool:
        if self._master is None:
            return False
        poller = select.poll()
        poller.register(self._master, select.POLLOUT | select.POLLHUP)
        events = poller.poll(0)
        return bool(events) and not events[0][1] & select.POLLHUP

    async def send(self, data: bytes) -> int:
        if not self.up or not self._poll_attached():
            if self._attached:
                self.stats["clients_gone"] += 1
                if self._master is not None:
                    _set_sentinel_speed(self._master)  # the next opener must configure it again
                    _take_packets(self._master)  # the gone client's: not the next opener's flush
            self._attached = False
            return 0
        if not self._attached:
            self._attached = True
            self.stats["clients_accepted"] += 1
            await self._wait_configured()
            if self.greeting is not None:
                await self._write(self.greeting)
        return 1 if await self._write(data) else 0

    async def _wait_configured(self) -> None:
        loop = asyncio.get_running_loop()
        deadline = loop.time() + _CLOSE_TIMEOUT_S
        while self._master is not None and _has_sentinel_speed(self._master) and loop.time() < deadline:
            await asyncio.sleep(_PTY_POLL_S / 2)
        if not self._packet_mode:
            await asyncio.sleep(_PTY_ATTACH_GRACE_S)
            return
        while self._master is not None and loop.time() < deadline:
            if _take_packets(self._master) & _TIOCPKT_FLUSHREAD:
                return
            await asyncio.sleep(_PTY_POLL_S / 2)

    async def _write(self, data: bytes) -> bool:
        view = memoryview(data)
        loop = asyncio.get_running_loop()
        while view:
            master = self._master
            if master is None:
                return False
            try:
                n = os.write(master, view)
            except BlockingIOError:
                n = 0
            view = view[n:]
            if not view:
                return True
            # The reader is behind (the pty buffer is full): wait for room, boundedly.
            ready: asyncio.Future[None] = loop.create_future()
            loop.add_writer(master, lambda f=ready: f.done() or f.set_result(None))
            try:
                async with asyncio.timeout(self.link.drain_timeout_s):
                    await ready
            except TimeoutError:
                self.stats["lines_overrun"] += 1
                _log.warning("virtual cart: pty reader %.1f s behind; %d bytes dropped",
                             self.link.drain_timeout_s, len(view))
                return False
            finally:
                loop.remove_writer(master)
        return True

    async def wait_for_client(self) -> None:
        while not (self.up and self._poll_attached()):
            await asyncio.sleep(_PTY_POLL_S)

    async def _drain(self) -> None:
        """Wait (boundedly) until the reader has taken what was written.

        Closing the master discards what the slave has not read yet; a graceful disconnect
        (like the TCP close) lets lines already written arrive. The master cannot tell how much
        is queued, the slave can (FIONREAD), so peek through a second, non-reading slave fd.
        """
        if not self._attached or not self.device:
            return
        try:
            fd = os.open(self.device, os.O_RDONLY | os.O_NOCTTY | os.O_NONBLOCK)
        except OSError as err:
            _log.debug("virtual cart: cannot peek at the pty queue: %s", err)
            return
        try:
            loop = asyncio.get_running_loop()
            deadline = loop.time() + _CLOSE_TIMEOUT_S
            empty_polls = 0
            # Written bytes reach the slave's queue through the kernel's flip buffer a moment
            # later (a work queue), so one empty look is not enough: ask for a few in a row.
            while empty_polls < _PTY_EMPTY_POLLS and loop.time() < deadline:
                empty_polls = 0 if _queued_bytes(fd) else empty_polls + 1
                await asyncio.sleep(_PTY_POLL_S)
        finally:
            os.close(fd)

    async def take_down(self) -> None:
        await self._drain()
        self.up = False
        master, self._master = self._master, None
        if master is not None:
            os.close(master)  # the reader's next read fails: a pulled cable
        if self._dir is not None:
            with contextlib.suppress(FileNotFoundError):
                self.path.unlink()
        if self._attached:
            self.stats["clients_gone"] += 1
        self._attached = False

    async def bring_up(self) -> None:
        self._new_pty()

    async def close(self) -> None:
        await self.take_down()
        directory, self._dir = self._dir, None
        if directory is not None:
            shutil.rmtree(directory, ignore_errors=True)

    def address_line(self) -> str:
        return f"serial {self.path}"


_TIOCPKT_FLUSHREAD = 0x01  # <linux/tty.h>: the slave's input queue was flushed


def _set_packet_mode(master: int) -> bool:
    """Put a pty master in packet mode (TIOCPKT) where the platform has it; True if it is."""
    import fcntl
    import termios

    request = getattr(termios, "TIOCPKT", None)
    if request is None:
        return False
    try:
        fcntl.ioctl(master, request, struct.pack("i", 1))
    except OSError as err:
        _log.debug("virtual cart: no pty packet mode: %s", err)
        return False
    return True


def _take_packets(master: int) -> int:
    """Read every pending packet from a packet-mode pty master; their control bits, OR-ed."""
    bits = 0
    while True:
        try:
            packet = os.read(master, 4096)
        except (BlockingIOError, OSError):
            return bits
        if not packet:
            return bits
        bits |= packet[0]


def _set_sentinel_speed(fd: int) -> None:
    import termios

    attrs = termios.tcgetattr(fd)
    attrs[4] = attrs[5] = termios.B50
    termios.tcsetattr(fd, termios.TCSANOW, attrs)


def _has_sentinel_speed(fd: int) -> bool:
    import termios

    return bool(termios.tcgetattr(fd)[4] == termios.B50)


def _queued_bytes(fd: int) -> int:
    import fcntl
    import termios

    raw = fcntl.ioctl(fd, termios.FIONREAD, b"\0\0\0\0")
    return int(struct.unpack("i", raw)[0])


_ENDPOINTS: dict[LinkKind, type[_Endpoint]] = {
    LinkKind.TCP: _TcpServer,
    LinkKind.UDP: _UdpSender,
    LinkKind.SERIAL: _PtyEndpoint,
}


# ------------------------------------------------------------------------------- the cart
@dataclass
class _Held:
    record: BreathRecord
    seq: int
    line: bytes


class VirtualCart:
    """Serves a simulated wearer's breaths at their simulated times (module docstring).

    Args:
        wearer: The simulated wearer; the cart owns its breath clock from now on (call its
            ``apply_*`` only through :meth:`on_profile_applied`).
        clock: The simulated clock (:mod:`virtual_hw.clock`); the cart registers as a
            participant.
        link: Transport and address (:class:`CartLink`).
        fmt: ``"hilbo-line"`` or ``"csv"`` (:class:`drivers.cart.CartFormat`).
        csv_mapping: The CSV layout for ``fmt="csv"``; default :data:`VIRTUAL_CSV_MAPPING`.
        faults: Fault specs (:class:`~virtual_hw.faults.FaultSpec` or text such as
            ``"disconnect@120+10"``), checked against :data:`CART_FAULTS`.
        end_s: Simulated time at which the session ends (:meth:`wait` returns); None serves
            until stopped.
        emit_period_s: Tick of the cart in simulated seconds (> 0): the longest delay between
            a breath's time and its line.
        wait_for_client: On a :class:`~virtual_hw.clock.VirtualClock`, keep time at its start
            until the first client is attached (a standalone ``--speed max`` cart would
            otherwise serve the whole session to nobody). Ignored on a ScaledClock, whose time
            does not wait.
        fault_seed: Seeds the garbage bytes.
        history_size: Breaths kept in :attr:`history`.

    Raises:
        VirtualConfigError: A bad option, named; FaultSpecError for a bad fault spec.
    """

    def __init__(
        self,
        wearer: Wearer,
        clock: SimClock,
        *,
        link: CartLink | None = None,
        fmt: CartFormat | str = CartFormat.HILBO_LINE,
        csv_mapping: CsvMapping | None = None,
        faults: Iterable[FaultSpec | str] = (),
        end_s: float | None = None,
        emit_period_s: float = 0.5,
        wait_for_client: bool = False,
        fault_seed: int = 0,
        history_size: int = 100_000,
    ) -> None:
        self.wearer = wearer
        self.clock = clock
        self.link = link if link is not None else CartLink()
        if not isinstance(self.link, CartLink):
            raise VirtualConfigError(f"link={link!r}: expected a CartLink")
        try:
            self.format = CartFormat(fmt)
        except ValueError as err:
            raise VirtualConfigError(
                f"fmt={fmt!r}: expected one of {[f.value for f in CartFormat]}"
            ) from err
        if self.format is CartFormat.CSV:
            self.csv_mapping: CsvMapping | None = (
                csv_mapping if csv_mapping is not None else VIRTUAL_CSV_MAPPING
            )
        elif csv_mapping is not None:
            raise VirtualConfigError(f"csv_mapping given but fmt={self.format.value!r}; use fmt='csv'")
        else:
            self.csv_mapping = None
        if self.csv_mapping is not None and not isinstance(self.csv_mapping, CsvMapping):
            raise VirtualConfigError(f"csv_mapping={csv_mapping!r}: expected a drivers.cart.CsvMapping")
        self.faults = FaultSchedule(CART_FAULTS, faults)
        if end_s is not None and (
            isinstance(end_s, bool) or not isinstance(end_s, int | float) or not math.isfinite(end_s)
        ):
            raise VirtualConfigError(f"end_s={end_s!r}: expected a finite simulated time or None")
        self.end_s = None if end_s is None else float(end_s)
        if isinstance(emit_period_s, bool) or not isinstance(emit_period_s, int | float) or not (
            math.isfinite(emit_period_s) and emit_period_s > 0
        ):
            raise VirtualConfigError(f"emit_period_s={emit_period_s!r}: expected a finite period > 0 s")
        self.emit_period_s = float(emit_period_s)
        self.wait_for_client = bool(wait_for_client)
        if isinstance(history_size, bool) or not isinstance(history_size, int) or history_size < 1:
            raise VirtualConfigError(f"history_size={history_size!r}: expected an integer >= 1")
        self.history: deque[EmittedBreath] = deque(maxlen=history_size)
        #: The simulated time of the tick the cart sleeps until (None before it serves).
        self.next_tick_s: float | None = None
        self.stats: Counter[str] = Counter()
        self._rng = np.random.default_rng(fault_seed)
        self._seq = 0
        self._pending: list[BreathRecord] = []
        self._held: _Held | None = None
        self._last_apply_s = 0.0
        self._tasks: set[asyncio.Task[None]] = set()
        self._serve_task: asyncio.Task[None] | None = None
        self._failure: BaseException | None = None
        self._me: Participant | None = None
        self._endpoint: _Endpoint | None = None
        self._started = False
        self._stopped = False

    # -- lifecycle ----------------------------------------------------------------------------

    async def start(self) -> None:
        """Open the link and start serving.

        Raises:
            OSError: The link cannot be created (port in use, no ptys).
            VirtualConfigError: Started twice.
        """
        if self._started:
            raise VirtualConfigError("this VirtualCart was already started; make a new one")
        self._started = True
        self._me = self.clock.participant("virtual-cart")
        endpoint = _ENDPOINTS[self.link.kind](self.link, self._greeting(), self._spawn, self.stats)
        try:
            await endpoint.open()
        except BaseException:
            self._me.close()
            await endpoint.close()
            raise
        self._endpoint = endpoint
        self._serve_task = self._spawn(self._serve(), "virtual-cart serve")

    async def stop(self) -> None:
        """Stop serving and close the link; idempotent.

        Raises:
            BaseException: The error a cart task failed with, if any.
        """
        await self._shutdown()
        if self._failure is not None:
            raise self._failure

    async def wait(self) -> None:
        """Wait until the session ends (``end_s``), or a cart task fails.

        Raises:
            VirtualConfigError: Not started.
            BaseException: The error a cart task failed with.
        """
        task = self._serve_task
        if task is None:
            raise VirtualConfigError("VirtualCart.wait() before start()")
        await asyncio.wait({task})
        if self._failure is not None:
            raise self._failure

    async def __aenter__(self) -> Self:
        await self.start()
        return self

    async def __aexit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        await self._shutdown()
        if exc is None and self._failure is not None:
            raise self._failure

    async def _shutdown(self) -> None:
        if self._stopped:
            return
        self._stopped = True
        tasks = list(self._tasks)
        for task in tasks:
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
        if self._endpoint is not None:
            await self._endpoint.close()
        if self._me is not None:
            self._me.close()

    def _spawn(self, coro: Coroutine[Any, Any, None], name: str) -> asyncio.Task[None]:
        task = asyncio.get_running_loop().create_task(coro, name=name)
        self._tasks.add(task)
        task.add_done_callback(self._task_done)
        return task

    def _task_done(self, task: asyncio.Task[None]) -> None:
        self._tasks.discard(task)
        if task.cancelled():
            return
        err = task.exception()
        if err is None:
            return
        _log.error("virtual cart task %r failed: %r", task.get_name(), err, exc_info=err)
        if self._failure is None:
            self._failure = err
        serve = self._serve_task
        if serve is not None and serve is not task and not serve.done():
            serve.cancel()  # so wait() returns and reports the failure

    # -- addresses ----------------------------------------------------------------------------

    def _started_endpoint(self) -> _Endpoint:
        if self._endpoint is None:
            raise VirtualConfigError("the VirtualCart is not started yet: no address")
        return self._endpoint

    @property
    def address(self) -> str:
        """One machine-readable line: ``serial PATH``, ``tcp HOST PORT`` or ``udp HOST PORT``."""
        return self._started_endpoint().address_line()

    @property
    def port(self) -> int:
        """The TCP port actually listened on, or the UDP destination port.

        Raises:
            VirtualConfigError: A serial cart, or not started.
        """
        ep = self._started_endpoint()
        if isinstance(ep, _TcpServer):
            return ep.port
        if isinstance(ep, _UdpSender):
            return self.link.port
        raise VirtualConfigError("a serial virtual cart has no port; use serial_path")

    @property
    def serial_path(self) -> str:
        """The stable symlink to the current pty slave (open this with pyserial).

        Raises:
            VirtualConfigError: Not a serial cart, or not started.
        """
        ep = self._started_endpoint()
        if not isinstance(ep, _PtyEndpoint):
            raise VirtualConfigError(f"a {self.link.kind.value} virtual cart has no serial path")
        return str(ep.path)

    def client_config(self, **options: Any) -> CartConfig:
        """The reader's :class:`drivers.cart.CartConfig` for this cart (after :meth:`start`).

        Args:
            **options: Extra fields of the transport's options dataclass (``backoff``,
                ``idle_timeout_s``, ``queue_size``, ...).
        """
        ep = self._started_endpoint()
        opts: Any
        if isinstance(ep, _TcpServer):
            opts = TcpOptions(host=self.link.host, port=ep.port, **options)
        elif isinstance(ep, _UdpSender):
            opts = UdpOptions(port=self.link.port, host=self.link.host, **options)
        else:
            opts = SerialOptions(port=self.serial_path, **options)
        return CartConfig(transport=self.link.kind.value, options=opts, format=self.format,
                          csv=self.csv_mapping)

    # -- assistance ---------------------------------------------------------------------------

    def on_profile_applied(self, profiles: Sequence[ForceProfile], t_sim: float | None = None) -> float:
        """The exosuit applies these force tables from ``t_sim`` on (None: now).

        Breaths up to ``t_sim`` are taken from the wearer first (they were breathed under the
        old assistance); a ``t_sim`` earlier than the last breath or change is moved up to it
        (a status message that arrives late cannot rewrite breaths already reported).

        Args:
            profiles: What the device applies (``()`` = assistance off).
            t_sim: Simulated time of the switch.

        Returns:
            The wearer's new steady-state cost in W.

        Raises:
            ClockError: ``t_sim`` is not finite.
            ConfigError: Bad profiles (from the wearer).
        """
        if t_sim is None:
            t = self.clock.now()
        else:
            if isinstance(t_sim, bool) or not isinstance(t_sim, int | float) or not math.isfinite(t_sim):
                raise ClockError(f"t_sim={t_sim!r}: expected a finite simulated time in s")
            t = float(t_sim)
        floor = max(self.wearer.t_s, self._last_apply_s, 0.0)
        if t < floor:
            _log.debug("virtual cart: profile applied at %.3f s moved up to %.3f s", t, floor)
            t = floor
        self._pending.extend(self.wearer.breaths_until(t))
        target = self.wearer.apply_profiles(profiles, t)
        self._last_apply_s = t
        self.stats["profiles_applied"] += 1
        return target

    # -- serving ------------------------------------------------------------------------------

    def _greeting(self) -> bytes | None:
        return None if self.csv_mapping is None else encode_csv_header(self.csv_mapping)

    def _next_tick(self, after_s: float) -> float:
        period = self.emit_period_s
        tick = (math.floor(after_s / period + 1e-9) + 1) * period
        boundary = self.faults.next_boundary(after_s)
        if boundary is not None:
            tick = min(tick, boundary)
        if self.end_s is not None and self.end_s > after_s:
            tick = min(tick, self.end_s)
        return tick

    async def _serve(self) -> None:
        me, endpoint = self._me, self._endpoint
        if me is None or endpoint is None:  # pragma: no cover - start() sets both first
            raise VirtualConfigError("VirtualCart served before start()")
        if self.wait_for_client and math.isinf(self.clock.speed):
            # Busy on purpose: time stays at its start until a reader is there.
            await endpoint.wait_for_client()
        start = self.clock.now()
        if start > self.wearer.t_s:
            # Joining a shared clock late (an --epoch in the past): a cart that was off did not
            # measure the breaths before now, so they are not reported at all.
            skipped = self.wearer.breaths_until(start)
            self.stats["breaths_before_start"] += len(skipped)
            if skipped:
                _log.info("virtual cart: started at %.1f s; %d earlier breaths not reported",
                          start, len(skipped))
        tick = self._next_tick(start)
        while self.end_s is None or tick <= self.end_s:
            self.next_tick_s = tick
            await me.sleep_until(tick)
            await self._step(tick)
            if self.end_s is not None and tick >= self.end_s:
                break
            tick = self._next_tick(max(tick, self.clock.now()))
        if self._held is not None:
            await self._release_held(tick, reordered=False)
        # The session is over: time must not wait for the cart any longer.
        me.close()
        _log.info("virtual cart: session over at %.1f s (%d breaths)", tick, len(self.history))

    async def _step(self, t: float) -> None:
        endpoint = self._endpoint
        if endpoint is None:  # pragma: no cover
            return
        down = self.faults.active(CartFault.DISCONNECT, t)
        if down and endpoint.up:
            _log.info("virtual cart: link down at %.1f s (fault)", t)
            self.stats["disconnects"] += 1
            await endpoint.take_down()
        elif not down and not endpoint.up:
            _log.info("virtual cart: link up again at %.1f s", t)
            await endpoint.bring_up()
        if t >= self.wearer.t_s:
            self._pending.extend(self.wearer.breaths_until(t))
        due = [b for b in self._pending if b.t_s <= t]
        self._pending = [b for b in self._pending if b.t_s > t]
        for record in due:
            await self._emit(record, t)

    def _encode(self, record: BreathRecord, seq: int) -> bytes:
        if self.csv_mapping is not None:
            return encode_csv_row(self.csv_mapping, record)
        return encode_line(record, seq)

    def _record(
        self, record: BreathRecord, seq: int | None, fate: BreathFate, clients: int, t: float
    ) -> None:
        self.history.append(EmittedBreath(record, seq, fate, clients, t))
        self.stats[f"breaths_{fate.value}"] += 1
        if fate is not BreathFate.STALLED and clients == 0:
            self.stats["breaths_undelivered"] += 1

    async def _emit(self, record: BreathRecord, t: float) -> None:
        faults = self.faults
        if faults.active(CartFault.STALL, record.t_s):
            self._record(record, None, BreathFate.STALLED, 0, t)
            return
        endpoint = self._endpoint
        if endpoint is None:  # pragma: no cover
            return
        seq = self._seq
        self._seq = (seq + 1) % SEQ_MODULUS
        if faults.take(CartFault.GARBAGE, record.t_s):
            await endpoint.send(self._garbage())
            self.stats["garbage_lines"] += 1
        fate = BreathFate.SENT
        if faults.take(CartFault.NAN, record.t_s):
            fate = BreathFate.NAN
            line = self._encode(dataclasses.replace(record, vo2_ml_min=math.nan, vco2_ml_min=math.nan), seq)
        elif faults.take(CartFault.MALFORMED, record.t_s):
            fate = BreathFate.MALFORMED
            line = self._corrupt(self._encode(record, seq))
        else:
            line = self._encode(record, seq)
        if fate is BreathFate.SENT and self._held is None and faults.take(CartFault.OUT_OF_ORDER, record.t_s):
            self._held = _Held(record, seq, line)  # goes out after the next intact breath
            return
        copies = 1
        if fate is BreathFate.SENT and faults.take(CartFault.DUPLICATE, record.t_s):
            fate, copies = BreathFate.DUPLICATED, 2
        clients = await endpoint.send(line)
        for _ in range(copies - 1):
            await endpoint.send(line)
        self._record(record, seq, fate, clients, t)
        if self._held is not None and fate in _READABLE_FATES and clients > 0:
            await self._release_held(t, reordered=True)

    async def _release_held(self, t: float, *, reordered: bool) -> None:
        held, self._held = self._held, None
        if held is None or self._endpoint is None:
            return
        clients = await self._endpoint.send(held.line)
        fate = BreathFate.REORDERED if reordered else BreathFate.SENT
        self._record(held.record, held.seq, fate, clients, t)

    def _garbage(self) -> bytes:
        # 0xFF never occurs in UTF-8 (so a CSV reader cannot decode it either) and is not '$':
        # the line is garbage to both parsers. No CR/LF inside, so it cannot eat a real line.
        n = int(self._rng.integers(8, 48))
        body = bytes(int(b) for b in self._rng.integers(0, 256, n) if b not in (0x0A, 0x0D))
        return b"\xff" + body + b"\r\n"

    def _corrupt(self, line: bytes) -> bytes:
        if self.csv_mapping is not None:
            # Keep only the time field: a row too short for the mapping (field_count).
            sep = self.csv_mapping.delimiter.encode(self.csv_mapping.encoding)
            first = line.rstrip(b"\r\n").split(sep)[0]
            return first + b"\r\n"
        # hilbo-line: change the first digit of VO2 after the CRC was computed (bad_checksum;
        # CRC-16 detects every single-byte error).
        fields = line.split(b",")
        vo2 = bytearray(fields[3])
        for i, c in enumerate(vo2):
            if 0x30 <= c <= 0x39:
                vo2[i] = 0x30 + (c - 0x30 + 1) % 10
                break
        fields[3] = bytes(vo2)
        return b",".join(fields)
