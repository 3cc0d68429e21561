"""Exception hierarchy of the bridge.

Every error the bridge raises on purpose derives from :class:`BridgeError`, and also from the
matching built-in, so callers that catch ``ValueError`` keep working.
"""

from __future__ import annotations

__all__ = [
    "BridgeConfigError",
    "BridgeError",
    "DeviceProcessError",
    "ReviewError",
    "UnsafeProfileError",
    "UsageError",
    "first_leaf",
]


class BridgeError(Exception):
    """Root of every error the bridge raises on purpose."""


class BridgeConfigError(BridgeError, ValueError):
    """The session config is invalid: the message names the key, the value and what is allowed."""


class DeviceProcessError(BridgeError, RuntimeError):
    """A virtual device started as a process (``hilbo sim --processes``) could not be started, or
    died: the message names the process, its exit status and the end of its stderr."""


class ReviewError(BridgeError, ValueError):
    """``hilbo review`` cannot review these files: the message names the file and what was expected."""


class UnsafeProfileError(BridgeError, ValueError):
    """A proposed setting or force profile violates the hardware limits; nothing was sent.

    Attributes:
        verdict: The :class:`bridge.safety.LimitVerdict` listing every violation.
        params: The proposed setting as given (may contain NaN).
    """

    def __init__(self, message: str, verdict: object, params: object = None) -> None:
        super().__init__(message)
        self.verdict = verdict
        self.params = params


class UsageError(BridgeError, ValueError):
    """The command line asks for options that do not go together, or gives a value refused before
    any work starts (``hilbo bench``): ``hilbo`` exits with status 2, like argparse's own usage
    errors (every other error, a failure at run time, is 1)."""


def first_leaf(err: BaseException) -> BaseException:
    """The first error inside nested exception groups (a task group's failed task), or ``err``."""
    while isinstance(err, BaseExceptionGroup) and err.exceptions:
        err = err.exceptions[0]
    return err
