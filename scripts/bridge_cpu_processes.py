"""The bridge's own CPU with the virtual devices in processes of their own (a measurement, not a test).

``hilbo bench perf --bridge-minutes M`` runs the virtual exosuit and cart inside the bridge's
process, so its CPU figure is the bridge's plus the devices'. This runs the same session (the
bench's protocol: 2 exploration points, N = 10, 20 s warm-ups, 2 × 1 kHz force feedback, speed
1) through ``hilbo sim --processes`` (bridge/sim/processes.py: the devices as child processes on
vcan0 or a python-can-remote server), so this process is the bridge alone, with its CAN client:

    nice -n -5 .venv/bin/python scripts/bridge_cpu_processes.py 5 --bus remote

From the first force-feedback frame to the end of the protocol it samples this process's CPU
time (all threads; ``time.process_time``) and the proposal worker's (``/proc/PID/stat``), and
prints the cores of each, the frames received and lost, and the stop decision → ack latencies.
"""

from __future__ import annotations

import argparse
import asyncio
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from bridge.bench.bridge_perf import BridgeRtConfig, _stat_cpu_s
from bridge.bench.common import blas_threads
from bridge.runtime import BridgeSession
from bridge.sim.processes import run_process_sim


async def main(minutes: float, bus: str) -> None:
    # As `hilbo` runs: single-threaded BLAS here and in the children (bridge/cli/main.py).
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    blas_threads(1)
    samples: list[tuple[float, float, float, int]] = []  # wall, own CPU, worker CPU, frames
    tasks: list[asyncio.Task[None]] = []
    held: dict[str, BridgeSession] = {}

    def sample(session: BridgeSession) -> None:
        pid = session.proposal_worker.pid
        worker = (_stat_cpu_s(f"/proc/{pid}/stat") if pid is not None else None) or 0.0
        samples.append((time.perf_counter(), time.process_time(), worker, session.device.feedback_frames))

    def on_session(session: BridgeSession) -> None:
        held["session"] = session

        async def sampler() -> None:
            while session.device.feedback_frames == 0:
                await asyncio.sleep(0.05)
            while not session.opt.done and session.endpoint.is_open:
                sample(session)
                await asyncio.sleep(1.0)
        tasks.append(asyncio.get_running_loop().create_task(sampler()))

    cfg = BridgeRtConfig(minutes=minutes, baseline_s=0).sim_config()
    with tempfile.TemporaryDirectory(prefix="hilbo-cpu-") as tmp:
        await run_process_sim(cfg, Path(tmp), bus=bus, on_session=on_session)
    for t in tasks:
        t.cancel()
    await asyncio.gather(*tasks, return_exceptions=True)
    if len(samples) < 2:
        sys.exit("the session ended before two samples were taken")
    (w0, c0, k0, f0), (w1, c1, k1, f1) = samples[0], samples[-1]
    session = held["session"]
    lat = np.asarray(session.stop_latencies_s) * 1e3
    sys.stdout.write(
        f"bus {bus}, window {w1 - w0:.0f} s: bridge process {(c1 - c0) / (w1 - w0):.3f} cores, "
        f"proposal worker {(k1 - k0) / (w1 - w0):.3f} cores; feedback received {f1 - f0} "
        f"({(f1 - f0) / (w1 - w0):.0f}/s), lost {session.device.feedback_lost}, "
        f"subscriber_overflow {session.endpoint.counters.get('subscriber_overflow', 0)}; "
        f"stop -> ack median {np.median(lat):.1f} ms, p99 {np.quantile(lat, 0.99):.1f} ms, "
        f"max {lat.max():.1f} ms (n = {lat.size}); load average {os.getloadavg()[0]:.2f}\n")


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("minutes", type=float, nargs="?", default=5.0)
    ap.add_argument("--bus", choices=("auto", "vcan", "remote"), default="auto")
    args = ap.parse_args()
    asyncio.run(main(args.minutes, args.bus))
