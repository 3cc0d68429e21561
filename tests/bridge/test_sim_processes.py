"""The bridge, the virtual exosuit and the virtual cart as separate processes.

* ``hilbo sim --processes`` (bridge/sim/processes.py): the bridge in this process, the two
  devices as children, over SocketCAN vcan0 (marked ``vcan``: natively, or inside user-mode
  Linux, tests/conftest.py) and over python-can-remote on this host.
* ``hilbo run`` with the example config (``hilbo config example``) as a process of its own, the
  devices started with the commands docs/simulation.md gives.

Did the cart's wearer feel the profile the exosuit applied? The simulated wearer is
deterministic from its seed, and its breath times and noise do not depend on the assistance, so
an unassisted wearer of the same seed yields, breath for breath, what the cart would have
reported without the exosuit: the ratio of the two is the assistance's effect on the metabolic
rate, free of noise.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import re
import signal
import socket
import subprocess
import sys
import time
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import pytest

from bridge.cli.main import main
from bridge.config import example_config_text
from bridge.errors import DeviceProcessError
from bridge.log.reader import LogContents, read_log
from bridge.runtime import RuntimeSettings
from bridge.sim.processes import ChildProcess, device_processes, run_process_sim, vcan_problem
from bridge.sim.virtual import VirtualSimConfig
from hilbo_core.presets import hip_6d
from virtual_hw.wearer_realistic import RealisticWearer

pytestmark = pytest.mark.timeout(240)

ROOT = Path(__file__).resolve().parents[2]
# Slower than in one process: four processes share two cores (one inside user-mode Linux), and a
# proposal's computing time is walking time at the new speed.
SPEED = 30.0
BUSES = [pytest.param("vcan", marks=pytest.mark.vcan), "remote"]
#: Transfers of a push that got no ack ([can] push_retries, the default in the sims and the config).
PUSH_ATTEMPTS = RuntimeSettings.push_retries + 1


def small(**kw: Any) -> VirtualSimConfig:
    opts: dict[str, Any] = {"minutes": 5.0, "seed": 2, "n_explore": 3, "max_breaths": 10,
                            "warmup_s": 20.0, "speed": SPEED, "feedback_hz": 50.0}
    opts.update(kw)
    return VirtualSimConfig(**opts)


def needs(bus: str) -> None:
    if bus == "remote":
        pytest.importorskip("can_remote", reason="python-can-remote (a dev extra) is not installed")


def _alive(pid: int) -> bool:
    try:
        state = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0]
    except (OSError, IndexError):
        return False
    return state != "Z"


def _children(pid: int) -> list[int]:
    found = []
    for stat in Path("/proc").glob("[0-9]*/stat"):
        with contextlib.suppress(OSError, IndexError, ValueError):
            if int(stat.read_text().rsplit(")", 1)[1].split()[1]) == pid:
                found.append(int(stat.parent.name))
    return found


def assert_the_wearer_felt_the_applied_profiles(log: LogContents, seed: int) -> None:
    """Unassisted until the first push; then, within every evaluation, the metabolic rate relaxes
    towards the cost of that setting (first order, Kim et al. 2019 §II.C) and away from unassisted."""
    breaths = log.data("/breaths")
    reference = RealisticWearer(hip_6d(), seed)  # the default wearer of the cart process
    unassisted = {b.t_s: b.watts for b in reference.breaths_until(breaths[-1]["t_s"])}
    # Same subject, breath for breath (the cart skipped those before it started).
    assert all(b["t_s"] in unassisted for b in breaths)
    ratio = [(b["t_s"], b["watts"] / unassisted[b["t_s"]]) for b in breaths]
    first_push = log.data("/profiles_sent")[0]["t_s"]  # the last breath before it
    warm_up = [r for t, r in ratio if t <= first_push]
    assert warm_up and all(abs(r - 1.0) < 1e-9 for r in warm_up)
    t0 = breaths[0]["t_s"]  # evaluation times are seconds since the first breath
    checked, skipped, targets = 0, 0, []
    for obs, after_pause in zip(log.data("/observations"), _remeasured_after_a_pause(log), strict=True):
        inside = [r for t, r in ratio if t0 + obs["t_start"] < t <= t0 + obs["t_end"] + 1e-9]
        if len(inside) < 6:
            continue  # stopped early: the switch may not be behind its first breaths yet
        if after_pause:
            # The pause's assistance-off and the resumed assistance reach the cart process's
            # wearer through its bus listener, which dates each switch by its own clock when it
            # handles the frame: on a loaded host at 20-30x real time a second of wall-clock lag
            # is half a minute of the wearer's, into the re-measured setting (seen once inside
            # user-mode Linux beside burners: the rate relaxed towards unassisted there). That the
            # device assisted throughout is checked from the bridge's own log instead
            # (assert_the_device_assisted_every_evaluation).
            skipped += 1
            continue
        target = reference.true_cost_w(obs["params"]) / reference.baseline_cost_w
        mid, last = inside[len(inside) // 2], inside[-1]
        assert abs(last - target) <= abs(mid - target) + 1e-3, (obs["index"], mid, last, target)
        checked += 1
        targets.append(target)
    assert checked >= 1 and checked + skipped >= 2
    # Assisted breaths, not a cart that ignored the suit (its ratio stays 1 to 1e-9, as in the
    # warm-up): a tenth of the way to the reduction of the best setting measured at least. The
    # realistic wearer's settings save 0-25 % with τ 30-60 s, a short evaluation ends a time
    # constant or less after its switch, and the devices' clocks run 20-30x the wall's, so a loaded
    # host's slow push is seconds of the wearer's time: inside user-mode Linux beside a burner
    # the evaluation of the best setting got 24.6 % of the way.
    assert min(targets) < 1.0
    assert min(r for _, r in ratio) < 1.0 - 0.1 * (1.0 - min(targets))


def _remeasured_after_a_pause(log: LogContents) -> list[bool]:
    """For each evaluation, whether it measures a setting a pause abandoned (an
    ``evaluation_cancelled`` event written since the previous evaluation)."""
    cancels = [m.log_time_ns for m in log.topic("/events") if m.record.kind == "evaluation_cancelled"]
    out, previous = [], -1
    for m in log.topic("/observations"):
        out.append(any(previous < t < m.log_time_ns for t in cancels))
        previous = m.log_time_ns
    return out


def assert_the_device_assisted_every_evaluation(log: LogContents) -> None:
    """Every evaluation was measured while the device assisted: among the statuses in force
    during its breaths (the last one logged before its first breath, and those logged until its
    last), every actuator said ``assist`` at least once. (Not every status: a fault reported
    just before the last breath pauses the session one watchdog period later, and that breath
    may already have ended the evaluation.)"""
    breath_log_ns = sorted((m.record.t_s, m.log_time_ns) for m in log.topic("/breaths"))
    statuses = [(m.log_time_ns, m.record) for m in log.topic("/device_status")]
    actuators = {r.actuator for _, r in statuses}
    t0 = breath_log_ns[0][0]
    for obs in log.data("/observations"):
        window = [ns for t, ns in breath_log_ns if t0 + obs["t_start"] < t <= t0 + obs["t_end"] + 1e-9]
        if not window:
            continue
        before = {}
        for ns, r in statuses:
            if ns < window[0]:
                before[r.actuator] = r  # the status in force when the first breath came
        during = [r for ns, r in statuses if window[0] <= ns <= window[-1]]
        assisted = {r.actuator for r in [*before.values(), *during] if r.mode == "assist"}
        assert assisted == actuators, (obs["index"], {r.actuator: r.mode for r in before.values()},
                                       [(r.actuator, r.mode) for r in during])


def assert_log_and_summary_agree(log: LogContents, s: dict[str, Any]) -> None:
    assert log.complete
    assert [o["params"] for o in log.data("/observations")] == [e["params"] for e in s["evaluations"]]
    assert len(log.data("/breaths")) == s["n_breaths"]
    acks = log.data("/acks")
    failed = [a for a in acks if not a["accepted"]]
    # A push may fail on a busy host, and then the session must take the protocol's failure
    # path: pause (assistance off), re-measure the setting, resume by the policy. Two ways were
    # seen inside user-mode Linux beside a CPU burner: no ack in 4 attempts of 0.25 s (the event
    # loop stalled for up to 200 ms), and "busy" nacks after a 690 ms stall had let the device's
    # heartbeat watchdog (DEVICE_HEARTBEAT_TIMEOUT_S) latch heartbeat_lost: a device with a
    # latched fault refuses every commit until the fault is cleared (PROTOCOL.md). The device
    # refused nothing else (no bad CRC, missing segment or out-of-limits table).
    assert all((a["reason"] == "none" and "no ack" in a["error"]) or a["reason"] == "busy"
               for a in failed), failed
    assert len(acks) - len(failed) >= s["n_evaluations"]
    events = log.data("/events")
    kinds = [e["kind"] for e in events]
    assert kinds[0] == "session_start" and "session_end" in kinds and "bus_error" not in kinds
    push_pauses = [e for e in events if e["kind"] == "pause" and "profile push failed" in e["message"]]
    assert len(push_pauses) == len(failed)


def assert_the_device_acked_every_push(log: LogContents, device_stats: dict[str, int]) -> None:
    # A retried push (its ack came after the bridge's timeout) is acked once per transfer; a
    # push that failed for want of an ack sent PUSH_ATTEMPTS transfers, each acked at most once.
    acks = log.data("/acks")
    accepted = [a for a in acks if a["accepted"]]
    most = sum(a["attempts"] for a in accepted) + PUSH_ATTEMPTS * (len(acks) - len(accepted))
    # Everything needed to tell which side miscounted, should this ever fail (it did once in
    # user-mode Linux beside a CPU burner, 18 accepted against 17 device acks, unexplained).
    assert len(accepted) <= device_stats["acks"] <= most, (
        device_stats, [(a["version"], a["accepted"], a.get("attempts"), a.get("reason")) for a in acks])


# --- hilbo sim --processes ------------------------------------------------------------------------


@pytest.mark.slow
@pytest.mark.parametrize("bus", BUSES)
def test_three_processes_log_summary_and_wearer_agree(tmp_path: Path, bus: str) -> None:
    needs(bus)
    # The session's time is walking time: every second from a stop decision to the
    # next setting's first breath counts. Inside user-mode Linux at 30x real time the proposal
    # worker process's first reply (its imports: 10-20 s of wall time there) alone was 90 % of a
    # 12-minute session, so there the proposals run in a thread.
    s = asyncio.run(run_process_sim(
        small(minutes=12.0, proposal_worker="thread" if bus == "vcan" else "process"), tmp_path, bus=bus))
    on_disk = json.loads((tmp_path / "summary.json").read_text())
    assert on_disk == json.loads(json.dumps(s))
    assert s["n_evaluations"] > 3
    log = read_log(tmp_path / "session.mcap")
    assert_log_and_summary_agree(log, s)
    # The simulation's truth, from the same subject the cart process simulated.
    assert s["true_cost_of_best"] >= s["true_optimum"]["cost_w"] - 1e-9
    assert s["regret_w"] == pytest.approx(s["true_cost_of_best"] - s["true_optimum"]["cost_w"])
    assert s["subject"]["seed"] == 2
    procs = s["sim"]["processes"]
    assert procs["bus"] == bus
    assert procs["can"]["interface"] == {"vcan": "socketcan", "remote": "remote"}[bus]
    children = procs["children"]
    assert sorted(children) == sorted(["virtual-exosuit", "virtual-cart"]
                                      + (["can-remote"] if bus == "remote" else []))
    assert children["virtual-exosuit"]["exit_status"] == 0 == children["virtual-cart"]["exit_status"]
    assert not any(_alive(c["pid"]) for c in children.values())
    assert_the_device_acked_every_push(log, procs["exosuit"]["stats"])
    assert_the_wearer_felt_the_applied_profiles(log, seed=2)
    assert_the_device_assisted_every_evaluation(log)


@pytest.mark.slow
def test_a_device_that_dies_at_start_is_reported_with_its_stderr(tmp_path: Path) -> None:
    needs("remote")
    with pytest.raises(DeviceProcessError, match="virtual-exosuit exited before it was ready") as err:
        asyncio.run(run_process_sim(small(exosuit_faults=("sparks@1",)), tmp_path, bus="remote"))
    assert "exit status 2" in str(err.value) and "no fault 'sparks'" in str(err.value)
    assert not (tmp_path / "summary.json").exists()


@pytest.mark.slow
async def test_every_child_is_stopped_when_the_block_fails(tmp_path: Path) -> None:
    needs("remote")
    pids: list[int] = []
    with pytest.raises(RuntimeError, match="boom"):
        async with device_processes(small(), bus="remote", log_dir=tmp_path) as devices:
            pids = [c.pid for c in devices.children if c.pid is not None]
            assert devices.exited() is None
            raise RuntimeError("boom")
    assert len(pids) == 3
    assert not any(_alive(pid) for pid in pids)
    assert [c.returncode for c in devices.children][1:] == [0, 0]  # the devices stop cleanly


@pytest.mark.slow
def test_ctrl_c_ends_the_session_and_stops_the_devices(tmp_path: Path) -> None:
    needs("remote")
    proc = subprocess.Popen(
        [sys.executable, "-m", "bridge.cli.main", "sim", "--processes", "--bus", "remote", "--minutes", "60",
         "--speed", "1", "--out", str(tmp_path)],
        cwd=ROOT, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )
    try:
        deadline = time.monotonic() + 90.0
        while not ((tmp_path / "session.mcap").exists() and len(_children(proc.pid)) >= 3):
            assert proc.poll() is None, proc.communicate()
            assert time.monotonic() < deadline, "the session did not start"
            time.sleep(0.1)  # real processes starting: bounded poll
        children = _children(proc.pid)
        proc.send_signal(signal.SIGINT)  # what Ctrl-C sends hilbo (the children are not in its group)
        out, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    assert proc.returncode == 130, err  # interrupted, as the README says; the files are written
    assert out.splitlines() == [str(tmp_path / "summary.json"), str(tmp_path / "session.mcap")]
    assert not any(_alive(pid) for pid in children)
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["sim"]["processes"]["bus"] == "remote" and summary["end_reason"] == "interrupted"
    kinds = [e["kind"] for e in read_log(tmp_path / "session.mcap").data("/events")]
    assert "session_end" in kinds


def test_bus_options_are_checked_before_anything_starts(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["sim", "--bus", "remote"]) == 2
    assert "--bus goes with --processes" in capsys.readouterr().err
    assert main(["sim", "--processes", "--engine", "core"]) == 2
    assert "--engine core" in capsys.readouterr().err
    if vcan_problem() is not None:
        assert main(["sim", "--processes", "--bus", "vcan"]) == 1  # this machine, not the usage
        assert "--bus vcan: " in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["run", "unused.toml", "--auto-resume", "-1"])
    assert "expected seconds >= 0" in capsys.readouterr().err


# --- hilbo run with the example config --------------------------------------------------------------


def example_for_a_test(tmp_path: Path, *, cart_port: int, can_url: str | None) -> Path:
    """The example config with a short protocol (and, for python-can-remote, that [can])."""
    text = example_config_text()
    changes = {"out_dir": f'"{tmp_path / "sessions"}"', "warmup_s": "20.0", "n_explore": "2",
               "max_breaths": "8", "budget_min": "2.0", "port": str(cart_port),
               # watchdog and heartbeats cross processes on a loaded 2-core host (or inside UML)
               "device_heartbeat_timeout_ms": "1000.0"}
    if can_url is not None:
        changes.update(interface='"remote"', channel=f'"{can_url}"')
    # The protocol keys the example leaves to the rule's defaults (commented out) are set here.
    text = re.sub(r"(?m)^# (protocol|n_explore|pause_between_bouts) = ", r"\1 = ", text)
    for key, value in changes.items():
        text, n = re.subn(rf"(?m)^{key}\s*=\s*[^#\n]*", f"{key} = {value} ", text)
        assert n == 1, key
    path = tmp_path / "my_session.toml"
    path.write_text(text)
    return path


def events_so_far(directory: Path) -> list[str]:
    """The events of the newest session log in ``directory`` (for a session that hung)."""
    logs = sorted(directory.glob("*.mcap"), key=lambda p: p.stat().st_mtime)
    return [f"{e['kind']}: {e['message']}" for e in read_log(logs[-1]).data("/events")] if logs else []


def _free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return int(probe.getsockname()[1])


@contextlib.asynccontextmanager
async def started(*children: ChildProcess) -> AsyncIterator[None]:
    try:
        for child in children:
            await child.start()
        yield
    finally:
        for child in reversed(children):
            await child.stop()


@pytest.mark.slow
@pytest.mark.parametrize("bus", BUSES)
async def test_hilbo_run_with_the_example_config_drives_the_device_processes(
    tmp_path: Path, bus: str,
) -> None:
    needs(bus)
    hilbo = [sys.executable, "-m", "bridge.cli.main"]  # = the hilbo console script
    cart_port = _free_port()
    servers: list[ChildProcess] = []
    if bus == "remote":
        can_port = _free_port()
        url = f"ws://127.0.0.1:{can_port}/"
        servers.append(ChildProcess("can-remote", [
            sys.executable, "-m", "can_remote", "--interface", "virtual", "--channel", "demo",
            "--host", "127.0.0.1", "--port", str(can_port)], tmp_path / "can-remote.log"))
        can = ["--interface", "remote", "--channel", url]
    else:
        url = None
        can = ["--interface", "socketcan", "--channel", "vcan0"]
    config = example_for_a_test(tmp_path, cart_port=cart_port, can_url=url)
    assert main(["config", "check", str(config)]) == 0
    clock = ["--speed", "20", "--epoch", repr(time.time())]
    exosuit = ChildProcess("virtual-exosuit", [*hilbo, "virtual-exosuit", *can, *clock, "--seed", "1",
                                               "--feedback-hz", "50", "--heartbeat-timeout", "0.5"],
                           tmp_path / "exosuit.log")
    cart = ChildProcess("virtual-cart", [
        *hilbo, "virtual-cart", "--transport", "tcp", "--host", "127.0.0.1", "--port", str(cart_port),
        *clock, "--seed", "1", "--can-interface", can[1], "--can-channel", can[3]], tmp_path / "cart.log")
    async with started(*servers):
        if servers:
            await servers[0].wait_listening("127.0.0.1", can_port)
        async with started(exosuit, cart):
            assert json.loads(await exosuit.first_line())["event"] == "ready"
            assert await cart.first_line() == f"tcp 127.0.0.1 {cart_port}"
            run = await asyncio.create_subprocess_exec(
                *hilbo, "run", str(config), "--no-view", "--auto-resume", "0", cwd=ROOT,
                stdin=asyncio.subprocess.DEVNULL, stdout=asyncio.subprocess.PIPE,
                stderr=asyncio.subprocess.PIPE)
            try:
                async with asyncio.timeout(150):
                    out, err = await run.communicate()
            except TimeoutError:
                pytest.fail(f"hilbo run did not end within 150 s: {events_so_far(tmp_path / 'sessions')}")
            finally:
                if run.returncode is None:
                    run.kill()
                    await run.wait()
            assert (exosuit.returncode, cart.returncode) == (None, None)
    assert run.returncode == 0, err.decode()
    log_path, summary_path = (Path(line) for line in out.decode().split())
    assert log_path.parent == tmp_path / "sessions"
    s = json.loads(summary_path.read_text())
    assert s["n_evaluations"] > 2
    # The end says why the session ended, what it did, walked minutes included, and the
    # recommended setting with its 95 % interval.
    from bridge.outcome import SessionEnd

    why = SessionEnd(s["end_reason"]).text
    assert f"session ended: {why}; {s['n_evaluations']} evaluations" in err.decode()
    assert f"{s['walking']['session_s'] / 60:.1f} min walked" in err.decode()
    assert "recommended setting: " in err.decode() and "(95 % CI " in err.decode()
    log = read_log(log_path)
    assert_log_and_summary_agree(log, s)
    kinds = [e["kind"] for e in log.data("/events")]
    # The example config walks the fast protocol: one walk, no pause between the bouts (a busy
    # machine may add pauses for a lost heartbeat, which --auto-resume ends).
    assert "bout_pause" not in kinds and "auto_resume_exhausted" not in kinds
    stopped = exosuit.json_record("stopped")
    assert exosuit.returncode == 0 and stopped is not None
    assert_the_device_acked_every_push(log, stopped["stats"])
    assert_the_wearer_felt_the_applied_profiles(log, seed=1)
    assert_the_device_assisted_every_evaluation(log)
