"""Line → breath: the parser interface and the synchronous parse-and-validate step.

Everything that turns lines into validated breaths goes through :func:`process_line`, so the
async :class:`~drivers.cart.stream.BreathStream` and the whole-file reader
:func:`read_breath_file` count rejects the same way.
"""

from __future__ import annotations

import itertools
import logging
from collections import Counter
from collections.abc import Iterable, Iterator
from os import PathLike
from typing import Protocol

from drivers.cart._numbers import shorten
from drivers.cart.errors import CartError
from drivers.cart.framing import DEFAULT_MAX_LINE_BYTES, LineFramer
from drivers.cart.line import ParsedBreath
from drivers.cart.validate import BreathValidator
from drivers.errors import DecodeError
from drivers.files import MAX_CART_FILE_BYTES, open_regular_file
from hilbo_core.types import BreathRecord

__all__ = [
    "DEFAULT_MAX_LEADING_REJECTS",
    "BreathParser",
    "BreathSpacingGuard",
    "LeadingRejectGuard",
    "check_breath_spacing",
    "describe_record",
    "iter_breaths",
    "process_line",
    "read_breath_file",
]

DEFAULT_MAX_LEADING_REJECTS = 20
"""Records rejected before the first accepted one after which a stream stops (``[cart]
max_leading_rejects``): a wrong unit, time format or column map rejects *every* breath, and a
session that waits on such a stream only ever says "0 evaluations"."""

# What to look at in the config for the reason that rejected every record.
_HINTS = {
    "bad_time": "the time format ([cart.csv] time_format, or the preset)",
    "bad_number": "the decimal mark ([cart.csv] decimal) and delimiter",
    "missing_field": "the column map ([cart.csv] *_column) and delimiter",
    "field_count": "the delimiter and the column map",
    "garbage": "[cart] format (hilbo-line, csv or a vendor preset)",
    "bad_checksum": "[cart] format (hilbo-line, csv or a vendor preset)",
    "truncated": "[cart] format (hilbo-line, csv or a vendor preset)",
    "vo2_range": "the gas units ([cart.csv] vo2_unit / vco2_unit: ml/min or l/min) and [cart.limits]",
    "vco2_range": "the gas units ([cart.csv] vo2_unit / vco2_unit: ml/min or l/min) and [cart.limits]",
    "rer_range": "the VO2 and VCO2 columns and units (swapped? one in l/min?) and [cart.limits]",
    "negative_time": "the time column ([cart.csv] time_column, time_format)",
    "hr_range": "the heart-rate column ([cart.csv] hr_column) and [cart.limits] hr_bpm",
    "ve_range": "the ventilation column ([cart.csv] ve_column) and [cart.limits] ve_l_min",
}


class LeadingRejectGuard:
    """Stops a stream whose first ``limit`` records are all rejected (see the constant above).

    Only the records *before the first accepted breath* count: once one breath is accepted the
    configuration is shown to work, and later silence is the bridge's cart watchdog's business.

    Attributes:
        limit: Rejected records, none accepted, after which :meth:`rejected` raises.
        active: False once a breath was accepted.
    """

    def __init__(self, limit: int = DEFAULT_MAX_LEADING_REJECTS, *, source: str = "cart") -> None:
        self.limit = limit
        self.source = source
        self.active = True
        self.reasons: Counter[str] = Counter()
        self.examples: dict[str, str] = {}

    def accepted(self) -> None:
        """A breath passed: stop watching."""
        self.active = False

    def rejected(self, reason: str, example: str) -> None:
        """Count one rejected record.

        Raises:
            CartError: The ``limit``-th rejected record with none accepted: names the dominant
                reason, an offending value and what to check in the config.
        """
        if not self.active:
            return
        key = str(reason)
        self.reasons[key] += 1
        self.examples.setdefault(key, example)
        if self.reasons.total() >= self.limit:
            top, n = self.reasons.most_common(1)[0]
            others = ", ".join(f"{k} {v}" for k, v in self.reasons.most_common()[1:])
            raise CartError(
                f"{self.source}: the first {self.reasons.total()} records were all rejected, none "
                f"accepted: {n} x {top}{f' (also {others})' if others else ''}; e.g. "
                f"{self.examples[top]}. Check {_HINTS.get(top, 'the [cart] table')}"
            )


#: Breaths whose spacing is checked at a stream's start.
SPACING_BREATHS = 8
#: Plausible median breath spacing (s). Walking adults breathe every 2-5 s (15-30 breaths a
#: minute; the simulated populations: 2.7-3.3 s mean in virtual_hw/wearer.py, 2.0-3.5 s in
#: virtual_hw/wearer_realistic.py), at rest up to ~10 s;
#: averaged exports (10-30 s bins) stay inside. A time column read in the wrong unit is 60x off
#: (seconds read as minutes: 3 s becomes 180 s; minutes read as seconds: 0.05 s), far outside.
PLAUSIBLE_SPACING_S = (0.25, 60.0)


def check_breath_spacing(times_s: Iterable[float], *, source: str = "cart") -> None:
    """Refuse breath times whose median spacing no person breathes at.

    Args:
        times_s: Accepted breath times (s), in order; at least two to check anything.
        source: Names the stream in the message.

    Raises:
        CartError: The median spacing is outside :data:`PLAUSIBLE_SPACING_S`; names it and the
            config keys to check.
    """
    t = sorted(float(x) for x in times_s)
    gaps = sorted(b - a for a, b in itertools.pairwise(t))
    if not gaps:
        return
    mid = len(gaps) // 2
    median = gaps[mid] if len(gaps) % 2 else 0.5 * (gaps[mid - 1] + gaps[mid])
    lo, hi = PLAUSIBLE_SPACING_S
    if not lo <= median <= hi:
        guess = ("seconds read as minutes?" if median > hi else "minutes read as seconds?")
        raise CartError(
            f"{source}: the first {len(t)} breaths are a median {median:.3g} s apart; a person "
            f"breathes every {lo:g}-{hi:g} s ({guess}). Check the time format ([cart.csv] "
            "time_format: s, min, hh:mm:ss or mm:ss) and the time column")


class BreathSpacingGuard:
    """Checks the spacing of a stream's first :data:`SPACING_BREATHS` accepted breaths
    (:func:`check_breath_spacing`): a time column in the wrong unit passes every per-breath
    check but would make a session's breaths minutes apart."""

    def __init__(self, n: int = SPACING_BREATHS, *, source: str = "cart") -> None:
        self.n = n
        self.source = source
        self.times_s: list[float] | None = []

    def accepted(self, t_s: float) -> None:
        """Note an accepted breath's time; raise CartError at the n-th if they are implausible."""
        if self.times_s is None:
            return
        self.times_s.append(t_s)
        if len(self.times_s) >= self.n:
            times, self.times_s = self.times_s, None
            check_breath_spacing(times, source=self.source)


def describe_record(record: BreathRecord) -> str:
    """One breath as ``t = 9 s, VO2 = 117.1 ml/min, ...`` for messages and reports."""
    parts = [f"t = {record.t_s:g} s", f"VO2 = {record.vo2_ml_min:g} ml/min",
             f"VCO2 = {record.vco2_ml_min:g} ml/min"]
    for name, value in (("VE", record.ve_l_min), ("RER", record.rer), ("HR", record.hr_bpm)):
        if value is not None:
            parts.append(f"{name} = {value:g}")
    return ", ".join(parts)

_log = logging.getLogger(__name__)


class BreathParser(Protocol):
    """What a line parser provides (:class:`~drivers.cart.line.HbrLineParser`,
    :class:`~drivers.cart.csvmap.CsvBreathParser`)."""

    format_name: str

    def parse(self, line: bytes) -> ParsedBreath | None:
        """Decode one line; None for a line that carries no breath (comment, header).

        Raises:
            DecodeError: The line should be a breath but is not (``reason`` says why).
        """
        ...


def process_line(
    line: bytes,
    parser: BreathParser,
    validator: BreathValidator,
    guard: LeadingRejectGuard | None = None,
) -> BreathRecord | None:
    """Parse and validate one line; return the breath, or None (a reject is counted).

    Only :class:`DecodeError` is a reject; any other exception (e.g. a CSV header that does not
    match the mapping, :class:`~drivers.errors.DriverConfigError`) propagates, because it means
    the configuration is wrong, not the data.

    Raises:
        CartError: From ``guard``, when its first records are all rejected.
    """
    try:
        parsed = parser.parse(line)
    except DecodeError as err:
        validator.reject(err.reason)
        _log.debug("rejected line (%s): %s", err.reason, err)
        if guard is not None:
            guard.rejected(str(err.reason), f"{err} in line {shorten(line)!r}")
        return None
    if parsed is None:
        return None
    if guard is None or not guard.active:
        return validator.check(parsed.record, parsed.seq)
    before = Counter(validator.counters)
    record = validator.check(parsed.record, parsed.seq)
    if record is not None:
        guard.accepted()
        return record
    reason = next((k for k, v in validator.counters.items() if v != before.get(k, 0)), "rejected")
    guard.rejected(reason, describe_record(parsed.record))
    return None


def iter_breaths(
    lines: Iterable[bytes], parser: BreathParser, validator: BreathValidator
) -> Iterator[BreathRecord]:
    """Yield the valid breaths of ``lines`` (already split, terminators optional)."""
    for line in lines:
        record = process_line(line, parser, validator)
        if record is not None:
            yield record


def read_breath_file(
    path: str | PathLike[str],
    parser: BreathParser,
    validator: BreathValidator | None = None,
    *,
    max_line_bytes: int = DEFAULT_MAX_LINE_BYTES,
) -> list[BreathRecord]:
    """Read every valid breath of a recorded file or a vendor export.

    Args:
        path: The file (hilbo-line recording or CSV export, matching ``parser``).
        parser: :class:`~drivers.cart.line.HbrLineParser` or a
            :class:`~drivers.cart.csvmap.CsvBreathParser`.
        validator: Receives the reject counts (framing ones included); a fresh default one
            if None.
        max_line_bytes: Longest line kept.

    Returns:
        The valid breaths in file order.

    Raises:
        OSError: The file cannot be read.
        DriverConfigError: Not a regular file, too large, or a CSV header that does not match
            the mapping.
    """
    validator = validator if validator is not None else BreathValidator()
    framer = LineFramer(max_line_bytes)
    out: list[BreathRecord] = []
    with open_regular_file(path, max_bytes=MAX_CART_FILE_BYTES, what="a cart recording or export") as fh:
        for chunk in iter(lambda: fh.read(1 << 16), b""):
            out.extend(iter_breaths(framer.feed(chunk), parser, validator))
    tail = framer.flush()
    if tail is not None:  # a last line without a terminator is still a line
        out.extend(iter_breaths([tail], parser, validator))
    validator.counters.update(framer.counters)
    return out
