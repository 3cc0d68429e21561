"""SessionProtocol: the walking protocol of a HIL session, a pure state machine driven by breaths.

Kim et al. 2019 §IV.A.3: "two separate walking bouts: a 20-min (approx.) bout initializing the algorithm
with an evenly distributed pseudo-random set of parameters and a 40-min (approx.) bout to run
actual Bayesian optimization ... including 3-min warm-up periods in the beginning of each bout".
The phases (:class:`SessionPhase`)::

    WARM_UP_EXPLORATION -> EXPLORATION -> [BOUT_PAUSE] -> [WARM_UP_OPTIMIZATION] -> OPTIMIZATION -> ENDED

The second warm-up is skipped when nothing separates the bouts and ``warmup_without_pause`` is
false (the fast protocol, :class:`ProtocolKind`); with ``confirm_s`` the last seconds confirm the
recommendation (:attr:`SessionProtocol.confirm_due`).

The protocol knows *when* things happen; the optimizer (:class:`~hilbo_core.optimizer.HILOptimizer`)
knows *what* is measured. A driver (the bridge's asyncio process, the in-process simulation, the
benchmarks) feeds every breath's time to :meth:`SessionProtocol.on_breath` and does what the
returned :class:`Action` says; it reports what it did with :meth:`~SessionProtocol.on_setting_applied`,
:meth:`~SessionProtocol.on_evaluation_done`, :meth:`~SessionProtocol.on_setting_dropped`,
:meth:`~SessionProtocol.on_pause`, :meth:`~SessionProtocol.on_resume` and
:meth:`~SessionProtocol.stop`, each of which returns the next action too. No clock, no I/O: time
is the breath clock (the breaths' ``t_s``, seconds), so a simulated session and a lab session go
through the same states, and :func:`drive` runs a whole session synchronously.

**Warm-ups** are breath time: a warm-up that starts at t_w (the last breath before it, or the
session start, or the resume) ends with the first breath at t >= t_w + ``warmup_s``; that breath
is the warm-up's, and the first setting of the bout is applied at its time.

**Session time is walking time** (a lab has the hour it has). Every second of the breath clock counts,
whatever the session is doing (warm-ups, setting changes, measurements, pauses):

* ``session_s`` — the whole session from its start (both bouts, both warm-ups and the pause
  between them): what ``hilbo sim --minutes`` means.
* ``budget_s`` — the optimisation bout from its start (the end of its first warm-up, where Algorithm
  1's optimisation phase and the old breath-time counter start; or, when no warm-up separates the
  bouts, the end of the exploration bout) to the end: setting changes, pushes,
  pauses and the warm-ups after a pause all count. ``budget_breaths`` counts every breath of the
  same span.

Whichever is spent first ends the session, at the first breath at or past the deadline, so a
session overruns its time by less than one breath interval. The evaluation in progress at that
breath is measured with it and then closed with its breaths so far (``Action.final``; in the
optimizer :meth:`~hilbo_core.optimizer.HILOptimizer.close_current`: reason ``"budget"``, not an
early stop by the rule, and the GP weighs it by its larger variance). An exploration evaluation
cut short is dropped instead (Algorithm 2 needs full-length traces), and so is a setting not yet
measured. :attr:`SessionProtocol.walking` lists where the time went.
"""

from __future__ import annotations

import enum
import math
from collections.abc import Callable, Mapping
from dataclasses import asdict, dataclass
from typing import TYPE_CHECKING, Any

from hilbo_core.errors import ConfigError, HilboError, MeasurementError
from hilbo_core.optimizer import OptimizerConfig

if TYPE_CHECKING:
    from hilbo_core.optimizer import BreathStep, Evaluation, HILOptimizer

__all__ = [
    "DEFAULT_BREATH_INTERVAL_S",
    "Action",
    "ActionKind",
    "EndReason",
    "ProtocolKind",
    "ProtocolStateError",
    "SessionPhase",
    "SessionProtocol",
    "SessionProtocolConfig",
    "WalkingTime",
    "drive",
    "expected_end_s",
    "protocol_preset",
]

DEFAULT_BREATH_INTERVAL_S = 3.0
"""Mean breath interval (s) for estimates of a session's end: adults walking breathe about
20 times a minute (the simulated wearer's population mean is 2.5-3.5 s, virtual_hw/wearer.py)."""


class ProtocolStateError(HilboError, RuntimeError):
    """A call that the protocol's current state does not allow (e.g. a result without a setting)."""


class SessionPhase(enum.Enum):
    """Where the session is (Kim et al. 2019 §IV.A.3)."""

    WARM_UP_EXPLORATION = "warm_up_exploration"
    EXPLORATION = "exploration"
    BOUT_PAUSE = "bout_pause"
    WARM_UP_OPTIMIZATION = "warm_up_optimization"
    OPTIMIZATION = "optimization"
    ENDED = "ended"


class ProtocolKind(enum.Enum):
    """A named walking protocol (:func:`protocol_preset`): ``[protocol] protocol``."""

    # The default: the first optimisation proposal at about minute 10 of walking, and the
    # recommendation confirmed in the session's last minutes.
    FAST = "fast"
    # Kim et al. 2019 §IV.A.3: two bouts, each with a 3-minute warm-up, the exploration
    # settings measured for N breaths each; what the seed benchmarks use.
    SEED = "seed"


# Why the fast protocol's values (measured on `hilbo bench hil`'s realistic wearer, 30 subjects;
# the lab may override each key):
# * no pause and one warm-up: the second warm-up of Kim et al. 2019 starts a second walking bout
#   after a rest; walking on, the body is at a walking steady state already and each setting's
#   estimator starts from the level the last one ended at (the transition model of
#   hilbo_core.estimation), so 3 more unassisted minutes tell nothing;
# * 3 exploration settings (N breaths each) instead of 6: an exploration setting walks its N
#   breaths (~2 min) whatever it is, while the sound rule rejects a poor proposal after ~1 min,
#   so the GP learns more per minute from proposals once it has a few points; the first proposal
#   comes at a median 9.1 min (6 settings: 15.1 min) and the median regret at 30 and 60 min fell
#   (7.5 -> 5.0 % and 4.9 -> 3.9 % of the possible reduction). Ending exploration settings early
#   once their SD was 4 % of the estimate (explore_rel_sd) reached minute 10 too but cost regret
#   (9.6 % at 30 min, 7.0 % at 60): the GP and Algorithm 2 lose more from imprecise first points
#   than the minutes are worth;
# * 4 minutes at the end confirm the recommendation: N = 45 breaths at up to 3.5 s plus the
#   change of setting, measured in full, so the reported cost is a measurement of the setting
#   the lab takes home, not the optimistic estimate it was chosen for.
_PRESETS: dict[ProtocolKind, tuple[dict[str, Any], dict[str, Any]]] = {
    ProtocolKind.FAST: ({"n_explore": 3, "pause_between_bouts": False, "warmup_without_pause": False,
                         "confirm_s": 240.0},
                        {"n_explore": 3, "explore_rel_sd": None}),
    ProtocolKind.SEED: ({"n_explore": 6, "pause_between_bouts": True, "warmup_without_pause": True,
                         "confirm_s": None},
                        {"n_explore": 6, "explore_rel_sd": None}),
}


def protocol_preset(kind: ProtocolKind | str) -> tuple[dict[str, Any], dict[str, Any]]:
    """The settings of a named protocol: (SessionProtocolConfig fields, OptimizerConfig fields).

    A driver lays its own explicit values over these (e.g. simulations never pause).

    Raises:
        ConfigError: Unknown name (naming the choices).
    """
    try:
        k = ProtocolKind(kind)
    except ValueError as err:
        raise ConfigError(f"protocol={kind!r}; expected one of {[m.value for m in ProtocolKind]}") from err
    proto, opt = _PRESETS[k]
    return dict(proto), dict(opt)


class ActionKind(enum.Enum):
    """What the driver does now."""

    WARM_UP = "warm_up"  # walk without assistance (Action.starts: switch it off now)
    PROPOSE = "propose"  # a new setting is needed: ask, apply, then on_setting_applied(t_s)
    TRANSITION = "transition"  # a breath while the setting changes: not measured
    MEASURE = "measure"  # give this breath to the optimizer at Action.t_setting_s
    PAUSED = "paused"  # a breath during a pause: not measured (Action.starts: pause now)
    PAUSE_BETWEEN_BOUTS = "pause_between_bouts"  # assistance off; on_resume() when the operator says
    END = "end"  # the session is over


class EndReason(enum.Enum):
    """Why the session ended."""

    SESSION = "session"  # session_s walked
    BUDGET = "budget"  # budget_s walked in the optimisation bout
    BUDGET_BREATHS = "budget_breaths"  # budget_breaths breathed in the optimisation bout
    STOPPED = "stopped"  # stop(): the operator or the driver ended it


@dataclass(frozen=True)
class SessionProtocolConfig:
    """The walking protocol. The defaults are Kim et al. 2019's (§IV.A.3) and the optimizer's own.

    Attributes:
        warmup_s: Unassisted walking at the start of each bout, in breath time (s, >= 0).
        n_explore: Evaluations of the exploration bout (E, >= 0; the optimizer's ``n_explore``).
        max_breaths: The optimizer's N; used only to estimate the exploration bout's length.
        session_s: The whole session, from its start, in seconds of walking; or None.
        budget_s: The optimisation bout, from its start (the end of its first warm-up, or of the
            exploration bout when no warm-up separates them), in seconds of walking
            (default: Kim et al. 2019's 40-minute bout); or None.
        budget_breaths: The optimisation bout in breaths (all of them, from the same moment); or
            None. At least one of the three budgets is set; the first spent ends the session.
        pause_between_bouts: Pause (assistance off) after the exploration bout until the driver
            calls :meth:`SessionProtocol.on_resume` (the operator's resume).
        warmup_without_pause: Without a pause between the bouts, warm up again before the
            optimisation bout anyway (the seed's two bouts). After a pause there is always a
            warm-up.
        confirm_s: The session's last seconds (of the first budget to run out) are for
            confirming the recommendation: from then on :attr:`SessionProtocol.confirm_due` is
            True and the driver measures the recommended setting in full
            (:meth:`~hilbo_core.optimizer.HILOptimizer.begin_confirmation`); None: no confirmation.
        short_pause_s: A pause at most this long (breath time, s >= 0; 0: none is short) ends
            without a warm-up: the setting it abandoned is measured again at once, from the
            body's level at the resume (a warm-up in progress goes on where it was). Longer
            pauses end with the bout's full warm-up. Why 30 s: VO2 follows a change of walking
            load with a time constant of about 42 s (Selinger & Donelan 2014, J Appl Physiol
            117:1406), on and off alike in moderate exercise (Özyener et al. 2001, J Physiol
            533:891), so 30 s unassisted moves the body about half of the way from the
            setting's level towards unassisted walking (1 − e^(−30/42) = 0.51): a step no larger
            than a change from a good setting to a poor one, which Kim et al. 2019 measure back
            to back (their 3-min warm-ups only open a bout) and the transition estimator models
            from the body's level at the push. 30 s also holds a glitch that the resume policy
            ends (its wait for 10 s of health after the cause is gone, plus the detection), so
            a heartbeat lost for a moment on a busy PC does not cost a 3-min warm-up. Longer
            pauses may mean the wearer stood or stepped off; those get the warm-up.
    """

    warmup_s: float = 180.0
    n_explore: int = OptimizerConfig.n_explore
    max_breaths: int = OptimizerConfig.max_breaths
    session_s: float | None = None
    budget_s: float | None = 2400.0
    budget_breaths: int | None = None
    pause_between_bouts: bool = True
    warmup_without_pause: bool = True
    confirm_s: float | None = None
    short_pause_s: float = 30.0

    def __post_init__(self) -> None:
        if not _is_number(self.warmup_s) or not (math.isfinite(self.warmup_s) and self.warmup_s >= 0):
            raise ConfigError(f"warmup_s={self.warmup_s!r}; expected a number of seconds >= 0")
        _int_at_least("n_explore", self.n_explore, 0)
        _int_at_least("max_breaths", self.max_breaths, 1)
        for name in ("session_s", "budget_s"):
            v = getattr(self, name)
            if v is not None and not (_is_number(v) and math.isfinite(v) and v > 0):
                raise ConfigError(f"{name}={v!r}; expected a positive number of seconds or None")
        if self.budget_breaths is not None:
            _int_at_least("budget_breaths", self.budget_breaths, 1)
        if self.session_s is None and self.budget_s is None and self.budget_breaths is None:
            raise ConfigError("no budget: expected session_s, budget_s or budget_breaths "
                              "(a session must end)")
        for name in ("pause_between_bouts", "warmup_without_pause"):
            if not isinstance(getattr(self, name), bool):
                raise ConfigError(f"{name}={getattr(self, name)!r}; expected true or false")
        c = self.confirm_s
        if c is not None and not (_is_number(c) and math.isfinite(c) and c > 0):
            raise ConfigError(f"confirm_s={c!r}; expected a positive number of seconds or None")
        if not _is_number(self.short_pause_s) or not (
                math.isfinite(self.short_pause_s) and self.short_pause_s >= 0):
            raise ConfigError(f"short_pause_s={self.short_pause_s!r}; expected a number of seconds >= 0")

    def to_json(self) -> dict[str, Any]:
        """JSON-able form."""
        return asdict(self)


def _is_number(v: object) -> bool:
    return isinstance(v, int | float) and not isinstance(v, bool)


def _int_at_least(name: str, value: object, low: int) -> None:
    if isinstance(value, bool) or not isinstance(value, int) or value < low:
        raise ConfigError(f"{name}={value!r}; expected an integer >= {low}")


@dataclass(frozen=True)
class Action:
    """What the driver does now.

    Attributes:
        kind: The instruction.
        phase: The session's phase after it.
        t_s: The breath clock now (s): the breath's time, or the last breath's for an action
            that answers a call (None before any breath when no start time was given).
        t_setting_s: MEASURE: seconds since the setting was applied (the optimizer's ``t``).
        final: MEASURE: the session's time runs out with this breath; give it to the optimizer,
            then close the evaluation (if the rule did not stop it) and call
            :meth:`SessionProtocol.on_evaluation_done` (or :meth:`~SessionProtocol.on_setting_dropped`).
        starts: The phase begins with this action (WARM_UP: switch assistance off now; PAUSED:
            the pause begins, the setting being measured is abandoned).
        end_reason: END: why.
    """

    kind: ActionKind
    phase: SessionPhase
    t_s: float | None
    t_setting_s: float | None = None
    final: bool = False
    starts: bool = False
    end_reason: EndReason | None = None


@dataclass(frozen=True)
class WalkingTime:
    """Where a session's walking time went (s, breath clock).

    Each breath interval counts once, for what the breath that ends it was for (the first
    measured breath's interval is split at the setting's switch).

    Attributes:
        session_s: From the session's start to the last breath.
        warm_up_s: In warm-ups.
        transition_s: From a proposal to the first measured breath of its setting (asking,
            pushing, waiting for the device, and the first breath interval up to the switch).
        measured_s: From each setting's switch to its last breath (what the optimizer sees).
        paused_s: In pauses, the pause between the bouts included.
        after_end_s: Breaths given after the end.
        optimization_s: The optimisation bout so far (what ``budget_s`` counts).
        optimization_breaths: Its breaths (what ``budget_breaths`` counts).
    """

    session_s: float = 0.0
    warm_up_s: float = 0.0
    transition_s: float = 0.0
    measured_s: float = 0.0
    paused_s: float = 0.0
    after_end_s: float = 0.0
    optimization_s: float = 0.0
    optimization_breaths: int = 0

    def to_json(self) -> dict[str, Any]:
        """JSON-able form (the session summary's ``walking`` entry)."""
        return asdict(self)


_MEASURING = (SessionPhase.EXPLORATION, SessionPhase.OPTIMIZATION)
_WARM_UP_OF = {SessionPhase.WARM_UP_EXPLORATION: SessionPhase.EXPLORATION,
               SessionPhase.WARM_UP_OPTIMIZATION: SessionPhase.OPTIMIZATION}


class SessionProtocol:
    """The session's walking protocol, one breath at a time (module docstring).

    Args:
        config: The protocol.
        t_start_s: The session's start on the breath clock (the first warm-up starts then); None:
            at the first breath.

    Example:
        >>> proto = SessionProtocol(SessionProtocolConfig(warmup_s=6.0, n_explore=1, budget_s=9.0,
        ...                                               pause_between_bouts=False), t_start_s=0.0)
        >>> proto.start().kind, proto.on_breath(3.0).kind, proto.on_breath(6.0).kind
        (<ActionKind.WARM_UP: 'warm_up'>, <ActionKind.WARM_UP: 'warm_up'>, <ActionKind.PROPOSE: 'propose'>)
    """

    def __init__(self, config: SessionProtocolConfig | None = None, *,
                 t_start_s: float | None = None) -> None:
        self.config = config if config is not None else SessionProtocolConfig()
        if t_start_s is not None:
            t_start_s = _check_t("t_start_s", t_start_s)
        self._t_last: float | None = t_start_s
        self._t0: float | None = t_start_s  # session start
        self._session_used_s = 0.0  # walked before a resume (resumed())
        self._phase = SessionPhase.WARM_UP_EXPLORATION
        self._paused = False
        self._t_pause: float | None = None  # the last breath before the pause began
        self._paused_warm_start: float | None = None  # the warm-up's start when the pause began
        self.last_pause_s: float | None = None  # the breath time of the last pause that ended
        self._warm_start: float | None = t_start_s  # None: the next breath starts the warm-up
        self._proposing = False  # PROPOSE given, on_setting_applied not yet called
        self._t_setting: float | None = None  # the measured setting's switch time
        self._setting_breaths = 0
        self._n_explored = 0
        self._opt_begun = False
        self._t_opt: float | None = None  # the optimisation bout's start (None: the next breath)
        self._opt_used_s = 0.0
        self._opt_breaths = 0
        self._final_reason: EndReason | None = None  # the budget ran out during a measurement
        self._end_reason: EndReason | None = None
        self._started = False
        self._walk = {k: 0.0 for k in ("warm_up_s", "transition_s", "measured_s", "paused_s", "after_end_s")}

    @classmethod
    def resumed(cls, config: SessionProtocolConfig, *, n_explored: int, t_start_s: float | None = None,
                session_used_s: float = 0.0, optimization_used_s: float = 0.0,
                optimization_used_breaths: int = 0) -> SessionProtocol:
        """The protocol of a session resumed from its log (the bridge's ``--resume``).

        It starts with a warm-up of the bout the session was in (no pause between the bouts when
        the exploration bout is complete) and counts what was walked before against the budgets.

        Args:
            config: The protocol.
            n_explored: Completed exploration evaluations (the optimizer's, capped at E).
            t_start_s: The resumed session's start on its breath clock (None: the first breath).
            session_used_s: Walking time of the session before the resume (s; it counts
                against ``session_s``, and in :attr:`walking`'s ``session_s`` only).
            optimization_used_s: Of the optimisation bout before the resume (s).
            optimization_used_breaths: Breaths of the optimisation bout before the resume.
        """
        _int_at_least("n_explored", n_explored, 0)
        _int_at_least("optimization_used_breaths", optimization_used_breaths, 0)
        for name, v in (("session_used_s", session_used_s), ("optimization_used_s", optimization_used_s)):
            if not (_is_number(v) and math.isfinite(v) and v >= 0):
                raise ConfigError(f"{name}={v!r}; expected a number of seconds >= 0")
        proto = cls(config, t_start_s=t_start_s)
        proto._n_explored = min(n_explored, config.n_explore)
        proto._session_used_s = float(session_used_s)
        if proto._n_explored == config.n_explore:
            proto._phase = SessionPhase.WARM_UP_OPTIMIZATION
            if optimization_used_s > 0 or optimization_used_breaths > 0:
                # The bout had begun: its resume warm-up counts against the budget. (Otherwise
                # the session stopped between the bouts, and the budget starts after the warm-up.)
                proto._opt_used_s = float(optimization_used_s)
                proto._opt_breaths = optimization_used_breaths
                proto._opt_begun = True
                proto._t_opt = t_start_s
        return proto

    # ------------------------------------------------------------------ read-only views
    @property
    def phase(self) -> SessionPhase:
        """The current phase."""
        return self._phase

    @property
    def session_used_s(self) -> float:
        """Walking time of the session before a resume (s; 0 for a session started afresh)."""
        return self._session_used_s

    @property
    def ended(self) -> bool:
        """The session is over."""
        return self._phase is SessionPhase.ENDED

    @property
    def end_reason(self) -> EndReason | None:
        """Why it ended (None while it runs)."""
        return self._end_reason

    @property
    def paused(self) -> bool:
        """An operator pause (:meth:`on_pause`) is in effect."""
        return self._paused

    @property
    def t_s(self) -> float | None:
        """The breath clock now: the last breath (before any, the start time or None)."""
        return self._t_last

    @property
    def optimization_started(self) -> bool:
        """The optimisation bout has begun (its first warm-up is over, or the exploration bout when
        no warm-up separates them, or it was resumed)."""
        return self._opt_begun

    @property
    def n_explored(self) -> int:
        """Completed exploration evaluations."""
        return self._n_explored

    @property
    def t_end_s(self) -> float | None:
        """The breath-clock time at which the walking-time budget runs out, once it is fixed:
        from the start with ``session_s``, from the optimisation bout's start with ``budget_s``;
        None before (or with a breath budget only: see :meth:`expected_t_end_s`)."""
        ends = []
        c = self.config
        if c.session_s is not None and self._t0 is not None:
            ends.append(self._t0 - self._session_used_s + c.session_s)
        if c.budget_s is not None and self._t_opt is not None:
            ends.append(self._t_opt - self._opt_used_s + c.budget_s)
        return min(ends) if ends else None

    def expected_t_end_s(self, breath_interval_s: float = DEFAULT_BREATH_INTERVAL_S) -> float | None:
        """The expected end on the breath clock (for the operator view): :attr:`t_end_s` when
        only time budgets remain, else an estimate with ``breath_interval_s`` per breath, the
        remaining exploration evaluations at N breaths, no pause between the bouts and no
        setting changes. None before the session's start is known."""
        if self._t_last is None:
            return None
        now = self._t_last
        if self.ended:
            return now
        c, bi = self.config, float(breath_interval_s)
        ends = []
        if c.session_s is not None and self._t0 is not None:
            ends.append(self._t0 - self._session_used_s + c.session_s)
        if self._t_opt is not None:
            t_opt, used_s, used_b = self._t_opt, self._opt_used_s, self._opt_breaths
        else:
            # The optimisation bout starts after what is left of the exploration bout and the
            # warm-ups (a pause's length is unknown: none is assumed).
            left = (max(0.0, self._warm_start + c.warmup_s - now)
                    if self._phase in _WARM_UP_OF and self._warm_start is not None else 0.0)
            if self._phase is not SessionPhase.WARM_UP_OPTIMIZATION and (
                    c.pause_between_bouts or c.warmup_without_pause):
                left += c.warmup_s
            n_left = c.n_explore - self._n_explored
            if n_left > 0:
                left += max(0, n_left * c.max_breaths - self._setting_breaths) * bi
            t_opt, used_s, used_b = now + left, 0.0, 0
        if c.budget_s is not None:
            ends.append(t_opt - used_s + c.budget_s)
        if c.budget_breaths is not None:
            ends.append(max(now, t_opt) + (c.budget_breaths - used_b) * bi)
        return max(min(ends), now)

    @property
    def confirm_due(self) -> bool:
        """The optimisation bout is in its last ``confirm_s`` (of the expected end): the next
        setting is the recommendation, measured in full (the driver calls
        :meth:`~hilbo_core.optimizer.HILOptimizer.begin_confirmation` before asking)."""
        c = self.config.confirm_s
        if c is None or self._phase is not SessionPhase.OPTIMIZATION or self._t_last is None:
            return False
        end = self.expected_t_end_s()
        return end is not None and end - self._t_last <= c

    @property
    def walking(self) -> WalkingTime:
        """Where the walking time went so far."""
        opt_s = 0.0
        if self._t_opt is not None and self._t_last is not None:
            opt_s = self._opt_used_s + max(0.0, self._t_last - self._t_opt)
        session_s = 0.0
        if self._t0 is not None and self._t_last is not None:
            session_s = self._session_used_s + self._t_last - self._t0
        return WalkingTime(session_s=session_s, optimization_s=opt_s,
                           optimization_breaths=self._opt_breaths, **self._walk)

    # ------------------------------------------------------------------ events
    def start(self) -> Action:
        """The first action: the first warm-up (or, with ``warmup_s`` 0, the first proposal).

        Raises:
            ProtocolStateError: Called twice.
        """
        if self._started:
            raise ProtocolStateError("start() called twice")
        self._started = True
        if self._phase is SessionPhase.WARM_UP_OPTIMIZATION:  # resumed()
            return self._enter_warm_up(SessionPhase.WARM_UP_OPTIMIZATION)
        return self._enter_warm_up(SessionPhase.WARM_UP_EXPLORATION)

    def on_breath(self, t_s: float) -> Action:
        """Account one breath (every breath of the session, in order) and say what to do with it.

        Args:
            t_s: The breath's time on the breath clock (s), later than the previous one.

        Returns:
            WARM_UP, TRANSITION, MEASURE, PAUSED or END; PROPOSE when the breath ends a warm-up.

        Raises:
            ProtocolStateError: Before :meth:`start`, or after a final MEASURE that was not answered.
            MeasurementError: ``t_s`` not finite or not later than the last breath.
        """
        if not self._started:
            raise ProtocolStateError("on_breath() before start()")
        if self._final_reason is not None:
            raise ProtocolStateError("on_breath() after the final breath: close the evaluation "
                                     "(on_evaluation_done or on_setting_dropped) first")
        t = _check_t("t_s", t_s)
        prev = self._t_last
        if prev is not None and t <= prev:
            raise MeasurementError(f"breath time t_s={t!r} does not increase (previous {prev!r} s)")
        dt = 0.0 if prev is None else t - prev
        self._t_last = t
        if self._t0 is None:
            self._t0 = t
        if self._opt_begun and self._t_opt is None:
            self._t_opt = t
        if self._phase is SessionPhase.ENDED:
            self._walk["after_end_s"] += dt
            return self._action(ActionKind.END, end_reason=self._end_reason)
        if self._t_opt is not None and t > self._t_opt:
            self._opt_breaths += 1
        spent = self._spent(t)
        if self._paused or self._phase is SessionPhase.BOUT_PAUSE:
            self._walk["paused_s"] += dt
            return self._end(spent) if spent else self._action(ActionKind.PAUSED)
        if self._phase in _WARM_UP_OF:
            self._walk["warm_up_s"] += dt
            if spent:
                return self._end(spent)
            if self._warm_start is None:
                self._warm_start = t
            if t - self._warm_start >= self.config.warmup_s:
                return self._enter_measuring(_WARM_UP_OF[self._phase])
            return self._action(ActionKind.WARM_UP)
        # measuring phase
        ts = self._t_setting
        if ts is None or t <= ts:
            self._walk["transition_s"] += dt
            return self._end(spent) if spent else self._action(ActionKind.TRANSITION)
        from_t = ts if prev is None else max(prev, ts)
        self._walk["measured_s"] += t - from_t
        self._walk["transition_s"] += dt - (t - from_t)
        self._setting_breaths += 1
        self._final_reason = spent
        return self._action(ActionKind.MEASURE, t_setting_s=t - ts, final=spent is not None)

    def on_setting_applied(self, t_s: float | None = None) -> None:
        """The proposed setting is in effect from ``t_s`` (default: the last breath) on; breaths
        after it are measured.

        Raises:
            ProtocolStateError: No PROPOSE is waiting for its setting.
            MeasurementError: ``t_s`` earlier than the last breath.
        """
        if not self._proposing or self._phase not in _MEASURING or self._paused:
            raise ProtocolStateError(f"on_setting_applied() without a proposal (phase {self._phase.value})")
        if t_s is None:
            t_s = self._t_last
            if t_s is None:
                raise ProtocolStateError("on_setting_applied() needs t_s before the first breath")
        t = _check_t("t_s", t_s)
        if self._t_last is not None and t < self._t_last:
            raise MeasurementError(f"setting applied at t_s={t!r}, before the last breath at "
                                   f"{self._t_last!r} s")
        if self._t_last is None:  # before any breath: the session starts now
            self._t_last = self._t0 = t
            if self._opt_begun and self._t_opt is None:
                self._t_opt = t
        self._proposing, self._t_setting, self._setting_breaths = False, t, 0

    def on_evaluation_done(self) -> Action:
        """The measured setting's evaluation is complete (the stopping rule, or closed after a
        final breath). Returns PROPOSE, PAUSE_BETWEEN_BOUTS, WARM_UP (starts) or END.

        Raises:
            ProtocolStateError: No setting is being measured.
        """
        if self._phase not in _MEASURING or self._paused or self._t_setting is None:
            raise ProtocolStateError("on_evaluation_done() without a measured setting "
                                     f"(phase {self._phase.value})")
        self._t_setting, self._setting_breaths = None, 0
        if self._phase is SessionPhase.EXPLORATION:
            self._n_explored += 1
        if self._final_reason is not None:
            return self._end(self._final_reason)
        return self._next_setting()

    def on_setting_dropped(self) -> Action:
        """The proposed or measured setting was abandoned (refused by the safety limits, cut by
        the end, ...): it does not count. Returns PROPOSE (ask again) or END.

        Raises:
            ProtocolStateError: No setting was proposed.
        """
        has_setting = self._proposing or self._t_setting is not None
        if self._phase not in _MEASURING or self._paused or not has_setting:
            raise ProtocolStateError(f"on_setting_dropped() without a setting (phase {self._phase.value})")
        self._proposing, self._t_setting, self._setting_breaths = False, None, 0
        if self._final_reason is not None:
            return self._end(self._final_reason)
        return self._next_setting()

    def on_pause(self) -> Action:
        """The session pauses (operator, fault): the setting being measured, if any, is abandoned
        (the driver cancels it in the optimizer). Breaths go on counting as walking time. Returns
        PAUSED (``starts`` when the pause begins now) or END after the end."""
        if self._phase is SessionPhase.ENDED:
            return self._action(ActionKind.END, end_reason=self._end_reason)
        if self._phase is SessionPhase.BOUT_PAUSE:
            return self._action(ActionKind.PAUSED)
        starts = not self._paused
        if starts:
            self._t_pause, self._paused_warm_start = self._t_last, self._warm_start
        self._paused = True
        self._proposing, self._t_setting, self._setting_breaths = False, None, 0
        self._final_reason = None
        self._warm_start = None
        return self._action(ActionKind.PAUSED, starts=starts)

    def on_resume(self, t_s: float | None = None) -> Action:
        """The operator resumes: after the pause between the bouts, the optimisation bout's
        warm-up; after another pause, a warm-up of the bout the session is in, unless the pause
        was short (``short_pause_s``, on the breath clock: from the last breath before it to
        ``t_s``): then PROPOSE at once (the driver measures the abandoned setting again), or the
        warm-up it interrupted goes on (WARM_UP, not ``starts``). A warm-up starts at ``t_s``
        (default: the last breath). Returns WARM_UP, PROPOSE or END.

        Raises:
            ProtocolStateError: Nothing is paused.
            MeasurementError: ``t_s`` earlier than the last breath.
        """
        if self._phase is SessionPhase.ENDED:
            return self._action(ActionKind.END, end_reason=self._end_reason)
        if not (self._paused or self._phase is SessionPhase.BOUT_PAUSE):
            raise ProtocolStateError(f"on_resume() while not paused (phase {self._phase.value})")
        t = None
        if t_s is not None:
            t = _check_t("t_s", t_s)
            if self._t_last is not None and t < self._t_last:
                raise MeasurementError(f"resume at t_s={t!r}, before the last breath at {self._t_last!r} s")
            if self._t_last is None:  # before any breath: the session starts now
                self._t_last = self._t0 = t
        between_bouts = self._phase is SessionPhase.BOUT_PAUSE
        self._paused = False
        short = self._short_resume(t, between_bouts)
        if short is not None:
            return short
        bout = (SessionPhase.WARM_UP_EXPLORATION
                if self._phase in (SessionPhase.WARM_UP_EXPLORATION, SessionPhase.EXPLORATION)
                else SessionPhase.WARM_UP_OPTIMIZATION)
        return self._enter_warm_up(bout, t)

    def _short_resume(self, t_s: float | None, between_bouts: bool) -> Action | None:
        """The end of a short pause (``short_pause_s``): the warm-up it interrupted goes on, or
        the abandoned setting is proposed again; None when the pause was long (or between the
        bouts, whose warm-up opens the optimisation bout). Sets :attr:`last_pause_s`."""
        t = self._t_last if t_s is None else t_s
        t_pause, warm_start = self._t_pause, self._paused_warm_start
        self._t_pause = self._paused_warm_start = None
        pause_s = None if t is None or t_pause is None else t - t_pause
        self.last_pause_s = pause_s
        limit_s = self.config.short_pause_s
        if between_bouts or pause_s is None or limit_s == 0 or pause_s > limit_s:
            return None
        if self._phase in _WARM_UP_OF:
            self._warm_start = warm_start
            return self._action(ActionKind.WARM_UP)
        return self._next_setting()

    def stop(self) -> Action:
        """End the session now (operator stop). Returns END."""
        if self._phase is not SessionPhase.ENDED:
            return self._end(EndReason.STOPPED)
        return self._action(ActionKind.END, end_reason=self._end_reason)

    # ------------------------------------------------------------------ internals
    def _action(self, kind: ActionKind, **kw: Any) -> Action:
        return Action(kind, self._phase, self._t_last, **kw)

    def _spent(self, t: float) -> EndReason | None:
        c = self.config
        if c.session_s is not None and self._t0 is not None and (
                self._session_used_s + t - self._t0 >= c.session_s):
            return EndReason.SESSION
        if self._t_opt is not None:
            if c.budget_s is not None and self._opt_used_s + t - self._t_opt >= c.budget_s:
                return EndReason.BUDGET
            if c.budget_breaths is not None and self._opt_breaths >= c.budget_breaths:
                return EndReason.BUDGET_BREATHS
        return None

    def _end(self, reason: EndReason) -> Action:
        self._phase = SessionPhase.ENDED
        self._paused = self._proposing = False
        self._t_setting, self._final_reason = None, None
        self._end_reason = reason
        return self._action(ActionKind.END, starts=True, end_reason=reason)

    def _enter_warm_up(self, phase: SessionPhase, t_s: float | None = None) -> Action:
        self._phase = phase
        self._warm_start = self._t_last if t_s is None else t_s
        if self.config.warmup_s == 0:
            return self._enter_measuring(_WARM_UP_OF[phase])
        return self._action(ActionKind.WARM_UP, starts=True)

    def _enter_measuring(self, phase: SessionPhase) -> Action:
        self._phase = phase
        self._warm_start = None
        if phase is SessionPhase.OPTIMIZATION and not self._opt_begun:
            self._opt_begun = True
            self._t_opt = self._t_last  # None before any breath: set by the first one
            if self._t_opt is not None:
                spent = self._spent(self._t_opt)
                if spent is not None:  # e.g. budget_s already used up before a resume
                    return self._end(spent)
        return self._next_setting()

    def _next_setting(self) -> Action:
        if self._phase is SessionPhase.EXPLORATION and self._n_explored >= self.config.n_explore:
            if self.config.pause_between_bouts:
                self._phase = SessionPhase.BOUT_PAUSE
                return self._action(ActionKind.PAUSE_BETWEEN_BOUTS, starts=True)
            if not self.config.warmup_without_pause:  # walking on: already at a steady state
                return self._enter_measuring(SessionPhase.OPTIMIZATION)
            return self._enter_warm_up(SessionPhase.WARM_UP_OPTIMIZATION)
        self._proposing = True
        return self._action(ActionKind.PROPOSE)


def _check_t(name: str, t: object) -> float:
    if not _is_number(t) or not math.isfinite(float(t)):  # type: ignore[arg-type]
        raise MeasurementError(f"{name}={t!r}; expected a finite breath-clock time in s")
    return float(t)  # type: ignore[arg-type]


def expected_end_s(config: SessionProtocolConfig, *, breath_interval_s: float = DEFAULT_BREATH_INTERVAL_S,
                   bout_pause_s: float = 0.0) -> float:
    """When a session is expected to end, in seconds of walking after its start.

    Exact for ``session_s``; otherwise the warm-ups (one when neither a pause nor
    ``warmup_without_pause`` separates the bouts), the exploration bout at N breaths of
    ``breath_interval_s`` per evaluation (setting changes not counted), ``bout_pause_s`` and the
    optimisation budget (``budget_breaths`` at ``breath_interval_s``), whichever budget ends first.

    Raises:
        ConfigError: ``breath_interval_s`` not positive or ``bout_pause_s`` negative.
    """
    if not (_is_number(breath_interval_s) and math.isfinite(breath_interval_s) and breath_interval_s > 0):
        raise ConfigError(f"breath_interval_s={breath_interval_s!r}; expected a positive number of seconds")
    if not (_is_number(bout_pause_s) and math.isfinite(bout_pause_s) and bout_pause_s >= 0):
        raise ConfigError(f"bout_pause_s={bout_pause_s!r}; expected a number of seconds >= 0")
    c = config
    warm_ups = 2 if (c.pause_between_bouts or c.warmup_without_pause) else 1
    t_opt = warm_ups * c.warmup_s + c.n_explore * c.max_breaths * breath_interval_s + (
        bout_pause_s if c.pause_between_bouts else 0.0)
    ends = [] if c.session_s is None else [c.session_s]
    if c.budget_s is not None:
        ends.append(t_opt + c.budget_s)
    if c.budget_breaths is not None:
        ends.append(t_opt + c.budget_breaths * breath_interval_s)
    return min(ends)


def drive(
    protocol: SessionProtocol,
    optimizer: HILOptimizer,
    next_breath: Callable[[], tuple[float, float]],
    apply_setting: Callable[[Mapping[str, float] | None, float], None],
    *,
    on_propose: Callable[[dict[str, float]], None] | None = None,
    on_measure: Callable[[BreathStep, float, float], None] | None = None,
    on_evaluation: Callable[[Evaluation, float, float], None] | None = None,
) -> None:
    """Run a whole session synchronously: the loop of the simulations and benchmarks.

    Nobody waits between the bouts (a pause between them is resumed at once), setting changes
    are instantaneous (a proposal is applied at the breath that asked for it) and every breath
    after it is measured.

    Args:
        protocol: A new protocol with a start time (``t_start_s``).
        optimizer: Its optimizer, without a budget of its own (the protocol ends the session).
        next_breath: The next breath ``(t_s, watts)``.
        apply_setting: Apply ``(params, t_s)``; ``params`` None = assistance off.
        on_propose: Called with each new setting before it is applied.
        on_measure: Called with each measured breath's ``(step, t_setting_s, watts)``.
        on_evaluation: Called with each completed evaluation and its ``(t_start_s, t_end_s)``.

    Raises:
        ProtocolStateError: ``protocol`` has no start time or has started already.
    """
    now = protocol.t_s
    if now is None:
        raise ProtocolStateError("drive() needs a protocol with t_start_s")
    act = protocol.start()
    t_applied = now
    while act.kind is not ActionKind.END:
        if act.kind is ActionKind.PAUSE_BETWEEN_BOUTS:
            apply_setting(None, now)
            act = protocol.on_resume()
            continue
        if act.kind is ActionKind.WARM_UP and act.starts:
            apply_setting(None, now)
        elif act.kind is ActionKind.PROPOSE:
            if protocol.confirm_due:
                optimizer.begin_confirmation()
            params = optimizer.ask()
            if on_propose is not None:
                on_propose(params)
            apply_setting(params, now)
            protocol.on_setting_applied(now)
            t_applied = now
        now, watts = next_breath()
        act = protocol.on_breath(now)
        if act.kind is not ActionKind.MEASURE or act.t_setting_s is None:
            continue
        step = optimizer.observe_breath(act.t_setting_s, watts)
        if on_measure is not None:
            on_measure(step, act.t_setting_s, watts)
        ev = step.evaluation if step.stop else None
        if ev is None and act.final:
            ev = optimizer.close_current()
            if ev is None:  # an exploration evaluation cut short: dropped
                act = protocol.on_setting_dropped()
                continue
        if ev is not None:
            if on_evaluation is not None:
                on_evaluation(ev, t_applied, now)
            act = protocol.on_evaluation_done()
    optimizer.cancel_current()  # a setting proposed but not measured when the session ended
