"""LineFramer: lines across chunk boundaries, all terminators, bounded memory."""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from drivers.cart.framing import LineFramer
from drivers.cart.reasons import RejectReason
from drivers.errors import DriverConfigError

pytestmark = pytest.mark.timeout(30)


def test_terminators_and_blank_lines() -> None:
    f = LineFramer()
    assert f.feed(b"a\r\nb\nc\rd\r\n\r\n\ne") == [b"a", b"b", b"c", b"d"]
    assert f.pending == 1
    assert f.flush() == b"e"
    assert f.flush() is None


def test_crlf_split_across_chunks_gives_no_empty_line() -> None:
    f = LineFramer()
    assert f.feed(b"one\r") == [b"one"]
    assert f.feed(b"\ntwo\r\n") == [b"two"]


def test_too_long_line_is_dropped_whole_and_counted_once() -> None:
    f = LineFramer(max_line_bytes=8)
    assert f.feed(b"ok\n" + b"x" * 5) == [b"ok"]
    assert f.feed(b"x" * 5) == []  # 10 bytes pending > 8: start discarding
    assert f.pending == 0
    assert f.feed(b"xxxxxxxxxxxxxxxxx") == []
    assert f.feed(b"xx\nnext\n") == [b"next"]
    assert f.feed(b"y" * 9 + b"\nz\n") == [b"z"]  # too long inside one chunk
    assert f.counters == {RejectReason.TOO_LONG: 2}


def test_discard_counts_a_cut_line() -> None:
    f = LineFramer()
    f.feed(b"$HBR,1,2")
    f.discard()
    f.discard()  # nothing pending: not counted again
    assert f.feed(b"\nfresh\n") == [b"fresh"]
    assert f.counters == {RejectReason.TRUNCATED: 1}


def test_flush_after_overlong_tail_returns_nothing() -> None:
    f = LineFramer(max_line_bytes=4)
    f.feed(b"abcdefgh")
    assert f.flush() is None


@pytest.mark.parametrize("bad", [0, -1, 1.5, True])
def test_bad_max_line_bytes(bad: object) -> None:
    with pytest.raises(DriverConfigError, match="max_line_bytes"):
        LineFramer(bad)  # type: ignore[arg-type]


lines_st = st.lists(
    st.binary(min_size=1, max_size=40).filter(lambda b: b"\r" not in b and b"\n" not in b), max_size=30
)


@given(lines_st, st.sampled_from([b"\n", b"\r\n", b"\r"]), st.data())
def test_any_chunking_gives_the_same_lines(lines: list[bytes], end: bytes, data: st.DataObject) -> None:
    blob = b"".join(line + end for line in lines)
    cuts = sorted(data.draw(st.lists(st.integers(0, len(blob)), max_size=10)))
    chunks = [blob[a:b] for a, b in zip([0, *cuts], [*cuts, len(blob)], strict=True)]
    f = LineFramer(max_line_bytes=40)
    out = [line for chunk in chunks for line in f.feed(chunk)]
    assert out == lines
    assert f.flush() is None and not f.counters
