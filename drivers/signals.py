"""Stop signals for the asyncio processes (the bridge, the virtual devices): one way to install
and remove them.

Why a helper: ``loop.remove_signal_handler`` (and ``loop.close()``, which calls it) leaves
Python's default handler behind, so a SIGINT that the caller ignores (a job that a
non-interactive shell started in the background, ``nohup``) would be armed again once the
process's session ends; these handlers put an ignored signal back to ignored.
"""

from __future__ import annotations

import asyncio
import contextlib
import signal
from collections.abc import Callable, Iterator, Sequence
from typing import Any

__all__ = ["STOP_SIGNALS", "stop_signal_handlers"]

#: The signals that stop a process of ours: Ctrl-C and a polite kill.
STOP_SIGNALS: tuple[signal.Signals, ...] = (signal.SIGINT, signal.SIGTERM)


@contextlib.contextmanager
def stop_signal_handlers(
    loop: asyncio.AbstractEventLoop, callback: Callable[..., Any], *args: Any,
    signals: Sequence[signal.Signals] = STOP_SIGNALS,
) -> Iterator[list[signal.Signals]]:
    """Call ``callback(*args)`` on the loop when one of ``signals`` arrives, inside the block.

    Where the loop cannot install handlers (Windows, or not the main thread) nothing is
    installed, and Ctrl-C arrives as KeyboardInterrupt as usual.

    Yields:
        The signals that got a handler.
    """
    installed: dict[signal.Signals, bool] = {}
    for sig in signals:
        with contextlib.suppress(NotImplementedError, RuntimeError, ValueError):
            was_ignored = signal.getsignal(sig) is signal.SIG_IGN
            loop.add_signal_handler(sig, callback, *args)
            installed[sig] = was_ignored
    try:
        yield list(installed)
    finally:
        for sig, was_ignored in installed.items():
            loop.remove_signal_handler(sig)
            if was_ignored:
                signal.signal(sig, signal.SIG_IGN)
