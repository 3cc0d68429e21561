"""Strict decimal-number parsing shared by the cart parsers.

``float()`` alone is too lenient for wire data: it accepts ``"1_000"``, surrounding whitespace
and ``"infinity"`` spelled any way. The grammar here is C's ``strtod`` decimal subset (what
``printf("%f")``/``"%g"`` and Python's ``repr`` produce) plus ``nan``/``inf`` in any case, which
are let through on purpose so the validator counts them as ``non_finite`` rather than as a
formatting fault.
"""

from __future__ import annotations

import re

from drivers.cart.reasons import RejectReason
from drivers.errors import DecodeError

__all__ = ["parse_decimal", "shorten"]

_DECIMAL = re.compile(r"[+-]?(?:(?:\d+(?:\.\d*)?|\.\d+)(?:[eE][+-]?\d+)?|nan|inf(?:inity)?)", re.IGNORECASE)


def parse_decimal(text: str, name: str) -> float:
    """Parse ``text`` as a decimal number, or raise ``DecodeError("bad_number")`` naming ``name``.

    Args:
        text: The field, already stripped of the record's delimiters.
        name: The field's name for the error message (e.g. ``"vo2_ml_min"``).
    """
    if _DECIMAL.fullmatch(text) is None:
        raise DecodeError(RejectReason.BAD_NUMBER, f"{name} = {shorten(text)!r} is not a number")
    return float(text)


def shorten(text: str | bytes, limit: int = 60) -> str | bytes:
    """Cut ``text`` to ``limit`` characters for an error message (wire junk can be long)."""
    return text if len(text) <= limit else text[:limit] + ("..." if isinstance(text, str) else b"...")
