"""kill -9 while a SessionLog is writing: every breath whose log call returned survives."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from mcap.reader import make_reader

from bridge.log import Topic
from bridge.log.reader import read_log, recover

ROOT = Path(__file__).resolve().parents[2]

# The writer: default SessionLog settings, a breath (+ its estimate and a force-feedback batch)
# every 20 ms; after each breath's log calls return it reports the count on stdout.
CHILD = r"""
import sys, time
from bridge.log import SessionLog
from hilbo_core.types import BreathRecord
log = SessionLog(sys.argv[1], session_id="crash", config_json={"test": True})
t0 = time.monotonic()
for i in range(1, 3001):
    rec = BreathRecord(t_s=0.5 * i, vo2_ml_min=1000.0 + i, vco2_ml_min=850.0, hr_bpm=100.0)
    log.log_breath(rec)
    log.log_estimate(index=0, breath=i - 1, t_setting_s=0.5 * i, watts=rec.watts, mean_w=400.0,
                     var_w2=25.0, phase="exploration", t_s=rec.t_s)
    log.log_force_feedback(actuator=0, desired_n=[float(i)] * 20, measured_n=[float(i)] * 20)
    sys.stdout.write(f"{i}\n")
    sys.stdout.flush()
    time.sleep(max(0.0, t0 + 0.02 * i - time.monotonic()))  # a real process paced to be SIGKILLed mid-run
"""


def _run_and_kill(path: Path, after: int) -> int:
    """Start the writer, SIGKILL it once it reported ``after`` breaths; return the last count it
    reported (it may have reported more between our read and the kill)."""
    proc = subprocess.Popen([sys.executable, "-c", CHILD, str(path)], cwd=ROOT, stdout=subprocess.PIPE,
                            text=True)
    assert proc.stdout is not None
    reported = 0
    deadline = time.monotonic() + 60.0
    try:
        while reported < after:
            line = proc.stdout.readline()
            assert line, f"the writer exited early with status {proc.poll()}"
            reported = int(line)
            assert time.monotonic() < deadline, "the writer is too slow"
        os.kill(proc.pid, signal.SIGKILL)
    finally:
        proc.kill()
        proc.wait(timeout=30)
    rest = proc.stdout.read().split()
    return int(rest[-1]) if rest else reported


@pytest.mark.parametrize("after", [5, 40])
def test_kill_9_loses_no_reported_breath_and_recovers(tmp_path: Path, after: int) -> None:
    path = tmp_path / "killed.mcap"
    reported = _run_and_kill(path, after)
    assert reported >= after
    c = read_log(path)
    assert c.truncated and c.session_id == "crash"
    kept = [b["vo2_ml_min"] - 1000.0 for b in c.data(Topic.BREATHS)]
    # Every breath whose log call returned is there; at most the one being written when the kill
    # came is there too (never a gap, never a duplicate).
    assert kept[:reported] == [float(i) for i in range(1, reported + 1)]
    assert reported <= len(kept) <= reported + 1
    assert len(c.topic(Topic.ESTIMATOR)) >= reported
    out = tmp_path / "recovered.mcap"
    report = recover(path, out)
    assert report.messages == len(c.messages) and report.unreadable_bytes == c.unreadable_bytes
    with open(out, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None and summary.statistics.message_count == len(c.messages)
        got = [(ch.topic, m.sequence, m.data) for _, ch, m in reader.iter_messages(log_time_order=False)]
    assert [(t, s) for t, s, _ in got] == [(m.topic, m.sequence) for m in c.messages]
    assert read_log(out).messages == c.messages
