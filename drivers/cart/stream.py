"""Validated breaths from a cart: transport + parser + validator, and the cart's config.

::

    config = CartConfig.from_dict(toml["cart"])
    async with BreathStream.from_config(config) as stream:
        async for breath in stream:          # BreathRecord, valid and in time order
            ...
    stream.counters                          # rejects by reason (framing, decoding, validation)

The stream never raises for bad data *once it has delivered a breath*. It raises
:class:`~drivers.errors.TransportError` when the link is gone for good (after the backoff's
``max_attempts``), :class:`~drivers.errors.DriverConfigError` when a CSV header does not match
the mapping (or a preset finds no header), and :class:`~drivers.cart.errors.CartError` when the
first ``max_leading_rejects`` records are all rejected (wrong units, time format or preset); it
ends (``StopAsyncIteration``) when a replayed file is exhausted.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Mapping
from dataclasses import dataclass, field
from enum import StrEnum
from types import TracebackType
from typing import Annotated, Any, Self

from msgspec import Meta

from drivers.cart._options import check_declared, check_keys, check_mapping, enum_value, within
from drivers.cart.csvmap import CsvBreathParser, CsvMapping
from drivers.cart.line import HbrLineParser
from drivers.cart.pipeline import (
    DEFAULT_MAX_LEADING_REJECTS,
    BreathParser,
    BreathSpacingGuard,
    LeadingRejectGuard,
    process_line,
)
from drivers.cart.registry import make_transport, transport_options_from_dict, transport_spec
from drivers.cart.replay import ReplayTransport
from drivers.cart.transport import CartTransport, TransportHooks
from drivers.cart.validate import BreathValidator, PhysioLimits
from drivers.cart.vendors import TableParser, VendorSpec, vendor_spec
from drivers.errors import DriverConfigError
from hilbo_core.types import BreathRecord

__all__ = ["BreathStream", "CartConfig", "CartFormat"]


class CartFormat(StrEnum):
    """Wire format of the cart's lines."""

    HILBO_LINE = "hilbo-line"
    """Our line format with sequence number and CRC-16 (``drivers/cart/FORMAT.md``)."""
    CSV = "csv"
    """A vendor's CSV, read through a :class:`~drivers.cart.csvmap.CsvMapping`."""
    COSMED = "cosmed"
    """COSMED Omnia/PFT Suite xlsx export (replay only)."""
    COSMED_CSV = "cosmed-csv"
    """COSMED K5/Quark CSV export (file or live lines)."""
    CORTEX = "cortex"
    """CORTEX MetaSoft Studio Excel-2003 XML export (replay only)."""
    VYNTUS = "vyntus"
    """Vyntus CPX SentrySuite tab-separated text export (file or live lines)."""
    PARVO = "parvo"
    """Parvo Medics TrueOne 2400 CSV export (file or live lines)."""

    @property
    def vendor(self) -> VendorSpec | None:
        """The vendor preset of this format (:mod:`drivers.cart.vendors`), None for ours and csv."""
        if self in (CartFormat.HILBO_LINE, CartFormat.CSV):
            return None
        return vendor_spec(self.value)


_CONFIG_KEYS = ("transport", "options", "format", "csv", "limits", "max_leading_rejects")


@dataclass(frozen=True, slots=True)
class CartConfig:
    """The ``[cart]`` table of the session config.

    TOML shape::

        [cart]
        transport = "tcp"              # "serial" | "tcp" | "udp" | "replay"
        format = "hilbo-line"          # "csv" (then [cart.csv] is required), or a vendor preset:
                                       # "cosmed", "cosmed-csv", "cortex", "vyntus", "parvo"
        max_leading_rejects = 20       # stop if the first 20 records are all rejected
        [cart.options]                 # the transport's options
        host = "192.168.10.20"
        port = 5000
        [cart.options.backoff]         # optional: reconnection policy
        max_s = 5.0
        [cart.limits]                  # optional: physiological limits, [low, high]
        hr_bpm = [30, 220]

    Attributes:
        transport: Registered transport name.
        options: That transport's options dataclass (e.g. :class:`TcpOptions`).
        format: Line format (:class:`CartFormat`).
        csv: The column mapping; required for ``format = "csv"``, refused otherwise.
        limits: Physiological limits for the validator.
        max_leading_rejects: Stop with :class:`~drivers.cart.errors.CartError` when this many
            records are rejected before the first accepted one (a wrong unit, time format or
            preset rejects every breath; the error names the reason and a value).
    """

    transport: str
    options: Any
    format: CartFormat = CartFormat.HILBO_LINE
    csv: CsvMapping | None = None
    limits: PhysioLimits = field(default_factory=PhysioLimits)
    max_leading_rejects: Annotated[int, Meta(ge=1, le=100_000)] = DEFAULT_MAX_LEADING_REJECTS

    def __post_init__(self) -> None:
        spec = transport_spec(self.transport)
        if not isinstance(self.options, spec.options_type):
            raise DriverConfigError(
                f"options = {self.options!r}: transport {self.transport!r} expects "
                f"{spec.options_type.__name__}"
            )
        check_declared(self)
        # transport/options, format/csv and format/transport go together: checked here.
        fmt = self.format
        if fmt is CartFormat.CSV and self.csv is None:
            raise DriverConfigError("format = 'csv' needs a [cart.csv] column mapping")
        if fmt is not CartFormat.CSV and self.csv is not None:
            raise DriverConfigError(
                f"csv mapping given but format = {fmt.value!r}; set format = 'csv' or remove it"
            )
        if not isinstance(self.limits, PhysioLimits):
            raise DriverConfigError(f"limits = {self.limits!r}: expected PhysioLimits")
        vendor = fmt.vendor
        if vendor is not None and not vendor.is_live_capable and self.transport != "replay":
            raise DriverConfigError(
                f"format = {fmt.value!r} is a file export ({vendor.title}); it needs "
                f"transport = 'replay', not {self.transport!r}"
            )
        if self.transport == "lsl" and fmt is not CartFormat.HILBO_LINE:
            raise DriverConfigError(
                f"format = {fmt.value!r} with transport = 'lsl': LSL carries samples, not lines; "
                "leave format out (the channels are mapped in [cart.options])"
            )

    @classmethod
    def from_dict(cls, data: Mapping[str, Any], where: str = "cart") -> CartConfig:
        """Build from the ``[cart]`` config table.

        Raises:
            DriverConfigError: An unknown key, a missing ``transport``, or a bad value; the
                message names the full key (``cart.options.port``), the value and what is
                allowed.
        """
        data = check_mapping(data, where)
        check_keys(data, _CONFIG_KEYS, where)
        if "transport" not in data:
            raise DriverConfigError(f"{where}: missing required key 'transport'")
        name = transport_spec(data["transport"], f"{where}.transport").name
        options = transport_options_from_dict(name, data.get("options", {}), f"{where}.options")
        fmt = enum_value(data.get("format", CartFormat.HILBO_LINE), CartFormat, f"{where}.format")
        csv = CsvMapping.from_dict(data["csv"], f"{where}.csv") if "csv" in data else None
        limits = (
            PhysioLimits.from_dict(data["limits"], f"{where}.limits") if "limits" in data else PhysioLimits()
        )
        extra = {"max_leading_rejects": data["max_leading_rejects"]} if "max_leading_rejects" in data else {}
        try:
            return cls(transport=name, options=options, format=fmt, csv=csv, limits=limits, **extra)
        except DriverConfigError as err:
            raise within(where, err) from err

    def make_parser(self) -> BreathParser:
        """A fresh parser for this format (CSV parsers are stateful: one per stream)."""
        if self.format is CartFormat.CSV and self.csv is not None:
            return CsvBreathParser(self.csv)
        vendor = self.format.vendor
        if vendor is not None:
            return TableParser(vendor)
        return HbrLineParser()


class BreathStream:
    """Async iterator of valid :class:`BreathRecord` from a transport, counting every reject.

    Attributes:
        transport: Where the lines come from.
        parser: How lines become records.
        validator: What is rejected, and the counts.
    """

    def __init__(
        self,
        transport: CartTransport,
        parser: BreathParser,
        validator: BreathValidator | None = None,
    ) -> None:
        self.transport = transport
        self.parser = parser
        self.validator = validator if validator is not None else BreathValidator()
        self.guard: LeadingRejectGuard | None = None
        self.spacing: BreathSpacingGuard | None = None

    @classmethod
    def from_config(cls, config: CartConfig, hooks: TransportHooks | None = None) -> BreathStream:
        """Build transport, parser and validator from a :class:`CartConfig`.

        Args:
            config: The cart config.
            hooks: Injectable sleep/clock for backoff and replay pacing (tests, simulation).
        """
        transport = make_transport(config.transport, config.options, hooks)
        vendor = config.format.vendor
        if vendor is not None and isinstance(transport, ReplayTransport):
            transport.loader = vendor.loader  # xlsx/XML presets replay their line image
        stream = cls(transport, config.make_parser(), BreathValidator(config.limits))
        source = f"cart ({transport.describe()}, format {config.format.value})"
        stream.guard = LeadingRejectGuard(config.max_leading_rejects, source=source)
        stream.spacing = BreathSpacingGuard(source=source)
        return stream

    @property
    def counters(self) -> Counter[str]:
        """Rejects by reason, framing (transport) and decoding/validation together; a copy."""
        merged: Counter[str] = Counter(self.validator.counters)
        merged.update(self.transport.counters)
        return merged

    @property
    def accepted(self) -> int:
        """Breaths delivered so far."""
        return self.validator.accepted

    @property
    def paced_by_reader(self) -> bool:
        """The transport's breaths are paced by this stream's reader alone (a replay at
        ``speed = "max"``): read it only as fast as the breaths can be used."""
        return self.transport.paced_by_reader

    @property
    def reconnects(self) -> int:
        """Times the transport reopened its link after a drop."""
        return self.transport.reconnects

    async def __aenter__(self) -> Self:
        await self.transport.open()
        return self

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        await self.transport.close()

    def __aiter__(self) -> Self:
        return self

    async def __anext__(self) -> BreathRecord:
        """The next valid breath (paced by the transport when it replays a file)."""
        async for line in self.transport:
            record = process_line(line, self.parser, self.validator, self.guard)
            if record is not None:
                if self.spacing is not None:
                    self.spacing.accepted(record.t_s)
                await self.transport.pace(record.t_s)
                return record
        raise StopAsyncIteration
