"""How long the session's event loop stops: a stall monitor.

Why: the bridge heartbeat is sent by an event-loop task (drivers/exosuit/endpoint.py,
``CanEndpoint.start_heartbeat``, on purpose: a hung bridge must look hung to the device), so
anything that holds the loop — a garbage collection, a slow log flush, a long computation in
a callback — delays the heartbeat by as much. The device latches ``heartbeat_lost`` after
100 ms without one (drivers/PROTOCOL.md). The session's rule is that no pause of the loop may
exceed *half* that watchdog while a device is connected; :mod:`bridge.collector` measures the
collector's share, this module measures every pause, whatever its cause.

How: one task sleeps ``period_s`` again and again and measures, with :func:`time.perf_counter`
(real time: a stall is real even when the session's clock is simulated or scaled), how much
later than asked it woke. A stall of length S that begins during a sleep shows as at least
``S - period_s``, so the measurement underestimates by at most one period (5 ms by default).
Each wake-up costs a timer and a few float operations (about 200 a second by default).
"""

from __future__ import annotations

import asyncio
import contextlib
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from bridge.errors import BridgeConfigError

__all__ = ["DEFAULT_PERIOD_S", "LoopMonitor", "LoopStats"]

#: How often the monitor wakes (s): the measurement's resolution.
DEFAULT_PERIOD_S = 0.005


@dataclass
class LoopStats:
    """Event-loop stalls seen by a :class:`LoopMonitor`.

    Attributes:
        threshold_ms: A stall longer than this is counted and reported (ms).
        period_ms: The monitor's wake-up period, the measurement's resolution (ms).
        worst_stall_ms: The longest stall while connected (ms; lateness of a wake-up).
        stalls_over_threshold: Stalls longer than ``threshold_ms`` while connected.
        wakeups: Wake-ups measured while connected.
    """

    threshold_ms: float
    period_ms: float
    worst_stall_ms: float = 0.0
    stalls_over_threshold: int = 0
    wakeups: int = 0

    def to_json(self) -> dict[str, Any]:
        """JSON-able form (summary.json's ``loop``; the names say the threshold is half the
        device's heartbeat watchdog, which is what the session passes)."""
        return {
            "worst_stall_ms": round(self.worst_stall_ms, 3),
            "stalls_over_half_heartbeat": self.stalls_over_threshold,
            "half_heartbeat_ms": round(self.threshold_ms, 3),
            "period_ms": round(self.period_ms, 3),
            "wakeups": self.wakeups,
        }


class LoopMonitor:
    """Measures how late the running event loop wakes a sleeping task; an async context manager.

    Entering starts the monitor task on the running loop; leaving cancels it and waits for it.
    An error inside the monitor (a failing ``on_stall``) ends the task and is raised again on
    exit, so it is never lost.

    Args:
        threshold_s: Stalls longer than this are counted and passed to ``on_stall`` (s).
        on_stall: Called with the stall's length (s), from the loop, after each such stall.
        connected: Whether a device is connected now; stalls are counted only then. None:
            always.
        period_s: Wake-up period (s), > 0 and below ``threshold_s``.
        clock: Real-time clock (s); injectable for tests.

    Raises:
        BridgeConfigError: A period or threshold that is not positive, or a period not below the
            threshold.
    """

    def __init__(self, threshold_s: float, on_stall: Callable[[float], None], *,
                 connected: Callable[[], bool] | None = None,
                 period_s: float = DEFAULT_PERIOD_S,
                 clock: Callable[[], float] = time.perf_counter) -> None:
        if not 0 < period_s < threshold_s:
            raise BridgeConfigError(f"LoopMonitor: need 0 < period_s < threshold_s, got "
                                    f"period_s={period_s!r}, threshold_s={threshold_s!r}")
        self.threshold_s = float(threshold_s)
        self.period_s = float(period_s)
        self.stats = LoopStats(threshold_ms=1e3 * self.threshold_s, period_ms=1e3 * self.period_s)
        self._on_stall = on_stall
        self._connected = connected
        self._clock = clock
        self._task: asyncio.Task[None] | None = None

    async def __aenter__(self) -> LoopMonitor:
        if self._task is not None:
            raise RuntimeError("LoopMonitor entered twice")
        self._task = asyncio.get_running_loop().create_task(self._run(), name="loop-monitor")
        return self

    async def __aexit__(self, *exc: object) -> None:
        task, self._task = self._task, None
        if task is None:
            return
        if not task.done():
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task
            return
        if not task.cancelled() and task.exception() is not None:
            raise task.exception()  # type: ignore[misc]  # the monitor's own failure

    async def _run(self) -> None:
        clock, period, threshold = self._clock, self.period_s, self.threshold_s
        connected, st = self._connected, self.stats
        due = clock() + period
        while True:
            await asyncio.sleep(period)
            now = clock()
            late = now - due
            due = now + period
            if connected is not None and not connected():
                continue
            st.wakeups += 1
            if late > 1e-3 * st.worst_stall_ms:
                st.worst_stall_ms = 1e3 * late
            if late > threshold:
                st.stalls_over_threshold += 1
                self._on_stall(late)
