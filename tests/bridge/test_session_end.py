"""The end of a session says what the lab needs (bridge/outcome.py, bridge/runtime.py).

A replay at ``speed = "max"`` is paced by what the session takes (back-pressure), so it
measures; the session's end states its reason (never null), the recommended setting with units
and a labelled interval; a signal's stop is ``interrupted``; the operator view's last frame says
the session ended.
"""

from __future__ import annotations

import asyncio
import dataclasses
import io
import os
import re
import signal
import uuid
from pathlib import Path
from typing import Any

import msgspec
import numpy as np
import pytest

from bridge.config import HilboConfig, parse_config
from bridge.log.reader import read_log
from bridge.log.resume import ResumeError
from bridge.operator_view import render_status
from bridge.run import RunResult, run_session
from bridge.runtime import BridgeSession
from bridge.sim.virtual import VirtualSimConfig, sim_config_text
from drivers.cart import CartConfig, encode_line
from drivers.exosuit import CanBusConfig
from hilbo_core.types import BreathRecord
from virtual_hw.clock import ScaledClock
from virtual_hw.exosuit import SUIT_JOINTS, VirtualExosuit

pytestmark = pytest.mark.timeout(120)

SIM = VirtualSimConfig(minutes=10.0, seed=3, warmup_s=30.0, n_explore=2, max_breaths=10)


def write_recording(path: Path, n: int, *, interval_s: float = 3.0, seed: int = 0) -> Path:
    """A hilbo-line recording of ``n`` breaths at about 400 W (Brockway) with 5 % noise."""
    rng = np.random.default_rng(seed)
    lines = [encode_line(BreathRecord(t_s=interval_s * (i + 1),
                                      vo2_ml_min=1200.0 * (1 + 0.05 * rng.standard_normal()),
                                      vco2_ml_min=1000.0 * (1 + 0.05 * rng.standard_normal())), i)
             for i in range(n)]
    path.write_bytes(b"".join(lines))
    return path


def replay_config(tmp: Path, recording: Path) -> tuple[HilboConfig, str]:
    cfg = parse_config(sim_config_text(SIM, tmp), source="<test>")
    channel = f"hilbo-end-{uuid.uuid4().hex[:8]}"
    cfg = dataclasses.replace(
        cfg,
        cart=CartConfig.from_dict({"transport": "replay", "format": "hilbo-line",
                                   "options": {"path": str(recording), "speed": "max"}}),
        can=msgspec.structs.replace(cfg.can, bus=CanBusConfig("virtual", channel)))
    return cfg, channel


def run_replay(tmp: Path, n_breaths: int, *, on_session: Any = None, auto_resume_s: float = 0.0,
               resume: Path | None = None, name: str = "s",
               operator_view: bool = False) -> tuple[RunResult, BridgeSession]:
    cfg, channel = replay_config(tmp, write_recording(tmp / "breaths.hbr", n_breaths))
    sessions: list[BridgeSession] = []

    def hook(session: BridgeSession) -> None:
        sessions.append(session)
        if on_session is not None:
            on_session(session)

    async def run() -> RunResult:
        async with VirtualExosuit(CanBusConfig("virtual", channel), ScaledClock(1.0),
                                  joints=SUIT_JOINTS[SIM.preset], seed=1):
            return await run_session(cfg, log_path=tmp / f"{name}.mcap", auto_resume_s=auto_resume_s,
                                     resume=resume,
                                     operator_view=operator_view,
                                     n_actuators=len(SUIT_JOINTS[SIM.preset]),
                                     on_session=hook)

    return asyncio.run(run()), sessions[0]


def test_a_replay_at_max_speed_is_paced_by_the_session_and_measures(tmp_path: Path) -> None:
    # 100 breaths (5 minutes) of a 10-minute protocol: the file ends first.
    result, session = run_replay(tmp_path, 100)
    s = result.summary
    # Every breath reached the protocol: none arrived before the proposal worker answered.
    events = read_log(result.log_path).records("/events")
    assert "breaths_before_start" not in [e.kind for e in events]
    assert s["n_breaths"] == 100
    assert s["n_evaluations"] >= 2, s["evaluations"]
    # The file ended before the session's time: the end says so, with its reason.
    assert s["end_reason"] == "cart_ended"
    (ended,) = [e for e in events if e.kind == "cart_ended"]
    assert "before the expected end" in ended.message and "min walked" in ended.message
    (end,) = [e for e in events if e.kind == "session_end"]
    assert end.details["end_reason"] == "cart_ended"
    # The recommendation: parameters with units, an estimate with its 95 % interval, how.
    rec = s["recommendation"]
    assert rec["params"] == s["best_params"] and rec["units"]["F_p"]
    lo, hi = rec["ci95_w"]
    assert lo < rec["mean_w"] < hi
    assert rec["method"] == "global" and rec["n_evaluations"] == s["n_evaluations"]
    # The operator view's last frame says the session ended, not "running".
    assert session.status.state.startswith("ended: the cart's data ended")
    assert "running" not in str(render_status(session.status).renderable.renderables[0].columns[1]._cells)


def test_a_signal_stops_the_session_as_interrupted(tmp_path: Path) -> None:
    def on_session(session: BridgeSession) -> None:
        def fire(rec: Any) -> None:
            if session.supervisor.assisting and session.end_reason is None:
                os.kill(os.getpid(), signal.SIGINT)  # Ctrl-C: the handler of run_session
        session.breath_listeners.append(fire)

    result, session = run_replay(tmp_path, 400, on_session=on_session)
    assert result.summary["end_reason"] == "interrupted"
    assert result.summary["n_breaths"] < 400
    # The stop's cause is the signal, not the operator (in the log too, unless a pause had
    # turned assistance off before it).
    assert session.supervisor.has_cause("interrupted (Ctrl-C or SIGTERM)")
    offs = [e.message for e in read_log(result.log_path).records("/events") if e.kind == "assistance_off"]
    assert not any("operator stop" in m for m in offs)


def test_the_logged_config_is_the_one_the_session_ran_with(tmp_path: Path) -> None:
    # The file says auto_resume_s = 0.0; the command line (--auto-resume) says 0.5.
    result, _ = run_replay(tmp_path, 40, auto_resume_s=0.5)
    (config,) = read_log(result.log_path).records("/config")
    assert config.config["watchdog"]["auto_resume_s"] == 0.5


def test_resuming_a_finished_session_is_refused_clearly(tmp_path: Path) -> None:
    # 260 breaths (13 minutes) of a 10-minute session: it ends by its walking time.
    result, _ = run_replay(tmp_path, 260)
    assert result.summary["end_reason"] == "session"
    with pytest.raises(ResumeError, match=r"is a finished session .*nothing to resume.*hilbo validate"):
        run_replay(tmp_path, 40, resume=result.log_path, name="again")
    assert not (tmp_path / "again.mcap").exists()


@pytest.mark.parametrize("operator_view", [False, True])
def test_without_a_terminal_the_session_prints_a_line_per_evaluation(
        tmp_path: Path, operator_view: bool, monkeypatch: pytest.MonkeyPatch,
        capsys: pytest.CaptureFixture[str]) -> None:
    # Output to a file or a pipe and no keyboard: with or without --no-view, a run is never
    # silent (the live view has nowhere to draw and no keys to read).
    monkeypatch.setattr("sys.stdin", io.StringIO(""))
    result, _ = run_replay(tmp_path, 100, operator_view=operator_view)
    err = capsys.readouterr().err
    n_evals = result.summary["n_evaluations"]
    assert n_evals >= 2
    assert len(re.findall(r"^\[ *\d+\.\d min \| [^\]]+\] eval \d+", err, flags=re.M)) == n_evals, err
    # Each line's prefix has the state's name only (a pause's whole reason is its own line).
    prefixes = re.findall(r"^\[ *\d+\.\d min \| ([^\]]+)\]", err, flags=re.M)
    assert prefixes and all(":" not in p for p in prefixes), set(prefixes)


def test_a_log_already_continued_is_not_resumed_again(tmp_path: Path) -> None:
    # A stops early (its cart ends); B continues it. Resuming A again would fork the session.
    first, _ = run_replay(tmp_path, 60, name="a")
    assert first.summary["end_reason"] == "cart_ended"
    second, _ = run_replay(tmp_path, 40, resume=first.log_path, name="b")
    # The resumed run's summary counts its own evaluations and the session's.
    s1, s2 = first.summary, second.summary
    assert s2["n_evaluations_session"] == s1["n_evaluations"] + s2["n_evaluations"] > s2["n_evaluations"]
    with pytest.raises(ResumeError, match=r"a\.mcap was already continued by .*b\.mcap.*--resume .*b\.mcap"):
        run_replay(tmp_path, 40, resume=first.log_path, name="c")
    assert not (tmp_path / "c.mcap").exists()
    # The copy `hilbo log recover` makes of A is the same point of the same session.
    copy = tmp_path / "a.recovered.mcap"
    copy.write_bytes(first.log_path.read_bytes())
    with pytest.raises(ResumeError, match="already continued by"):
        run_replay(tmp_path, 40, resume=copy, name="d")
