"""drivers.signals: stop handlers on the loop inside the block, the caller's ignored signal after."""

from __future__ import annotations

import asyncio
import os
import signal

import pytest

from drivers.signals import stop_signal_handlers


@pytest.mark.parametrize("before", [signal.SIG_IGN, signal.default_int_handler])
def test_handlers_call_back_inside_and_an_ignored_signal_stays_ignored(before) -> None:
    old = signal.signal(signal.SIGINT, before)
    got: list[str] = []
    try:
        async def main() -> list[signal.Signals]:
            loop = asyncio.get_running_loop()
            stopped = asyncio.Event()
            with stop_signal_handlers(loop, lambda: (got.append("stop"), stopped.set()),
                                      signals=(signal.SIGINT,)) as installed:
                os.kill(os.getpid(), signal.SIGINT)
                await asyncio.wait_for(stopped.wait(), 5.0)  # delivered through the loop
            return installed

        assert asyncio.run(main()) == [signal.SIGINT]
        assert got == ["stop"]
        assert signal.getsignal(signal.SIGINT) is before
    finally:
        signal.signal(signal.SIGINT, old)
