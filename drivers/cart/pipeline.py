"""Line → breath: the parser interface and the synchronous parse-and-validate step.

Everything that turns lines into validated breaths goes through :func:`process_line`, so the
async :class:`~drivers.cart.stream.BreathStream` and the whole-file reader
:func:`read_breath_file` count rejects the same way.
"""

from __future__ import annotations

import logging
from collections.abc import Iterable, Iterator
from os import PathLike
from typing import Protocol

from drivers.cart.framing import DEFAULT_MAX_LINE_BYTES, LineFramer
from drivers.cart.line import ParsedBreath
from drivers.cart.validate import BreathValidator
from drivers.errors import DecodeError
from hilbo_core.types import BreathRecord

__all__ = ["BreathParser", "iter_breaths", "process_line", "read_breath_file"]

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


def process_line(line: bytes, parser: BreathParser, validator: BreathValidator) -> BreathRecord | None:
    """Parse and validate one line; return the breath, or None (a reject is counted).

    Only :class:`DecodeError` is a reject; any other exception (e.g. a CSV header that does not
    match the mapping, :class:`~drivers.errors.DriverConfigError`) propagates, because it means
    the configuration is wrong, not the data.
    """
    try:
        parsed = parser.parse(line)
    except DecodeError as err:
        validator.reject(err.reason)
        _log.debug("rejected line (%s): %s", err.reason, err)
        return None
    if parsed is None:
        return None
    return validator.check(parsed.record, parsed.seq)


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
        DriverConfigError: A CSV header does not match the mapping.
    """
    validator = validator if validator is not None else BreathValidator()
    framer = LineFramer(max_line_bytes)
    out: list[BreathRecord] = []
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 16), b""):
            out.extend(iter_breaths(framer.feed(chunk), parser, validator))
    tail = framer.flush()
    if tail is not None:  # a last line without a terminator is still a line
        out.extend(iter_breaths([tail], parser, validator))
    validator.counters.update(framer.counters)
    return out
