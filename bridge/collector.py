"""When CPython's cyclic garbage collector may stop the session's event loop.

Why: a full ("generation 2") collection walks every container object the interpreter tracks,
holding the GIL. After a session's imports (numpy, scipy, cantools, mcap, python-can) that is
about 85 000 objects; one full collection took 20–56 ms on this project's test machine, and
37–66 ms inside real-time sessions (docs/results.md, "Compute latency", "Bridge at real time", with the
commands). CPython starts one by itself whenever enough objects have survived younger
collections, and 2000 CAN frames/s of force feedback allocate enough for one every few minutes,
at a moment nothing chooses: an instrumented ``scripts/loop_lag_probe.py`` run found a 53.6 ms
event-loop stall that was a 52.4 ms collection. A stall of that length stretches a paced
profile transfer (the target: stop decision → commit on the bus within 100 ms) and delays the
watchdog's assistance-off by as much.

:attr:`GcMode.FREEZE` (the default) moves the collections to moments where they cost nothing:

* **session start** (:meth:`Collector.__enter__`): ``gc.freeze()`` — every object alive now
  (modules, classes, the session's setup) goes to the permanent generation, which collections
  never walk;
* **quiet points** (:meth:`Collector.quiet_point`, called when the device has just reported a
  new profile active, breaths before the next stop decision): ``gc.collect()`` of what is not
  frozen — what the session allocated since the last quiet point, a few thousand objects —
  then ``gc.freeze()`` again. The collections CPython starts by itself in between walk only
  what one evaluation allocated;
* **never a whole-heap walk while a device is connected**: :meth:`Collector.full` (unfreeze and
  collect everything) took 113-176 ms between the bouts, longer than the device's 100 ms
  heartbeat watchdog, which then latched ``heartbeat_lost``, so the session no
  longer calls it; the pause between the bouts is a quiet point like the others. Frozen
  objects are still freed by reference counting the moment nothing uses them; only a
  reference *cycle* among objects that were frozen while alive waits for the session's end;
* **end** (:meth:`Collector.__exit__`): ``gc.unfreeze()``, CPython's schedule as before.

:attr:`GcMode.AUTOMATIC` leaves CPython's own schedule alone (the pauses are still measured).

The collector is process-wide: sessions that overlap in one process (tests) share it, and only
the outermost one's exit unfreezes.
"""

from __future__ import annotations

import enum
import gc
import threading
import time
from dataclasses import dataclass, field
from typing import Any

__all__ = ["Collector", "CollectorStats", "GcMode"]


class GcMode(enum.Enum):
    """``[protocol] gc``: when full garbage collections may run (see this module)."""

    FREEZE = "freeze"  # at quiet points of the session (the default)
    AUTOMATIC = "automatic"  # whenever CPython decides


@dataclass
class CollectorStats:
    """Collections seen while a :class:`Collector` was entered.

    Attributes:
        automatic: Collections CPython started by itself, per generation (0, 1, 2).
        automatic_max_ms: The longest of those per generation (ms).
        quiet_points: :meth:`Collector.quiet_point` calls that collected.
        quiet_max_ms: The longest quiet-point collection (ms).
        full: :meth:`Collector.full` calls that collected.
        full_max_ms: The longest of those (ms).
    """

    automatic: list[int] = field(default_factory=lambda: [0, 0, 0])
    automatic_max_ms: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])
    quiet_points: int = 0
    quiet_max_ms: float = 0.0
    full: int = 0
    full_max_ms: float = 0.0

    def to_json(self) -> dict[str, Any]:
        """JSON-able form (the session log's ``gc`` event)."""
        return {
            "automatic": list(self.automatic),
            "automatic_max_ms": [round(x, 3) for x in self.automatic_max_ms],
            "quiet_points": self.quiet_points, "quiet_max_ms": round(self.quiet_max_ms, 3),
            "full": self.full, "full_max_ms": round(self.full_max_ms, 3),
        }


_depth_lock = threading.Lock()
_depth = 0  # entered Collectors in FREEZE mode, process-wide


class Collector:
    """The session's garbage-collection policy; a context manager (see the module docstring).

    Args:
        mode: :class:`GcMode` (or its value).
    """

    def __init__(self, mode: GcMode | str = GcMode.FREEZE) -> None:
        self.mode = GcMode(mode)
        self.stats = CollectorStats()
        self._entered = False
        self._ours = False  # a collection this object started (not counted as automatic)
        self._t0 = 0.0

    def __enter__(self) -> Collector:
        global _depth
        if self._entered:
            raise RuntimeError("Collector entered twice")
        self._entered = True
        gc.callbacks.append(self._on_gc)
        if self.mode is GcMode.FREEZE:
            with _depth_lock:
                _depth += 1
            gc.freeze()
        return self

    def __exit__(self, *exc: object) -> None:
        global _depth
        if not self._entered:
            return
        self._entered = False
        gc.callbacks.remove(self._on_gc)
        if self.mode is GcMode.FREEZE:
            with _depth_lock:
                _depth -= 1
                if _depth == 0:
                    gc.unfreeze()

    def quiet_point(self) -> float | None:
        """Collect what was allocated since the last freeze and freeze the survivors.

        Returns:
            The collection's wall time (s), or None (``AUTOMATIC`` mode, or not entered).
        """
        return self._collect(unfreeze=False)

    def full(self) -> float | None:
        """Collect everything, frozen objects included, and freeze the survivors (long pauses).

        Returns:
            The collection's wall time (s), or None (``AUTOMATIC`` mode, or not entered).
        """
        return self._collect(unfreeze=True)

    # ------------------------------------------------------------------ internals
    def _collect(self, *, unfreeze: bool) -> float | None:
        if not (self._entered and self.mode is GcMode.FREEZE):
            return None
        t0 = time.perf_counter()
        self._ours = True
        try:
            if unfreeze:
                gc.unfreeze()
            gc.collect()
        finally:
            self._ours = False
            gc.freeze()
        dt = time.perf_counter() - t0
        st = self.stats
        if unfreeze:
            st.full, st.full_max_ms = st.full + 1, max(st.full_max_ms, 1e3 * dt)
        else:
            st.quiet_points, st.quiet_max_ms = st.quiet_points + 1, max(st.quiet_max_ms, 1e3 * dt)
        return dt

    def _on_gc(self, phase: str, info: dict[str, Any]) -> None:
        # gc.callbacks run in the thread that triggered the collection, with the GIL held.
        if phase == "start":
            self._t0 = time.perf_counter()
            return
        if self._ours:
            return
        gen = info["generation"]  # 0, 1 or 2
        self.stats.automatic[gen] += 1
        self.stats.automatic_max_ms[gen] = max(self.stats.automatic_max_ms[gen],
                                               1e3 * (time.perf_counter() - self._t0))
