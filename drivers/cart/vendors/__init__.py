"""Vendor presets: ``[cart] format = "cosmed" | "cosmed-csv" | "cortex" | "vyntus" | "parvo"``.

Each preset (one module per vendor) is a :class:`~drivers.cart.vendors._table.VendorSpec` read by
the shared :class:`~drivers.cart.vendors._table.TableParser`: localized column names, units rows,
metadata blocks, decimal commas, ``h:mm:ss``/``mm:ss`` times; VO2 and VCO2 are converted to
ml/min by the units the file states, times to seconds since the start of the test.
:func:`detect_format` tells which format a file is (``hilbo cart inspect``).
"""

from __future__ import annotations

from os import PathLike, fspath

from drivers.cart.vendors._table import TableParser, VendorSpec, normalize_name
from drivers.cart.vendors.cortex import CORTEX
from drivers.cart.vendors.cosmed import COSMED, COSMED_CSV
from drivers.cart.vendors.parvo import PARVO
from drivers.cart.vendors.vyntus import VYNTUS
from drivers.errors import DecodeError, DriverConfigError
from drivers.files import MAX_CART_FILE_BYTES, open_regular_file, read_regular_file

__all__ = [
    "VENDORS",
    "TableParser",
    "VendorSpec",
    "detect_format",
    "line_image",
    "vendor_spec",
]

VENDORS: dict[str, VendorSpec] = {s.name: s for s in (COSMED, COSMED_CSV, CORTEX, VYNTUS, PARVO)}
"""The presets by ``[cart] format`` value."""

_SNIFF_BYTES = 1 << 16


def vendor_spec(name: str) -> VendorSpec:
    """The preset ``name``.

    Raises:
        DriverConfigError: Not a preset, naming the presets.
    """
    if name not in VENDORS:
        raise DriverConfigError(f"format = {name!r}: expected one of {', '.join(map(repr, VENDORS))}")
    return VENDORS[name]


def line_image(spec: VendorSpec, path: str | PathLike[str]) -> bytes:
    """The lines the preset's parser reads from the file ``path`` (its loader's, or its bytes).

    Raises:
        OSError: The file cannot be opened.
        DriverConfigError: Not a regular file, too large, or unreadable as the preset's kind.
    """
    if spec.loader is not None:
        return spec.loader(fspath(path))
    return read_regular_file(path, max_bytes=MAX_CART_FILE_BYTES, what=f"a {spec.title}")


def _header_found(spec: VendorSpec, data: bytes) -> TableParser | None:
    parser = TableParser(spec)
    for line in data.splitlines()[: spec.max_preamble_lines - 1]:
        try:
            parser.parse(line)
        except (DecodeError, DriverConfigError):  # not this format
            return None
        if parser.has_header:
            return parser
    return None


def detect_format(path: str | PathLike[str]) -> str | None:
    """Which format the file is: a preset name, ``"hilbo-line"``, or None when unknown.

    xlsx is read as COSMED, Excel-2003 XML as CORTEX (the presets of those file kinds), if
    their header is found. A text file is hilbo-line when a line starts with ``$HBR``; else
    each text preset whose header is found in the first 64 kB is a candidate, and the one
    whose markers (vendor or software name, Vyntus's ``ID-nummer``) appear wins; without
    markers, ``TIME`` in capitals says Parvo, ``,``/``;`` separators COSMED CSV, tabs Vyntus.

    Raises:
        OSError: The file cannot be read.
        DriverConfigError: Not a regular file, larger than any cart file
            (:data:`~drivers.files.MAX_CART_FILE_BYTES`), or an xlsx or Excel-2003 XML file
            that its loader cannot read (naming the sheet and row).
    """
    with open_regular_file(path, max_bytes=MAX_CART_FILE_BYTES, what="a cart export or recording") as fh:
        head = fh.read(_SNIFF_BYTES)
    if head.startswith(b"PK\x03\x04"):
        # A zip is an xlsx or nothing a cart writes: its loader's error (a damaged sheet, with
        # the row) says more than "unknown format".
        image = COSMED.loader(fspath(path)) if COSMED.loader else b""
        return COSMED.name if _header_found(COSMED, image) else None
    if b"urn:schemas-microsoft-com:office:spreadsheet" in head:
        image = CORTEX.loader(fspath(path)) if CORTEX.loader else b""
        return CORTEX.name if _header_found(CORTEX, image) else None
    if any(line.lstrip().startswith(b"$HBR,") for line in head.splitlines()):
        return "hilbo-line"
    text = head.decode("utf-8", errors="replace").lower()
    found = {}
    for spec in (PARVO, VYNTUS, COSMED_CSV):
        parser = _header_found(spec, head)
        if parser is not None:
            found[spec.name] = parser
    if not found:
        return None
    for name in found:
        if any(m in text for m in VENDORS[name].markers):
            return name
    for name, parser in found.items():
        time_name = parser.mapping["t_s"].name
        if name == PARVO.name and time_name == "TIME":
            return name
        if name == COSMED_CSV.name and parser.delimiter in (",", ";"):
            return name
        if name == VYNTUS.name and parser.delimiter == "\t" and normalize_name(time_name) != "time":
            return name
    return next(iter(found))
