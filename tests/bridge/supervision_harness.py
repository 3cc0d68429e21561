"""A deterministic stand-in for the CAN side of a session, for the pause-holds tests.

Everything runs on one event loop with fake time (looptime): the exosuit endpoint is a model of
the device that keeps a transcript of what reached it, the cart yields a breath every
``BREATH_S`` of loop time, and the proposal worker asks in the loop. With no thread and no real
I/O in the session's path the loop's schedule is the same in every run, so "the k-th suspension
of any task" names the same moment each time: :class:`Injector` counts the suspensions of every
task (a task factory wraps each coroutine) and fires a fault at the chosen one.

The safety property checked after every suspension and at every commit: while the supervisor
says "paused", nothing is committed and the device model is not assisting.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import itertools
import math
import os
from collections import Counter
from collections.abc import AsyncIterator, Callable, Iterator, Mapping
from pathlib import Path
from typing import Any

import looptime
import numpy as np

from bridge.log import SessionLog
from bridge.log.resume import rebuild_optimizer
from bridge.proposals import Asked
from bridge.runtime import BridgeSession, Command, RuntimeSettings
from bridge.safety import ProfileLimits, SafeProfileGate
from drivers.cart.validate import BreathValidator
from drivers.errors import ProfilePushAborted, TransportError
from drivers.exosuit import (
    FAULT_INFO,
    AssistanceOffReason,
    BridgeState,
    ClearFaultsAck,
    ClearFaultsResult,
    DeviceFault,
    DeviceMode,
    DeviceStatus,
    NackReason,
    ProfileNackError,
    PushResult,
)
from hilbo_core import HILOptimizer, OptimizerConfig, fit_hyperparameters
from hilbo_core.presets import hip_6d
from hilbo_core.protocol import SessionProtocol, SessionProtocolConfig
from hilbo_core.types import BreathRecord

BREATH_S = 3.0
#: The name of the task that runs ``BridgeSession.run`` when ``run_session`` has a ``watch``.
SESSION_TASK = "session"
STATUS_PERIOD_S = 0.1
SEGMENT_PACE_S = 0.001
ACK_DELAY_S = 0.003


class FakeExosuit:
    """The endpoint interface the session uses, over a model of the device.

    The model assists while its last commit was accepted with the heartbeat ``running``, no
    AssistanceOff came after it, and the heartbeat still says ``running``.
    """

    def __init__(self, n_actuators: int = 2) -> None:
        self.n_actuators = n_actuators
        self.bridge_state = BridgeState.IDLE
        #: (loop time, what, detail) of every frame that reached the device.
        self.transcript: list[tuple[float, str, Any]] = []
        #: Every breach of the safety property, with where it was seen.
        self.violations: list[str] = []
        self.counters: Counter[str] = Counter()
        self.active_version = 0
        self.pending_version = 0
        self.latched_off = True
        self.silent = False
        #: Loop time of every DeviceStatus round the device sent.
        self.status_times: list[float] = []
        #: Latched fault bits (reported in every status) and the bits whose cause is present
        #: (a held emergency stop): a ClearFaults clears a latched bit only once its cause is gone.
        self.latched = DeviceFault(0)
        self.cause = DeviceFault(0)
        self.is_paused: Callable[[], bool] = lambda: False
        self._failed = asyncio.Event()
        self._error: BaseException | None = None
        self._subs: list[tuple[tuple[type, ...], asyncio.Queue[Any]]] = []
        self._status_task: asyncio.Task[None] | None = None

    # -------------------------------------------------------------- the model
    @property
    def assisting(self) -> bool:
        return (not self.latched_off and self.active_version != 0
                and self.bridge_state == BridgeState.RUNNING)

    def check(self, where: str) -> None:
        if self.is_paused() and self.assisting:
            self.violations.append(f"assisting while paused ({where}); transcript tail "
                                   f"{self.transcript[-4:]}")

    def _record(self, what: str, detail: Any) -> None:
        self.transcript.append((asyncio.get_running_loop().time(), what, detail))

    def times_of(self, what: str, detail: Any) -> list[float]:
        return [t for t, w, d in self.transcript if w == what and d == detail]

    def raise_fault(self, bit: DeviceFault, duration_s: float) -> None:
        """The fault's cause is present for ``duration_s`` (loop time): the bit latches and the
        device goes slack at once, as a real device does (PROTOCOL.md, "Faults")."""
        self.cause |= bit
        self.latched |= bit
        self.latched_off = True
        self._record("fault", bit)
        asyncio.get_running_loop().call_later(duration_s, self._cause_gone, bit)

    def _cause_gone(self, bit: DeviceFault) -> None:
        self.cause &= ~bit
        if bit & DeviceFault.BUS_ERROR:  # the node clears it itself once error-active again
            self.latched &= ~DeviceFault.BUS_ERROR
        self._record("fault_cause_gone", bit)

    def fail(self, err: BaseException) -> None:
        self._error = err
        self._failed.set()

    def _publish(self, msg: Any) -> None:
        for kinds, q in self._subs:
            if isinstance(msg, kinds):
                if q.full():
                    q.get_nowait()
                q.put_nowait(msg)

    async def _status_loop(self) -> None:
        counter = 0
        while True:
            await asyncio.sleep(STATUS_PERIOD_S)
            if self.pending_version:  # a gait-cycle boundary every status period
                self.active_version, self.pending_version = self.pending_version, 0
            if self.silent:
                continue
            self.status_times.append(asyncio.get_running_loop().time())
            mode = DeviceMode.ASSISTANCE_OFF if self.latched_off else DeviceMode.ASSIST
            for a in range(self.n_actuators):
                self._publish(DeviceStatus(actuator=a, mode=mode, faults=self.latched,
                                           gait_phase_pct=None,
                                           profile_version_active=self.active_version,
                                           profile_version_pending=self.pending_version,
                                           counter=counter))
            counter = (counter + 1) % 256

    # -------------------------------------------------------------- the endpoint interface
    def start_heartbeat(self, period_s: float) -> None:
        if self._status_task is None:
            self._status_task = asyncio.get_running_loop().create_task(self._status_loop())

    async def stop_heartbeat(self) -> None:
        task, self._status_task = self._status_task, None
        if task is not None:
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task

    async def wait_failed(self) -> BaseException:
        await self._failed.wait()
        assert self._error is not None
        return self._error

    @contextlib.contextmanager
    def subscribe(self, *kinds: type, maxsize: int = 1024) -> Iterator[_Sub]:
        q: asyncio.Queue[Any] = asyncio.Queue(maxsize)
        entry = (kinds, q)
        self._subs.append(entry)
        try:
            yield _Sub(q)
        finally:
            self._subs.remove(entry)

    async def send_assistance_off(self, reason: AssistanceOffReason) -> None:
        if self.bridge_state == BridgeState.RUNNING:
            self.bridge_state = BridgeState.PAUSED
        if self._failed.is_set():
            raise TransportError("bus failed")
        self._record("assistance_off", AssistanceOffReason(reason))
        self.latched_off = True
        await asyncio.sleep(0)

    async def clear_faults(self, mask: DeviceFault | int, *, n_actuators: int) -> ClearFaultsResult:
        self._record("clear_faults", DeviceFault(int(mask)))
        cleared = self.latched & DeviceFault(int(mask)) & ~self.cause
        self.latched &= ~cleared
        await asyncio.sleep(0.002)
        ack = {a: ClearFaultsAck(actuator=a, sequence=0, cleared=cleared, held=self.latched)
               for a in range(n_actuators)}
        return ClearFaultsResult(sequence=0, mask=DeviceFault(int(mask)), answers=ack)

    async def push_profile(self, forces_n: np.ndarray, version: int, *, timeout_s: float,
                           retries: int, pace_s: float,
                           permit: Callable[[str], bool] | None = None) -> PushResult:
        n_segments = math.ceil(len(forces_n) / 3)
        for k in range(n_segments):
            if k == 0 and permit is not None and not permit("first_segment"):
                raise ProfilePushAborted(version, "first_segment", 1, 0)
            self._record("segment", (version, k))
            await asyncio.sleep(SEGMENT_PACE_S)
        if permit is not None and not permit("commit"):
            raise ProfilePushAborted(version, "commit", 1, 0)
        if self.is_paused():
            self.violations.append(f"commit of v{version} while paused")
        if self.latched:
            self._record("commit_refused", version)
            raise ProfileNackError(version, NackReason.BUSY, 0, 1)
        self._record("commit", version)
        if self.bridge_state == BridgeState.RUNNING:
            self.latched_off = False
        self.pending_version = version
        await asyncio.sleep(ACK_DELAY_S)
        self._record("ack", version)
        return PushResult(version=version, n_points=len(forces_n), crc32=0, attempts=1,
                          elapsed_s=ACK_DELAY_S, nacks=(), timeouts=0)


@dataclasses.dataclass
class _Sub:
    q: asyncio.Queue[Any]

    async def get(self) -> Any:
        return await self.q.get()

    def __aiter__(self) -> _Sub:
        return self

    async def __anext__(self) -> Any:
        return await self.q.get()


class InlineWorker:
    """The proposal worker's interface, asking in the loop (no thread, no process)."""

    lost: str | None = None
    in_process = True

    def __init__(self, start_s: float = 0.0, fit_s: float = 0.03) -> None:
        self.start_s = start_s  # loop time its "process" takes to answer the first call
        self.fit_s = fit_s  # loop time a hyperparameter fit takes (tens of ms in the worker)

    async def __aenter__(self) -> InlineWorker:
        return self

    async def __aexit__(self, *exc: object) -> None:
        return None

    def start_ask(self, opt: HILOptimizer) -> asyncio.Task[Asked]:
        async def ask() -> Asked:
            await asyncio.sleep(0.02)  # the GP work takes tens of ms
            params = opt.ask()
            return Asked(opt, params, 0.0, 0.0)
        return asyncio.get_running_loop().create_task(ask())

    async def fit(self, fit: Any) -> Any:
        await asyncio.sleep(self.fit_s)
        return fit_hyperparameters(fit)

    async def worker_pid(self) -> int:
        await asyncio.sleep(self.start_s)
        return os.getpid()


class Cart:
    """A breath every ``BREATH_S`` through the real validator; ``restart_at_s`` restarts the
    cart's clock (it starts again near 0) at that loop time."""

    def __init__(self, restart_at_s: float | None = None, n: int = 10_000,
                 scaled: Mapping[int, float] | None = None) -> None:
        self.validator = BreathValidator()
        self.restart_at_s = restart_at_s
        self.n = n
        #: Breath number -> factor on its VO2 and VCO2 (an implausible single breath).
        self.scaled = dict(scaled or {})

    def __aiter__(self) -> AsyncIterator[BreathRecord]:
        return self._breaths()

    async def _breaths(self) -> AsyncIterator[BreathRecord]:
        rng = np.random.default_rng(3)
        offset = 0.0
        loop = asyncio.get_running_loop()
        for i in range(self.n):
            await asyncio.sleep(BREATH_S)
            if self.restart_at_s is not None and offset == 0.0 and loop.time() >= self.restart_at_s:
                offset = loop.time() - 1.0
            vo2 = 1200.0 * (1 + 0.05 * rng.standard_normal()) * self.scaled.get(i, 1.0)
            raw = BreathRecord(t_s=(i + 1) * BREATH_S - offset, vo2_ml_min=vo2, vco2_ml_min=0.85 * vo2)
            rec = self.validator.check(raw)
            if rec is not None:
                yield rec


class Injector:
    """Counts the suspensions of every task; calls ``fire`` at suspension number ``at``."""

    def __init__(self, device: FakeExosuit, at: int | None = None,
                 fire: Callable[[], None] | None = None) -> None:
        self.device = device
        self.at = at
        self.fire = fire
        self.count = 0
        #: Loop time of every suspension, by suspension number.
        self.times: list[float] = []
        #: Called with the suspension number and the coroutine that just suspended (its task's)
        #: after every suspension: every task is then at an await point.
        self.watch: Callable[[int, Any], None] | None = None

    def factory(self, loop: asyncio.AbstractEventLoop, coro: Any, **kw: Any) -> asyncio.Task[Any]:
        return asyncio.Task(self._wrap(coro), loop=loop, **kw)

    async def _wrap(self, coro: Any) -> Any:
        return await _Counted(coro, self)

    def suspended(self, coro: Any = None) -> None:
        self.device.check(f"suspension {self.count}")
        self.times.append(asyncio.get_running_loop().time())
        if self.count == self.at and self.fire is not None:
            self.fire()
        if self.watch is not None:
            self.watch(self.count, coro)
        self.count += 1


class _Counted:
    def __init__(self, coro: Any, inj: Injector) -> None:
        self.coro, self.inj = coro, inj

    def __await__(self) -> Any:
        value: Any = None
        exc: BaseException | None = None
        while True:
            try:
                y = self.coro.send(value) if exc is None else self.coro.throw(exc)
            except StopIteration as stop:
                return stop.value
            self.inj.suspended(self.coro)
            try:
                value, exc = (yield y), None
            except BaseException as err:  # delivered into the wrapped coroutine
                value, exc = None, err


@dataclasses.dataclass
class Outcome:
    summary: dict[str, Any]
    device: FakeExosuit
    session: BridgeSession
    injector: Injector
    cart: Cart
    #: Every event line of the session, in order.
    events: list[str]
    #: The session's log.
    log: Path


#: What ``run_session(fault=...)`` can inject; ``"device:<name>"`` (not listed here) also latches
#: that device fault bit (drivers/exosuit/faults.py names) with its cause present for ``fault_s``.
FAULTS = ("pause", "stop", "heartbeat_loss", "bus_error")


def harness_protocol_config(n_evaluations: int = 4, pause_between_bouts: bool = False, *,
                            n_explore: int = 2, warmup_s: float = 0.0) -> SessionProtocolConfig:
    """The protocol of :func:`run_session`: by default warm-ups 0, 2 exploration points of 3
    breaths, an optimisation budget in breaths of about ``n_evaluations - n_explore``
    evaluations."""
    return SessionProtocolConfig(
        warmup_s=warmup_s, n_explore=n_explore, max_breaths=3, budget_s=None,
        budget_breaths=3 * max(n_evaluations - n_explore, 1), pause_between_bouts=pause_between_bouts)
_RUNS = itertools.count()
_FAULT_BITS = {info.name: bit for bit, info in FAULT_INFO.items()}


def run_session(tmp: Path, *, at: int | None = None, at_time_s: float | None = None,
                fault: str = "pause", n_evaluations: int = 4, resume_after_s: float = 5.0,
                end_after_s: float | None = None, cart_restart_at_s: float | None = None,
                worker_start_s: float = 0.0, fault_s: float = 0.5,
                operator_r_s: tuple[float, ...] = (), scaled_breaths: Mapping[int, float] | None = None,
                n_explore: int = 2, warmup_s: float = 0.0,
                refit_lag: int = 0, fit_s: float = 0.03, resume_from: Path | None = None,
                watch: Callable[[int, BridgeSession, Any], None] | None = None,
                optimizer: HILOptimizer | None = None, protocol: SessionProtocol | None = None,
                on_session: Callable[[BridgeSession], None] | None = None,
                **settings_kw: Any) -> Outcome:
    """One short session (by default: warm-ups 0, 2 exploration points of 3 breaths, then
    optimisation).

    Args:
        at: Suspension number at which ``fault`` fires (None: no fault).
        at_time_s: Or the loop time at which it fires.
        fault: One of :data:`FAULTS`.
        n_evaluations: The optimisation budget in breaths is set so the session ends after
            about this many evaluations.
        resume_after_s: After a pause or heartbeat loss, the operator presses "r" this long
            after the device is healthy again (loop time).
        end_after_s: The operator stops the session this long after the fault (None: the
            session runs to its budget's end).
        cart_restart_at_s: The cart's clock restarts near 0 at this loop time.
        worker_start_s: The proposal worker answers its first call after this long (loop time).
        fault_s: How long a ``device:<name>`` fault's cause lasts (loop time).
        operator_r_s: The operator presses "r" at these loop times as well.
        scaled_breaths: Breath number -> factor on that breath's gas exchange (the cart's).
        n_explore: Exploration points.
        warmup_s: Each bout's warm-up (breath time, s).
        refit_lag: The optimizer's (1: hyperparameters fitted ahead, as the bridge's default).
        fit_s: How long a hyperparameter fit made ahead takes (loop time).
        resume_from: Continue the session of this (crashed) log, as ``hilbo run --resume``
            does: the optimizer rebuilt from it, the protocol resumed, the new log linked to it.
        watch: Called with the suspension number, the session and the coroutine of the task
            that suspended (suspended at its await point) after every suspension; the
            log is then written without the background flusher, so its bytes on disk at each
            suspension are the same in every run.
        optimizer: The optimizer to continue (a resumed session's); None: a new one.
        protocol: Its protocol (:meth:`SessionProtocol.resumed`); None: a new one.
        on_session: Called with the session before it runs.
        settings_kw: :class:`RuntimeSettings` fields to override, and ``pause_between_bouts``
            (the protocol's).
    """
    device = FakeExosuit()
    space = hip_6d()
    opt = optimizer or HILOptimizer(space, config=OptimizerConfig(
        n_explore=n_explore, max_breaths=3, seed=1,
        n_candidates=64, n_local=0, refit_lag=refit_lag))
    gate = SafeProfileGate(space, ProfileLimits(), body_mass_kg=75.0)
    pause_between_bouts = bool(settings_kw.pop("pause_between_bouts", False))
    settings = RuntimeSettings(**{
        "device_timeout_s": 0.35, "watchdog_period_s": 0.05, "cart_timeout_s": 60.0,
        "apply_timeout_s": 2.0, "pace_s": SEGMENT_PACE_S,
        # The stall monitor measures real time, which a loop-time session does not have; at its
        # default 5 ms it was a third of each run's loop iterations.
        "loop_monitor_period_s": 0.04, **settings_kw})
    protocol_config = harness_protocol_config(n_evaluations, pause_between_bouts,
                                              n_explore=n_explore, warmup_s=warmup_s)
    if protocol is None:
        protocol = SessionProtocol(protocol_config)
    if resume_from is not None:  # what bridge/run.py does for --resume
        opt, _ = rebuild_optimizer(resume_from)
        used = opt.budget_used
        protocol = SessionProtocol.resumed(
            protocol_config, n_explored=min(len(opt.evaluations), n_explore),
            optimization_used_s=float(used["seconds"]), optimization_used_breaths=int(used["breaths"]))
    holder: dict[str, BridgeSession] = {}

    def fire() -> None:
        s = holder["session"]
        loop = asyncio.get_running_loop()
        if fault == "pause":
            s.command(Command.PAUSE)
            loop.call_later(resume_after_s, s.command, Command.RESUME)
        elif fault == "stop":
            s.command(Command.STOP)
        elif fault == "heartbeat_loss":
            device.silent = True
            loop.call_later(1.0, setattr, device, "silent", False)
            loop.call_later(1.0 + resume_after_s, s.command, Command.RESUME)
        elif fault == "bus_error":
            device.fail(TransportError("injected bus error"))
        elif fault.startswith("device:"):
            device.raise_fault(_FAULT_BITS[fault.removeprefix("device:")], fault_s)
            loop.call_later(fault_s + resume_after_s, s.command, Command.RESUME)
        else:
            raise ValueError(f"fault={fault!r}: expected one of {FAULTS}")
        if end_after_s is not None:
            loop.call_later(end_after_s, s.command, Command.STOP)

    inj = Injector(device, at, fire if at is not None else None)
    if watch is not None:
        inj.watch = lambda k, coro: watch(k, holder["session"], coro) if "session" in holder else None
    cart = Cart(restart_at_s=cart_restart_at_s, scaled=scaled_breaths)
    events: list[str] = []
    log_path = tmp / f"s{next(_RUNS)}.mcap"

    async def main() -> dict[str, Any]:
        loop = asyncio.get_running_loop()
        loop.set_task_factory(inj.factory)
        flusher: dict[str, Any] = {} if watch is None else {"flush_interval_s": None}
        with SessionLog(log_path, session_id="t", config_json={},
                        previous_log=None if resume_from is None else str(resume_from),
                        **flusher) as log:
            if resume_from is not None:
                log.log_optimizer_state(opt, reason="resume")
            session = BridgeSession(opt, gate, device, cart, log, settings,  # type: ignore[arg-type]
                                    protocol=protocol, clock=loop.time)
            holder["session"] = session
            session.status.listeners.append(events.append)
            session._worker = InlineWorker(worker_start_s, fit_s)  # type: ignore[assignment]
            device.is_paused = lambda: session.supervisor.paused
            if at_time_s is not None:
                loop.call_at(at_time_s, fire)
            for t in operator_r_s:
                loop.call_at(t, session.command, Command.RESUME)
            if on_session is not None:
                on_session(session)
            if watch is None:
                return await session.run()
            # Its own (counted) task: the session loop's own await points are suspensions too.
            return await loop.create_task(session.run(), name=SESSION_TASK)

    loop = looptime.new_event_loop(start=0.0, noop_cycles=1)
    try:
        summary = loop.run_until_complete(asyncio.wait_for(main(), 4000.0))
    finally:
        loop.run_until_complete(loop.shutdown_asyncgens())
        loop.close()
    return Outcome(summary, device, holder["session"], inj, cart, events, log_path)
