"""Fault injection specs shared by the virtual devices: what goes wrong, when, and for how long.

Every virtual device publishes a :class:`FaultCatalog` of the faults it can inject (the
virtual cart's is :data:`virtual_hw.cart.CART_FAULTS`); a fault is a frozen :class:`FaultSpec`
with a start and a duration or a count in **simulated seconds** (the session's breath clock,
:mod:`virtual_hw.clock`), so a fault hits the same breath at speed 1 and at ``max``. At run
time a device keeps a :class:`FaultSchedule`, which answers "is this fault on now?" and hands
out the counted events.

Text syntax (command line ``--fault SPEC``, repeatable; Python: ``catalog.parse(text)``)::

    KIND@START+DURATION   active from START for DURATION sim seconds:  disconnect@120+10
    KIND@STARTxCOUNT      the next COUNT events at or after START:       duplicate@300x2
    KIND@START            one event at or after START (= KIND@STARTx1):  garbage@60

``KIND`` is a lower-case name from the device's catalog (``a-z``, digits, ``-``); ``START`` and
``DURATION`` are decimal seconds (``90``, ``90.5``, ``1.5e3``), ``COUNT`` a positive integer. Two shapes
of fault exist (:class:`FaultShape`): a *window* fault is a state that lasts (a link that is
down, a stalled analyser, a bridge heartbeat that is not answered) and needs ``+DURATION``; an
*events* fault hits individual items (breaths, frames, profile transfers) and takes ``xCOUNT``
— or ``+DURATION`` to hit every item in that window.
"""

from __future__ import annotations

import math
import re
from collections import Counter
from collections.abc import Iterable
from dataclasses import dataclass
from enum import StrEnum

from virtual_hw.errors import FaultSpecError

__all__ = ["FaultCatalog", "FaultKind", "FaultSchedule", "FaultShape", "FaultSpec"]

_NUM = r"(?:\d+(?:\.\d*)?|\.\d+)(?:[eE][+-]?\d+)?"
_SPEC = re.compile(
    rf"(?P<kind>[a-z][a-z0-9-]*)@(?P<start>{_NUM})(?:\+(?P<duration>{_NUM})|x(?P<count>\d+))?"
)
_KIND_NAME = re.compile(r"[a-z][a-z0-9-]*")


class FaultShape(StrEnum):
    """How a fault kind is bounded."""

    WINDOW = "window"
    """A state that lasts: needs ``+DURATION``."""
    EVENTS = "events"
    """Hits individual items: ``xCOUNT`` (default 1) or every item in ``+DURATION``."""


@dataclass(frozen=True)
class FaultKind:
    """One kind of fault a device can inject.

    Attributes:
        name: The name used in specs (``"disconnect"``, ``"out-of-order"``).
        shape: :class:`FaultShape`.
        help: One line for ``--help``: what the device does while the fault is on.
    """

    name: str
    shape: FaultShape
    help: str

    def __post_init__(self) -> None:
        if not isinstance(self.name, str) or _KIND_NAME.fullmatch(self.name) is None:
            raise FaultSpecError(
                f"fault kind name {self.name!r}: expected lower-case letters, digits and '-'"
            )
        try:
            object.__setattr__(self, "shape", FaultShape(self.shape))
        except ValueError as err:
            raise FaultSpecError(
                f"fault kind {self.name!r}: shape {self.shape!r} is not one of "
                f"{[s.value for s in FaultShape]}"
            ) from err


def _format_number(value: float) -> str:
    return f"{value:g}" if value == float(f"{value:g}") else repr(value)


@dataclass(frozen=True)
class FaultSpec:
    """One fault to inject: a kind, a start, and a duration or a count.

    Attributes:
        kind: Fault kind name from the device's :class:`FaultCatalog`.
        start_s: When it begins, in simulated seconds (>= 0).
        duration_s: How long it lasts in simulated seconds (> 0), or None for a counted fault.
        count: How many events it hits (>= 1), or None for a windowed fault. With neither set
            the spec means one event (``count`` 1) once a catalog has checked it.

    Raises:
        FaultSpecError: A negative or non-finite time, a non-positive duration or count, or
            both a duration and a count.
    """

    kind: str
    start_s: float
    duration_s: float | None = None
    count: int | None = None

    def __post_init__(self) -> None:
        if not isinstance(self.kind, str) or _KIND_NAME.fullmatch(self.kind) is None:
            raise FaultSpecError(f"fault kind {self.kind!r}: expected a name such as 'disconnect'")
        if not _is_number(self.start_s) or not (math.isfinite(self.start_s) and self.start_s >= 0):
            raise FaultSpecError(f"{self.kind}: start_s={self.start_s!r} must be a finite time >= 0 s")
        if self.duration_s is not None and self.count is not None:
            raise FaultSpecError(
                f"{self.kind}: give a duration ({self.duration_s!r} s) or a count ({self.count!r}), "
                "not both"
            )
        if self.duration_s is not None and not (
            _is_number(self.duration_s) and math.isfinite(self.duration_s) and self.duration_s > 0
        ):
            raise FaultSpecError(
                f"{self.kind}: duration_s={self.duration_s!r} must be a finite duration > 0 s"
            )
        if self.count is not None and (
            isinstance(self.count, bool) or not isinstance(self.count, int) or self.count < 1
        ):
            raise FaultSpecError(f"{self.kind}: count={self.count!r} must be an integer >= 1")

    @property
    def end_s(self) -> float | None:
        """End of the window in simulated seconds (exclusive), or None for a counted fault."""
        return None if self.duration_s is None else self.start_s + self.duration_s

    def covers(self, t_s: float) -> bool:
        """True when this is a windowed fault and ``start_s <= t_s < end_s``."""
        end = self.end_s
        return end is not None and self.start_s <= t_s < end

    def __str__(self) -> str:
        text = f"{self.kind}@{_format_number(self.start_s)}"
        if self.duration_s is not None:
            return f"{text}+{_format_number(self.duration_s)}"
        return f"{text}x{self.count if self.count is not None else 1}"


def _is_number(value: object) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool)


@dataclass(frozen=True)
class FaultCatalog:
    """The faults one device can inject, and the parser of their specs.

    Attributes:
        device: Device name for messages (``"virtual cart"``).
        kinds: The fault kinds, in the order ``--help`` lists them.
    """

    device: str
    kinds: tuple[FaultKind, ...]

    def __post_init__(self) -> None:
        names = [k.name for k in self.kinds]
        if len(set(names)) != len(names):
            raise FaultSpecError(f"{self.device}: duplicate fault kind names in {names!r}")

    @property
    def names(self) -> tuple[str, ...]:
        """The kind names."""
        return tuple(k.name for k in self.kinds)

    def kind(self, name: str) -> FaultKind:
        """The kind called ``name``.

        Raises:
            FaultSpecError: No such kind for this device.
        """
        for k in self.kinds:
            if k.name == name:
                return k
        raise FaultSpecError(
            f"{self.device} has no fault {name!r}; choose one of {', '.join(self.names)}"
        )

    def check(self, spec: FaultSpec) -> FaultSpec:
        """Validate ``spec`` against this catalog and fill the default count.

        Returns:
            ``spec``, or a copy with ``count=1`` for an events fault given neither a duration
            nor a count.

        Raises:
            FaultSpecError: Unknown kind, or a window fault without a duration (or with a count).
        """
        if not isinstance(spec, FaultSpec):
            raise FaultSpecError(f"expected a FaultSpec, got {type(spec).__name__}: {spec!r}")
        kind = self.kind(spec.kind)
        if kind.shape is FaultShape.WINDOW and spec.duration_s is None:
            raise FaultSpecError(
                f"{self.device} fault {spec.kind!r} lasts a while: give a duration, "
                f"e.g. {spec.kind}@{_format_number(spec.start_s)}+10"
            )
        if kind.shape is FaultShape.EVENTS and spec.duration_s is None and spec.count is None:
            return FaultSpec(spec.kind, spec.start_s, count=1)
        return spec

    def parse(self, text: str) -> FaultSpec:
        """Parse one spec (module docstring) and check it against the catalog.

        Raises:
            FaultSpecError: The text does not parse, or does not fit the kind (the message shows
                the syntax and the kinds).
        """
        if not isinstance(text, str):
            raise FaultSpecError(f"fault spec {text!r}: expected text such as 'disconnect@120+10'")
        match = _SPEC.fullmatch(text.strip())
        if match is None:
            raise FaultSpecError(
                f"fault spec {text!r}: expected KIND@START+DURATION, KIND@STARTxCOUNT or "
                f"KIND@START (seconds), KIND one of {', '.join(self.names)}"
            )
        duration = match["duration"]
        count = match["count"]
        spec = FaultSpec(
            kind=match["kind"],
            start_s=float(match["start"]),
            duration_s=None if duration is None else float(duration),
            count=None if count is None else int(count),
        )
        return self.check(spec)

    def parse_all(self, specs: Iterable[str | FaultSpec]) -> tuple[FaultSpec, ...]:
        """Parse texts and check specs; the result is in the given order."""
        if isinstance(specs, str | FaultSpec):
            specs = (specs,)
        return tuple(self.parse(s) if isinstance(s, str) else self.check(s) for s in specs)

    def describe(self) -> str:
        """A help text: the syntax and one line per kind."""
        lines = [
            "fault SPEC: KIND@START+DURATION | KIND@STARTxCOUNT | KIND@START "
            "(simulated seconds); KIND:"
        ]
        for k in self.kinds:
            form = "+DURATION" if k.shape is FaultShape.WINDOW else "xCOUNT or +DURATION"
            lines.append(f"  {k.name} ({form}): {k.help}")
        return "\n".join(lines)


class FaultSchedule:
    """Run-time state of a device's faults: which windows are on, which counts are left.

    Window and events faults alike are answered from simulated times the device passes in; a
    counted fault is consumed one event at a time by :meth:`take`, so the same items are hit at
    every clock speed.

    Attributes:
        catalog: The device's catalog.
        specs: The checked specs.
        taken: Events handed out so far, by kind.
    """

    def __init__(self, catalog: FaultCatalog, specs: Iterable[str | FaultSpec] = ()) -> None:
        self.catalog = catalog
        self.specs: tuple[FaultSpec, ...] = catalog.parse_all(specs)
        self._left = [s.count for s in self.specs]
        self.taken: Counter[str] = Counter()

    def active(self, kind: str, t_s: float) -> bool:
        """True when a windowed spec of ``kind`` covers ``t_s``.

        Raises:
            FaultSpecError: ``kind`` is not in the catalog (a typo in device code).
        """
        self.catalog.kind(kind)
        return any(s.kind == kind and s.covers(t_s) for s in self.specs)

    def take(self, kind: str, t_s: float) -> bool:
        """Should the item at ``t_s`` be hit by a ``kind`` fault? Consumes one counted event.

        True when a windowed spec of ``kind`` covers ``t_s``, or a counted spec of ``kind``
        with ``start_s <= t_s`` has events left (the earliest-starting such spec gives one).
        """
        self.catalog.kind(kind)
        if any(s.kind == kind and s.covers(t_s) for s in self.specs):
            self.taken[kind] += 1
            return True
        best: int | None = None
        for i, s in enumerate(self.specs):
            left = self._left[i]
            if s.kind == kind and left and s.start_s <= t_s and (
                best is None or s.start_s < self.specs[best].start_s
            ):
                best = i
        if best is None:
            return False
        self._left[best] = (self._left[best] or 0) - 1
        self.taken[kind] += 1
        return True

    def left(self, kind: str) -> int:
        """Counted events of ``kind`` not handed out yet."""
        self.catalog.kind(kind)
        return sum(n or 0 for s, n in zip(self.specs, self._left, strict=True) if s.kind == kind)

    def next_boundary(self, after_s: float) -> float | None:
        """The first start or window end strictly after ``after_s`` (None if there is none).

        A device that only looks at its faults at discrete ticks wakes here as well, so a
        window begins and ends on time.
        """
        times = [s.start_s for s in self.specs] + [e for s in self.specs if (e := s.end_s) is not None]
        later = [t for t in times if t > after_s]
        return min(later) if later else None
