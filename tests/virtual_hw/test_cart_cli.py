"""``hilbo virtual-cart`` as a separate process, and its argument handling."""

from __future__ import annotations

import argparse
import asyncio
import math
import signal
import sys
from pathlib import Path

import pytest

from drivers.cart import (
    Backoff,
    BreathStream,
    CartConfig,
    HbrLineParser,
    SerialOptions,
    TcpOptions,
    TcpTransport,
)
from hilbo_core.presets import hip_6d
from virtual_hw.cli_cart import add_virtual_cart_parser, main, run_from_args
from virtual_hw.faults import FaultSpec
from virtual_hw.wearer import SimulatedWearer
from virtual_hw.wearer_realistic import RealisticWearer

pytestmark = pytest.mark.timeout(90)

ROOT = Path(__file__).resolve().parents[2]
START_TIMEOUT_S = 40.0  # interpreter + numpy/scipy import on a loaded 2-core machine
STOP_TIMEOUT_S = 10.0


async def start_cart(*args: str) -> tuple[asyncio.subprocess.Process, list[str]]:
    proc = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "virtual_hw.cli_cart", *args,
        cwd=ROOT, stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE,
    )
    assert proc.stdout is not None
    try:
        line = await asyncio.wait_for(proc.stdout.readline(), timeout=START_TIMEOUT_S)
    except TimeoutError:
        proc.kill()
        await proc.wait()
        raise
    if not line:
        _, err = await proc.communicate()
        pytest.fail(f"virtual cart exited before printing its address: {err.decode()}")
    return proc, line.decode().split()


async def stop(proc: asyncio.subprocess.Process) -> tuple[int, str]:
    if proc.returncode is None:
        proc.send_signal(signal.SIGTERM)
    try:
        _, err = await asyncio.wait_for(proc.communicate(), timeout=STOP_TIMEOUT_S)
    except TimeoutError:
        proc.kill()
        await proc.wait()
        raise
    assert proc.returncode is not None
    return proc.returncode, err.decode()


@pytest.mark.slow
async def test_tcp_cart_process_serves_the_wearers_breaths_and_stops_on_sigterm() -> None:
    proc, address = await start_cart("--transport", "tcp", "--port", "0", "--speed", "30", "--seed", "3")
    try:
        assert address[:2] == ["tcp", "127.0.0.1"]
        port = int(address[2])
        transport = TcpTransport(TcpOptions(host="127.0.0.1", port=port, backoff=Backoff(max_attempts=1)))
        got = []
        async with BreathStream(transport, HbrLineParser()) as stream:
            async with asyncio.timeout(20.0):
                while len(got) < 6:
                    got.append(await anext(stream))
    finally:
        code, err = await stop(proc)
    assert code == 0, err
    # The same subject as in-process: the breaths are a run of the seeded wearer's breaths
    # (those before the client connected went to nobody); the default wearer is the realistic one.
    reference = RealisticWearer(hip_6d(), 3).breaths_until(got[-1].t_s)
    first = reference.index(got[0])
    assert reference[first:first + len(got)] == got


@pytest.mark.slow
async def test_serial_cart_process_at_max_speed_waits_for_its_reader_and_ends_after_minutes() -> None:
    proc, address = await start_cart("--transport", "serial", "--speed", "max", "--minutes", "2",
                                     "--seed", "4", "--wearer", "legacy", "--fault", "duplicate@30x2")
    try:
        assert address[0] == "serial" and Path(address[1]).is_symlink()
        config = CartConfig(transport="serial", options=SerialOptions(port=address[1],
                                                                      backoff=Backoff(max_attempts=1)))
        expected = SimulatedWearer(hip_6d(), 4).breaths_until(120.0)
        got = []
        async with BreathStream.from_config(config) as stream:
            async with asyncio.timeout(20.0):
                while len(got) < len(expected):
                    got.append(await anext(stream))
            assert stream.counters == {"duplicate": 2}
        assert got == expected  # nothing served before the reader attached
        code, err = await asyncio.wait_for(stop(proc), timeout=STOP_TIMEOUT_S)
    finally:
        if proc.returncode is None:
            await stop(proc)
    assert code == 0, err
    assert not Path(address[1]).exists()


def test_subcommand_registers_with_its_runner() -> None:
    parser = argparse.ArgumentParser(prog="hilbo")
    add_virtual_cart_parser(parser.add_subparsers(dest="command"))
    args = parser.parse_args(["virtual-cart", "--speed", "max", "--fault", "stall@10+5",
                              "--fault", "nan@20", "--transport", "serial", "--format", "csv"])
    assert args.func is run_from_args
    assert math.isinf(args.speed) and args.transport == "serial" and args.format == "csv"
    assert args.fault == [FaultSpec("stall", 10.0, duration_s=5.0), FaultSpec("nan", 20.0, count=1)]
    assert args.minutes is None and args.can_interface is None


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--fault", "disconnect@10"], "lasts a while"),
        (["--fault", "teleport@10"], "no fault 'teleport'"),
        (["--speed", "fast"], "speed"),
        (["--minutes", "0"], "minutes"),
    ],
)
def test_bad_options_exit_2_naming_the_problem(
    argv: list[str], message: str, capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(SystemExit) as exc:
        main(argv)
    assert exc.value.code == 2
    assert message in capsys.readouterr().err


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--transport", "udp"], "UDP needs the receiver's port"),
        (["--speed", "max", "--epoch", "1700000000"], "epoch"),
        (["--can-interface", "virtual"], "--can-interface and --can-channel go together"),
    ],
)
def test_bad_combinations_exit_2_before_serving(
    argv: list[str], message: str, capsys: pytest.CaptureFixture[str]
) -> None:
    assert main(argv) == 2
    captured = capsys.readouterr()
    assert message in captured.err and captured.out == ""
