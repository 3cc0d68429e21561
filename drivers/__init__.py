"""drivers: wire protocols and async transports (exosuit CAN, metabolic-cart breath streams)."""

from drivers.cart import (
    BreathStream,
    BreathValidator,
    CartConfig,
    CartFormat,
    CsvMapping,
    PhysioLimits,
    RejectReason,
    TransportHooks,
    encode_csv_header,
    encode_csv_row,
    encode_line,
    make_transport,
    parse_line,
)
from drivers.errors import (
    DecodeError,
    DriverConfigError,
    DriverError,
    ProfilePushError,
    TransportError,
)

__all__ = [
    "BreathStream",
    "BreathValidator",
    "CartConfig",
    "CartFormat",
    "CsvMapping",
    "DecodeError",
    "DriverConfigError",
    "DriverError",
    "PhysioLimits",
    "ProfilePushError",
    "RejectReason",
    "TransportError",
    "TransportHooks",
    "encode_csv_header",
    "encode_csv_row",
    "encode_line",
    "make_transport",
    "parse_line",
]
