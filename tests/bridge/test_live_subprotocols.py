"""The live view's front (bridge/live_front.py): clients of either Foxglove subprotocol name
connect through it to the SDK's server, a client of neither is refused, and the front is bounded
and leaves no thread behind. The client is test_live.py's (a socket with timeouts)."""

from __future__ import annotations

import contextlib
import json
import logging
import socket
import time
from collections.abc import Iterator

import pytest
from test_live import SCHEMA, FoxgloveClient, _our_threads, _until

from bridge.live import LiveServer
from bridge.live_front import SubprotocolFront, rewrite_request, rewrite_response

LEGACY = "foxglove.websocket.v1"
SDK = "foxglove.sdk.v1"
MESSAGE = b'{"t_s":1.0,"vo2_ml_min":1000.0,"vco2_ml_min":800.0,"watts":345.6}'


@contextlib.contextmanager
def live_server() -> Iterator[LiveServer]:
    live = LiveServer(port=0)
    try:
        assert live.start()
        yield live
    finally:
        live.stop()


@contextlib.contextmanager
def client(url: str, subprotocol: str) -> Iterator[FoxgloveClient]:
    c = FoxgloveClient(url, subprotocol=subprotocol)
    try:
        yield c
    finally:
        c.close()


def _header(client: FoxgloveClient, name: str) -> list[str]:
    return [line.split(":", 1)[1].strip() for line in client.headers.split("\r\n")
            if line.split(":", 1)[0] == name]


@pytest.mark.parametrize("offer", [LEGACY, SDK, f"{LEGACY}, {SDK}"])
def test_clients_of_either_name_get_the_advertisement_and_a_message(offer: str) -> None:
    before = _our_threads()
    with live_server() as live, client(live.url or "", offer) as c:
        assert c.status_line == "HTTP/1.1 101 Switching Protocols"
        # Answered with the name the client offered (the SDK's when it offered both).
        assert _header(c, "sec-websocket-protocol") == [LEGACY if offer == LEGACY else SDK]
        kind, info = c.next_event()
        assert kind == "serverInfo" and info["name"] == "hilbo"
        live.publish("/breaths", "hilbo.Breath", SCHEMA, MESSAGE, 7)
        (channel,) = _until(c, "advertise")["channels"]
        assert channel["topic"] == "/breaths" and channel["schemaName"] == "hilbo.Breath"
        c.subscribe(channel["id"])
        topic, log_time, payload = _until(
            c, "message", lambda: live.publish("/breaths", "hilbo.Breath", SCHEMA, MESSAGE, 7))
        assert (topic, log_time, json.loads(payload)["watts"]) == ("/breaths", 7, 345.6)
        assert live.translated == (1 if offer == LEGACY else 0)
    assert not live.stats.errors
    assert _our_threads() <= before  # the front's thread ended with the server


@pytest.mark.parametrize("offer", ["foxglove.websocket.v2", "", "chat, superchat"])
def test_a_client_of_neither_name_is_refused_by_the_sdk(offer: str) -> None:
    with live_server() as live:
        c = FoxgloveClient(live.url or "", subprotocol=offer)
        try:
            assert c.status_line.startswith("HTTP/1.1 400"), c.status_line
            assert not _header(c, "sec-websocket-protocol")
        finally:
            c.sock.close()
        assert live.translated == 0
        # The refusal ended that connection only: the next client connects.
        with client(live.url or "", LEGACY) as ok:
            assert ok.status_line == "HTTP/1.1 101 Switching Protocols"


def test_the_handshake_rewrite_touches_the_subprotocol_header_only() -> None:
    head = (b"GET / HTTP/1.1\r\nHost: 127.0.0.1:8765\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
            b"Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\nSec-WebSocket-Version: 13\r\n"
            b"sec-websocket-protocol: foxglove.websocket.v1\r\n"
            b"Sec-WebSocket-Extensions: permessage-deflate")
    out, answer_as = rewrite_request(head)
    assert answer_as == LEGACY
    assert out == head.replace(b"sec-websocket-protocol: foxglove.websocket.v1\r\n", b"") \
        + b"\r\nSec-WebSocket-Protocol: foxglove.sdk.v1"
    # Offered in two headers, or together with the SDK's name: as it is.
    two = head.replace(b"Sec-WebSocket-Version: 13", b"Sec-WebSocket-Protocol: x.v1")
    assert rewrite_request(two)[1] == LEGACY and b"x.v1" not in rewrite_request(two)[0]
    both = head.replace(b"foxglove.websocket.v1", b"foxglove.websocket.v1, foxglove.sdk.v1")
    assert rewrite_request(both) == (both, None)
    assert rewrite_request(head.replace(b"websocket.v1", b"websocket.v2")) == (
        head.replace(b"websocket.v1", b"websocket.v2"), None)
    answer = (b"HTTP/1.1 101 Switching Protocols\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
              b"Sec-WebSocket-Accept: s3pPLMBiTxaQ9kYGzzhZRbK+xOo=\r\n"
              b"Sec-WebSocket-Protocol: foxglove.sdk.v1")
    assert rewrite_response(answer, LEGACY) == answer.replace(b"foxglove.sdk.v1", b"foxglove.websocket.v1")
    assert rewrite_response(answer, None) == answer


def test_the_front_is_bounded_and_its_stop_ends_open_connections(caplog: pytest.LogCaptureFixture) -> None:
    before = _our_threads()
    with caplog.at_level(logging.WARNING), live_server() as live:
        errors: list[tuple[str, str]] = []
        sdk_port = live._front.target_port if live._front is not None else 0
        # Why the front exists: the SDK itself refuses the older name (if a later SDK takes
        # it, this fails and the front can go).
        direct = FoxgloveClient(f"ws://127.0.0.1:{sdk_port}", subprotocol=LEGACY)
        direct.sock.close()
        assert direct.status_line.startswith("HTTP/1.1 400"), direct.status_line
        front = SubprotocolFront("127.0.0.1", 0, sdk_port, max_clients=1, handshake_timeout_s=2.0,
                                 on_error=lambda kind, text: errors.append((kind, text)))
        front.start()
        try:
            url = f"ws://127.0.0.1:{front.port}"
            first = FoxgloveClient(url, subprotocol=LEGACY)
            assert first.status_line == "HTTP/1.1 101 Switching Protocols"
            second = FoxgloveClient(url, subprotocol=LEGACY)  # one too many
            second.sock.close()
            assert second.status_line == "HTTP/1.1 503 Service Unavailable"
            assert errors and errors[0][0] == "too_many_clients"
            # A client that never finishes its head is dropped after the handshake timeout.
            first.close()
            end = time.monotonic() + 5.0
            while front.open_connections and time.monotonic() < end:  # its close reaches the front
                time.sleep(0.01)
            assert front.open_connections == 0
            with socket.create_connection(("127.0.0.1", front.port or 0), timeout=5.0) as silent:
                silent.sendall(b"GET / HTTP/1.1\r\n")
                assert silent.recv(1024) == b""  # closed by the front
            assert any(kind == "TimeoutError" for kind, _ in errors), errors
            # Stopping the front with a client still connected ends that connection.
            third = FoxgloveClient(url, subprotocol=SDK)
            assert third.status_line == "HTTP/1.1 101 Switching Protocols"
        finally:
            front.stop()
        third.sock.settimeout(5.0)
        end = time.monotonic() + 5.0
        with pytest.raises(EOFError):
            while time.monotonic() < end:
                third.frame()
        third.sock.close()
        front.stop()  # idempotent
        assert front.port is None
    assert _our_threads() <= before
    # Every failure went to on_error; nothing to the terminal (asyncio's own error log included).
    assert not [r for r in caplog.records if r.name.startswith(("asyncio", "bridge"))], caplog.text
