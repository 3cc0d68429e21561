"""Exception hierarchy of the virtual devices (virtual cart, virtual exosuit, simulated clock).

The wearer model (:mod:`virtual_hw.wearer`) is a pure model and raises the
:mod:`hilbo_core.errors` types; the device machinery raises these.
"""

from __future__ import annotations

__all__ = ["ClockError", "FaultSpecError", "VirtualConfigError", "VirtualHwError"]


class VirtualHwError(Exception):
    """Root of every error the virtual devices raise on purpose."""


class VirtualConfigError(VirtualHwError, ValueError):
    """A virtual device's option is invalid (names the option, the value and what is allowed)."""


class FaultSpecError(VirtualConfigError):
    """A fault specification does not parse or does not fit the device's fault kinds."""


class ClockError(VirtualHwError, RuntimeError):
    """A simulated clock was used wrongly (a non-finite time, outside an event loop)."""
