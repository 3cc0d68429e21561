"""Validation of decoded breaths, shared by every cart format and transport.

A :class:`BreathValidator` sits after the parser: it rejects records that are well formed but
cannot be a real breath (NaN/inf, a negative time, values outside physiological limits) or that
break the stream's order (a time not later than the last accepted breath, a repeated sequence
number). It never raises for bad data: :meth:`BreathValidator.check` returns the record or
``None`` and counts the reason in :attr:`BreathValidator.counters`. Gaps (a long interval between
breaths, skipped sequence numbers) are *not* rejected: whether to pause estimation over a gap is
the bridge's decision, so the validator only counts them. A cart clock that resets or jumps
(a restart, a clock set to another day) is not rejected for good either: after a few breaths
confirm the new clock the validator re-anchors, and the breaths go on on a monotonic session
time base (see :class:`BreathValidator`).
"""

from __future__ import annotations

import itertools
import logging
import statistics
from collections import Counter, deque
from collections.abc import Mapping
from dataclasses import dataclass, fields, replace
from typing import Any

from drivers.cart._options import check_keys, check_mapping, number
from drivers.cart.reasons import ReanchorKind, RejectReason
from drivers.errors import DriverConfigError
from hilbo_core.types import BreathRecord

__all__ = [
    "DEFAULT_CONFIRM_BREATHS",
    "DEFAULT_MAX_TIME_JUMP_S",
    "SEQ_MODULUS",
    "BreathValidator",
    "PhysioLimits",
    "Reanchor",
]

_log = logging.getLogger(__name__)

SEQ_MODULUS = 2**32
"""Sequence numbers are unsigned 32-bit and wrap to 0 after ``SEQ_MODULUS - 1``."""


@dataclass(frozen=True, slots=True)
class PhysioLimits:
    """Closed ranges ``(low, high)`` outside which a breath is physiologically impossible.

    The defaults are deliberately wide — they must never reject a real breath of a healthy adult
    walking with an exosuit, only sensor faults and corrupted numbers. Resting VO2 of a small
    adult is ~200 ml/min and elite VO2max ~6000 ml/min; single-breath RER is noisier than a
    steady-state RER (0.7–1.0), hence 0.5–1.6.

    Attributes:
        vo2_ml_min: VO2 range in ml/min; the low bound must be > 0 (RER divides by VO2).
        vco2_ml_min: VCO2 range in ml/min (default: VO2 range times the RER range).
        rer: Range of the reported RER and of the ratio VCO2/VO2 (dimensionless).
        ve_l_min: Minute-ventilation range in l/min (checked only when reported).
        hr_bpm: Heart-rate range in beats/min (checked only when reported).
    """

    vo2_ml_min: tuple[float, float] = (100.0, 8000.0)
    vco2_ml_min: tuple[float, float] = (50.0, 12800.0)
    rer: tuple[float, float] = (0.5, 1.6)
    ve_l_min: tuple[float, float] = (1.0, 300.0)
    hr_bpm: tuple[float, float] = (25.0, 250.0)

    def __post_init__(self) -> None:
        for f in fields(self):
            value = getattr(self, f.name)
            if not isinstance(value, tuple | list) or len(value) != 2:
                raise DriverConfigError(
                    f"{f.name} = {value!r}: expected a pair [low, high] of numbers"
                )
            lo = number(value[0], f"{f.name}[0]", lo=0.0)
            hi = number(value[1], f"{f.name}[1]", lo=0.0)
            if not lo < hi:
                raise DriverConfigError(
                    f"{f.name} = [{lo:g}, {hi:g}]: expected [low, high] with low < high"
                )
            object.__setattr__(self, f.name, (lo, hi))
        if self.vo2_ml_min[0] <= 0.0:
            raise DriverConfigError(
                f"vo2_ml_min = {list(self.vo2_ml_min)!r}: the low bound must be > 0 "
                "(the RER check divides by VO2)"
            )

    @classmethod
    def from_dict(cls, data: Mapping[str, Any], where: str = "limits") -> PhysioLimits:
        """Build from a config table; keys are the attribute names, values ``[low, high]``.

        Raises:
            DriverConfigError: Unknown key, or a value that is not an increasing pair of numbers.
        """
        data = check_mapping(data, where)
        check_keys(data, [f.name for f in fields(cls)], where)
        try:
            return cls(**{k: tuple(v) if isinstance(v, list) else v for k, v in data.items()})
        except DriverConfigError as err:
            raise DriverConfigError(f"{where}.{err}") from err  # "cart.limits.hr_bpm = ..."


@dataclass(frozen=True, slots=True)
class Reanchor:
    """One move of the validator's time base onto a new cart clock.

    Attributes:
        kind: Why (a cart clock reset, a forward jump, or :meth:`BreathValidator.reset`).
        index: 1-based count of this re-anchor in the session (``BreathValidator.reanchors``).
        raw_t_s: Cart time of the first breath on the new clock, s.
        t_s: Session time that breath maps to (last accepted session time + one typical
            breath interval), s.
        offset_s: Added to every later cart time until the next re-anchor, s.
        dropped: Breaths of the new clock rejected while it was being confirmed.
    """

    kind: ReanchorKind
    index: int
    raw_t_s: float
    t_s: float
    offset_s: float
    dropped: int


DEFAULT_MAX_TIME_JUMP_S = 300.0
"""Longest forward step between breaths taken as a gap rather than a jump of the cart's clock.

A gap is a dropout (the analyser stalled, the link was down): breaths after it keep their
times. Five minutes is longer than any dropout a session survives anyway (the bridge pauses
after ``cart_data_timeout_s``) and far shorter than the jump of a clock set to another day."""

DEFAULT_CONFIRM_BREATHS = 2
"""Consecutive breaths that must continue a new cart clock before the validator re-anchors:
one breath with an absurd time costs only itself, a real reset costs this many breaths (its
first one on the new clock and the next ones until this many; the breath after them, which
confirms it, is accepted)."""

_TYPICAL_INTERVAL_S = 3.0  # walking adults breathe ~20/min; used only with no interval history
_INTERVAL_HISTORY = 16
_MIN_INTERVAL_S = 1e-3  # keeps the re-anchored session time strictly after the last breath


class BreathValidator:
    """Stateful filter that passes plausible, in-order breaths and counts the rest by reason.

    Time base: the records it returns carry the *session* time, the cart time plus
    :attr:`offset_s` (0 until the first re-anchor, so a well-behaved cart's times pass unchanged
    and the very object is returned). When the cart's clock resets (a restart starts it near 0)
    or jumps forwards by more than ``max_time_jump_s``, the breaths on the new clock are first
    rejected (``out_of_order`` / ``time_jump``) and held as a *pending* new time base; once
    ``confirm_breaths`` more breaths continue that clock (each later than the one before by at
    most ``max_time_jump_s``, none fitting the old clock) the validator re-anchors: the offset
    is set so the new clock's first breath lands one typical breath interval (median of the
    last accepted intervals) after the last accepted breath, and the confirming breath is
    returned on that base. A breath that fits the old clock again cancels the pending base, so
    a single absurd time costs only that breath. Each re-anchor increments :attr:`reanchors`,
    sets :attr:`last_reanchor` and logs a warning: the bridge compares :attr:`reanchors` with
    the value it saw to log the event and re-measure the evaluation in progress.

    Attributes:
        limits: The physiological limits in force.
        max_time_jump_s: Longest forward step accepted as a gap, s.
        confirm_breaths: Breaths after the first one on a new clock that confirm it.
        counters: Rejected records per :class:`RejectReason` (parsers' rejects are counted here
            too, through :meth:`reject`).
        accepted: Number of records passed.
        missing_seq: Sequence numbers skipped between accepted records — breaths the cart sent
            that never arrived (or arrived corrupted).
        seq_resets: Times the sequence number went backwards while time went forwards (the cart
            restarted its counter); such records are accepted.
        reanchors: Times the time base moved to a new cart clock (all kinds).
        reanchor_counts: The same per :class:`ReanchorKind`.
        last_reanchor: The latest re-anchor, or None.
    """

    def __init__(
        self,
        limits: PhysioLimits | None = None,
        *,
        history: int = 64,
        max_time_jump_s: float = DEFAULT_MAX_TIME_JUMP_S,
        confirm_breaths: int = DEFAULT_CONFIRM_BREATHS,
    ) -> None:
        """Create a validator.

        Args:
            limits: Physiological limits; defaults to :class:`PhysioLimits()`.
            history: How many recently accepted breaths to remember to tell a duplicate of an
                older breath (``duplicate``) from a genuinely late one (``out_of_order``).
            max_time_jump_s: Longest forward step between breaths that is a gap, not a jump of
                the cart's clock, s (> 0).
            confirm_breaths: Breaths (>= 1) that must continue a new cart clock, after its first
                one, before the validator re-anchors on it.

        Raises:
            DriverConfigError: A value of the wrong type or out of range.
        """
        if isinstance(history, bool) or not isinstance(history, int) or history < 1:
            raise DriverConfigError(f"history = {history!r}: expected an integer >= 1")
        if (
            isinstance(confirm_breaths, bool)
            or not isinstance(confirm_breaths, int)
            or confirm_breaths < 1
        ):
            raise DriverConfigError(f"confirm_breaths = {confirm_breaths!r}: expected an integer >= 1")
        self.max_time_jump_s = number(max_time_jump_s, "max_time_jump_s", lo=0.0)
        if not 0.0 < self.max_time_jump_s < float("inf"):
            raise DriverConfigError(
                f"max_time_jump_s = {max_time_jump_s!r}: expected a finite number of seconds > 0"
            )
        self.confirm_breaths = confirm_breaths
        self.limits = limits if limits is not None else PhysioLimits()
        self.counters: Counter[str] = Counter()
        self.accepted = 0
        self.missing_seq = 0
        self.seq_resets = 0
        self.reanchors = 0
        self.reanchor_counts: Counter[str] = Counter()
        self.last_reanchor: Reanchor | None = None
        self._offset_s = 0.0
        self._last_t: float | None = None  # cart time of the last accepted breath
        self._last_session_t: float | None = None
        self._last_seq: int | None = None
        self._recent_t: deque[float] = deque(maxlen=history)
        self._recent_seq: deque[int] = deque(maxlen=history)
        self._intervals: deque[float] = deque(maxlen=_INTERVAL_HISTORY)
        # The breaths of a candidate new cart clock: (cart time, seq), oldest first.
        self._pending: list[tuple[float, int | None]] = []
        self._pending_kind: ReanchorKind | None = None
        self._reanchor_next = False

    @property
    def rejected(self) -> int:
        """Total number of rejected records and lines."""
        return sum(self.counters.values())

    @property
    def offset_s(self) -> float:
        """Session time minus cart time of the breaths returned now, s (0 before any re-anchor)."""
        return self._offset_s

    @property
    def pending(self) -> int:
        """Breaths held (and already counted as rejected) on a candidate new cart clock."""
        return len(self._pending)

    def reject(self, reason: str) -> None:
        """Count one rejected line or record (used by parsers and streams for decode errors)."""
        try:
            key: str = RejectReason(reason)
        except ValueError:
            key = str(reason)
        self.counters[key] += 1

    def reset(self) -> None:
        """Forget the stream order (last time and sequence number); keep all counters.

        Call it when the cart is known to have restarted its clock: the next plausible breath
        re-anchors at once (kind ``reset``, no confirmation) and the session time goes on.
        """
        self._last_t = None
        self._last_seq = None
        self._recent_t.clear()
        self._recent_seq.clear()
        self._pending.clear()
        self._pending_kind = None
        self._reanchor_next = self._last_session_t is not None

    def check(self, record: BreathRecord, seq: int | None = None) -> BreathRecord | None:
        """Return ``record`` if it is plausible and in order, else count the reason and return None.

        Args:
            record: The decoded breath, its time on the cart's clock.
            seq: Its sequence number when the format carries one (hilbo-line), else None.

        Returns:
            The record on the session time base (``record`` itself while :attr:`offset_s` is
            0, else a copy with ``t_s`` shifted), or None when rejected. Never raises for bad
            data.
        """
        reason = self._physio_reason(record)
        if reason is None and self._reanchor_next:
            self._reanchor_next = False
            self._reanchor(ReanchorKind.RESET, [(record.t_s, seq)], dropped=0)
            self._accept(record, seq)
            return self._on_session_base(record)
        if reason is None:
            reason, jump = self._order_reason(record, seq)
            if reason is None:
                self._pending.clear()  # the old clock goes on: whatever was pending was bad
                self._pending_kind = None
            elif jump is not None and self._continue_pending(record, seq, jump):
                self._reanchor(self._pending_kind or jump, self._pending, dropped=len(self._pending) - 1)
                self._accept(record, seq)
                return self._on_session_base(record)
        if reason is not None:
            self.counters[reason] += 1
            _log.debug("rejected breath (%s): %r seq=%r", reason.value, record, seq)
            return None
        self._accept(record, seq)
        return self._on_session_base(record)

    def _physio_reason(self, record: BreathRecord) -> RejectReason | None:
        if not record.is_finite():
            return RejectReason.NON_FINITE
        if record.t_s < 0.0:
            return RejectReason.NEGATIVE_TIME
        lim = self.limits
        if not _within(record.vo2_ml_min, lim.vo2_ml_min):
            return RejectReason.VO2_RANGE
        if not _within(record.vco2_ml_min, lim.vco2_ml_min):
            return RejectReason.VCO2_RANGE
        # VO2 > 0 here (limits guarantee a positive lower bound), so the ratio is defined.
        if not _within(record.vco2_ml_min / record.vo2_ml_min, lim.rer):
            return RejectReason.RER_RANGE
        if record.rer is not None and not _within(record.rer, lim.rer):
            return RejectReason.RER_RANGE
        if record.ve_l_min is not None and not _within(record.ve_l_min, lim.ve_l_min):
            return RejectReason.VE_RANGE
        if record.hr_bpm is not None and not _within(record.hr_bpm, lim.hr_bpm):
            return RejectReason.HR_RANGE
        return None

    def _order_reason(
        self, record: BreathRecord, seq: int | None
    ) -> tuple[RejectReason | None, ReanchorKind | None]:
        """The reject reason on the current clock, and which jump the record could start."""
        if self._last_t is None:
            return None, None
        t = record.t_s
        if t in self._recent_t:
            return RejectReason.DUPLICATE, None  # a breath sent again: never a new clock
        step = t - self._last_t
        if step < 0.0:
            reason = RejectReason.DUPLICATE if seq is not None and seq in self._recent_seq else (
                RejectReason.OUT_OF_ORDER
            )
            return reason, ReanchorKind.CLOCK_RESET
        if step > self.max_time_jump_s:
            return RejectReason.TIME_JUMP, ReanchorKind.TIME_JUMP
        if seq is not None and seq in self._recent_seq:
            return RejectReason.DUPLICATE, None
        if self._last_session_t is not None and t + self._offset_s <= self._last_session_t:
            # Distinct cart times that the offset rounds to one session time (sub-ns apart).
            return RejectReason.DUPLICATE, None
        return None, None

    def _continue_pending(self, record: BreathRecord, seq: int | None, jump: ReanchorKind) -> bool:
        """Hold a breath off the current clock; True when it confirms the pending new clock."""
        t = record.t_s
        if self._pending and 0.0 < t - self._pending[-1][0] <= self.max_time_jump_s:
            self._pending.append((t, seq))
        else:  # the first breath off the clock, or one that fits neither clock: start again
            self._pending = [(t, seq)]
            self._pending_kind = jump
        return len(self._pending) > self.confirm_breaths

    def _reanchor(
        self, kind: ReanchorKind, chain: list[tuple[float, int | None]], *, dropped: int
    ) -> None:
        """Move the time base so ``chain[0]`` lands one typical interval after the last breath."""
        chain = list(chain)
        first_t = chain[0][0]
        if self._intervals:
            interval = statistics.median(self._intervals)
        elif len(chain) > 1:
            interval = (chain[-1][0] - first_t) / (len(chain) - 1)
        else:
            interval = _TYPICAL_INTERVAL_S
        interval = max(interval, _MIN_INTERVAL_S)
        last = self._last_session_t if self._last_session_t is not None else first_t - interval
        new_first = last + interval
        self._offset_s = new_first - first_t
        self.reanchors += 1
        self.reanchor_counts[kind] += 1
        self.last_reanchor = Reanchor(kind, self.reanchors, first_t, new_first, self._offset_s, dropped)
        _log.warning(
            "cart clock %s: breath time %.3f s after %s s; re-anchored (session time %.3f s, "
            "offset %+.3f s, %d breath(s) dropped while confirming)",
            kind.value, first_t, "?" if self._last_t is None else f"{self._last_t:.3f}",
            new_first, self._offset_s, dropped,
        )
        # The new clock's breaths, not the old one's, are what later breaths are compared with.
        self._recent_t.clear()
        self._recent_seq.clear()
        self._intervals.clear()
        for (a, _), (b, _) in itertools.pairwise(chain):
            self._intervals.append(b - a)
        for t, s in chain[:-1]:
            self._recent_t.append(t)
            if s is not None:
                self._recent_seq.append(s)
        self._last_t = None
        self._last_seq = None  # a sequence restart with the clock is not "missing" breaths
        self._pending.clear()
        self._pending_kind = None

    def _on_session_base(self, record: BreathRecord) -> BreathRecord:
        if self._offset_s == 0.0:
            return record
        return replace(record, t_s=record.t_s + self._offset_s)

    def _accept(self, record: BreathRecord, seq: int | None) -> None:
        if seq is not None and self._last_seq is not None:
            step = (seq - self._last_seq) % SEQ_MODULUS
            if step < SEQ_MODULUS // 2:
                self.missing_seq += step - 1
            else:
                # Backwards sequence but forward time: the cart restarted its counter.
                self.seq_resets += 1
                _log.info("cart sequence number restarted: %d after %d", seq, self._last_seq)
        if self._last_t is not None:
            self._intervals.append(record.t_s - self._last_t)
        self._last_t = record.t_s
        self._last_session_t = record.t_s + self._offset_s
        self._recent_t.append(record.t_s)
        if seq is not None:
            self._last_seq = seq
            self._recent_seq.append(seq)
        self.accepted += 1


def _within(value: float, bounds: tuple[float, float]) -> bool:
    return bounds[0] <= value <= bounds[1]
