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

import datetime as dt
import zipfile
from os import PathLike, fspath

from drivers.cart.vendors._table import VendorSpec, cells_to_line
from drivers.errors import DriverConfigError

__all__ = ["COSMED", "COSMED_CSV", "cell_text", "load_xlsx"]

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

    Raises:
        OSError: The file cannot be read.
        DriverConfigError: The file is not an xlsx workbook.
    """
    import openpyxl  # imported here: only the xlsx presets need it
    from openpyxl.utils.exceptions import InvalidFileException

    from drivers.cart.vendors._table import TableParser

    try:
        wb = openpyxl.load_workbook(fspath(path), read_only=True, data_only=True)
    except (InvalidFileException, zipfile.BadZipFile, KeyError, ValueError) as err:
        raise DriverConfigError(f"{fspath(path)}: not an xlsx workbook ({err})") from err
    try:
        images: list[bytes] = []
        for ws in wb.worksheets:
            lines = [cells_to_line([cell_text(v) for v in row]) for row in ws.iter_rows(values_only=True)]
            parser = TableParser(COSMED)
            for line in lines[: COSMED.max_preamble_lines - 1]:
                parser.parse(line)
                if parser.has_header:
                    return b"\n".join(lines) + b"\n"
            images.append(b"\n".join(lines) + b"\n")
    finally:
        wb.close()
    return images[0] if images else b""


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
