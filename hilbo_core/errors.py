"""Exception hierarchy of hilbo_core.

Every error raised on purpose by hilbo_core derives from :class:`HilboError`, and also from the
matching built-in so callers that catch ``ValueError`` keep working.
"""

from __future__ import annotations

__all__ = [
    "ConfigError",
    "EstimatorError",
    "HilboError",
    "InfeasibleError",
    "MeasurementError",
    "OptimizerStateError",
]


class HilboError(Exception):
    """Root of every error hilbo_core raises on purpose."""


class ConfigError(HilboError, ValueError):
    """A parameter, option or definition is invalid (names the key, value and what is allowed)."""


class InfeasibleError(HilboError, ValueError):
    """A parameter vector or a space violates bounds or constraints, or the space is empty."""


class MeasurementError(HilboError, ValueError):
    """A measurement (breath, watts, time) is NaN, infinite, negative, absurd or out of order."""


class EstimatorError(HilboError, ArithmeticError):
    """A numerical estimator failed (e.g. a covariance that is no longer positive definite)."""


class OptimizerStateError(HilboError, RuntimeError):
    """A call that the optimizer's current phase does not allow (e.g. observe before ask)."""
