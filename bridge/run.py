"""``hilbo run``: wire a config's devices into a :class:`~bridge.runtime.BridgeSession` and run it.

The same function runs the lab session (real CAN adapter and cart) and ``hilbo sim`` (virtual
devices started by :mod:`bridge.sim.virtual`, reached over the same transports). A session writes
``OUT_DIR/<subject>_<time>.mcap`` and, at the end, ``<same name>.summary.json``; a resumed session
writes a new log linked to the old one.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import datetime as dt
import json
import logging
import os
import sys
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import msgspec
from rich.console import Console

from bridge.config import HilboConfig
from bridge.errors import first_leaf
from bridge.live import LiveServer
from bridge.log import DEFAULT_FILE_MODE, EventLevel, LogError, SessionLog, Topic, new_session_id
from bridge.log.reader import read_log
from bridge.log.resume import ResumeError, ResumeInfo, rebuild_optimizer
from bridge.operator_view import run_operator_view
from bridge.outcome import format_params
from bridge.runtime import BridgeSession, RuntimeSettings
from bridge.validate import ValidationPlan, plan_event
from drivers.cart import BreathStream
from drivers.exosuit import CanEndpoint
from drivers.signals import stop_signal_handlers
from hilbo_core import Evaluation, HILOptimizer, InfeasibleError
from hilbo_core.protocol import SessionProtocol

__all__ = ["RunResult", "continued_by", "finished_session", "keyboard_present", "newest_log",
           "resume_config_warnings", "run_session", "runtime_settings", "write_json_atomic"]

logger = logging.getLogger(__name__)


@dataclass(frozen=True)
class RunResult:
    """Where a session's files went, and its summary."""

    log_path: Path
    summary_path: Path
    summary: dict[str, Any]


def runtime_settings(cfg: HilboConfig, *, auto_resume_s: float | None = None,
                     n_actuators: int = 2, feedback_log_period_s: float = 0.1,
                     operator_present: bool = False) -> RuntimeSettings:
    """The runtime's settings from a validated config."""
    return RuntimeSettings(
        auto_resume_s=cfg.watchdog.auto_resume_s if auto_resume_s is None else auto_resume_s,
        max_auto_resumes=cfg.watchdog.max_auto_resumes,
        operator_present=operator_present,
        device_timeout_s=cfg.watchdog.device_heartbeat_timeout_ms / 1000.0,
        cart_timeout_s=cfg.watchdog.cart_data_timeout_s,
        push_timeout_s=cfg.can.push_timeout_ms / 1000.0,
        push_retries=cfg.can.push_retries,
        pace_s=cfg.can.segment_pace_ms / 1000.0,
        heartbeat_period_s=cfg.can.heartbeat_period_s,
        feedback_log_period_s=feedback_log_period_s,
        n_actuators=n_actuators,
        proposal_worker=cfg.protocol.proposal_worker,
        gc=cfg.protocol.gc,
    )


def keyboard_present(operator_view: bool = True) -> bool:
    """A person can press p, r and q: the live view is wanted and stdin and stderr are terminals
    (the view reads the keys on stdin and draws on stderr). Otherwise the session prints one
    line per evaluation and per pause instead, and only the resume policy ends a pause."""
    return operator_view and sys.stdin.isatty() and sys.stderr.isatty()


def _headless_line(session: BridgeSession) -> Callable[[str], None]:
    """A printer of the session's event lines on stderr, with the session's breath time and
    state, for runs without the live view."""
    console = Console(stderr=True, markup=False, highlight=False, soft_wrap=True)

    def line(text: str) -> None:
        st = session.status
        # The state without its causes ("paused", not the whole pause reason on every line):
        # the pause's own line says why.
        state = st.state.split(":", 1)[0]
        console.print(f"[{st.breath_time_s / 60:6.1f} min | {state}] {text}")
    return line


def write_json_atomic(path: Path, data: Any, *, mode: int = DEFAULT_FILE_MODE) -> None:
    """Write JSON so a reader never sees half a file (temporary file, then rename).

    The file gets permission bits ``mode`` (default 0o600: a summary holds health data).
    """
    tmp = path.with_suffix(path.suffix + ".tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, mode)
    with os.fdopen(fd, "w") as f:
        os.fchmod(f.fileno(), mode)
        f.write(json.dumps(data, indent=2) + "\n")
    os.replace(tmp, path)


def _log_path(cfg: HilboConfig, out_dir: Path | None) -> Path:
    directory = Path(out_dir) if out_dir is not None else Path(cfg.session.out_dir)
    directory.mkdir(parents=True, exist_ok=True)
    stamp = dt.datetime.now().strftime("%Y%m%d-%H%M%S")
    path = directory / f"{cfg.session.subject}_{stamp}.mcap"
    n = 1
    while path.exists():
        n += 1
        path = directory / f"{cfg.session.subject}_{stamp}_{n}.mcap"
    return path


def _walked_lower_bound(evaluations: Sequence[Evaluation], warmup_s: float) -> float:
    """What a crashed session walked, as far as its log's evaluations show (s, a lower bound):
    their breath time, and the warm-up of each bout that has one (pauses, setting changes and
    an unfinished setting are not known). It counts against ``[protocol] session_min``."""
    walked = sum(e.duration_s for e in evaluations)
    bouts = {e.phase for e in evaluations}
    return float(walked + warmup_s * len(bouts))


def _walked_before_resume(log: Path, events: Sequence[Any], evaluations: Sequence[Evaluation],
                          warmup_s: float) -> float:
    """What the session of ``log`` walked before this resume (s), counted against
    ``[protocol] session_min``.

    A run that ended (an operator's stop, a signal, the cart's end) logged its walking time at
    its ``session_end``: that, exactly. A run cut off by a crash did not; it walked what it was
    given when it started (its ``session_start``'s ``walked_before_s``, 0 for a first run) plus
    the span of its own breaths on the cart's clock, which counts the pauses and setting changes
    that :func:`_walked_lower_bound` cannot see (a person in the suit walked through them). The
    lower bound stays a floor for logs written before ``walked_before_s`` was logged.
    """
    floor = _walked_lower_bound(evaluations, warmup_s)
    end = next((e for e in reversed(events) if getattr(e, "kind", None) == "session_end"), None)
    walking = (getattr(end, "details", None) or {}).get("walking") if end is not None else None
    if isinstance(walking, dict) and isinstance(walking.get("session_s"), int | float):
        return max(float(walking["session_s"]), 0.0)
    start = next((e for e in reversed(events) if getattr(e, "kind", None) == "session_start"), None)
    before = (getattr(start, "details", None) or {}).get("walked_before_s") if start is not None else None
    if not isinstance(before, int | float):
        return floor
    breaths = read_log(log, topics=[Topic.BREATHS]).records(Topic.BREATHS)
    span = max(b.t_s for b in breaths) - min(b.t_s for b in breaths) if breaths else 0.0
    return max(floor, float(before) + span)


def _sdk_lines_to(log: SessionLog, loop: asyncio.AbstractEventLoop) -> Callable[[str, int], None]:
    """The live view's SDK log lines as the session log's ``live_view`` events (called from the
    SDK's thread: handed to the loop, which owns the log)."""
    def write(text: str, level: int) -> None:
        if not log.closed:
            log.log_event("live_view", f"live view: {text}",
                          level=EventLevel.ERROR if level >= logging.ERROR else EventLevel.WARNING)

    def forward(text: str, level: int) -> None:
        with contextlib.suppress(RuntimeError):  # the loop has closed: the session is over
            loop.call_soon_threadsafe(write, text, level)
    return forward


def finished_session(path: Path) -> str | None:
    """Why the session of the log at ``path`` is over for good, or None when it can go on.

    A session whose walking time or budget was spent (the protocol's end: the log's
    ``budget_spent`` event) has nothing left to resume; one stopped by the operator, a signal,
    the cart's end, the resume budget or a crash has.
    """
    return _budget_spent(read_log(path, topics=["/events"]).records("/events"))


def _budget_spent(events: Sequence[Any]) -> str | None:
    """The message of the ``budget_spent`` event among a log's events, or None."""
    return next((e.message for e in events if getattr(e, "kind", None) == "budget_spent"), None)


def _log_stem(path: str | Path) -> str:
    """A log's file name without ``.mcap`` and without the ``.recovered`` of ``hilbo log recover``."""
    name = Path(path).name.removesuffix(".mcap")
    return name.removesuffix(".recovered")


def continued_by(resume: Path, directories: Iterable[Path]) -> Path | None:
    """A log in ``directories`` that already continues the session of ``resume`` from it (same
    session id, its ``previous_log`` naming ``resume`` or the copy ``hilbo log recover`` made of
    it), or None.

    Resuming such a log again would fork one session into two branches; the newer log holds
    everything and is the one to resume. Unreadable files are passed over.
    """
    info = read_log(resume, topics=["/config"])
    sid, stem = info.session_id, _log_stem(resume)
    if sid is None:
        return None
    seen: set[Path] = set()
    for d in directories:
        for p in sorted(Path(d).glob("*.mcap")):
            rp = p.resolve()
            if rp in seen or _log_stem(p) == stem:  # resume itself, or its recovered copy
                continue
            seen.add(rp)
            try:
                other = read_log(p, topics=["/config"])
            except LogError:
                continue
            prev = other.previous_log
            if other.session_id == sid and prev is not None and _log_stem(prev) == stem:
                return p
    return None


def newest_log(path: Path, directories: Iterable[Path]) -> Path | None:
    """The newest log of the session ``path`` belongs to, following :func:`continued_by` from
    log to log, or None when no log continues ``path``."""
    dirs = {Path(d) for d in directories}
    newest: Path | None = None
    seen = {path.resolve()}
    later = continued_by(path, dirs)
    while later is not None and later.resolve() not in seen:  # a copied log could loop
        newest = later
        seen.add(later.resolve())
        later = continued_by(later, dirs | {later.parent})
    return newest


def _bounds(lower: float, upper: float) -> str:
    return f"[{lower:g}, {upper:g}]"


def resume_config_warnings(cfg: HilboConfig, opt: HILOptimizer, info: ResumeInfo) -> list[str]:
    """Check that ``cfg`` can continue the session rebuilt from a log: refuse what the safety gate
    would refuse later, and return what is allowed but probably a mistake.

    The rebuilt optimizer keeps the space its session ran with and proposes in it, while the
    gate admits only ``cfg``'s space: a narrower one would refuse the session's own proposals
    mid-session.

    Args:
        cfg: The config of the resumed run.
        opt: The optimizer rebuilt from the log (its space is the session's).
        info: What the rebuild read (the log's recorded config).

    Returns:
        One line per warning: another subject, or a parameter's bounds wider than the session's
        (the session keeps its own).

    Raises:
        ResumeError: The parameter names or the profile builder differ, a parameter's bounds in
            the log's session are not inside ``cfg``'s, or a completed evaluation's setting is
            outside ``cfg``'s space (its constraints).
    """
    old, new = opt.space, cfg.space.space
    where = info.log_path
    if set(old.names) != set(new.names):
        raise ResumeError(f"space: the session of {where} optimised {', '.join(old.names)}; this config "
                          f"has {', '.join(new.names)}; resume with the session's [space]")
    if old.name != new.name:
        raise ResumeError(f"space: the session of {where} built its profiles with {old.name!r}; this "
                          f"config with {new.name!r}; resume with the session's [space]")
    refused: list[str] = []
    warnings: list[str] = []
    by_name = {p.name: (i, p) for i, p in enumerate(new.parameters)}
    for p in old.parameters:
        i, q = by_name[p.name]
        key = f"space.bounds.{p.name}" if cfg.space.preset is not None else f"space.parameters[{i}]"
        if p.lower < q.lower or p.upper > q.upper:
            refused.append(f"{key}: the log's session used {_bounds(p.lower, p.upper)}, this config "
                           f"has {_bounds(q.lower, q.upper)}")
        elif (p.lower, p.upper) != (q.lower, q.upper):
            warnings.append(f"{key}: this config has {_bounds(q.lower, q.upper)}, the log's session "
                            f"used {_bounds(p.lower, p.upper)}; the resumed session keeps searching "
                            f"{_bounds(p.lower, p.upper)}")
    if refused:
        raise ResumeError(f"{where}: this config's [space] does not hold the session's: "
                          + "; ".join(refused) + ". Resume with the session's bounds")
    for k, e in enumerate(opt.evaluations):
        try:
            new.check(e.params)
        except InfeasibleError as err:
            raise ResumeError(f"{where}: evaluation {k} ({format_params(e.params, new.units)}) is "
                              f"outside this config's space: {err}; resume with the session's "
                              "[space]") from err
    session = (info.config or {}).get("session")
    subject = session.get("subject") if isinstance(session, Mapping) else None
    if subject is not None and subject != cfg.session.subject:
        warnings.append(f"session.subject: the log's session is subject {subject!r}, this config has "
                        f"{cfg.session.subject!r}; the new log continues that session under "
                        f"{cfg.session.subject!r}'s name")
    return warnings


async def run_session(
    cfg: HilboConfig,
    *,
    resume: Path | None = None,
    out_dir: Path | None = None,
    log_path: Path | None = None,
    auto_resume_s: float | None = None,
    operator_view: bool = True,
    n_actuators: int = 2,
    on_session: Callable[[BridgeSession], None] | None = None,
    validation: ValidationPlan | None = None,
) -> RunResult:
    """Run one session from a config to its end.

    Args:
        cfg: The validated config.
        resume: A previous session's log (possibly cut off by a crash) to continue.
        out_dir: Overrides ``[session] out_dir``.
        log_path: Exact log path (else ``OUT_DIR/<subject>_<time>.mcap``).
        auto_resume_s: The resume policy (``[watchdog] auto_resume_s``, which this overrides):
            end a pause the operator did not ask for after this long of a healthy device and
            cart (wall s; simulations, and ``hilbo run --auto-resume`` without a keyboard).
        operator_view: Show the live terminal view when stdin and stderr are terminals (it
            reads the keys there); otherwise, or when False, one line per evaluation and per
            pause on stderr.
        n_actuators: Actuators whose heartbeat the watchdog requires.
        on_session: Called with the session before it runs (tests, simulation wiring).
        validation: Measure this validation walk (``hilbo validate``, bridge/validate.py)
            instead of optimising: its optimizer, protocol and gate; ``resume`` is then unused
            (the plan was built from the log it continues).

    Returns:
        Paths of the log and summary, and the summary.

    Raises:
        ResumeError: ``resume`` cannot be continued, before anything is written: a validation
            walk's log, a finished session, a log a later one already continues, or a config whose
            parameter space does not hold the session's (:func:`resume_config_warnings`).
    """
    if auto_resume_s is not None and auto_resume_s != cfg.watchdog.auto_resume_s:
        # The log records the config the session ran with: --auto-resume overrides the file's.
        watchdog = msgspec.structs.replace(cfg.watchdog, auto_resume_s=auto_resume_s)
        cfg = dataclasses.replace(cfg, watchdog=watchdog)
    space = cfg.space.space
    previous: str | None = None
    resume_warnings: list[str] = []
    if validation is not None:
        opt, protocol = validation.optimizer, validation.protocol
        session_id, previous = new_session_id(), None if resume is None else str(resume)
    elif resume is not None:
        events = read_log(resume, topics=["/events"]).records("/events")
        walk = plan_event(events)
        if walk is not None:
            # Its optimizer only measured fixed conditions: "resuming" it would start an
            # exploration in a session that was never an optimisation.
            validated = (walk.details or {}).get("source_log")
            raise ResumeError(f"{resume} is a validation walk's log (hilbo validate); continue it with "
                              f"hilbo validate CONFIG --resume {resume}, or resume the optimisation "
                              "session's newest log"
                              + (f" (this walk validated {validated})" if validated else ""))
        done = _budget_spent(events)
        if done is not None:
            raise ResumeError(f"{resume} is a finished session ({done}); there is nothing to resume. "
                              "Start a new session, or measure its recommendation with "
                              f"hilbo validate CONFIG --from {resume}")
        directories = {resume.parent, Path(out_dir or cfg.session.out_dir)}
        later = continued_by(resume, directories)
        if later is not None:
            raise ResumeError(f"{resume} was already continued by {later}; resuming it again would fork "
                              f"the session. Resume the newest log of the session: hilbo run CONFIG "
                              f"--resume {newest_log(later, directories) or later}")
        opt, info = rebuild_optimizer(resume)
        resume_warnings = resume_config_warnings(cfg, opt, info)
        for text in resume_warnings:
            logger.warning("resuming %s: %s", resume, text)
        session_id, previous = info.session_id, str(resume)
        # What the crashed session walked of its optimisation bout is known as the measured
        # breath time of its evaluations (the log's optimizer state), a lower bound; the
        # session's walking time from the log's own account (_walked_before_resume).
        used = opt.budget_used
        protocol = SessionProtocol.resumed(
            cfg.protocol.session_protocol_config(),
            n_explored=min(len(opt.evaluations), cfg.protocol.explore_points),
            session_used_s=_walked_before_resume(resume, events, opt.evaluations,
                                                 cfg.protocol.warmup_s),
            optimization_used_s=float(used["seconds"]), optimization_used_breaths=int(used["breaths"]))
        logger.info("resuming %s: %d evaluations recovered", resume, info.n_evaluations)
        if cfg.prior.priors:
            logger.info("[prior] not re-applied on resume: the rebuilt optimizer holds its own priors")
    else:
        # Fast prior (Antonova 2016 §3.3): validated and inflated when the config was loaded.
        # The protocol ends the session on walking time; the optimizer keeps no budget.
        opt = HILOptimizer(space, config=cfg.protocol.optimizer_config(with_budget=False),
                           prior_observations=cfg.prior.priors)
        protocol = SessionProtocol(cfg.protocol.session_protocol_config())
        session_id = new_session_id()
    path = Path(log_path) if log_path is not None else _log_path(cfg, out_dir)
    summary_path = path.with_suffix(".summary.json")
    # A person can press r only where the operator view reads the keyboard (bridge/operator_view.py).
    operator_present = keyboard_present(operator_view)
    settings = runtime_settings(cfg, auto_resume_s=auto_resume_s, n_actuators=n_actuators,
                                operator_present=operator_present)
    loop = asyncio.get_running_loop()
    stream = BreathStream.from_config(cfg.cart)
    live = LiveServer(host=cfg.live.host, port=cfg.live.port) if cfg.live.enabled else None
    # Ctrl-C and SIGTERM stop the session from before its log exists: a stop that comes before
    # the session is made is handed to it then, so no signal falls in a window where it is lost
    # (or ignored, when the caller ignores SIGINT).
    session: BridgeSession | None = None
    stop_early = False

    def stop() -> None:
        nonlocal stop_early
        if session is not None:
            session.interrupt()
        else:
            stop_early = True

    with stop_signal_handlers(loop, stop):
        async with CanEndpoint(cfg.can.bus) as endpoint, stream:
            # Before anything is logged or sent: a bus that another session's bridge already
            # drives is refused (two bridges would push conflicting profiles to one person).
            await endpoint.check_no_other_bridge()
            with live or contextlib.nullcontext(), \
                    SessionLog(path, session_id=session_id, config_json=cfg.to_json(),
                               previous_log=previous, param_names=space.names,
                               file_mode=cfg.session.file_mode_bits, live=live) as log:
                if resume is not None:
                    log.log_optimizer_state(opt, reason="resume")
                    for text in resume_warnings:
                        log.log_event("resume_config", f"resuming {resume}: {text}",
                                      level=EventLevel.WARNING)
                elif cfg.prior.priors:
                    log.log_event("prior", cfg.prior.describe(), **cfg.prior.event_details())
                gate: Any = cfg.make_gate()
                if validation is not None:
                    gate = validation.gate(gate, lambda: session)  # type: ignore[arg-type,return-value]
                session = BridgeSession(opt, gate, endpoint, stream, log, settings, protocol=protocol)
                if validation is not None:
                    validation.attach(session)
                session.status.budget_s = protocol.config.budget_s
                if stop_early:
                    session.interrupt()
                if live is not None:
                    session.status.event(f"live view: {live.url or 'off, ' + str(live.start_error)}")
                    live.on_sdk_log = _sdk_lines_to(log, loop)
                if on_session is not None:
                    on_session(session)
                # The live view needs a terminal to draw on and a keyboard to read: without
                # either (--no-view, output to a file, stdin not a terminal) the session prints
                # one line per evaluation and per pause, resume or refusal instead, so that a
                # run without a terminal is never silent (docs/config.md, "Pauses").
                view = asyncio.create_task(run_operator_view(session), name="operator-view") \
                    if operator_present else None
                if not operator_present:
                    session.status.listeners.append(_headless_line(session))
                failure: Exception | None = None
                try:
                    summary = await session.run()
                    if validation is not None:
                        summary["validation"] = validation.results(session)
                        validation.label_summary(summary)
                except Exception as err:  # recorded, then raised again below
                    # A session that has started writes its summary whatever ends it (the
                    # evaluations it completed are the lab's data); the error goes on up.
                    failure = err
                    leaf = first_leaf(err)
                    text = str(leaf) or type(leaf).__name__
                    log.log_event("session_error", f"the session failed: {text}")
                    summary = session.summary()
                    summary["error"] = text
                finally:
                    if view is not None:
                        view.cancel()
                        with contextlib.suppress(asyncio.CancelledError):
                            await view
    summary.update(session_id=session_id, log=str(path), previous_log=previous,
                   config_source=str(cfg.source))
    write_json_atomic(summary_path, summary, mode=cfg.session.file_mode_bits)
    if failure is not None:
        raise failure
    return RunResult(path, summary_path, summary)
