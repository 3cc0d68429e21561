"""Column-mapped CSV: breath-by-breath exports of vendor carts (COSMED, Parvo, Vyntus, ...).

Every vendor names and formats its columns differently (COSMED: ``t`` as ``hh:mm:ss``, ``VO2``
and ``VCO2`` in ml/min, a units row under the header; Parvo: time in decimal minutes, gases in
l/min; European locales: ``;`` between fields and ``,`` as the decimal mark). A
:class:`CsvMapping` — built from the ``[cart.csv]`` table of the config — says where each
quantity is and in which unit; :class:`CsvBreathParser` applies it one line at a time, so the
same code reads a live stream and, through :func:`drivers.cart.pipeline.read_breath_file`, a
whole exported file.

Limits: one record per line (quoted fields may not contain line breaks); no thousands
separators (``1,234.5`` is rejected as ``bad_number``, never read as 1.2345); with a header the
first column carrying a mapped name is used if a name repeats.
"""

from __future__ import annotations

import csv
import io
import re
from collections.abc import Mapping
from dataclasses import dataclass, fields
from enum import StrEnum
from typing import Annotated, Any

from msgspec import Meta

from drivers.cart._numbers import parse_decimal, shorten
from drivers.cart._options import check_declared, check_keys, check_mapping, text, within
from drivers.cart.errors import EncodeError
from drivers.cart.line import ParsedBreath
from drivers.cart.reasons import RejectReason
from drivers.errors import DecodeError, DriverConfigError
from hilbo_core.types import BreathRecord

__all__ = [
    "CsvBreathParser",
    "CsvMapping",
    "GasUnit",
    "TimeFormat",
    "encode_csv_header",
    "encode_csv_row",
]

_BOM = "\ufeff"
_HMS = re.compile(r"(\d+):([0-5]?\d):([0-5]?\d(?:\.\d*)?)")
_MS = re.compile(r"(\d+):([0-5]?\d(?:\.\d*)?)")


class TimeFormat(StrEnum):
    """How the time column is written."""

    SECONDS = "s"
    """Decimal seconds, e.g. ``83.5``."""
    MINUTES = "min"
    """Decimal minutes, e.g. ``1.3917`` (Parvo)."""
    HMS = "hh:mm:ss"
    """Clock time since the test began, seconds may have a fraction: ``0:01:23.5`` (COSMED)."""
    MS = "mm:ss"
    """Minutes (may exceed 59) and seconds: ``75:23.5``."""


class GasUnit(StrEnum):
    """Unit of a VO2 or VCO2 column."""

    ML_MIN = "ml/min"
    L_MIN = "l/min"

    @property
    def to_ml_min(self) -> float:
        """Factor from this unit to ml/min."""
        return 1000.0 if self is GasUnit.L_MIN else 1.0


@dataclass(frozen=True, slots=True)
class CsvMapping:
    """Where each breath quantity is in a vendor CSV and how it is written.

    Attributes:
        time_column: Header name of the breath time.
        vo2_column: Header name of VO2 (unit ``vo2_unit``).
        vco2_column: Header name of VCO2 (unit ``vco2_unit``).
        ve_column: Header name of minute ventilation in l/min, or None.
        rer_column: Header name of RER, or None.
        hr_column: Header name of heart rate in beats/min, or None.
        time_format: How the time is written (:class:`TimeFormat`).
        vo2_unit: Unit of the VO2 column (:class:`GasUnit`).
        vco2_unit: Unit of the VCO2 column.
        delimiter: One-character field separator (``","``, ``";"``, ``"\\t"``).
        decimal: Decimal mark, ``"."`` or ``","``; must differ from ``delimiter``.
        header_row: 0-based index, among non-blank lines, of the header line; None finds the
            header as the first line that contains all mapped column names (vendor preambles
            vary in length with the patient data filled in).
        skip_rows: Lines to skip after the header (e.g. 1 for COSMED's units row).
        columns: Column names in order for a stream *without* a header line (then
            ``header_row`` must be None); None when the data has a header.
        missing: Field texts that mean "not reported" (a required field that is missing
            rejects the row as ``missing_field``).
        encoding: Text encoding of the bytes (``"utf-8"``, ``"latin-1"``, ...). A UTF-8 byte
            order mark before the header is ignored.
        max_preamble_lines: With ``header_row`` None, give up looking for the header after
            this many lines (a wrong mapping must fail loudly, not yield nothing forever).
    """

    time_column: Annotated[str, Meta(min_length=1)]
    vo2_column: Annotated[str, Meta(min_length=1)]
    vco2_column: Annotated[str, Meta(min_length=1)]
    ve_column: Annotated[str, Meta(min_length=1)] | None = None
    rer_column: Annotated[str, Meta(min_length=1)] | None = None
    hr_column: Annotated[str, Meta(min_length=1)] | None = None
    time_format: TimeFormat = TimeFormat.SECONDS
    vo2_unit: GasUnit = GasUnit.ML_MIN
    vco2_unit: GasUnit = GasUnit.ML_MIN
    delimiter: str = ","
    decimal: str = "."
    header_row: Annotated[int, Meta(ge=0)] | None = None
    skip_rows: Annotated[int, Meta(ge=0)] = 0
    columns: tuple[str, ...] | None = None
    missing: tuple[str, ...] = ("", "-", "--", "NA", "N/A")
    encoding: str = "utf-8"
    max_preamble_lines: Annotated[int, Meta(ge=1)] = 200

    def __post_init__(self) -> None:
        check_declared(self)
        # delimiter, decimal, columns, missing and encoding: sets of characters, checks between
        # fields and a codec look-up, checked here.
        if (
            not isinstance(self.delimiter, str)
            or len(self.delimiter) != 1
            or self.delimiter in ('"', "\r", "\n")
        ):
            raise DriverConfigError(
                f"delimiter = {self.delimiter!r}: expected one character other than '\"', CR, LF"
            )
        if self.decimal not in (".", ","):
            raise DriverConfigError(f"decimal = {self.decimal!r}: expected '.' or ','")
        if self.decimal == self.delimiter:
            raise DriverConfigError(
                f"decimal = {self.decimal!r} equals delimiter; use e.g. delimiter ';' with ','"
            )
        if self.columns is not None:
            cols = _str_tuple(self.columns, "columns")
            if self.header_row is not None:
                raise DriverConfigError(
                    f"columns = {list(cols)!r} and header_row = {self.header_row!r}: "
                    "give columns only for data without a header line"
                )
            absent = [c for c in self.mapped_columns if c not in cols]
            if absent:
                raise DriverConfigError(f"columns = {list(cols)!r} lacks the mapped column(s) {absent!r}")
            _set(self, "columns", cols)
        _set(self, "missing", _str_tuple(self.missing, "missing", allow_empty_items=True))
        try:
            "".encode(text(self.encoding, "encoding"))
        except LookupError as err:
            raise DriverConfigError(f"encoding = {self.encoding!r}: unknown text encoding") from err

    @property
    def mapped_columns(self) -> tuple[str, ...]:
        """The column names this mapping reads, required ones first."""
        names = (self.time_column, self.vo2_column, self.vco2_column)
        optional = (self.ve_column, self.rer_column, self.hr_column)
        return names + tuple(c for c in optional if c is not None)

    @classmethod
    def from_dict(cls, data: Mapping[str, Any], where: str = "csv") -> CsvMapping:
        """Build from a config table (TOML lists become tuples).

        Raises:
            DriverConfigError: Naming the unknown key, or the key with a bad value and what is
                allowed; required keys are ``time_column``, ``vo2_column``, ``vco2_column``.
        """
        data = check_mapping(data, where)
        check_keys(data, [f.name for f in fields(cls)], where)
        for key in ("time_column", "vo2_column", "vco2_column"):
            if key not in data:
                raise DriverConfigError(f"{where}: missing required key {key!r}")
        kwargs = {k: tuple(v) if isinstance(v, list) else v for k, v in data.items()}
        try:
            return cls(**kwargs)
        except DriverConfigError as err:
            raise within(where, err) from err


def _set(obj: object, name: str, value: object) -> None:
    object.__setattr__(obj, name, value)


def _str_tuple(value: object, name: str, *, allow_empty_items: bool = False) -> tuple[str, ...]:
    if not isinstance(value, tuple | list) or not all(
        isinstance(v, str) and (allow_empty_items or v) for v in value
    ):
        raise DriverConfigError(f"{name} = {value!r}: expected a list of strings")
    return tuple(value)


class CsvBreathParser:
    """Stateful line parser applying a :class:`CsvMapping`; feed it lines in order.

    Lines before the header, the header itself, the ``skip_rows`` after it and repeats of the
    header return None. A data row returns a :class:`ParsedBreath` (``seq`` None: CSV carries
    none) or raises :class:`DecodeError` with a :class:`RejectReason`.
    """

    format_name = "csv"

    def __init__(self, mapping: CsvMapping) -> None:
        self.mapping = mapping
        self._lines_seen = 0
        self._skip_left = 0
        self._header: list[str] | None = None
        self._index: dict[str, int] | None = None
        self._best_hits = 0
        self._best_row: list[str] = []
        if mapping.columns is not None:
            self._index = self._resolve(list(mapping.columns))

    @property
    def has_header(self) -> bool:
        """True once the column layout is known (header found, or ``columns`` configured)."""
        return self._index is not None

    def parse(self, line: bytes) -> ParsedBreath | None:
        """Parse one line (terminator optional).

        Raises:
            DecodeError: A data row that is not a breath (reason: ``garbage``, ``field_count``,
                ``missing_field``, ``bad_number``, ``bad_time``).
            DriverConfigError: The header does not contain the mapped columns (at
                ``header_row``, or nowhere in the first ``max_preamble_lines`` lines).
        """
        m = self.mapping
        try:
            decoded = line.rstrip(b"\r\n").decode(m.encoding)
        except UnicodeDecodeError as err:
            if self._index is None:
                self._count_preamble(line)
                return None
            raise DecodeError(RejectReason.GARBAGE, f"not {m.encoding} text at byte {err.start}") from err
        if self._index is None:
            self._find_header(decoded)
            return None
        if self._skip_left:
            self._skip_left -= 1
            return None
        row = self._split(decoded)
        if self._header is not None and [c.strip() for c in row] == self._header:
            return None  # exports and live streams repeat the header (new stage, reconnect)
        return ParsedBreath(self._record(row), seq=None)

    def _split(self, decoded: str) -> list[str]:
        try:
            return next(csv.reader([decoded], delimiter=self.mapping.delimiter, strict=True))
        except (csv.Error, StopIteration) as err:
            raise DecodeError(RejectReason.GARBAGE, f"not a CSV row: {shorten(decoded)!r}") from err

    def _count_preamble(self, line: str | bytes) -> None:
        self._lines_seen += 1
        if self._lines_seen > self.mapping.max_preamble_lines:
            best = (f"; the line most like a header has the columns {_listed(self._best_row)}"
                    if self._best_row else "")
            raise DriverConfigError(
                f"csv: no header with columns {list(self.mapping.mapped_columns)!r} in the first "
                f"{self.mapping.max_preamble_lines} lines{best}; last line: {shorten(line)!r}"
            )

    def _find_header(self, decoded: str) -> None:
        m = self.mapping
        try:
            row = [c.strip() for c in self._split(decoded)]
        except DecodeError:
            row = []  # an unparseable preamble line is simply not the header
        if row:
            row[0] = row[0].lstrip(_BOM).strip()
        if m.header_row is not None:
            if self._lines_seen == m.header_row:
                self._index = self._resolve(row)  # raises if the mapped names are absent
                self._header = row
                self._skip_left = m.skip_rows
            self._lines_seen += 1
            return
        required = m.mapped_columns[:3]
        hits = sum(c in row for c in m.mapped_columns)
        if hits > self._best_hits:
            self._best_hits, self._best_row = hits, row
        # A row with the time, VO2 and VCO2 names is the header even if an optional mapped
        # column is absent: then say which one, instead of searching on for 200 lines.
        if all(c in row for c in required):
            self._index = self._resolve(row)
            self._header = row
            self._skip_left = m.skip_rows
            return
        self._count_preamble(decoded)

    def _resolve(self, names: list[str]) -> dict[str, int]:
        absent = [c for c in self.mapping.mapped_columns if c not in names]
        if absent:
            m = self.mapping
            keys = [k for k in ("time_column", "vo2_column", "vco2_column", "ve_column", "rer_column",
                                "hr_column") if getattr(m, k) in absent]
            given = ", ".join(f"csv.{k} = {getattr(m, k)!r}" for k in keys)
            raise DriverConfigError(
                f"{given}: no column {' or '.join(map(repr, absent))} in the header; the file's "
                f"columns are: {_listed(names)}"
            )
        return {c: names.index(c) for c in self.mapping.mapped_columns}

    def _record(self, row: list[str]) -> BreathRecord:
        m = self.mapping
        index = self._index
        if index is None:  # pragma: no cover - parse() only calls this after the header
            raise RuntimeError("CSV header not resolved")
        needed = max(index.values()) + 1
        if len(row) < needed:
            raise DecodeError(RejectReason.FIELD_COUNT, f"{len(row)} fields, need {needed}")

        def field(column: str) -> str | None:
            value = row[index[column]].strip()
            return None if value in m.missing else value

        def required(column: str) -> str:
            value = field(column)
            if value is None:
                raise DecodeError(RejectReason.MISSING_FIELD, f"column {column!r} is empty")
            return value

        def optional(column: str | None) -> float | None:
            value = None if column is None else field(column)
            return None if value is None else self._number(value, column or "")

        return BreathRecord(
            t_s=self._time(required(m.time_column)),
            vo2_ml_min=self._number(required(m.vo2_column), m.vo2_column) * m.vo2_unit.to_ml_min,
            vco2_ml_min=(self._number(required(m.vco2_column), m.vco2_column) * m.vco2_unit.to_ml_min),
            ve_l_min=optional(m.ve_column),
            rer=optional(m.rer_column),
            hr_bpm=optional(m.hr_column),
        )

    def _number(self, value: str, column: str) -> float:
        if self.mapping.decimal == ",":
            if "." in value:
                # With a decimal comma a '.' is a thousands separator: 1.234 would be misread.
                raise DecodeError(RejectReason.BAD_NUMBER, f"{column} = {value!r} contains '.'")
            value = value.replace(",", ".")
        return parse_decimal(value, column)

    def _time(self, value: str) -> float:
        fmt = self.mapping.time_format
        if fmt in (TimeFormat.SECONDS, TimeFormat.MINUTES) and ":" in value:
            raise DecodeError(RejectReason.BAD_TIME, f"time {shorten(value)!r} is a clock time, not "
                              f"{fmt.value} (time_format = 'hh:mm:ss' or 'mm:ss'?)")
        if fmt is TimeFormat.SECONDS:
            return self._number(value, self.mapping.time_column)
        if fmt is TimeFormat.MINUTES:
            return 60.0 * self._number(value, self.mapping.time_column)
        clock = value.replace(",", ".") if self.mapping.decimal == "," else value
        pattern = _HMS if fmt is TimeFormat.HMS else _MS
        match = pattern.fullmatch(clock)
        if match is None:
            raise DecodeError(RejectReason.BAD_TIME, f"time {shorten(value)!r} is not {fmt.value}")
        parts = [float(g) for g in match.groups()]
        if fmt is TimeFormat.HMS:
            return parts[0] * 3600.0 + parts[1] * 60.0 + parts[2]
        return parts[0] * 60.0 + parts[1]


def _listed(names: list[str]) -> str:
    listed = ", ".join(repr(n) for n in names[:80] if n) + (" ..." if len(names) > 80 else "")
    return listed or "(none)"


def _write_row(mapping: CsvMapping, row: list[str]) -> bytes:
    buf = io.StringIO()
    csv.writer(buf, delimiter=mapping.delimiter, lineterminator="\r\n").writerow(row)
    return buf.getvalue().encode(mapping.encoding)


def _layout(mapping: CsvMapping) -> list[str]:
    return list(mapping.columns) if mapping.columns is not None else list(mapping.mapped_columns)


def encode_csv_header(mapping: CsvMapping) -> bytes:
    """The header line for :func:`encode_csv_row` rows (mapped columns, or ``columns``)."""
    return _write_row(mapping, _layout(mapping))


def encode_csv_row(mapping: CsvMapping, record: BreathRecord) -> bytes:
    """Write ``record`` as one CSV line in ``mapping``'s layout, units and number format.

    The inverse of :meth:`CsvBreathParser.parse` up to float rounding of the unit and time
    conversions; used by the virtual cart to emulate a vendor's live CSV output.

    Raises:
        EncodeError: A negative or non-finite time in a clock format (``hh:mm:ss``, ``mm:ss``).
    """
    m = mapping

    def num(value: float | None) -> str:
        if value is None:
            return ""
        out = repr(float(value))
        return out.replace(".", ",") if m.decimal == "," else out

    t = float(record.t_s)
    if m.time_format in (TimeFormat.HMS, TimeFormat.MS) and not 0.0 <= t < float("inf"):
        raise EncodeError(f"t_s = {t!r}: a {m.time_format.value} time must be finite and >= 0")
    if m.time_format is TimeFormat.SECONDS:
        time_text = num(t)
    elif m.time_format is TimeFormat.MINUTES:
        time_text = num(t / 60.0)
    else:
        # Integer microseconds, so carries are exact (59.9999999 s never prints as "60.0").
        minutes, micros = divmod(round(t * 1_000_000), 60_000_000)
        sec = f"{micros // 1_000_000:02d}.{micros % 1_000_000:06d}"
        sec = sec.replace(".", ",") if m.decimal == "," else sec
        if m.time_format is TimeFormat.HMS:
            hours, minutes = divmod(minutes, 60)
            time_text = f"{hours}:{minutes:02d}:{sec}"
        else:
            time_text = f"{minutes:02d}:{sec}"
    values = {
        m.time_column: time_text,
        m.vo2_column: num(record.vo2_ml_min / m.vo2_unit.to_ml_min),
        m.vco2_column: num(record.vco2_ml_min / m.vco2_unit.to_ml_min),
    }
    for column, value in (
        (m.ve_column, record.ve_l_min),
        (m.rer_column, record.rer),
        (m.hr_column, record.hr_bpm),
    ):
        if column is not None:
            values[column] = num(value)
    return _write_row(m, [values.get(c, "") for c in _layout(m)])
