"""bridge.log.reader: reading logs whole or cut off by a crash, and recovering them."""

from __future__ import annotations

import json
import struct
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from mcap.reader import make_reader
from mcap.writer import Writer

from bridge.log import LogFormatError, LogWriteError, SessionLog, Topic
from bridge.log.reader import read_log, recover
from hilbo_core.types import BreathRecord

N_BREATHS = 12


@pytest.fixture(scope="module")
def log_file(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, list[int]]:
    """A closed log of N_BREATHS breaths; also the file size after each breath was flushed."""
    path = tmp_path_factory.mktemp("read") / "s.mcap"
    sizes = []
    with SessionLog(path, session_id="r", config_json={"k": 1}, flush_interval_s=None) as log:
        sizes.append(path.stat().st_size)
        for i in range(N_BREATHS):
            log.log_breath(BreathRecord(t_s=3.0 * i, vo2_ml_min=1000.0 + i, vco2_ml_min=800.0))
            sizes.append(path.stat().st_size)
        log.log_event("end", "done")
    return path, sizes


def _cut(src: Path, dst: Path, n: int) -> Path:
    dst.write_bytes(src.read_bytes()[:n])
    return dst


def _standard_reader_messages(path: Path) -> list[tuple[str, int, int, int, bytes]]:
    with open(path, "rb") as f:
        return [(c.topic, m.sequence, m.log_time, m.publish_time, m.data)
                for _, c, m in make_reader(f).iter_messages(log_time_order=False)]


def test_a_closed_file_reads_completely(log_file) -> None:
    path, _ = log_file
    c = read_log(path)
    assert c.complete and c.data_complete and not c.truncated and c.stop_reason == ""
    assert c.readable_bytes == c.size_bytes == path.stat().st_size
    assert [b["vo2_ml_min"] for b in c.data(Topic.BREATHS)] == [1000.0 + i for i in range(N_BREATHS)]
    assert c.profile == "hilbo" and c.library.startswith("hilbo ")
    assert c.channels[Topic.BREATHS].message_count == N_BREATHS
    assert c.time_range_ns is not None and c.time_range_ns[0] <= c.time_range_ns[1]


@pytest.mark.parametrize("k", [0, 1, 5, N_BREATHS])
def test_a_cut_at_a_flush_boundary_keeps_every_flushed_breath(log_file, tmp_path: Path, k: int) -> None:
    path, sizes = log_file
    c = read_log(_cut(path, tmp_path / "cut.mcap", sizes[k]))
    assert c.truncated and not c.data_complete and c.unreadable_bytes == 0
    assert "without a footer" in c.stop_reason
    assert len(c.topic(Topic.BREATHS)) == k
    assert c.session_id == "r"


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(frac=st.floats(0.0, 1.0))
def test_any_cut_reads_a_prefix_without_error(log_file, tmp_path: Path, frac: float) -> None:
    path, sizes = log_file
    n = sizes[0] + round(frac * (path.stat().st_size - sizes[0]))
    c = read_log(_cut(path, tmp_path / "any.mcap", n))
    k = len(c.topic(Topic.BREATHS))
    # Every breath whose flush completed before byte n survives; the next one too when its chunk
    # record is whole and only the message-index records written after it are cut.
    flushed = sum(1 for s in sizes[1:] if s <= n)
    assert flushed <= k <= flushed + 1
    assert c.readable_bytes + c.unreadable_bytes == n
    full = read_log(path).messages
    assert c.messages == full[: len(c.messages)]


def test_a_damaged_chunk_is_skipped_and_named(log_file, tmp_path: Path) -> None:
    path, sizes = log_file
    data = bytearray(path.read_bytes()[: sizes[6]])
    data[sizes[5] + 60] ^= 0xFF  # inside the 6th breath's chunk
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(bytes(data))
    c = read_log(bad)
    assert len(c.topic(Topic.BREATHS)) == 5
    [damage] = c.damage
    assert damage.start == sizes[5] and "damaged" in damage.reason and c.damaged
    assert f"bytes {sizes[5]:,}" in c.damage_text()


@pytest.mark.parametrize("where", ["overwrite", "insert"])
def test_garbage_in_the_middle_reads_what_lies_after_it(log_file, tmp_path: Path, where: str) -> None:
    """A closed log with garbage over (or inserted into) breaths 4-5: the rest is read, the damage named."""
    path, sizes = log_file
    data = path.read_bytes()
    garbage = bytes(range(7, 250)) * 2
    start = sizes[4] + 3
    if where == "overwrite":
        damaged = data[:start] + garbage[: sizes[6] - start] + data[sizes[6]:]
    else:
        damaged = data[:start] + garbage + data[start:]
    bad = tmp_path / "garbage.mcap"
    bad.write_bytes(damaged)
    c = read_log(bad)
    got = [b.vo2_ml_min for b in c.records(Topic.BREATHS)]
    full = [1000.0 + i for i in range(N_BREATHS)]
    assert got[:4] == full[:4] and got[-(N_BREATHS - 6):] == full[6:]  # everything after the damage
    assert len(got) >= N_BREATHS - 2
    assert c.complete and c.damaged and c.damage[0].start == sizes[4]
    assert c.topic(Topic.EVENTS)[-1].record.kind == "end"
    report = recover(bad, tmp_path / "fixed.mcap")
    fixed = read_log(tmp_path / "fixed.mcap")
    assert report.damage and fixed.records(Topic.BREATHS) == c.records(Topic.BREATHS)


def test_recover_writes_an_indexed_file_with_the_same_messages(log_file, tmp_path: Path) -> None:
    path, sizes = log_file
    cut = _cut(path, tmp_path / "crashed.mcap", sizes[7] + 25)  # 7 breaths and a torn chunk
    report = recover(cut, tmp_path / "fixed.mcap")
    assert report.messages == 8 and report.per_topic == {Topic.CONFIG: 1, Topic.BREATHS: 7}
    assert not report.source_complete and report.unreadable_bytes == 25
    fixed = read_log(tmp_path / "fixed.mcap")
    assert fixed.complete
    original = read_log(cut)
    assert fixed.messages == original.messages
    with open(tmp_path / "fixed.mcap", "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None and summary.statistics.message_count == 8
        assert len(summary.chunk_indexes) >= 1
        meta = {m.name: m.metadata for m in reader.iter_metadata()}
    assert meta["hilbo.recovered"]["unreadable_bytes"] == "25"
    assert meta["hilbo.session"]["session_id"] == "r"
    assert _standard_reader_messages(tmp_path / "fixed.mcap") == [
        (m.topic, m.sequence, m.log_time_ns, m.publish_time_ns, json.dumps(m.data, separators=(",", ":"))
         .encode()) for m in original.messages]


def test_recover_of_a_complete_file_is_a_faithful_copy(log_file, tmp_path: Path) -> None:
    path, _ = log_file
    report = recover(path, tmp_path / "copy.mcap")
    assert report.source_complete and report.unreadable_bytes == 0
    assert _standard_reader_messages(tmp_path / "copy.mcap") == _standard_reader_messages(path)


def test_recover_refuses_to_overwrite(log_file, tmp_path: Path) -> None:
    path, _ = log_file
    out = tmp_path / "o.mcap"
    out.write_bytes(b"x")
    with pytest.raises(LogWriteError, match="exists"):
        recover(path, out)
    assert out.read_bytes() == b"x"
    recover(path, out, overwrite=True)
    assert read_log(out).complete
    with pytest.raises(LogFormatError, match="is the input"):
        recover(out, out, overwrite=True)


def test_topic_filter_decodes_only_what_is_asked(log_file) -> None:
    c = read_log(log_file[0], topics=[Topic.CONFIG])
    assert {m.topic for m in c.messages} == {Topic.CONFIG}
    assert c.undecoded == N_BREATHS + 1 and c.channels[Topic.BREATHS].message_count == N_BREATHS


@pytest.mark.parametrize(("content", "match"), [
    (b"", "empty"),
    (b"\x89MCA", "cut inside the MCAP magic"),
    (b"col1,col2\n1,2\n", "not an MCAP file"),
    (b"\x89MCAP0\r\n\x05" + b"\x00" * 8, "without a header"),
])
def test_bad_input_is_a_clear_format_error(tmp_path: Path, content: bytes, match: str) -> None:
    path = tmp_path / "bad.mcap"
    path.write_bytes(content)
    with pytest.raises(LogFormatError, match=match):
        read_log(path)
    with pytest.raises(LogFormatError):
        recover(path, tmp_path / "out.mcap")
    assert not (tmp_path / "out.mcap").exists()


def test_missing_file_and_directory(tmp_path: Path) -> None:
    with pytest.raises(LogFormatError, match="no such file"):
        read_log(tmp_path / "nope.mcap")
    with pytest.raises(LogFormatError, match="directory"):
        read_log(tmp_path)


def test_another_programs_mcap_is_refused_unless_asked(tmp_path: Path) -> None:
    path = tmp_path / "other.mcap"
    with open(path, "wb") as f:
        w = Writer(f)
        w.start(profile="ros2", library="someone else")
        sid = w.register_schema("pkg/Thing", "ros2msg", b"float64 x")
        cid = w.register_channel("/thing", "cdr", sid)
        w.add_message(cid, log_time=1, publish_time=1, data=b"\x00" * 8)
        w.finish()
    with pytest.raises(LogFormatError, match=r"not a hilbo session log.*'/thing'"):
        read_log(path)
    c = read_log(path, require_hilbo=False)
    assert c.complete and c.messages == () and c.undecoded == 1
    assert c.channels["/thing"].schema_name == "pkg/Thing" and c.channels["/thing"].message_count == 1
    report = recover(path, tmp_path / "other2.mcap")  # recover works on any MCAP
    assert report.messages == 1 and report.per_topic == {"/thing": 1}


def test_damage_found_when_its_last_bytes_look_like_a_record_header(log_file, tmp_path: Path) -> None:
    """Resynchronising after damage finds the next record even when a false header candidate in
    the damaged bytes overlaps it (an opcode byte 3 bytes before it, whose length field would
    end in the real header's zero length bytes)."""
    path, sizes = log_file
    data = bytearray(path.read_bytes()[: sizes[6]])
    chunk = sizes[5]
    (length,) = struct.unpack_from("<Q", data, chunk + 1)
    after = chunk + 9 + length  # the chunk's first message index
    assert data[after] == 0x07 and after < sizes[6]
    data[chunk + 60] ^= 0xFF
    data[after - 3] = 0x05  # a known opcode; bytes after+3..after+5 are zero
    bad = tmp_path / "overlap.mcap"
    bad.write_bytes(bytes(data))
    c = read_log(bad)
    assert len(c.topic(Topic.BREATHS)) == 5
    [damage] = c.damage
    assert (damage.start, damage.end) == (chunk, after)
