"""Errors of the metabolic-cart drivers beyond the roots in :mod:`drivers.errors`."""

from __future__ import annotations

from drivers.errors import DriverError

__all__ = ["CartError", "EncodeError"]


class EncodeError(DriverError, ValueError):
    """A record or sequence number cannot be written in the requested wire format."""


class CartError(DriverError, RuntimeError):
    """The cart stream cannot deliver breaths as configured (e.g. every first record rejected)."""
