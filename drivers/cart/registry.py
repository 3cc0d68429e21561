"""Transports by name: what ``cart.transport = "..."`` in the config selects.

Each entry pairs a frozen options dataclass (validated from the ``[cart.options]`` table) with
the transport class built from it. :func:`register_transport` adds one (e.g. a vendor's own
protocol in a lab-specific package) without touching this module.
"""

from __future__ import annotations

import difflib
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from drivers.cart.lsl import LslOptions, LslTransport
from drivers.cart.net import TcpOptions, TcpTransport, UdpOptions, UdpTransport
from drivers.cart.replay import ReplayOptions, ReplayTransport
from drivers.cart.serial_port import SerialOptions, SerialTransport
from drivers.cart.transport import CartTransport, TransportHooks, options_from_dict
from drivers.errors import DriverConfigError

__all__ = [
    "TRANSPORTS",
    "TransportSpec",
    "make_transport",
    "register_transport",
    "transport_options_from_dict",
    "transport_spec",
]


@dataclass(frozen=True, slots=True)
class TransportSpec:
    """A registered transport: its options type and its class (``cls(options, hooks)``)."""

    name: str
    options_type: type[Any]
    transport_type: type[CartTransport]


TRANSPORTS: dict[str, TransportSpec] = {
    "serial": TransportSpec("serial", SerialOptions, SerialTransport),
    "tcp": TransportSpec("tcp", TcpOptions, TcpTransport),
    "udp": TransportSpec("udp", UdpOptions, UdpTransport),
    "replay": TransportSpec("replay", ReplayOptions, ReplayTransport),
    "lsl": TransportSpec("lsl", LslOptions, LslTransport),
}


def register_transport(name: str, options_type: type[Any], transport_type: type[CartTransport]) -> None:
    """Register a transport under ``name``.

    Raises:
        DriverConfigError: ``name`` is already taken.
    """
    if name in TRANSPORTS:
        raise DriverConfigError(f"transport {name!r} is already registered")
    TRANSPORTS[name] = TransportSpec(name, options_type, transport_type)


def transport_spec(name: object, where: str = "transport") -> TransportSpec:
    """Look a transport up by name.

    Raises:
        DriverConfigError: Naming the value and the registered names.
    """
    if not isinstance(name, str) or name not in TRANSPORTS:
        allowed = ", ".join(repr(n) for n in sorted(TRANSPORTS))
        close = difflib.get_close_matches(str(name), sorted(TRANSPORTS), n=1, cutoff=0.6)
        hint = f" (did you mean {close[0]!r}?)" if close else ""
        raise DriverConfigError(f"{where} = {name!r}{hint}: expected one of {allowed}")
    return TRANSPORTS[name]


def transport_options_from_dict(name: str, data: Mapping[str, Any], where: str = "options") -> Any:
    """Validate a transport's options table into its options dataclass."""
    return options_from_dict(transport_spec(name).options_type, data, where)


def make_transport(name: str, options: Any, hooks: TransportHooks | None = None) -> CartTransport:
    """Build the transport ``name`` from its options (a dataclass, or a dict to validate).

    Raises:
        DriverConfigError: Unknown name, or options of the wrong type or invalid.
    """
    spec = transport_spec(name)
    if isinstance(options, Mapping):
        options = options_from_dict(spec.options_type, options, "options")
    if not isinstance(options, spec.options_type):
        raise DriverConfigError(
            f"options = {options!r}: transport {name!r} expects {spec.options_type.__name__}"
        )
    return spec.transport_type(options, hooks)
