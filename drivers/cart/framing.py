"""Cutting a byte stream into lines, with a bound on line length.

Serial ports and TCP deliver arbitrary chunks; a line may arrive in pieces, several lines may
arrive at once, and a line may never end (a cart spewing binary after a baud-rate mismatch).
:class:`LineFramer` buffers at most ``max_line_bytes`` and discards (and counts) anything longer,
so memory stays bounded whatever comes in.
"""

from __future__ import annotations

import re
from collections import Counter

from drivers.cart.reasons import RejectReason
from drivers.errors import DriverConfigError

__all__ = ["DEFAULT_MAX_LINE_BYTES", "LineFramer"]

DEFAULT_MAX_LINE_BYTES = 4096
"""Long enough for a vendor CSV row with ~100 columns; hilbo-lines are under 256 bytes."""

# CR LF, LF and CR all end a line (carts differ); runs of them are one break, so blank lines
# vanish here and never reach a parser.
_BREAK = re.compile(rb"[\r\n]+")


class LineFramer:
    """Incremental splitter of bytes into lines without their terminators.

    Attributes:
        max_line_bytes: Longest line kept; longer lines are dropped whole.
        counters: ``too_long`` and ``truncated`` counts (keys are :class:`RejectReason`).
    """

    def __init__(self, max_line_bytes: int = DEFAULT_MAX_LINE_BYTES) -> None:
        if isinstance(max_line_bytes, bool) or not isinstance(max_line_bytes, int) or (max_line_bytes < 1):
            raise DriverConfigError(f"max_line_bytes = {max_line_bytes!r}: expected an integer >= 1")
        self.max_line_bytes = max_line_bytes
        self.counters: Counter[str] = Counter()
        self._buf = b""
        self._discarding = False  # inside an over-long line whose start was already dropped

    @property
    def pending(self) -> int:
        """Bytes buffered of a line not yet terminated."""
        return len(self._buf)

    def feed(self, chunk: bytes) -> list[bytes]:
        """Add ``chunk`` and return the complete, non-empty lines it finished, in order."""
        parts = _BREAK.split(self._buf + chunk)
        self._buf = parts.pop()  # after the last break: an unfinished line (maybe empty)
        lines: list[bytes] = []
        for part in parts:
            if self._discarding:
                self._discarding = False  # the tail of a line already counted as too long
                continue
            if len(part) > self.max_line_bytes:
                self.counters[RejectReason.TOO_LONG] += 1
            elif part:
                lines.append(part)
        if len(self._buf) > self.max_line_bytes:
            if not self._discarding:
                self.counters[RejectReason.TOO_LONG] += 1
            self._discarding = True
            self._buf = b""
        return lines

    def flush(self) -> bytes | None:
        """Return the unterminated last line as complete (end of a file), or None if there is none."""
        tail, self._buf = self._buf, b""
        discarding, self._discarding = self._discarding, False
        return tail if tail and not discarding else None

    def discard(self) -> None:
        """Drop an unterminated line because its source dropped (counted as ``truncated``)."""
        if self._buf:
            self.counters[RejectReason.TRUNCATED] += 1
        self._buf = b""
        self._discarding = False
