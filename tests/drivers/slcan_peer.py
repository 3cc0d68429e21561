"""TEST SCAFFOLDING: a pretend USB slcan adapter on a pseudo-terminal.

The endpoint under test opens the pty's slave path with python-can's ``slcan`` interface exactly
as it would open ``/dev/ttyACM0``; this peer speaks the adapter side of the slcan (Lawicel) ASCII
protocol on the master end and bridges the frames to a python-can ``virtual`` channel, where the
test's responder sits:

    CanEndpoint(slcan, /dev/pts/N) ⇄ pty ⇄ SlcanPtyPeer ⇄ virtual channel ⇄ Responder

Handled: ``tiiildd..`` / ``Tiiiiiiiildd..`` frames (answered ``z``/``Z`` like a real adapter),
``O``/``L``/``C``/``Sn``/``sxxyy`` (answered CR), ``V``/``N``/``F`` queries; anything else BEL.
"""

from __future__ import annotations

import errno
import os
import select
import threading
import tty

import can

__all__ = ["SlcanPtyPeer", "slcan_line"]


def slcan_line(msg: can.Message) -> bytes:
    """The slcan ASCII line an adapter sends for a received frame."""
    if msg.is_extended_id:
        head = f"T{msg.arbitration_id:08X}{len(msg.data):d}"
    else:
        head = f"t{msg.arbitration_id:03X}{len(msg.data):d}"
    return (head + bytes(msg.data).hex().upper() + "\r").encode()


class SlcanPtyPeer:
    """See the module docstring. Use as a context manager; ``path`` is the tty to open."""

    def __init__(self, virtual_channel: str) -> None:
        self.virtual_channel = virtual_channel
        self.master, self._slave = os.openpty()
        tty.setraw(self._slave)
        os.set_blocking(self.master, False)
        self.path = os.ttyname(self._slave)
        self.commands: list[str] = []
        self.dropped = 0
        self._stop = threading.Event()
        self._bus: can.BusABC | None = None
        self._notifier: can.Notifier | None = None
        self._thread: threading.Thread | None = None
        self._write_lock = threading.Lock()

    def __enter__(self) -> SlcanPtyPeer:
        self._bus = can.Bus(interface="virtual", channel=self.virtual_channel)
        self._notifier = can.Notifier(self._bus, [self._to_pty], timeout=0.05)
        self._thread = threading.Thread(target=self._from_pty, name="slcan-peer", daemon=True)
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout=2.0)
        if self._notifier is not None:
            self._notifier.stop()
        if self._bus is not None:
            self._bus.shutdown()
        os.close(self.master)
        os.close(self._slave)

    def _write(self, data: bytes) -> None:
        with self._write_lock:
            try:
                os.write(self.master, data)
            except BlockingIOError:
                self.dropped += 1  # nobody reads the tty (endpoint closed): drop, like a UART

    def _to_pty(self, msg: can.Message) -> None:
        self._write(slcan_line(msg))

    def _from_pty(self) -> None:
        buffer = b""
        while not self._stop.is_set():
            ready, _, _ = select.select([self.master], [], [], 0.05)
            if not ready:
                continue
            try:
                buffer += os.read(self.master, 4096)
            except BlockingIOError:
                continue
            except OSError as err:
                if err.errno == errno.EIO:  # no slave open right now
                    continue
                raise
            *lines, buffer = buffer.split(b"\r")
            for line in lines:
                self._command(line.decode("ascii", "replace"))

    def _command(self, line: str) -> None:
        self.commands.append(line)
        if not line:
            return
        kind = line[0]
        try:
            if kind in "tT":
                n_id = 3 if kind == "t" else 8
                arbitration_id = int(line[1:1 + n_id], 16)
                dlc = int(line[1 + n_id])
                data = bytes.fromhex(line[2 + n_id:2 + n_id + 2 * dlc])
                if len(data) != dlc:
                    raise ValueError(f"frame line {line!r} is short")
                if self._bus is None:
                    raise RuntimeError("peer not started")
                self._bus.send(can.Message(arbitration_id=arbitration_id, data=data,
                                           is_extended_id=kind == "T"))
                self._write(b"z\r" if kind == "t" else b"Z\r")
            elif kind in "OLCSs":
                self._write(b"\r")
            elif kind == "V":
                self._write(b"V1013\r")
            elif kind == "N":
                self._write(b"NHILB\r")
            elif kind == "F":
                self._write(b"F00\r")
            else:
                self._write(b"\a")
        except ValueError:
            self._write(b"\a")
