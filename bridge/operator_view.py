"""Operator view: a live terminal status of the session, and keys to pause, resume and stop.

Keys (when stdin is a terminal): ``p`` pause (assistance off), ``r`` resume, ``q`` stop.
Without a terminal (CI, a pipe) the view prints nothing live; signals still stop the session.

A console that goes away (the reader of a pipe, ``hilbo run ... | tee run.log`` with tee
killed) does not end the session: :func:`console_guard` drops what is printed after it, and the
session's log, the record, gets one ``console_lost`` warning.

Read at a glance: device faults are shown by name with what clears them (:func:`describe_faults`, from
drivers/exosuit/faults.py),
the session's expected end (``SessionStatus.expected_end_s``, walking time, else the optimisation budget), and
"best so far" is what ``HILOptimizer.best()`` returns, the same quantity as the summary's best.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import os
import sys
import threading
import time
from collections.abc import Callable, Iterable, Iterator, Mapping
from typing import Any, TextIO

from rich.console import Console, Group
from rich.live import Live
from rich.panel import Panel
from rich.table import Table
from rich.text import Text

from bridge.log import SessionLog
from bridge.outcome import format_params
from bridge.runtime import BridgeSession, Command, SessionStatus
from drivers.exosuit import DeviceFault
from drivers.exosuit.faults import FAULT_INFO

__all__ = ["KEYS", "ConsoleGuard", "console_guard", "describe_faults", "render_status", "run_operator_view"]

KEYS = {"p": Command.PAUSE, "r": Command.RESUME, "q": Command.STOP}

def _fault_clears(bits: int) -> list[tuple[str, str]]:
    """(name, what clears it) of each fault bit set in ``bits`` (drivers/exosuit/faults.py)."""
    out = []
    for k in range(bits.bit_length()):
        if bits >> k & 1:
            info = FAULT_INFO.get(DeviceFault(1 << k)) if k < 8 else None
            out.append((info.name, info.clears) if info is not None
                       else (f"bit{k}", "not defined by the protocol"))
    return out


def describe_faults(faults: Mapping[int, int]) -> list[str]:
    """One line per fault: its name, the actuators reporting it and what clears it.

    Args:
        faults: Actuator index -> DeviceFault bits (``SessionStatus.device_faults``).

    Returns:
        E.g. ``["heartbeat_lost on actuators 0, 1: latched: clears on resume [r] ..."]``.
    """
    by_name: dict[str, tuple[list[int], str]] = {}
    for actuator, bits in sorted(faults.items()):
        for name, clears in _fault_clears(int(bits)):
            by_name.setdefault(name, ([], clears))[0].append(actuator)
    return [f"{name} on actuator{'s' if len(acts) > 1 else ''} {', '.join(map(str, acts))}: {clears}"
            for name, (acts, clears) in by_name.items()]


def _expected_end(st: SessionStatus, now_unix_s: float) -> str:
    if st.expected_end_s is not None:  # the protocol's estimate, in walking time
        left_min = max(st.expected_end_s - st.breath_time_s, 0.0) / 60
        return f"after {st.expected_end_s / 60:.1f} min of walking ({left_min:.1f} min left)"
    if st.budget_s is not None:
        left_min = max(st.budget_s - st.budget_used_s, 0.0) / 60
        return f"budget {st.budget_s / 60:.1f} min ({left_min:.1f} min left)"
    return "—"


def _best(st: SessionStatus) -> str:
    if st.best_mean_w is None:
        return "—"
    text = f"{st.best_mean_w:.0f} W"
    if st.best_sd_w is not None:
        text = f"{st.best_mean_w:.0f} ± {1.96 * st.best_sd_w:.0f} W (95 %)"
    if st.best_params:
        text += " at " + format_params(st.best_params, st.units)
    return text


def render_status(st: SessionStatus, now_unix_s: float | None = None) -> Panel:
    """One frame of the operator view (``now_unix_s``: the wall clock, for the expected end).

    Every cell is a :class:`~rich.text.Text`: the session's texts are shown as they are (a
    plain string would be read as Rich markup, and "check [limits] against [space]" would lose
    its brackets on the screen the operator reads during a pause)."""
    t = Table.grid(padding=(0, 2))
    t.add_column(style="bold")
    t.add_column()
    budget = "" if st.budget_s is None else f" / {st.budget_s / 60:.1f} min"
    t.add_row("state", Text(st.state))
    t.add_row("bout", Text(st.bout))
    t.add_row("elapsed", Text(f"{st.breath_time_s / 60:.1f} min walked; optimisation "
                              f"{st.budget_used_s / 60:.1f} min{budget}"))
    t.add_row("expected end", Text(_expected_end(st, time.time() if now_unix_s is None else now_unix_s)))
    t.add_row("evaluation", Text(str(st.evaluation)))
    if st.params:
        t.add_row("setting", Text(format_params(st.params, st.units)))
    estimate = "—" if st.mean_w is None else f"{st.mean_w:.0f} ± {1.96 * (st.sd_w or 0):.0f} W (95 %)"
    t.add_row("estimate", Text(f"{estimate}  after {st.breaths_in_setting} breaths"))
    t.add_row("decision", Text(st.last_decision or "—"))
    t.add_row("best so far", Text(_best(st)))
    dev_style = "green" if st.device == "ok" else "bold red"
    cart_style = "green" if st.cart == "ok" else "bold red"
    faults = describe_faults(st.device_faults)
    device = "faults:\n" + "\n".join(faults) if faults and st.device != "LOST" else st.device
    t.add_row("device", Text(device, style=dev_style))
    t.add_row("cart", Text(st.cart, style=cart_style))
    events = Text("\n".join(st.events[-5:]) or "—", style="dim")
    keys = Text("keys: [p] pause (assistance off)  [r] resume  [q] stop", style="cyan")
    return Panel(Group(t, Text(""), events, keys), title="hilbo session")


async def _read_keys(on_key: Callable[[str], None]) -> None:
    """Read single keys from a terminal in cbreak mode (restored on exit)."""
    import termios
    import tty

    fd = sys.stdin.fileno()
    old = termios.tcgetattr(fd)
    loop = asyncio.get_running_loop()
    queue: asyncio.Queue[str] = asyncio.Queue()

    def readable() -> None:
        ch = os.read(fd, 1).decode(errors="ignore")
        if ch:
            queue.put_nowait(ch)

    try:
        tty.setcbreak(fd)
        loop.add_reader(fd, readable)
        while True:
            on_key(await queue.get())
    finally:
        loop.remove_reader(fd)
        termios.tcsetattr(fd, termios.TCSADRAIN, old)


@contextlib.contextmanager
def _log_above_the_view(terminal: TextIO) -> Iterator[None]:
    """Log handlers writing to the terminal write through Live's stderr (now ``sys.stderr``) while
    the view is drawn, so Rich prints their lines above the frame.

    A handler made before the view (``logging.basicConfig``) holds the terminal itself and wrote
    past Rich: every warning scrolled the frame and left an older one on the screen, so on a
    loaded PC (loop-stall and heartbeat warnings) the screen showed a stale "paused" state above
    the live one.
    """
    handlers = [h for h in logging.getLogger().handlers
                if type(h) is logging.StreamHandler and h.stream is terminal]
    proxy = sys.stderr
    for h in handlers:
        h.setStream(proxy)
    try:
        yield
    finally:
        for h in handlers:
            h.setStream(terminal)


async def run_operator_view(session: BridgeSession, console: Console | None = None,
                            refresh_s: float = 0.25) -> None:
    """Show the live status until cancelled; forward keys as commands when stdin is a TTY."""
    console = console or Console(stderr=True)
    if not console.is_terminal:
        await asyncio.Event().wait()  # nothing to draw; wait to be cancelled
        return
    keys_task: asyncio.Task[None] | None = None
    if sys.stdin.isatty():
        def on_key(ch: str) -> None:
            cmd = KEYS.get(ch.lower())
            if cmd is not None:
                session.command(cmd)

        keys_task = asyncio.create_task(_read_keys(on_key), name="operator-keys")
    try:
        terminal = sys.stderr
        with Live(render_status(session.status), console=console, refresh_per_second=4) as live, \
                _log_above_the_view(terminal):
            try:
                while True:
                    await asyncio.sleep(refresh_s)
                    live.update(render_status(session.status))
                    if keys_task is not None and keys_task.done():
                        keys_task.result()  # surface a key-reader error instead of losing keys
            finally:
                # The last frame stays on the screen: it says how the session ended, not "running".
                live.update(render_status(session.status), refresh=True)
    finally:
        if keys_task is not None:
            keys_task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await keys_task


class _PipeSafeStream:
    """``sys.stdout`` or ``sys.stderr`` of a session: a write to a pipe whose reader has gone
    (BrokenPipeError, EPIPE: Python ignores SIGPIPE) is dropped instead of raised, and so is
    every write after it.

    Without it the first line printed after the reader left ended the session: Rich's console
    answers a broken pipe with SystemExit, which no handler of the session catches, so no
    event named it and no summary was written. Every other error of a write is raised as before.
    """

    def __init__(self, stream: TextIO, name: str, on_lost: Callable[[str], None]) -> None:
        self._stream = stream
        self._name = name
        self._on_lost = on_lost
        self.lost = False

    def write(self, text: str) -> int:
        if not self.lost:
            try:
                return self._stream.write(text)
            except BrokenPipeError:
                self._lose()
        return len(text)

    def writelines(self, lines: Iterable[str]) -> None:
        for line in lines:
            self.write(line)

    def flush(self) -> None:
        if not self.lost:
            try:
                self._stream.flush()
            except BrokenPipeError:
                self._lose()

    def __getattr__(self, name: str) -> Any:
        # isatty, fileno, encoding...: the stream's own (Rich and logging ask for them).
        return getattr(self._stream, name)

    def _lose(self) -> None:
        self.lost = True
        # Python's "Note on SIGPIPE" (the signal module's docs): point the descriptor at
        # /dev/null, so that what is still buffered, and the interpreter's own flush at exit,
        # go there instead of raising again ("Exception ignored ... BrokenPipeError").
        with contextlib.suppress(OSError, ValueError):  # a stream without a descriptor
            fd = self._stream.fileno()
            devnull = os.open(os.devnull, os.O_WRONLY)
            try:
                os.dup2(devnull, fd)
            finally:
                os.close(devnull)
        self._on_lost(self._name)


class ConsoleGuard:
    """Which console stream was lost, and the session log that records it (once).

    Made by :func:`console_guard`; :meth:`record_to` names the session's log once it exists.
    """

    def __init__(self) -> None:
        #: The first stream whose reader left ("stdout" or "stderr"), or None.
        self.lost: str | None = None
        self._log: SessionLog | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._recorded = False
        # Both streams may be lost at once from different threads (a logging thread, the loop).
        self._lock = threading.Lock()

    def record_to(self, log: SessionLog) -> None:
        """Record the console's loss in ``log`` (now, if it was lost before the log existed).

        Call it from the session's event loop: the event is written there, as the session's
        other events are (a console write may come from any thread, or from inside a write
        to the log).
        """
        self._log = log
        self._loop = asyncio.get_running_loop()
        if self.lost is not None:
            self._record()

    def _lost(self, name: str) -> None:
        with self._lock:
            if self.lost is None:
                self.lost = name
        self._record()

    def _record(self) -> None:
        with self._lock:
            if self._loop is None or self._recorded or self.lost is None:
                return
            self._recorded = True
        with contextlib.suppress(RuntimeError):  # the loop has closed: the session is over
            self._loop.call_soon_threadsafe(self._write_event)

    def _write_event(self) -> None:
        log = self._log
        if log is None or log.closed:
            return
        log.log_event("console_lost",
                      f"the console was lost ({self.lost}: its reader closed the pipe); the session "
                      "goes on without printing, and this log keeps everything", stream=self.lost)


@contextlib.contextmanager
def console_guard() -> Iterator[ConsoleGuard]:
    """Run a session whose console may go away: ``sys.stdout``, ``sys.stderr`` and the log
    handlers writing to them drop their writes once the reader of their pipe has left.

    A person may be walking in the suit: losing the screen must not end the session. The
    streams and handlers are restored on exit, after a last flush (which drops what a lost
    reader would never read).
    """
    guard = ConsoleGuard()
    originals = {"stdout": sys.stdout, "stderr": sys.stderr}
    safe = {name: _PipeSafeStream(stream, name, guard._lost) for name, stream in originals.items()}
    handlers = [(h, name) for h in logging.getLogger().handlers for name, stream in originals.items()
                if type(h) is logging.StreamHandler and h.stream is stream]
    for h, name in handlers:
        h.setStream(safe[name])  # type: ignore[arg-type]
    sys.stdout, sys.stderr = safe["stdout"], safe["stderr"]  # type: ignore[assignment]
    try:
        yield guard
    finally:
        for stream in safe.values():
            stream.flush()
        for h, name in handlers:
            h.setStream(originals[name])
        sys.stdout, sys.stderr = originals["stdout"], originals["stderr"]
