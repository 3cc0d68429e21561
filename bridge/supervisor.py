"""The one owner of a session's supervision state (shared/DESIGN.md, safety invariants).

A person wears the exosuit, so *a pause holds*: nothing is committed or assisting while the
session is paused, whatever task was in the middle of a push. Before this module the state that
decides it (paused, stopped, assistance on, the bridge heartbeat's state, the safety gate's
rate-limit baseline) had writers in the main, watchdog, command, cart and bus tasks, and a pause
that arrived while the next proposal was computed was undone by the push that followed.

Now :class:`Supervisor` alone writes that state. Every other task sends it an event
(:meth:`~Supervisor.pause`, :meth:`~Supervisor.stop`, :meth:`~Supervisor.assistance_off`,
:meth:`~Supervisor.resume`) or asks it for permission:

* a push opens a :class:`PushTicket` (:meth:`~Supervisor.begin_push`), refused while paused;
* the endpoint asks :meth:`~Supervisor.permit` at the last moment before the first segment and
  before every commit; only a permitted first segment switches the heartbeat to ``running``
  (the device leaves assistance-off only when a commit is acked while the heartbeat says
  ``running``: drivers/PROTOCOL.md);
* the ack is accepted only through :meth:`~Supervisor.acknowledged`, which refuses a ticket that
  a pause, stop or assistance-off overtook (the epoch counter) -- the gate's baseline and the
  "assisting" flag are set there and nowhere else.

Every event that turns assistance off advances the epoch *synchronously*, before its first
``await``, so no permission check can come between a pause and its effect.
"""

from __future__ import annotations

import asyncio
import enum
import logging
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol

from drivers.errors import DriverError
from drivers.exosuit import AssistanceOffReason, BridgeState, FaultRecovery

__all__ = ["PushRefused", "PushStage", "PushTicket", "Supervisor", "SupervisorState"]

logger = logging.getLogger(__name__)


class SupervisorState(enum.Enum):
    """What the session is doing, as the supervisor sees it."""

    STARTING = "starting"  # no profile acknowledged yet in this session
    RUNNING = "running"  # a profile was acknowledged since the last pause
    PAUSED = "paused"
    STOPPED = "stopped"


class PushStage(enum.Enum):
    """The moments of a push at which the endpoint asks for permission."""

    FIRST_SEGMENT = "first_segment"
    COMMIT = "commit"


class PushRefused(Exception):
    """:meth:`Supervisor.begin_push` while the session is paused or stopped (no frame is sent)."""


class _Endpoint(Protocol):
    """What the supervisor drives on the CAN endpoint."""

    bridge_state: BridgeState

    async def send_assistance_off(self, reason: AssistanceOffReason) -> None:
        """Command the safe state now."""


class _Gate(Protocol):
    """The safety gate's baseline, which only the supervisor moves."""

    def acknowledge(self, admitted: Any) -> None:
        """``admitted`` was acknowledged by the device: the new rate-limit baseline."""

    def assistance_off(self) -> None:
        """Assistance went off: no rate-limit baseline."""


@dataclass(frozen=True)
class PushTicket:
    """One push's permission, valid while no pause, stop or assistance-off overtakes it.

    Attributes:
        epoch: The supervisor's epoch when the push began.
        version: The profile version pushed (1..255).
        admitted: What the safety gate admitted (``bridge.safety.AdmittedProfile``).
    """

    epoch: int
    version: int
    admitted: Any


class Supervisor:
    """Owns pause, stop, assistance on/off, the heartbeat's bridge state and the gate's baseline.

    Args:
        endpoint: The CAN endpoint (its ``bridge_state`` is written only here from now on).
        gate: The safety gate (its baseline is moved only here).
        on_event: ``(kind, text)`` for the session's events log and display.
        health: Returns why the session may not resume now (device, cart), or None.
    """

    def __init__(self, endpoint: _Endpoint, gate: _Gate, *,
                 on_event: Callable[[str, str], None],
                 health: Callable[[], str | None] = lambda: None) -> None:
        self._endpoint = endpoint
        self._gate = gate
        self._on_event = on_event
        self._health = health
        self._paused = asyncio.Event()
        self._stopped = asyncio.Event()
        self._epoch = 0
        self._pauses = 0
        self._assist_on = False
        self._acked_once = False
        #: The reasons of the current pause, oldest first, with their assistance-off reasons.
        self._causes: dict[str, AssistanceOffReason] = {}
        #: The causes of the current pause after which only a person may resume: kept here, not
        #: re-read from the device, so a fault that disappears by itself (an emergency stop
        #: released, a device that unlatches) still needs the person's ``r``.
        self._person_causes: list[str] = []
        self._last_reason = ""
        #: Counts of what the supervisor refused or saw: pushes refused at begin, first segments
        #: and commits refused (an aborted push), acks overtaken by a pause, resumes refused.
        self.counters: Counter[str] = Counter()

    # ---------------------------------------------------------------- queries
    @property
    def state(self) -> SupervisorState:
        """The session's supervision state."""
        if self._stopped.is_set():
            return SupervisorState.STOPPED
        if self._paused.is_set():
            return SupervisorState.PAUSED
        return SupervisorState.RUNNING if self._acked_once else SupervisorState.STARTING

    @property
    def paused(self) -> bool:
        """True while paused (a stop is a pause that never ends)."""
        return self._paused.is_set()

    @property
    def stopped(self) -> bool:
        """True once the session was stopped."""
        return self._stopped.is_set()

    @property
    def assisting(self) -> bool:
        """True between an accepted ack and the next assistance-off."""
        return self._assist_on

    @property
    def pause_reason(self) -> str:
        """Why the session is paused ("; "-joined reasons), or was last ("" before any pause)."""
        return "; ".join(self._causes) if self._causes else self._last_reason

    @property
    def by_operator(self) -> bool:
        """True while the current pause includes the operator's own pause (or stop)."""
        return AssistanceOffReason.OPERATOR_STOP in self._causes.values()

    @property
    def needs_person(self) -> bool:
        """True while the current pause has a cause after which only a person may resume: the
        operator's own pause, or a fault of class ``PERSON`` (drivers/exosuit/faults.py)."""
        return bool(self._person_causes)

    def has_cause(self, text: str) -> bool:
        """True while the current pause (or the stop) has ``text`` among its causes."""
        return text in self._causes

    def has_reason(self, reason: AssistanceOffReason) -> bool:
        """True while the current pause (or the stop) has a cause of this ``reason``."""
        return AssistanceOffReason(reason) in self._causes.values()

    @property
    def person_causes(self) -> tuple[str, ...]:
        """The causes of the current pause that need a person, oldest first."""
        return tuple(self._person_causes)

    @property
    def epoch(self) -> int:
        """Advances at every pause, stop and assistance-off; a ticket of an older epoch is void."""
        return self._epoch

    @property
    def pauses(self) -> int:
        """How many pauses the session has had (each new cause of a pause counts)."""
        return self._pauses

    def describe(self) -> str:
        """The state line of the operator view."""
        st = self.state
        if st is SupervisorState.PAUSED:
            return f"paused: {self.pause_reason}"
        return st.value

    async def wait_paused(self) -> None:
        """Return once the session is paused (or stopped)."""
        await self._paused.wait()

    async def wait_stopped(self) -> None:
        """Return once the session is stopped."""
        await self._stopped.wait()

    # ---------------------------------------------------------------- events
    async def pause(self, reason: AssistanceOffReason, text: str, *,
                    recovery: FaultRecovery = FaultRecovery.POLICY) -> None:
        """Pause the session and command assistance-off now (idempotent for the same reason).

        Args:
            reason: The AssistanceOff reason sent to the device.
            text: The cause, for the operator and the log.
            recovery: Who may end this pause. ``PERSON`` (always for the operator's own pause):
                only :meth:`resume` with ``by_person=True``. ``END`` stops the session.
        """
        recovery = FaultRecovery(recovery)
        if recovery is FaultRecovery.END:
            await self.stop(reason, text)
            return
        if text not in self._causes:
            # A pause during a pause adds its reason (the operator sees "between bouts" as well
            # as the heartbeat loss before it); one resume ends them all.
            self._causes[text] = AssistanceOffReason(reason)
            self._paused.set()
            self._pauses += 1
            self._on_event("pause", text)
        if ((recovery is FaultRecovery.PERSON or reason == AssistanceOffReason.OPERATOR_STOP)
                and text not in self._person_causes):
            self._person_causes.append(text)
        await self._off(reason, text)

    async def stop(self, reason: AssistanceOffReason, text: str) -> None:
        """Stop the session for good: assistance-off, and every later push is refused."""
        if not self._stopped.is_set():
            self._stopped.set()
            self._paused.set()
            self._causes[text] = AssistanceOffReason(reason)
        await self._off(reason, text)

    async def assistance_off(self, reason: AssistanceOffReason, text: str) -> None:
        """Assistance off without pausing (warm-ups, the session's end)."""
        await self._off(reason, text)

    def resume(self, source: str, *, by_person: bool = False) -> str | None:
        """End a pause if the session is healthy and whoever resumes may end it.

        Args:
            source: Who resumes ("operator", "resume policy (1 of 10)"), for the event.
            by_person: A person at the PC asked for it (the operator's ``r``). A pause with a
                cause of class ``PERSON`` (:attr:`needs_person`) ends only so.

        Returns:
            None when resumed (or not paused), else why the resume was refused.
        """
        if self._stopped.is_set():
            return "the session is stopped"
        if not self._paused.is_set():
            return None
        if self._person_causes and not by_person:
            why = ("only a person at the PC may resume after "
                   + "; ".join(self._person_causes) + " (press r once it is safe)")
            self.counters["resume_refused"] += 1
            return why
        why = self._health()
        if why is not None:
            self.counters["resume_refused"] += 1
            self._on_event("resume_refused", f"cannot resume ({source}): {why}")
            return why
        self._last_reason = self.pause_reason
        self._causes.clear()
        self._person_causes.clear()
        self._paused.clear()
        self._on_event("resume", f"resumed by the {source}")
        return None

    async def _off(self, reason: AssistanceOffReason, text: str) -> None:
        # Synchronously first: the epoch voids every ticket in flight and the heartbeat says
        # "paused" from its next frame on, even if the AssistanceOff frame below is lost.
        self._epoch += 1
        was_assisting = self._assist_on
        self._assist_on = False
        if self._endpoint.bridge_state == BridgeState.RUNNING:
            self._endpoint.bridge_state = BridgeState.PAUSED
        try:
            await self._endpoint.send_assistance_off(reason)
        except DriverError as err:
            logger.exception("assistance-off could not be sent (%s)", text)
            self._on_event("assistance_off_failed", f"{text}: {err}")
            return
        # Only once the device was told: until then its last acked table is the baseline.
        self._gate.assistance_off()
        if was_assisting:
            self._on_event("assistance_off", f"assistance off: {text}")

    # ---------------------------------------------------------------- the push
    def begin_push(self, admitted: Any, version: int) -> PushTicket:
        """Open a push of ``admitted`` as ``version``.

        Raises:
            PushRefused: The session is paused or stopped; nothing may be sent.
        """
        if self._paused.is_set():
            self.counters["push_refused"] += 1
            raise PushRefused(f"push of v{version} refused: {self.describe()}")
        return PushTicket(self._epoch, version, admitted)

    def permit(self, ticket: PushTicket, stage: PushStage | str) -> bool:
        """The endpoint's last-moment question before the first segment and before each commit.

        A permitted first segment switches the heartbeat to ``running``. Refused once a pause,
        stop or assistance-off overtook the ticket: the endpoint then sends nothing more.
        """
        stage = PushStage(stage)
        if self._paused.is_set() or ticket.epoch != self._epoch:
            self.counters[f"{stage.value}_refused"] += 1
            return False
        if stage is PushStage.FIRST_SEGMENT:
            self._endpoint.bridge_state = BridgeState.RUNNING
        return True

    def acknowledged(self, ticket: PushTicket) -> bool:
        """The device acked ``ticket``'s commit. Returns False when a pause overtook it.

        An overtaken ack changes nothing: the assistance-off that overtook it followed the commit
        on the bus, and the heartbeat says ``paused``, so the device stays off.
        """
        if self._paused.is_set() or ticket.epoch != self._epoch:
            self.counters["ack_overtaken"] += 1
            return False
        self._gate.acknowledge(ticket.admitted)
        self._assist_on = True
        self._acked_once = True
        return True
