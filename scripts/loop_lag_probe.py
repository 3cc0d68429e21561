"""Count event-loop stalls during a real-time ``hilbo sim`` session (a diagnostic, not a test).

A task in the session's event loop sleeps 1 ms over and over and records every wake-up more
than 8 ms late, with the session's bout and breath count at the time. The session is the one of
``hilbo bench perf --bridge-minutes M`` (speed 1, 2 × 1 kHz force feedback, devices in-process).

    nice -n -5 .venv/bin/python scripts/loop_lag_probe.py 2.7     # minutes of wall time

Prints the number of stalls, their total, and the first 40.
"""

from __future__ import annotations

import asyncio
import sys
import tempfile
import time
from pathlib import Path

from bridge.bench.bridge_perf import BridgeRtConfig
from bridge.runtime import BridgeSession
from bridge.sim import run_virtual_sim

STALL_S = 0.008


async def main(minutes: float) -> None:
    stalls: list[tuple[float, float, str, int]] = []
    tasks: list[asyncio.Task[None]] = []

    def on_session(session: BridgeSession) -> None:
        async def probe() -> None:
            loop = asyncio.get_running_loop()
            while True:
                t = loop.time()
                await asyncio.sleep(0.001)
                lag = loop.time() - t - 0.001
                if lag > STALL_S:
                    stalls.append((time.monotonic(), lag, session.status.bout,
                                   session.status.breaths_in_setting))
        tasks.append(asyncio.get_running_loop().create_task(probe()))

    t0 = time.monotonic()
    with tempfile.TemporaryDirectory(prefix="hilbo-lag-") as tmp:
        cfg = BridgeRtConfig(minutes=minutes, baseline_s=0)
        await run_virtual_sim(cfg.sim_config(), Path(tmp), on_session=on_session)
    for t in tasks:
        t.cancel()
    await asyncio.gather(*tasks, return_exceptions=True)
    total_ms = 1e3 * sum(lag for _, lag, *_ in stalls)
    sys.stdout.write(f"stalls > {STALL_S * 1e3:g} ms: {len(stalls)}, total {total_ms:.0f} ms\n")
    for t, lag, bout, breaths in stalls[:40]:
        sys.stdout.write(f"  t = {t - t0:7.2f} s  {1e3 * lag:5.1f} ms  {bout}, breath {breaths}\n")


if __name__ == "__main__":
    asyncio.run(main(float(sys.argv[1]) if len(sys.argv) > 1 else 2.7))
