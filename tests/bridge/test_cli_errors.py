"""Bad input gets a clear error and the right exit status; the documented commands are whole
(every variable they use set, every job they start stopped)."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import textwrap
import tomllib
from pathlib import Path

import pytest

import bridge.cli.main as cli
from bridge.config import check_out_dir, config_warnings, example_config_text, parse_config
from bridge.errors import BridgeConfigError
from bridge.proposals import ProposalWorker
from drivers.cart import CartConfig
from drivers.exosuit.rating import RATED_FORCE_N

pytestmark = pytest.mark.timeout(120)

ROOT = Path(__file__).resolve().parents[2]
README = (ROOT / "README.md").read_text(encoding="utf-8")
#: The README and the reference pages under docs/ (not the results, a record of past runs).
GUIDES = ["README.md", *sorted(f"docs/{p.name}" for p in (ROOT / "docs").glob("*.md")
                                if not p.name.startswith("results"))]
DOCS = "\n".join((ROOT / name).read_text(encoding="utf-8") for name in GUIDES)
PROTOCOL = (ROOT / "drivers" / "PROTOCOL.md").read_text(encoding="utf-8")
EXAMPLE = example_config_text()


def _config(tmp_path: Path, *, out_dir: Path | None = None, max_force_n: float | None = None) -> Path:
    text = EXAMPLE
    if out_dir is not None:
        text = text.replace('out_dir = "sessions"', f"out_dir = {str(out_dir)!r}", 1)
    if max_force_n is not None:
        text = text.replace("max_force_n = 250.0", f"max_force_n = {max_force_n}", 1)
    path = tmp_path / "session.toml"
    path.write_text(text, encoding="utf-8")
    return path


def _one_error_line(err: str, prefix: str) -> str:
    assert "Traceback" not in err
    lines = [line for line in err.splitlines() if line.strip() and ": warning: " not in line]
    assert len(lines) == 1 and lines[0].startswith(prefix), err
    return lines[0]


# --- out_dir / --out naming a file -----------------------------------------------------------


def test_out_dir_that_is_a_file_is_refused_by_config_check(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    blocker = tmp_path / "results"
    blocker.write_text("not a directory")
    assert cli.main(["config", "check", "--samples", "0", str(_config(tmp_path, out_dir=blocker))]) == 1
    line = _one_error_line(capsys.readouterr().err, "hilbo config check: invalid config:")
    assert f"session.out_dir = {str(blocker)!r}: expected a directory" in line and "is a file" in line


@pytest.mark.parametrize("via", ["config", "--out"])
def test_run_with_out_dir_a_file_is_rc_1_before_anything_starts(
    via: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    blocker = tmp_path / "results"
    blocker.write_text("x")
    if via == "config":
        argv = ["run", "--no-view", str(_config(tmp_path, out_dir=blocker))]
    else:
        argv = ["run", "--no-view", "--out", str(blocker / "sub"), str(_config(tmp_path))]
    assert cli.main(argv) == 1
    line = _one_error_line(capsys.readouterr().err, "hilbo run: error:")
    assert ("--out" if via == "--out" else "session.out_dir") in line and str(blocker) in line


def test_sim_out_naming_a_file_is_rc_1(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    blocker = tmp_path / "f"
    blocker.write_text("x")
    assert cli.main(["sim", "--engine", "core", "--minutes", "20", "--out", str(blocker)]) == 1
    assert "--out" in _one_error_line(capsys.readouterr().err, "hilbo sim: error:")


@pytest.mark.parametrize("engine", ["core", "bridge"])
def test_a_sim_too_short_for_the_protocol_is_a_usage_error_before_anything_starts(
        tmp_path: Path, engine: str, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "out"
    assert cli.main(["sim", "--engine", engine, "--minutes", "5", "--out", str(out)]) == 2
    line = _one_error_line(capsys.readouterr().err, "hilbo sim: error: --minutes 5: ")
    assert "leaves 0.0 min for optimisation" in line and not out.exists()


@pytest.mark.parametrize("argv, message", [
    (["sim", "--minutes", "-5"], "argument --minutes: expected minutes in (0, 600], got '-5'"),
    (["sim", "--seed", "-1"], "argument --seed: expected an integer >= 0, got '-1'"),
])
def test_sim_option_values_are_usage_errors_naming_the_option(
        argv: list[str], message: str, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        cli.main(argv)
    assert exc.value.code == 2 and message in capsys.readouterr().err


@pytest.mark.parametrize("argv, usage", [
    (["sim", "--bogus"], "usage: hilbo sim "),
    (["config", "check", "x.toml", "--bogus"], "usage: hilbo config check "),
    (["--bogus", "sim"], "usage: hilbo "),
])
def test_an_unknown_option_shows_the_usage_of_the_command_it_was_given_to(
        argv: list[str], usage: str, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        cli.main(argv)
    err = capsys.readouterr().err
    assert exc.value.code == 2 and err.startswith(usage) and "unrecognized arguments: --bogus" in err


def test_check_out_dir_accepts_new_and_existing_directories(tmp_path: Path) -> None:
    assert check_out_dir(tmp_path) == tmp_path
    assert check_out_dir(tmp_path / "a" / "b") == tmp_path / "a" / "b"
    (tmp_path / "file").write_text("")
    with pytest.raises(BridgeConfigError, match=r"its parent .* is not a directory"):
        check_out_dir(tmp_path / "file" / "sub")


# --- a force limit above the rated force -----------------------------------------------------


def test_rated_force_matches_the_virtual_device() -> None:
    from virtual_hw.exosuit import DeviceLimits

    assert RATED_FORCE_N == DeviceLimits().max_force_n == 600.0


def test_max_force_above_the_rating_is_refused_by_config_check(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert cli.main(["config", "check", "--samples", "0", str(_config(tmp_path, max_force_n=2500.0))]) == 1
    line = _one_error_line(capsys.readouterr().err, "hilbo config check: invalid config:")
    assert "limits.max_force_n = 2500 N is above the exosuit's rated force, limits.rated_force_n = " \
           "600 N" in line and "set [limits] rated_force_n" in line


def test_max_force_up_to_the_rating_loads_without_a_warning(tmp_path: Path) -> None:
    cfg = parse_config(_config(tmp_path, max_force_n=600.0).read_text(), source="t")
    assert config_warnings(cfg) == [] and cfg.limits.default.max_force_n == 600.0


@pytest.mark.parametrize("rated, hip_max, ok", [
    (900.0, None, True),  # a device rated higher: the lab says so
    (700.0, None, False),
    (900.0, 950.0, False),  # every actuator's limit too
])
def test_the_rating_is_the_labs_to_raise_and_bounds_every_actuator(
        tmp_path: Path, rated: float, hip_max: float | None, ok: bool) -> None:
    text = _config(tmp_path, max_force_n=800.0).read_text()
    text = text.replace("rated_force_n = 600.0", f"rated_force_n = {rated}", 1)
    if hip_max is not None:
        hip = f"[limits.actuators.hip]\nmax_force_n = {hip_max}"
        text = text.replace("# [limits.actuators.ankle]", hip, 1)
    if ok:
        assert parse_config(text, source="t").limits.default.max_force_n == 800.0
    else:
        with pytest.raises(BridgeConfigError, match=rf"max_force_n = {hip_max or 800:g} N is above .*"
                                                     rf"limits.rated_force_n = {rated:g} N"):
            parse_config(text, source="t")


def test_max_force_above_the_rating_stops_hilbo_run_before_anything_starts(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert cli.main(["run", "--no-view", str(_config(tmp_path, max_force_n=2500.0))]) == 1
    _one_error_line(capsys.readouterr().err, "hilbo run: error:")
    assert not (tmp_path / "sessions").exists()


# --- exit status and --version ---------------------------------------------------------------


def test_version(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        cli.main(["--version"])
    assert exc.value.code == 0
    assert re.fullmatch(r"hilbo \S+( \(not installed\))?\n", capsys.readouterr().out)


def test_usage_errors_are_2_runtime_errors_are_1(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        cli.main(["run", "--no-such-option", "x.toml"])
    assert exc.value.code == 2
    capsys.readouterr()
    assert cli.main(["run", str(tmp_path / "missing.toml")]) == 1  # a config that is not there
    _one_error_line(capsys.readouterr().err, "hilbo run: error: cannot read config")
    bad = tmp_path / "bad.toml"
    bad.write_text(EXAMPLE.replace("[can]\n", "[can]\nbitrat = 1\n", 1))
    assert cli.main(["config", "check", str(bad)]) == 1
    _one_error_line(capsys.readouterr().err, "hilbo config check: invalid config:")


def test_an_os_error_at_run_time_is_rc_1_without_traceback(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    def unwritable(args: object) -> int:
        raise PermissionError(13, "Permission denied", "/sessions/s01.mcap")

    monkeypatch.setattr(cli, "_cmd_vcan_setup", unwritable)
    assert cli.main(["vcan-setup"]) == 1
    assert "/sessions/s01.mcap" in _one_error_line(capsys.readouterr().err, "hilbo vcan-setup: error:")


# --- SIGINT to the process group: the proposal worker stays quiet -----------------------------


async def test_the_worker_ignores_sigint_and_keeps_answering(capfd: pytest.CaptureFixture[str]) -> None:
    async with ProposalWorker() as worker:
        pid = await worker.worker_pid()
        os.kill(pid, signal.SIGINT)
        assert await worker.worker_pid() == pid and worker.lost is None
    assert "KeyboardInterrupt" not in capfd.readouterr().err


_SESSION = textwrap.dedent("""
    import asyncio, signal, sys
    from bridge.proposals import ProposalWorker

    async def main():
        stop = asyncio.Event()
        asyncio.get_running_loop().add_signal_handler(signal.SIGINT, stop.set)  # as bridge/run.py
        async with ProposalWorker() as worker:
            await worker.worker_pid()
            print("ready", flush=True)
            await stop.wait()
            await worker.worker_pid()  # the worker survived the group's SIGINT
        print("stopped cleanly", flush=True)

    asyncio.run(main())
""")


def test_sigint_to_the_process_group_gives_no_traceback(tmp_path: Path) -> None:
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    proc = subprocess.Popen([sys.executable, "-c", _SESSION], cwd=ROOT, env=env, text=True,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, start_new_session=True)
    try:
        assert proc.stdout is not None
        assert proc.stdout.readline() == "ready\n"
        os.killpg(proc.pid, signal.SIGINT)  # what Ctrl-C in a terminal does
        out, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0 and out == "stopped cleanly\n"
    assert "Traceback" not in err and "KeyboardInterrupt" not in err, err


# --- the README's and the example's commands --------------------------------------------------


def _code_blocks(text: str) -> list[str]:
    return re.findall(r"^```[a-z]*\n(.*?)^```", text, flags=re.S | re.M)


def test_every_readme_block_sets_the_variables_it_uses() -> None:
    for block in _code_blocks(DOCS):
        for var in set(re.findall(r"\$([A-Z_]+)\b", block)):
            assert re.search(rf"^{var}=", block, flags=re.M), f"${var} used but not set in:\n{block}"


def test_every_readme_block_that_starts_jobs_kills_them_all() -> None:
    for block in _code_blocks(DOCS):
        commands = re.sub(r"\\\n", " ", block).splitlines()
        jobs = sum(1 for c in commands if re.search(r"&\s*(#.*)?$", c))
        kills = [c for c in commands if c.startswith("kill ")]
        if jobs and kills:
            assert kills == ["kill " + " ".join(f"%{k}" for k in range(1, jobs + 1))
                             + kills[0].split("%" + str(jobs), 1)[1]], block
        elif jobs and "hilbo run" in block:
            raise AssertionError(f"{jobs} background job(s) never killed in:\n{block}")


def test_the_heartbeat_advice_names_the_device_watchdog() -> None:
    advice = DOCS[DOCS.index("Two watchdogs guard the link"):][:900]
    assert "--heartbeat-timeout" in advice and "heartbeat_lost" in advice
    assert "[watchdog] device_heartbeat_timeout_ms" in advice


def test_the_example_config_names_the_same_vcan_setup_as_the_readme() -> None:
    assert "scripts/vcan-setup.sh" not in EXAMPLE
    assert "hilbo vcan-setup | sudo sh" in EXAMPLE and "hilbo vcan-setup | sudo sh" in README


def test_the_example_cart_alternatives_parse_when_followed() -> None:
    cart = tomllib.loads(EXAMPLE)["cart"]
    assert CartConfig.from_dict(cart).transport == "tcp"
    serial = re.search(r'^# For a serial cart:.*port = ("[^"]+")\s+baudrate = (\d+)\n#.*delete (.*)$',
                       EXAMPLE, flags=re.M)
    assert serial is not None
    options = {k: v for k, v in cart["options"].items() if k not in ("host", "connect_timeout_s")}
    assert "host" in serial.group(3) and "connect_timeout_s" in serial.group(3)
    options.update(port=tomllib.loads(f"p = {serial.group(1)}")["p"], baudrate=int(serial.group(2)))
    assert CartConfig.from_dict({**cart, "transport": "serial", "options": options}).transport == "serial"
    replay = re.search(r'^# For a recorded file:.*path = ("[^"]+")\s+speed = ("[^"]+")\n#.*delete (.*)$',
                       EXAMPLE, flags=re.M)
    assert replay is not None
    for key in ("host", "port", "connect_timeout_s", "backoff"):
        assert key in replay.group(3)
    options = {"path": tomllib.loads(f"p = {replay.group(1)}")["p"],
               "speed": tomllib.loads(f"s = {replay.group(2)}")["s"]}
    assert CartConfig.from_dict({**cart, "transport": "replay", "options": options}).transport == "replay"


@pytest.mark.parametrize("name", [*GUIDES, "drivers/PROTOCOL.md", "bridge/config_example.toml"])
def test_every_documented_can_remote_server_binds_loopback(name: str) -> None:
    text = (ROOT / name).read_text(encoding="utf-8")
    commands = re.findall(r"python -m can_remote[^`\n)]*", text)
    if name in ("docs/simulation.md", "docs/exosuit-bus.md", "drivers/PROTOCOL.md"):
        assert commands, f"{name} no longer shows how to start the server"
    for command in commands:
        assert "--host 127.0.0.1" in command, command
    for channel in re.findall(r"ws://[^/\"`\s]+", text):
        assert channel.startswith("ws://127.0.0.1:"), channel
    # 0.0.0.0 only ever appears as the thing not to do.
    for m in re.finditer(r"0\.0\.0\.0", text):
        around = text[max(0, m.start() - 120): m.end() + 120]
        assert re.search(r"never|default|would", around), around


def test_the_process_sim_starts_can_remote_on_loopback() -> None:
    source = (ROOT / "bridge" / "sim" / "processes.py").read_text(encoding="utf-8")
    assert '"--host", _LOOPBACK' in source and '_LOOPBACK = "127.0.0.1"' in source


# --- a bus-error policy that is not implemented ----------------------------------------------


def test_bus_error_pause_loads_but_is_warned_as_not_implemented(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    text = EXAMPLE.replace('bus_error = "stop"', 'bus_error = "pause"', 1)
    assert 'bus_error = "pause"' in text
    path = tmp_path / "session.toml"
    path.write_text(text, encoding="utf-8")
    assert cli.main(["config", "check", "--samples", "0", str(path)]) == 0
    out, err = capsys.readouterr()
    assert "hilbo config check: warning: watchdog.bus_error = 'pause' is not implemented yet: a CAN " \
           "bus failure commands assistance-off and ends the session" in err
    # What the session will do, not what was asked for.
    assert "bus error -> assistance-off and the session ends" in out
    # The example (and the default) asks for what is implemented: no warning.
    assert config_warnings(parse_config(EXAMPLE, source="t")) == []
