"""Validation of decoded breaths, shared by every cart format and transport.

A :class:`BreathValidator` sits after the parser: it rejects records that are well formed but
cannot be a real breath (NaN/inf, a negative time, values outside physiological limits) or that
break the stream's order (a time not later than the last accepted breath, a repeated sequence
number). It never raises for bad data: :meth:`BreathValidator.check` returns the record or
``None`` and counts the reason in :attr:`BreathValidator.counters`. Gaps (a long interval between
breaths, skipped sequence numbers) are *not* rejected: whether to pause estimation over a gap is
the bridge's decision, so the validator only counts them.
"""

from __future__ import annotations

import logging
from collections import Counter, deque
from collections.abc import Mapping
from dataclasses import dataclass, fields
from typing import Any

from drivers.cart._options import check_keys, check_mapping, number
from drivers.cart.reasons import RejectReason
from drivers.errors import DriverConfigError
from hilbo_core.types import BreathRecord

__all__ = ["SEQ_MODULUS", "BreathValidator", "PhysioLimits"]

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
                    f"limits.{f.name} = {value!r}: expected a pair [low, high] of numbers"
                )
            lo = number(value[0], f"limits.{f.name}[0]", lo=0.0)
            hi = number(value[1], f"limits.{f.name}[1]", lo=0.0)
            if not lo < hi:
                raise DriverConfigError(
                    f"limits.{f.name} = {value!r}: expected low < high, got {lo:g} >= {hi:g}"
                )
            object.__setattr__(self, f.name, (lo, hi))
        if self.vo2_ml_min[0] <= 0.0:
            raise DriverConfigError(
                f"limits.vo2_ml_min = {self.vo2_ml_min!r}: the low bound must be > 0 "
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
            raise DriverConfigError(f"{where}: {err}") from err


class BreathValidator:
    """Stateful filter that passes plausible, in-order breaths and counts the rest by reason.

    Attributes:
        limits: The physiological limits in force.
        counters: Rejected records per :class:`RejectReason` (parsers' rejects are counted here
            too, through :meth:`reject`).
        accepted: Number of records passed.
        missing_seq: Sequence numbers skipped between accepted records — breaths the cart sent
            that never arrived (or arrived corrupted).
        seq_resets: Times the sequence number went backwards while time went forwards (the cart
            restarted its counter); such records are accepted.
    """

    def __init__(self, limits: PhysioLimits | None = None, *, history: int = 64) -> None:
        """Create a validator.

        Args:
            limits: Physiological limits; defaults to :class:`PhysioLimits()`.
            history: How many recently accepted breaths to remember to tell a duplicate of an
                older breath (``duplicate``) from a genuinely late one (``out_of_order``).
        """
        if isinstance(history, bool) or not isinstance(history, int) or history < 1:
            raise DriverConfigError(f"history = {history!r}: expected an integer >= 1")
        self.limits = limits if limits is not None else PhysioLimits()
        self.counters: Counter[str] = Counter()
        self.accepted = 0
        self.missing_seq = 0
        self.seq_resets = 0
        self._last_t: float | None = None
        self._last_seq: int | None = None
        self._recent_t: deque[float] = deque(maxlen=history)
        self._recent_seq: deque[int] = deque(maxlen=history)

    @property
    def rejected(self) -> int:
        """Total number of rejected records and lines."""
        return sum(self.counters.values())

    def reject(self, reason: str) -> None:
        """Count one rejected line or record (used by parsers and streams for decode errors)."""
        try:
            key: str = RejectReason(reason)
        except ValueError:
            key = str(reason)
        self.counters[key] += 1

    def reset(self) -> None:
        """Forget the stream order (last time and sequence number); keep all counters.

        Call it when the cart is known to have restarted its clock; without it every breath
        after a clock restart is rejected as ``out_of_order``.
        """
        self._last_t = None
        self._last_seq = None
        self._recent_t.clear()
        self._recent_seq.clear()

    def check(self, record: BreathRecord, seq: int | None = None) -> BreathRecord | None:
        """Return ``record`` if it is plausible and in order, else count the reason and return None.

        Args:
            record: The decoded breath.
            seq: Its sequence number when the format carries one (hilbo-line), else None.

        Returns:
            The same record, or None when rejected. Never raises for bad data.
        """
        reason = self._physio_reason(record) or self._order_reason(record, seq)
        if reason is not None:
            self.counters[reason] += 1
            _log.debug("rejected breath (%s): %r seq=%r", reason.value, record, seq)
            return None
        self._accept(record, seq)
        return record

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

    def _order_reason(self, record: BreathRecord, seq: int | None) -> RejectReason | None:
        if self._last_t is None:
            return None
        if seq is not None and seq in self._recent_seq:
            return RejectReason.DUPLICATE
        if record.t_s in self._recent_t:
            return RejectReason.DUPLICATE
        if record.t_s < self._last_t:
            return RejectReason.OUT_OF_ORDER
        return None

    def _accept(self, record: BreathRecord, seq: int | None) -> None:
        if seq is not None and self._last_seq is not None:
            step = (seq - self._last_seq) % SEQ_MODULUS
            if step < SEQ_MODULUS // 2:
                self.missing_seq += step - 1
            else:
                # Backwards sequence but forward time: the cart restarted its counter.
                self.seq_resets += 1
                _log.info("cart sequence number restarted: %d after %d", seq, self._last_seq)
        self._last_t = record.t_s
        self._recent_t.append(record.t_s)
        if seq is not None:
            self._last_seq = seq
            self._recent_seq.append(seq)
        self.accepted += 1


def _within(value: float, bounds: tuple[float, float]) -> bool:
    return bounds[0] <= value <= bounds[1]
