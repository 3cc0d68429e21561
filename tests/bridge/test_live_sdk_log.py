"""The SDK's own log lines (a client refused at the handshake) reach the live server's
``on_sdk_log`` (the session log's events), not the terminal the operator view is drawn on."""

from __future__ import annotations

import base64
import os
import socket
import threading

import pytest

from bridge.live import LiveServer

pytestmark = pytest.mark.timeout(60)


def unknown_protocol_handshake(port: int) -> bytes:
    """An upgrade request offering only a subprotocol neither name of the Foxglove protocol
    (``foxglove.websocket.v1`` is let in by the live view's front); the server's answer."""
    key = base64.b64encode(os.urandom(16)).decode()
    with socket.create_connection(("127.0.0.1", port), timeout=20) as s:
        s.sendall((f"GET / HTTP/1.1\r\nHost: 127.0.0.1\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
                   f"Sec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n"
                   "Sec-WebSocket-Protocol: foxglove.websocket.v0\r\n\r\n").encode())
        return s.recv(4096)


def test_a_refused_client_is_a_logged_line_not_terminal_output(capfd: pytest.CaptureFixture[str]) -> None:
    lines: list[tuple[str, int]] = []
    got = threading.Event()

    def on_sdk_log(text: str, level: int) -> None:
        lines.append((text, level))
        got.set()

    live = LiveServer(port=0)
    live.on_sdk_log = on_sdk_log
    with live:
        assert live.running
        answer = unknown_protocol_handshake(live.port or 0)
        assert answer.startswith(b"HTTP/1.1 400")  # refused by the SDK, through the front
        assert got.wait(20.0), "the SDK's line did not arrive"  # generous: the SDK's thread
    assert any("handshake failed" in text for text, _ in lines)
    assert "handshake failed" not in capfd.readouterr().err
    assert sum(n for k, n in live.stats.errors.items() if k.startswith("sdk_")) >= 1
