"""COSMED (Omnia / PFT Suite, K5 and Quark CPET): the xlsx export and the CSV export.

Layout of both (checked against ``shared/data/cart-exports/cosmed_test.xlsx``, an Omnia export in
German): the subject and test block sits in the first columns (``ID1``, ``Nachname``, ...,
``Gewicht (kg)`` | ``71.5``) *beside* the data table, whose header (``t``, ``Rf``/``Af``, ``VT``,
``VE``, ``VO2``, ``VCO2``, ``R``, ..., ``HR``/``HF``) starts in a later column of the first row;
the row under it holds the units (``s``, ``mL/min``, ``L/min``) and the data follow after a blank
row. ``t`` is clock time since the start of the test (``h:mm:ss``; in xlsx a time cell). VO2 and
VCO2 are in mL/min, HR is 0 when no heart-rate belt was paired (read as "not reported").

The CSV export (``cosmed-csv``) is the same table written as text: ``,`` between fields with a
``.`` decimal mark, or ``;`` with a ``,`` decimal mark in European locales. No CSV fixture from
a real cart was available; the preset follows the xlsx layout above and is tested on synthetic
files (``tests/data/cart/cosmed_k5.csv``). Being text, it also reads the same lines live.
"""

from __future__ import annotations

import contextlib
import datetime as dt
import warnings
import zipfile
from os import PathLike, fspath
from typing import BinaryIO

from drivers.cart.vendors._table import LineImage, VendorSpec
from drivers.errors import DecodeError, DriverConfigError
from drivers.files import MAX_CART_FILE_BYTES, describe_size, open_regular_file

__all__ = ["COSMED", "COSMED_CSV", "MAX_XLSX_UNPACKED_BYTES", "cell_text", "load_xlsx"]

MAX_XLSX_UNPACKED_BYTES = 256 << 20
"""Most bytes an xlsx export's members may unpack to (256 MiB; the real export: 60 kB)."""

_ALIASES = {
    "t_s": ("t", "time", "zeit", "tempo", "tiempo", "temps"),
    "vo2_ml_min": ("vo2",),
    "vco2_ml_min": ("vco2",),
    "ve_l_min": ("ve",),
    "rer": ("r", "rer", "rq"),
    "hr_bpm": ("hr", "hf", "fc"),
}
_UNITS = {"t_s": "s", "vo2_ml_min": "ml/min", "vco2_ml_min": "ml/min"}
_EXCEL_EPOCH = dt.datetime(1899, 12, 30)


def cell_text(value: object) -> str:
    """A spreadsheet cell's value as the text the table reader parses.

    Times become ``h:mm:ss.ffffff`` (openpyxl gives a ``datetime.time`` for a cell formatted as
    time, a ``datetime`` past 24 h), numbers their shortest exact text.
    """
    if value is None:
        return ""
    if isinstance(value, dt.datetime):
        value = value - _EXCEL_EPOCH
    if isinstance(value, dt.time):
        value = dt.timedelta(hours=value.hour, minutes=value.minute, seconds=value.second,
                             microseconds=value.microsecond)
    if isinstance(value, dt.timedelta):
        micros = round(value.total_seconds() * 1_000_000)
        minutes, us = divmod(micros, 60_000_000)
        hours, minutes = divmod(minutes, 60)
        return f"{hours}:{minutes:02d}:{us // 1_000_000:02d}.{us % 1_000_000:06d}"
    if isinstance(value, bool):
        return str(value)
    if isinstance(value, int | float):
        return repr(value)
    return str(value)


def load_xlsx(path: str | PathLike[str]) -> bytes:
    """The line image of an xlsx workbook: its first sheet with a data header, tab-separated.

    Bounded: a regular file of at most :data:`~drivers.files.MAX_CART_FILE_BYTES`, at most
    :data:`MAX_XLSX_UNPACKED_BYTES` unpacked (a zip bomb is refused before it is inflated) and
    at most :data:`~drivers.cart.vendors._table.MAX_SHEET_CELLS` cells. openpyxl's read-only
    mode parses each sheet lazily while its rows are iterated, so the whole read (not only the
    opening) is inside one error boundary (:meth:`LineImage.reading`).

    Raises:
        OSError: The file cannot be opened.
        DriverConfigError: Not a regular file, too large, or not a readable xlsx workbook
            (naming the file and the sheet and row reached).
    """
    import openpyxl  # imported here: only the xlsx presets need it

    from drivers.cart.vendors._table import TableParser

    p = fspath(path)
    image = LineImage(p)
    first: bytes | None = None
    with (open_regular_file(p, max_bytes=MAX_CART_FILE_BYTES, what="a COSMED xlsx export") as fh,
          image.reading("xlsx workbook"), warnings.catch_warnings()):
        # openpyxl warns about the parts it drops (an unknown extension, a missing stylesheet);
        # the data cells are what is read, and a damaged file is refused below, not warned about.
        warnings.simplefilter("ignore")
        _check_unpacked_size(fh, p)
        wb = openpyxl.load_workbook(fh, read_only=True, data_only=True)
        try:
            for ws in wb.worksheets:
                image.new_sheet(str(ws.title))
                parser = TableParser(COSMED)
                for row in ws.iter_rows(values_only=True):
                    line = image.add([cell_text(v) for v in row])
                    if not parser.has_header and image.rows < COSMED.max_preamble_lines:
                        with contextlib.suppress(DecodeError):  # a preamble line: not the header
                            parser.parse(line)
                if parser.has_header:
                    return image.data()
                first = image.data() if first is None else first
        finally:
            wb.close()
    return first or b""


def _check_unpacked_size(fh: BinaryIO, path: str) -> None:
    """Refuse a workbook whose members unpack to more than :data:`MAX_XLSX_UNPACKED_BYTES`.

    The sizes are the zip directory's; zipfile stops inflating a member at its stated size and
    checks its CRC, so a member cannot unpack to more than is checked here.
    """
    with zipfile.ZipFile(fh) as archive:
        unpacked = sum(i.file_size for i in archive.infolist())
    if unpacked > MAX_XLSX_UNPACKED_BYTES:
        raise DriverConfigError(f"{path}: unpacks to {describe_size(unpacked)}, more than the "
                                f"{describe_size(MAX_XLSX_UNPACKED_BYTES)} a cart export may have")
    fh.seek(0)


COSMED = VendorSpec(
    name="cosmed",
    title="COSMED Omnia/PFT Suite xlsx export",
    aliases=_ALIASES,
    default_units=_UNITS,
    delimiters=("\t",),
    loader=load_xlsx,
    markers=("cosmed",),
)

COSMED_CSV = VendorSpec(
    name="cosmed-csv",
    title="COSMED K5/Quark CSV export",
    aliases=_ALIASES,
    default_units=_UNITS,
    delimiters=(",", ";", "\t"),
    markers=("cosmed",),
)
