"""Vendor presets on real exports (shared/data/cart-exports) and on synthetic files of the layouts.

The expected numbers were read by hand from the files (the xlsx in a spreadsheet view of its
cells, the XML's <Data> elements, the text file's lines), not from the reader under test.
"""

from __future__ import annotations

import asyncio
from pathlib import Path

import pytest
from cart_exports import EXPORTS, needs_exports
from hypothesis import given
from hypothesis import strategies as st

import bridge.cli.main as cli
from drivers.cart import BreathStream, CartConfig
from drivers.cart.inspect import inspect_file
from drivers.cart.pipeline import iter_breaths
from drivers.cart.validate import BreathValidator
from drivers.cart.vendors import VENDORS, TableParser, detect_format, line_image
from drivers.cart.vendors._table import parse_clock
from drivers.errors import DriverConfigError
from hilbo_core.types import BreathRecord

pytestmark = pytest.mark.timeout(30)

REPO = Path(__file__).resolve().parents[2]
DATA = REPO / "tests" / "data" / "cart"


# (file, format, n breaths, first (t_s, VO2, VCO2), last (t_s, VO2, VCO2), body mass kg), by hand:
# COSMED: row 4 of sheet "Daten": t 0:00:30, VO2 506.1618208, VCO2 440.9817142 mL/min; row 13:
#   0:02:00, 2707.7314704, 2212.4235569; 10 rows; "Gewicht (kg)" 71.5.
# CORTEX: first breath row 0:00:09, V'O2 0.117052380441247 L/min, V'CO2 0.120985138144411 L/min;
#   last 0:01:10, 0.486221924235746, 0.428477322470274; 13 rows; "Gewicht" "74,8kg".
# Vyntus: " 00:56" V'O2 321, V'CO2 267 mL/min; " 06:00" 2245, 1927; 7 rows; no body mass.
REAL = [
    ("cosmed_test.xlsx", "cosmed", 10, (30.0, 506.1618208, 440.9817142),
     (120.0, 2707.7314704, 2212.4235569), 71.5),
    ("cortex_test.xml", "cortex", 13, (9.0, 117.052380441247, 120.985138144411),
     (70.0, 486.221924235746, 428.477322470274), 74.8),
    ("vyntus_test.txt", "vyntus", 7, (56.0, 321.0, 267.0), (360.0, 2245.0, 1927.0), None),
]


def _read(path: Path, fmt: str) -> tuple[list[BreathRecord], TableParser, BreathValidator]:
    spec = VENDORS[fmt]
    parser, validator = TableParser(spec), BreathValidator()
    records = list(iter_breaths(line_image(spec, path).splitlines(), parser, validator))
    return records, parser, validator


def _triple(rec: BreathRecord) -> tuple[float, float, float]:
    return (rec.t_s, rec.vo2_ml_min, rec.vco2_ml_min)


@needs_exports
@pytest.mark.parametrize(("name", "fmt", "n", "first", "last", "mass"), REAL)
def test_real_exports_read_by_hand_values(name: str, fmt: str, n: int, first: tuple[float, ...],
                                          last: tuple[float, ...], mass: float | None) -> None:
    assert EXPORTS is not None
    records, parser, validator = _read(EXPORTS / name, fmt)
    assert len(records) == n
    assert validator.rejected == 0
    assert _triple(records[0]) == pytest.approx(first, rel=1e-12)
    assert _triple(records[-1]) == pytest.approx(last, rel=1e-12)
    assert parser.metadata.get("body_mass_kg") == mass
    assert [r.t_s for r in records] == sorted(r.t_s for r in records)
    assert detect_format(EXPORTS / name) == fmt


@needs_exports
def test_cortex_other_fields_and_cosmed_zero_hr_is_not_reported() -> None:
    assert EXPORTS is not None
    cortex, _, _ = _read(EXPORTS / "cortex_test.xml", "cortex")
    # Row 0:00:09: V'E 6.54588 L/min, RER 1.03359827188768, HF 53.
    first = (cortex[0].ve_l_min, cortex[0].rer, cortex[0].hr_bpm)
    assert first == pytest.approx((6.54588, 1.03359827188768, 53))
    cosmed, _, _ = _read(EXPORTS / "cosmed_test.xlsx", "cosmed")
    # HF is 0 in every row (no belt): read as not reported, not rejected as hr_range.
    assert all(r.hr_bpm is None for r in cosmed)
    assert (cosmed[0].ve_l_min, cosmed[0].rer) == (19.4, 0.87)


@needs_exports
@pytest.mark.parametrize(("name", "fmt", "n", "first", "last", "mass"), REAL)
def test_replay_stream_yields_every_breath(name: str, fmt: str, n: int, first: tuple[float, ...],
                                           last: tuple[float, ...], mass: float | None) -> None:
    assert EXPORTS is not None
    config = CartConfig.from_dict({"transport": "replay", "format": fmt,
                                   "options": {"path": str(EXPORTS / name), "speed": "max"}})

    async def run() -> tuple[list[BreathRecord], dict[str, int]]:
        async with BreathStream.from_config(config) as stream:
            return [rec async for rec in stream], dict(stream.counters)

    records, counters = asyncio.run(run())
    assert len(records) == n and counters == {}
    assert _triple(records[0]) == pytest.approx(first) and _triple(records[-1]) == pytest.approx(last)


def test_cosmed_csv_synthetic_decimal_comma_semicolons() -> None:
    # tests/data/cart/cosmed_k5.csv: the Omnia table layout as ';'-separated text, decimal commas.
    records, parser, validator = _read(DATA / "cosmed_k5.csv", "cosmed-csv")
    assert validator.rejected == 0
    assert [_triple(r) for r in records] == [
        (3.0, 301.5, 245.25), (7.0, 352.0, 290.4), (11.0, 410.75, 340.0), (62.5, 1050.0, 890.5)]
    assert records[0].hr_bpm is None and records[1].hr_bpm == 88.0  # 0 = no belt
    assert parser.metadata == {"body_mass_kg": 72.5}
    assert parser.delimiter == ";"
    assert detect_format(DATA / "cosmed_k5.csv") == "cosmed-csv"


def test_parvo_synthetic_minutes_litres_and_events_block() -> None:
    records, parser, validator = _read(DATA / "parvo_trueone.csv", "parvo")
    # The Events block after the table is not read as breaths, and not lost silently either:
    # its marker and its note are counted under their own reason.
    assert validator.counters == {"event": 2}
    flat = [v for r in records for v in _triple(r)]
    assert flat == pytest.approx([15.0, 312.0, 265.0, 30.0, 355.0, 298.0, 45.0, 1105.0, 962.0,
                                  60.0, 1250.0, 1100.0])
    assert parser.mapping["vo2_ml_min"].unit == "L/min"
    assert parser.metadata == {"body_mass_kg": 64.0}
    assert detect_format(DATA / "parvo_trueone.csv") == "parvo"


def test_text_preset_reads_a_live_line_stream_over_tcp() -> None:
    """The same parser on lines arriving in arbitrary chunks over a live link (TCP)."""
    payload = (DATA / "parvo_trueone.csv").read_bytes()

    async def run() -> list[BreathRecord]:
        async def serve(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
            for i in range(0, len(payload), 7):  # 7-byte chunks cut lines anywhere
                writer.write(payload[i:i + 7])
                await writer.drain()
            writer.close()

        server = await asyncio.start_server(serve, "127.0.0.1", 0)
        port = server.sockets[0].getsockname()[1]
        config = CartConfig.from_dict({"transport": "tcp", "format": "parvo",
                                       "options": {"host": "127.0.0.1", "port": port,
                                                   "backoff": {"max_attempts": 1, "initial_s": 0.01}}})
        out: list[BreathRecord] = []
        async with server, BreathStream.from_config(config) as stream:
            while len(out) < 4:
                out.append(await asyncio.wait_for(anext(stream), 5.0))
        return out

    records = asyncio.run(run())
    assert [r.t_s for r in records] == pytest.approx([15.0, 30.0, 45.0, 60.0])


def test_file_presets_refuse_a_live_transport() -> None:
    with pytest.raises(DriverConfigError,
                       match=r"format = 'cosmed' is a file export.*needs transport = 'replay'"):
        CartConfig.from_dict({"transport": "tcp", "format": "cosmed",
                              "options": {"host": "127.0.0.1", "port": 5}})


def test_detect_unknown_and_hilbo_line(tmp_path: Path) -> None:
    other = tmp_path / "notes.txt"
    other.write_text("time,oxygen\n1,2\n")
    assert detect_format(other) is None
    with pytest.raises(DriverConfigError, match=r"unknown cart format.*\[cart.csv\] column map"):
        inspect_file(other)
    line = tmp_path / "rec.hbr"
    line.write_bytes(b"# recorded\n$HBR,0,3.0,250.0,200.0,,,*1C76\n")
    assert detect_format(line) == "hilbo-line"
    report = inspect_file(line)
    assert len(report.records) == 1 and report.format == "hilbo-line"


def test_preset_without_header_fails_loudly(tmp_path: Path) -> None:
    path = tmp_path / "x.txt"
    path.write_text("".join(f"line {i}\n" for i in range(400)))
    with pytest.raises(DriverConfigError, match=r"vyntus: no header row .* first 300 lines"):
        _read(path, "vyntus")


def test_units_per_kg_under_vo2_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "kg.txt"
    path.write_text("Tid\tV'O2\tV'CO2\nmin\tmL/min/kg\tmL/min\n01:00\t12\t300\n")
    with pytest.raises(DriverConfigError, match=r"column \"V'O2\" is in 'mL/min/kg'"):
        _read(path, "vyntus")


def test_bad_rows_are_counted_not_raised(tmp_path: Path) -> None:
    path = tmp_path / "bad.txt"
    path.write_text("Tid\tV'O2\tV'CO2\nmin\tmL/min\tmL/min\n00:10\t300\t250\n00:1x\t300\t250\n"
                    "00:20\t1.234,5\t250\n00:30\t\t250\n00:40\t310,5\t260\n")
    records, _, validator = _read(path, "vyntus")
    assert [r.t_s for r in records] == [10.0, 40.0]
    assert records[1].vo2_ml_min == 310.5  # decimal comma
    assert dict(validator.counters) == {"bad_time": 1, "bad_number": 1, "missing_field": 1}


@pytest.mark.parametrize(("text", "seconds"), [
    ("0:00:09", 9.0), ("1:02:03.5", 3723.5), ("00:56", 56.0), ("75:23,5", 4523.5), ("12", None),
    ("0:61:00", None), ("1:00:60", None),
])
def test_parse_clock(text: str, seconds: float | None) -> None:
    assert parse_clock(text) == seconds


def test_inspect_renders_mapping_counts_and_toml() -> None:
    report = inspect_file(DATA / "parvo_trueone.csv")
    text = report.render()
    assert "format    parvo (Parvo Medics TrueOne 2400 CSV export)" in text
    assert "vo2_ml_min   <- 'VO2' [L/min]" in text
    assert "breaths   4 read, 2 rejected (event 2)" in text  # the Events block, counted
    assert 'format = "parvo"' in text and 'transport = "replay"' in text


@given(st.integers(min_value=0, max_value=100 * 3600 * 1000 - 1))
def test_parse_clock_round_trip(ms: int) -> None:
    minutes, rest = divmod(ms, 60_000)
    hours, minutes = divmod(minutes, 60)
    seconds = f"{rest // 1000:02d}.{rest % 1000:03d}"
    assert parse_clock(f"{hours}:{minutes:02d}:{seconds}") == pytest.approx(ms / 1000.0, abs=1e-9)
    assert parse_clock(f"{hours * 60 + minutes}:{seconds.replace('.', ',')}") == pytest.approx(ms / 1000.0,
                                                                                                abs=1e-9)


@given(st.floats(min_value=100.0, max_value=8000.0), st.floats(min_value=0.6, max_value=1.5),
       st.booleans(), st.booleans())
def test_decimal_mark_and_unit_do_not_change_the_breath(vo2: float, rer: float, comma: bool,
                                                        litres: bool) -> None:
    vco2 = vo2 * rer
    unit, scale = ("L/min", 1000.0) if litres else ("mL/min", 1.0)

    def num(v: float) -> str:
        text = repr(v / scale)
        return text.replace(".", ",") if comma else text

    lines = [b"Tid\tV'O2\tV'CO2", f"min\t{unit}\t{unit}".encode(), f"01:00\t{num(vo2)}\t{num(vco2)}".encode()]
    if "e" in num(vo2) or "e" in num(vco2):
        return  # exponent notation is not what carts write
    records = list(iter_breaths(lines, TableParser(VENDORS["vyntus"]), BreathValidator()))
    assert len(records) == 1
    assert (records[0].vo2_ml_min, records[0].vco2_ml_min) == pytest.approx((vo2, vco2), rel=1e-12)


def test_cli_cart_inspect(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    assert cli.main(["cart", "inspect", str(DATA / "cosmed_k5.csv")]) == 0
    out = capsys.readouterr().out
    assert "format    cosmed-csv (COSMED K5/Quark CSV export)" in out
    assert "breaths   4 read, 0 rejected" in out and 'format = "cosmed-csv"' in out
    assert "metadata  body_mass_kg = 72.5" in out
    other = tmp_path / "x.dat"
    other.write_text("hello\n")
    assert cli.main(["cart", "inspect", str(other)]) == 1
    err = capsys.readouterr().err
    assert "unknown cart format" in err and "Traceback" not in err
    assert cli.main(["cart", "inspect", str(tmp_path / "missing.csv")]) == 1
    assert "cannot read" in capsys.readouterr().err
