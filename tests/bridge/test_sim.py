"""The whole system in one process: bridge, virtual exosuit (python-can virtual), virtual cart (TCP)."""

from __future__ import annotations

import asyncio
import json
import signal

import numpy as np
import pytest

from bridge.log.reader import read_log
from bridge.runtime import BridgeSession, Command
from bridge.safety import ProfileLimits, check_profile
from bridge.sim.virtual import VirtualSimConfig, run_virtual_sim
from hilbo_core.optimizer import HILOptimizer
from hilbo_core.presets import hip_6d
from hilbo_core.profiles import ForceProfile

pytestmark = pytest.mark.slow


def small(**kw) -> VirtualSimConfig:
    # Walking time counts every push, and at --speed max a second of wall time is 100 s
    # of it. The proposal worker's process start (2-3 s beside CPU burners) once ate 5 of 8
    # minutes; the session's clock now waits for the worker (test_session_start.py), but these
    # tests are not about the worker (test_sim_worker.py is), so they ask in a thread.
    opts = {"minutes": 8.0, "seed": 2, "n_explore": 3, "max_breaths": 10, "warmup_s": 20.0,
            "proposal_worker": "thread"}
    opts.update(kw)
    return VirtualSimConfig(**opts)


def test_session_log_and_summary_agree(tmp_path) -> None:
    s = asyncio.run(run_virtual_sim(small(), tmp_path))
    assert (tmp_path / "summary.json").exists() and (tmp_path / "session.mcap").exists()
    on_disk = json.loads((tmp_path / "summary.json").read_text())
    assert on_disk["n_evaluations"] == s["n_evaluations"] > 3
    log = read_log(tmp_path / "session.mcap")
    assert log.complete
    observations = log.data("/observations")
    assert [o["params"] for o in observations] == [e["params"] for e in s["evaluations"]]
    assert len(log.data("/breaths")) == s["n_breaths"]
    # Every profile that reached the bus is inside the configured limits and belongs to a
    # feasible setting.
    space = hip_6d()
    limits = ProfileLimits()
    sent = log.data("/profiles_sent")
    assert len(sent) >= s["n_evaluations"]
    for msg in sent:
        profiles = [ForceProfile(p["actuator"], np.array(p["gait_pct"]), np.array(p["force_n"]))
                    for p in msg["profiles"]]
        assert check_profile(profiles, limits).ok
        assert space.is_feasible(msg["params"])
    acks = log.data("/acks")
    assert all(a["accepted"] for a in acks)
    assert s["true_cost_of_best"] >= s["true_optimum"]["cost_w"] - 1e-9
    kinds = [e["kind"] for e in log.data("/events")]
    assert kinds[0] == "session_start" and "session_end" in kinds
    # The session's minutes are `[protocol] session_min`, as a lab sets them: it ends at the
    # first breath past 8 walked minutes (breaths come every 2-3.5 s).
    assert on_disk["end_reason"] == "session"
    assert 480.0 <= on_disk["walking"]["session_s"] < 480.0 + 3.5
    # At --speed max without faults the clock skipped the waits for breaths (bridge/sim/virtual.py).
    assert on_disk["sim"]["clock_skipped_s"] > 60.0
    # The event-loop stall monitor: in the summary and in the session-end record.
    loop = on_disk["loop"]
    assert loop["half_heartbeat_ms"] == 50.0 and loop["wakeups"] > 100
    assert 0.0 < loop["worst_stall_ms"] and loop["stalls_over_half_heartbeat"] >= 0
    end = next(e for e in log.data("/events") if e["kind"] == "session_end")
    assert end["details"]["loop"] == loop


def test_lost_device_heartbeat_turns_assistance_off_and_resumes(tmp_path) -> None:
    # The device stops its status for 60 sim-s (0.6 s wall at 100x) inside the exploration bout.
    def operator(session: BridgeSession) -> None:
        async def resume_when_healthy() -> None:
            while True:
                await asyncio.sleep(0.05)  # an operator's wall-time poll beside a 100x ScaledClock session
                if session.status.state.startswith("paused: device") and session.status.device == "ok":
                    session.command(Command.RESUME)
        asyncio.get_running_loop().create_task(resume_when_healthy())

    s = asyncio.run(run_virtual_sim(small(minutes=6.0, exosuit_faults=("drop-status@60+60",)),
                                    tmp_path, on_session=operator))
    events = read_log(tmp_path / "session.mcap").data("/events")
    texts = [e["message"] for e in events]
    assert any("device heartbeat lost" in t for t in texts)
    lost = next(i for i, t in enumerate(texts) if "device heartbeat lost" in t)
    assert any(e["kind"] == "assistance_off" for e in events[lost:])
    assert any(e["kind"] == "resume" for e in events[lost:])
    # The interrupted setting was re-measured; nothing was counted twice.
    indices = [e["index"] for e in s["evaluations"]]
    assert indices == list(range(len(indices)))
    assert s["n_evaluations"] >= 3


def test_nacked_profiles_are_retried(tmp_path) -> None:
    s = asyncio.run(run_virtual_sim(small(exosuit_faults=("nack-bad-crc@0x2",)), tmp_path))
    acks = read_log(tmp_path / "session.mcap").data("/acks")
    assert acks[0]["accepted"] and acks[0]["attempts"] == 3
    assert s["n_evaluations"] > 3


def test_the_log_ends_with_the_state_the_summary_recommends_from_and_an_ignored_sigint_stays(
        tmp_path) -> None:
    # A job started in the background by a non-interactive shell ignores SIGINT; the session's
    # own Ctrl-C handler must not leave Python's default behind.
    old = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        s = asyncio.run(run_virtual_sim(small(), tmp_path))
        assert signal.getsignal(signal.SIGINT) is signal.SIG_IGN
    finally:
        signal.signal(signal.SIGINT, old)
    snaps = read_log(tmp_path / "session.mcap").data("/optimizer_state")
    assert snaps[0]["reason"] == "start" and snaps[-1]["reason"] == "end"
    params, mean, var = HILOptimizer.from_json(snaps[-1]["state"]).best()
    assert params == s["best_params"]
    assert mean == pytest.approx(s["best_mean"], rel=1e-12) and var == pytest.approx(s["best_var"], rel=1e-12)
