"""The cart-transport interface: an async source of lines that reconnects when its link drops.

A :class:`CartTransport` is an async context manager (opens and closes the link) and an async
iterator of raw lines (bytes, terminator removed). Concrete transports implement three hooks —
``_open_link``, ``_read_chunk`` and ``_close_link`` — and the base class does the rest the same
way for all of them: framing (:class:`~drivers.cart.framing.LineFramer`), the idle watchdog,
and reconnection with capped exponential backoff (:class:`Backoff`), whose sleep is injectable
(:class:`TransportHooks`) so tests never wait on the wall clock.

Link failures are ``OSError`` (which covers ``ConnectionError``, ``TimeoutError`` and pyserial's
``SerialException``). The first :meth:`CartTransport.open` fails fast with
:class:`~drivers.errors.TransportError` — a cart that is not there at start-up is an operator
error to show at once — while a link that drops later is reopened until ``max_attempts``
consecutive attempts have brought no data.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
from abc import ABC, abstractmethod
from collections import Counter, deque
from collections.abc import Awaitable, Callable, Mapping
from contextlib import AbstractContextManager
from dataclasses import MISSING, dataclass, fields
from types import TracebackType
from typing import Annotated, Any, ClassVar, Self

from msgspec import Meta

from drivers.cart._options import check_declared, check_keys, check_mapping, number, within
from drivers.cart.framing import DEFAULT_MAX_LINE_BYTES, LineFramer
from drivers.config_model import FINITE
from drivers.errors import DriverConfigError, TransportError

__all__ = ["Backoff", "CartTransport", "Clock", "Sleep", "TransportHooks", "options_from_dict"]

_log = logging.getLogger(__name__)

Sleep = Callable[[float], Awaitable[None]]
"""An ``asyncio.sleep``-like coroutine function: wait this many seconds."""
Clock = Callable[[], float]
"""A monotonic clock in seconds (default: the running loop's ``time``)."""


@dataclass(frozen=True, slots=True)
class Backoff:
    """Capped exponential backoff between reconnection attempts.

    The k-th consecutive attempt (k = 0, 1, ...) waits ``min(initial_s * factor**k, max_s)``.
    The count restarts when data arrives, so a link that connects but drops at once keeps
    backing off instead of hammering the cart.

    Attributes:
        initial_s: First delay in seconds (> 0).
        factor: Growth per attempt (>= 1).
        max_s: Cap on the delay in seconds (>= ``initial_s``).
        max_attempts: Give up (raise :class:`TransportError`) after this many consecutive
            attempts without data; None retries forever (a cart cable can be replugged).
    """

    initial_s: Annotated[float, Meta(gt=0.0, le=FINITE)] = 0.5
    factor: Annotated[float, Meta(ge=1.0, le=FINITE)] = 2.0
    max_s: float = 10.0
    max_attempts: Annotated[int, Meta(ge=1)] | None = None

    def __post_init__(self) -> None:
        check_declared(self)
        # max_s >= initial_s involves two fields: checked here, not declared.
        object.__setattr__(self, "max_s", number(self.max_s, "max_s", lo=self.initial_s))

    def delay_s(self, attempt: int) -> float:
        """Delay before the ``attempt``-th consecutive attempt (0-based), in seconds."""
        # Compare exponents, not powers, so a long outage cannot overflow factor**attempt.
        if self.factor == 1.0 or attempt * math.log(self.factor) < math.log(self.max_s / self.initial_s):
            return min(self.initial_s * self.factor**attempt, self.max_s)
        return self.max_s

    @classmethod
    def from_dict(cls, data: Mapping[str, Any], where: str = "backoff") -> Backoff:
        """Build from a config table, rejecting unknown keys."""
        data = check_mapping(data, where)
        check_keys(data, [f.name for f in fields(cls)], where)
        try:
            return cls(**data)
        except DriverConfigError as err:
            raise within(where, err) from err


@dataclass(frozen=True, slots=True)
class TransportHooks:
    """Injectable time for transports (tests pass a simulated clock and sleep).

    Attributes:
        sleep: Used for reconnection backoff and replay pacing.
        clock: Used for replay pacing; None means the running loop's ``time``.
        waiting: Wraps each wait for the link's bytes, and nothing else. A reader on a
            simulated clock passes its participant's ``idle``: time may move while the
            transport waits for the cart, never while it recovers from a drop (closing,
            backing off on ``sleep``, reopening the link in a thread).
    """

    sleep: Sleep = asyncio.sleep
    clock: Clock | None = None
    waiting: Callable[[], AbstractContextManager[object]] = contextlib.nullcontext


def options_from_dict(cls: type[Any], data: Mapping[str, Any], where: str) -> Any:
    """Build a transport's frozen options dataclass from a config table.

    Rejects unknown and missing keys by name, turns a ``backoff`` table into :class:`Backoff`
    and prefixes the dataclass's own validation errors with ``where``.
    """
    data = check_mapping(data, where)
    names = [f.name for f in fields(cls)]
    check_keys(data, names, where)
    missing = [
        f.name
        for f in fields(cls)
        if f.name not in data and f.default is MISSING and f.default_factory is MISSING
    ]
    if missing:
        raise DriverConfigError(f"{where}: missing required key(s) {missing!r}")
    kwargs = dict(data)
    if kwargs.get("backoff") is not None:
        kwargs["backoff"] = Backoff.from_dict(kwargs["backoff"], f"{where}.backoff")
    try:
        return cls(**kwargs)
    except DriverConfigError as err:
        raise within(where, err) from err


class CartTransport(ABC):
    """Async source of raw lines from a metabolic cart (see the module docstring).

    Use::

        async with transport:
            async for line in transport:
                ...

    Attributes:
        name: Registry name of the transport class (``"serial"``, ``"tcp"``, ...).
        counters: Framing rejects (``too_long``, ``truncated``, ``overflow``).
        drops: Times the link dropped after being open.
        reconnects: Times the link was reopened after a drop.
    """

    name: ClassVar[str] = ""

    def __init__(
        self,
        *,
        max_line_bytes: int = DEFAULT_MAX_LINE_BYTES,
        backoff: Backoff | None = None,
        idle_timeout_s: float | None = None,
        hooks: TransportHooks | None = None,
    ) -> None:
        """Set up framing and reconnection; subclasses pass their options through.

        Args:
            max_line_bytes: Longest line kept.
            backoff: Reconnection policy; None means a drop ends the stream with
                :class:`TransportError`.
            idle_timeout_s: Treat this long without any byte as a dropped link (catches a
                half-open TCP connection); None disables it.
            hooks: Injectable sleep and clock.
        """
        self._framer = LineFramer(max_line_bytes)
        self.counters: Counter[str] = self._framer.counters
        self._backoff = backoff
        self._idle_timeout_s = idle_timeout_s
        self._hooks = hooks if hooks is not None else TransportHooks()
        self._lines: deque[bytes] = deque()
        self._failures = 0
        self._is_open = False
        self._ended = False
        self.drops = 0
        self.reconnects = 0

    # -- what a concrete transport implements -------------------------------------------------

    @abstractmethod
    def describe(self) -> str:
        """Short human-readable identity for logs and errors, e.g. ``"tcp 10.0.0.5:5000"``."""

    @abstractmethod
    async def _open_link(self) -> None:
        """Open the link; raise ``OSError`` on failure."""

    @abstractmethod
    async def _read_chunk(self) -> bytes | None:
        """Wait for and return some bytes (never empty); None at a clean end of the stream.

        Raise ``OSError`` (``ConnectionError`` for a peer that closed) when the link dropped.
        """

    @abstractmethod
    async def _close_link(self) -> None:
        """Release the link; must be safe to call when it is already closed or half-open."""

    # -- pacing ----------------------------------------------------------------------------------

    async def pace(self, t_s: float) -> None:
        """Wait until the breath at cart time ``t_s`` is due (replay); live transports return."""
        return None

    @property
    def paced_by_reader(self) -> bool:
        """True when nothing but the reader paces the breaths (a replay at ``speed = "max"``):
        the reader must then take them no faster than it can use them (back-pressure), or a
        whole file arrives before the session is ready for its first breath."""
        return False

    # -- lifecycle -------------------------------------------------------------------------------

    @property
    def is_open(self) -> bool:
        """True between a successful :meth:`open` and :meth:`close`."""
        return self._is_open

    async def open(self) -> None:
        """Open the link once.

        Raises:
            TransportError: The link cannot be opened (the ``OSError`` is chained).
        """
        if self._is_open:
            return
        try:
            await self._open_link()
        except OSError as err:
            await self._close_link()
            raise TransportError(f"{self.describe()}: cannot open: {err}") from err
        self._is_open = True
        self._ended = False
        _log.info("cart transport open: %s", self.describe())

    async def close(self) -> None:
        """Close the link; iteration then ends. Idempotent."""
        was_open, self._is_open = self._is_open, False
        await self._close_link()
        if was_open:
            _log.info("cart transport closed: %s", self.describe())

    async def __aenter__(self) -> Self:
        await self.open()
        return self

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        await self.close()

    # -- iteration -------------------------------------------------------------------------------

    def __aiter__(self) -> Self:
        return self

    async def __anext__(self) -> bytes:
        """Return the next line (terminator removed).

        Raises:
            StopAsyncIteration: Closed, or the source ended (replay at end of file).
            TransportError: The link dropped and could not be reopened within the backoff's
                ``max_attempts`` (or the transport does not reconnect).
        """
        while not self._lines:
            if not self._is_open or self._ended:
                raise StopAsyncIteration
            try:
                chunk = await self._read_with_watchdog()
            except OSError as err:
                await self._recover(err)
                continue
            if chunk is None:
                self._ended = True
                tail = self._framer.flush()
                if tail is not None:
                    self._lines.append(tail)
                continue
            self._failures = 0  # data flows again: the next drop starts backoff from scratch
            self._lines.extend(self._framer.feed(chunk))
        return self._lines.popleft()

    async def _read_with_watchdog(self) -> bytes | None:
        with self._hooks.waiting():
            if self._idle_timeout_s is None:
                return await self._read_chunk()
            return await self._read_with_idle_timeout(self._idle_timeout_s)

    async def _read_with_idle_timeout(self, timeout_s: float) -> bytes | None:
        try:
            async with asyncio.timeout(timeout_s):
                return await self._read_chunk()
        except TimeoutError as err:
            raise TimeoutError(f"no data for {timeout_s:g} s (idle_timeout_s)") from err

    async def _recover(self, cause: OSError) -> None:
        """Reopen the link after ``cause`` with backoff, or raise TransportError."""
        self.drops += 1
        self._framer.discard()  # a line cut off by the drop cannot be completed by the new link
        await self._close_link()
        if self._backoff is None:
            self._is_open = False
            raise TransportError(f"{self.describe()}: link dropped: {cause}") from cause
        _log.warning("cart transport dropped (%s): %s; reconnecting", self.describe(), cause)
        last: OSError = cause
        while True:
            if self._backoff.max_attempts is not None and self._failures >= self._backoff.max_attempts:
                self._is_open = False
                raise TransportError(
                    f"{self.describe()}: gave up after {self._failures} reconnection attempts "
                    f"without data; last error: {last}"
                ) from last
            delay = self._backoff.delay_s(self._failures)
            self._failures += 1
            await self._hooks.sleep(delay)
            try:
                await self._open_link()
            except OSError as err:
                last = err
                _log.warning(
                    "cart reconnect attempt %d (%s) failed: %s", self._failures, self.describe(), err
                )
                await self._close_link()
                continue
            self.reconnects += 1
            _log.info("cart transport reconnected: %s", self.describe())
            return
