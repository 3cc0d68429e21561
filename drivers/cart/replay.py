"""Replay of a recorded cart file (hilbo-line recording or vendor CSV export) at a chosen speed.

The transport itself only reads the file's lines. Pacing is by *breath time*: a
:class:`~drivers.cart.stream.BreathStream` calls :meth:`ReplayTransport.pace` with the time of
every breath it accepts, and the transport waits until ``(t - t_first) / speed`` seconds after
the first breath. Pacing on validated times (not on whatever the line says) means one corrupted
time stamp cannot stall the replay for an hour. The schedule is anchored on the first breath, so
processing time does not accumulate as drift. ``speed = "max"`` never sleeps but still yields to
the event loop after every breath, so a fast replay cannot starve the bridge's other tasks; it is
paced by its reader (:attr:`ReplayTransport.paced_by_reader`: the bridge takes the next breath
once it is ready for it, so a file is not read to its end before the session starts).

Sleep and clock come from :class:`~drivers.cart.transport.TransportHooks`, so tests replay on a
simulated clock.
"""

from __future__ import annotations

import asyncio
import io
import math
from collections.abc import Callable
from dataclasses import dataclass
from os import PathLike, fspath
from typing import Annotated, BinaryIO

from msgspec import Meta

from drivers.cart._options import check_declared, number, text
from drivers.cart.framing import DEFAULT_MAX_LINE_BYTES
from drivers.cart.transport import CartTransport, TransportHooks
from drivers.errors import DriverConfigError
from drivers.files import MAX_CART_FILE_BYTES, open_regular_file

__all__ = ["ReplayOptions", "ReplayTransport"]

_READ_BYTES = 1 << 16


@dataclass(frozen=True, slots=True)
class ReplayOptions:
    """Options of the ``"replay"`` transport.

    Attributes:
        path: The recorded file.
        speed: Playback speed factor (> 0; 1 = real time, 10 = ten times faster) or ``"max"``
            (as fast as possible). Stored as a float, ``math.inf`` for ``"max"``.
        max_line_bytes: Longest line kept.
    """

    path: str
    speed: float = 1.0
    max_line_bytes: Annotated[int, Meta(ge=16)] = DEFAULT_MAX_LINE_BYTES

    def __post_init__(self) -> None:
        # path (a str or a PathLike) and speed (a number or "max") are not one type: checked here.
        if isinstance(self.path, PathLike):
            object.__setattr__(self, "path", fspath(self.path))
        text(self.path, "path")
        speed: object = self.speed
        if speed == "max" or (isinstance(speed, float) and speed == math.inf):
            speed = math.inf
        else:
            try:
                speed = number(speed, "speed", lo=0.0, lo_open=True)
            except DriverConfigError as err:
                raise DriverConfigError(f"speed = {self.speed!r}: expected a number > 0 or 'max'") from err
        object.__setattr__(self, "speed", speed)
        check_declared(self)

    @property
    def is_max_speed(self) -> bool:
        """True for ``speed = "max"``."""
        return math.isinf(self.speed)


class ReplayTransport(CartTransport):
    """Lines of a recorded file; ends at end of file (no reconnection)."""

    name = "replay"

    def __init__(
        self,
        options: ReplayOptions,
        hooks: TransportHooks | None = None,
        *,
        loader: Callable[[str], bytes] | None = None,
    ) -> None:
        """Create the transport.

        Args:
            options: Path and speed.
            hooks: Injectable sleep and clock.
            loader: Turns the file into the lines to replay (a vendor preset's xlsx or XML
                reader, :mod:`drivers.cart.vendors`); None reads the file's own bytes.
        """
        super().__init__(max_line_bytes=options.max_line_bytes, backoff=None, hooks=hooks)
        self.options = options
        self.loader = loader
        self._file: BinaryIO | None = None
        self._t0_s: float | None = None
        self._wall0_s = 0.0

    @property
    def paced_by_reader(self) -> bool:
        """A replay at ``speed = "max"`` is paced by its reader alone."""
        return self.options.is_max_speed

    def describe(self) -> str:
        speed = "max" if self.options.is_max_speed else f"{self.options.speed:g}x"
        return f"replay {self.options.path} at {speed}"

    async def _open_link(self) -> None:
        # A local file: opening and reading are fast enough to do on the loop.
        if self.loader is not None:
            self._file = io.BytesIO(self.loader(self.options.path))
        else:
            self._file = open_regular_file(  # closed in _close_link
                self.options.path, max_bytes=MAX_CART_FILE_BYTES, what="a cart recording or export")
        self._t0_s = None

    async def _read_chunk(self) -> bytes | None:
        if self._file is None:
            raise ConnectionResetError("replay file is closed")
        data = self._file.read(_READ_BYTES)
        return data or None

    async def _close_link(self) -> None:
        fh, self._file = self._file, None
        if fh is not None:
            fh.close()

    def _now(self) -> float:
        clock = self._hooks.clock
        return clock() if clock is not None else asyncio.get_running_loop().time()

    async def pace(self, t_s: float) -> None:
        """Wait until the breath at recorded time ``t_s`` is due at the configured speed."""
        if self.options.is_max_speed:
            await asyncio.sleep(0)  # yield only: not a wait on the wall clock
            return
        now = self._now()
        if self._t0_s is None:
            self._t0_s, self._wall0_s = t_s, now
            return
        delay = self._wall0_s + (t_s - self._t0_s) / self.options.speed - now
        if delay > 0.0:
            await self._hooks.sleep(delay)
