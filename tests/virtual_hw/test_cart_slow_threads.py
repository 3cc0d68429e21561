"""The serial reader's threads, descheduled: the harness keeps the order of events of speed 1.

pyserial reads and opens the pty in executor threads, which the VirtualClock cannot see. On a
busy PC such a thread can be late by hundreds of ms, while the cart at ``max`` speed simulates
minutes in that time. These tests make the threads late on purpose (a wall delay in the thread,
the fault being injected) and check that the reader still sees the drop when it happens and
reconnects before the session ends.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

import pytest
from serial import serialposix
from vcart_harness import run_session

from drivers.cart import serial_port
from virtual_hw.cart import LinkKind

_LATE_S = 0.3  # a descheduled thread on a loaded 2-core PC (seen: stalls of 100-225 ms)


def _late(fn: Callable[..., Any], *, on_error_only: bool = False,
          before: bool = False) -> Callable[..., Any]:
    def slow(*args: Any, **kwargs: Any) -> Any:
        if before:
            time.sleep(_LATE_S)
            return fn(*args, **kwargs)
        try:
            result = fn(*args, **kwargs)
        except OSError:
            time.sleep(_LATE_S)
            raise
        if not on_error_only:
            time.sleep(_LATE_S)
        return result

    return slow


@pytest.mark.parametrize(("owner", "name", "on_error_only"), [
    pytest.param(serial_port, "_read_available", True, id="a drop seen late by the read thread"),
    pytest.param(serial_port.SerialTransport, "_open_blocking", False, id="a slow reopen"),
])
async def test_a_late_serial_thread_still_sees_the_drop_and_reconnects_in_time(
    monkeypatch: pytest.MonkeyPatch, owner: object, name: str, on_error_only: bool,
) -> None:
    monkeypatch.setattr(owner, name, _late(getattr(owner, name), on_error_only=on_error_only))
    session = await run_session(LinkKind.SERIAL, faults=["disconnect@60+10"], end_s=150.0, seed=7)
    assert session.stream.transport.drops == 1 and session.stream.reconnects == 1
    # The link came back at 70 s: every breath from a few backoff seconds after it arrived.
    assert min(r.t_s for r in session.records if r.t_s > 60.0) < 75.0
    assert session.stream.validator.missing_seq == session.undelivered_seqs()


async def test_a_reader_late_to_flush_its_input_at_open_loses_no_line(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # pyserial's open() sets the port up (tcsetattr), then flushes its input (tcflush): a line the
    # cart writes in between is flushed. The cart waits for the flush itself (pty packet mode).
    monkeypatch.setattr(serialposix.Serial, "reset_input_buffer",
                        _late(serialposix.Serial.reset_input_buffer, before=True))
    session = await run_session(LinkKind.SERIAL, faults=["disconnect@60+10"], end_s=150.0, seed=7)
    assert session.stream.transport.drops == 1 and session.stream.reconnects == 1
    assert session.stream.validator.missing_seq == session.undelivered_seqs()
    assert len(session.records) == len(session.readable())
