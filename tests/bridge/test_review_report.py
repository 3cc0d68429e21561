"""hilbo review's report: faults, nacks and rejected records/frames from the log, across files."""

from __future__ import annotations

import csv
from pathlib import Path

from bridge.log import EventLevel, SessionLog
from bridge.review.command import review_session
from bridge.review.report import BREATH_COLUMNS
from bridge.review.session import load_session
from hilbo_core.types import BreathRecord


def write_log(path: Path, *, previous: Path | None = None, t0: float = 500.0) -> Path:
    """A few breaths, a device fault and its clearing, a nack, an event and reject counters."""
    with SessionLog(path, session_id="s", config_json={"session": {"subject": "x"}}, previous_log=previous,
                    flush_interval_s=None) as log:
        for k in range(4):
            log.log_breath(BreathRecord(t_s=t0 + 3.0 * k, vo2_ml_min=1000.0, vco2_ml_min=800.0, hr_bpm=90.0))
            if k == 1:
                log.log_device_status(actuator=1, mode="fault", faults=0b100)
                log.log_ack(version=3, accepted=False, reason="bad_crc", error="CRC mismatch")
            if k == 2:
                log.log_device_status(actuator=1, mode="assist", faults=0)
                log.log_event("pause", "operator pause", level=EventLevel.WARNING)
        log.log_rejects("cart", {"bad_crc": 1, "out_of_order": 2})
        log.log_rejects("cart", {"bad_crc": 2, "out_of_order": 2})  # cumulative: the last one counts
        log.log_rejects("can", {"unknown_id": 5})
    return path


def test_faults_nacks_events_and_rejects_reach_the_report(tmp_path: Path) -> None:
    old = write_log(tmp_path / "old.mcap")
    new = write_log(tmp_path / "new.mcap", previous=old, t0=20.0)
    result = review_session([old, new], tmp_path / "out")
    s = result.session
    assert s.rejects == {"cart": {"bad_crc": 4, "out_of_order": 4}, "can": {"unknown_id": 10}}
    kinds = [(e.file, e.kind) for e in s.events]
    # Format 2: the writer logs a latched fault as an /events ERROR (once, not again from /device_status).
    assert kinds.count((0, "device_fault")) == kinds.count((1, "device_fault")) == 1
    assert "fault" not in {k for _, k in kinds}
    assert (0, "device_fault_cleared") in kinds and (1, "nack") in kinds and (1, "resumed") in kinds
    fault = next(e for e in s.events if e.kind == "device_fault")
    assert fault.time_s == 3.0 and fault.level == "error"  # placed at the breath logged before it
    pause = next(e for e in s.events if e.kind == "pause" and e.file == 1)
    assert pause.time_s == 9.0 + 6.0  # old file: 0-9 s; new file starts there
    md = (result.out_dir / "report.md").read_text()
    assert "| cart | bad_crc | 4 |" in md and "| can | unknown_id | 10 |" in md
    assert "profile version 3 not accepted: CRC mismatch" in md
    assert "| warning | pause | operator pause |" in md
    assert "No evaluation completed" in md and "not drawn" in md
    with open(result.out_dir / "breaths.csv", newline="") as f:
        rows = list(csv.reader(f))
    assert tuple(rows[0]) == BREATH_COLUMNS and len(rows) == 1 + 8
    assert [float(r[3]) for r in rows[1:]] == [0.0, 3.0, 6.0, 9.0, 9.0, 12.0, 15.0, 18.0]
    with open(result.out_dir / "evaluations.csv", newline="") as f:
        assert len(list(csv.reader(f))) == 1  # header only


def test_plots_without_evaluations_are_skipped_with_the_reason(tmp_path: Path) -> None:
    result = review_session([write_log(tmp_path / "a.mcap")], tmp_path / "out")
    assert set(result.skipped) == {"best_so_far", "parameters", "thresholds", "force_tracking"}
    assert [p.name for p in result.files][:1] == ["timeline.png"]
    assert load_session([tmp_path / "a.mcap"]).recommended is None


def test_setting_values_show_round_off_as_zero_and_keep_real_values() -> None:
    from bridge.review.report import _num, _param

    assert _param(6.117e-16) == "0" and _param(-3e-12) == "0"
    assert _param(54.99999999999885) == "55" and _param(0.00123) == "0.00123"
    assert _num(float("nan")) == "–" and _num(None) == "–" and _num(323.25) == "323.2"
