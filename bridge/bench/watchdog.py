"""``hilbo bench watchdog``: from a lost device heartbeat to AssistanceOff on the bus, at real time.

A short ``hilbo sim`` session over the virtual devices at speed 1 with the bridge's device
watchdog at its default (``[watchdog] device_heartbeat_timeout_ms = 100``). The virtual exosuit
stops sending DeviceStatus (its ``drop-status`` fault, as a pulled cable or a hung device would)
``n`` times, ``spacing_s`` apart, for ``drop_s`` each; the bridge pauses, the resume policy
resumes once the statuses are back. A **bus spy** — a python-can listener on the same virtual
bus, in its own receive thread — records every DeviceStatus and AssistanceOff frame with the
bus's timestamp (python-can's virtual bus stamps a frame when it is sent).

Latency of one drop (a silence of the statuses on the bus of at least 0.6 ``drop_s``): the first
AssistanceOff(``device_heartbeat_lost``) frame after it began minus the last DeviceStatus before
it of the stalest actuator (the one the watchdog counts from; the two actuators' statuses go out
together). The target (drivers/PROTOCOL.md, "Heartbeats and their timeouts"): every latency
below the configured timeout, on an idle machine and beside CPU burners (``--burners K``: K
processes spinning ``while 1: pass`` for the whole run, killed at its end). Also counted: drops
that began while the bridge was paused already (its heartbeat says so: assistance was off, there
is nothing to command), drops that brought no AssistanceOff (missed), and heartbeat-lost
AssistanceOffs outside the drops with the longest status silence in the half second before them:
the virtual exosuit runs in the bridge's process and event loop, so a stalled loop silences it
too; an off after less silence than the watchdog's limit would be a false alarm.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import math
import os
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import can
import numpy as np

from bridge.argtypes import nonnegative_int, positive_int
from bridge.bench.common import machine_info, markdown_table, raise_if_interrupted, round_sig, write_json
from bridge.runtime import BridgeSession, Command
from drivers.errors import DecodeError
from drivers.exosuit import (
    AssistanceOff,
    AssistanceOffReason,
    BridgeHeartbeat,
    BridgeState,
    DeviceStatus,
    decode_frame,
)
from hilbo_core.errors import ConfigError

__all__ = ["BusSpy", "WatchdogBenchConfig", "add_watchdog_bench_parser", "latencies", "run_watchdog_bench"]

#: The burner: one core's worth of CPU for as long as it runs.
_BURNER = "while 1: pass"


@dataclass(frozen=True)
class WatchdogBenchConfig:
    """One run of the benchmark.

    Attributes:
        n: Device-status drops (the sample size).
        timeout_ms: The bridge's ``[watchdog] device_heartbeat_timeout_ms``.
        drop_s: How long each drop lasts (simulated = wall s at speed 1).
        spacing_s: Between the starts of two drops (s).
        first_s: The first drop's start on the session's clock (s; after the worker's start).
        burners: CPU burner processes beside the run.
        seed: The simulated session's seed.
    """

    n: int = 20
    timeout_ms: float = 100.0
    drop_s: float = 0.5
    spacing_s: float = 3.0
    first_s: float = 8.0
    burners: int = 0
    seed: int = 1

    def __post_init__(self) -> None:
        if isinstance(self.n, bool) or not isinstance(self.n, int) or not 1 <= self.n <= 1000:
            raise ConfigError(f"n={self.n!r}; expected an integer in 1..1000")
        if not 40.0 <= self.timeout_ms <= 1000.0:
            raise ConfigError(f"timeout_ms={self.timeout_ms!r}; expected 40..1000 ms")
        if not 2 * self.timeout_ms / 1000.0 <= self.drop_s <= 10.0:
            raise ConfigError(f"drop_s={self.drop_s!r}; expected 2x the timeout to 10 s")
        if not self.drop_s + 1.0 <= self.spacing_s <= 60.0:
            raise ConfigError(f"spacing_s={self.spacing_s!r}; expected drop_s + 1 to 60 s")
        if isinstance(self.burners, bool) or not isinstance(self.burners, int) or not 0 <= self.burners <= 16:
            raise ConfigError(f"burners={self.burners!r}; expected an integer in 0..16")

    @property
    def windows(self) -> list[tuple[float, float]]:
        """The drops as (start, end) on the session's clock (s)."""
        return [(self.first_s + i * self.spacing_s, self.first_s + i * self.spacing_s + self.drop_s)
                for i in range(self.n)]

    @property
    def session_s(self) -> float:
        """How long the session runs (wall s): the last drop, and time to resume after it."""
        return self.windows[-1][1] + 2.0


class BusSpy(can.Listener):
    """Records DeviceStatus, BridgeHeartbeat and AssistanceOff frames with their bus timestamps.

    Attributes:
        statuses: ``(t, actuator)`` of every DeviceStatus.
        heartbeats: ``(t, state)`` of every BridgeHeartbeat.
        offs: ``(t, reason)`` of every AssistanceOff.
    """

    def __init__(self) -> None:
        self.statuses: list[tuple[float, int]] = []
        self.heartbeats: list[tuple[float, BridgeState]] = []
        self.offs: list[tuple[float, AssistanceOffReason]] = []
        self.undecodable = 0

    def on_message_received(self, msg: can.Message) -> None:
        """Keep the frames this benchmark times (python-can's receive thread)."""
        try:
            message = decode_frame(msg)
        except DecodeError:
            self.undecodable += 1
            return
        t = float(msg.timestamp)
        if isinstance(message, DeviceStatus):
            self.statuses.append((t, int(message.actuator)))
        elif isinstance(message, BridgeHeartbeat):
            self.heartbeats.append((t, BridgeState(message.state)))
        elif isinstance(message, AssistanceOff):
            self.offs.append((t, AssistanceOffReason(message.reason)))

    @contextlib.contextmanager
    def listening(self, channel: str) -> Iterator[None]:
        """Spy on the python-can virtual bus ``channel`` while inside."""
        bus = can.Bus(interface="virtual", channel=channel)
        notifier = can.Notifier(bus, [self], timeout=0.05)
        try:
            yield
        finally:
            notifier.stop()
            bus.shutdown()


def latencies(spy: BusSpy, n_actuators: int, *, min_drop_s: float) -> dict[str, Any]:
    """The injected drops found on the bus, and the bridge's AssistanceOff after each.

    A drop is a silence of every actuator's DeviceStatus of at least ``min_drop_s``; its latency
    is the first AssistanceOff(``device_heartbeat_lost``) after it began minus the stalest
    actuator's last status before it (what the bridge's watchdog counts from).

    Returns:
        ``latencies_ms``: one per drop answered by an AssistanceOff; ``already_off``: drops
        that began while the bridge's heartbeat said it was not running (paused: assistance
        was off already, nothing to command); ``missed``: drops while running that brought no
        AssistanceOff before the statuses came back; ``other_offs_silence_ms``: for each
        heartbeat-lost AssistanceOff outside the drops, the longest status silence on the bus in the
        half second before it (a stall of this process silences the in-process virtual device
        too; below the watchdog's limit it would be a false alarm).
    """
    stamps = sorted(spy.statuses)
    times = np.array([t for t, _ in stamps])
    per_actuator = {a: np.array([t for t, act in stamps if act == a]) for a in range(n_actuators)}
    lost = sorted(t for t, r in spy.offs if r == AssistanceOffReason.DEVICE_HEARTBEAT_LOST)
    hb_t = np.array([t for t, _ in spy.heartbeats])
    hb_state = [st for _, st in spy.heartbeats]
    used: set[float] = set()
    out: list[float] = []
    already_off = missed = 0
    for k in np.flatnonzero(np.diff(times) >= min_drop_s):
        start, back = times[k], times[k + 1]
        lasts = [float(ts[np.searchsorted(ts, start, side="right") - 1]) for ts in per_actuator.values()
                 if ts.size and ts[0] <= start]
        if len(lasts) < n_actuators:
            continue
        last = min(lasts)
        answer = next((t for t in lost if last < t <= back), None)
        if answer is not None:
            used.add(answer)
            out.append((answer - last) * 1e3)
            continue
        h = int(np.searchsorted(hb_t, start, side="right")) - 1
        if h >= 0 and hb_state[h] != BridgeState.RUNNING:
            already_off += 1
        else:
            missed += 1
    others = []
    for t in lost:
        if t in used:
            continue
        # The longest status silence in the half second before this off (it may have ended
        # just before it: statuses sent when a stalled loop woke, not yet read by the bridge).
        window = times[(times > t - 0.5) & (times < t)]
        gaps = np.diff(np.concatenate([window, [t]]))
        others.append(float(gaps.max()) * 1e3 if gaps.size else math.inf)
    return {"latencies_ms": out, "already_off": already_off, "missed": missed,
            "other_offs_silence_ms": others}


@contextlib.contextmanager
def burners(n: int) -> Iterator[list[int]]:
    """``n`` CPU burner processes while inside (killed and reaped on the way out)."""
    procs: list[subprocess.Popen[bytes]] = []
    try:
        for _ in range(n):
            # Their own session: a Ctrl-C at the terminal is the benchmark's to handle (it kills
            # them on the way out), not theirs to answer with a traceback each.
            procs.append(subprocess.Popen([sys.executable, "-c", _BURNER], start_new_session=True))
        yield [p.pid for p in procs]
    finally:
        for p in procs:
            p.kill()
        for p in procs:
            p.wait(timeout=10)


def run_watchdog_bench(cfg: WatchdogBenchConfig, out: Path) -> dict[str, Any]:
    """Run the session with its drops and spy on the bus; the latencies and their quantiles."""
    from bridge.sim.devices import SUIT_JOINTS
    from bridge.sim.virtual import VirtualSimConfig, run_virtual_sim

    sim = VirtualSimConfig(
        minutes=5.0, seed=cfg.seed, speed=1.0, n_explore=2, max_breaths=10, warmup_s=20.0,
        exosuit_faults=tuple(f"drop-status@{a:g}+{cfg.drop_s:g}" for a, _ in cfg.windows))
    n_actuators = len(SUIT_JOINTS[sim.preset])
    spy = BusSpy()
    stack = contextlib.ExitStack()

    def on_session(session: BridgeSession) -> None:
        stack.enter_context(spy.listening(session.endpoint.config.channel))
        asyncio.get_running_loop().call_later(cfg.session_s, session.command, Command.STOP)

    wall0 = time.perf_counter()
    load0 = os.getloadavg()[0]
    with burners(cfg.burners), stack:
        summary = asyncio.run(run_virtual_sim(sim, out, on_session=on_session,
                                              device_timeout_ms=cfg.timeout_ms))
    raise_if_interrupted(summary)
    found = latencies(spy, n_actuators, min_drop_s=0.6 * cfg.drop_s)
    lat = np.asarray(found["latencies_ms"])
    limit_ms = cfg.timeout_ms - min(25.0, cfg.timeout_ms / 4)  # RuntimeSettings.device_silence_limit_s
    false_alarms = sum(1 for v in found["other_offs_silence_ms"] if v < limit_ms)
    result: dict[str, Any] = {
        "benchmark": "watchdog", "config": asdict(cfg), "wall_s": time.perf_counter() - wall0,
        "drops_injected": cfg.n, "drops_seen": int(lat.size) + found["already_off"] + found["missed"],
        "n": int(lat.size), "already_off": found["already_off"], "missed": found["missed"],
        "other_offs_silence_ms": found["other_offs_silence_ms"], "false_alarms": false_alarms,
        "statuses_seen": len(spy.statuses), "offs_seen": len(spy.offs), "undecodable": spy.undecodable,
        "latency_ms": None if lat.size == 0 else {
            "p50": float(np.median(lat)), "p95": float(np.quantile(lat, 0.95)),
            "max": float(lat.max()), "min": float(lat.min())},
        "latencies_ms": [float(v) for v in lat],
        "within_timeout": bool(lat.size and found["missed"] == 0 and lat.max() < cfg.timeout_ms),
        "n_evaluations": summary.get("n_evaluations"),
        # What else the machine ran: the 1-minute load average before and after (the burners
        # included), and the stalls of the session's event loop (bridge/loop_monitor.py).
        "loadavg_1min": [load0, os.getloadavg()[0]],
        "loop": summary.get("loop"),
    }
    return result


def watchdog_table(results: list[dict[str, Any]]) -> str:
    """The Markdown table of one or more runs."""
    rows = []
    for r in results:
        q = r["latency_ms"] or {}
        rows.append([r["config"]["burners"], r["config"]["timeout_ms"],
                     f"{r['n']} of {r['drops_injected']}", r["already_off"], r["missed"],
                     *(f"{q[k]:.1f}" if k in q else "-" for k in ("p50", "p95", "max")),
                     len(r["other_offs_silence_ms"]), r["false_alarms"],
                     "yes" if r["within_timeout"] else "NO",
                     " → ".join(f"{v:.1f}" for v in r["loadavg_1min"]),
                     f"{(r['loop'] or {}).get('worst_stall_ms', math.nan):.0f}"])
    return markdown_table(["burners", "timeout ms", "drops answered", "already off", "missed",
                           "p50 ms", "p95 ms", "max ms", "other offs", "false alarms",
                           "all < timeout", "load avg", "worst loop stall ms"], rows)


def _cmd_watchdog(args: argparse.Namespace) -> int:
    from rich.console import Console

    from bridge.bench.common import options

    console = Console(stderr=True, markup=False, highlight=False, soft_wrap=True)
    with options():  # the command line's values are checked before any work (exit status 2)
        try:
            loads = [int(v) for v in str(args.burners).split(",")]
        except ValueError as err:
            raise ConfigError(f"--burners {args.burners!r}; expected comma-separated integers") from err
        configs = [WatchdogBenchConfig(n=args.n, timeout_ms=args.timeout_ms, drop_s=args.drop_s,
                                       spacing_s=args.spacing_s, burners=k, seed=args.seed)
                   for k in loads]
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    results = []
    for cfg in configs:
        k = cfg.burners
        console.print(f"hilbo bench watchdog: {cfg.n} drops of the device status, {cfg.timeout_ms:g} ms "
                      f"watchdog, {k} CPU burner(s), ~{cfg.session_s + 10:.0f} s at real time")
        with tempfile.TemporaryDirectory(prefix="hilbo-watchdog-") as tmp:
            results.append(round_sig(run_watchdog_bench(cfg, Path(tmp))))
    command = (f"hilbo bench watchdog --n {args.n} --timeout-ms {args.timeout_ms:g} --drop-s {args.drop_s:g} "
               f"--spacing-s {args.spacing_s:g} --burners {args.burners} --seed {args.seed} --out {args.out}")
    write_json(out / "watchdog.json", {"benchmark": "watchdog", "command": command,
                                       "machine": machine_info(), "runs": results})
    table = watchdog_table(results)
    (out / "watchdog_table.md").write_text(table)
    console.print(table)
    console.print(str(out / "watchdog.json"))
    return 0 if all(r["within_timeout"] and r["false_alarms"] == 0 for r in results) else 1


def add_watchdog_bench_parser(bench_subparsers: Any) -> argparse.ArgumentParser:
    """Add ``watchdog`` to the ``hilbo bench`` subcommands; returns its parser."""
    p = bench_subparsers.add_parser(
        "watchdog", help="lost device heartbeat → AssistanceOff on the bus, at real time",
        description="A short hilbo-sim session at real time whose virtual exosuit stops sending "
                    "DeviceStatus N times; a bus spy times the bridge's AssistanceOff against the "
                    "last status (p50/p95/max), idle and beside CPU burners. Exit status 1 when an "
                    "AssistanceOff came later than the watchdog time, never came, or came while "
                    "the statuses still flowed.")
    p.add_argument("--n", type=positive_int, default=20, help="status drops per run (20)")
    p.add_argument("--timeout-ms", type=float, default=100.0,
                   help="[watchdog] device_heartbeat_timeout_ms (100, the default)")
    p.add_argument("--drop-s", type=float, default=0.5, help="each drop's length (0.5 s)")
    p.add_argument("--spacing-s", type=float, default=3.0, help="between drops (3 s)")
    p.add_argument("--burners", default="0,2", metavar="K,K",
                   help="CPU burner processes beside each run, one run per value (0,2)")
    p.add_argument("--seed", type=nonnegative_int, default=1, help="the simulated session's seed (1)")
    p.add_argument("--out", default="runs/bench/watchdog", help="output directory")
    p.set_defaults(func=_cmd_watchdog)
    return p
