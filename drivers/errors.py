"""Exception hierarchy of the drivers package."""

from __future__ import annotations

__all__ = [
    "DecodeError",
    "DriverConfigError",
    "DriverError",
    "ProfilePushError",
    "TransportError",
]


class DriverError(Exception):
    """Root of every error the drivers raise on purpose."""


class DriverConfigError(DriverError, ValueError):
    """A transport or codec option is invalid (names the key, the value and what is allowed)."""


class DecodeError(DriverError, ValueError):
    """Bytes or a frame that do not decode; carries a short machine-readable ``reason``."""

    def __init__(self, reason: str, detail: str = "") -> None:
        self.reason = reason
        super().__init__(f"{reason}: {detail}" if detail else reason)


class TransportError(DriverError, ConnectionError):
    """A transport could not be opened, or dropped and could not be reopened."""


class ProfilePushError(DriverError, TimeoutError):
    """A force-profile push was not acknowledged after the allowed retries (or was nacked)."""
