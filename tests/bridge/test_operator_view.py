"""The terminal operator view: faults by name, the expected end, best = opt.best()."""

from __future__ import annotations

import asyncio
import contextlib
import io
import logging
import sys
from types import SimpleNamespace

import pytest
from rich.console import Console

from bridge.operator_view import describe_faults, render_status, run_operator_view
from bridge.runtime import SessionStatus
from drivers.exosuit import DeviceFault


def text_of(st: SessionStatus, now_unix_s: float = 1_800_000_000.0) -> str:
    console = Console(record=True, width=160, color_system=None, file=io.StringIO())
    console.print(render_status(st, now_unix_s=now_unix_s))
    return console.export_text()


def row(text: str, label: str) -> str:
    line = next(ln for ln in text.splitlines() if f" {label} " in ln)
    return " ".join(line.strip("│ ").split()[len(label.split()):])


def test_faults_are_named_with_what_clears_them_not_bits() -> None:
    lost = int(DeviceFault.HEARTBEAT_LOST)
    st = SessionStatus(device=f"faults [{lost}, {lost}]", device_faults={0: lost, 1: lost})
    text = text_of(st)
    assert "[16, 16]" not in text
    assert "heartbeat_lost on actuators 0, 1: cleared by the bridge once the bridge heartbeat" in text


def test_describe_faults_groups_by_fault_and_names_unknown_bits() -> None:
    bits = DeviceFault.OVERTEMPERATURE | DeviceFault.EMERGENCY_STOP
    lines = describe_faults({1: int(bits), 0: int(DeviceFault.OVERTEMPERATURE)})
    assert lines == [
        "overtemperature on actuators 0, 1: cleared by the bridge once motor and driver have cooled "
        "below their limit",
        "emergency_stop on actuator 1: cleared by the bridge, when the operator resumes, once the "
        "emergency stop is released",
    ]
    assert describe_faults({0: 0}) == []
    assert describe_faults({0: 1 << 9}) == ["bit9 on actuator 0: not defined by the protocol"]


def test_a_lost_device_still_reads_lost() -> None:
    st = SessionStatus(device="LOST", device_faults={0: int(DeviceFault.HEARTBEAT_LOST)})
    assert row(text_of(st), "device") == "LOST"


def test_the_expected_end_is_shown_in_walking_time_else_from_the_budget() -> None:
    now = 1_800_000_000.0
    st = SessionStatus(budget_s=1800.0, budget_used_s=600.0)
    assert row(text_of(st, now), "expected end") == "budget 30.0 min (20.0 min left)"
    assert row(text_of(SessionStatus(), now), "expected end") == "—"
    st = SessionStatus(expected_end_s=3600.0, breath_time_s=2700.0, budget_s=1800.0)
    assert row(text_of(st, now), "expected end") == "after 60.0 min of walking (15.0 min left)"


def test_best_so_far_is_what_opt_best_returns() -> None:
    # opt.best() is the GP's choice, not the lowest raw mean; the view shows what it is given.
    st = SessionStatus(best_mean_w=312.4, best_sd_w=5.0, best_params={"t_p": 30.0, "F_p": 150.0})
    assert row(text_of(st), "best so far") == "312 ± 10 W (95 %) at t_p = 30.0, F_p = 150.0"
    assert row(text_of(SessionStatus(best_mean_w=300.0)), "best so far") == "300 W"
    assert row(text_of(SessionStatus()), "best so far") == "—"


@pytest.mark.parametrize("device", ["ok", "unknown"])
def test_a_healthy_device_shows_its_state(device: str) -> None:
    assert row(text_of(SessionStatus(device=device)), "device") == device


async def test_log_lines_are_printed_above_the_live_view_not_past_it(
        monkeypatch: pytest.MonkeyPatch) -> None:
    # A handler made before the view, as `logging.basicConfig` in `hilbo` makes it, holds the
    # terminal: written past Rich, its lines left stale frames (and a stale state) on the screen.
    terminal = io.StringIO()
    monkeypatch.setattr(sys, "stderr", terminal)
    handler = logging.StreamHandler(terminal)
    root = logging.getLogger()
    root.addHandler(handler)
    screen = io.StringIO()
    console = Console(file=screen, force_terminal=True, width=100, color_system=None)
    session = SimpleNamespace(status=SessionStatus(), command=lambda cmd: None)
    try:
        view = asyncio.create_task(run_operator_view(session, console=console))  # type: ignore[arg-type]
        await asyncio.sleep(0)  # the view is drawn and waits for its next refresh
        logging.getLogger("bridge.runtime").warning("event loop stalled 84.2 ms")
        view.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await view
    finally:
        root.removeHandler(handler)
    assert "event loop stalled 84.2 ms" in screen.getvalue()  # through Rich, above the frame
    assert terminal.getvalue() == ""
    assert handler.stream is terminal  # given back when the view ends


def test_parameters_show_with_units_and_without_exponents() -> None:
    st = SessionStatus(params={"t_on": 1.66e-11, "F_p": 152.37, "F_r": 0.254},
                       units={"t_on": "%GC", "F_p": "N", "F_r": ""})
    assert row(text_of(st), "setting") == "t_on = 0.00 %GC, F_p = 152.4 N, F_r = 0.25"


def test_an_ended_session_says_so_and_why() -> None:
    from bridge.outcome import SessionEnd

    st = SessionStatus(supervisor=SimpleNamespace(describe=lambda: "running"))  # type: ignore[arg-type]
    assert row(text_of(st), "state") == "running"
    st.ended = SessionEnd.BUDGET
    assert row(text_of(st), "state").startswith("ended: the optimisation bout's budget")


def test_bracketed_texts_reach_the_screen_as_they_are() -> None:
    # A pause cause names config tables in brackets; Rich markup would eat them.
    from bridge.outcome import SessionEnd

    pause = "paused: a proposal outside the limits; check [limits] against [space]"
    st = SessionStatus(supervisor=SimpleNamespace(describe=lambda: pause),  # type: ignore[arg-type]
                       last_decision="[bold]reject[/bold]")
    text = text_of(st)
    assert row(text, "state") == pause and row(text, "decision") == "[bold]reject[/bold]"
    st.ended = SessionEnd.RESUME_BUDGET
    assert "[watchdog] max_auto_resumes" in row(text_of(st), "state")


async def test_the_last_frame_is_drawn_when_the_view_ends() -> None:
    from bridge.outcome import SessionEnd

    screen = io.StringIO()
    console = Console(file=screen, force_terminal=True, width=140, color_system=None)
    session = SimpleNamespace(status=SessionStatus(), command=lambda cmd: None)
    view = asyncio.create_task(run_operator_view(session, console=console, refresh_s=60.0))  # type: ignore[arg-type]
    await asyncio.sleep(0)
    session.status.ended = SessionEnd.OPERATOR_STOP  # the session ends, then the view is cancelled
    view.cancel()
    with contextlib.suppress(asyncio.CancelledError):
        await view
    assert "ended: stopped by the operator" in screen.getvalue()
