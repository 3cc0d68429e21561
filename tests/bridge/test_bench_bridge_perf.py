"""bridge.bench.bridge_perf: the real-time bridge measurement at toy size (fast clock, short session).

Only structure and invariants are asserted, never wall times: the numbers depend on the machine.
"""

from __future__ import annotations

import json
import os

import pytest

from bridge.bench.bridge_perf import (
    BRIDGE_TARGETS,
    BridgeProtocol,
    BridgeRtConfig,
    _Sample,
    _steal_around,
    bridge_realtime,
    bridge_table,
)
from bridge.bench.cli import bench_main
from bridge.bench.perf import PerfConfig
from hilbo_core.errors import ConfigError

#: A session of ~15 s wall time: 5 simulated minutes at 20 × real time. Walking time counts the
#: first ask's wait for the proposal worker process to start (numpy and scipy imports: 1.5 s idle,
#: up to ~6 s beside CPU burners), which at 60 × ate a 1.8-minute session whole (0 evaluations);
#: the first 60-s warm-up (3 s of wall time) hides most of that start, as the lab's 180 s do.
TOY = BridgeRtConfig(minutes=5.0, speed=20.0, feedback_hz=500.0, warmup_s=60.0, max_breaths=6,
                     sample_period_s=0.25, baseline_s=0.5)


def _check(b: dict, cfg: BridgeRtConfig) -> None:
    assert b["actuators"] == 2 and b["joints"] == ["hip", "hip"]
    assert b["config"]["feedback_hz"] == cfg.feedback_hz
    assert b["wall_s"] > 0 and b["n_evaluations"] >= 2
    for key in ("stop_to_ack_ms", "push_latency_ms", "push_only_ms"):
        q = b[key]
        assert q["n"] >= 1, key
        assert 0 < q["median"] <= q["p99"] <= q["max"], key
    # Every stop-decision push is a push; each latency holds its push's transfer.
    assert b["stop_to_ack_ms"]["n"] <= b["push_latency_ms"]["n"] == b["push_only_ms"]["n"]
    assert len(b["stop_to_ack_samples_ms"]) == b["stop_to_ack_ms"]["n"]
    # The log's pushes pair with the session's latencies: ask + transfer + rest = total, and
    # ask() itself in the worker is part of the ask as the session waited for it.
    bd = b["stop_to_ack_breakdown"]
    rows = bd["per_push_ms"]
    assert {q["n"] for k, q in bd.items() if k != "per_push_ms"} == {b["stop_to_ack_ms"]["n"]} == {len(rows)}
    # Each row's total is its sample to 0.01 ms. The JSON's samples are rounded to 6 significant
    # digits on their own (round_sig), so rounding them again may land a hundredth away (211.17
    # against 211.18 once).
    assert [r["total"] for r in rows] == pytest.approx(b["stop_to_ack_samples_ms"], abs=0.0101)
    for r in rows:
        assert r["ask"] + r["transfer"] + r["rest"] == pytest.approx(r["total"], abs=0.03)
        assert r["steal_cores"] is None or r["steal_cores"] >= 0
    slow = b["slow_stop_decisions"]
    assert slow["of"] == len(rows) and slow["over_ms"] == BRIDGE_TARGETS["stop_to_ack_p99_ms"]
    assert slow["n"] == sum(r["total"] > slow["over_ms"] for r in rows)
    assert b["protocol"] == cfg.protocol
    assert bd["transfer_ms"]["median"] > 0 and 0 < bd["compute_ms"]["median"] <= bd["ask_ms"]["median"]
    # The parts' maxima bound the whole's (up to the JSON's rounding to 6 significant digits).
    parts = bd["ask_ms"]["max"] + bd["transfer_ms"]["max"] + bd["rest_ms"]["max"]
    assert parts >= b["stop_to_ack_ms"]["max"] * (1 - 1e-5)
    assert b["cpu"]["proposal_worker"] == "process" and b["cpu"]["worker_cpu_s"] >= 0
    fb = b["force_feedback"]
    assert 0 < fb["bridge_received_total"] <= fb["device_sent_total"]
    assert fb["lost_counter_gaps"] >= 0 and fb["subscriber_overflow"] >= 0
    # The feedback task logs its last batch too, so every received frame is in the log.
    assert fb["logged_to_mcap"] == fb["bridge_received_total"]
    assert fb["not_logged"] == 0
    assert set(fb["logged_per_actuator"]) == {"0", "1"}
    w = fb["window"]
    assert w["window_s"] > 0
    assert 0 < w["received"] <= w["sent"] + 50  # + the frames in flight at the first sample
    assert w["rate_hz"]["target"] == 2 * cfg.feedback_hz
    assert 0 < w["rate_hz"]["received_min"] <= w["rate_hz"]["received"]
    cpu = b["cpu"]
    assert cpu["process_cpu_s"] > 0 and cpu["cores"] > 0
    assert any(name.startswith("MainThread") for name in cpu["threads_in_window"])
    if cfg.baseline_s > 0:
        alone = cpu["device_alone"]
        assert alone["cores"] > 0 and alone["sent_rate_hz"] > 0 and alone["seconds"] > 0
        estimate = cpu["cores_in_window"] - alone["cores"]
        assert cpu["bridge_estimate_cores"] == pytest.approx(estimate, abs=1e-5)
    assert b["targets"] == BRIDGE_TARGETS
    if cpu["machine_steal_cores_in_window"] is not None:  # Linux: /proc/stat
        assert 0 <= cpu["machine_steal_cores_in_window"] <= cpu["machine_steal_cores_max_interval"] + 1e-9
    g = b["gc"]
    assert g["mode"] == cfg.gc
    # FREEZE collects at every applied profile and at the pause between the bouts; AUTOMATIC
    # leaves it to CPython (none of ours). A pause while a pushed profile waits to be applied (a
    # loop stall on a busy machine can latch the device's heartbeat fault) abandons that setting
    # before its collection: at most one push per abandoned setting goes without one.
    ours = b["push_latency_ms"]["n"] + b["events"].get("bout_pause", 0)
    if cfg.gc == "freeze":
        assert ours - b["events"].get("evaluation_cancelled", 0) <= g["quiet_points"] <= ours
    else:
        assert g["quiet_points"] == 0
    assert set(b["met"]) == {"stop_to_ack_p99_ms", "cores", "dropped_frames", "feedback_rate"}
    assert b["events"]["session_end"] == 1


def test_toy_real_time_session_reports_latency_frames_and_cpu(tmp_path) -> None:
    b = bridge_realtime(TOY, tmp_path)
    _check(b, TOY)
    assert (tmp_path / "session.mcap").exists() and (tmp_path / "summary.json").exists()
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["stop_to_ack_ms"]["n"] == b["stop_to_ack_ms"]["n"]
    table = bridge_table(b)
    assert "| stop decision → device ack of the next profile |" in table
    assert "protocol custom (2 exploration points, N = 6, 60 s warm-ups)" in table
    assert "stop decisions over 100 ms" in table
    assert "< 0.5 core" in table
    assert f"at quiet points {b['gc']['quiet_points']} " in table and "[freeze]" in table


@pytest.mark.slow
def test_perf_cli_with_bridge_minutes_writes_perf_and_perf_bridge_json(tmp_path) -> None:
    out = tmp_path / "perf"
    code = bench_main(["perf", "--breaths", "10", "--sizes", "3", "--reps", "1", "--sessions", "0",
                       "--bridge-minutes", "4", "--bridge-speed", "20", "--bridge-feedback-hz", "500",
                       "--bridge-baseline-s", "0", "--bridge-gc", "automatic", "--bridge-protocol", "quick",
                       "--out", str(out)])
    assert code == 0
    perf = json.loads((out / "perf.json").read_text())
    for key in ("benchmark", "config", "load_average_at_start", "breath_latency_ms", "proposal_latency_ms",
                "proposal_profile", "session_60min_wall_s", "sessions", "targets", "wall_s", "command",
                "machine", "bridge_realtime"):
        assert key in perf, key
    assert ("--bridge-minutes 4 --bridge-speed 20 --bridge-feedback-hz 500 --bridge-baseline-s 0 "
            "--bridge-gc automatic --bridge-protocol quick") in perf["command"]
    small = json.loads((out / "perf_bridge.json").read_text())
    assert small["benchmark"] == "perf-bridge" and small["command"] == perf["command"]
    # 4 walked minutes: at 2.7 a loaded machine (4 busy processes on 2 cores) left 1 evaluation.
    cfg = BridgeRtConfig(minutes=4.0, speed=20.0, feedback_hz=500.0, baseline_s=0.0, gc="automatic")
    _check(small, cfg)
    assert small["protocol"] == "quick"
    assert small["cpu"]["device_alone"] is None and small["cpu"]["bridge_estimate_cores"] is None
    assert (out / "bridge_session" / "session.mcap").exists()
    assert "The bridge at real time" in (out / "perf_table.md").read_text()
    assert "stop decision → device ack" in (out / "perf_bridge_table.md").read_text()


def test_steal_is_read_from_the_cpu_line_of_proc_stat(tmp_path) -> None:
    from bridge.bench.bridge_perf import _steal_s

    stat = tmp_path / "stat"
    tick = os.sysconf("SC_CLK_TCK")
    stat.write_text(f"cpu  10 0 5 900 1 0 2 {3 * tick} 0 0\ncpu0 5 0 2 450 0 0 1 0 0 0\n")
    assert _steal_s(stat) == pytest.approx(3.0)
    stat.write_text("intr 1 2 3\n")
    assert _steal_s(stat) is None
    assert _steal_s(tmp_path / "missing") is None


def _sample(wall_s: float, steal_s: float | None) -> _Sample:
    return _Sample(wall_s, 0.0, 0, 0, 0, {}, 0.0, steal_s, unix_ns=round(1e9 * (1000 + wall_s)))


def test_a_push_gets_the_worst_steal_of_the_sampling_intervals_it_overlaps() -> None:
    # Intervals [0, 1] s: 0.1 cores, [1, 2]: 0.5, [2, 3]: 0.0.
    samples = [_sample(0.0, 10.0), _sample(1.0, 10.1), _sample(2.0, 10.6), _sample(3.0, 10.6)]
    ns = lambda t: round(1e9 * (1000 + t))  # noqa: E731
    assert _steal_around(samples, ns(0.2), ns(0.3)) == pytest.approx(0.1)
    assert _steal_around(samples, ns(0.9), ns(1.1)) == pytest.approx(0.5)  # spans two intervals
    assert _steal_around(samples, ns(2.5), ns(2.6)) == pytest.approx(0.0)
    assert _steal_around(samples, ns(5.0), ns(6.0)) is None  # after the last sample
    assert _steal_around([_sample(0.0, None), _sample(1.0, None)], ns(0.2), ns(0.3)) is None


def test_protocols_set_exploration_n_and_warm_ups() -> None:
    lab = BridgeRtConfig.for_protocol("lab", minutes=60.0)
    assert (lab.n_explore, lab.max_breaths, lab.warmup_s) == (3, 45, 180.0)  # the fast protocol
    assert lab.protocol == "lab" and lab.minutes == 60.0
    assert BridgeRtConfig().protocol == BridgeProtocol.QUICK.value
    assert TOY.protocol == "custom"
    assert PerfConfig(bridge_minutes=60.0, bridge_protocol="lab").bridge_config() == lab
    with pytest.raises(ConfigError, match=r"protocol='lap'; expected one of \['quick', 'lab'\]"):
        PerfConfig(bridge_minutes=60.0, bridge_protocol="lap")
    with pytest.raises(ConfigError, match=r"\['max_breaths'\] are set by the 'lab' protocol"):
        BridgeRtConfig.for_protocol("lab", minutes=60.0, max_breaths=30)
    with pytest.raises(ConfigError, match="minutes=10 leaves"):  # the lab's warm-ups + exploration
        PerfConfig(bridge_minutes=10.0, bridge_protocol="lab")


def test_perf_without_bridge_minutes_skips_it(tmp_path) -> None:
    assert PerfConfig().bridge_minutes == 0


def test_too_short_bridge_session_is_refused_before_any_work(tmp_path, capsys) -> None:
    with pytest.raises(ConfigError, match="bridge_minutes=1"):
        PerfConfig(bridge_minutes=1.0)
    with pytest.raises(ConfigError, match="speed"):
        BridgeRtConfig(speed=0.0)
    with pytest.raises(ConfigError, match=r"gc='never'.*'automatic', 'freeze'"):
        BridgeRtConfig(gc="never")
    code = bench_main(["perf", "--bridge-minutes", "1", "--out", str(tmp_path / "x")])
    assert code == 2
    assert "bridge_minutes=1" in capsys.readouterr().err
    assert not (tmp_path / "x").exists()
