"""Column-mapped CSV: mappings from config, vendor-style exports, streaming and whole files."""

from __future__ import annotations

from pathlib import Path

import pytest
from hypothesis import given
from hypothesis import strategies as st

from drivers.cart.csvmap import (
    CsvBreathParser,
    CsvMapping,
    GasUnit,
    TimeFormat,
    encode_csv_header,
    encode_csv_row,
)
from drivers.cart.errors import EncodeError
from drivers.cart.line import ParsedBreath
from drivers.cart.pipeline import read_breath_file
from drivers.cart.reasons import RejectReason
from drivers.cart.validate import BreathValidator
from drivers.errors import DecodeError, DriverConfigError
from hilbo_core.types import BreathRecord

pytestmark = pytest.mark.timeout(30)

# A COSMED-style export: patient preamble of variable length, header, units row, clock times.
COSMED = """\
ID1,Subject 07,,
Test date,01/05/2024,,
Protocol,walking exo,,

t,Rf,VE,VO2,VCO2,R,HR
hh:mm:ss,1/min,L/min,mL/min,mL/min,---,bpm
0:00:03,14.2,11.5,402.1,331.0,0.82,88
0:00:07,15.0,12.8,455.6,372.9,0.82,
0:01:05.5,16.3,13.9,510.0,433.5,0.85,91
"""

COSMED_MAPPING = {
    "time_column": "t",
    "time_format": "hh:mm:ss",
    "vo2_column": "VO2",
    "vco2_column": "VCO2",
    "ve_column": "VE",
    "rer_column": "R",
    "hr_column": "HR",
    "skip_rows": 1,
}

# A Parvo-style export in a European locale: ';' between fields, decimal comma, l/min, minutes.
PARVO = """\
TIME;VO2;VCO2;HR\r
min;STPD;STPD;bpm\r
0,05;0,402;0,331;88\r
0,125;0,4556;0,3729;90\r
"""

PARVO_MAPPING = {
    "time_column": "TIME",
    "time_format": "min",
    "vo2_column": "VO2",
    "vco2_column": "VCO2",
    "hr_column": "HR",
    "vo2_unit": "l/min",
    "vco2_unit": "l/min",
    "delimiter": ";",
    "decimal": ",",
    "header_row": 0,
    "skip_rows": 1,
}


def parse_all(mapping: CsvMapping, text: str | bytes) -> list[ParsedBreath | None]:
    parser = CsvBreathParser(mapping)
    data = text.encode() if isinstance(text, str) else text
    return [parser.parse(line) for line in data.splitlines() if line.strip()]


def test_cosmed_style_export_line_by_line() -> None:
    out = [p for p in parse_all(CsvMapping.from_dict(COSMED_MAPPING), COSMED) if p is not None]
    assert [p.record for p in out] == [
        BreathRecord(3.0, 402.1, 331.0, 11.5, 0.82, 88.0),
        BreathRecord(7.0, 455.6, 372.9, 12.8, 0.82, None),
        BreathRecord(65.5, 510.0, 433.5, 13.9, 0.85, 91.0),
    ]
    assert all(p.seq is None for p in out)


def test_parvo_style_export_with_units_and_locale() -> None:
    out = [p for p in parse_all(CsvMapping.from_dict(PARVO_MAPPING), PARVO) if p is not None]
    assert [p.record for p in out] == [
        BreathRecord(3.0, 402.0, 331.0, None, None, 88.0),
        BreathRecord(7.5, pytest.approx(455.6), pytest.approx(372.9), None, None, 90.0),
    ]


def test_whole_file_equals_streaming(tmp_path: Path) -> None:
    path = tmp_path / "export.csv"
    path.write_bytes(("\ufeff" + COSMED).encode("utf-8"))  # Excel writes a BOM
    mapping = CsvMapping.from_dict(COSMED_MAPPING)
    validator = BreathValidator()
    records = read_breath_file(path, CsvBreathParser(mapping), validator)
    streamed = [p.record for p in parse_all(mapping, COSMED) if p is not None]
    assert records == streamed
    assert validator.accepted == 3 and not validator.counters


@pytest.mark.parametrize(
    ("fmt", "text", "seconds"),
    [
        (TimeFormat.SECONDS, "83.25", 83.25),
        (TimeFormat.MINUTES, "1.5", 90.0),
        (TimeFormat.HMS, "1:02:03.5", 3723.5),
        (TimeFormat.HMS, "00:00:00", 0.0),
        (TimeFormat.MS, "75:30", 4530.0),
        (TimeFormat.MS, "0:05.25", 5.25),
    ],
)
def test_time_formats(fmt: TimeFormat, text: str, seconds: float) -> None:
    mapping = CsvMapping("t", "vo2", "vco2", time_format=fmt, columns=("t", "vo2", "vco2"))
    parsed = CsvBreathParser(mapping).parse(f"{text},500,400".encode())
    assert parsed is not None
    assert parsed.record.t_s == pytest.approx(seconds)


def test_decimal_comma_in_clock_time() -> None:
    mapping = CsvMapping(
        "t", "vo2", "vco2", time_format="hh:mm:ss", delimiter=";", decimal=",", columns=("t", "vo2", "vco2")
    )
    parsed = CsvBreathParser(mapping).parse(b"0:00:05,5;500,5;400")
    assert parsed is not None and parsed.record == BreathRecord(5.5, 500.5, 400.0)


@pytest.mark.parametrize(
    ("row", "reason"),
    [
        (b"1.0,500", RejectReason.FIELD_COUNT),
        (b",500,400", RejectReason.MISSING_FIELD),
        (b"1.0,--,400", RejectReason.MISSING_FIELD),
        (b"1.0,5OO,400", RejectReason.BAD_NUMBER),
        (b"1.0,1_000,400", RejectReason.BAD_NUMBER),
        (b"x1.0,500,400", RejectReason.BAD_NUMBER),
        (b'1.0,"500,400', RejectReason.GARBAGE),
        (b"1.0,\xff\xfe,400", RejectReason.GARBAGE),
    ],
)
def test_bad_rows_have_reasons(row: bytes, reason: RejectReason) -> None:
    parser = CsvBreathParser(CsvMapping("t", "vo2", "vco2", columns=("t", "vo2", "vco2")))
    with pytest.raises(DecodeError) as info:
        parser.parse(row)
    assert info.value.reason == reason


@pytest.mark.parametrize(
    ("fmt", "text"),
    [
        (TimeFormat.HMS, "0:61:00"),
        (TimeFormat.HMS, "1:00"),
        (TimeFormat.MS, "1:2:3"),
        (TimeFormat.MS, "-1:00"),
    ],
)
def test_bad_clock_times(fmt: TimeFormat, text: str) -> None:
    parser = CsvBreathParser(CsvMapping("t", "v", "c", time_format=fmt, columns=("t", "v", "c")))
    with pytest.raises(DecodeError) as info:
        parser.parse(f"{text},500,400".encode())
    assert info.value.reason == RejectReason.BAD_TIME


def test_thousands_separator_is_refused_not_misread() -> None:
    mapping = CsvMapping("t", "v", "c", delimiter=";", decimal=",", columns=("t", "v", "c"))
    with pytest.raises(DecodeError) as info:
        CsvBreathParser(mapping).parse(b"1;1.234;900")
    assert info.value.reason == RejectReason.BAD_NUMBER


def test_repeated_header_is_skipped() -> None:
    mapping = CsvMapping("t", "VO2", "VCO2")
    out = parse_all(mapping, "t,VO2,VCO2\n1,500,400\nt,VO2,VCO2\n2,510,410\n")
    assert [p.record.t_s for p in out if p is not None] == [1.0, 2.0]


def test_missing_header_fails_loudly() -> None:
    mapping = CsvMapping("t", "VO2", "VCO2", max_preamble_lines=3)
    parser = CsvBreathParser(mapping)
    for line in (b"a,b", b"c,d", b"e,f"):
        assert parser.parse(line) is None
    with pytest.raises(DriverConfigError, match=r"no header with columns \['t', 'VO2', 'VCO2'\]"):
        parser.parse(b"g,h")


def test_header_at_row_without_mapped_column_fails_loudly() -> None:
    parser = CsvBreathParser(CsvMapping("t", "VO2", "VCO2", header_row=1))
    assert parser.parse(b"Cart export v2") is None
    with pytest.raises(DriverConfigError,
                       match=r"no column 'VCO2' in the header; the file's columns are: 't', 'VO2', 'CO2'"):
        parser.parse(b"t,VO2,CO2")


def test_from_dict_rejects_unknown_and_bad_keys() -> None:
    with pytest.raises(DriverConfigError, match=(
            r"unknown key cart\.csv\.vo2_units = 'l/min' \(did you mean 'vo2_unit'\?\)")):
        CsvMapping.from_dict({**COSMED_MAPPING, "vo2_units": "l/min"}, "cart.csv")
    with pytest.raises(DriverConfigError, match=(
            r"csv.time_format = 'h:m:s' \(did you mean 'hh:mm:ss'\?\): "
            r"expected one of 'hh:mm:ss', 'min', 'mm:ss', 's'")):
        CsvMapping.from_dict({**COSMED_MAPPING, "time_format": "h:m:s"})
    with pytest.raises(DriverConfigError, match="missing required key 'vco2_column'"):
        CsvMapping.from_dict({"time_column": "t", "vo2_column": "VO2"})
    with pytest.raises(DriverConfigError, match="decimal = ','"):
        CsvMapping.from_dict({**COSMED_MAPPING, "decimal": ","})
    with pytest.raises(DriverConfigError, match="encoding = 'klingon'"):
        CsvMapping.from_dict({**COSMED_MAPPING, "encoding": "klingon"})
    with pytest.raises(DriverConfigError, match="lacks the mapped column"):
        CsvMapping.from_dict({**COSMED_MAPPING, "columns": ["t", "VO2"]})
    with pytest.raises(DriverConfigError, match="skip_rows = -1"):
        CsvMapping.from_dict({**COSMED_MAPPING, "skip_rows": -1})


def test_from_dict_converts_lists_and_enums() -> None:
    m = CsvMapping.from_dict({**PARVO_MAPPING, "missing": ["", "n/a"]})
    assert m.vo2_unit is GasUnit.L_MIN and m.time_format is TimeFormat.MINUTES
    assert m.missing == ("", "n/a")
    assert m.mapped_columns == ("TIME", "VO2", "VCO2", "HR")


def test_encode_rejects_negative_clock_time() -> None:
    with pytest.raises(EncodeError, match=r"t_s = -1\.0"):
        encode_csv_row(CsvMapping("t", "v", "c", time_format="mm:ss"), BreathRecord(-1.0, 500.0, 400.0))


mappings = st.builds(
    CsvMapping,
    time_column=st.just("time"),
    vo2_column=st.just("VO2 (ml/min)"),
    vco2_column=st.just("VCO2"),
    ve_column=st.sampled_from([None, "VE"]),
    rer_column=st.sampled_from([None, "RER"]),
    hr_column=st.sampled_from([None, "HR"]),
    time_format=st.sampled_from(list(TimeFormat)),
    vo2_unit=st.sampled_from(list(GasUnit)),
    vco2_unit=st.sampled_from(list(GasUnit)),
    delimiter=st.sampled_from([",", ";", "\t"]),
    decimal=st.just("."),
).filter(lambda m: m.delimiter != m.decimal) | st.builds(
    CsvMapping,
    time_column=st.just("t"),
    vo2_column=st.just("VO2"),
    vco2_column=st.just("VCO2"),
    time_format=st.sampled_from(list(TimeFormat)),
    delimiter=st.just(";"),
    decimal=st.just(","),
)
value = st.floats(0.0, 1e5, allow_nan=False)
records = st.builds(
    BreathRecord,
    t_s=st.floats(0.0, 36_000.0),
    vo2_ml_min=value,
    vco2_ml_min=value,
    ve_l_min=st.none() | value,
    rer=st.none() | value,
    hr_bpm=st.none() | value,
)


@given(mappings, st.lists(records, min_size=1, max_size=5))
def test_encode_then_parse_round_trip(mapping: CsvMapping, recs: list[BreathRecord]) -> None:
    parser = CsvBreathParser(mapping)
    assert parser.parse(encode_csv_header(mapping)) is None
    for rec in recs:
        parsed = parser.parse(encode_csv_row(mapping, rec))
        assert parsed is not None
        got = parsed.record
        assert got.t_s == pytest.approx(rec.t_s, abs=1e-6, rel=1e-12)
        assert got.vo2_ml_min == pytest.approx(rec.vo2_ml_min, rel=1e-12, abs=1e-9)
        assert got.vco2_ml_min == pytest.approx(rec.vco2_ml_min, rel=1e-12, abs=1e-9)
        for name, column in (
            ("ve_l_min", mapping.ve_column),
            ("rer", mapping.rer_column),
            ("hr_bpm", mapping.hr_column),
        ):
            expected = getattr(rec, name) if column is not None else None
            assert getattr(got, name) == expected
