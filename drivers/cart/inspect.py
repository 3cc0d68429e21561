"""What a cart file holds, as the session would read it: ``hilbo cart inspect`` and ``config check``.

:func:`inspect_file` reads a whole export or recording with a format (detected, or given) through
the same parser and validator as a session, and reports which columns it maps to which fields in
which units, the metadata found, how many breaths it accepts and rejects (by reason, with an
example of each), the first and last breaths, and the ``[cart]`` TOML table that replays it.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field
from os import PathLike, fspath
from typing import Any

from drivers.cart._numbers import shorten
from drivers.cart.csvmap import CsvBreathParser, CsvMapping
from drivers.cart.framing import DEFAULT_MAX_LINE_BYTES, LineFramer
from drivers.cart.line import HbrLineParser
from drivers.cart.pipeline import BreathParser, describe_record
from drivers.cart.stream import CartConfig, CartFormat
from drivers.cart.validate import BreathValidator, PhysioLimits
from drivers.cart.vendors import TableParser, detect_format, line_image
from drivers.errors import DecodeError, DriverConfigError
from drivers.files import MAX_CART_FILE_BYTES, read_regular_file
from hilbo_core.types import BreathRecord

__all__ = ["FileReport", "inspect_config", "inspect_file"]

_N_EXAMPLES = 3


@dataclass
class FileReport:
    """What :func:`inspect_file` found.

    Attributes:
        path: The file.
        format: The format it was read as.
        title: Human-readable name of the format.
        columns: The header row (vendor presets and csv), else empty.
        mapping: Field -> (column name, unit as written) for the mapped columns.
        metadata: Recognised preamble values (``body_mass_kg``).
        records: Every accepted breath, in file order.
        rejects: Rejected lines/records by reason.
        reject_examples: Per reason, up to 3 examples (the error text or the record).
    """

    path: str
    format: str
    title: str
    columns: list[str] = field(default_factory=list)
    mapping: dict[str, tuple[str, str]] = field(default_factory=dict)
    metadata: dict[str, Any] = field(default_factory=dict)
    records: list[BreathRecord] = field(default_factory=list)
    rejects: Counter[str] = field(default_factory=Counter)
    reject_examples: dict[str, list[str]] = field(default_factory=dict)

    @property
    def n_rejected(self) -> int:
        """Rejected lines and records in total."""
        return self.rejects.total()

    def toml(self) -> str:
        """The ``[cart]`` table that replays this file in a session."""
        lines = ["[cart]", 'transport = "replay"', f'format = "{self.format}"', "[cart.options]",
                 f"path = {_toml_str(self.path)}", 'speed = 1.0            # or "max"']
        if self.format == CartFormat.CSV.value:
            lines.append("# and your [cart.csv] column map")
        return "\n".join(lines)

    def render(self, n: int = 3) -> str:
        """Plain-text report: format, mapping, counts, first and last ``n`` breaths, the table."""
        out = [f"file      {self.path}", f"format    {self.format} ({self.title})"]
        if self.columns:
            out.append(f"columns   {len(self.columns)}: {', '.join(c for c in self.columns if c)}")
        for name, (column, unit) in self.mapping.items():
            out.append(f"  {name:12s} <- {column!r}" + (f" [{unit}]" if unit else ""))
        if self.metadata:
            out.append("metadata  " + ", ".join(f"{k} = {v}" for k, v in self.metadata.items()))
        by_reason = ", ".join(f"{k} {v}" for k, v in self.rejects.most_common())
        out.append(f"breaths   {len(self.records)} read, {self.n_rejected} rejected"
                   + (f" ({by_reason})" if by_reason else ""))
        for reason, examples in self.reject_examples.items():
            for example in examples:
                out.append(f"  reject {reason}: {example}")
        if self.records:
            t0 = self.records[0].t_s
            out.append(f"time      {t0:g} s to {self.records[-1].t_s:g} s "
                       f"({(self.records[-1].t_s - t0) / 60:.1f} min)")
            shown = self.records if len(self.records) <= 2 * n else [*self.records[:n], None,
                                                                     *self.records[-n:]]
            for rec in shown:
                out.append("  ..." if rec is None else f"  {describe_record(rec)}")
        out.append("")
        out.append(self.toml())
        return "\n".join(out)


def _toml_str(text: str) -> str:
    return '"' + text.replace("\\", "\\\\").replace('"', '\\"') + '"'


def _read(report: FileReport, data: bytes, parser: BreathParser, validator: BreathValidator,
          max_line_bytes: int) -> None:
    framer = LineFramer(max_line_bytes)
    lines = framer.feed(data)
    tail = framer.flush()
    if tail is not None:
        lines.append(tail)
    for line in lines:
        try:
            parsed = parser.parse(line)
        except DecodeError as err:
            report.rejects[str(err.reason)] += 1
            _example(report, str(err.reason), f"{err} in line {shorten(line)!r}")
            continue
        if parsed is None:
            continue
        before = Counter(validator.counters)
        record = validator.check(parsed.record, parsed.seq)
        if record is not None:
            report.records.append(record)
            continue
        reason = next((k for k, v in validator.counters.items() if v != before.get(k, 0)), "rejected")
        report.rejects[reason] += 1
        _example(report, reason, describe_record(parsed.record))
    report.rejects.update(framer.counters)


def _example(report: FileReport, reason: str, text: str) -> None:
    examples = report.reject_examples.setdefault(reason, [])
    if len(examples) < _N_EXAMPLES:
        examples.append(text)


def inspect_file(
    path: str | PathLike[str],
    fmt: str | CartFormat | None = None,
    *,
    csv: CsvMapping | None = None,
    limits: PhysioLimits | None = None,
    max_line_bytes: int = DEFAULT_MAX_LINE_BYTES,
) -> FileReport:
    """Read ``path`` as a session would and report what it holds.

    Args:
        path: An export or recording.
        fmt: Its format; None detects it (:func:`drivers.cart.vendors.detect_format`).
        csv: The column map, for ``fmt = "csv"``.
        limits: The validator's limits (default ones if None).
        max_line_bytes: Longest line kept.

    Raises:
        OSError: The file cannot be read.
        DriverConfigError: The format is unknown (not detected), ``csv`` is missing for
            ``"csv"``, the file is not a regular file or too large, or it does not fit the
            format (no header; a mapped column missing; a damaged spreadsheet).
    """
    path_s = fspath(path)
    if fmt is None:
        detected = detect_format(path_s)
        if detected is None:
            raise DriverConfigError(
                f"{path_s}: unknown cart format: not hilbo-line, and no header of a preset "
                f"({', '.join(f.value for f in CartFormat if f.vendor is not None)}) found; for another "
                "CSV give [cart] format = \"csv\" and a [cart.csv] column map (drivers/cart/FORMAT.md)"
            )
        fmt = detected
    cart_format = CartFormat(fmt) if not isinstance(fmt, CartFormat) else fmt
    vendor = cart_format.vendor
    validator = BreathValidator(limits)
    parser: BreathParser
    if vendor is not None:
        parser = TableParser(vendor)
        title = vendor.title
        data = line_image(vendor, path_s)
    else:
        data = read_regular_file(path_s, max_bytes=MAX_CART_FILE_BYTES, what="a cart recording or export")
        if cart_format is CartFormat.CSV:
            if csv is None:
                raise DriverConfigError("format 'csv' needs a [cart.csv] column map")
            parser, title = CsvBreathParser(csv), "CSV with a [cart.csv] column map"
        else:
            parser, title = HbrLineParser(), "hilbo-line (drivers/cart/FORMAT.md)"
    report = FileReport(path=path_s, format=cart_format.value, title=title)
    _read(report, data, parser, validator, max_line_bytes)
    if isinstance(parser, TableParser):
        if not parser.has_header:
            raise DriverConfigError(f"{path_s}: no {vendor.title if vendor else ''} header row found")
        # The table's own columns: COSMED writes its subject block in the columns before it.
        first = min(c.index for c in parser.mapping.values())
        report.columns = list(parser.columns or [])[first:]
        report.mapping = {f: (c.name, c.unit) for f, c in parser.mapping.items()}
        report.metadata = dict(parser.metadata)
    elif isinstance(parser, CsvBreathParser) and csv is not None:
        m = csv
        report.mapping = {"t_s": (m.time_column, m.time_format.value),
                          "vo2_ml_min": (m.vo2_column, m.vo2_unit.value),
                          "vco2_ml_min": (m.vco2_column, m.vco2_unit.value)}
        for name, column in (("ve_l_min", m.ve_column), ("rer", m.rer_column), ("hr_bpm", m.hr_column)):
            if column is not None:
                report.mapping[name] = (column, "")
    return report


def inspect_config(config: CartConfig) -> FileReport | None:
    """:func:`inspect_file` of a replay config's file with its format, map and limits.

    Returns:
        The report, or None when the transport is not ``"replay"`` (nothing to open).

    Raises:
        OSError, DriverConfigError: As :func:`inspect_file`.
    """
    if config.transport != "replay":
        return None
    opts = config.options
    return inspect_file(opts.path, config.format, csv=config.csv, limits=config.limits,
                        max_line_bytes=opts.max_line_bytes)
