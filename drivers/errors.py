"""Exception hierarchy of the drivers package."""

from __future__ import annotations

__all__ = [
    "DecodeError",
    "DriverConfigError",
    "DriverError",
    "ProfilePushAborted",
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


class ProfilePushAborted(DriverError):
    """A force-profile push was stopped because its ``permit`` hook refused the next step.

    Raised by ``CanEndpoint.push_profile`` when ``permit(stage)`` returns False right before the
    first segment of an attempt (``stage == "first_segment"``) or right before the commit
    (``stage == "commit"``): the refused step is not sent, and neither is anything after it, so
    the commit of the refused attempt never reaches the bus.

    Attributes:
        version: the profile version of the push.
        stage: the step that was refused, ``"first_segment"`` or ``"commit"``.
        attempt: the attempt (1-based) that was stopped.
        commits_sent: commits of this version already on the bus from earlier attempts of the
            same push (nonzero only when a retry was refused: the device may then hold the
            table as pending, so the caller's assistance-off still matters).
    """

    def __init__(self, version: int, stage: str, attempt: int, commits_sent: int) -> None:
        self.version = version
        self.stage = str(stage)
        self.attempt = attempt
        self.commits_sent = commits_sent
        super().__init__(
            f"profile version {version}: push aborted before the {self.stage.replace('_', ' ')} "
            f"of attempt {attempt} (permit refused; {commits_sent} earlier commit(s) sent)"
        )
