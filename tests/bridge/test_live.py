"""The live view (bridge/live.py): a Foxglove WebSocket client subscribes and decodes what the
session log writes.

The client below speaks just enough of the Foxglove WebSocket protocol (RFC 6455 framing over a
blocking socket; subprotocol ``foxglove.sdk.v1``, the one foxglove-sdk 0.30 accepts): it reads
``serverInfo`` and ``advertise``, sends ``subscribe`` and decodes binary ``messageData`` frames
(opcode 1, uint32 subscription id, uint64 log time in ns, payload; all little-endian).
Every socket operation has a timeout; every server is stopped in a ``finally``.
"""

from __future__ import annotations

import asyncio
import base64
import contextlib
import json
import logging
import os
import re
import socket
import struct
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from mcap.reader import make_reader

from bridge.config import LiveConfig, parse_config
from bridge.errors import BridgeConfigError
from bridge.live import LiveError, LiveServer
from bridge.log import CHANNELS, SessionLog, Topic
from hilbo_core.types import BreathRecord

SUBPROTOCOL = "foxglove.sdk.v1"
TIMEOUT_S = 10.0


class FoxgloveClient:
    """A minimal Foxglove WebSocket client (text and binary frames, ping/pong, no fragmentation)."""

    def __init__(self, url: str, *, subprotocol: str = SUBPROTOCOL, timeout_s: float = TIMEOUT_S) -> None:
        m = re.fullmatch(r"ws://([^:/]+):(\d+)", url)
        assert m is not None, url
        self.sock = socket.create_connection((m[1], int(m[2])), timeout=timeout_s)
        self._buf = b""
        key = base64.b64encode(os.urandom(16)).decode()
        self.sock.sendall(
            (f"GET / HTTP/1.1\r\nHost: {m[1]}:{m[2]}\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
             f"Sec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n"
             f"Sec-WebSocket-Protocol: {subprotocol}\r\n\r\n").encode())
        while b"\r\n\r\n" not in self._buf:
            self._fill()
        head, self._buf = self._buf.split(b"\r\n\r\n", 1)
        self.status_line = head.split(b"\r\n", 1)[0].decode()
        self.headers = head.decode().lower()
        self.channels: dict[int, dict[str, Any]] = {}
        self._sub_ids: dict[int, int] = {}

    def close(self) -> None:
        """Close politely (a close frame first): the SDK logs a reset connection as an error."""
        with contextlib.suppress(OSError, EOFError):
            self._send(8, struct.pack(">H", 1000))
            self.sock.settimeout(0.5)
            end = time.monotonic() + 2.0
            while time.monotonic() < end:  # until the server's close frame (EOFError)
                self.frame()
        self.sock.close()

    # framing ---------------------------------------------------------------------------
    def _fill(self) -> None:
        data = self.sock.recv(65536)
        if not data:
            raise EOFError("the server closed the connection")
        self._buf += data

    def _take(self, n: int) -> bytes:
        while len(self._buf) < n:
            self._fill()
        out, self._buf = self._buf[:n], self._buf[n:]
        return out

    def _send(self, opcode: int, payload: bytes) -> None:
        mask = os.urandom(4)
        n = len(payload)
        head = bytes([0x80 | opcode])
        if n < 126:
            head += bytes([0x80 | n])
        elif n < 65536:
            head += bytes([0x80 | 126]) + struct.pack(">H", n)
        else:
            head += bytes([0x80 | 127]) + struct.pack(">Q", n)
        self.sock.sendall(head + mask + bytes(b ^ mask[i % 4] for i, b in enumerate(payload)))

    def frame(self) -> tuple[int, bytes]:
        """The next data frame (opcode 1 text or 2 binary); answers pings."""
        while True:
            b0, b1 = self._take(2)
            n = b1 & 0x7F
            if n == 126:
                n = struct.unpack(">H", self._take(2))[0]
            elif n == 127:
                n = struct.unpack(">Q", self._take(8))[0]
            payload = self._take(n)  # server frames are never masked
            opcode = b0 & 0x0F
            if opcode == 9:
                self._send(10, payload)
            elif opcode == 8:
                raise EOFError("close frame")
            elif opcode in (1, 2):
                return opcode, payload

    # protocol --------------------------------------------------------------------------
    def send_json(self, message: dict[str, Any]) -> None:
        self._send(1, json.dumps(message).encode())

    def next_event(self) -> tuple[str, Any]:
        """("serverInfo"/"advertise"/... , JSON) or ("message", (topic, log_time_ns, payload))."""
        opcode, payload = self.frame()
        if opcode == 1:
            msg = json.loads(payload)
            if msg["op"] == "advertise":
                self.channels.update({c["id"]: c for c in msg["channels"]})
            return msg["op"], msg
        assert payload[0] == 1, f"binary opcode {payload[0]}"
        sub_id, log_time = struct.unpack("<IQ", payload[1:13])
        topic = self.channels[self._sub_ids[sub_id]]["topic"]
        return "message", (topic, log_time, payload[13:])

    def subscribe(self, channel_id: int) -> int:
        sub_id = len(self._sub_ids) + 1
        self._sub_ids[sub_id] = channel_id
        self.send_json({"op": "subscribe", "subscriptions": [{"id": sub_id, "channelId": channel_id}]})
        return sub_id

    def unsubscribe(self, sub_id: int) -> None:
        self.send_json({"op": "unsubscribe", "subscriptionIds": [sub_id]})

    def channel_id(self, topic: str) -> int | None:
        return next((cid for cid, c in self.channels.items() if c["topic"] == topic), None)


@contextlib.contextmanager
def client_of(live: LiveServer) -> Iterator[FoxgloveClient]:
    assert live.url is not None
    client = FoxgloveClient(live.url)
    try:
        yield client
    finally:
        client.close()


def _our_threads() -> set[threading.Thread]:
    # The SDK's Rust runtime calls into Python (its log output) from threads Python then lists
    # as _DummyThread forever; they are the SDK's, shared by every server, not ours.
    return {t for t in threading.enumerate() if not isinstance(t, threading._DummyThread)}


def _until(client: FoxgloveClient, want: str, publish: Any = None, deadline_s: float = TIMEOUT_S) -> Any:
    """Read events until one of kind ``want``; ``publish()`` is called between reads (the
    server may see the subscription after our first publish)."""
    end = time.monotonic() + deadline_s
    client.sock.settimeout(0.05)
    try:
        while time.monotonic() < end:
            if publish is not None:
                publish()
            try:
                kind, data = client.next_event()
            except TimeoutError:
                continue
            if kind == want:
                return data
    finally:
        client.sock.settimeout(TIMEOUT_S)
    raise AssertionError(f"no {want} within {deadline_s} s")


SCHEMA = CHANNELS[Topic.BREATHS].json_schema()


def test_a_client_subscribes_and_decodes_a_message() -> None:
    before = _our_threads()
    live = LiveServer(port=0)
    try:
        assert live.start() and live.port and live.port > 0
        assert live.url == f"ws://127.0.0.1:{live.port}"
        with client_of(live) as client:
            assert client.status_line == "HTTP/1.1 101 Switching Protocols"
            assert f"sec-websocket-protocol: {SUBPROTOCOL}" in client.headers
            assert client.next_event()[1]["name"] == "hilbo"  # serverInfo
            message = b'{"t_s":12.5,"vo2_ml_min":1000.0,"vco2_ml_min":800.0,"watts":345.6}'
            live.publish("/breaths", "hilbo.Breath", SCHEMA, message, 12_500_000_000)
            adv = _until(client, "advertise")
            (channel,) = adv["channels"]
            assert channel["topic"] == "/breaths" and channel["encoding"] == "json"
            assert channel["schemaName"] == "hilbo.Breath" and channel["schemaEncoding"] == "jsonschema"
            assert json.loads(channel["schema"]) == SCHEMA
            client.subscribe(channel["id"])
            topic, log_time, payload = _until(
                client, "message",
                lambda: live.publish("/breaths", "hilbo.Breath", SCHEMA, message, 12_500_000_000))
            assert (topic, log_time) == ("/breaths", 12_500_000_000)
            assert json.loads(payload) == {"t_s": 12.5, "vo2_ml_min": 1000.0, "vco2_ml_min": 800.0,
                                           "watts": 345.6}
            # A str message is sent as its UTF-8 bytes; a second topic gets its own channel.
            live.publish("/events", "foxglove.Log", {"type": "object", "properties": {}}, '{"m":"é"}', 1)
            adv = _until(client, "advertise")
            assert [c["topic"] for c in adv["channels"]] == ["/events"]
        assert live.stats.channels == 2 and not live.stats.errors
    finally:
        live.stop()
    live.stop()  # idempotent
    assert not live.running and live.url is None
    assert _our_threads() <= before


def test_the_session_log_streams_each_record_with_its_log_schema(tmp_path: Path) -> None:
    live = LiveServer(port=0)
    path = tmp_path / "s.mcap"
    clock = iter(range(1_000_000_000, 10**12, 1_000_000)).__next__
    try:
        live.start()
        with client_of(live) as client, SessionLog(path, session_id="live-test", config_json={},
                                                   flush_interval_s=None, clock_ns=clock,
                                                   live=live) as log:
            _until(client, "serverInfo")
            assert _until(client, "advertise")["channels"][0]["topic"] == "/config"
            rec = BreathRecord(t_s=30.0, vo2_ml_min=1100.0, vco2_ml_min=900.0)
            log.log_breath(rec)
            cid = None
            while cid is None:
                _until(client, "advertise")
                cid = client.channel_id("/breaths")
            client.subscribe(cid)
            topic, log_time, payload = _until(client, "message", lambda: log.log_breath(rec))
            streamed = json.loads(payload)
            assert topic == "/breaths" and streamed["t_s"] == 30.0 and streamed["watts"] == rec.watts
            advertised = client.channels[cid]
        with path.open("rb") as f:
            reader = make_reader(f)
            summary = reader.get_summary()
            assert summary is not None
            ch = next(c for c in summary.channels.values() if c.topic == "/breaths")
            schema = summary.schemas[ch.schema_id]
            logged = [(m.log_time, m.data) for _, c, m in reader.iter_messages(topics=["/breaths"])]
        # The same schema name and schema text as the file, and the same bytes and log time.
        assert advertised["schemaName"] == schema.name == "hilbo.Breath"
        assert json.loads(advertised["schema"]) == json.loads(schema.data)
        assert (log_time, payload) in logged
        assert live.stats.published == log.stats.messages and not live.stats.errors
    finally:
        live.stop()


def test_a_client_that_never_reads_does_not_slow_publishing() -> None:
    live = LiveServer(port=0, message_backlog_size=256)
    n, size = 20_000, 4096
    message = json.dumps({"x": "a" * size}).encode()
    try:
        live.start()
        with client_of(live) as client:
            client.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
            _until(client, "serverInfo")
            live.publish("/big", "hilbo.Big", {"type": "object", "properties": {}}, message, 0)
            client.subscribe(_until(client, "advertise")["channels"][0]["id"])
            time.sleep(0.2)  # let the server see the subscription (real sockets; no sim clock here)
            worst = 0.0
            t0 = time.perf_counter()
            for i in range(n):
                t = time.perf_counter()
                live.publish("/big", "hilbo.Big", {}, message, i)
                worst = max(worst, time.perf_counter() - t)
            total = time.perf_counter() - t0
        # 80 MB offered to a client reading nothing: the SDK drops the oldest, the caller waits
        # for nothing (measured here: ~0.1 s in all, < 5 ms worst call).
        assert live.stats.published == n + 1 and not live.stats.errors
        assert total < 5.0 and worst < 0.5, (total, worst)
    finally:
        live.stop()


def test_publishing_never_raises_errors_are_logged_once_and_counted(caplog) -> None:
    live = LiveServer(port=0)
    try:
        live.start()
        with caplog.at_level(logging.ERROR, logger="bridge.live"):
            for _ in range(3):
                live.publish("/bad", "hilbo.Bad", {"type": "object", "x": object()}, b"{}", 0)
        assert live.stats.errors["TypeError"] == 3 and live.stats.published == 0
        assert len([r for r in caplog.records if "live view" in r.getMessage()]) == 1
        # The topic that failed does not stop the others.
        live.publish("/ok", "hilbo.Ok", {"type": "object", "properties": {}}, b"{}", 0)
        assert live.stats.published == 1
    finally:
        live.stop()


def test_a_taken_port_leaves_the_view_off_and_the_session_unharmed(caplog) -> None:
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        live = LiveServer(port=taken.getsockname()[1])
        with caplog.at_level(logging.ERROR, logger="bridge.live"), live:
            assert not live.running and live.url is None
            assert "Address already in use" in (live.start_error or "")
            live.publish("/breaths", "hilbo.Breath", SCHEMA, b"{}", 0)  # no-op, no raise
        assert "the session goes on without it" in caplog.text


@pytest.mark.parametrize(("kwargs", "text"), [
    ({"port": 70000}, "live port=70000"), ({"port": True}, "live port=True"),
    ({"host": ""}, "live host=''"), ({"message_backlog_size": 0}, "message_backlog_size=0"),
])
def test_bad_options_are_refused(kwargs, text) -> None:
    with pytest.raises(LiveError, match=re.escape(text)):
        LiveServer(**kwargs)


# ------------------------------------------------------------------------------------ config
_CFG = """
[session]
subject = "S1"
body_mass_kg = 70
[space]
preset = "hip_6d"
[cart]
transport = "tcp"
format = "hilbo-line"
[cart.options]
host = "127.0.0.1"
port = 5050
[can]
interface = "virtual"
channel = "x"
"""


def test_the_live_table_is_off_by_default_and_typed() -> None:
    assert parse_config(_CFG).live == LiveConfig(enabled=False, host="127.0.0.1", port=8765)
    cfg = parse_config(_CFG + '[live]\nenabled = true\nport = 0\n')
    assert cfg.live == LiveConfig(enabled=True, host="127.0.0.1", port=0)
    assert cfg.to_json()["live"] == {"enabled": True, "host": "127.0.0.1", "port": 0}


@pytest.mark.parametrize(("table", "text"), [
    ("prot = 1", "unknown key live.prot = 1 (did you mean 'port'?)"),
    ("port = 65536", "live.port = 65536: expected an integer in [0, 65535]"),
    ('enabled = "yes"', "live.enabled = 'yes': expected true or false"),
])
def test_the_live_table_refuses_unknown_keys_and_bad_values(table, text) -> None:
    with pytest.raises(BridgeConfigError, match=re.escape(text)):
        parse_config(_CFG + f"[live]\n{table}\n")


# ------------------------------------------------------------------------------------ a session
@pytest.mark.slow
def test_a_simulated_session_streams_breaths_and_estimates_live(tmp_path: Path) -> None:
    from bridge.runtime import BridgeSession, Command
    from bridge.sim.virtual import VirtualSimConfig, run_virtual_sim

    seen: dict[str, list[dict[str, Any]]] = {}
    errors: list[BaseException] = []
    want = ("/breaths", "/estimator")
    stop = threading.Event()
    trace: list[Any] = []

    def watch(url: str, done: Any) -> None:
        try:
            client = FoxgloveClient(url)
            try:
                client.sock.settimeout(0.1)
                subscribed: dict[str, float] = {}
                end = time.monotonic() + 60.0
                while time.monotonic() < end and not stop.is_set():
                    # Seen here (3 of ~12 runs, machine under load, not reproduced in isolation):
                    # one of two subscribed channels delivered nothing for a whole minute while
                    # the other streamed. Subscribe again after 5 s of silence, and say so.
                    for topic, since in list(subscribed.items()):
                        if not seen.get(topic) and time.monotonic() - since > 5.0:
                            cid = client.channel_id(topic)
                            assert cid is not None
                            trace.append(f"resubscribe {topic}")
                            client.unsubscribe(max(k for k, v in client._sub_ids.items() if v == cid))
                            client.subscribe(cid)
                            subscribed[topic] = time.monotonic()
                    try:
                        kind, data = client.next_event()
                    except TimeoutError:
                        continue
                    if kind == "status":
                        trace.append(data)
                    if kind == "advertise":
                        trace.append([c["topic"] for c in data["channels"]])
                        for topic in want:
                            cid = client.channel_id(topic)
                            if cid is not None and topic not in subscribed:
                                client.subscribe(cid)
                                subscribed[topic] = time.monotonic()
                    elif kind == "message":
                        seen.setdefault(data[0], []).append(json.loads(data[2]))
                        if all(len(seen.get(t, ())) >= 3 for t in want):
                            return
            finally:
                client.close()
                done()  # seen enough (or gave up): end the session, no need to walk on
        except (OSError, EOFError, AssertionError) as err:
            errors.append(err)

    watcher: list[threading.Thread] = []
    tasks: list[asyncio.Task[None]] = []

    def on_session(session: BridgeSession) -> None:
        m = next(re.search(r"ws://\S+", e) for e in session.status.events if "live view" in e)
        assert m is not None, session.status.events
        loop = asyncio.get_running_loop()
        done = lambda: loop.call_soon_threadsafe(session.command, Command.STOP)  # noqa: E731
        t = threading.Thread(target=watch, args=(m[0], done), name="test-live-client")
        t.start()
        watcher.append(t)

        async def resume_when_healthy() -> None:
            # On a loaded machine the device watchdog may pause the session; an operator resumes.
            while True:
                await asyncio.sleep(0.05)
                if session.status.state.startswith("paused") and session.status.device == "ok":
                    session.command(Command.RESUME)

        tasks.append(loop.create_task(resume_when_healthy()))

    # Long enough not to end before the client has seen enough under load; stopped once it has.
    cfg = VirtualSimConfig(minutes=10.0, seed=2, n_explore=2, max_breaths=10, warmup_s=20.0, speed=20.0)
    try:
        summary = asyncio.run(run_virtual_sim(cfg, tmp_path, on_session=on_session,
                                              live=LiveConfig(enabled=True, port=0)))
    finally:
        stop.set()
        for t in watcher:
            t.join(timeout=TIMEOUT_S)
    counts = {k: len(v) for k, v in seen.items()}
    assert watcher and not watcher[0].is_alive() and not errors, (errors, counts, trace[:12],
                                                                    summary["n_breaths"])
    assert summary["n_breaths"] >= 3
    assert all(len(seen.get(t, ())) >= 3 for t in want), ({k: len(v) for k, v in seen.items()}, trace)
    assert all(b["watts"] > 0 for b in seen["/breaths"])
    assert all("mean_w" in e and "hi95_w" in e for e in seen["/estimator"])
