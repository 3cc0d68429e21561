"""Why a line or a breath was rejected: the keys of every reject counter of the cart drivers."""

from __future__ import annotations

from enum import StrEnum

__all__ = ["ReanchorKind", "RejectReason"]


class RejectReason(StrEnum):
    """Short machine-readable reasons; the value is the string used in counters and logs.

    Being a :class:`~enum.StrEnum`, a member compares and hashes equal to its value, so
    ``counters["bad_checksum"]`` and ``counters[RejectReason.BAD_CHECKSUM]`` are the same entry.
    """

    # Framing (transports): the byte stream could not be cut into a whole line.
    TOO_LONG = "too_long"
    """A line exceeded the configured maximum length (its bytes are discarded)."""
    TRUNCATED = "truncated"
    """A line ended early: no checksum, or a partial line cut off by a dropped connection."""
    OVERFLOW = "overflow"
    """A datagram was dropped because the reader fell too far behind."""

    # Decoding (parsers): the line is whole but not a well-formed record.
    GARBAGE = "garbage"
    """Not a record at all: not text, not an ``$HBR`` sentence, control characters."""
    BAD_CHECKSUM = "bad_checksum"
    """The checksum field is not 4 hex digits or does not match the line."""
    FIELD_COUNT = "field_count"
    """The line has the wrong number of fields (or a CSV row is too short)."""
    BAD_SEQ = "bad_seq"
    """The sequence number is not an unsigned 32-bit decimal integer."""
    BAD_NUMBER = "bad_number"
    """A numeric field is not a decimal number."""
    BAD_TIME = "bad_time"
    """A clock-format time field (``hh:mm:ss``, ``mm:ss``) does not parse."""
    MISSING_FIELD = "missing_field"
    """A required field (time, VO2, VCO2) is empty, or a vendor table row holds text but none in
    the columns a breath is read from (another field separator?)."""
    EVENT = "event"
    """A vendor's events block: its marker row (Parvo's ``Events``) and the rows under it that
    are not breaths (notes such as ``0.60,Start exercise``)."""

    # Validation (BreathValidator): a well-formed record that cannot be a real breath.
    NON_FINITE = "non_finite"
    """A value is NaN or infinite."""
    NEGATIVE_TIME = "negative_time"
    """The breath time is below zero."""
    OUT_OF_ORDER = "out_of_order"
    """The breath time is earlier than the last accepted breath (a late breath, or the first
    breaths after a cart clock reset, before the validator re-anchors)."""
    TIME_JUMP = "time_jump"
    """The breath time is later than the last accepted breath by more than ``max_time_jump_s``:
    a single absurd time, or the first breaths on a new cart time base before the validator
    re-anchors on it."""
    DUPLICATE = "duplicate"
    """Same sequence number or same breath time as a recently accepted breath."""
    VO2_RANGE = "vo2_range"
    """VO2 is outside the physiological limits."""
    VCO2_RANGE = "vco2_range"
    """VCO2 is outside the physiological limits."""
    RER_RANGE = "rer_range"
    """The reported RER, or VCO2/VO2, is outside the physiological limits."""
    VE_RANGE = "ve_range"
    """Minute ventilation is outside the physiological limits."""
    HR_RANGE = "hr_range"
    """Heart rate is outside the physiological limits."""


class ReanchorKind(StrEnum):
    """Why the validator moved its time base (the keys of ``BreathValidator.reanchor_counts``)."""

    CLOCK_RESET = "clock_reset"
    """The cart's clock went backwards and stayed there (a cart restart resets it near 0)."""
    TIME_JUMP = "time_jump"
    """The cart's clock jumped forwards by more than ``max_time_jump_s`` and stayed there."""
    RESET = "reset"
    """The caller said so (:meth:`BreathValidator.reset`)."""
