"""Bad cart files: a clear error naming the file (and the row), never a traceback, hang or unbounded read.

Damaged spreadsheets (an xlsx whose sheet XML or deflate stream is broken: read-only openpyxl
only meets the damage while the rows are iterated), a CORTEX cell index of 4e9, a device, a FIFO
or a directory given as the file; and the rows a vendor table reader drops are counted with a
reason (Parvo's ``Events`` block, a row with text but no mapped value), while later breaths are
still read.
"""

from __future__ import annotations

import io
import os
import re
import zipfile
from pathlib import Path

import openpyxl
import pytest
from file_inputs import NOT_REGULAR, not_regular_file
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import bridge.cli.main as cli
from drivers.cart.inspect import inspect_file
from drivers.cart.pipeline import process_line, read_breath_file
from drivers.cart.replay import ReplayOptions, ReplayTransport
from drivers.cart.validate import BreathValidator
from drivers.cart.vendors import VENDORS, TableParser, detect_format, line_image
from drivers.cart.vendors.cortex import load_spreadsheet_xml
from drivers.cart.vendors.cosmed import load_xlsx
from drivers.errors import DecodeError, DriverConfigError

pytestmark = pytest.mark.timeout(60)

DATA = Path(__file__).resolve().parents[1] / "data" / "cart"
SHEET = "xl/worksheets/sheet1.xml"


def cosmed_workbook(path: Path, rows: int = 12) -> Path:
    """A small COSMED-layout xlsx (subject block beside the table, units row, then breaths)."""
    wb = openpyxl.Workbook()
    ws = wb.active
    ws.title = "Daten"
    ws.append(["ID1", "", "", "t", "VO2", "VCO2", "R", "HR"])
    ws.append(["Gewicht (kg)", 71.5, "", "s", "mL/min", "mL/min", "---", "bpm"])
    for k in range(rows):
        ws.append(["", "", "", f"0:00:{10 + 3 * k:02d}", 500.0 + k, 420.0 + k, 0.84, 90])
    wb.save(path)
    return path


def rewrite_member(src: Path, dst: Path, name: str, body: bytes) -> Path:
    """A copy of the zip ``src`` with member ``name`` replaced by ``body``."""
    with zipfile.ZipFile(src) as zin, zipfile.ZipFile(dst, "w", zipfile.ZIP_DEFLATED) as zout:
        for info in zin.infolist():
            zout.writestr(info.filename, body if info.filename == name else zin.read(info))
    return dst


def damaged_deflate(src: Path, dst: Path, name: str) -> Path:
    """A copy of ``src`` whose member ``name`` has bytes of its deflate stream overwritten."""
    data = bytearray(src.read_bytes())
    with zipfile.ZipFile(src) as z:
        info = z.getinfo(name)
    # Local header: 30 bytes + name + extra; the compressed data follow.
    n_name, n_extra = int.from_bytes(data[info.header_offset + 26:info.header_offset + 28], "little"), \
        int.from_bytes(data[info.header_offset + 28:info.header_offset + 30], "little")
    start = info.header_offset + 30 + n_name + n_extra
    middle = start + info.compress_size // 2
    data[middle:middle + 16] = b"\xff" * 16
    dst.write_bytes(bytes(data))
    return dst


def one_line_error(err: str, prefix: str, *needles: str) -> None:
    assert "Traceback" not in err
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith(prefix), lines[0]
    for needle in needles:
        assert needle in lines[0], (needle, lines[0])


# --------------------------------------------------------------------------------- xlsx
@pytest.fixture
def workbook(tmp_path: Path) -> Path:
    return cosmed_workbook(tmp_path / "good.xlsx")


def test_the_synthetic_workbook_reads(workbook: Path) -> None:
    report = inspect_file(workbook)
    assert report.format == "cosmed" and len(report.records) == 12 and report.n_rejected == 0


def test_a_sheet_cut_in_half_is_an_error_naming_the_file_and_row(workbook: Path, tmp_path: Path) -> None:
    with zipfile.ZipFile(workbook) as z:
        sheet = z.read(SHEET)
    bad = rewrite_member(workbook, tmp_path / "cut.xlsx", SHEET, sheet[: len(sheet) * 2 // 3])
    with pytest.raises(DriverConfigError, match=r"cut\.xlsx: not a readable xlsx workbook \(sheet "
                                                r"'Daten', row \d+: ParseError"):
        load_xlsx(bad)
    with pytest.raises(DriverConfigError, match="not a readable xlsx workbook"):
        inspect_file(bad)  # detection says the same, not "unknown format"


def test_a_damaged_deflate_stream_is_an_error(workbook: Path, tmp_path: Path) -> None:
    bad = damaged_deflate(workbook, tmp_path / "deflate.xlsx", SHEET)
    with pytest.raises(DriverConfigError, match=r"deflate\.xlsx: not a readable xlsx workbook"):
        inspect_file(bad, "cosmed")


def test_cart_inspect_and_config_check_exit_1_with_one_line(
    workbook: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    with zipfile.ZipFile(workbook) as z:
        sheet = z.read(SHEET)
    bad = rewrite_member(workbook, tmp_path / "cut.xlsx", SHEET, sheet[: len(sheet) // 2])
    assert cli.main(["cart", "inspect", str(bad)]) == 1
    err = capsys.readouterr().err
    one_line_error(err, "hilbo cart inspect: error: ", "cut.xlsx", "not a readable xlsx workbook")
    config = tmp_path / "c.toml"
    config.write_text(_replay_config(tmp_path, bad, "cosmed"))
    assert cli.main(["config", "check", str(config), "--samples", "0"]) == 1
    err = capsys.readouterr().err
    one_line_error(err, "hilbo config check: ", "cut.xlsx", "not a readable xlsx workbook")


def test_a_zip_that_unpacks_to_more_than_the_bound_is_refused_unread(
    workbook: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import drivers.cart.vendors.cosmed as cosmed

    monkeypatch.setattr(cosmed, "MAX_XLSX_UNPACKED_BYTES", 1000)
    with pytest.raises(DriverConfigError, match=r"unpacks to .* more than the 1,000 bytes"):
        load_xlsx(workbook)


def test_a_sheet_with_a_row_number_of_a_billion_is_bounded(workbook: Path, tmp_path: Path,
                                                           monkeypatch: pytest.MonkeyPatch) -> None:
    import drivers.cart.vendors._table as table

    with zipfile.ZipFile(workbook) as z:
        sheet = z.read(SHEET)
    # The last row claims to be row 10^9 (and the sheet's dimension agrees): read-only openpyxl
    # yields every empty row before it, 10^9 rows of 8 cells.
    damaged = (sheet.replace(b'<row r="14">', b'<row r="1000000000">').replace(b'14"', b'1000000000"')
               .replace(b'ref="A1:H14"', b'ref="A1:H1000000000"'))
    assert damaged.count(b"1000000000") >= 3
    bad = rewrite_member(workbook, tmp_path / "far.xlsx", SHEET, damaged)
    monkeypatch.setattr(table, "MAX_SHEET_CELLS", 20_000)  # the bound's logic, at a test's size
    with pytest.raises(DriverConfigError, match=r"far\.xlsx: more than 20,000 cells"):
        load_xlsx(bad)


# --------------------------------------------------------------------------------- CORTEX XML
_SS = "urn:schemas-microsoft-com:office:spreadsheet"


def cortex_xml(cells_row: str) -> str:
    return (f'<?xml version="1.0"?><Workbook xmlns="{_SS}" xmlns:ss="{_SS}"><Worksheet ss:Name="M">'
            "<Table><Row><Cell><Data ss:Type=\"String\">t</Data></Cell><Cell><Data ss:Type=\"String\">"
            "V'O2</Data></Cell><Cell><Data ss:Type=\"String\">V'CO2</Data></Cell></Row>"
            f"<Row>{cells_row}</Row></Table></Worksheet></Workbook>")


def test_a_cortex_cell_index_of_4e9_is_refused_at_once(tmp_path: Path) -> None:
    bad = tmp_path / "index.xml"
    bad.write_text(cortex_xml('<Cell ss:Index="4000000000"><Data ss:Type="Number">1</Data></Cell>'))
    with pytest.raises(DriverConfigError, match=r"index\.xml: row 2: a cell at column 4000000000; "
                                                r"expected .* at most 16384"):
        load_spreadsheet_xml(bad)
    with pytest.raises(DriverConfigError, match="column 4000000000"):
        inspect_file(bad)


def test_a_cortex_index_within_bounds_still_places_the_cell(tmp_path: Path) -> None:
    good = tmp_path / "ok.xml"
    good.write_text(cortex_xml('<Cell><Data ss:Type="String">0:00:09</Data></Cell>'
                               '<Cell ss:Index="3"><Data ss:Type="Number">0.12</Data></Cell>'))
    assert load_spreadsheet_xml(good).splitlines()[1] == b"0:00:09\t\t0.12"


def test_malformed_xml_names_the_file(tmp_path: Path) -> None:
    bad = tmp_path / "broken.xml"
    bad.write_text(cortex_xml("<Cell>")[:-40])
    with pytest.raises(DriverConfigError, match=r"broken\.xml: not a readable XML spreadsheet .*ParseError"):
        load_spreadsheet_xml(bad)


# --------------------------------------------------------------------------------- not regular files
def _replay_config(tmp_path: Path, path: Path, fmt: str) -> str:
    from bridge.sim.virtual import VirtualSimConfig, sim_config_text

    text = sim_config_text(VirtualSimConfig(minutes=30.0, seed=1), tmp_path)
    head, _, rest = text.partition("[cart]")
    tail = rest[rest.index("\n[", 1):] if "\n[" in rest[1:] else ""
    while tail.lstrip().startswith("[cart."):  # the old cart's sub-tables go too
        tail = tail[tail.index("\n[", 1):] if "\n[" in tail[1:] else ""
    return (f'{head}[cart]\ntransport = "replay"\nformat = "{fmt}"\n[cart.options]\n'
            f'path = "{path}"\nspeed = "max"\n{tail}')


@pytest.fixture(params=NOT_REGULAR)
def not_a_file(request: pytest.FixtureRequest, tmp_path: Path) -> tuple[Path, str]:
    return not_regular_file(request.param, tmp_path)


@pytest.mark.parametrize("fmt", [None, "hilbo-line", "cosmed", "cortex", "vyntus"])
def test_inspect_refuses_what_is_not_a_regular_file(not_a_file: tuple[Path, str], fmt: str | None) -> None:
    path, kind = not_a_file
    with pytest.raises(DriverConfigError, match=re.escape(f"{path} is {kind}")) as caught:
        inspect_file(path, fmt)
    assert "not a regular file" in str(caught.value)


def test_every_reader_refuses_a_fifo(tmp_path: Path) -> None:
    import asyncio

    from drivers.cart.line import HbrLineParser

    pipe = tmp_path / "pipe"
    os.mkfifo(pipe)
    for read in (detect_format, lambda p: line_image(VENDORS["vyntus"], p),
                 lambda p: read_breath_file(p, HbrLineParser())):
        with pytest.raises(DriverConfigError, match="is a FIFO"):
            read(pipe)
    transport = ReplayTransport(ReplayOptions(path=str(pipe), speed="max"))
    with pytest.raises(DriverConfigError, match="is a FIFO"):
        asyncio.run(transport.open())


def test_config_check_refuses_a_replay_file_that_is_not_regular(tmp_path: Path, not_a_file: tuple[Path, str],
                                                          capsys: pytest.CaptureFixture[str]) -> None:
    path, kind = not_a_file
    config = tmp_path / "c.toml"
    config.write_text(_replay_config(tmp_path, path, "vyntus"))
    assert cli.main(["config", "check", str(config), "--samples", "0"]) == 1
    _, err = capsys.readouterr()
    one_line_error(err, "hilbo config check: ", str(path), kind)


def test_a_file_larger_than_the_bound_is_refused_before_reading(tmp_path: Path) -> None:
    from drivers.files import read_regular_file

    big = tmp_path / "big.txt"
    big.write_bytes(b"x" * 5000)
    with pytest.raises(DriverConfigError, match=r"big\.txt: 5,000 bytes, more than the 4,096 bytes"):
        read_regular_file(big, max_bytes=4096, what="a test file")


# --------------------------------------------------------------------------------- dropped rows counted
PARVO_HEAD = [b"Parvo Medics TrueOne 2400", b"TIME,VO2,VCO2,RER,VE,HR", b",STPD,STPD,,BTPS,",
              b"min,L/min,L/min,,L/min,BPM", b"-" * 40]


def feed(parser: TableParser, lines: list[bytes]) -> tuple[list[float], BreathValidator]:
    validator = BreathValidator()
    times = []
    for line in lines:
        record = process_line(line, parser, validator)
        if record is not None:
            times.append(record.t_s)
    return times, validator


def test_a_parvo_events_row_does_not_end_a_live_stream() -> None:
    rows = [f"{0.25 * (k + 1):.2f},1.1,0.95,0.86,30.0,110".encode() for k in range(10)]
    times, validator = feed(TableParser(VENDORS["parvo"]),
                            [*PARVO_HEAD, rows[0], b"Events", b"0.30,Start exercise", *rows[1:]])
    assert times == pytest.approx([15.0 * (k + 1) for k in range(10)])  # all 10 valid rows
    assert validator.counters == {"event": 2}  # the marker and the note, counted with their reason


def test_a_row_with_text_but_no_mapped_value_is_counted() -> None:
    # The cart switched its separator from ';' to ',': the row is one cell, the mapped ones empty.
    head = [b"ID1;;t;VO2;VCO2;R;HR", b"Nachname;X;s;mL/min;mL/min;---;bpm"]
    lines = [*head, b";;00:00:03;301,5;245,25;0,81;80", b"", b";;;;;;",
             b"00:00:07,352.0,290.4,0.83,88", b"Vorname;Max;;;;;", b";;00:00:11;410,75;340,0;0,83;91"]
    parser = TableParser(VENDORS["cosmed-csv"])
    times, validator = feed(parser, lines)
    assert times == [3.0, 11.0]
    # The blank lines and the subject block beside a blank table row carry nothing: not counted.
    assert validator.counters == {"missing_field": 1}
    with pytest.raises(DecodeError, match="another field separator"):
        parser.parse(b"00:00:15,352.0,290.4,0.83,88")


# --------------------------------------------------------------------------------- properties
_PRESET_LINES = {
    "parvo": PARVO_HEAD,
    "cosmed-csv": [b"ID1;;t;VO2;VCO2;R;HR", b"Nachname;X;s;mL/min;mL/min;---;bpm"],
    "vyntus": [b"ID-nummer: 1", b"", b"Tid\tV'O2\tV'CO2\tRER\tHF", b"min\tmL/min\tmL/min\t\t/min"],
}


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(fmt=st.sampled_from(sorted(_PRESET_LINES)),
       lines=st.lists(st.binary(max_size=80) | st.text(alphabet=";,\t0123456789.:-Events ", max_size=60)
                      .map(str.encode), max_size=30))
def test_a_vendor_table_only_returns_breaths_or_counted_rejects(fmt: str, lines: list[bytes]) -> None:
    parser = TableParser(VENDORS[fmt])
    validator = BreathValidator()
    accepted = 0
    for line in [*_PRESET_LINES[fmt], *lines]:
        try:
            if process_line(line, parser, validator) is not None:
                accepted += 1
        except DriverConfigError:  # a unit the preset refuses (mL/min/kg): the config's error
            return
    # Every line is a breath, a counted reject, or carries nothing (blank, units, repeated header).
    assert accepted + validator.rejected <= len(lines)


@settings(max_examples=100, deadline=None, suppress_health_check=[HealthCheck.too_slow,
                                                                   HealthCheck.function_scoped_fixture])
@given(cut=st.integers(min_value=0, max_value=10_000), junk=st.binary(max_size=64))
def test_the_loaders_raise_only_their_error(tmp_path: Path, cut: int, junk: bytes) -> None:
    good = cosmed_workbook(tmp_path / "w.xlsx", rows=3)
    with zipfile.ZipFile(good) as z:
        sheet = z.read(SHEET)
    at = cut % (len(sheet) + 1)
    bad = rewrite_member(good, tmp_path / "m.xlsx", SHEET, sheet[:at] + junk + sheet[at + len(junk):])
    xml = tmp_path / "m.xml"
    text = cortex_xml('<Cell><Data ss:Type="String">0:00:09</Data></Cell>').encode()
    xml.write_bytes(text[: cut % (len(text) + 1)] + junk + text[cut % (len(text) + 1):])
    for loader, path in ((load_xlsx, bad), (load_spreadsheet_xml, xml)):
        try:
            image = loader(path)
        except DriverConfigError as err:
            assert str(path) in str(err)
        else:
            assert isinstance(image, bytes)


def test_a_zip_in_memory_is_not_a_path() -> None:
    # load_xlsx takes paths only: what it opens is checked as a regular file first.
    with pytest.raises(TypeError):
        load_xlsx(io.BytesIO(b"PK"))  # type: ignore[arg-type]
