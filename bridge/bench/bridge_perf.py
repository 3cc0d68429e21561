"""``hilbo bench perf --bridge-minutes M``: the bridge at real time.

A short :func:`bridge.sim.virtual.run_virtual_sim` session at ``speed`` (1 = real time) with the virtual
exosuit sending force feedback of both actuators at ``feedback_hz`` (1 kHz), with one of two
protocols (:class:`BridgeProtocol`): ``quick``, cut down so that profile pushes come often (2
exploration points, N = 10 breaths, 20 s warm-ups), or ``lab``, the lab's own (Kim et al. 2019 §IV.A.3,
as in ``hilbo config example``: 6 exploration points, N = 45, 180 s warm-ups), measuring what
the bridge's targets (:data:`BRIDGE_TARGETS`) are about:

* **stop → ack latency** — wall time from the stopping rule's decision (the breath's
  ``observe_breath`` returning *stop*) to the device's ack of the commit of the next setting's
  profile: the proposal (in the proposal worker, started at the decision; EI maximisation, the
  GP hyperparameters having been fitted ahead), the safety gate, the paced segments (34 at the
  ``[can] segment_pace_ms`` pace, 1.5 ms by default, for a 101-point table), the commit and the
  ack (``BridgeSession.stop_latencies_s``). The ack follows the commit within a frame time on
  this bus, so this bounds "stop decision → new profile committed on the bus" from above. Pushes
  not preceded by a stop decision (the first of each bout, counted from the end of its warm-up)
  are in ``push_latency_ms`` only. The breakdown takes the ask from the ``/proposals`` log
  (``total_ms``, of which ``compute_ms`` in the worker) and the transfer from the ``/acks`` log
  (``elapsed_s``: first segment → ack); the rest is everything else on the path.
* **force feedback** — frames the device sent (``VirtualExosuit.stats["feedback_sent"]``) vs
  frames the bridge's feedback task received (``DeviceView.feedback_frames``) over the window in
  which the session ran its protocol (sampled every ``sample_period_s``; the difference also
  holds the frames in flight at the two sampling instants, a handful); frames missing from the
  received sequence (gaps in each actuator's 8-bit frame counter, ``DeviceView.feedback_lost``,
  exact whatever the window); the endpoint's ``subscriber_overflow``; samples in the MCAP log's
  ``/force_feedback``; and the achieved rates (sent and received frames per second, mean and the
  lowest over one sampling interval) against ``n_actuators × feedback_hz``.
* **CPU** — this process's CPU time (``time.process_time``, all threads) over the session's wall
  time, in cores. The virtual exosuit and the virtual cart run in this process and in the same
  event loop as the bridge, so this is an **upper bound** on the bridge's own use. Per thread
  (Linux ``/proc/self/task``): the event-loop thread runs the bridge, the devices and python-can's
  callbacks together; each bus has its own python-can receive thread; the proposals and fits run
  in the proposal worker process, whose CPU (``/proc/PID/stat``, as of the last sample) is added
  to the process's (``worker_cpu_s``). To separate the bridge's share, the virtual
  exosuit then runs alone for ``baseline_s`` (same feedback rate, one idle receiving bus in place
  of the bridge's, no bridge heartbeat so it latches assistance-off and sends zero desired force):
  the whole process's cores minus the device's alone estimate the bridge's (plus the cart's, a
  breath every ~3 s).

Python-can's ``virtual`` bus queues are unbounded, so in this process frames can only be lost in
the endpoint's bounded subscription queues (dropped oldest first and counted) — or not sent on
time by a starved device loop, which the sent rate shows.
"""

from __future__ import annotations

import asyncio
import collections
import itertools
import math
import os
import tempfile
import threading
import time
import uuid
from dataclasses import asdict, dataclass, fields
from enum import StrEnum
from pathlib import Path
from typing import Any, NamedTuple

import can
import numpy as np

from bridge.bench.common import blas_threads, markdown_table, raise_if_interrupted
from bridge.log import Topic
from bridge.log.reader import read_log
from bridge.runtime import BridgeSession
from bridge.sim.devices import SUIT_JOINTS, ScaledClock, VirtualExosuit
from bridge.sim.virtual import VirtualSimConfig, run_virtual_sim
from drivers.exosuit import CanBusConfig
from hilbo_core.errors import ConfigError
from hilbo_core.protocol import ProtocolKind, protocol_preset

__all__ = ["BRIDGE_TARGETS", "BridgeProtocol", "BridgeRtConfig", "bridge_realtime", "bridge_table"]

#: The bridge's targets: p99 of stop → committed under 100 ms at speed 1; 2 × 1 kHz feedback plus logging
#: without dropping frames, under half a core.
BRIDGE_TARGETS = {"stop_to_ack_p99_ms": 100.0, "cores": 0.5, "dropped_frames": 0}


class BridgeProtocol(StrEnum):
    """The real-time session's protocol."""

    #: 2 exploration points, N = 10, 20 s warm-ups: a stop decision every ~20 s, many per minute.
    QUICK = "quick"
    #: The lab's own (``hilbo config example``, :class:`~bridge.sim.virtual.VirtualSimConfig`'s
    #: defaults: the fast walking protocol's 3 exploration points), N = 45, 180 s warm-ups; the
    #: GP sizes of a real session.
    LAB = "lab"

    def settings(self) -> dict[str, Any]:
        """``n_explore``, ``max_breaths`` and ``warmup_s`` of this protocol: :class:`BridgeRtConfig`'s
        defaults for ``quick``, :class:`~bridge.sim.virtual.VirtualSimConfig`'s for ``lab``."""
        source = BridgeRtConfig if self is BridgeProtocol.QUICK else VirtualSimConfig
        keys = ("n_explore", "max_breaths", "warmup_s")
        out = {f.name: f.default for f in fields(source) if f.name in keys}
        if out["n_explore"] is None:  # the walking protocol's: hilbo sim's sound rule walks the fast one
            out["n_explore"] = protocol_preset(ProtocolKind.FAST)[1]["n_explore"]
        return out

    @classmethod
    def parse(cls, value: str) -> BridgeProtocol:
        """The protocol named ``value``.

        Raises:
            ConfigError: Not one of the names.
        """
        try:
            return cls(value)
        except ValueError as err:
            raise ConfigError(f"bridge protocol={value!r}; expected one of "
                              f"{[p.value for p in cls]}") from err


@dataclass(frozen=True)
class BridgeRtConfig:
    """The real-time bridge session.

    Attributes:
        minutes: Session length (both bouts and warm-ups), minutes of walking; at ``speed`` 1
            also the wall time.
        speed: Real-time factor of the simulated clock (1 = real time, where the targets hold).
        feedback_hz: Force-feedback rate per actuator (Hz, wall clock).
        n_explore: Exploration points (the ``quick`` protocol's by default; see
            :meth:`for_protocol`).
        max_breaths: N, breaths per evaluation at most.
        warmup_s: Each bout's warm-up (breath time, s).
        seed: Subject and optimizer seed.
        preset: Parameter space (``hip_6d``: 2 actuators, one 101-point table).
        sample_period_s: Counter sampling period (wall s).
        baseline_s: How long the virtual exosuit runs alone afterwards (wall s; 0 = skip).
        gc: The bridge's garbage-collection policy (``freeze``, the default, or ``automatic``).
    """

    minutes: float = 5.0
    speed: float = 1.0
    feedback_hz: float = 1000.0
    n_explore: int = 2
    max_breaths: int = 10
    warmup_s: float = 20.0
    seed: int = 1
    preset: str = "hip_6d"
    sample_period_s: float = 1.0
    baseline_s: float = 30.0
    gc: str = "freeze"

    def __post_init__(self) -> None:
        if not (isinstance(self.baseline_s, int | float) and math.isfinite(self.baseline_s)
                and self.baseline_s >= 0):
            raise ConfigError(f"bridge baseline_s={self.baseline_s!r}; expected a number >= 0")
        for name, lo in (("speed", 0.0), ("feedback_hz", 0.0), ("sample_period_s", 0.0)):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int | float) or not (math.isfinite(v) and v > lo):
                raise ConfigError(f"bridge {name}={v!r}; expected a positive number")
        if self.feedback_hz > 10_000:
            raise ConfigError(f"bridge feedback_hz={self.feedback_hz!r}; expected at most 10000")
        if self.preset not in SUIT_JOINTS:
            raise ConfigError(f"bridge preset={self.preset!r}; expected one of {sorted(SUIT_JOINTS)}")
        self.sim_config()  # minutes vs the protocol (names the offending value)

    @classmethod
    def for_protocol(cls, protocol: BridgeProtocol | str, **kwargs: Any) -> BridgeRtConfig:
        """A session with ``protocol``'s exploration points, N and warm-ups; ``kwargs`` the rest.

        Raises:
            ConfigError: An unknown protocol, ``kwargs`` naming what the protocol sets, or a bad
                value in ``kwargs``.
        """
        p = protocol if isinstance(protocol, BridgeProtocol) else BridgeProtocol.parse(protocol)
        settings = p.settings()
        if clash := sorted(set(kwargs) & set(settings)):
            raise ConfigError(f"{clash} are set by the {p.value!r} protocol; leave them out or build "
                              "BridgeRtConfig directly")
        return cls(**kwargs, **settings)

    @property
    def protocol(self) -> str:
        """The name of the protocol this session's n_explore, N and warm-ups are, or ``custom``."""
        mine = {"n_explore": self.n_explore, "max_breaths": self.max_breaths, "warmup_s": self.warmup_s}
        return next((p.value for p in BridgeProtocol if p.settings() == mine), "custom")

    def sim_config(self) -> VirtualSimConfig:
        """The :class:`~bridge.sim.virtual.VirtualSimConfig` of this session."""
        sim = VirtualSimConfig(minutes=self.minutes, seed=self.seed, speed=self.speed, preset=self.preset,
                               n_explore=self.n_explore, max_breaths=self.max_breaths,
                               warmup_s=self.warmup_s, feedback_hz=self.feedback_hz, gc=self.gc)
        _ = sim.budget_min  # raises ConfigError when the minutes leave no optimisation bout
        return sim


@dataclass(frozen=True)
class _Sample:
    """Counters at one instant (all read in one event-loop callback, so mutually consistent)."""

    wall_s: float
    cpu_s: float
    sent: int
    received: int
    lost: int
    threads: dict[int, float]
    worker_cpu_s: float  # the proposal worker process's CPU so far (0 without one)
    steal_s: float | None = None  # the machine's CPU steal so far, all CPUs (/proc/stat), or None
    unix_ns: int = 0  # time.time_ns(): the session log's log_time clock, to place pushes


def _steal_s(stat_path: str | Path = "/proc/stat") -> float | None:
    """CPU time (s, summed over the CPUs) the hypervisor gave to others while this virtual
    machine wanted it: the ``steal`` field of /proc/stat's ``cpu`` line; None where unreadable."""
    tick = os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 100
    try:
        fields = Path(stat_path).read_text().split("\n", 1)[0].split()
        return int(fields[8]) / tick if fields[0] == "cpu" and len(fields) > 8 else None
    except (OSError, ValueError):
        return None


def _stat_cpu_s(stat_path: str | Path) -> float | None:
    """User + system CPU time (s) from a /proc ``stat`` file; None when it cannot be read."""
    tick = os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 100
    try:
        stat = Path(stat_path).read_text()
    except OSError:
        return None  # ended meanwhile, or not Linux
    fields = stat.rsplit(")", 1)[1].split()  # fields[0] is field 3 (state) of proc(5)
    return (int(fields[11]) + int(fields[12])) / tick  # utime, stime


def _thread_cpu_s() -> dict[int, float]:
    """CPU time (user + system, s) of every thread of this process by native id; {} off Linux."""
    out: dict[int, float] = {}
    try:
        entries = list(os.scandir("/proc/self/task"))
    except OSError:
        return out
    for entry in entries:
        cpu = _stat_cpu_s(Path(entry.path, "stat"))
        if cpu is not None:
            out[int(entry.name)] = cpu
    return out


def _quantiles(values_ms: list[float]) -> dict[str, float] | None:
    if not values_ms:
        return None
    a = np.asarray(values_ms, dtype=float)
    return {"median": float(np.median(a)), "p99": float(np.quantile(a, 0.99)), "max": float(a.max()),
            "n": int(a.size)}


async def _measure(cfg: BridgeRtConfig, out: Path) -> dict[str, Any]:
    held: dict[str, Any] = {}
    samples: list[_Sample] = []
    tasks: list[asyncio.Task[None]] = []
    names: dict[int, str] = {}  # thread names by native id (the bus threads end with the session)

    def sample() -> _Sample:
        exo: VirtualExosuit = held["exo"]
        s: BridgeSession = held["session"]
        names.update({t.native_id: t.name for t in threading.enumerate() if t.native_id is not None})
        pid = s.proposal_worker.pid
        worker = (_stat_cpu_s(f"/proc/{pid}/stat") if pid is not None else None) or 0.0
        held["worker_cpu_s"] = max(held.get("worker_cpu_s", 0.0), worker)
        return _Sample(time.perf_counter(), time.process_time(), int(exo.stats.get("feedback_sent", 0)),
                       s.device.feedback_frames, s.device.feedback_lost, _thread_cpu_s(), worker,
                       _steal_s(), time.time_ns())

    async def sampler(session: BridgeSession) -> None:
        # Only while the session runs its protocol: its feedback task ends once the budget is
        # spent (opt.done) or the session stops, while the device sends on until it closes.
        last = 0
        while True:
            await asyncio.sleep(cfg.sample_period_s)
            frames = session.device.feedback_frames
            if session.opt.done or not session.endpoint.is_open or (last and frames == last):
                return
            if frames:
                samples.append(sample())
            last = frames

    def on_exosuit(exo: VirtualExosuit) -> None:
        held["exo"] = exo
        held["threads_before_bridge"] = {t.native_id for t in threading.enumerate()}

    def on_session(session: BridgeSession) -> None:
        held["session"] = session
        tasks.append(asyncio.get_running_loop().create_task(sampler(session), name="bench-sampler"))

    load0 = os.getloadavg()
    wall0, cpu0 = time.perf_counter(), time.process_time()
    try:
        summary = await run_virtual_sim(cfg.sim_config(), out, on_session=on_session, on_exosuit=on_exosuit)
        raise_if_interrupted(summary)
    finally:
        for t in tasks:
            t.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
    wall, cpu = time.perf_counter() - wall0, time.process_time() - cpu0
    load1 = os.getloadavg()
    return {"summary": summary, "samples": samples, "wall_s": wall,
            # The worker's CPU as of the last sample (it exits with the session): the part of
            # the session after that sample (< one sample period) is missing from it.
            "cpu_s": cpu + held.get("worker_cpu_s", 0.0), "worker_cpu_s": held.get("worker_cpu_s", 0.0),
            "load": (load0, load1), "exo": held["exo"], "session": held["session"],
            "threads_before_bridge": held.get("threads_before_bridge", set()), "thread_names": names}


async def _device_alone(cfg: BridgeRtConfig) -> dict[str, Any]:
    """CPU of the virtual exosuit alone for ``cfg.baseline_s`` (see the module docstring)."""
    channel = f"hilbo-bench-device-{uuid.uuid4().hex[:8]}"
    sink = can.Bus(interface="virtual", channel=channel)  # gets the copies the bridge's bus got
    try:
        async with VirtualExosuit(CanBusConfig("virtual", channel), ScaledClock(cfg.speed),
                                  joints=SUIT_JOINTS[cfg.preset], seed=cfg.seed,
                                  feedback_hz=cfg.feedback_hz) as exo:
            await asyncio.sleep(min(1.0, cfg.baseline_s))  # past the start-up
            w0, c0, s0 = time.perf_counter(), time.process_time(), exo.stats.get("feedback_sent", 0)
            await asyncio.sleep(cfg.baseline_s)
            wall = time.perf_counter() - w0
            cpu = time.process_time() - c0
            sent = exo.stats.get("feedback_sent", 0) - s0
    finally:
        sink.shutdown()
    return {"seconds": wall, "cpu_s": cpu, "cores": cpu / wall, "sent_rate_hz": sent / wall}


def _window(samples: list[_Sample], n_streams: int, target_hz: float,
            before: set[int], names: dict[int, str]) -> dict[str, Any]:
    """Feedback and CPU between the first and the last sample."""
    if len(samples) < 2:
        return {"window_s": None}
    a, b = samples[0], samples[-1]
    dt = b.wall_s - a.wall_s
    sent, received = b.sent - a.sent, b.received - a.received
    pairs = [(p, q) for p, q in itertools.pairwise(samples) if q.wall_s > p.wall_s]
    steps = [(q.received - p.received) / (q.wall_s - p.wall_s) for p, q in pairs]
    sent_steps = [(q.sent - p.sent) / (q.wall_s - p.wall_s) for p, q in pairs]
    threads: dict[str, dict[str, Any]] = {}
    for tid, cpu_b in b.threads.items():
        name = names.get(tid, f"thread {tid} (not a Python thread)")
        if tid in before:
            name += " [started before the bridge]"
        row = threads.setdefault(name, {"threads": 0, "cpu_s": 0.0})
        row["threads"] += 1
        row["cpu_s"] += cpu_b - a.threads.get(tid, 0.0)
    for row in threads.values():
        row["cores"] = row["cpu_s"] / dt if dt > 0 else None
    return {
        "window_s": dt,
        "sent": sent,
        "received": received,
        "dropped": sent - received,
        "lost_counter_gaps": b.lost - a.lost,
        "rate_hz": {"target": n_streams * target_hz, "sent": sent / dt, "received": received / dt,
                    "sent_min": min(sent_steps), "received_min": min(steps)},
        "cores": (b.cpu_s - a.cpu_s + b.worker_cpu_s - a.worker_cpu_s) / dt,
        "worker_cores": (b.worker_cpu_s - a.worker_cpu_s) / dt,
        "threads": dict(sorted(threads.items(), key=lambda kv: -kv[1]["cpu_s"])),
        # CPU the hypervisor took from this machine (cores, all CPUs together): in the window, and
        # the most in one sampling interval. Slow stretches with steal are not the bridge's.
        "steal_cores": None if a.steal_s is None or b.steal_s is None else (b.steal_s - a.steal_s) / dt,
        "steal_cores_max": max(((q.steal_s - p.steal_s) / (q.wall_s - p.wall_s) for p, q in pairs
                                if p.steal_s is not None and q.steal_s is not None), default=None),
    }


#: Events after which the next push answers a warm-up's end, not a stop decision.
_WARM_UP_EVENTS = frozenset({"pause", "bout_pause", "resume"})


class _Push(NamedTuple):
    """One accepted push in the session log."""

    after_stop: bool  # answers a stop decision (an /observations message since the last warm-up)
    ask_ms: float  # the ask as the session saw it (/proposals total_ms; NaN in logs without it)
    compute_ms: float  # ask() itself in the worker (/proposals compute_ms)
    transfer_ms: float  # first segment → ack (the ack's elapsed_s)
    acked_ns: int  # the ack's log_time (time.time_ns() at the bridge)


def _log_counts(path: Path) -> dict[str, Any]:
    """Force-feedback samples, events and the pushes in the session log.

    Each accepted push gives a :class:`_Push`.
    """
    topics = [Topic.FORCE_FEEDBACK, Topic.ACKS, Topic.EVENTS, Topic.OBSERVATIONS, Topic.PROPOSALS]
    contents = read_log(path, topics=topics)
    per_act: collections.Counter[str] = collections.Counter()
    events: collections.Counter[str] = collections.Counter()
    pushes: list[_Push] = []
    after_stop = False
    ask_ms = compute_ms = math.nan
    for m in contents.messages:
        r = m.record
        if r is None:
            continue
        if m.topic == Topic.FORCE_FEEDBACK:
            per_act[str(r.actuator)] += r.n
        elif m.topic == Topic.EVENTS:
            events[r.kind] += 1
            after_stop = after_stop and r.kind not in _WARM_UP_EVENTS
        elif m.topic == Topic.OBSERVATIONS:
            after_stop = True
        elif m.topic == Topic.PROPOSALS:
            ask_ms = math.nan if r.total_ms is None else r.total_ms
            compute_ms = math.nan if r.compute_ms is None else r.compute_ms
        elif m.topic == Topic.ACKS and r.accepted and r.elapsed_s is not None:
            pushes.append(_Push(after_stop, ask_ms, compute_ms, 1e3 * r.elapsed_s, m.log_time_ns))
            after_stop, ask_ms, compute_ms = False, math.nan, math.nan
    return {"feedback_logged": sum(per_act.values()), "feedback_logged_per_actuator": dict(per_act),
            "pushes": pushes, "events": dict(events)}


def _steal_around(samples: list[_Sample], start_ns: int, end_ns: int) -> float | None:
    """The most CPU (cores) the host stole from this machine in a sampling interval that overlaps
    ``[start_ns, end_ns]`` (wall clock); None without /proc/stat or samples around it."""
    worst = None
    for p, q in itertools.pairwise(samples):
        if (q.unix_ns >= start_ns and p.unix_ns <= end_ns and q.wall_s > p.wall_s
                and p.steal_s is not None and q.steal_s is not None):
            v = (q.steal_s - p.steal_s) / (q.wall_s - p.wall_s)
            worst = v if worst is None else max(worst, v)
    return worst


def _breakdown(stop_ms: list[float], pushes: list[_Push],
               samples: list[_Sample] | None = None) -> dict[str, Any] | None:
    """Split every stop → ack latency into the ask (started at the decision, in the worker:
    ``ask_ms``, of which ``compute_ms`` is ``ask()`` itself), the transfer (first segment → ack)
    and the rest (everything else on the path: the decision's breath logging, the safety gate,
    starting the push); None if the log's pushes and the session's latencies do not pair up.
    With ``samples``, each push's row also has ``steal_cores``: what the host took from this
    virtual machine around it (:func:`_steal_around`), to tell its slow stretches from ours."""
    after = [p for p in pushes if p.after_stop]
    if len(after) != len(stop_ms) or not stop_ms:
        return None
    rest = [total - p.ask_ms - p.transfer_ms for total, p in zip(stop_ms, after, strict=True)]
    rows = []
    for total, p, r in zip(stop_ms, after, rest, strict=True):
        row: dict[str, Any] = {"total": round(total, 2), "ask": round(p.ask_ms, 2),
                               "compute": round(p.compute_ms, 2), "transfer": round(p.transfer_ms, 2),
                               "rest": round(r, 2)}
        if samples:
            steal = _steal_around(samples, p.acked_ns - round(total * 1e6), p.acked_ns)
            row["steal_cores"] = None if steal is None else round(steal, 3)
        rows.append(row)
    return {"ask_ms": _quantiles([p.ask_ms for p in after]),
            "compute_ms": _quantiles([p.compute_ms for p in after]),
            "transfer_ms": _quantiles([p.transfer_ms for p in after]),
            "rest_ms": _quantiles(rest),
            # Each stop decision's parts, in session order: which part a slow one spent its time in.
            "per_push_ms": rows}


def _slow(breakdown: dict[str, Any] | None) -> dict[str, Any] | None:
    """How many stop decisions missed the target, and the host's steal around them and around
    all of them (median cores; None without steal readings)."""
    if breakdown is None:
        return None
    rows, limit = breakdown["per_push_ms"], BRIDGE_TARGETS["stop_to_ack_p99_ms"]

    def median_steal(rs: list[dict[str, Any]]) -> float | None:
        v = [r["steal_cores"] for r in rs if r.get("steal_cores") is not None]
        return float(np.median(v)) if v else None

    slow = [r for r in rows if r["total"] > limit]
    return {"over_ms": limit, "n": len(slow), "of": len(rows), "steal_median_cores": median_steal(slow),
            "steal_median_cores_all": median_steal(rows)}


def bridge_realtime(cfg: BridgeRtConfig, out: Path | None = None) -> dict[str, Any]:
    """Run the real-time bridge session and measure it (see the module docstring).

    Args:
        cfg: The session.
        out: Where ``session.mcap`` and ``summary.json`` go (default a temporary directory,
            removed afterwards).

    Returns:
        The ``bridge_realtime`` part of ``perf.json``: latencies in ms, frame counts, rates in
        frames/s, CPU in s and cores, the targets and whether each was met.
    """
    blas_threads(1)  # as the perf benchmark and (recommended) the lab bridge run
    if out is None:
        with tempfile.TemporaryDirectory(prefix="hilbo-bench-bridge-") as tmp:
            return bridge_realtime(cfg, Path(tmp))
    out = Path(out)
    raw = asyncio.run(_measure(cfg, out))
    alone = asyncio.run(_device_alone(cfg)) if cfg.baseline_s > 0 else None
    summary, session, exo = raw["summary"], raw["session"], raw["exo"]
    n_act = len(SUIT_JOINTS[cfg.preset])
    logged = _log_counts(out / "session.mcap")
    received_total = session.device.feedback_frames
    window = _window(raw["samples"], n_act, cfg.feedback_hz, raw["threads_before_bridge"],
                     raw["thread_names"])
    overflow = int(session.endpoint.counters.get("subscriber_overflow", 0))
    stop = summary.get("stop_to_ack_ms")
    stop_samples = [1e3 * v for v in session.stop_latencies_s]
    cores = raw["cpu_s"] / raw["wall_s"]
    dropped = session.device.feedback_lost + overflow
    not_logged = received_total - logged["feedback_logged"]
    met = {
        "stop_to_ack_p99_ms": None if stop is None
        else bool(stop["p99"] < BRIDGE_TARGETS["stop_to_ack_p99_ms"]),
        "cores": bool(cores < BRIDGE_TARGETS["cores"]),
        "dropped_frames": bool(dropped == 0 and not_logged == 0),
        "feedback_rate": None if window.get("window_s") is None
        else bool(window["rate_hz"]["received"] >= 0.99 * window["rate_hz"]["target"]),
    }
    return {
        "config": asdict(cfg),
        "protocol": cfg.protocol,
        "actuators": n_act,
        "joints": list(SUIT_JOINTS[cfg.preset]),
        "load_average_at_start": list(raw["load"][0]),
        "load_average_at_end": list(raw["load"][1]),
        "wall_s": raw["wall_s"],
        "n_evaluations": summary["n_evaluations"],
        "n_early_stops": summary["n_early_stops"],
        "n_breaths": summary["n_breaths"],
        "stop_to_ack_ms": stop,
        "push_latency_ms": summary.get("push_latency_ms"),
        "push_only_ms": _quantiles([p.transfer_ms for p in logged["pushes"]]),
        "stop_to_ack_samples_ms": stop_samples,
        "stop_to_ack_breakdown": (bd := _breakdown(stop_samples, logged["pushes"], raw["samples"])),
        "slow_stop_decisions": _slow(bd),
        "force_feedback": {
            "device_sent_total": int(exo.stats.get("feedback_sent", 0)),
            "bridge_received_total": received_total,
            "lost_counter_gaps": session.device.feedback_lost,
            "subscriber_overflow": overflow,
            "logged_to_mcap": logged["feedback_logged"],
            "logged_per_actuator": logged["feedback_logged_per_actuator"],
            "not_logged": not_logged,
            "window": {k: v for k, v in window.items()
                       if k not in ("cores", "threads", "worker_cores", "steal_cores", "steal_cores_max")},
        },
        "cpu": {
            "process_cpu_s": raw["cpu_s"],
            "worker_cpu_s": raw["worker_cpu_s"],
            "proposal_worker": session.settings.proposal_worker.value,
            "worker_cores_in_window": window.get("worker_cores"),
            "machine_steal_cores_in_window": window.get("steal_cores"),
            "machine_steal_cores_max_interval": window.get("steal_cores_max"),
            "cores": cores,
            "cores_in_window": window.get("cores"),
            "threads_in_window": window.get("threads"),
            "note": "the virtual exosuit and cart run in this process and event loop: an upper "
                    "bound on the bridge's own use; process_cpu_s includes the proposal worker "
                    "process (worker_cpu_s)",
            "device_alone": alone,
            "bridge_estimate_cores": None if alone is None or window.get("cores") is None
            else window["cores"] - alone["cores"],
        },
        "can_counters": dict(session.endpoint.counters),
        # Collector pauses in this process (bridge/collector.py): automatic collections per
        # generation and the longest of each, and the session's own at its quiet points.
        "gc": {"mode": session.collector.mode.value, **session.collector.stats.to_json()},
        "events": logged["events"],
        "targets": BRIDGE_TARGETS,
        "met": met,
    }


def bridge_table(result: dict[str, Any]) -> str:
    """Markdown: the real-time measurements against :data:`BRIDGE_TARGETS`."""

    def q(d: dict[str, float] | None) -> str:
        if not d:
            return "–"
        return f"median {d['median']:.1f} ms, p99 {d['p99']:.1f} ms, max {d['max']:.1f} ms (n = {d['n']})"

    def yes(v: bool | None) -> str:
        return "–" if v is None else ("yes" if v else "no")

    fb, cpu, met = result["force_feedback"], result["cpu"], result["met"]
    w = fb["window"]
    rate = w.get("rate_hz")
    c = result["config"]
    rows = [
        ["session", f"{c['minutes']:g} min at speed {c['speed']:g}, protocol "
                    f"{result.get('protocol', 'custom')} ({c['n_explore']} exploration points, "
                    f"N = {c['max_breaths']}, {c['warmup_s']:g} s warm-ups): "
                    f"{result['n_evaluations']} evaluations, {result['n_early_stops']} early stops",
         "–", "–"],
        ["stop decision → device ack of the next profile", q(result["stop_to_ack_ms"]),
         f"p99 < {BRIDGE_TARGETS['stop_to_ack_p99_ms']:g} ms", yes(met["stop_to_ack_p99_ms"])],
        *([[label, q(bd[key]), "–", "–"] for key, label in (
            ("ask_ms", "… of which the proposal, as the session waited for it (in the worker, "
                       "started at the decision)"),
            ("compute_ms", "… … of that, ask() itself in the worker (EI; GP fit only when not "
                           "fitted ahead)"),
            ("transfer_ms", "… of which the transfer (paced segments, commit → ack)"),
            ("rest_ms", "… of which the rest (the decision's logging, the safety gate, starting "
                        "the push)"))]
          if (bd := result.get("stop_to_ack_breakdown")) else []),
        *([[f"stop decisions over {slow['over_ms']:g} ms; the host's steal around them (median) "
            "and around all", f"{slow['n']} of {slow['of']}; "
            + ("–" if slow["steal_median_cores"] is None else f"{slow['steal_median_cores']:.3f} cores")
            + ("" if slow["steal_median_cores_all"] is None
               else f", all {slow['steal_median_cores_all']:.3f} cores"), "–", "–"]]
          if (slow := result.get("slow_stop_decisions")) else []),
        *([["garbage collections started by Python (gen 0/1/2) and the longest",
             " / ".join(f"{n} ({m:.1f} ms)" for n, m in zip(g["automatic"], g["automatic_max_ms"],
                                                           strict=True))
             + f"; at quiet points {g['quiet_points']} (longest {g['quiet_max_ms']:.1f} ms)"
             + f"; between bouts {g['full']} ({g['full_max_ms']:.1f} ms) [{g['mode']}]", "–", "–"]]
          if (g := result.get("gc")) else []),
        ["every push: the transfer alone (first segment → ack)", q(result["push_only_ms"]), "–", "–"],
        ["every push (incl. the first of each bout, from its warm-up's end)", q(result["push_latency_ms"]),
         "–", "–"],
        ["feedback frames: device sent / bridge received (window)",
         "–" if rate is None else f"{w['sent']} / {w['received']} in {w['window_s']:.0f} s "
                                  f"(difference {w['dropped']})", "–", "–"],
        ["feedback frames lost (counter gaps + queue overflow), whole session",
         f"{fb['lost_counter_gaps']} + {fb['subscriber_overflow']}", "0", yes(met["dropped_frames"])],
        ["feedback frames received / logged to MCAP, whole session",
         f"{fb['bridge_received_total']} / {fb['logged_to_mcap']}", "equal", yes(met["dropped_frames"])],
        ["feedback rate received (mean, lowest 1-interval)",
         "–" if rate is None else f"{rate['received']:.0f} /s, {rate['received_min']:.0f} /s "
                                  f"(device sent {rate['sent']:.0f} /s)",
         "–" if rate is None else f"{rate['target']:.0f} /s", yes(met["feedback_rate"])],
        ["CPU of the whole process (bridge + virtual devices) and its proposal worker",
         f"{cpu['cores']:.3f} cores ({cpu['process_cpu_s']:.1f} s CPU in {result['wall_s']:.1f} s, "
         f"of which the worker {cpu.get('worker_cpu_s', 0.0):.1f} s)",
         f"< {BRIDGE_TARGETS['cores']:g} core", yes(met["cores"])],
    ]
    alone = cpu.get("device_alone")
    if alone and cpu.get("bridge_estimate_cores") is not None:
        rows.append(["CPU of the bridge, estimated (process in the window − the virtual exosuit alone)",
                     f"{cpu['bridge_estimate_cores']:.3f} cores ({cpu['cores_in_window']:.3f} − "
                     f"{alone['cores']:.3f}, exosuit alone for {alone['seconds']:.0f} s)", "–", "–"])
    if cpu.get("machine_steal_cores_in_window") is not None:
        rows.append(["CPU stolen from this virtual machine by its host (/proc/stat steal), mean and "
                     "the most in one sampling interval",
                     f"{cpu['machine_steal_cores_in_window']:.3f} cores, "
                     f"{cpu['machine_steal_cores_max_interval'] or 0.0:.3f} cores", "–", "–"])
    return markdown_table(["measurement", "value", "target", "met"], rows)
