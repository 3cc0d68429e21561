"""BreathStream and CartConfig; the contract suite: every transport x every format, same out.

The same mix of valid and bad lines goes through serial (pseudo-terminal), TCP (loopback),
UDP (loopback) and replay (a file), in both formats; each must deliver exactly the valid
breaths, in order, and count exactly the same rejects by reason.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import socket
import sys
import tty
from collections.abc import AsyncIterator, Awaitable, Callable
from pathlib import Path
from typing import Any

import pytest

from drivers.cart.csvmap import CsvMapping
from drivers.cart.line import encode_line
from drivers.cart.net import TcpOptions, UdpOptions, UdpTransport
from drivers.cart.reasons import RejectReason
from drivers.cart.registry import TRANSPORTS, make_transport, register_transport
from drivers.cart.replay import ReplayOptions, ReplayTransport
from drivers.cart.stream import BreathStream, CartConfig, CartFormat
from drivers.cart.transport import TransportHooks
from drivers.cart.validate import PhysioLimits
from drivers.errors import DriverConfigError
from hilbo_core.types import BreathRecord

pytestmark = pytest.mark.timeout(20)

VALID = [BreathRecord(5.0 + 3.0 * i, 900.0 + 10 * i, 780.0 + 10 * i, None, None, 95.0 + i) for i in range(6)]


def hbr_lines() -> list[bytes]:
    v = [encode_line(r, i) for i, r in enumerate(VALID)]
    bad_crc = v[2].replace(b"*", b"0*", 1)  # a byte inserted: CRC no longer matches
    return [
        v[0],
        b"hello world\r\n",
        v[1],
        bad_crc,
        v[2],
        v[3][:20] + b"\r\n",  # truncated
        encode_line(BreathRecord(16.0, float("nan"), 800.0), 100),
        v[3],
        v[3],  # duplicate
        encode_line(BreathRecord(18.0, 900.0, 800.0, hr_bpm=400.0), 101),
        encode_line(BreathRecord(1.0, 900.0, 800.0), 102),  # out of order
        v[4],
        b"\x00\xff\x10$HB\x7f\r\n",
        v[5],
    ]


HBR_REJECTS = {
    RejectReason.GARBAGE: 2,
    RejectReason.BAD_CHECKSUM: 1,
    RejectReason.TRUNCATED: 1,
    RejectReason.NON_FINITE: 1,
    RejectReason.DUPLICATE: 1,
    RejectReason.HR_RANGE: 1,
    RejectReason.OUT_OF_ORDER: 1,
}

CSV_MAPPING = {"time_column": "t", "vo2_column": "VO2", "vco2_column": "VCO2", "hr_column": "HR"}


def csv_lines() -> list[bytes]:
    v = [f"{r.t_s!r},{r.vo2_ml_min!r},{r.vco2_ml_min!r},{r.hr_bpm!r}\r\n".encode() for r in VALID]
    return [
        b"Cart export, subject 07\r\n",  # preamble before the header
        b"t,VO2,VCO2,HR\r\n",
        v[0],
        b"hello,world,x,y\r\n",
        v[1],
        b"10.0,,800,90\r\n",  # missing VO2
        v[2],
        b"12.0,nan,800,90\r\n",
        v[3],
        v[3],
        b"18.0,900,800,400\r\n",
        b"1.0,900,800,100\r\n",
        v[4],
        b"x\r\n",
        v[5],
    ]


CSV_REJECTS = {
    RejectReason.BAD_NUMBER: 1,
    RejectReason.MISSING_FIELD: 1,
    RejectReason.NON_FINITE: 1,
    RejectReason.DUPLICATE: 1,
    RejectReason.HR_RANGE: 1,
    RejectReason.OUT_OF_ORDER: 1,
    RejectReason.FIELD_COUNT: 1,
}

Feed = Callable[[BreathStream], Awaitable[None]]


async def no_feed(stream: BreathStream) -> None:
    return None


@contextlib.asynccontextmanager
async def replay_rig(tmp_path: Path, lines: list[bytes]) -> AsyncIterator[tuple[dict[str, Any], Feed]]:
    path = tmp_path / "recording.txt"
    path.write_bytes(b"".join(lines))
    yield {"path": str(path), "speed": "max"}, no_feed


@contextlib.asynccontextmanager
async def tcp_rig(tmp_path: Path, lines: list[bytes]) -> AsyncIterator[tuple[dict[str, Any], Feed]]:
    done = asyncio.Event()

    async def handle(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        for line in lines:  # one write per line: the client sees arbitrary chunking
            writer.write(line)
            await writer.drain()
        await done.wait()
        writer.close()

    server = await asyncio.start_server(handle, "127.0.0.1", 0)
    try:
        yield {"host": "127.0.0.1", "port": server.sockets[0].getsockname()[1]}, no_feed
    finally:
        done.set()
        server.close()
        await server.wait_closed()


@contextlib.asynccontextmanager
async def udp_rig(tmp_path: Path, lines: list[bytes]) -> AsyncIterator[tuple[dict[str, Any], Feed]]:
    async def feed(stream: BreathStream) -> None:
        assert isinstance(stream.transport, UdpTransport)
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as tx:
            for line in lines:
                tx.sendto(line, stream.transport.local_address)
                await asyncio.sleep(0)  # let the reader keep up (loopback never loses, but queues)

    yield {"port": 0, "queue_size": 64}, feed


@contextlib.asynccontextmanager
async def serial_rig(tmp_path: Path, lines: list[bytes]) -> AsyncIterator[tuple[dict[str, Any], Feed]]:
    master, slave = os.openpty()
    tty.setraw(slave)

    async def feed(stream: BreathStream) -> None:
        os.write(master, b"".join(lines))

    try:
        yield {"port": os.ttyname(slave), "baudrate": 115200, "read_timeout_s": 0.05}, feed
    finally:
        os.close(master)
        os.close(slave)


RIGS = {"replay": replay_rig, "tcp": tcp_rig, "udp": udp_rig, "serial": serial_rig}
FORMATS = {
    "hilbo-line": (hbr_lines, HBR_REJECTS, None),
    "csv": (csv_lines, CSV_REJECTS, CSV_MAPPING),
}


class FakeSleep:
    def __init__(self) -> None:
        self.sleeps: list[float] = []

    async def __call__(self, delay_s: float) -> None:
        self.sleeps.append(delay_s)
        await asyncio.sleep(0)


async def take(stream: BreathStream, n: int) -> list[BreathRecord]:
    async def run() -> list[BreathRecord]:
        out: list[BreathRecord] = []
        async for record in stream:
            out.append(record)
            if len(out) == n:
                break
        return out

    return await asyncio.wait_for(run(), 10)


@pytest.mark.parametrize("fmt", sorted(FORMATS))
@pytest.mark.parametrize(
    "transport",
    [
        pytest.param(
            n, marks=pytest.mark.skipif(n == "serial" and sys.platform == "win32", reason="POSIX pty")
        )
        for n in sorted(RIGS)
    ],
)
async def test_contract_same_lines_in_same_breaths_out(transport: str, fmt: str, tmp_path: Path) -> None:
    make_lines, rejects, mapping = FORMATS[fmt]
    async with RIGS[transport](tmp_path, make_lines()) as (options, feed):
        table: dict[str, Any] = {"transport": transport, "format": fmt, "options": options}
        if mapping is not None:
            table["csv"] = mapping
        config = CartConfig.from_dict(table)
        stream = BreathStream.from_config(config, TransportHooks(sleep=FakeSleep()))
        async with stream:
            await feed(stream)
            assert await take(stream, len(VALID)) == VALID
        assert stream.counters == rejects
        assert stream.accepted == len(VALID)
        assert stream.reconnects == 0


async def test_replay_stream_is_paced_by_accepted_breaths_only(tmp_path: Path) -> None:
    path = tmp_path / "rec.hbr"
    lines = [encode_line(VALID[0], 0), encode_line(BreathRecord(1e9, 1e6, 800.0), 1)]
    lines += [encode_line(r, i + 2) for i, r in enumerate(VALID[1:3])]
    path.write_bytes(b"".join(lines))
    sleep = FakeSleep()
    now = [0.0]
    hooks = TransportHooks(sleep=sleep, clock=lambda: now[0])
    stream = BreathStream(
        ReplayTransport(ReplayOptions(str(path), speed=3.0), hooks),
        CartConfig("replay", ReplayOptions(str(path))).make_parser(),
    )
    async with stream:
        assert [r async for r in stream] == VALID[:3]
    # The absurd breath (t = 1e9) was rejected, so it never set the pace: 3 s and 6 s at 3x.
    assert sleep.sleeps == pytest.approx([1.0, 2.0])
    assert stream.counters == {RejectReason.VO2_RANGE: 1}


async def test_counters_merge_framing_and_validation(tmp_path: Path) -> None:
    path = tmp_path / "rec.hbr"
    path.write_bytes(b"x" * 100 + b"\n" + encode_line(VALID[0], 0) + b"junk\n")
    stream = BreathStream.from_config(
        CartConfig.from_dict(
            {"transport": "replay", "options": {"path": str(path), "speed": "max", "max_line_bytes": 80}}
        )
    )
    async with stream:
        assert [r async for r in stream] == [VALID[0]]
    assert stream.counters == {RejectReason.TOO_LONG: 1, RejectReason.GARBAGE: 1}
    stream.counters.clear()  # a copy: clearing it does not lose the counts
    assert sum(stream.counters.values()) == 2


def test_config_from_dict_full() -> None:
    cfg = CartConfig.from_dict(
        {
            "transport": "tcp",
            "format": "csv",
            "options": {"host": "10.0.0.5", "port": 5000, "backoff": {"max_s": 4.0, "max_attempts": 20}},
            "csv": CSV_MAPPING,
            "limits": {"hr_bpm": [30, 220]},
        }
    )
    assert isinstance(cfg.options, TcpOptions)
    assert cfg.options.backoff.max_s == 4.0 and cfg.options.backoff.max_attempts == 20
    assert cfg.format is CartFormat.CSV
    assert cfg.csv == CsvMapping.from_dict(CSV_MAPPING)
    assert cfg.limits == PhysioLimits(hr_bpm=(30.0, 220.0))
    assert (
        CartConfig.from_dict({"transport": "udp", "options": {"port": 9000}}).format is CartFormat.HILBO_LINE
    )


@pytest.mark.parametrize(
    ("table", "match"),
    [
        (
            {"transport": "tcp", "options": {"host": "h", "port": 1}, "speed": 2},
            r"unknown key cart.speed = 2; allowed keys in \[cart\]: csv, format, limits, "
            r"max_leading_rejects, options, transport",
        ),
        ({"transport": "usb"},
         r"cart.transport = 'usb': expected one of 'lsl', 'replay', 'serial', 'tcp', 'udp'"),
        ({"transport": "tpc"},
         r"cart.transport = 'tpc' \(did you mean 'tcp'\?\): expected one of 'lsl', 'replay'"),
        ({"options": {}}, "cart: missing required key 'transport'"),
        (
            {"transport": "tcp", "options": {"host": "h"}},
            r"cart.options: missing required key\(s\) \['port'\]",
        ),
        (
            {"transport": "tcp", "options": {"host": "h", "port": 1, "baud": 9600}},
            "unknown key cart.options.baud = 9600",
        ),
        ({"transport": "tcp", "options": {"host": "h", "port": 99999}}, "cart.options.port = 99999"),
        ({"transport": "replay", "options": {"path": "f", "speed": "fast"}}, "cart.options.speed = 'fast'"),
        (
            {"transport": "udp", "options": {"port": 1}, "format": "json"},
            "cart.format = 'json': expected one of 'cortex', 'cosmed', 'cosmed-csv', 'csv', 'hilbo-line'",
        ),
        ({"transport": "udp", "options": {"port": 1}, "format": "csv"}, "cart.format = 'csv' needs a"),
        (
            {"transport": "udp", "options": {"port": 1}, "csv": CSV_MAPPING},
            "cart.csv mapping given but format",
        ),
        (
            {"transport": "udp", "options": {"port": 1}, "format": "csv", "csv": {**CSV_MAPPING, "sep": ";"}},
            "unknown key cart.csv.sep = ';'",
        ),
        (
            {"transport": "udp", "options": {"port": 1}, "limits": {"vo2": [1, 2]}},
            "unknown key cart.limits.vo2 = ",
        ),
        ({"transport": "udp", "options": 5}, "cart.options = 5: expected a table"),
    ],
)
def test_config_errors_name_key_value_and_allowed(table: dict[str, Any], match: str) -> None:
    with pytest.raises(DriverConfigError, match=match):
        CartConfig.from_dict(table)


def test_config_refuses_options_of_another_transport() -> None:
    with pytest.raises(DriverConfigError, match="transport 'tcp' expects TcpOptions"):
        CartConfig("tcp", UdpOptions(port=1))


def test_registry() -> None:
    assert sorted(TRANSPORTS) == ["lsl", "replay", "serial", "tcp", "udp"]
    t = make_transport("udp", {"port": 0})
    assert isinstance(t, UdpTransport) and t.name == "udp"
    with pytest.raises(DriverConfigError, match=r"options\.port = -1"):
        make_transport("udp", {"port": -1})
    with pytest.raises(DriverConfigError, match="expects UdpOptions"):
        make_transport("udp", TcpOptions("h", 1))
    with pytest.raises(DriverConfigError, match="'udp' is already registered"):
        register_transport("udp", UdpOptions, UdpTransport)
