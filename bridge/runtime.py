"""The bridge's session: one asyncio process from breaths to force profiles on the bus.

Data flow (shared/DESIGN.md "One breath through the system")::

    cart stream ─▶ breath queue ─▶ HILOptimizer.observe_breath ─▶ stop? ─▶ ask() ─▶ safety gate
                                                                              ─▶ CAN push ─▶ ack
                                                                              ─▶ device applies

Ownership: the optimizer, the current setting and the protocol phase belong to the *main* task
alone; the cart task only enqueues breaths; the CAN tasks only update the device view
(:class:`DeviceView`); every task that turns assistance off (the watchdogs, the resume policy,
the bus-failure task, the main task) asks the :class:`~bridge.supervisor.Supervisor`, the one
owner of pause, stop and assistance-off. Every task runs in one ``asyncio.TaskGroup`` so an error in any of
them surfaces and stops the session (after assistance-off) instead of dying silently.

Time: estimation, stopping and budgets use the cart's breath time. A new setting's clock starts
at the last breath received before the device reported the setting *active* (it switches at a
gait-cycle boundary): at most one breath interval (~3 s) early against a metabolic time
constant of ~40 s, and independent of any clock offset between the cart and this PC. Wall clock
(``time.monotonic``) is used only by watchdogs and latency measurements.
"""

from __future__ import annotations

import asyncio
import contextlib
import enum
import logging
import math
import time
from collections.abc import AsyncIterator, Callable
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from bridge.collector import Collector, GcMode
from bridge.errors import UnsafeProfileError
from bridge.log import EventLevel, LogError, SessionLog
from bridge.loop_monitor import DEFAULT_PERIOD_S as DEFAULT_LOOP_MONITOR_PERIOD_S
from bridge.loop_monitor import LoopMonitor
from bridge.outcome import SessionEnd, recommendation, session_end
from bridge.proposals import Asked, ProposalWorker, WorkerKind
from bridge.safety import AdmittedProfile
from bridge.supervisor import PushRefused, Supervisor
from drivers.errors import DriverError, ProfilePushAborted, ProfilePushError
from drivers.exosuit import (
    CLEARABLE_FAULTS,
    DEFAULT_PACE_S,
    HEARTBEAT_WATCHDOG_S,
    PERSON_FAULTS,
    POLICY_CLEARABLE_FAULTS,
    AssistanceOffReason,
    CanEndpoint,
    DeviceFault,
    DeviceMode,
    DeviceStatus,
    FaultRecovery,
    ForceFeedback,
    describe_faults,
    fault_names,
    pack_tables,
)
from hilbo_core import HILOptimizer, HyperparameterFit, brockway_watts
from hilbo_core.protocol import Action, ActionKind, ProtocolStateError, SessionPhase, SessionProtocol
from hilbo_core.types import BreathRecord

__all__ = [
    "BridgeSession",
    "Command",
    "DeviceView",
    "RuntimeSettings",
    "SessionStatus",
]

logger = logging.getLogger(__name__)

# The watchdog woke this much later than asked: this event loop stalled (one device status
# period, PROTOCOL.md), and it waits for the receive path at most this many periods.
_STALL_GRACE_S = 0.020
_MAX_STALL_DEFERRALS = 3


class ProfileGate(Protocol):
    """What the session needs from the safety layer (bridge.safety.SafeProfileGate)."""

    def admit(self, params: dict[str, float]) -> AdmittedProfile | None:
        """Build and check the profiles of ``params``; raise when anything is out of limits.
        None: the setting is walked without assistance (``hilbo validate``'s unassisted
        condition): nothing is pushed and assistance is off."""

    def acknowledge(self, admitted: AdmittedProfile) -> None:
        """Record that the device acknowledged ``admitted`` (the reference for rate limits)."""

    def assistance_off(self) -> None:
        """Assistance went off: the next profile has no rate-of-change baseline."""

    @property
    def rejections_exhausted(self) -> bool:
        """Too many consecutive proposals were rejected."""


class Command(enum.Enum):
    """Operator commands."""

    PAUSE = "pause"
    RESUME = "resume"
    STOP = "stop"


@dataclass(frozen=True)
class RuntimeSettings:
    """Protocol and supervision settings of a session (from the config's [protocol]/[can]/[watchdog]).

    Attributes:
        auto_resume_s: The resume policy of headless runs: a pause the operator did not ask
            for ends once the device and the cart have been healthy this long (wall s;
            simulations, ``hilbo run --auto-resume S``, ``[watchdog] auto_resume_s``); None:
            only the operator resumes.
        max_auto_resumes: Automatic resumes per session at most; the next pause that would
            need one stops the session (a headless run never waits for nobody).
        operator_present: A person at the PC can press ``r`` (the operator view reads the
            keyboard). After a fault that only a person may resume from (the emergency stop;
            drivers/exosuit/faults.py, ``FaultRecovery.PERSON``) the resume policy waits for
            that person, or, with nobody to press ``r``, stops the session.
        device_timeout_s: Device status silence that triggers assistance-off (wall s): the
            AssistanceOff is on the bus within this time of the last status (see
            ``device_margin_s``).
        device_margin_s: How much earlier than ``device_timeout_s`` the watchdog acts (wall s;
            capped at a quarter of the timeout): :attr:`device_silence_limit_s`.
        watchdog_period_s: How often the watchdog looks at the device's faults and the cart
            (wall s; the device's silence is checked at its deadline instead).
        cart_timeout_s: Breath silence after which estimation pauses (wall s).
        apply_timeout_s: How long to wait for the device to report a pushed profile active.
        push_timeout_s, push_retries, pace_s: Profile push (see CanEndpoint.push_profile).
        heartbeat_period_s: Bridge heartbeat period (s).
        feedback_log_period_s: Force feedback is logged in batches this long (s).
        status_log_period_s: Device status is logged at every change, and an unchanged one again
            every this many seconds per actuator (s).
        n_actuators: Actuators whose status must be alive.
        proposal_worker: Where proposals and hyperparameter fits run (bridge/proposals.py).
        gc: When full garbage collections may stop the event loop (bridge/collector.py).
        loop_monitor_period_s: How often the event-loop stall monitor wakes (real s; its
            resolution, below half the device's heartbeat watchdog; bridge/loop_monitor.py).
    """

    auto_resume_s: float | None = None
    max_auto_resumes: int = 10
    operator_present: bool = False
    device_timeout_s: float = 0.25
    device_margin_s: float = 0.025
    watchdog_period_s: float = 0.01
    cart_timeout_s: float = 20.0
    apply_timeout_s: float = 5.0
    push_timeout_s: float = 0.25
    push_retries: int = 3
    pace_s: float = DEFAULT_PACE_S
    heartbeat_period_s: float = 0.02
    feedback_log_period_s: float = 0.1
    status_log_period_s: float = 0.5
    n_actuators: int = 2
    proposal_worker: WorkerKind = WorkerKind.PROCESS
    gc: GcMode = GcMode.FREEZE
    loop_monitor_period_s: float = DEFAULT_LOOP_MONITOR_PERIOD_S

    @property
    def device_silence_limit_s(self) -> float:
        """Device status silence after which the watchdog commands assistance-off (wall s).

        The configured timeout is a promise about the bus: AssistanceOff follows the last good
        DeviceStatus within ``device_timeout_s`` (drivers/PROTOCOL.md, "Heartbeats and their
        timeouts"). Between that status on the bus and the AssistanceOff frame on it lie (a) the
        status's way into the session (python-can's reader, the endpoint's receive task, the
        status task: a few turns of the event loop, each late when the loop is busy; and the
        2 ms the check gives statuses still on their way before it decides), (b) the
        lateness of the timer that wakes the check (the scheduler, on a PC whose cores other
        processes keep busy), and (c) the pause's event and the frame's transmission (well
        under a millisecond at 1 Mbit/s). The margin covers all three: 25 ms by default, a
        quarter of the lab's 100 ms (on the virtual devices at real time, 2 cores at a load
        average of 4-10, the off came 76-99 ms after the last status, idle and beside two CPU
        burners: ``hilbo bench watchdog``); a stall of the loop longer than the margin (the
        loop monitor logs those over 50 ms; 250-1400 ms at a load average of 12-17) still
        makes it late. It is capped at a quarter of the timeout, so that a
        short timeout still waits for more than a missed status (40 ms: 30 ms of silence, 1.5
        status periods of 20 ms).
        """
        return self.device_timeout_s - min(self.device_margin_s, self.device_timeout_s / 4)


@dataclass
class DeviceView:
    """What the bridge knows about the exosuit (updated by the CAN tasks only)."""

    last_status_wall: dict[int, float] = field(default_factory=dict)
    status: dict[int, DeviceStatus] = field(default_factory=dict)
    #: ForceFeedback frames received by the feedback task.
    feedback_frames: int = 0
    #: ForceFeedback frames missing from the received sequence: the gaps in each actuator's
    #: 8-bit frame counter (lost on the bus, in a queue, or dropped by a full subscription).
    feedback_lost: int = 0
    feedback_counter: dict[int, int] = field(default_factory=dict)

    def active_version(self, n_actuators: int) -> int | None:
        """The profile version every actuator runs, or None when they disagree or are unknown."""
        versions = {s.profile_version_active for a, s in self.status.items() if a < n_actuators}
        if len(versions) != 1 or len(self.status) < n_actuators:
            return None
        return versions.pop()

    def faults(self, n_actuators: int) -> DeviceFault:
        """The faults any actuator reports now (the union of their last statuses)."""
        out = DeviceFault(0)
        for a, st in self.status.items():
            if a < n_actuators:
                out |= DeviceFault(int(st.faults))
        return out

    def silent_for(self, now: float, n_actuators: int) -> float:
        """Seconds since the stalest actuator's last status (inf before any)."""
        last = self.stalest_status(n_actuators)
        return math.inf if last is None else now - last

    def stalest_status(self, n_actuators: int) -> float | None:
        """Wall time of the stalest actuator's last status (None until every one reported)."""
        if len(self.last_status_wall) < n_actuators:
            return None
        return min(self.last_status_wall[a] for a in range(n_actuators))


@dataclass
class SessionStatus:
    """A snapshot for the operator view (written by the main task, read by the display).

    ``state`` is not stored: it is the supervisor's (the one owner of pause/stop/assist).
    """

    supervisor: Supervisor | None = field(default=None, repr=False)
    #: Called with every event line as it happens (a run without the live view prints them).
    listeners: list[Callable[[str], None]] = field(default_factory=list, repr=False)
    bout: str = "warm-up"
    evaluation: int = 0
    params: dict[str, float] | None = None
    breaths_in_setting: int = 0
    mean_w: float | None = None
    sd_w: float | None = None
    last_decision: str = ""
    best_mean_w: float | None = None
    breath_time_s: float = 0.0
    budget_used_s: float = 0.0
    budget_s: float | None = None
    #: When the session is expected to end (session time: walking s since the first breath).
    expected_end_s: float | None = None
    device: str = "unknown"
    cart: str = "waiting"
    events: list[str] = field(default_factory=list)
    # The operator view's best_mean_w is opt.best()'s mean: the same quantity as the summary's.
    best_params: dict[str, float] | None = None  # opt.best()'s setting
    best_sd_w: float | None = None  # sqrt of opt.best()'s variance, W
    device_faults: dict[int, int] = field(default_factory=dict)  # actuator -> DeviceFault bits
    #: Why the session ended, once it has (the last frame of the operator view says so).
    ended: SessionEnd | None = None
    #: The parameters' units, for the display.
    units: dict[str, str] = field(default_factory=dict)

    @property
    def state(self) -> str:
        """The supervision state line ("starting", "running", "paused: why", "ended: why")."""
        if self.ended is not None:
            return f"ended: {self.ended.text}"
        return "starting" if self.supervisor is None else self.supervisor.describe()

    def event(self, text: str) -> None:
        """Remember a recent event for the display."""
        self.events.append(text)
        del self.events[:-6]
        for listener in self.listeners:
            listener(text)


class _Paused(Exception):
    """Raised inside the measurement loop when the session pauses (internal control flow)."""


class _Remeasure(Exception):
    """Raised inside the measurement loop when the cart's clock was re-anchored (a cart restart
    or a time jump): the breaths of the setting being measured are not one series any more."""


#: How long the device watchdog lets statuses already received reach the session before it
#: declares the device silent (s; part of RuntimeSettings.device_margin_s).
_RECEIVE_GRACE_S = 0.002

#: The operator view's name of the bout a protocol phase belongs to.
_BOUT_OF = {
    SessionPhase.WARM_UP_EXPLORATION: "exploration", SessionPhase.EXPLORATION: "exploration",
    SessionPhase.BOUT_PAUSE: "optimization", SessionPhase.WARM_UP_OPTIMIZATION: "optimization",
    SessionPhase.OPTIMIZATION: "optimization", SessionPhase.ENDED: "ended",
}


@dataclass(frozen=True)
class _Setting:
    """The setting being measured: its evaluation index, its session start time (s) and the
    cart validator's re-anchors when it began."""

    index: int
    t_start: float
    reanchors: int


class _Stopped(Exception):
    """Raised when the operator or a signal stops the session (internal control flow)."""


@dataclass
class _Breaths:
    """Breath queue with arrival bookkeeping (owned by the cart task; read by the others)."""

    queue: asyncio.Queue[BreathRecord] = field(default_factory=asyncio.Queue)
    last_wall: float | None = None
    last_t: float | None = None
    count: int = 0
    ended: bool = False
    #: The validator's re-anchors seen so far (drivers/cart/validate.py, BreathValidator.reanchors).
    reanchors: int = 0


class BridgeSession:
    """One HIL session: the optimizer driven by breaths, its proposals pushed to the exosuit.

    Args:
        optimizer: A new or resumed optimizer.
        gate: The safety layer; the only source of profiles that may be sent.
        endpoint: An open CAN endpoint.
        breaths: The cart's validated breath stream.
        log: The session log.
        settings: Supervision settings.
        protocol: The walking protocol (warm-ups, bouts, the pause between them, the session's
            time); for a resumed optimizer, :meth:`SessionProtocol.resumed`.
        clock: Wall clock for watchdogs (monotonic seconds); injectable for tests.
    """

    def __init__(
        self,
        optimizer: HILOptimizer,
        gate: ProfileGate,
        endpoint: CanEndpoint,
        breaths: AsyncIterator[BreathRecord],
        log: SessionLog,
        settings: RuntimeSettings | None = None,
        *,
        protocol: SessionProtocol,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        self.opt = optimizer
        self.gate = gate
        self.endpoint = endpoint
        self._stream = breaths
        self.log = log
        self.settings = settings or RuntimeSettings()
        self.protocol = protocol
        self._setting: _Setting | None = None
        self._clock = clock
        self.device = DeviceView()
        #: The one owner of pause, stop, assistance, the heartbeat's state and the gate's
        #: baseline (bridge/supervisor.py); every other task asks it.
        self.supervisor = Supervisor(endpoint, gate, on_event=self._event, health=self._health)
        self.status = SessionStatus(supervisor=self.supervisor, units=optimizer.space.units)
        # A source paced by its reader (a replay at speed = "max") gets back-pressure: one
        # breath waits in the queue at most, and none is read before the session is ready for
        # it, so the session takes every breath it is given instead of finding a whole file
        # queued (or dropped) by the time its proposal worker answers.
        self._pull = bool(getattr(breaths, "paced_by_reader", False))
        self._breaths = _Breaths(queue=asyncio.Queue(maxsize=1 if self._pull else 0))
        self._ready_for_breaths = asyncio.Event()
        #: Set while the protocol waits for a breath that has not arrived (nothing else is in
        #: flight: a simulation may skip its clock to the next one, bridge/sim/virtual.py).
        self.breath_wanted = asyncio.Event()
        self._commands: asyncio.Queue[Command] = asyncio.Queue()
        self._version = 0
        self._auto_resumes = 0
        # Wall time from the decision to change the setting to the device's ack of the commit:
        # every push (the first of a bout counts from the end of its warm-up) and the pushes that
        # follow a stop decision (the latency target: stop decision -> new profile committed on the bus).
        self.latencies_s: list[float] = []
        self.stop_latencies_s: list[float] = []
        self._t_stop: float | None = None  # wall time of the last stop decision not yet pushed
        # The supervisor's pause count at that decision: a pause between the decision and the ack
        # puts the pause's length into the latency, which is then no stop -> ack latency (the
        # log's analysis, bridge/bench/bridge_perf.py, leaves those out as well).
        self._t_stop_pauses = 0
        self._worker = ProposalWorker(self.settings.proposal_worker)
        #: The garbage-collection policy; its ``stats`` hold the collections' pauses.
        self.collector = Collector(self.settings.gc)
        #: Every stall of the event loop (it sends the heartbeat), counted once a device has
        #: reported: none may exceed half the device's heartbeat watchdog (drivers/PROTOCOL.md).
        self.loop_monitor = LoopMonitor(HEARTBEAT_WATCHDOG_S / 2, self._on_loop_stall,
                                        connected=lambda: bool(self.device.status),
                                        period_s=self.settings.loop_monitor_period_s)
        self._worker_lost_logged = False
        # A hyperparameter fit running ahead of the next proposal (refit_lag >= 1).
        self._fit_ahead: tuple[HyperparameterFit, asyncio.Task[Any]] | None = None
        self._next_ask: asyncio.Task[Any] | None = None  # started at a stop decision
        # A pause abandoned a setting: measure it again (_propose). A resumed session whose
        # log ended between such a cancel and the re-proposal does the same.
        self._ask_again = optimizer.cancelled_params is not None
        self.records: list[dict[str, Any]] = []  # completed evaluations with session times
        self._t_session0: float | None = None
        #: Why the session ended (the first cause wins); None while it runs.
        self.end_reason: SessionEnd | None = None
        #: Called with every breath the protocol accounts.
        self.breath_listeners: list[Callable[[BreathRecord], None]] = []
        #: ``(n, reason)``: end the session with ``reason`` as soon as ``n`` evaluations are
        #: complete, before anything else is asked or pushed (hilbo validate: its conditions are
        #: the only settings the walk may apply).
        self.end_after: tuple[int, SessionEnd] | None = None
        #: Names an evaluation by its index in the event lines (hilbo validate: its condition).
        self.evaluation_name: Callable[[int], str] | None = None

    @property
    def proposal_worker(self) -> ProposalWorker:
        """Where this session's proposals and hyperparameter fits run."""
        return self._worker

    # ------------------------------------------------------------------ public control
    def command(self, cmd: Command) -> None:
        """Queue an operator command (call from the event loop's thread)."""
        self._commands.put_nowait(cmd)

    def interrupt(self) -> None:
        """Stop the session for a signal (Ctrl-C, SIGTERM): as the operator's stop, with its
        own end reason (``hilbo run`` exits 130)."""
        self.finish(SessionEnd.INTERRUPTED)

    def finish(self, reason: SessionEnd) -> None:
        """Stop the session as the operator's stop does (assistance off, the log closed), with
        ``reason`` as its end reason (:meth:`interrupt`: a signal)."""
        self._ended_by(reason)
        self._commands.put_nowait(Command.STOP)

    def _ended_by(self, reason: SessionEnd) -> None:
        if self.end_reason is None:
            self.end_reason = reason

    async def run(self) -> dict[str, Any]:
        """Run the session to its end (budget spent, stop command, or fatal error).

        Returns:
            Summary fields: evaluations, counts, best setting.
        """
        # The starting point of a resume: without it a crash before the first completed
        # evaluation could not be resumed.
        self.log.log_optimizer_state(self.opt, reason="start")
        self._status_from_optimizer()
        # What was walked before (a resume's estimate): a crash of this run is resumed from it
        # plus this log's breaths (bridge/run.py).
        self._event("session_start", f"session started ({self.opt.phase.value})",
                    walked_before_s=self.protocol.session_used_s)
        ok = False
        try:
            with self.collector:
                async with self._worker:  # the session's walking starts once it answers
                    await self._run_tasks()
            ok = True
        except* _Stopped:
            ok = True
        finally:
            # A stop whose cause was not recorded is the operator's; anything else an error.
            self._ended_by(SessionEnd.OPERATOR_STOP if ok else SessionEnd.ERROR)
            self.status.ended = self.end_reason
            await self.supervisor.assistance_off(
                AssistanceOffReason.OPERATOR_STOP if self.supervisor.stopped
                else AssistanceOffReason.SESSION_END, "session end")
            self._log_counters()
            self.log.log_event("gc", f"garbage collection ({self.collector.mode.value})",
                               mode=self.collector.mode.value, **self.collector.stats.to_json())
            with contextlib.suppress(DriverError):
                await self.endpoint.stop_heartbeat()
            # A failed session's log says how it ended too (its error goes on up to the caller,
            # which writes the summary: bridge/run.py).
            self._log_end()
        return self.summary()

    def _log_end(self) -> None:
        """The end of the session in the log: the optimizer's last state (a fit made ahead may
        have been applied since the last evaluation's snapshot; `hilbo review` recommends from
        it) and the ``session_end`` event."""
        self.log.log_optimizer_state(self.opt, reason="end")
        loop = self.loop_monitor.stats
        reason = self.end_reason or SessionEnd.OPERATOR_STOP
        self._event("session_end", f"session ended ({reason.text}) after {len(self.records)} "
                    f"evaluations; worst event-loop stall {loop.worst_stall_ms:.1f} ms",
                    loop=loop.to_json(), end_reason=reason.value,
                    walking=self.protocol.walking.to_json())

    def _status_from_optimizer(self) -> None:
        """The operator view of a resumed session starts from what the log holds: the
        evaluations done, the best so far, the optimisation time walked."""
        n = len(self.opt.evaluations)
        if n == 0:
            return
        self.status.evaluation = n
        self.status.best_params, self.status.best_mean_w, best_var = self.opt.best()
        self.status.best_sd_w = math.sqrt(best_var)
        self.status.budget_used_s = float(self.opt.budget_used["seconds"])

    async def _run_tasks(self) -> None:
        try:
            async with self.loop_monitor, asyncio.TaskGroup() as tg:
                tasks = [
                    tg.create_task(self._cart_task(), name="cart"),
                    tg.create_task(self._status_task(), name="device-status"),
                    tg.create_task(self._feedback_task(), name="force-feedback"),
                    tg.create_task(self._watchdog_task(), name="watchdog"),
                    tg.create_task(self._device_silence_task(), name="device-watchdog"),
                    tg.create_task(self._command_task(), name="commands"),
                    tg.create_task(self._bus_failure_task(), name="bus-failure"),
                    tg.create_task(self._resume_policy_task(), name="resume-policy"),
                ]
                self.endpoint.start_heartbeat(self.settings.heartbeat_period_s)
                try:
                    await self._worker_started()
                    await self._main()
                finally:
                    for t in tasks:
                        t.cancel()
        finally:
            await self._drop_fit_ahead()

    async def _worker_started(self) -> None:
        """Wait until the proposal worker answers, then start the session's walking time.

        Starting the worker process (numpy, scipy) takes a second or two, several on a busy
        host. That is the bridge's start, not walked session time: in the lab it delays the
        warm-up by that long; at ``hilbo sim --speed max`` (100x) each second of it was more
        than a minute of a simulated session's budget (12 s on a loaded 2-core host: 20
        minutes of a 30-minute session). Breaths that came in meanwhile were walked before the
        session: the cart task has logged them, the protocol never sees them, and its clock
        starts at the next one.
        """
        if self._worker.in_process:  # a process starts; a thread would need no wait
            self.status.event("starting the proposal worker")
            await self._worker.worker_pid()
        self._ready_for_breaths.set()
        b = self._breaths
        dropped = 0
        while not b.queue.empty():
            b.queue.get_nowait()
            dropped += 1
        if dropped:
            b.last_t = None  # the protocol's clock starts at the next breath
            self._event("breaths_before_start",
                        f"{dropped} breaths arrived while the proposal worker started; the "
                        "session's walking time starts at the next one", n_breaths=dropped)

    def summary(self) -> dict[str, Any]:
        """The summary.json fields of shared/DESIGN.md (without simulation truth)."""
        out: dict[str, Any] = {
            "n_evaluations": len(self.records),
            # A resumed session's: with the evaluations of the logs it continues (the
            # recommendation is made from all of them).
            "n_evaluations_session": len(self.opt.evaluations),
            "n_early_stops": sum(r["stopped_early"] for r in self.records),
            "n_breaths": self._breaths.count,
            "evaluations": self.records,
            "best_params": None, "best_mean": None, "best_var": None,
            "push_latency_ms": _quantiles_ms(self.latencies_s),
            "stop_to_ack_ms": _quantiles_ms(self.stop_latencies_s),
            # Session time is walking time (a lab has the hour it has): where every walked second went.
            "walking": self.protocol.walking.to_json(),
            "end_reason": None if self.end_reason is None else self.end_reason.value,
            "recommendation": None,
            "loop": self.loop_monitor.stats.to_json(),
        }
        if self.opt.evaluations:
            params, mean, var = self.opt.best()
            out.update(best_params=params, best_mean=mean, best_var=var)
            out["recommendation"] = recommendation(
                params, mean, var, evaluations=[e.to_json() for e in self.opt.evaluations],
                method=self.opt.config.recommend.value, units=self.opt.space.units)
        conf = self.opt.confirmation  # the recommendation measured in full at the end
        out["confirmation"] = None if conf is None else conf.to_json()
        return out

    # ------------------------------------------------------------------ main protocol
    async def _main(self) -> None:
        """The session's walking protocol (hilbo_core/protocol.py: warm-ups, the two bouts, the
        pause between them, the budget in walking time), driven by the cart's breaths: the one
        protocol loop of the process (the simulations run the same machine through ``drive``)."""
        p = self.protocol
        act = p.start()
        while act.kind is not ActionKind.END:
            if self.supervisor.stopped:
                p.stop()
                raise _Stopped
            try:
                act = await self._step(act)
            except (_Paused, _Remeasure) as err:
                act = await self._abandon(err)
        self.opt.cancel_current()  # a setting proposed but never measured
        if p.end_reason is not None:
            self._ended_by(session_end(p.end_reason))
        if self.end_after is not None and self.end_reason is self.end_after[1]:
            reason = self.end_reason.text  # the walk's own end (hilbo validate), not a stop
        else:
            reason = p.end_reason.value if p.end_reason is not None else "stopped"
        self._event("budget_spent", f"session time spent ({reason}): "
                    f"{p.walking.session_s / 60:.1f} min walked")

    async def _step(self, act: Action) -> Action:
        """Do what ``act`` says, then give the next breath to the protocol; its next action.

        Raises:
            _Paused: The session paused (the caller abandons the setting, waits, warms up).
            _Remeasure: The cart's clock was re-anchored during a measurement.
        """
        p = self.protocol
        if act.kind is ActionKind.PAUSE_BETWEEN_BOUTS:
            end = await self._bout_pause()
            return end or p.on_resume(self._breaths.last_t)
        if self.supervisor.paused:
            raise _Paused
        if act.kind is ActionKind.WARM_UP:
            self.status.bout = f"warm-up ({_BOUT_OF[act.phase]})"
            if act.starts:
                self._t_stop = None  # the next push answers the warm-up's end, not a stop decision
                await self.supervisor.assistance_off(AssistanceOffReason.SESSION_END, "warm-up")
        elif act.kind is ActionKind.PROPOSE:
            # No warm-up and no breath yet (or only breaths dropped at the start): the clock starts.
            if self._breaths.last_t is None:
                act = self._on_breath(await self._next_breath())
                if act.kind is not ActionKind.TRANSITION:
                    return act
            if not await self._propose(act):
                return p.on_setting_dropped()
            p.on_setting_applied(self._breaths.last_t)
        rec = await self._next_breath()
        if self._setting is not None and self._breaths.reanchors != self._setting.reanchors:
            raise _Remeasure
        act = self._on_breath(rec)
        if act.kind is ActionKind.MEASURE:
            return await self._measure(rec, act)
        return act

    async def _abandon(self, err: _Paused | _Remeasure) -> Action:
        """The setting being proposed or measured is given up (a pause, or a re-anchored cart
        clock); after a pause, wait for the resume. Returns the protocol's next action."""
        p = self.protocol
        why = (f"the pause ({self.supervisor.pause_reason})" if isinstance(err, _Paused)
               else "the cart's clock re-anchoring")
        self._setting = None
        # A fit made ahead is applied with the cancel and recorded by its snapshot (see
        # _measure): the setting's re-proposal after the pause uses it, as before the pause.
        applied = await self._collect_fit_ahead()
        dropped = self.opt.cancel_current()
        self._ask_again = dropped is not None
        if dropped is not None or applied:
            self.log.log_optimizer_state(self.opt, reason="cancel")
        if dropped is not None:
            self._event("evaluation_cancelled",
                        f"setting abandoned by {why}; it is measured again when the session resumes")
        if isinstance(err, _Remeasure):
            return p.on_setting_dropped()
        act = p.on_pause()
        if act.kind is ActionKind.END:
            return act
        end = await self._wait_resumed()
        if end is not None:
            return end
        act = p.on_resume(self._breaths.last_t)
        self._log_recovery(act)
        return act

    async def _propose(self, act: Action) -> bool:
        """Ask for the next setting, push it and wait until the device runs it.

        Returns:
            False when the safety limits refused the setting (nothing was sent).
        """
        t_stop, self._t_stop = self._t_stop, None
        t_decided = t_stop if t_stop is not None else self._clock()
        # The GP work takes tens of ms: off the loop (a worker process by default, so it does
        # not compete with the CAN traffic for the GIL). Only this task touches the optimizer.
        # After a stop decision the ask was started at the decision (_start_next_ask).
        asked = self._asked_again()
        if asked is None:
            task, self._next_ask = self._next_ask, None
            if task is None:
                task = await self._start_next_ask()
            asked = await task
        self.opt, params = asked.opt, asked.params
        if self._worker.lost is not None and not self._worker_lost_logged:
            self._worker_lost_logged = True
            self._event("proposal_worker_lost", self._worker.lost)
        self.status.bout = _BOUT_OF[act.phase]
        index = len(self.opt.evaluations)

        def log_proposal() -> None:
            self.log.log_proposal(params, index=index, phase=self.opt.phase.value,
                                  t_s=self._breaths.last_t, incumbent=self.opt.incumbent,
                                  compute_ms=1e3 * asked.compute_s, total_ms=1e3 * asked.total_s,
                                  to_worker_ms=1e3 * asked.to_worker_s,
                                  from_worker_ms=1e3 * asked.from_worker_s,
                                  worker="process" if self._worker.in_process else "thread")

        try:
            admitted = self.gate.admit(params)
        except UnsafeProfileError as err:
            log_proposal()
            # Never transmit what the limits forbid, and never clip (bridge/safety.py): nothing
            # is sent, the device keeps its last acknowledged profile, the setting is dropped
            # and the optimizer asked again; after too many in a row, assistance-off and pause.
            self.opt.cancel_current(again=False)
            self._t_stop = t_stop  # the next proposal still answers that stop decision
            self.log.log_optimizer_state(self.opt, reason="cancel")
            self.log.log_event("unsafe_proposal", str(err), verdict=err.verdict.to_json(), params=params)
            self.status.event(f"proposal rejected by the limits: {err}")
            if self.gate.rejections_exhausted:
                await self.supervisor.pause(AssistanceOffReason.LIMIT_VIOLATION,
                                            "too many proposals rejected by the safety limits; "
                                            "check [limits] against [space]")
            return False
        if admitted is None:
            # Walked without assistance (hilbo validate's unassisted condition): nothing to push.
            log_proposal()
            await self.supervisor.assistance_off(AssistanceOffReason.SESSION_END, "unassisted condition")
        else:
            self._version = self._version % 255 + 1
            await self._push(admitted, self._version, index, log_first=log_proposal)
            latency = self._clock() - t_decided
            self.latencies_s.append(latency)
            if t_stop is not None and self._t_stop_pauses == self.supervisor.pauses:
                self.stop_latencies_s.append(latency)
            await self._wait_applied(self._version)
        # The new setting's measurement starts: the next stop decision is breaths away, so a
        # collection costs nothing now (bridge/collector.py).
        self.collector.quiet_point()
        self._start_fit_ahead()
        t0 = self._breaths.last_t if self._breaths.last_t is not None else 0.0
        self._setting = _Setting(index, self._session_time(t0), self._breaths.reanchors)
        self.status.evaluation, self.status.params = index + 1, params
        self.status.breaths_in_setting, self.status.mean_w, self.status.sd_w = 0, None, None
        return True

    def _asked_again(self) -> Asked | None:
        """After a pause abandoned a setting: that same setting again (HILOptimizer.ask_again:
        no GP work, so nothing goes to the worker), or None to ask for a new one."""
        again, self._ask_again = self._ask_again, False
        params = self.opt.ask_again() if again and self._next_ask is None else None
        return None if params is None else Asked(self.opt, params, 0.0, 0.0, 0.0, 0.0)

    def _log_recovery(self, act: Action) -> None:
        """Say how the session goes on after a pause: at once (a short pause) or warmed up."""
        pause_s = self.protocol.last_pause_s
        limit_s = self.protocol.config.short_pause_s
        walked = "" if pause_s is None else f"{pause_s:.0f} s of walking paused; "
        if act.kind is ActionKind.WARM_UP and act.starts:
            text = f"{walked}longer than {limit_s:g} s: a warm-up first"
        elif act.kind in (ActionKind.WARM_UP, ActionKind.PROPOSE):
            text = f"{walked}at most {limit_s:g} s: no new warm-up" + (
                ", the abandoned setting is measured again at once"
                if act.kind is ActionKind.PROPOSE and self._ask_again else "")
        else:
            return
        # In the log only: the view already says "resumed" and then shows the warm-up or the
        # setting being pushed.
        logger.info("recovery: %s", text)
        self.log.log_event("recovery", text, pause_s=pause_s, short_pause_s=limit_s,
                           warm_up=bool(act.kind is ActionKind.WARM_UP and act.starts))

    async def _measure(self, rec: BreathRecord, act: Action) -> Action:
        """Give a measured breath to the optimizer; close the evaluation when the stopping rule
        (or the end of the session's time, ``act.final``) says so. Returns the next action."""
        p, setting = self.protocol, self._setting
        if setting is None or act.t_setting_s is None:
            raise ProtocolStateError("a measured breath without a setting being measured")
        watts = brockway_watts(rec.vo2_ml_min, rec.vco2_ml_min)
        step = self.opt.observe_breath(act.t_setting_s, watts)
        self.status.breaths_in_setting = step.index + 1
        self.status.mean_w, self.status.sd_w = step.mean, math.sqrt(step.var)
        self.log.log_step(step, index=setting.index, t_setting_s=act.t_setting_s, watts=watts,
                          t_s=rec.t_s, incumbent=self.opt.incumbent)
        if step.decision is not None:
            d = step.decision
            self.status.last_decision = f"{d.reason.name.lower()} z={d.z:+.2f}"
        self.status.budget_used_s = p.walking.optimization_s
        ev = step.evaluation if step.stop else None
        if ev is None and act.final:
            ev = self.opt.close_current()  # the session's time ran out in this evaluation
            if ev is None:  # an exploration evaluation cut short: Algorithm 2 needs it whole
                self._setting = None
                return p.on_setting_dropped()
        if ev is None:
            return act
        self._setting = None
        nxt = p.on_evaluation_done()
        if (self.end_after is not None and nxt.kind is not ActionKind.END
                and len(self.opt.evaluations) >= self.end_after[0]):
            self._ended_by(self.end_after[1])
            nxt = p.stop()
        if nxt.kind is ActionKind.PROPOSE and step.stop and not self.supervisor.paused:
            self._t_stop, self._t_stop_pauses = self._clock(), self.supervisor.pauses
        # The hyperparameters fitted ahead are applied here, whatever comes next (a proposal, a
        # warm-up, the pause between the bouts), and the snapshot below records them before
        # the session awaits anything: every state the optimizer is in at an await point can
        # be rebuilt from the log (bridge/log/resume.py replays asks and breaths, not fits).
        # At the session's end nothing uses them, and an await before the observation is logged
        # would leave a log without the evaluation the session's time just closed.
        if nxt.kind is not ActionKind.END:
            await self._collect_fit_ahead()
        if nxt.kind is ActionKind.PROPOSE:
            # The next proposal starts now, on a copy taken now; the worker gets it once this
            # task next awaits, after the logging below (the snapshot: 2 ms at 60 evaluations,
            # 4-9 ms at 160, measured): the snapshot must reach the file before anything the
            # session awaits, where a kill would leave a log without it.
            self._begin_confirmation_if_due()  # before the snapshot below, which records it
            self._next_ask = self._worker.start_ask(self.opt)
        t_end = self._session_time(rec.t_s)
        self.records.append({**ev.to_json(), "t_start": setting.t_start, "t_end": t_end})
        self.log.log_observation(ev, t_start=setting.t_start, t_end=t_end, t_s=rec.t_s)
        self.log.log_optimizer_state(self.opt, reason="evaluation", t_s=rec.t_s)
        self.status.best_params, self.status.best_mean_w, best_var = self.opt.best()
        self.status.best_sd_w = math.sqrt(best_var)
        self.status.expected_end_s = self._expected_end_s()
        name = "" if self.evaluation_name is None else f" ({self.evaluation_name(ev.index)})"
        self.status.event(f"eval {ev.index + 1}{name}: {ev.mean:.0f} W, {ev.breaths} breaths, {ev.reason}")
        return nxt

    # ------------------------------------------------------------------ hyperparameters ahead
    def _start_fit_ahead(self) -> None:
        """Fit the GP hyperparameters on the completed evaluations while this one is measured
        (``refit_lag`` >= 1), so the proposal after the stop decision only conditions the GP
        and maximises EI: the fit is off the stop -> push path (its latency target)."""
        if not self.opt.config.refit_lag or self._fit_ahead is not None:
            return
        fit = self.opt.hyperparameter_fit()
        if fit is not None:
            self._fit_ahead = (fit, asyncio.ensure_future(self._worker.fit(fit)))

    async def _collect_fit_ahead(self, *, apply: bool = True) -> bool:
        """Keep the result of the fit made ahead (waiting for it if it still runs: a fit takes
        tens of ms, a measurement at least a breath).

        The caller logs an optimizer snapshot right after (no await in between) when this
        returns True: the log records every state a resume must rebuild.

        Args:
            apply: False: wait for the fit and drop its result.

        Returns:
            True when hyperparameters were applied to the optimizer.
        """
        if self._fit_ahead is None:
            return False
        fit, task = self._fit_ahead
        self._fit_ahead = None
        try:
            hyp = await task
        except Exception as err:
            logger.exception("hyperparameter fit ahead of the proposal failed")
            self._event("fit_ahead_failed", f"hyperparameter fit on {fit.n_obs} observations failed "
                        f"({err!r}); the proposal fits them itself")
            return False
        return apply and self.opt.apply_hyperparameters(fit, hyp)

    async def _drop_fit_ahead(self) -> None:
        """At the session's end: cancel a fit made ahead and an ask started at a stop decision."""
        task, self._next_ask = self._next_ask, None
        await _cancel_and_wait(task, "a proposal started at the last stop decision")
        fit, self._fit_ahead = self._fit_ahead, None
        await _cancel_and_wait(None if fit is None else fit[1], "a hyperparameter fit ahead")

    def _begin_confirmation_if_due(self) -> None:
        """In the session's last minutes (``[protocol] confirm_min``), mark the recommendation
        for confirmation before the next ask: that ask freezes it (in the worker) and every
        setting from then on measures it in full."""
        if self.protocol.confirm_due and not self.opt.confirming and self.opt.begin_confirmation():
            self._event("confirmation", "the session's last minutes: measuring the recommended "
                        "setting in full")

    async def _start_next_ask(self) -> asyncio.Task[Any]:
        """Start ``ask()`` in the worker on the optimizer as it is now.

        A fit made ahead is applied where a snapshot records it (an evaluation's end, an
        abandoned setting); none is left by then. One that still were would be dropped, not
        applied unlogged: the ask then fits the hyperparameters itself, which a resume replays.
        """
        await self._collect_fit_ahead(apply=False)
        self._begin_confirmation_if_due()
        return self._worker.start_ask(self.opt)

    async def _push(self, admitted: AdmittedProfile, version: int, index: int, *,
                    log_first: Callable[[], None] | None = None) -> None:
        """Push what the gate admitted and wait for the device's ack, with the supervisor's leave.

        The supervisor is asked before the push, before its first segment and before every
        commit (bridge/supervisor.py): a pause that arrives during the push aborts it (no commit)
        and the pause's assistance-off is already on its way. The proposal (``log_first``) and
        the profile are logged while the paced segments go out: the first segment is on the bus
        before the logging starts, and the logging (a few ms of JSON) fits in the gaps between
        segments instead of delaying the first one.

        Raises:
            _Paused: A pause overtook the push, or the push failed (the session then pauses).
        """
        s = self.settings
        # A fault the device latched while nothing assisted (before the session's first
        # heartbeat, during a warm-up) would make it refuse the commit (busy).
        await self._clear_device_faults()
        try:
            ticket = self.supervisor.begin_push(admitted, version)
        except PushRefused as err:
            if log_first is not None:
                log_first()
            raise _Paused from err
        table = pack_tables([p.force_n for p in admitted.profiles])
        push = asyncio.ensure_future(self.endpoint.push_profile(
            table, version, timeout_s=s.push_timeout_s, retries=s.push_retries, pace_s=s.pace_s,
            permit=lambda stage: self.supervisor.permit(ticket, stage)))
        await asyncio.sleep(0)  # lets the push send its first segment
        try:
            if log_first is not None:
                log_first()
            self.log.log_profile_sent(admitted.profiles, version=version, index=index,
                                      params=admitted.params, t_s=self._breaths.last_t)
        except BaseException:
            push.cancel()
            with contextlib.suppress(asyncio.CancelledError, DriverError):
                await push
            raise
        try:
            result = await push
        except ProfilePushAborted as err:
            self._event("push_aborted", f"{err} ({self.supervisor.describe()})")
            raise _Paused from err
        except ProfilePushError as err:
            reason = getattr(err, "reason", "none")
            self.log.log_ack(version=version, accepted=False, reason=reason, error=str(err))
            await self.supervisor.pause(AssistanceOffReason.INTERNAL_ERROR, f"profile push failed: {err}")
            raise _Paused from err
        if not self.supervisor.acknowledged(ticket):
            # Committed before the pause, acked after it: the pause's assistance-off followed
            # the commit on the bus and the heartbeat says "paused"; the device stays off.
            self._event("ack_overtaken", f"profile v{version} acknowledged after the pause; "
                        "the device stays off")
            raise _Paused
        self.log.log_ack(version=version, accepted=True, attempts=result.attempts,
                         elapsed_s=result.elapsed_s, crc32=result.crc32)

    async def _wait_applied(self, version: int) -> None:
        deadline = self._clock() + self.settings.apply_timeout_s
        while self.device.active_version(self.settings.n_actuators) != version:
            if self.supervisor.paused:
                raise _Paused
            if self._clock() > deadline:
                await self.supervisor.pause(AssistanceOffReason.INTERNAL_ERROR,
                                  f"profile v{version} acknowledged but not active after "
                                  f"{self.settings.apply_timeout_s:g} s")
                raise _Paused
            await asyncio.sleep(0.005)

    async def _next_breath(self) -> BreathRecord:
        """The next breath, raising _Paused if the session pauses while waiting."""
        getter = asyncio.ensure_future(self._breaths.queue.get())
        pauser = asyncio.ensure_future(self.supervisor.wait_paused())
        if self._breaths.queue.empty():
            self.breath_wanted.set()
        try:
            done, _ = await asyncio.wait({getter, pauser}, return_when=asyncio.FIRST_COMPLETED)
        except BaseException:
            getter.cancel()  # cancelled (the session ends): no task left waiting on the queue
            raise
        finally:
            self.breath_wanted.clear()
            pauser.cancel()
        if getter in done:
            return getter.result()
        getter.cancel()
        raise _Paused

    async def _bout_pause(self) -> Action | None:
        """The pause between the bouts (assistance off) until the operator or the resume
        policy resumes. Returns END when the session's time runs out during it."""
        self._event("bout_pause", "exploration bout complete; pausing until the operator resumes")
        await self.supervisor.pause(AssistanceOffReason.SESSION_END, "between bouts")
        # Not a full collection (113-176 ms measured between the bouts): the device's 100 ms heartbeat
        # watchdog would latch heartbeat_lost. What was allocated since the last freeze only.
        self.collector.quiet_point()
        return await self._wait_resumed()

    async def _wait_resumed(self) -> Action | None:
        """Wait out a pause. Its breaths are logged and given to the protocol (walking time:
        they count against the session's time, not as measurements). Returns END when the
        session's time runs out during the pause, else None once resumed."""
        while self.supervisor.paused:
            if self.supervisor.stopped:
                raise _Stopped
            # asyncio.timeout, not wait_for: Python 3.11's wait_for swallows a cancellation
            # that arrives as the inner get() completes, and the task then never ends.
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(0.05):
                    rec = await self._breaths.queue.get()
                    act = self._on_breath(rec)
                    if act.kind is ActionKind.END:
                        return act
        return None

    # ------------------------------------------------------------------ background tasks
    async def _cart_task(self) -> None:
        b = self._breaths
        validator = getattr(self._stream, "validator", None)
        if self._pull:
            await self._ready_for_breaths.wait()
        async for rec in self._stream:
            if validator is not None and validator.reanchors != b.reanchors:
                b.reanchors = validator.reanchors
                ra = validator.last_reanchor
                self._event("cart_reanchor",
                            f"cart clock {ra.kind.value} (cart t = {ra.raw_t_s:.1f} s -> session "
                            f"t = {ra.t_s:.1f} s, {ra.dropped} breaths dropped): the setting being "
                            "measured starts again")
            b.last_wall, b.last_t = self._clock(), rec.t_s
            b.count += 1
            if self._t_session0 is None:
                self._t_session0 = rec.t_s
            self.status.breath_time_s = self._session_time(rec.t_s)
            self.status.cart = "ok"
            self.log.log_breath(rec)
            await b.queue.put(rec)  # waits only with back-pressure (a bounded queue)
            if self._pull:  # the wait was the session's, not a silent cart
                b.last_wall = self._clock()
        b.ended = True
        self._ended_by(SessionEnd.CART_ENDED)
        walked = self.protocol.walking.session_s / 60
        end = self._expected_end_s()
        early = "" if end is None else f", {max(end / 60 - walked, 0.0):.1f} min before the expected end"
        self._event("cart_ended", f"the cart stream ended after {walked:.1f} min walked{early} "
                    f"({b.count} breaths): stopping", walked_s=self.protocol.walking.session_s)
        self._commands.put_nowait(Command.STOP)

    async def _status_task(self) -> None:
        last_logged: dict[int, tuple[float, Any]] = {}
        with self.endpoint.subscribe(DeviceStatus) as sub:
            async for st in sub:
                now = self._clock()
                self.device.last_status_wall[st.actuator] = now
                self.device.status[st.actuator] = st
                key = (st.mode, st.faults, st.profile_version_active, st.profile_version_pending)
                prev = last_logged.get(st.actuator)
                if prev is None or prev[1] != key or now - prev[0] >= self.settings.status_log_period_s:
                    last_logged[st.actuator] = (now, key)
                    self.log.log_device_status(
                        actuator=st.actuator, mode=DeviceMode(st.mode), faults=st.faults,
                        gait_phase_pct=st.gait_phase_pct,
                        profile_version_active=st.profile_version_active,
                        profile_version_pending=st.profile_version_pending)

    async def _feedback_task(self) -> None:
        period = self.settings.feedback_log_period_s
        batch: dict[int, list[tuple[float, float, float | None]]] = {}
        dev = self.device

        def flush() -> None:
            # Batched: 2 actuators at 1 kHz would be 2000 log messages a second.
            version = dev.active_version(self.settings.n_actuators)
            for act, rows in batch.items():
                if rows:
                    d, m, g = zip(*rows, strict=True)
                    self.log.log_force_feedback(actuator=act, desired_n=d, measured_n=m,
                                                gait_phase_pct=g, profile_version=version)
            batch.clear()

        t_flush = self._clock() + period
        try:
            with self.endpoint.subscribe(ForceFeedback, maxsize=8192) as sub:
                while True:
                    try:
                        # Not wait_for: on Python 3.11 it swallows a cancellation that arrives as
                        # a frame does (at 2 kHz, often), so the session hung on shutdown.
                        async with asyncio.timeout(period):
                            fb = await sub.get()
                        dev.feedback_frames += 1
                        last = dev.feedback_counter.get(fb.actuator)
                        if last is not None:
                            dev.feedback_lost += (fb.counter - last - 1) % 256
                        dev.feedback_counter[fb.actuator] = fb.counter
                        batch.setdefault(fb.actuator, []).append(
                            (fb.desired_force_n, fb.measured_force_n, fb.gait_phase_pct))
                    except TimeoutError:
                        pass
                    now = self._clock()
                    if now >= t_flush:
                        flush()
                        t_flush = now + period
        finally:
            # The last batch too, so every received frame is logged; a failing log must not turn
            # the session's shutdown into an error (the next log call reports it anyway).
            if not self.log.closed:
                try:
                    flush()
                except LogError as err:
                    logger.warning("the last force-feedback batch was not logged: %s", err)

    async def _device_silence_task(self) -> None:
        """Assistance-off when the device's statuses stop: the check is scheduled for the
        moment the silence reaches :attr:`RuntimeSettings.device_silence_limit_s` (the stalest
        actuator's last status + the limit), not polled, so the AssistanceOff frame is on the
        bus within ``device_timeout_s`` of the last status; while the device stays silent, it
        looks again every watchdog period. Before the first status, the limit counts from the
        session's start."""
        s = self.settings
        limit = s.device_silence_limit_s
        started = self._clock()
        while True:
            last = self.device.stalest_status(s.n_actuators)
            due = (started if last is None else last) + limit
            now = self._clock()
            if now < due:
                await asyncio.sleep(due - now)
                continue
            # Statuses that arrived while this process was held up may still be on their way in:
            # python-can's reader thread (pcan, kvaser, virtual; socketcan's reader is a loop
            # callback) needs the GIL, then the CAN receive task and the status task a turn of
            # the loop each. A short real wait lets them through first (the loop waits in
            # select, which releases the GIL), so a busy PC is not taken for a silent device.
            stalled = now - due > _STALL_GRACE_S  # this loop itself woke late
            await asyncio.sleep(_RECEIVE_GRACE_S)
            if self.device.stalest_status(s.n_actuators) != last:
                continue  # a status came in
            if stalled and self.supervisor.assisting:
                # After a stall of this loop, statuses of the stall may still be queued: the
                # device (whose own watchdog guards the bridge heartbeat, sent by the kernel or a
                # sender thread through the stall) gets a few status periods more.
                silent, _ = await self._device_silence_after_stall()
                if silent <= s.device_timeout_s:
                    continue
            silent = self.device.silent_for(self._clock(), s.n_actuators)
            healthy = self.status.device == "ok"
            self.status.device = "LOST"
            if healthy or not self.supervisor.paused:
                text = ("no device status since the session started" if math.isinf(silent)
                        else f"device heartbeat lost: no status for {silent * 1e3:.0f} ms (assistance "
                             f"off from {s.device_silence_limit_s * 1e3:.0f} ms, so that it is on the "
                             f"bus within the {s.device_timeout_s * 1e3:.0f} ms timeout)")
                if self.supervisor.has_reason(AssistanceOffReason.DEVICE_HEARTBEAT_LOST):
                    # Lost again during the pause it caused: assistance-off once more, and the
                    # pause keeps its one heartbeat cause (the operator's line does not grow).
                    await self.supervisor.assistance_off(AssistanceOffReason.DEVICE_HEARTBEAT_LOST, text)
                else:
                    await self.supervisor.pause(AssistanceOffReason.DEVICE_HEARTBEAT_LOST, text)
            await asyncio.sleep(s.watchdog_period_s)

    async def _watchdog_task(self) -> None:
        s = self.settings
        started = self._clock()
        next_counts = started + 5.0
        while True:
            await asyncio.sleep(s.watchdog_period_s)
            now = self._clock()
            if now >= next_counts:
                next_counts = now + 5.0
                self._log_counters()
            silent = self.device.silent_for(now, s.n_actuators)
            if silent <= s.device_silence_limit_s:  # silence: _device_silence_task
                faults = self.device.faults(s.n_actuators)
                self.status.device = "ok" if not faults else \
                    "faults: " + "; ".join(describe_faults(faults))
                person = faults & PERSON_FAULTS
                if person:
                    # An emergency stop (or another fault only a person may resume from) pauses
                    # the session whatever it is doing, a warm-up included, and the pause keeps
                    # needing the person after the fault is gone (ISO 13850: releasing the
                    # button must not restart the machine).
                    text = f"device faults: {', '.join(fault_names(person))}"
                    if not self.supervisor.has_cause(text):
                        await self.supervisor.pause(AssistanceOffReason.INTERNAL_ERROR, text,
                                                    recovery=FaultRecovery.PERSON)
                elif faults and self.supervisor.assisting:
                    # The device latched a fault (its own heartbeat watchdog, overheating) while
                    # it assisted: it is slack, so the setting being measured is not what the
                    # wearer feels. Pause; the resume clears what the policy may clear. Such a
                    # fault while nothing assists (a warm-up, the start) is cleared before the
                    # next push.
                    await self.supervisor.pause(
                        AssistanceOffReason.DEVICE_HEARTBEAT_LOST if faults & DeviceFault.HEARTBEAT_LOST
                        else AssistanceOffReason.INTERNAL_ERROR,
                        f"device faults: {', '.join(fault_names(faults))}")
            b = self._breaths
            if b.last_wall is not None and now - b.last_wall > s.cart_timeout_s:
                if self.status.cart == "ok":
                    self.status.cart = "SILENT"
                    await self.supervisor.pause(AssistanceOffReason.INTERNAL_ERROR,
                                                f"no breath for {now - b.last_wall:.0f} s")

    async def _device_silence_after_stall(self) -> tuple[float, float]:
        """The device's silence once the receive path has caught up, after this event loop
        itself stalled: statuses that arrived during the stall still wait in the receive path
        (the notifier, the endpoint, the subscription), so give it up to
        :data:`_MAX_STALL_DEFERRALS` status periods before judging the device silent (as the
        device's own watchdog does for the bridge heartbeat, virtual_hw/exosuit.py). A device
        that really went silent is still found, at most that much later. Returns (silence,
        now)."""
        s = self.settings
        for _ in range(_MAX_STALL_DEFERRALS):
            await asyncio.sleep(_STALL_GRACE_S)
            now = self._clock()
            silent = self.device.silent_for(now, s.n_actuators)
            if silent <= s.device_timeout_s:
                break
        return silent, now

    async def _resume_policy_task(self) -> None:
        """Headless runs: end a pause the operator did not ask for once the device and the cart
        have been healthy for ``auto_resume_s``, at most ``max_auto_resumes`` times; then stop
        (without it ``hilbo sim`` once waited forever for an ``r`` that never came)."""
        s, sup = self.settings, self.supervisor
        if s.auto_resume_s is None:
            return
        while not sup.stopped:
            await sup.wait_paused()
            healthy_since: float | None = None
            told_person = False
            while sup.paused and not sup.stopped:
                if sup.needs_person and not sup.by_operator:
                    # A fault only a person may resume from: never this policy. With nobody at
                    # the keyboard the session stops (assistance stays off; --resume continues).
                    causes = "; ".join(sup.person_causes)
                    if not s.operator_present:
                        text = (f"only a person at the PC may resume after {causes}, and this run "
                                "has no operator keyboard: stopping (hilbo run --resume continues)")
                        self._event("person_required", text)
                        self._ended_by(SessionEnd.PERSON_REQUIRED)
                        await sup.stop(AssistanceOffReason.SESSION_END, text)
                        return
                    if not told_person:
                        told_person = True
                        self._event("person_required", "assistance stays off until a person "
                                    f"presses r once it is safe ({causes})")
                elif not sup.needs_person:
                    now = self._clock()
                    if self._health(clearable=POLICY_CLEARABLE_FAULTS) is not None:
                        healthy_since = None
                    elif healthy_since is None:
                        healthy_since = now
                    elif now - healthy_since >= s.auto_resume_s:
                        break
                await asyncio.sleep(s.watchdog_period_s)
            if not sup.paused or sup.stopped:
                continue
            if self._auto_resumes >= s.max_auto_resumes:
                text = (f"{s.max_auto_resumes} automatic resumes used; stopping instead of "
                        f"waiting ({sup.pause_reason})")
                self._ended_by(SessionEnd.RESUME_BUDGET)
                self._event("auto_resume_exhausted", text)
                await sup.stop(AssistanceOffReason.SESSION_END, text)
                return
            n = self._auto_resumes + 1
            if await self._resume(f"resume policy ({n} of {s.max_auto_resumes})"):
                self._auto_resumes = n

    def _log_counters(self) -> None:
        """Rejected breaths and frames by reason (cumulative), for the log and the review."""
        cart_counts = getattr(self._stream, "counters", None)
        if cart_counts:
            self.log.log_rejects("cart", cart_counts, t_s=self._breaths.last_t)
        if self.endpoint.counters:
            self.log.log_rejects("can", self.endpoint.counters, t_s=self._breaths.last_t)
        flagged = self.opt.flagged_breaths
        if flagged:
            # Breaths the cart passed but the estimator left out as implausible for the level:
            # counted like the cart's rejects, not dropped silently.
            self.log.log_rejects("estimator", {"implausible_for_level": flagged},
                                 t_s=self._breaths.last_t)

    async def _bus_failure_task(self) -> None:
        err = await self.endpoint.wait_failed()
        self._ended_by(SessionEnd.BUS_FAILED)
        self._event("bus_error", f"CAN bus failed: {err}")
        await self.supervisor.stop(AssistanceOffReason.INTERNAL_ERROR, f"CAN bus failed: {err}")
        raise _Stopped from err

    async def _command_task(self) -> None:
        while True:
            cmd = await self._commands.get()
            if cmd is Command.PAUSE:
                await self.supervisor.pause(AssistanceOffReason.OPERATOR_STOP, "operator pause")
            elif cmd is Command.RESUME:
                await self._resume("operator", by_person=True)
            elif cmd is Command.STOP:
                self._ended_by(SessionEnd.OPERATOR_STOP)
                # The stop's cause as the log and the view say it: the operator's q, a signal,
                # or another cause given to finish(); the frame's reason is the operator's.
                why = ("operator stop" if self.end_reason in (None, SessionEnd.OPERATOR_STOP)
                       else self.end_reason.text)
                await self.supervisor.stop(AssistanceOffReason.OPERATOR_STOP, why)
                raise _Stopped

    # ------------------------------------------------------------------ helpers
    def _health(self, *, clearable: DeviceFault | int = 0) -> str | None:
        """Why the session may not resume now, or None (the supervisor's resume condition).

        Args:
            clearable: Latched device faults that do not count, because the resume clears them
                first (:meth:`_resume`): the policy's own, or every clearable one for a person.
        """
        s = self.settings
        silent = self.device.silent_for(self._clock(), s.n_actuators)
        if silent > s.device_silence_limit_s:
            return f"device heartbeat lost ({silent * 1e3:.0f} ms)" if math.isfinite(silent) \
                else "no device status yet"
        faults = self.device.faults(s.n_actuators) & ~clearable
        if faults:
            return "device faults: " + "; ".join(describe_faults(faults))
        if self.status.cart == "SILENT":
            return "no breaths from the cart"
        return None

    async def _resume(self, source: str, *, by_person: bool = False) -> bool:
        """Resume the session: clear the device's latched faults first, then ask the supervisor.

        Only a person's resume (the operator's ``r``) clears the faults of class ``PERSON``
        (drivers/exosuit/faults.py); the policy's clears only its own, and the supervisor
        refuses it while the pause needs a person.
        """
        sup = self.supervisor
        if sup.needs_person and not by_person:
            return False
        mask = CLEARABLE_FAULTS if by_person else POLICY_CLEARABLE_FAULTS
        if sup.paused and self._health(clearable=mask) is None:
            await self._clear_device_faults(mask)
        return sup.resume(source, by_person=by_person) is None

    async def _clear_device_faults(self, mask: DeviceFault = POLICY_CLEARABLE_FAULTS) -> None:
        """Ask the device to clear the latched faults in ``mask`` (PROTOCOL.md, "Clearing a
        latched fault": it clears one only once its cause is gone) and wait, briefly, for a
        status that shows them gone. The bridge passes every clearable fault only when a person
        resumes; on its own (before a push) only the policy's (``POLICY_CLEARABLE_FAULTS``)."""
        s = self.settings
        faults = self.device.faults(s.n_actuators)
        if faults & mask:
            try:
                result = await self.endpoint.clear_faults(faults & mask,
                                                          n_actuators=s.n_actuators)
            except DriverError as err:
                self._event("clear_faults_failed", f"clearing {', '.join(fault_names(faults))} failed: {err}")
            else:
                self.log.log_event("clear_faults", f"asked the device to clear "
                                   f"{', '.join(fault_names(faults))}; cleared "
                                   f"{', '.join(fault_names(result.cleared)) or 'none'}")
            # The cleared bits show in the next DeviceStatus (every 20 ms).
            deadline = self._clock() + 0.2
            while self.device.faults(s.n_actuators) & mask and self._clock() < deadline:
                await asyncio.sleep(s.watchdog_period_s)

    def _on_breath(self, rec: BreathRecord) -> Action:
        """Give a breath to the protocol; keep the operator view's times current (the expected
        end, the optimisation minutes: at every breath, a pause's too)."""
        act = self.protocol.on_breath(rec.t_s)
        self.status.budget_used_s = self.protocol.walking.optimization_s
        self.status.expected_end_s = self._expected_end_s()
        for listener in self.breath_listeners:
            listener(rec)
        return act

    def _expected_end_s(self) -> float | None:
        """The protocol's expected end in session time (s), or None."""
        t_end = self.protocol.expected_t_end_s()
        return None if t_end is None or self._t_session0 is None else t_end - self._t_session0

    def _session_time(self, t_cart: float) -> float:
        return t_cart - (self._t_session0 if self._t_session0 is not None else t_cart)

    def _event(self, kind: str, text: str, **details: Any) -> None:
        logger.info("%s: %s", kind, text)
        self.status.event(text)
        self.log.log_event(kind, text, **details)

    def _on_loop_stall(self, stall_s: float) -> None:
        """A stall longer than the monitor's threshold: log it with what the session was doing."""
        phase, state = self.protocol.phase.value, self.supervisor.describe()
        text = (f"event loop stalled {stall_s * 1e3:.1f} ms (> {self.loop_monitor.threshold_s * 1e3:.0f} ms, "
                f"half the device's heartbeat watchdog) in {phase}, {state}")
        logger.warning("%s", text)
        self.log.log_event("loop_stall", text, level=EventLevel.WARNING,
                           t_s=self._breaths.last_t, stall_ms=round(stall_s * 1e3, 3),
                           threshold_ms=self.loop_monitor.stats.threshold_ms, phase=phase, state=state)



def _quantiles_ms(values: list[float]) -> dict[str, float] | None:
    if not values:
        return None
    a = np.asarray(values) * 1e3
    return {"median": float(np.median(a)), "p99": float(np.quantile(a, 0.99)), "max": float(a.max()),
            "n": len(values)}


async def _cancel_and_wait(task: asyncio.Task[Any] | None, what: str) -> None:
    """Cancel ``task`` (if any) and wait for it; a failure it ends with is logged, not raised
    (the session is over and its result is not needed)."""
    if task is None:
        return
    task.cancel()
    try:
        await task
    except asyncio.CancelledError:
        pass
    except Exception:
        logger.exception("%s failed as the session ended", what)
