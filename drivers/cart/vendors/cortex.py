"""CORTEX MetaLyzer (MetaSoft Studio): the Excel-2003 XML spreadsheet export.

Layout (checked against ``shared/data/cart-exports/cortex_test.xml``, a MetaLyzer 3B-R3 export in
German): one worksheet ``MetasoftStudio`` holding, as rows of one table, the patient block
(``Gewicht`` | ``74,8kg``), the test block, a summary table per phase and then the breath table:
a header (``t``, ``Phase``, ``Marker``, ``V'O2/kg``, ``HF``, ..., ``V'CO2``, ``V'O2``, ...), a
units row (``h:mm:ss``, ``L/min``) and one row per breath. Times are ``h:mm:ss`` strings, gases
in L/min as XML numbers; values typed as strings may carry a decimal comma.
"""

from __future__ import annotations

import io
import xml.etree.ElementTree as ET
from os import PathLike, fspath

from drivers.cart._numbers import shorten
from drivers.cart.vendors._table import LineImage, VendorSpec
from drivers.errors import DriverConfigError
from drivers.files import MAX_CART_FILE_BYTES, read_regular_file

__all__ = ["CORTEX", "load_spreadsheet_xml"]

_SS = "urn:schemas-microsoft-com:office:spreadsheet"


def load_spreadsheet_xml(path: str | PathLike[str]) -> bytes:
    """The line image of an Excel-2003 XML spreadsheet: every row of every table, tab-separated.

    ``ss:Index`` (a cell's 1-based column after skipped empty cells) is honoured up to
    :data:`~drivers.cart.vendors._table.MAX_SHEET_COLUMNS`. The export is a local file written
    by the cart's software; ``xml.etree`` does not fetch external entities, and expat (2.4 and
    later) refuses entity-expansion bombs. Streamed row by row (``iterparse``). Bounded: a regular
    file of at most :data:`~drivers.files.MAX_CART_FILE_BYTES` and at most
    :data:`~drivers.cart.vendors._table.MAX_SHEET_CELLS` cells, read inside one error boundary.

    Raises:
        OSError: The file cannot be opened.
        DriverConfigError: Not a regular file, too large, not well-formed XML, not a
            spreadsheet, or a cell index out of range (naming the file and the row).
    """
    p = fspath(path)
    data = read_regular_file(p, max_bytes=MAX_CART_FILE_BYTES, what="a CORTEX XML export")
    image = LineImage(p)
    with image.reading("XML spreadsheet"):
        # Streamed: each row is turned into its line and cleared, so memory holds one row, not
        # the whole tree of a large file.
        root_seen = False
        for event, el in ET.iterparse(io.BytesIO(data), events=("start", "end")):
            if event == "start":
                if not root_seen and el.tag != f"{{{_SS}}}Workbook":
                    raise DriverConfigError(f"{p}: XML root {shorten(el.tag)!r} is not an Excel-2003 "
                                            "spreadsheet <Workbook>")
                root_seen = True
                continue
            if el.tag != f"{{{_SS}}}Row":
                continue
            cells: list[str] = []
            for cell in el.findall(f"{{{_SS}}}Cell"):
                index = cell.get(f"{{{_SS}}}Index")
                if index is not None and index.isdigit():
                    # Bounded before the gap is filled: a damaged index must not allocate 4e9 cells.
                    at = image.column(int(index), len(cells))
                    cells.extend([""] * (at - 1 - len(cells)))
                data_el = cell.find(f"{{{_SS}}}Data")
                cells.append("" if data_el is None else "".join(data_el.itertext()))
            image.add(cells)
            el.clear()
    return image.data()


CORTEX = VendorSpec(
    name="cortex",
    title="CORTEX MetaSoft Studio XML export",
    aliases={
        "t_s": ("t", "time", "zeit"),
        "vo2_ml_min": ("vo2",),
        "vco2_ml_min": ("vco2",),
        "ve_l_min": ("ve",),
        "rer": ("rer", "rq"),
        "hr_bpm": ("hf", "hr"),
    },
    default_units={"t_s": "s", "vo2_ml_min": "l/min", "vco2_ml_min": "l/min"},
    delimiters=("\t",),
    loader=load_spreadsheet_xml,
    markers=("metasoft", "metalyzer", "cortex"),
)
