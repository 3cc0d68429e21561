"""Rebuild the optimizer of a crashed session from its log (shared/DESIGN.md).

The rule: **no completed evaluation is lost or counted twice.**

1. Start from the last ``/optimizer_state`` snapshot (a full ``HILOptimizer.to_json()``; the
   session logs one at the start and after every completed evaluation).
2. Replay, in file order, what the session did to the optimizer after that snapshot: every
   ``/proposals`` message is an ``ask()`` (preceded by ``cancel_current()`` when a setting was
   still open: the session re-asks after abandoning one), every ``/estimator`` message is one
   breath fed with the very ``t_setting_s`` and ``watts`` the session used. The optimizer is
   deterministic given its state (Kim et al. 2019 Algorithm 1 as implemented by HILOptimizer: one
   seeded generator, serialised with the state), so the replay reproduces the session's calls
   exactly: an evaluation that completed after the snapshot (the snapshot message itself was cut
   off) is completed again, with the same estimate. Breaths already inside the snapshot are
   recognised by (evaluation index, breath index) and skipped, so none is counted twice.
3. Check the result against the log: every ``/observations`` message (a completed evaluation)
   must be in the rebuilt optimizer with the same setting and estimate, and every replayed
   proposal must equal the logged one; otherwise :class:`ResumeError` (e.g. the session used a
   different estimator than ``estimator_factory``).
4. An evaluation cut off by the crash is **discarded** by default (:attr:`ResumePolicy.DISCARD`):
   the optimizer goes back to its state just before that setting's ``ask()``, so the resumed
   session's first ``ask()`` proposes the *same* setting again and it is measured from scratch.
   Why not continue it: after a crash the wearer has walked for an unknown time with assistance
   off or on the old profile, so the metabolic transient the UKF models (Kim et al. 2019 §II.C,
   m_t = c(1−e^{−t/τ}) + c0·e^{−t/τ0}, t = time since the setting began) no longer starts where
   the logged breaths left it, and the breath clock of the new process does not continue the old
   one. Re-measuring costs a few minutes; mixing two transients biases the estimate the GP is
   told. :attr:`ResumePolicy.RESUME` keeps the replayed breaths for a caller that re-applies the
   same setting immediately (e.g. a brief logging restart with the device untouched).

If the log holds no snapshot but names a previous log (a resumed session that crashed before its
first snapshot reached the disk), the previous log is rebuilt first and this log's events are
replayed on top.
"""

from __future__ import annotations

import enum
import logging
import math
import os
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from bridge.log import LogError, Topic
from bridge.log import records as rec
from bridge.log.reader import LogContents, LogMessage, read_log
from hilbo_core.errors import HilboError
from hilbo_core.metabolic import Estimator
from hilbo_core.optimizer import HILOptimizer

__all__ = ["RESUME_TOPICS", "ResumeError", "ResumeInfo", "ResumePolicy", "rebuild_optimizer"]

logger = logging.getLogger(__name__)

RESUME_TOPICS = (Topic.CONFIG, Topic.OPTIMIZER_STATE, Topic.PROPOSALS, Topic.ESTIMATOR,
                 Topic.OBSERVATIONS, Topic.BREATHS)
"""The topics :func:`rebuild_optimizer` reads (pass contents read with at least these)."""
_MAX_CHAIN = 32
_REL_TOL = 1e-9


class ResumeError(LogError, ValueError):
    """The log cannot be turned back into the optimizer it came from (names what is missing)."""


class ResumePolicy(enum.Enum):
    """What happens to an evaluation the crash cut off (see the module docstring)."""

    DISCARD = "discard"
    RESUME = "resume"


@dataclass(frozen=True)
class ResumeInfo:
    """What :func:`rebuild_optimizer` recovered.

    Attributes:
        log_path: The log that was read (pass it as ``previous_log`` of the new log).
        session_id: The session's id (the new log keeps it).
        previous_log: The log *that* log had resumed, if any (the chain).
        config: The session config stored in its ``/config``.
        truncated: The log was cut off (crash); ``unreadable_bytes`` were lost.
        unreadable_bytes: Bytes of torn tail.
        n_evaluations: Completed evaluations in the rebuilt optimizer.
        n_from_snapshot: Of those, how many the snapshot held.
        n_replayed: Of those, how many were completed again by replaying breaths.
        snapshot_reason: The ``reason`` of the snapshot used.
        discarded_params: The setting cut off by the crash and discarded, or None.
        discarded_breaths: Its breaths (not counted anywhere).
        in_progress_params: With RESUME, the setting whose breaths were kept, or None.
        last_breath_t_s: Cart time of the last logged breath, or None.
        observations: The logged ``/observations`` records of the recovered evaluations (in
            this log), with their session times, in index order.
        warnings: Anything odd that did not prevent the rebuild.
    """

    log_path: str
    session_id: str | None
    previous_log: str | None
    config: Mapping[str, Any] | None
    truncated: bool
    unreadable_bytes: int
    n_evaluations: int
    n_from_snapshot: int
    n_replayed: int
    snapshot_reason: str
    discarded_params: dict[str, float] | None
    discarded_breaths: int
    in_progress_params: dict[str, float] | None
    last_breath_t_s: float | None
    observations: tuple[rec.Evaluation, ...]
    warnings: tuple[str, ...]


def rebuild_optimizer(
    source: LogContents | str | os.PathLike[str],
    *,
    estimator_factory: Callable[[], Estimator] | None = None,
    policy: ResumePolicy = ResumePolicy.DISCARD,
) -> tuple[HILOptimizer, ResumeInfo]:
    """Rebuild a session's optimizer from its (possibly crash-truncated) log.

    Args:
        source: The log path, or its :func:`bridge.log.reader.read_log` contents (decoded with
            at least :data:`RESUME_TOPICS`).
        estimator_factory: The estimator the session used (default: HILOptimizer's UKF).
        policy: What to do with an evaluation cut off by the crash.

    Returns:
        ``(optimizer, info)``: the optimizer ready for ``ask()`` (or, with RESUME, for the next
        breath of the setting in progress), and what was recovered.

    Raises:
        ResumeError: No snapshot to start from, or the log and the replay disagree.
        LogFormatError: The file is not a hilbo session log.
    """
    try:
        policy = ResumePolicy(policy)
    except ValueError as err:
        raise ResumeError(f"policy={policy!r}; expected one of {[p.value for p in ResumePolicy]}") from err
    contents = source if isinstance(source, LogContents) else read_log(source, topics=RESUME_TOPICS)
    warnings: list[str] = []
    opt, tail, n_snap, reason = _starting_point(contents, estimator_factory, warnings, depth=0)
    replay = _Replay(opt, estimator_factory, contents.path, _damage(contents))
    for msg in tail:
        replay.apply(msg)
    opt = replay.opt
    discarded: dict[str, float] | None = None
    discarded_breaths = 0
    in_progress: dict[str, float] | None = None
    if opt.current_params is not None:
        if policy is ResumePolicy.DISCARD:
            discarded, discarded_breaths = opt.current_params, replay.cur_breaths
            if replay.pre_ask_state is not None:
                # Back to just before the ask: the next ask() proposes this setting again.
                opt = HILOptimizer.from_json(replay.pre_ask_state, estimator_factory=estimator_factory)
            else:
                # The snapshot itself was taken mid-evaluation: no earlier state to return to.
                opt.cancel_current()
            logger.info("%s: discarded the evaluation cut off by the crash (%d breaths of %s)",
                        contents.path, discarded_breaths, discarded)
        else:
            in_progress = opt.current_params
    observations = _check_observations(contents, opt, warnings)
    breaths = contents.records(Topic.BREATHS)
    info = ResumeInfo(
        log_path=contents.path, session_id=contents.session_id, previous_log=contents.previous_log,
        config=contents.config, truncated=contents.truncated, unreadable_bytes=contents.unreadable_bytes,
        n_evaluations=len(opt.evaluations), n_from_snapshot=n_snap, n_replayed=replay.n_completed,
        snapshot_reason=reason, discarded_params=discarded, discarded_breaths=discarded_breaths,
        in_progress_params=in_progress,
        last_breath_t_s=breaths[-1].t_s if breaths else None,
        observations=observations, warnings=tuple(warnings + replay.warnings),
    )
    return opt, info


# ---------------------------------------------------------------------------------- internals
def _mid_evaluation_end(record: object) -> bool:
    return (isinstance(record, rec.OptimizerState) and record.reason == "end"
            and record.state.get("current") is not None)


def _starting_point(
    contents: LogContents, estimator_factory: Callable[[], Estimator] | None, warnings: list[str],
    depth: int,
) -> tuple[HILOptimizer, Sequence[LogMessage], int, str]:
    """The optimizer at the last snapshot and the messages after it."""
    messages = contents.messages
    # A session's "end" snapshot taken in the middle of an evaluation is skipped: resuming from
    # the snapshot before it and replaying the breaths after it restores the state before that
    # evaluation's ask (its proposal is made again, as after a crash).
    last = max((i for i, m in enumerate(messages) if m.topic == Topic.OPTIMIZER_STATE
                and not _mid_evaluation_end(m.record)), default=None)
    if last is not None:
        snap = messages[last].record
        if not isinstance(snap, rec.OptimizerState):
            raise ResumeError(f"{contents.path}: the optimizer snapshot (message {messages[last].sequence}) "
                              f"is not a valid {Topic.OPTIMIZER_STATE} record{_damage(contents)}")
        try:
            opt = HILOptimizer.from_json(snap.state, estimator_factory=estimator_factory)
        except (KeyError, TypeError, HilboError) as err:
            raise ResumeError(f"{contents.path}: the optimizer snapshot (message {messages[last].sequence}) "
                              f"cannot be loaded: {err}") from err
        return opt, messages[last + 1:], len(opt.evaluations), snap.reason or ""
    previous = contents.previous_log
    if previous is None or depth >= _MAX_CHAIN:
        cut = f"; the file is cut off ({contents.stop_reason})" if contents.truncated else ""
        raise ResumeError(
            f"{contents.path}: no {Topic.OPTIMIZER_STATE} snapshot in the log ({len(messages)} messages "
            f"read{cut}{_damage(contents)}); a session writes one when it starts, so this log cannot be "
            "resumed: start a new session without --resume"
        )
    prev_path = _resolve(previous, Path(contents.path).parent)
    warnings.append(f"{contents.path} has no snapshot; rebuilt from the previous log {prev_path} first")
    prev = read_log(prev_path, topics=RESUME_TOPICS)
    opt, tail, n_snap, reason = _starting_point(prev, estimator_factory, warnings, depth + 1)
    replay = _Replay(opt, estimator_factory, prev.path, _damage(prev))
    for msg in tail:
        replay.apply(msg)
    warnings.extend(replay.warnings)
    if replay.opt.current_params is not None:
        # The previous process crashed mid-evaluation and this one started over: so do we.
        if replay.pre_ask_state is None:
            replay.opt.cancel_current()
        else:
            replay.opt = HILOptimizer.from_json(replay.pre_ask_state, estimator_factory=estimator_factory)
    return replay.opt, messages, n_snap + replay.n_completed, reason


def _resolve(previous: str, here: Path) -> Path:
    p = Path(previous)
    if p.is_absolute() or p.exists():
        return p
    return here / p


class _Replay:
    """Re-executes the logged ask()/breath calls on an optimizer."""

    def __init__(self, opt: HILOptimizer, estimator_factory: Callable[[], Estimator] | None,
                 path: str, damage: str = "") -> None:
        self.opt = opt
        self.path = path
        self.damage = damage
        self.estimator_factory = estimator_factory
        state_cur = opt.to_json()["current"] if opt.current_params is not None else None
        self.cur_breaths = 0 if state_cur is None else len(state_cur["breaths"])
        self.pre_ask_state: dict[str, Any] | None = None
        self.n_completed = 0
        self.warnings: list[str] = []

    def apply(self, msg: LogMessage) -> None:
        if msg.topic == Topic.PROPOSALS:
            self._proposal(msg)
        elif msg.topic == Topic.ESTIMATOR:
            self._breath(msg)

    def _record(self, msg: LogMessage, kind: type[Any]) -> Any:
        if not isinstance(msg.record, kind):
            raise ResumeError(f"{self.path}: {msg.topic} message {msg.sequence} is not a valid "
                              f"{kind.__name__} record ({msg.raw[:80]!r})")
        return msg.record

    def _ask(self, msg: LogMessage) -> dict[str, float]:
        self.pre_ask_state = self.opt.to_json()
        try:
            params = self.opt.ask()
        except HilboError as err:
            raise ResumeError(f"{self.path}: replaying {msg.topic} message {msg.sequence}: ask() "
                              f"failed: {err}") from err
        self.cur_breaths = 0
        return params

    def _proposal(self, msg: LogMessage) -> None:
        n = len(self.opt.evaluations)
        proposal = self._record(msg, rec.Proposal)
        k = proposal.index
        if k < n:
            self.warnings.append(f"{msg.topic} message {msg.sequence} for evaluation {k} precedes the "
                                 f"snapshot's {n} evaluations; ignored")
            return
        if k > n:
            raise ResumeError(f"{self.path}: {msg.topic} message {msg.sequence} is for evaluation {k}, but "
                              f"only {n} evaluations exist at that point of the log")
        if self.opt.current_params is not None:
            # A second proposal for the same index: the session abandoned the setting
            # (cancel_current, e.g. a pause) and asked again. Do the same.
            self.opt.cancel_current()
        logged = proposal.params
        gone = self.opt.cancelled_params
        if gone is not None and _same_params(gone, logged):
            # After a pause the session measures the abandoned setting once more
            # (HILOptimizer.ask_again, bridge/runtime.py) instead of asking for a new one.
            self.pre_ask_state = self.opt.to_json()
            params = self.opt.ask_again()
            self.cur_breaths = 0
            if params is None:
                params = self._ask(msg)
        else:
            params = self._ask(msg)
        if not _same_params(params, logged):
            raise ResumeError(
                f"{self.path}: replayed proposal for evaluation {k} is {params}, but the log has {logged} "
                f"(message {msg.sequence}); the optimizer state and the log disagree"
            )

    def _breath(self, msg: LogMessage) -> None:
        n = len(self.opt.evaluations)
        est = self._record(msg, rec.Estimate)
        k, b = est.index, est.breath
        if k < n or (k == n and self.opt.current_params is not None and b < self.cur_breaths):
            return  # already inside the snapshot
        if k > n:
            raise ResumeError(f"{self.path}: {msg.topic} message {msg.sequence} is breath {b} of evaluation "
                              f"{k}, but evaluation {n} has not completed")
        if self.opt.current_params is None:
            # No proposal after the snapshot (its message was lost or never logged): the
            # optimizer's ask() is deterministic, so asking reproduces it.
            self._ask(msg)
            self.warnings.append(f"evaluation {k}: no {Topic.PROPOSALS} message before its breaths; "
                                 "asked the optimizer again")
        if b != self.cur_breaths:
            raise ResumeError(f"{self.path}: evaluation {k} needs breath {self.cur_breaths} next, but the "
                              f"log has breath {b} (message {msg.sequence}); breaths are missing"
                              f"{self.damage}")
        try:
            step = self.opt.observe(est.t_setting_s, est.watts)
        except (TypeError, ValueError, HilboError) as err:
            raise ResumeError(f"{self.path}: cannot replay breath {b} of evaluation {k} "
                              f"(message {msg.sequence}): {err!r}") from err
        self.cur_breaths += 1
        if step.stop:
            self.n_completed += 1
            self.pre_ask_state = None
            self.cur_breaths = 0


def _close(a: float, b: float) -> bool:
    return math.isclose(a, b, rel_tol=_REL_TOL, abs_tol=_REL_TOL)


def _same_params(a: Mapping[str, float], b: Mapping[str, Any]) -> bool:
    if set(a) != set(b):
        return False
    try:
        return all(_close(float(a[k]), float(b[k])) for k in a)
    except (TypeError, ValueError):
        return False


def _damage(contents: LogContents) -> str:
    """``"; the file is damaged: ..."`` when part of it could not be read, else ""."""
    return f"; the file is damaged: {contents.damage_text()}" if contents.damaged else ""


def _check_observations(contents: LogContents, opt: HILOptimizer,
                        warnings: list[str]) -> tuple[rec.Evaluation, ...]:
    """Every logged completed evaluation is in ``opt``, unchanged; returns them by index."""
    evs = opt.evaluations
    seen: dict[int, rec.Evaluation] = {}
    for msg in contents.topic(Topic.OBSERVATIONS):
        d = msg.record
        if not isinstance(d, rec.Evaluation):
            raise ResumeError(f"{contents.path}: {Topic.OBSERVATIONS} message {msg.sequence} is not a valid "
                              f"evaluation record ({msg.raw[:80]!r})")
        k = d.index
        if k >= len(evs):
            raise ResumeError(
                f"{contents.path}: evaluation {k} was logged as completed (message {msg.sequence}) but the "
                f"rebuilt optimizer has only {len(evs)} evaluations: its snapshot and breaths are missing"
                f"{_damage(contents)}"
            )
        ev = evs[k]
        same = (_same_params(ev.params, d.params) and _close(ev.mean, d.mean)
                and _close(ev.var, d.var) and d.breaths == ev.breaths)
        if not same:
            raise ResumeError(
                f"{contents.path}: evaluation {k} in the log (mean {d.mean} W, var {d.var}, "
                f"{d.breaths} breaths) differs from the rebuilt one (mean {ev.mean} W, var {ev.var}, "
                f"{ev.breaths} breaths); was the session run with another estimator?"
            )
        if k in seen:
            # A repeated log message; the optimizer holds the evaluation once either way.
            warnings.append(f"evaluation {k} is logged as completed twice (message {msg.sequence})")
            continue
        seen[k] = d
    return tuple(seen[k] for k in sorted(seen))
