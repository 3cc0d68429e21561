"""Bad input: random bytes, truncated lines, wrong checksums, NaN, absurd values,
duplicates and late breaths mixed with valid ones, in arbitrary chunks.

Properties: nothing raises; every valid breath around the bad data comes out, in order; every
bad line is counted exactly once, under the reason its kind implies.
"""

from __future__ import annotations

import asyncio
import math
import tempfile
from collections import Counter
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from drivers.cart.csvmap import CsvBreathParser, CsvMapping, encode_csv_row
from drivers.cart.framing import LineFramer
from drivers.cart.line import HbrLineParser, encode_line, parse_line
from drivers.cart.pipeline import iter_breaths
from drivers.cart.reasons import RejectReason
from drivers.cart.replay import ReplayOptions, ReplayTransport
from drivers.cart.stream import BreathStream
from drivers.cart.validate import BreathValidator
from drivers.errors import DecodeError
from hilbo_core.types import BreathRecord

pytestmark = pytest.mark.timeout(60)

FAR_SEQ = 2**31  # sequence numbers for injected records: never near the valid ones


@st.composite
def valid_breaths(draw: st.DrawFn) -> list[BreathRecord]:
    n = draw(st.integers(1, 12))
    out: list[BreathRecord] = []
    t = draw(st.floats(0.0, 100.0))
    for _ in range(n):
        t += draw(st.floats(1.0, 8.0))  # >= 1 s apart: "last - 0.5" below is never a recent time
        vo2 = draw(st.floats(300.0, 4000.0))
        ratio = draw(st.floats(0.7, 1.1))
        out.append(
            BreathRecord(
                t_s=t,
                vo2_ml_min=vo2,
                vco2_ml_min=vo2 * ratio,
                ve_l_min=draw(st.none() | st.floats(5.0, 120.0)),
                rer=draw(st.none() | st.just(ratio)),
                hr_bpm=draw(st.none() | st.floats(45.0, 190.0)),
            )
        )
    return out


junk = st.binary(min_size=1, max_size=300).filter(
    lambda b: b"\r" not in b and b"\n" not in b and not b.startswith(b"#")
)
bad_kinds = st.one_of(
    st.tuples(st.just("random"), junk),
    st.tuples(st.just("truncated"), st.floats(0.0, 1.0)),
    st.tuples(st.just("bad_crc"), st.integers(1, 0xFFFF)),
    st.tuples(st.just("nan"), st.sampled_from(["t_s", "vo2_ml_min", "vco2_ml_min", "hr_bpm"])),
    st.tuples(st.just("absurd"), st.sampled_from(["vo2", "hr", "rer", "negative_t"])),
    st.tuples(st.just("duplicate"), st.none()),
    st.tuples(st.just("late"), st.none()),
)
EXPECTED_REASON = {
    "truncated": RejectReason.TRUNCATED,
    "bad_crc": RejectReason.BAD_CHECKSUM,
    "nan": RejectReason.NON_FINITE,
    "duplicate": RejectReason.DUPLICATE,
    "late": RejectReason.OUT_OF_ORDER,
}
ABSURD = {
    "vo2": ({"vo2_ml_min": 50_000.0, "vco2_ml_min": 40_000.0}, RejectReason.VO2_RANGE),
    "hr": ({"hr_bpm": 400.0}, RejectReason.HR_RANGE),
    "rer": ({"rer": 3.0}, RejectReason.RER_RANGE),
    "negative_t": ({"t_s": -5.0}, RejectReason.NEGATIVE_TIME),
}


def with_field(record: BreathRecord, **changes: float) -> BreathRecord:
    values = {f: getattr(record, f) for f in BreathRecord.__dataclass_fields__}
    values.update(changes)
    return BreathRecord(**values)


def build_hbr(
    valid: list[BreathRecord], bad: list[tuple[int, tuple[str, object]]]
) -> tuple[bytes, Counter[str], int]:
    """Interleave bad lines into the valid ones; return the bytes, the reasons that must be
    counted (at least), and the number of bad lines."""
    lines: list[bytes] = []
    typed: Counter[str] = Counter()
    n_bad = 0
    injected = 0
    for i, record in enumerate(valid):
        for _, (kind, arg) in [b for b in bad if b[0] == i]:
            previous = valid[i - 1] if i > 0 else None
            if kind == "random":
                assert isinstance(arg, bytes)
                lines.append(arg + b"\r\n")
            elif kind == "truncated":
                assert isinstance(arg, float)
                full = encode_line(record, i).rstrip(b"\r\n")
                lines.append(full[: 1 + int(arg * (len(full) - 2))] + b"\r\n")
            elif kind == "bad_crc":
                assert isinstance(arg, int)
                good = encode_line(record, i)
                crc = int(good[-6:-2], 16)
                lines.append(good[:-6] + f"{crc ^ arg:04X}".encode() + b"\r\n")
            elif kind == "nan":
                lines.append(encode_line(with_field(record, **{str(arg): math.nan}), FAR_SEQ + injected))
            elif kind == "absurd":
                changes, reason = ABSURD[str(arg)]
                lines.append(encode_line(with_field(record, **changes), FAR_SEQ + injected))
                typed[reason] += 1
            elif kind == "duplicate" and previous is not None:
                lines.append(encode_line(previous, i - 1))
            elif kind == "late" and previous is not None:
                lines.append(encode_line(with_field(previous, t_s=previous.t_s - 0.5), FAR_SEQ + injected))
            else:  # duplicate/late before any valid breath: nothing to repeat, send junk
                lines.append(b"zzz\r\n")
                typed[RejectReason.GARBAGE] += 1
                n_bad += 1
                continue
            injected += 1
            n_bad += 1
            if kind in EXPECTED_REASON:
                typed[EXPECTED_REASON[kind]] += 1
        lines.append(encode_line(record, i))
    return b"".join(lines), typed, n_bad


def chunked(blob: bytes, cuts: list[int]) -> list[bytes]:
    edges = sorted({min(c, len(blob)) for c in cuts})
    return [blob[a:b] for a, b in zip([0, *edges], [*edges, len(blob)], strict=True)]


bad_positions = st.lists(st.tuples(st.integers(0, 12), bad_kinds), max_size=25)


@settings(max_examples=100, deadline=None)
@given(valid_breaths(), bad_positions, st.lists(st.integers(0, 20_000), max_size=30))
def test_hbr_stream_keeps_every_valid_breath(
    valid: list[BreathRecord], bad: list[tuple[int, tuple[str, object]]], cuts: list[int]
) -> None:
    blob, typed, n_bad = build_hbr(valid, bad)
    framer = LineFramer()
    validator = BreathValidator()
    parser = HbrLineParser()
    out: list[BreathRecord] = []
    for chunk in chunked(blob, cuts):
        out.extend(iter_breaths(framer.feed(chunk), parser, validator))
    assert framer.flush() is None
    assert out == valid
    counts = validator.counters + framer.counters
    assert sum(counts.values()) == n_bad
    for reason, n in typed.items():
        assert counts[reason] >= n, (reason, counts)


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(valid_breaths(), bad_positions)
def test_hbr_bad_input_through_the_replay_transport(
    valid: list[BreathRecord], bad: list[tuple[int, tuple[str, object]]]
) -> None:
    blob, typed, n_bad = build_hbr(valid, bad)
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "fuzz.hbr"
        path.write_bytes(blob)

        async def run() -> tuple[list[BreathRecord], Counter[str]]:
            stream = BreathStream(ReplayTransport(ReplayOptions(str(path), speed="max")), HbrLineParser())
            async with stream:
                records = [r async for r in stream]
            return records, stream.counters

        records, counts = asyncio.run(asyncio.wait_for(run(), 10))
    assert records == valid
    assert sum(counts.values()) == n_bad
    for reason, n in typed.items():
        assert counts[reason] >= n


@given(st.binary(max_size=400))
def test_parse_line_only_ever_raises_decode_error(data: bytes) -> None:
    try:
        parsed = parse_line(data)
    except DecodeError as err:
        assert isinstance(err.reason, str) and err.reason in set(RejectReason)
    else:  # only reachable with a matching CRC: then it must be a well-formed record
        assert isinstance(parsed.record, BreathRecord)


CSV = CsvMapping("t", "VO2", "VCO2", hr_column="HR", time_format="mm:ss")


@given(st.lists(st.binary(max_size=120), max_size=20))
def test_csv_parser_only_ever_raises_decode_error(rows: list[bytes]) -> None:
    parser = CsvBreathParser(CSV)
    assert parser.parse(b"t,VO2,VCO2,HR") is None
    for row in rows:
        try:
            parser.parse(row)
        except DecodeError as err:
            assert err.reason in set(RejectReason)


csv_junk = st.text(st.characters(blacklist_categories=("Cs",)), max_size=60).map(
    lambda s: "x" + s.replace("\r", "").replace("\n", "")
)


@settings(max_examples=60, deadline=None)
@given(
    valid_breaths(),
    st.lists(
        st.tuples(
            st.integers(0, 12),
            st.one_of(
                st.tuples(st.just("junk"), csv_junk),
                st.tuples(st.just("nan"), st.none()),
                st.tuples(st.just("short"), st.none()),
                st.tuples(st.just("absurd"), st.none()),
            ),
        ),
        max_size=20,
    ),
)
def test_csv_stream_keeps_every_valid_breath(
    valid: list[BreathRecord], bad: list[tuple[int, tuple[str, object]]]
) -> None:
    def row(r: BreathRecord) -> bytes:
        return encode_csv_row(CSV, r)

    lines = [b"export v1\r\n", b"t,VO2,VCO2,HR\r\n"]
    expected: Counter[str] = Counter()
    n_bad = 0
    for i, record in enumerate(valid):
        for _, (kind, arg) in [b for b in bad if b[0] == i]:
            n_bad += 1
            if kind == "junk":
                lines.append(str(arg).encode() + b"\r\n")
            elif kind == "nan":
                lines.append(b"0:01,nan,800,90\r\n")
                expected[RejectReason.NON_FINITE] += 1
            elif kind == "short":
                lines.append(b"0:01,800\r\n")
                expected[RejectReason.FIELD_COUNT] += 1
            else:
                lines.append(row(with_field(record, hr_bpm=999.0)))
                expected[RejectReason.HR_RANGE] += 1
        lines.append(row(record))
    framer = LineFramer()
    validator = BreathValidator()
    out = list(iter_breaths(framer.feed(b"".join(lines)), CsvBreathParser(CSV), validator))
    assert len(out) == len(valid)
    for got, want in zip(out, valid, strict=True):
        assert abs(got.t_s - want.t_s) < 1e-5  # mm:ss with microsecond seconds
        assert (got.vo2_ml_min, got.vco2_ml_min, got.hr_bpm) == (
            want.vo2_ml_min,
            want.vco2_ml_min,
            want.hr_bpm,
        )
    assert sum(validator.counters.values()) == n_bad
    for reason, n in expected.items():
        assert validator.counters[reason] >= n
