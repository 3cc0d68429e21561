"""Metabolic-cart breath streams: wire formats, validation and async transports.

The pieces, in the order a breath passes through them:

- transports (:mod:`.transport`, :mod:`.serial_port`, :mod:`.net`, :mod:`.replay`, :mod:`.lsl`),
  chosen by name through :mod:`.registry`: ``"serial"``, ``"tcp"``, ``"udp"``, ``"lsl"``,
  ``"replay"``;
- parsers: the hilbo-line format (:mod:`.line`, specified in ``FORMAT.md``), column-mapped
  vendor CSV (:mod:`.csvmap`) and the vendor presets (:mod:`.vendors`: COSMED, CORTEX, Vyntus,
  Parvo exports); :mod:`.inspect` reports what a file holds (``hilbo cart inspect``);
- :class:`BreathValidator` (:mod:`.validate`): rejects with a counted :class:`RejectReason`;
- :class:`BreathStream` (:mod:`.stream`): all of it behind ``async for breath in stream``,
  configured by :class:`CartConfig`.
"""

from __future__ import annotations

from drivers.cart.csvmap import (
    CsvBreathParser,
    CsvMapping,
    GasUnit,
    TimeFormat,
    encode_csv_header,
    encode_csv_row,
)
from drivers.cart.errors import CartError, EncodeError
from drivers.cart.framing import LineFramer
from drivers.cart.line import HbrLineParser, ParsedBreath, crc16, encode_line, parse_line
from drivers.cart.lsl import LslOptions, LslTransport
from drivers.cart.net import TcpOptions, TcpTransport, UdpOptions, UdpTransport
from drivers.cart.pipeline import BreathParser, iter_breaths, process_line, read_breath_file
from drivers.cart.reasons import RejectReason
from drivers.cart.registry import TRANSPORTS, make_transport, register_transport
from drivers.cart.replay import ReplayOptions, ReplayTransport
from drivers.cart.serial_port import SerialOptions, SerialTransport
from drivers.cart.stream import BreathStream, CartConfig, CartFormat
from drivers.cart.transport import Backoff, CartTransport, TransportHooks
from drivers.cart.validate import BreathValidator, PhysioLimits

__all__ = [
    "TRANSPORTS",
    "Backoff",
    "BreathParser",
    "BreathStream",
    "BreathValidator",
    "CartConfig",
    "CartError",
    "CartFormat",
    "CartTransport",
    "CsvBreathParser",
    "CsvMapping",
    "EncodeError",
    "GasUnit",
    "HbrLineParser",
    "LineFramer",
    "LslOptions",
    "LslTransport",
    "ParsedBreath",
    "PhysioLimits",
    "RejectReason",
    "ReplayOptions",
    "ReplayTransport",
    "SerialOptions",
    "SerialTransport",
    "TcpOptions",
    "TcpTransport",
    "TimeFormat",
    "TransportHooks",
    "UdpOptions",
    "UdpTransport",
    "crc16",
    "encode_csv_header",
    "encode_csv_row",
    "encode_line",
    "iter_breaths",
    "make_transport",
    "parse_line",
    "process_line",
    "read_breath_file",
    "register_transport",
]
