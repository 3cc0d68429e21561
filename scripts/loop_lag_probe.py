"""Count event-loop stalls during a real-time ``hilbo sim`` session (a diagnostic, not a test).

A task in the session's event loop sleeps 1 ms over and over and records every wake-up more
than 8 ms late, with the session's bout and breath count at the time. The session is the one of
``hilbo bench perf --bridge-minutes M`` (speed 1, 2 × 1 kHz force feedback, devices in-process).

    nice -n -5 .venv/bin/python scripts/loop_lag_probe.py 2.7     # minutes of wall time
    nice -n -5 .venv/bin/python scripts/loop_lag_probe.py 2.7 --pace-ms 2 --worker thread
    nice -n -5 .venv/bin/python scripts/loop_lag_probe.py 10 --gc automatic

Prints the number of stalls, their total, the endpoint's ``heartbeat_overrun`` count (heartbeat
task woke more than a period late), the stop decision → ack latencies and the garbage
collections (bridge/collector.py's counts: started by Python per generation with the longest,
at quiet points, between bouts), then the first 40 stalls, each with the garbage collection
that overlapped it, if one did. ``--pace-ms``, ``--worker`` and ``--gc`` override the session's
segment pace, proposal worker and collection policy.
"""

from __future__ import annotations

import argparse
import asyncio
import dataclasses
import gc
import sys
import tempfile
import time
from pathlib import Path

import bridge.run as run
from bridge.bench.bridge_perf import BridgeRtConfig
from bridge.collector import GcMode
from bridge.proposals import WorkerKind
from bridge.runtime import BridgeSession
from bridge.sim.virtual import run_virtual_sim

STALL_S = 0.008


async def main(minutes: float) -> None:
    stalls: list[tuple[float, float, str, int]] = []
    tasks: list[asyncio.Task[None]] = []
    held: dict[str, BridgeSession] = {}
    collections: list[tuple[float, float, int]] = []  # (end, duration, generation), > 1 ms
    started: list[float] = []

    def on_gc(phase: str, info: dict[str, int]) -> None:
        if phase == "start":
            started[:] = [time.monotonic()]
        elif started and (d := time.monotonic() - started[0]) > 0.001:
            collections.append((time.monotonic(), d, info["generation"]))

    gc.callbacks.append(on_gc)

    def on_session(session: BridgeSession) -> None:
        held["session"] = session

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
    gc.callbacks.remove(on_gc)
    for t in tasks:
        t.cancel()
    await asyncio.gather(*tasks, return_exceptions=True)
    total_ms = 1e3 * sum(lag for _, lag, *_ in stalls)
    session = held["session"]
    st = session.settings
    sys.stdout.write(f"pace {1e3 * st.pace_s:g} ms, worker {st.proposal_worker.value}: "
                     f"stalls > {STALL_S * 1e3:g} ms: {len(stalls)}, total {total_ms:.0f} ms; "
                     f"heartbeat_overrun {session.endpoint.counters.get('heartbeat_overrun', 0)}; "
                     f"stop -> ack ms {[round(1e3 * x) for x in session.stop_latencies_s]}\n")
    sys.stdout.write(f"gc [{session.collector.mode.value}]: {session.collector.stats.to_json()}\n")
    for t, lag, bout, breaths in stalls[:40]:
        # A collection overlapped the stall if it ended within the stall's window.
        hit = [f"gen{g} {1e3 * d:.1f} ms" for end, d, g in collections if t - lag - 0.001 <= end <= t]
        sys.stdout.write(f"  t = {t - t0:7.2f} s  {1e3 * lag:5.1f} ms  {bout}, breath {breaths}"
                         f"{'  gc: ' + ', '.join(hit) if hit else ''}\n")


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("minutes", type=float, nargs="?", default=2.7)
    ap.add_argument("--pace-ms", type=float, default=None, help="segment pace (default: the session's)")
    ap.add_argument("--worker", choices=[k.value for k in WorkerKind], default=None)
    ap.add_argument("--gc", choices=[k.value for k in GcMode], default=None)
    args = ap.parse_args()
    settings = run.runtime_settings

    def patched(*a: object, **k: object):  # the session's settings with the overrides
        st = settings(*a, **k)
        if args.pace_ms is not None:
            st = dataclasses.replace(st, pace_s=args.pace_ms / 1000.0)
        if args.worker is not None:
            st = dataclasses.replace(st, proposal_worker=WorkerKind(args.worker))
        if args.gc is not None:
            st = dataclasses.replace(st, gc=GcMode(args.gc))
        return st

    run.runtime_settings = patched
    asyncio.run(main(args.minutes))
