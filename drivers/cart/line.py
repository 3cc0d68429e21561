"""The hilbo-line format: one breath per ASCII line, with a sequence number and a CRC-16.

Line layout (full specification in ``drivers/cart/FORMAT.md``)::

    $HBR,<seq>,<t_s>,<vo2_ml_min>,<vco2_ml_min>,<ve_l_min>,<rer>,<hr_bpm>*<CRC>\\r\\n

- ``$`` starts the line; ``HBR`` ("hilbo breath record") names the sentence.
- ``seq``: unsigned 32-bit decimal integer, +1 per breath the cart emits, wrapping to 0 after
  4294967295. A gap shows breaths lost on the way; a repeat shows a duplicate.
- ``t_s``: breath time in seconds on the cart's clock (the session's time base).
- ``vo2_ml_min``, ``vco2_ml_min``: required, ml/min. ``ve_l_min`` (l/min), ``rer``, ``hr_bpm``:
  optional; an empty field means "not reported".
- Numbers are decimal (``[+-]digits[.digits][e[+-]digits]``, the ``strtod`` subset that
  ``printf("%.3f")`` and Python's ``repr`` produce); ``nan``/``inf`` decode, and the validator
  rejects them, so a fault can be reported faithfully rather than as a garbled line.
- ``CRC``: CRC-16/CCITT-FALSE (polynomial 0x1021, initial value 0xFFFF, no reflection, no final
  XOR; check value 0x29B1 for ``"123456789"``) over every byte between ``$`` and ``*``
  exclusive, as 4 hex digits (written uppercase, read in either case).
- The line ends with CR LF (LF alone, or CR alone, is accepted); at most 256 bytes without it.

Why a CRC-16 and not NMEA's 8-bit XOR: XOR is blind to any two flipped bits in the same bit
position and to swapped characters — ``...,1250.0,...`` and ``...,1520.0,...`` have the same XOR
— and a swapped digit in VO2 is exactly the silent error that would bias the estimate. CRC-16
detects all single, double and odd-count bit errors and every burst up to 16 bits in lines this
short, costs two more characters, and is in the standard library (:func:`binascii.crc_hqx`), so
a device implementation is a 10-line table-free loop.
"""

from __future__ import annotations

import binascii
import re
from dataclasses import dataclass

from drivers.cart._numbers import parse_decimal, shorten
from drivers.cart.errors import EncodeError
from drivers.cart.reasons import RejectReason
from drivers.cart.validate import SEQ_MODULUS
from drivers.errors import DecodeError
from hilbo_core.types import BreathRecord

__all__ = [
    "LINE_PREFIX",
    "MAX_LINE_BYTES",
    "SENTENCE",
    "HbrLineParser",
    "ParsedBreath",
    "crc16",
    "encode_line",
    "parse_line",
]

SENTENCE = "HBR"
"""The sentence identifier; an incompatible future layout gets a new one (e.g. ``HBR2``)."""
LINE_PREFIX = b"$" + SENTENCE.encode("ascii") + b","
MAX_LINE_BYTES = 256
"""Longest accepted line, without its terminator (a full line with 17-digit floats is ~170)."""

_N_FIELDS = 8  # sentence, seq, t_s, vo2, vco2, ve, rer, hr
_HEX = re.compile(rb"[0-9A-Fa-f]{0,4}")
_SEQ = re.compile(r"\d{1,10}")
_COMMENT = b"#"


@dataclass(frozen=True, slots=True)
class ParsedBreath:
    """A decoded breath and the sequence number it carried (None for formats without one)."""

    record: BreathRecord
    seq: int | None = None


def crc16(data: bytes) -> int:
    """CRC-16/CCITT-FALSE of ``data`` (poly 0x1021, init 0xFFFF); ``crc16(b"123456789") == 0x29B1``."""
    return binascii.crc_hqx(data, 0xFFFF)


def _fmt(value: float | None) -> str:
    # repr() is the shortest text that reads back to the same double, so encode→parse is exact.
    return "" if value is None else repr(float(value))


def encode_line(record: BreathRecord, seq: int) -> bytes:
    """Encode one breath as a hilbo-line, terminator included.

    Args:
        record: The breath. Non-finite values are written as ``nan``/``inf`` (the virtual cart
            uses that to inject faults); the receiving validator rejects them.
        seq: Sequence number in ``[0, 2**32)``; callers wrap with ``seq % 2**32``.

    Returns:
        ASCII bytes ending in ``b"\\r\\n"``.

    Raises:
        EncodeError: ``seq`` is not an integer in range.
    """
    if isinstance(seq, bool) or not isinstance(seq, int) or not 0 <= seq < SEQ_MODULUS:
        raise EncodeError(f"seq = {seq!r}: expected an integer in [0, {SEQ_MODULUS})")
    body = ",".join(
        [
            SENTENCE,
            str(seq),
            _fmt(record.t_s),
            _fmt(record.vo2_ml_min),
            _fmt(record.vco2_ml_min),
            _fmt(record.ve_l_min),
            _fmt(record.rer),
            _fmt(record.hr_bpm),
        ]
    ).encode("ascii")
    return b"$" + body + b"*" + f"{crc16(body):04X}".encode("ascii") + b"\r\n"


def parse_line(line: bytes) -> ParsedBreath:
    """Decode one hilbo-line (with or without its terminator).

    The checks run from the outside in, so each fault gets the most telling reason: length,
    prefix, checksum presence, checksum value, then fields.

    Args:
        line: The raw bytes of one line.

    Returns:
        The record and its sequence number. Values are not range-checked here; that is
        :class:`~drivers.cart.validate.BreathValidator`'s job.

    Raises:
        DecodeError: With ``reason`` one of ``too_long``, ``garbage``, ``truncated``,
            ``bad_checksum``, ``field_count``, ``bad_seq``, ``missing_field``, ``bad_number``
            (see :class:`~drivers.cart.reasons.RejectReason`).
    """
    line = line.rstrip(b"\r\n")
    if len(line) > MAX_LINE_BYTES:
        raise DecodeError(RejectReason.TOO_LONG, f"{len(line)} bytes > {MAX_LINE_BYTES}")
    if not line.startswith(LINE_PREFIX):
        if LINE_PREFIX.startswith(line):
            raise DecodeError(RejectReason.TRUNCATED, f"{line!r} ends inside the sentence name")
        raise DecodeError(RejectReason.GARBAGE, f"{shorten(line)!r} is not a ${SENTENCE} line")
    star = line.rfind(b"*")
    if star < 0:
        raise DecodeError(RejectReason.TRUNCATED, f"{shorten(line)!r} has no '*' checksum")
    given = line[star + 1 :]
    if _HEX.fullmatch(given) is None:
        raise DecodeError(RejectReason.BAD_CHECKSUM, f"checksum field {shorten(given)!r}")
    if len(given) < 4:
        raise DecodeError(RejectReason.TRUNCATED, f"checksum field {given!r} has < 4 digits")
    body = line[1:star]
    expected = crc16(body)
    if int(given, 16) != expected:
        raise DecodeError(RejectReason.BAD_CHECKSUM, f"checksum {given.decode()} != computed {expected:04X}")
    try:
        text = body.decode("ascii")
    except UnicodeDecodeError as err:
        raise DecodeError(RejectReason.GARBAGE, f"non-ASCII byte at {err.start}") from err
    fields = text.split(",")
    if len(fields) != _N_FIELDS:
        raise DecodeError(
            RejectReason.FIELD_COUNT, f"{len(fields)} fields, expected {_N_FIELDS}: {shorten(text)!r}"
        )
    _, seq_s, t_s, vo2, vco2, ve, rer, hr = fields
    if _SEQ.fullmatch(seq_s) is None or int(seq_s) >= SEQ_MODULUS:
        raise DecodeError(RejectReason.BAD_SEQ, f"seq = {shorten(seq_s)!r}")
    record = BreathRecord(
        t_s=_required(t_s, "t_s"),
        vo2_ml_min=_required(vo2, "vo2_ml_min"),
        vco2_ml_min=_required(vco2, "vco2_ml_min"),
        ve_l_min=_optional(ve, "ve_l_min"),
        rer=_optional(rer, "rer"),
        hr_bpm=_optional(hr, "hr_bpm"),
    )
    return ParsedBreath(record=record, seq=int(seq_s))


def _required(text: str, name: str) -> float:
    if not text:
        raise DecodeError(RejectReason.MISSING_FIELD, f"{name} is empty")
    return parse_decimal(text, name)


def _optional(text: str, name: str) -> float | None:
    return parse_decimal(text, name) if text else None


class HbrLineParser:
    """Line parser for the hilbo-line format, as used by :class:`~drivers.cart.stream.BreathStream`.

    Lines starting with ``#`` are comments (recorded files may carry a header) and are skipped.
    """

    format_name = "hilbo-line"

    def parse(self, line: bytes) -> ParsedBreath | None:
        """Decode ``line``; None for a comment. Raises :class:`DecodeError` like :func:`parse_line`."""
        if line.startswith(_COMMENT):
            return None
        return parse_line(line)
