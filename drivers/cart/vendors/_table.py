"""The table reader shared by the vendor presets: a header found by localized names, units rows.

Vendor exports are tables with a preamble (patient data, test settings), a header row whose names
depend on the software's language (``t``/``Tid``/``TIME``; ``VO2``/``V'O2``; ``HR``/``HF``), one
or more rows under it with units (``mL/min``, ``L/min``, ``mm:ss``) and data rows with a decimal
point or a decimal comma. A :class:`VendorSpec` lists a vendor's names, default units and field
separators; :class:`TableParser` applies it one line at a time (a :class:`BreathParser`), so the
same code reads an exported file (:mod:`drivers.cart.pipeline`), a replayed file and, for the
vendors that stream text, the live line stream. Binary exports (xlsx, Excel-2003 XML) are first
turned into a *line image* (tab-separated lines of the cells' text) by the vendor's loader.

How a line is read:

1. Before the header, each line is split with every candidate separator; the first split that
   holds a time, a VO2 and a VCO2 name (compared after :func:`normalize_name`) is the header.
   Label/value pairs seen on the way (``Gewicht (kg)`` | ``71.5``) fill :attr:`TableParser.metadata`.
2. Up to ``max_subheader_rows`` rows after the header whose time cell is not a time are header
   continuation (units, ``STPD``, ``-----``); a unit found there under a mapped column sets that
   column's unit (``L/min`` -> x1000 to ml/min, ``min`` -> x60 to s).
3. Data rows: times ``h:mm:ss``/``mm:ss`` (a fraction allowed, ``.`` or ``,``) or a number in the
   column's unit; numbers with ``.`` or ``,`` as decimal mark (a number holding both is rejected
   as ``bad_number``, never guessed). A blank row is skipped; a row with text but none in the
   mapped columns is rejected (``missing_field``) and so counted.
"""

from __future__ import annotations

import contextlib
import csv
import re
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from drivers.cart._numbers import parse_decimal, shorten
from drivers.cart.line import ParsedBreath
from drivers.cart.reasons import RejectReason
from drivers.errors import DecodeError, DriverConfigError, DriverError
from hilbo_core.types import BreathRecord

__all__ = [
    "FIELDS",
    "MAX_SHEET_CELLS",
    "MAX_SHEET_COLUMNS",
    "REQUIRED_FIELDS",
    "LineImage",
    "TableParser",
    "VendorSpec",
    "cells_to_line",
    "normalize_name",
    "parse_clock",
]

FIELDS = ("t_s", "vo2_ml_min", "vco2_ml_min", "ve_l_min", "rer", "hr_bpm")
"""The :class:`BreathRecord` fields a vendor table can fill, required ones first."""
REQUIRED_FIELDS = FIELDS[:3]

_CLOCK = re.compile(r"(?:(\d+):)?(\d+):(\d+(?:[.,]\d*)?)")
_MISSING = frozenset({"", "-", "--", "---", "na", "n/a", "nan", "null"})
_GAS_UNITS = {"ml/min": 1.0, "l/min": 1000.0}
_TIME_UNITS = {"s": 1.0, "sec": 1.0, "min": 60.0, "hh:mm:ss": 1.0, "h:mm:ss": 1.0, "mm:ss": 1.0,
               "m:ss": 1.0}
_MASS = re.compile(r"(\d+(?:[.,]\d+)?)\s*(?:kg)?\s*$", re.IGNORECASE)


def normalize_name(text: str) -> str:
    """A header cell as compared with the aliases: lower case, no spaces, quotes or BOM.

    ``V'O2``, ``V’O2`` and ``VO2`` are all ``vo2``; ``VO2/kg`` stays ``vo2/kg`` (another quantity).
    """
    return re.sub(r"[\s'’`\ufeff\u0307]", "", text).lower()


def _normalize_unit(text: str) -> str:
    out = normalize_name(text)
    for noise in ("(stpd)", "stpd", "(btps)", "btps", "(", ")"):
        out = out.replace(noise, "")
    return out


def parse_clock(text: str) -> float | None:
    """Seconds of ``h:mm:ss[.f]`` or ``mm:ss[.f]`` (``,`` allowed as decimal mark), else None."""
    match = _CLOCK.fullmatch(text.strip())
    if match is None:
        return None
    hours, minutes, seconds = match.groups()
    value = float(seconds.replace(",", "."))
    if (int(minutes) > 59 and hours is not None) or value >= 60.0:
        return None
    return (int(hours) if hours else 0) * 3600.0 + int(minutes) * 60.0 + value


def cells_to_line(cells: Sequence[str]) -> bytes:
    """One row of a spreadsheet as a tab-separated UTF-8 line (tabs and breaks in cells -> space)."""
    return "\t".join(re.sub(r"[\t\r\n]+", " ", c) for c in cells).encode("utf-8")


MAX_SHEET_COLUMNS = 16_384
"""Most cells a spreadsheet row may have (Excel's own limit, column ``XFD``)."""
MAX_SHEET_CELLS = 2_000_000
"""Most cells a spreadsheet export may have: a one-hour breath-by-breath export has about 1,500
rows of 100-150 columns (~200,000 cells), so this leaves a factor of 10, and bounds the time and
memory a damaged sheet (a row number or a column index of 10^9) can take (about 1 s of CPU to
refuse one)."""


class LineImage:
    """The line image of a spreadsheet being read, bounded, with the one error boundary of its loader.

    A loader (xlsx, Excel-2003 XML) adds rows with :meth:`add` inside :meth:`reading`; whatever
    the parsing library raises there (a damaged zip member, malformed XML, a value of the wrong
    type) becomes a :class:`DriverConfigError` naming the file and the row reached, so a damaged
    export is refused with its name, never a traceback.

    Attributes:
        path: The file, for messages.
        sheet: The worksheet being read (for messages), "" before the first.
        rows: Rows added to the current sheet.
        cells: Cells added in total (every sheet).
    """

    def __init__(self, path: str) -> None:
        self.path = path
        self.sheet = ""
        self.rows = 0
        self.cells = 0
        self._max_cells = MAX_SHEET_CELLS
        self._max_columns = MAX_SHEET_COLUMNS
        self._lines: list[bytes] = []

    def new_sheet(self, name: str) -> None:
        """Start another worksheet: the rows so far are dropped (:meth:`data` is one sheet's)."""
        self.sheet, self.rows, self._lines = name, 0, []

    def column(self, index: int, row_cells: int) -> int:
        """Check a 1-based column index a cell gives (``ss:Index``); return it.

        Raises:
            DriverConfigError: Beyond :data:`MAX_SHEET_COLUMNS`, or not after the row's
                ``row_cells`` cells already read (a spreadsheet's indexes only grow).
        """
        if not row_cells < index <= self._max_columns:
            raise DriverConfigError(
                f"{self.path}: {self.position()}: a cell at column {index}; expected a column "
                f"after the row's {row_cells} cells and at most {self._max_columns}")
        return index

    def position(self) -> str:
        """Where reading is: ``sheet 'Daten', row 13``, the row being read (1-based)."""
        sheet = f"sheet {self.sheet!r}, " if self.sheet else ""
        return f"{sheet}row {self.rows + 1}"

    def add(self, cells: Sequence[str]) -> bytes:
        """Add one row (its cells' texts); return its line.

        Raises:
            DriverConfigError: More than :data:`MAX_SHEET_COLUMNS` cells in the row, or more
                than :data:`MAX_SHEET_CELLS` in the file.
        """
        if len(cells) > self._max_columns:
            raise DriverConfigError(f"{self.path}: {self.position()} has {len(cells):,} cells; "
                                    f"a spreadsheet row has at most {self._max_columns:,}")
        self.cells += len(cells)
        if self.cells > self._max_cells:
            raise DriverConfigError(f"{self.path}: more than {self._max_cells:,} cells by "
                                    f"{self.position()}; a cart export has far fewer (a damaged "
                                    "row number or column index?)")
        self.rows += 1
        line = cells_to_line(cells)
        self._lines.append(line)
        return line

    def data(self) -> bytes:
        """The current sheet's lines, each ended by a newline."""
        return b"\n".join(self._lines) + b"\n"

    @contextlib.contextmanager
    def reading(self, what: str) -> Iterator[None]:
        """The loader's error boundary: anything but a DriverError becomes one naming the file.

        Args:
            what: What the file should be (``"xlsx workbook"``), for the message.

        Raises:
            DriverConfigError: ``"<path>: not a readable <what> (<position>: <type>: <error>)"``.
        """
        try:
            yield
        except DriverError:
            raise
        except Exception as err:  # the boundary: a damaged file makes libraries raise anything
            raise DriverConfigError(f"{self.path}: not a readable {what} ({self.position()}: "
                                    f"{type(err).__name__}: {shorten(str(err))})") from err


@dataclass(frozen=True, slots=True)
class VendorSpec:
    """What a vendor's export looks like.

    Attributes:
        name: The ``[cart] format`` value (``"cosmed"``, ...).
        title: Cart and software, for messages and ``hilbo cart inspect``.
        aliases: Per field of :data:`FIELDS`, the header names it may have, as
            :func:`normalize_name` gives them (all languages the software exports in).
        default_units: Per field, the unit when no units row says otherwise
            (``"ml/min"``/``"l/min"`` for the gases, ``"s"``/``"min"`` for a numeric time).
        delimiters: Field separators to try on each line before the header.
        loader: Turns a file into its line image (xlsx, XML); None when the file's own lines are
            read (text exports, which can then also come over a live link).
        mass_labels: Normalized labels of the body mass in the preamble.
        markers: Texts (case-insensitive) that identify the vendor in a file's first kilobytes,
            for :func:`drivers.cart.vendors.detect_format`.
        zero_hr_is_missing: Read a heart rate of 0 as "not reported" (carts write 0 when no
            heart-rate monitor is paired; the validator would reject every breath otherwise).
        end_markers: Normalized first cells of a row that starts a block of non-breath rows
            (Parvo's ``Events``): the rows under it that are not breaths are counted as
            ``event`` rejects; a breath after them is still read (a live stream goes on).
        max_preamble_lines: Give up looking for the header after this many lines.
        max_subheader_rows: Rows after the header that may hold units.
    """

    name: str
    title: str
    aliases: Mapping[str, tuple[str, ...]]
    default_units: Mapping[str, str]
    delimiters: tuple[str, ...] = ("\t",)
    loader: Callable[[str], bytes] | None = None
    mass_labels: tuple[str, ...] = ("gewicht", "gewicht(kg)", "weight", "weight(kg)", "bodymass",
                                    "vikt", "vikt(kg)", "poids", "peso")
    markers: tuple[str, ...] = ()
    zero_hr_is_missing: bool = True
    end_markers: tuple[str, ...] = ()
    max_preamble_lines: int = 300
    max_subheader_rows: int = 4

    @property
    def is_live_capable(self) -> bool:
        """True when the export is text lines, which a live link can carry too."""
        return self.loader is None


@dataclass
class _Column:
    index: int
    name: str
    unit: str = ""
    factor: float = 1.0


@dataclass
class TableParser:
    """Stateful line parser of a vendor table (see the module docstring); one per stream.

    Attributes:
        spec: The vendor.
        columns: The header row once found (cell texts), else None.
        mapping: Per field, the column it is read from (index, header name, unit), once found.
        metadata: Label/value pairs of the preamble that were recognised (``body_mass_kg``).
        delimiter: The separator the header was found with.
    """

    spec: VendorSpec
    columns: list[str] | None = None
    mapping: dict[str, _Column] = field(default_factory=dict)
    metadata: dict[str, Any] = field(default_factory=dict)
    delimiter: str | None = None
    _preamble: int = 0
    _subheader_left: int = 0
    _data_seen: bool = False
    _header_norm: list[str] | None = None
    _in_events: bool = False

    @property
    def format_name(self) -> str:
        """The ``[cart] format`` value of this parser."""
        return self.spec.name

    @property
    def has_header(self) -> bool:
        """True once the header row has been found."""
        return self.columns is not None

    def parse(self, line: bytes) -> ParsedBreath | None:
        """Parse one line: None for preamble, header, units and blank rows.

        A blank row (no text at all, or none in the table's columns beside COSMED's subject
        block) carries nothing and returns None. Every other row that is not a breath raises,
        so it is counted with its reason: a row with text but none in the mapped columns
        (``missing_field``: another field separator?), an end marker (Parvo's ``Events``) and
        the rows under it that are not breaths (``event``). Breaths after an events block are
        read: on a live link the table may go on after it.

        Raises:
            DecodeError: A data row that is not a breath (``bad_time``, ``bad_number``,
                ``missing_field``, ``field_count``, ``garbage``, ``event``).
            DriverConfigError: No header in the first ``max_preamble_lines`` lines, or a unit
                under VO2/VCO2 that is not a flow (``mL/min/kg``).
        """
        text = _decode(line.rstrip(b"\r\n"))
        if self.columns is None:
            self._find_header(text)
            return None
        cells = self._split(text, self.delimiter or "\t")
        norm = [normalize_name(c) for c in cells]
        if norm and norm[0] in self.spec.end_markers:
            self._in_events = True
            raise DecodeError(RejectReason.EVENT, f"{shorten(cells[0].strip())!r}: the rows under it "
                                                  "are events, not breaths (a breath after them is read)")
        try:
            return self._data_row(cells, norm)
        except DecodeError as err:
            if not self._in_events:
                raise
            raise DecodeError(RejectReason.EVENT, f"a row of the events block, not a breath "
                                                  f"({err}): {shorten(text)!r}") from err

    def _data_row(self, cells: list[str], norm: list[str]) -> ParsedBreath | None:
        if norm[: len(self._header_norm or [])] == self._header_norm:
            return None  # a repeated header (live stream reconnect, new stage)
        time_cell = _cell(cells, self.mapping["t_s"].index)
        mapped_empty = all(_cell(cells, c.index).strip().lower() in _MISSING for c in self.mapping.values())
        first = min(c.index for c in self.mapping.values())
        if mapped_empty and (
            not any(c.strip() for c in cells)
            or (len(cells) > first and all(c.strip().lower() in _MISSING for c in cells[first:]))
        ):
            return None  # a blank row, or blank in the table's columns (beside a subject block)
        if not self._data_seen and self._subheader_left > 0 and self._time(time_cell) is None:
            self._subheader_left -= 1
            self._read_units(cells)
            return None
        if mapped_empty:
            names = ", ".join(repr(c.name) for c in self.mapping.values())
            row = (self.delimiter or "\t").join(cells)
            raise DecodeError(RejectReason.MISSING_FIELD,
                              f"no value in any of the mapped columns ({names}), yet the row holds "
                              f"{shorten(row)!r}: another field separator?")
        record = self._record(cells)
        self._data_seen = True
        self._in_events = False  # the table goes on after the events block
        if "body_mass_kg" not in self.metadata:
            # COSMED puts the subject block beside the table, in the columns before it.
            self._read_metadata(cells[:first])
        return ParsedBreath(record, seq=None)

    # -- header -----------------------------------------------------------------------------------

    def _find_header(self, text: str) -> None:
        for delimiter in self.spec.delimiters:
            cells = self._split(text, delimiter)
            norm = [normalize_name(c) for c in cells]
            found: dict[str, int] = {}
            for f in FIELDS:
                for alias in self.spec.aliases.get(f, ()):
                    if alias in norm:
                        found[f] = norm.index(alias)
                        break
            if all(f in found for f in REQUIRED_FIELDS):
                self.columns = [c.strip() for c in cells]
                self._header_norm = norm
                self.delimiter = delimiter
                self.mapping = {
                    f: _Column(i, self.columns[i], self.spec.default_units.get(f, ""),
                               _factor(f, self.spec.default_units.get(f, "")))
                    for f, i in found.items()
                }
                self._subheader_left = self.spec.max_subheader_rows
                return
            self._read_metadata(cells)
        self._preamble += 1
        if self._preamble >= self.spec.max_preamble_lines:
            names = ", ".join(f"{f}: {'/'.join(self.spec.aliases[f])}" for f in REQUIRED_FIELDS)
            raise DriverConfigError(
                f"{self.spec.name}: no header row with the columns ({names}) in the first "
                f"{self.spec.max_preamble_lines} lines; is this a {self.spec.title} export? "
                f"last line: {shorten(text)!r}"
            )

    def _read_metadata(self, cells: list[str]) -> None:
        if "body_mass_kg" in self.metadata:
            return
        for i, cell in enumerate(cells[:-1]):
            if normalize_name(cell) in self.spec.mass_labels:
                value = next((c for c in cells[i + 1:] if c.strip()), "")
                match = _MASS.search(value.strip())
                if match:
                    self.metadata["body_mass_kg"] = float(match.group(1).replace(",", "."))
                    return

    def _read_units(self, cells: list[str]) -> None:
        for f, col in self.mapping.items():
            unit = _normalize_unit(_cell(cells, col.index))
            if f in ("vo2_ml_min", "vco2_ml_min") and unit:
                if unit in _GAS_UNITS:
                    col.unit, col.factor = _cell(cells, col.index).strip(), _GAS_UNITS[unit]
                elif "/kg" in unit or unit.endswith("kg"):
                    raise DriverConfigError(
                        f"{self.spec.name}: column {col.name!r} is in {_cell(cells, col.index)!r}; "
                        "expected an absolute flow in mL/min or L/min"
                    )
            elif f == "t_s" and unit in _TIME_UNITS:
                col.unit, col.factor = _cell(cells, col.index).strip(), _TIME_UNITS[unit]

    # -- data -------------------------------------------------------------------------------------

    @staticmethod
    def _split(text: str, delimiter: str) -> list[str]:
        try:
            return next(csv.reader([text], delimiter=delimiter))
        except (csv.Error, StopIteration) as err:
            raise DecodeError(RejectReason.GARBAGE, f"not a table row: {shorten(text)!r}") from err

    def _time(self, cell: str) -> float | None:
        cell = cell.strip()
        if ":" in cell:
            return parse_clock(cell)
        try:
            return _number(cell, "t") * self.mapping["t_s"].factor
        except DecodeError:
            return None

    def _record(self, cells: list[str]) -> BreathRecord:
        needed = max(c.index for c in self.mapping.values() if c.index >= 0) + 1
        required_needed = max(self.mapping[f].index for f in REQUIRED_FIELDS) + 1
        if len(cells) < required_needed:
            raise DecodeError(RejectReason.FIELD_COUNT, f"{len(cells)} fields, need {needed}")
        values: dict[str, float | None] = {}
        for f, col in self.mapping.items():
            text = _cell(cells, col.index).strip()
            if text.lower() in _MISSING:
                if f in REQUIRED_FIELDS:
                    raise DecodeError(RejectReason.MISSING_FIELD, f"column {col.name!r} is empty")
                values[f] = None
                continue
            if f == "t_s":
                t = self._time(text)
                if t is None:
                    raise DecodeError(RejectReason.BAD_TIME,
                                      f"time {shorten(text)!r} in column {col.name!r} is not "
                                      f"h:mm:ss, mm:ss or a number ({col.unit or 's'})")
                values[f] = t
            else:
                values[f] = _number(text, col.name) * col.factor
        if self.spec.zero_hr_is_missing and values.get("hr_bpm") == 0.0:
            values["hr_bpm"] = None
        return BreathRecord(
            t_s=values["t_s"] or 0.0,
            vo2_ml_min=values["vo2_ml_min"] or 0.0,
            vco2_ml_min=values["vco2_ml_min"] or 0.0,
            ve_l_min=values.get("ve_l_min"),
            rer=values.get("rer"),
            hr_bpm=values.get("hr_bpm"),
        )


def _factor(field_name: str, unit: str) -> float:
    u = _normalize_unit(unit)
    if field_name in ("vo2_ml_min", "vco2_ml_min"):
        return _GAS_UNITS.get(u, 1.0)
    if field_name == "t_s":
        return _TIME_UNITS.get(u, 1.0)
    return 1.0


def _cell(cells: list[str], index: int) -> str:
    return cells[index] if 0 <= index < len(cells) else ""


def _decode(raw: bytes) -> str:
    try:
        return raw.decode("utf-8")
    except UnicodeDecodeError:
        # Windows exports in a Western-European locale are cp1252 (ä, ö, ü, °, µ).
        return raw.decode("cp1252", errors="replace")


def _number(text: str, name: str) -> float:
    text = text.strip()
    if "," in text:
        if "." in text:
            # 1.234,5 or 1,234.5: a thousands separator; reading either way could be wrong.
            raise DecodeError(RejectReason.BAD_NUMBER, f"{name} = {shorten(text)!r} has both '.' and ','")
        text = text.replace(",", ".")
    return parse_decimal(text, name)
