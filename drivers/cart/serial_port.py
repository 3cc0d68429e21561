"""Serial-port transport (RS-232 / USB-serial carts) on pyserial.

Why blocking reads in a worker thread (``loop.run_in_executor``) and not ``loop.add_reader`` on
the port's file descriptor: ``add_reader`` does not exist on Windows' default Proactor event loop
(and a Windows lab PC is a supported set-up), pyserial's Windows and URL back-ends
(``rfc2217://``, ``socket://``) have no selectable descriptor at all, and on POSIX an unplugged
USB adapter shows up as a descriptor that is "readable" forever, which pyserial's own ``read``
already turns into a clean ``SerialException``. A read with a short ``timeout`` returns at least
every ``read_timeout_s``, so closing never waits long on the thread; one in-flight read is
kept across cancellations (the idle watchdog, a cancelled task) and never doubled, so two threads
never read the same port.
"""

from __future__ import annotations

import asyncio
import logging
from dataclasses import dataclass, field
from typing import Annotated

import serial
from msgspec import Meta

from drivers.cart._options import check_declared
from drivers.cart.framing import DEFAULT_MAX_LINE_BYTES
from drivers.cart.transport import Backoff, CartTransport, TransportHooks
from drivers.config_model import FINITE
from drivers.errors import DriverConfigError

__all__ = ["SerialOptions", "SerialTransport"]

_log = logging.getLogger(__name__)

_PARITIES = {
    "N": serial.PARITY_NONE,
    "E": serial.PARITY_EVEN,
    "O": serial.PARITY_ODD,
    "M": serial.PARITY_MARK,
    "S": serial.PARITY_SPACE,
}


@dataclass(frozen=True, slots=True)
class SerialOptions:
    """Options of the ``"serial"`` transport (``[cart.options]`` in the config).

    Attributes:
        port: Device path (``/dev/ttyUSB0``, a udev symlink such as
            ``/dev/serial/by-id/...``, ``COM3``) or a pyserial URL (``rfc2217://host:port``
            for a serial-over-Ethernet server).
        baudrate: Bits per second.
        bytesize: Data bits, 5–8.
        parity: ``"N"``, ``"E"``, ``"O"``, ``"M"`` or ``"S"``.
        stopbits: 1, 1.5 or 2.
        read_timeout_s: Longest a blocking read waits before checking for close (latency of
            closing, not of data: bytes are returned as soon as they arrive).
        idle_timeout_s: Reopen the port after this long without a byte; None disables.
        max_line_bytes: Longest line kept.
        backoff: Reconnection policy after an unplug.
    """

    port: Annotated[str, Meta(min_length=1)]
    baudrate: Annotated[int, Meta(ge=50, le=20_000_000)] = 9600
    bytesize: Annotated[int, Meta(ge=5, le=8)] = 8
    parity: str = "N"
    stopbits: float = 1
    read_timeout_s: Annotated[float, Meta(gt=0.0, le=10.0)] = 0.1
    idle_timeout_s: Annotated[float, Meta(gt=0.0, le=FINITE)] | None = None
    max_line_bytes: Annotated[int, Meta(ge=16)] = DEFAULT_MAX_LINE_BYTES
    backoff: Backoff = field(default_factory=Backoff)

    def __post_init__(self) -> None:
        check_declared(self)
        # parity and stopbits: a set of letters, a set of numbers (not ranges): checked here.
        if self.parity not in _PARITIES:
            raise DriverConfigError(
                f"parity = {self.parity!r}: expected one of {', '.join(map(repr, _PARITIES))}"
            )
        if self.stopbits not in (1, 1.5, 2) or isinstance(self.stopbits, bool):
            raise DriverConfigError(f"stopbits = {self.stopbits!r}: expected 1, 1.5 or 2")
        if not isinstance(self.backoff, Backoff):
            raise DriverConfigError(f"backoff = {self.backoff!r}: expected a Backoff table")


def _read_available(port: serial.SerialBase) -> bytes:
    """Blocking: wait up to the port's timeout for one byte, then take whatever else is there."""
    first = port.read(1)
    if not first:
        return b""
    waiting = port.in_waiting
    return first + port.read(waiting) if waiting else first


class SerialTransport(CartTransport):
    """Lines from a serial port; reopens the port with backoff after an unplug."""

    name = "serial"

    def __init__(self, options: SerialOptions, hooks: TransportHooks | None = None) -> None:
        super().__init__(
            max_line_bytes=options.max_line_bytes,
            backoff=options.backoff,
            idle_timeout_s=options.idle_timeout_s,
            hooks=hooks,
        )
        self.options = options
        self._port: serial.SerialBase | None = None
        self._pending: asyncio.Future[bytes] | None = None

    def describe(self) -> str:
        o = self.options
        return f"serial {o.port} {o.baudrate} {o.bytesize}{o.parity}{o.stopbits:g}"

    def _open_blocking(self) -> serial.SerialBase:
        o = self.options
        return serial.serial_for_url(
            o.port,
            baudrate=o.baudrate,
            bytesize=o.bytesize,
            parity=_PARITIES[o.parity],
            stopbits=o.stopbits,
            timeout=o.read_timeout_s,
        )

    async def _open_link(self) -> None:
        loop = asyncio.get_running_loop()
        # Opening can block (USB enumeration, rfc2217 negotiation): keep it off the loop.
        self._port = await loop.run_in_executor(None, self._open_blocking)

    async def _read_chunk(self) -> bytes | None:
        loop = asyncio.get_running_loop()
        while True:
            port = self._port
            if port is None:
                raise ConnectionResetError("serial port is closed")
            if self._pending is None:
                self._pending = loop.run_in_executor(None, _read_available, port)
            fut = self._pending
            try:
                # shield: a cancelled await (watchdog, task cancel) leaves the thread's read
                # running; it is picked up by the next read or awaited by _close_link.
                chunk = await asyncio.shield(fut)
            finally:
                if fut.done():
                    self._pending = None
            if chunk:
                return chunk

    async def _close_link(self) -> None:
        pending, self._pending = self._pending, None
        if pending is not None:
            try:
                await pending  # returns within read_timeout_s
            except OSError as err:
                _log.debug("serial read ended with %s while closing", err)
        port, self._port = self._port, None
        if port is not None:
            port.close()
