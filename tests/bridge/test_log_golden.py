"""Golden session logs: every reader opens the log of every format version, and the writer's
output cannot change without a format-version bump (tests/data/logs/, bridge.log.FORMAT_VERSION)."""

from __future__ import annotations

import hashlib
import importlib.util
import json
import sys
from pathlib import Path
from typing import Any

import pytest

from bridge.bench.bridge_perf import _log_counts
from bridge.bench.tune_stopping import evaluations_from_log, trajectories_from_log
from bridge.cli.log import log_info
from bridge.cli.main import main
from bridge.log import FORMAT_VERSION, READABLE_VERSIONS, RECORD_TYPES, Topic
from bridge.log import records as rec
from bridge.log.reader import read_log, recover
from bridge.log.resume import ResumeError, rebuild_optimizer
from bridge.review.session import load_session
from hilbo_core.metabolic import GaussianProductEstimator

DATA = Path(__file__).resolve().parents[1] / "data" / "logs"
DIGESTS = DATA / "digests.json"
VERSIONS = sorted(int(p.name[1:]) for p in DATA.glob("v*") if (p / "session.mcap").exists())


def _make_golden() -> Any:
    spec = importlib.util.spec_from_file_location("make_golden", DATA / "make_golden.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules.setdefault("make_golden", module)
    spec.loader.exec_module(module)
    return module


def _estimator() -> GaussianProductEstimator:
    return GaussianProductEstimator(400.0, 1e4, 1600.0)


def _rounded(value: Any) -> Any:
    # Floats to 6 significant digits: the GP's numbers may differ in the last bits between
    # machines (BLAS); a format change changes keys, types, order or values far beyond that.
    if isinstance(value, float):
        return float(f"{value:.6g}")
    if isinstance(value, dict):
        return {k: _rounded(v) for k, v in value.items()}
    if isinstance(value, list):
        return [_rounded(v) for v in value]
    return value


def writer_digest(path: Path) -> str:
    """SHA-256 of what the writer put in a log: every channel's schema, every message's topic,
    times, keys (in order) and values (floats rounded; the hilbo version in /config normalised:
    it is not the format)."""
    c = read_log(path)
    h = hashlib.sha256()
    for topic, info in sorted(c.channels.items()):
        h.update(json.dumps([topic, info.schema_name, info.schema_encoding, info.message_encoding,
                             info.schema], sort_keys=True).encode())
    for m in c.messages:
        data = dict(m.data)
        if m.topic == Topic.CONFIG:
            data["hilbo_version"] = "-"
        h.update(json.dumps([m.topic, m.log_time_ns, m.publish_time_ns, m.sequence, _rounded(data)]).encode())
    return h.hexdigest()


def test_there_is_a_golden_log_of_the_current_format() -> None:
    assert FORMAT_VERSION in VERSIONS, (
        f"no tests/data/logs/v{FORMAT_VERSION}/session.mcap: run `python tests/data/logs/make_golden.py`")
    assert set(VERSIONS) <= READABLE_VERSIONS and 1 in VERSIONS


def test_the_writer_output_matches_the_digest_of_its_format_version(tmp_path: Path) -> None:
    """Fails when the writer's schemas or records change while FORMAT_VERSION stays the same."""
    path = tmp_path / "golden.mcap"
    golden = _make_golden()
    golden.write_session(path, started_unix_ns=golden.STARTED_UNIX_NS)
    digests = json.loads(DIGESTS.read_text())
    got = writer_digest(path)
    assert str(FORMAT_VERSION) in digests, (
        f"format version {FORMAT_VERSION} has no digest in {DIGESTS}; add {got!r} with its golden log")
    assert got == digests[str(FORMAT_VERSION)], (
        f"the writer's output changed but bridge.log.FORMAT_VERSION is still {FORMAT_VERSION}: bump it, "
        f"write tests/data/logs/v{FORMAT_VERSION + 1}/session.mcap (make_golden.py) and record its digest "
        f"{got!r} in {DIGESTS.name}")
    # The committed golden file of this version is what this writer writes.
    assert writer_digest(DATA / f"v{FORMAT_VERSION}" / "session.mcap") == got


@pytest.mark.parametrize("version", VERSIONS)
def test_every_reader_opens_the_golden_log(version: int, tmp_path: Path) -> None:
    path = DATA / f"v{version}" / "session.mcap"
    c = read_log(path)
    assert c.complete and not c.damaged and c.invalid == 0 and c.undecodable == 0
    assert c.format_version == version and c.session_id == "golden"
    # Every message of a known channel decodes into its typed record.
    for m in c.messages:
        assert isinstance(m.record, RECORD_TYPES[m.topic]), (m.topic, m.raw[:80])
    assert [b.vo2_ml_min for b in c.records(Topic.BREATHS)][:3] == [1000.0, 1007.0, 1014.0]
    assert [e.index for e in c.records(Topic.OBSERVATIONS)] == [0, 1, 2]
    # resume
    opt, info = rebuild_optimizer(path, estimator_factory=_estimator)
    assert info.n_evaluations == len(opt.evaluations) == 3 and info.discarded_params is None
    assert [o.index for o in info.observations] == [0, 1, 2]
    # review
    session = load_session([path])
    assert len(session.evaluations) == 3 and session.recommended is not None
    assert len(session.breaths) == 7
    kinds = {e.kind for e in session.events}
    assert {"pause", "resume", "nack"} <= kinds
    assert ("device_fault" if version >= 2 else "fault") in kinds
    # tune-stopping, the benchmarks, hilbo log info, recover
    trajs, evs = trajectories_from_log(path)
    assert len(trajs) == len(evs) >= 1 and all(isinstance(e, rec.Evaluation) for e in evs)
    assert [e["index"] for e in evaluations_from_log(path)] == [0, 1, 2]
    counts = _log_counts(path)
    assert counts["feedback_logged"] == 9 and len(counts["pushes"]) == 3
    summary = log_info(read_log(path))
    assert summary["evaluations"] == 3 and summary["last_snapshot_evaluations"] == 3
    report = recover(path, tmp_path / "copy.mcap")
    assert report.source_complete and read_log(tmp_path / "copy.mcap").records(Topic.BREATHS) == \
        c.records(Topic.BREATHS)


@pytest.mark.parametrize("version", VERSIONS)
def test_event_levels_of_the_golden_logs(version: int) -> None:
    events = {e.kind: e.level for e in read_log(DATA / f"v{version}" / "session.mcap").records(Topic.EVENTS)}
    if version == 1:
        assert set(events.values()) == {rec.EventLevel.INFO}  # what format 1 wrote
    else:
        assert events["pause"] == events["resume_refused"] == rec.EventLevel.WARNING
        assert events["device_fault"] == rec.EventLevel.ERROR
        assert events["resume"] == events["session_start"] == rec.EventLevel.INFO


def test_review_of_a_log_damaged_mid_file_says_where_and_reads_on(tmp_path: Path,
                                                                  capsys: pytest.CaptureFixture[str]) -> None:
    src = DATA / f"v{FORMAT_VERSION}" / "session.mcap"
    data = src.read_bytes()
    intact = read_log(src)
    start, end = len(data) // 3, len(data) // 3 + 400
    bad = tmp_path / "damaged.mcap"
    bad.write_bytes(data[:start] + bytes(range(256)) * 2 + data[end:])  # garbage over 400 bytes
    c = read_log(bad)
    assert c.damaged and c.complete
    first = c.damage[0]
    assert first.start <= start < first.end
    assert "damaged" in first.reason or "no MCAP record" in first.reason
    # What lies after the damage is read: the last breaths and the session's end.
    assert c.records(Topic.BREATHS)[-1] == intact.records(Topic.BREATHS)[-1]
    assert c.records(Topic.EVENTS)[-1].kind == "session_end"
    assert len(c.messages) < len(intact.messages)
    out = tmp_path / "review"
    assert main(["review", str(bad), "--out", str(out)]) == 1  # written, but not a clean log
    err = capsys.readouterr().err
    assert "damaged inside" in err and f"bytes {first.start:,}" in err
    md = (out / "report.md").read_text()
    assert "log_damaged" in md and f"{first.start:,}" in md
    assert main(["review", str(src), "--out", str(tmp_path / "clean")]) == 0


def test_resume_of_a_damaged_log_names_the_damage(tmp_path: Path) -> None:
    src = DATA / f"v{FORMAT_VERSION}" / "session.mcap"
    data = src.read_bytes()
    c = read_log(src)
    # Garbage over the middle: the last snapshot survives, breaths before it may not matter.
    bad = tmp_path / "damaged.mcap"
    mid = len(data) // 2
    bad.write_bytes(data[:mid] + b"\xff" * 300 + data[mid + 300:])
    try:
        opt, info = rebuild_optimizer(bad, estimator_factory=_estimator)
    except ResumeError as err:
        text = str(err)
        assert "damaged" in text and "bytes" in text and "SessionLog" not in text
    else:
        assert info.n_evaluations == len(opt.evaluations) == len(c.records(Topic.OBSERVATIONS))

