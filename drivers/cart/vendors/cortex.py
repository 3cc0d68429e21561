"""CORTEX MetaLyzer (MetaSoft Studio): the Excel-2003 XML spreadsheet export.

Layout (checked against ``shared/data/cart-exports/cortex_test.xml``, a MetaLyzer 3B-R3 export in
German): one worksheet ``MetasoftStudio`` holding, as rows of one table, the patient block
(``Gewicht`` | ``74,8kg``), the test block, a summary table per phase and then the breath table:
a header (``t``, ``Phase``, ``Marker``, ``V'O2/kg``, ``HF``, ..., ``V'CO2``, ``V'O2``, ...), a
units row (``h:mm:ss``, ``L/min``) and one row per breath. Times are ``h:mm:ss`` strings, gases
in L/min as XML numbers; values typed as strings may carry a decimal comma.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from os import PathLike, fspath

from drivers.cart.vendors._table import VendorSpec, cells_to_line
from drivers.errors import DriverConfigError

__all__ = ["CORTEX", "load_spreadsheet_xml"]

_SS = "urn:schemas-microsoft-com:office:spreadsheet"


def load_spreadsheet_xml(path: str | PathLike[str]) -> bytes:
    """The line image of an Excel-2003 XML spreadsheet: every row of every table, tab-separated.

    ``ss:Index`` (a cell's 1-based column after skipped empty cells) is honoured. The export is
    a local file written by the cart's software; ``xml.etree`` does not fetch external entities.

    Raises:
        OSError: The file cannot be read.
        DriverConfigError: Not well-formed XML, or not a spreadsheet.
    """
    try:
        root = ET.parse(fspath(path)).getroot()
    except ET.ParseError as err:
        raise DriverConfigError(f"{fspath(path)}: not an XML spreadsheet ({err})") from err
    if root.tag != f"{{{_SS}}}Workbook":
        raise DriverConfigError(f"{fspath(path)}: XML root {root.tag!r} is not an Excel-2003 "
                                "spreadsheet <Workbook>")
    lines: list[bytes] = []
    for row in root.iter(f"{{{_SS}}}Row"):
        cells: list[str] = []
        for cell in row.findall(f"{{{_SS}}}Cell"):
            index = cell.get(f"{{{_SS}}}Index")
            if index is not None and index.isdigit():
                cells.extend([""] * max(0, int(index) - 1 - len(cells)))
            data = cell.find(f"{{{_SS}}}Data")
            cells.append("" if data is None else "".join(data.itertext()))
        lines.append(cells_to_line(cells))
    return b"\n".join(lines) + b"\n"


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
