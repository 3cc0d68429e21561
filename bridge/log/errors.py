"""The session log's exception hierarchy (one root, :class:`LogError`, under BridgeError)."""

from __future__ import annotations

from bridge.errors import BridgeError

__all__ = ["LogError", "LogFormatError", "LogStateError", "LogValueError", "LogWriteError"]


class LogError(BridgeError):
    """Root of every error the session log (writing, reading, recovering, resuming) raises."""


class LogFormatError(LogError, ValueError):
    """A file is not a readable hilbo session log (not MCAP, empty, or another program's MCAP)."""


class LogValueError(LogError, ValueError):
    """A value given to the log is invalid (a negative time, an unknown channel option...)."""


class LogStateError(LogError, RuntimeError):
    """The log cannot do this now (written to after close)."""


class LogWriteError(LogError, OSError):
    """Writing or flushing the file failed (disk full, file removed...)."""
