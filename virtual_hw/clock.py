"""Simulated clocks for the virtual devices: real time scaled by a speed factor, or discrete events.

Every virtual device (the metabolic cart, the exosuit node) and, in ``hilbo sim``, the bridge
read time from a :class:`SimClock` instead of the PC's clock, in **simulated seconds** since the
session began (the breath clock of shared/DESIGN.md). Two implementations:

* :class:`ScaledClock` — ``sim = (time.time() - epoch_wall) · speed``. ``speed = 1`` is real
  time. The epoch is a Unix time, so **separate processes given the same ``--epoch`` and
  ``--speed`` share one clock** (they agree to within the hosts' clock sync: on one machine,
  exactly). An epoch slightly in the future makes every process start at sim time 0 together
  (before it, :meth:`ScaledClock.now` is negative).
* :class:`VirtualClock` — discrete-event time for one process (tests, ``--speed max``): sim time
  jumps straight to the next wake-up, but only when every registered *participant* is waiting,
  so a 60-minute protocol runs as fast as the computer allows with the same order of events as
  at speed 1.

The participant contract (VirtualClock)
=======================================

A *participant* is a task whose progress time must wait for. ``clock.participant(name)``
registers one (and is a context manager that unregisters it). At any moment a participant is

* **busy** — running code. Sim time does not move. This is the default: a task is busy from
  registration until it waits, and again from the moment it is woken until it waits again;
* **sleeping** — inside ``await p.sleep_until(t)`` (or ``p.sleep(dt)``); it has a wake-up time;
* **idle** — inside ``with p.idle():``, waiting for something that is *not* the clock (a socket,
  a queue, another task). An idle participant does not hold time back and has no wake-up time.

Time advances only when (1) at least one participant is registered, (2) none is busy, (3) no
:class:`Hold` is held, and (4) something sleeps; it then jumps to the earliest wake-up and wakes
every sleeper due at that instant — a woken participant counts as busy *from the jump itself*,
before its task even resumes, so it can never miss the next step. Before jumping, the clock lets
the event loop run ``settle_turns`` more iterations (and optionally ``settle_wall_s`` wall
seconds) and starts over if any participant changed state meanwhile: bytes written to an
in-process loopback socket reach the reading task in 3 loop iterations (measured for TCP and UDP
stream/datagram readers), so a reader that is idle on a socket wakes, turns busy and is waited
for. Data that crosses a thread (pyserial's reader thread on a pty) or another process is *not*
covered by the settle turns: hold the clock explicitly (:meth:`VirtualClock.hold`) from the
moment you know data is coming until it is processed, or set ``settle_wall_s``.

Rules of thumb for a participant:

* await the clock with ``p.sleep_until``/``p.sleep`` (pass ``p.sleep`` as a transport's backoff
  sleep, ``TransportHooks(sleep=p.sleep, clock=clock.now)``, so reconnect delays are sim time);
* wrap every other await (reading a socket, ``queue.get()``) in ``with p.idle():`` — awaiting
  something that only another participant's *future* step can provide while busy deadlocks the
  session (the clock logs a warning naming the busy participants after ``stall_warning_s``);
* the bridge holds time while it processes a breath simply by being busy (a participant that
  leaves ``idle()`` as soon as the breath arrives), or with ``with clock.hold("estimator"):``.

With no participant registered, a VirtualClock moves only when told to:
:meth:`VirtualClock.advance` / :meth:`VirtualClock.run_until` (unit tests).

On a :class:`ScaledClock` the same calls work and cost nothing: participants sleep on the wall
clock, ``idle()`` and ``hold()`` are no-ops. Device code is therefore written once against
:class:`SimClock`.
"""

from __future__ import annotations

import asyncio
import heapq
import itertools
import logging
import math
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from enum import StrEnum
from types import TracebackType
from typing import Protocol, Self, runtime_checkable

from virtual_hw.errors import ClockError, VirtualConfigError

__all__ = [
    "Hold",
    "Participant",
    "ParticipantState",
    "ScaledClock",
    "SimClock",
    "SkippingClock",
    "VirtualClock",
    "make_clock",
    "parse_speed",
]

_log = logging.getLogger(__name__)

# Loop iterations a VirtualClock waits, with nobody changing state, before it jumps. Loopback
# TCP/UDP data reaches an awaiting StreamReader/queue reader in 3 iterations (measured); 8 leaves
# margin and costs ~40 µs per jump (one iteration is ~5 µs), ~0.3 s for 7200 jumps (an hour of
# cart ticks at 0.5 s).
DEFAULT_SETTLE_TURNS = 8
_SPEED_EXPECTED = "expected 'max' or a positive factor such as 1 or 10"


def _check_time(name: str, value: float) -> float:
    try:
        t = float(value)
    except (TypeError, ValueError) as err:
        raise ClockError(f"{name}={value!r} is not a time in simulated seconds") from err
    if not math.isfinite(t):
        raise ClockError(f"{name}={value!r} must be a finite time in simulated seconds")
    return t


class ParticipantState(StrEnum):
    """What a participant is doing, as far as the clock is concerned."""

    BUSY = "busy"
    SLEEPING = "sleeping"
    IDLE = "idle"
    CLOSED = "closed"


class Hold:
    """A token that keeps a :class:`VirtualClock` from advancing until it is released.

    A context manager (``with clock.hold("reason"):``) or released explicitly with
    :meth:`release`; releasing twice is harmless. On a :class:`ScaledClock` it does nothing.
    Like everything on a clock, take and release it on the event loop's thread (from another
    thread, hand the release over with ``loop.call_soon_threadsafe(hold.release)``).

    Attributes:
        reason: Shown in the clock's stall warning.
    """

    def __init__(self, reason: str, on_release: Callable[[Hold], None] | None = None) -> None:
        self.reason = reason
        self._on_release = on_release
        self._released = False

    @property
    def released(self) -> bool:
        """True once :meth:`release` ran."""
        return self._released

    def release(self) -> None:
        """Let time move again (as far as this hold is concerned). Idempotent."""
        if self._released:
            return
        self._released = True
        if self._on_release is not None:
            self._on_release(self)

    def __enter__(self) -> Self:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.release()

    def __repr__(self) -> str:
        return f"Hold({self.reason!r}, released={self._released})"


class Participant:
    """A task whose progress simulated time waits for (module docstring: the contract).

    Get one from :meth:`SimClock.participant`; it is registered (and busy) at once. Use it as a
    context manager, or call :meth:`close` when the task ends.

    Attributes:
        name: Shown in logs and stall warnings.
    """

    def __init__(self, clock: SimClock, name: str, owner: VirtualClock | None) -> None:
        self.name = name
        self._clock = clock
        self._owner = owner
        self._sleeping = False
        self._woken = False
        self._idle_depth = 0
        self._closed = False

    @property
    def clock(self) -> SimClock:
        """The clock this participant belongs to."""
        return self._clock

    @property
    def state(self) -> ParticipantState:
        """Busy, sleeping, idle or closed (a woken sleeper is busy until its task resumes)."""
        if self._closed:
            return ParticipantState.CLOSED
        if self._woken or (not self._sleeping and self._idle_depth == 0):
            return ParticipantState.BUSY
        return ParticipantState.SLEEPING if self._sleeping else ParticipantState.IDLE

    async def sleep_until(self, t_sim: float) -> None:
        """Wait until simulated time ``t_sim`` (returns after one loop turn if it has passed).

        Raises:
            ClockError: ``t_sim`` is not finite, or the participant is closed.
        """
        if self._closed:
            raise ClockError(f"participant {self.name!r} is closed; it cannot sleep")
        if self._owner is None:
            await self._clock.sleep_until(t_sim)
            return
        await self._owner._sleep(t_sim, self)

    async def sleep(self, dt_s: float) -> None:
        """Wait ``dt_s`` simulated seconds (an ``asyncio.sleep`` stand-in, e.g. for backoff)."""
        dt = _check_time("dt_s", dt_s)
        await self.sleep_until(self._clock.now() + max(dt, 0.0))

    @contextmanager
    def idle(self) -> Iterator[None]:
        """Mark the enclosed awaits as waiting on something other than the clock."""
        self._idle_depth += 1
        self._notify()
        try:
            yield
        finally:
            self._idle_depth -= 1
            self._notify()

    def close(self) -> None:
        """Unregister: time no longer waits for this task. Idempotent."""
        if self._closed:
            return
        self._closed = True
        if self._owner is not None:
            self._owner._unregister(self)

    def _notify(self) -> None:
        if self._owner is not None and not self._closed:
            self._owner._changed()

    def __enter__(self) -> Self:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"Participant({self.name!r}, {self.state.value})"


@runtime_checkable
class SimClock(Protocol):
    """What every virtual device needs from a clock (module docstring).

    Attributes:
        speed: Simulated seconds per wall second; ``math.inf`` for a :class:`VirtualClock`.
    """

    @property
    def speed(self) -> float:
        """Simulated seconds per wall second (``math.inf``: as fast as possible)."""
        ...

    def now(self) -> float:
        """Current simulated time in seconds."""
        ...

    async def sleep_until(self, t_sim: float) -> None:
        """Wait until simulated time ``t_sim`` (not as a participant)."""
        ...

    async def sleep(self, dt_s: float) -> None:
        """Wait ``dt_s`` simulated seconds (not as a participant)."""
        ...

    def participant(self, name: str) -> Participant:
        """Register a task that time must wait for (a no-op registration on a ScaledClock)."""
        ...

    def hold(self, reason: str = "") -> Hold:
        """Keep time from advancing until the returned hold is released (no-op when scaled)."""
        ...


class ScaledClock:
    """Wall time scaled by ``speed``: ``now() = (wall_time() - epoch_wall) · speed``.

    Args:
        speed: Simulated seconds per wall second, finite and > 0 (1 = real time).
        epoch_wall: Unix time (s) at which simulated time is 0; None means "now". Give several
            processes the same epoch and speed and they share one clock.
        wall_time: The wall clock, ``time.time`` (injectable for tests). It must be the same
            clock in every process that shares the epoch, hence not ``time.monotonic``.

    Raises:
        VirtualConfigError: A non-positive or non-finite speed, or a non-finite epoch.
    """

    def __init__(
        self, speed: float, epoch_wall: float | None = None, *, wall_time: Callable[[], float] = time.time
    ) -> None:
        if isinstance(speed, bool) or not isinstance(speed, int | float) or not (
            math.isfinite(speed) and speed > 0
        ):
            raise VirtualConfigError(
                f"speed={speed!r}: a ScaledClock needs a finite factor > 0 (use VirtualClock for 'max')"
            )
        self._speed = float(speed)
        self._wall = wall_time
        if epoch_wall is None:
            epoch_wall = wall_time()
        if isinstance(epoch_wall, bool) or not isinstance(epoch_wall, int | float) or not math.isfinite(
            epoch_wall
        ):
            raise VirtualConfigError(f"epoch_wall={epoch_wall!r}: expected a Unix time in seconds")
        self.epoch_wall = float(epoch_wall)

    @property
    def speed(self) -> float:
        """Simulated seconds per wall second."""
        return self._speed

    def now(self) -> float:
        """Simulated seconds since the epoch (negative before it)."""
        return (self._wall() - self.epoch_wall) * self._speed

    async def sleep_until(self, t_sim: float) -> None:
        """Sleep on the event loop until ``now() >= t_sim`` (re-checked after every wake-up).

        Raises:
            ClockError: ``t_sim`` is not finite.
        """
        t = _check_time("t_sim", t_sim)
        remaining = (t - self.now()) / self._speed
        if remaining <= 0:
            await asyncio.sleep(0)  # always a scheduling point, like asyncio.sleep(0)
            return
        # asyncio sleeps on the monotonic clock and may wake a hair early or late relative to
        # time.time(); loop until the shared (wall) clock says we are there.
        while remaining > 0:
            await asyncio.sleep(remaining)
            remaining = (t - self.now()) / self._speed

    async def sleep(self, dt_s: float) -> None:
        """Sleep ``dt_s`` simulated seconds."""
        dt = _check_time("dt_s", dt_s)
        await self.sleep_until(self.now() + max(dt, 0.0))

    def participant(self, name: str) -> Participant:
        """A participant whose calls go straight to this clock (nothing waits for it)."""
        return Participant(self, name, None)

    def hold(self, reason: str = "") -> Hold:
        """A hold that holds nothing (wall time cannot be stopped)."""
        return Hold(reason)

    def __repr__(self) -> str:
        return f"ScaledClock(speed={self._speed:g}, epoch_wall={self.epoch_wall!r})"


class SkippingClock(ScaledClock):
    """A :class:`ScaledClock` that can also jump ahead (:meth:`skip_to`), for one process.

    ``hilbo sim --speed max`` runs the devices at a real-time factor, and the bridge then spends
    most of the wall time waiting for the next breath (three quarters of ``make sim``). When the
    bridge waits for a breath and nothing else needs time to pass (no profile pending, no fault
    scheduled), the simulation skips the clock to the cart's next tick: the same session, bound
    by its computing instead of by the factor. The epoch moves, so this clock cannot be shared
    with another process (they would disagree); sleepers wake at every skip and re-check.
    """

    def __init__(self, speed: float, epoch_wall: float | None = None, *,
                 wall_time: Callable[[], float] = time.time) -> None:
        super().__init__(speed, epoch_wall, wall_time=wall_time)
        self._moved: asyncio.Event | None = None
        #: Simulated seconds skipped so far.
        self.skipped_s = 0.0

    def skip_to(self, t_sim: float) -> float:
        """Jump to ``t_sim`` if it is ahead (never back); wake every sleeper to re-check.

        Returns:
            The simulated seconds skipped (0 when ``t_sim`` is not ahead).
        """
        ahead = _check_time("t_sim", t_sim) - self.now()
        if ahead <= 0:
            return 0.0
        self.epoch_wall -= ahead / self._speed
        self.skipped_s += ahead
        moved, self._moved = self._moved, None
        if moved is not None:
            moved.set()
        return ahead

    async def sleep_until(self, t_sim: float) -> None:
        """Sleep until ``now() >= t_sim``: the wall time it takes, or less after a skip."""
        t = _check_time("t_sim", t_sim)
        remaining = (t - self.now()) / self._speed
        if remaining <= 0:
            await asyncio.sleep(0)
            return
        while remaining > 0:
            if self._moved is None:
                self._moved = asyncio.Event()
            moved = self._moved
            try:
                async with asyncio.timeout(remaining):
                    await moved.wait()
            except TimeoutError:
                pass
            remaining = (t - self.now()) / self._speed

    def __repr__(self) -> str:
        return f"SkippingClock(speed={self._speed:g}, epoch_wall={self.epoch_wall!r})"


class VirtualClock:
    """Discrete-event simulated time for one event loop (module docstring: the contract).

    Args:
        start_s: Initial simulated time in seconds.
        settle_turns: Event-loop iterations without any participant changing state before a
            jump (>= 1).
        settle_wall_s: Extra wall seconds to wait, still without changes, before a jump (for
            data that crosses threads); 0 disables.
        stall_warning_s: Log a warning naming the busy participants and holds when time has
            been blocked this long in wall seconds with wake-ups pending.

    Raises:
        VirtualConfigError: A bad option (named).
    """

    def __init__(
        self,
        start_s: float = 0.0,
        *,
        settle_turns: int = DEFAULT_SETTLE_TURNS,
        settle_wall_s: float = 0.0,
        stall_warning_s: float = 10.0,
    ) -> None:
        try:
            self._now = _check_time("start_s", start_s)
        except ClockError as err:
            raise VirtualConfigError(str(err)) from err
        if isinstance(settle_turns, bool) or not isinstance(settle_turns, int) or settle_turns < 1:
            raise VirtualConfigError(f"settle_turns={settle_turns!r}: expected an integer >= 1")
        for name, value in (("settle_wall_s", settle_wall_s), ("stall_warning_s", stall_warning_s)):
            if isinstance(value, bool) or not isinstance(value, int | float) or not (
                math.isfinite(value) and value >= 0
            ):
                raise VirtualConfigError(f"{name}={value!r}: expected a finite number of seconds >= 0")
        if stall_warning_s <= 0:
            raise VirtualConfigError(f"stall_warning_s={stall_warning_s!r}: expected > 0 s")
        self._settle_turns = settle_turns
        self._settle_wall_s = float(settle_wall_s)
        self._stall_warning_s = float(stall_warning_s)
        # Heap of [deadline, tie-break, future, participant or None]; cancelled futures are
        # dropped lazily when they reach the top.
        self._heap: list[tuple[float, int, asyncio.Future[None], Participant | None]] = []
        self._tiebreak = itertools.count()
        self._participants: list[Participant] = []
        self._holds: list[Hold] = []
        self._generation = 0
        self._kick = asyncio.Event()
        self._advancer: asyncio.Task[None] | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self.jumps = 0

    # -- SimClock ---------------------------------------------------------------------------

    @property
    def speed(self) -> float:
        """``math.inf``: time runs as fast as the participants allow."""
        return math.inf

    def now(self) -> float:
        """Current simulated time in seconds."""
        return self._now

    async def sleep_until(self, t_sim: float) -> None:
        """Wait, not as a participant, until simulated time reaches ``t_sim``.

        Raises:
            ClockError: ``t_sim`` is not finite.
        """
        await self._sleep(t_sim, None)

    async def sleep(self, dt_s: float) -> None:
        """Wait ``dt_s`` simulated seconds, not as a participant."""
        dt = _check_time("dt_s", dt_s)
        await self._sleep(self._now + max(dt, 0.0), None)

    def participant(self, name: str) -> Participant:
        """Register a participant (busy until it sleeps or idles); must run inside the loop.

        Raises:
            ClockError: No running event loop, or a different loop than earlier participants.
        """
        self._bind_loop()
        p = Participant(self, str(name), self)
        self._participants.append(p)
        self._changed()
        if self._advancer is None:
            self._advancer = asyncio.get_running_loop().create_task(
                self._advance_loop(), name="VirtualClock.advance"
            )
            self._advancer.add_done_callback(self._advancer_done)
        return p

    def hold(self, reason: str = "") -> Hold:
        """A :class:`Hold` that stops time until released."""
        h = Hold(reason, self._release_hold)
        self._holds.append(h)
        self._changed()
        return h

    # -- manual stepping (unit tests) -------------------------------------------------------

    async def run_until(self, t_sim: float) -> None:
        """Move time to ``t_sim`` through every wake-up on the way, in order.

        After each jump the loop runs ``settle_turns`` iterations so woken tasks can act (and
        schedule new wake-ups, which are honoured if they are due by ``t_sim``). Meant for tests
        without participants; it ignores busy participants and holds. A ``t_sim`` in the past
        does nothing.

        Raises:
            ClockError: ``t_sim`` is not finite.
        """
        target = _check_time("t_sim", t_sim)
        while (due := self._earliest()) is not None and due <= target:
            self._advance_to(due)
            for _ in range(self._settle_turns):
                await asyncio.sleep(0)
        if target > self._now:
            self._now = target
            self._changed()

    async def advance(self, dt_s: float) -> None:
        """``run_until(now() + dt_s)``."""
        dt = _check_time("dt_s", dt_s)
        await self.run_until(self._now + max(dt, 0.0))

    # -- introspection ----------------------------------------------------------------------

    @property
    def participants(self) -> tuple[Participant, ...]:
        """The registered participants."""
        return tuple(self._participants)

    @property
    def holds(self) -> tuple[Hold, ...]:
        """The holds not released yet."""
        return tuple(self._holds)

    def next_wakeup(self) -> float | None:
        """The earliest pending wake-up time, or None."""
        return self._earliest()

    # -- internals --------------------------------------------------------------------------

    def _bind_loop(self) -> asyncio.AbstractEventLoop:
        try:
            loop = asyncio.get_running_loop()
        except RuntimeError as err:
            raise ClockError("a VirtualClock is used from inside a running event loop") from err
        if self._loop is None or self._loop.is_closed():
            self._loop = loop
        elif self._loop is not loop:
            raise ClockError("this VirtualClock already serves another event loop")
        return loop

    async def _sleep(self, t_sim: float, who: Participant | None) -> None:
        t = _check_time("t_sim", t_sim)
        loop = self._bind_loop()
        if t <= self._now:
            await asyncio.sleep(0)
            return
        fut: asyncio.Future[None] = loop.create_future()
        heapq.heappush(self._heap, (t, next(self._tiebreak), fut, who))
        if who is not None:
            who._sleeping = True
        self._changed()
        try:
            await fut
        finally:
            if not fut.done():
                fut.cancel()  # cancelled waiter: its heap entry is skipped when it surfaces
            if who is not None:
                who._sleeping = False
                who._woken = False
                self._changed()

    def _earliest(self) -> float | None:
        heap = self._heap
        while heap and heap[0][2].done():
            heapq.heappop(heap)
        return heap[0][0] if heap else None

    def _advance_to(self, t: float) -> None:
        self._now = max(self._now, t)
        self.jumps += 1
        heap = self._heap
        while heap and heap[0][0] <= self._now:
            _, _, fut, who = heapq.heappop(heap)
            if fut.done():
                continue
            if who is not None:
                who._woken = True  # busy from this instant, before its task resumes
            fut.set_result(None)
        self._changed()

    def _changed(self) -> None:
        self._generation += 1
        self._kick.set()

    def _unregister(self, p: Participant) -> None:
        if p in self._participants:
            self._participants.remove(p)
        self._changed()

    def _release_hold(self, h: Hold) -> None:
        if h in self._holds:
            self._holds.remove(h)
        self._changed()

    def _blocked_by(self) -> list[str]:
        busy = [p.name for p in self._participants if p.state is ParticipantState.BUSY]
        return [f"participant {n!r} busy" for n in busy] + [f"hold {h.reason!r}" for h in self._holds]

    def _can_advance(self) -> bool:
        if not self._participants or self._holds:
            return False
        if any(p.state is ParticipantState.BUSY for p in self._participants):
            return False
        return self._earliest() is not None

    async def _advance_loop(self) -> None:
        while self._participants:
            if not self._can_advance():
                self._kick.clear()
                if self._can_advance() or not self._participants:
                    continue
                try:
                    async with asyncio.timeout(self._stall_warning_s):
                        await self._kick.wait()
                except TimeoutError:
                    if self._earliest() is not None:
                        _log.warning(
                            "VirtualClock stuck at t=%.3f s for %.0f s wall: %s",
                            self._now, self._stall_warning_s, "; ".join(self._blocked_by()) or "?",
                        )
                continue
            generation = self._generation
            for _ in range(self._settle_turns):
                await asyncio.sleep(0)
                if self._generation != generation:
                    break
            if self._generation == generation and self._settle_wall_s > 0:
                await asyncio.sleep(self._settle_wall_s)
            if self._generation == generation and self._can_advance():
                due = self._earliest()
                if due is not None:
                    self._advance_to(due)

    def _advancer_done(self, task: asyncio.Task[None]) -> None:
        self._advancer = None
        if task.cancelled():
            return
        err = task.exception()
        if err is not None:
            # Never expected; fail every sleeper loudly rather than leave them hanging.
            _log.error("VirtualClock advancer failed: %r", err)
            for _, _, fut, _ in self._heap:
                if not fut.done():
                    fut.set_exception(ClockError(f"VirtualClock advancer failed: {err!r}"))
        elif self._participants:
            # A participant registered while the loop was exiting: keep time running for it.
            loop = self._loop
            if loop is not None and not loop.is_closed():
                self._advancer = loop.create_task(self._advance_loop(), name="VirtualClock.advance")
                self._advancer.add_done_callback(self._advancer_done)

    def __repr__(self) -> str:
        return (
            f"VirtualClock(t={self._now:.6g}, participants={[p.name for p in self._participants]}, "
            f"holds={len(self._holds)})"
        )


def parse_speed(value: str | float) -> float:
    """``"max"`` (or ``math.inf``) → ``math.inf``; a positive number (or its text) → that factor.

    Raises:
        VirtualConfigError: Anything else.
    """
    if isinstance(value, str):
        text = value.strip().lower()
        if text == "max":
            return math.inf
        try:
            value = float(text)
        except ValueError as err:
            raise VirtualConfigError(f"speed={value!r}: {_SPEED_EXPECTED}") from err
    if isinstance(value, bool) or not isinstance(value, int | float) or math.isnan(value) or value <= 0:
        raise VirtualConfigError(f"speed={value!r}: {_SPEED_EXPECTED}")
    return float(value)


def make_clock(speed: str | float, epoch_wall: float | None = None) -> SimClock:
    """The clock for a ``--speed``/``--epoch`` pair.

    Args:
        speed: ``"max"`` (or ``math.inf``) for a :class:`VirtualClock`; a positive factor for a
            :class:`ScaledClock` (1 = real time).
        epoch_wall: Unix time of simulated time 0 for a ScaledClock (None: now). Refused with
            ``"max"``: a VirtualClock cannot be shared between processes.

    Raises:
        VirtualConfigError: A bad speed, or an epoch with ``"max"``.
    """
    factor = parse_speed(speed)
    if math.isinf(factor):
        if epoch_wall is not None:
            raise VirtualConfigError(
                f"epoch_wall={epoch_wall!r} with speed 'max': an as-fast-as-possible clock lives in "
                "one process and cannot share an epoch; give a numeric speed to share a clock"
            )
        return VirtualClock()
    return ScaledClock(factor, epoch_wall)
