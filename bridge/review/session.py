"""``hilbo review``: plots, a report and CSV tables of a session, from its MCAP log(s).

``hilbo review LOG.mcap [LOG2.mcap ...] [--out DIR]``
    Reads one session: one log, or the files of a session resumed after a crash (the old log
    and the one ``hilbo run --resume`` wrote; any order: the ``previous_log`` link orders them).
    Two logs given that hold the same stretch of the session (a log and the copy ``hilbo log
    recover`` made of it) are reviewed once: the fuller one, with a warning naming the one left
    out. A log that resumes one not given (the first and third of three) is noted in the report.
    A log cut off by a crash is read up to its last intact record (:func:`bridge.log.reader.read_log`).
    Writes into DIR (default ``<log dir>/<log stem>-review/``):

    * ``timeline.png``: breath-by-breath metabolic power (W) with the session's estimate of
      each setting (labelled by the estimator it used) and its ±1 σ band on one continuous time
      axis, setting changes and pauses marked (Kim et al. 2019 Fig. 1), and the estimate's σ below;
    * ``best_so_far.png``: best estimated cost so far (W) against minutes walked;
    * ``parameters.png``: each parameter against evaluation number, early stops marked;
    * ``thresholds.png``: the threshold schedule the session used (Algorithm 2's A, floored
      by the sound rule when it was the rule) over breath index with the
      standardised exploration traces X it is the envelope of (Kim et al. 2019 Algorithm 2) and the
      z of the optimisation evaluations (skipped when exploration did not complete);
    * ``force_tracking.png``: desired vs measured force over the gait cycle while the
      recommended setting was measured, or the measured setting nearest to a recommendation
      never applied (Kim et al. 2019 Fig. 4; skipped without ``/force_feedback``);
    * ``report.md`` and ``report.html`` (self-contained, images inlined): configuration,
      recommended setting, evaluations, events and faults, rejected records/frames by reason;
    * ``evaluations.csv`` (one row per evaluation) and ``breaths.csv`` (one row per breath).

``hilbo review --compare A.mcap B.mcap [--out DIR]``
    Two sessions side by side: ``compare.png`` (best so far against minutes, evaluation counts)
    and ``compare.md``/``compare.html`` (default DIR ``<A's dir>/compare-<A stem>-vs-<B stem>/``).

Times. Every breath-tied time is the *session time*: seconds since the file's first breath on
the cart's clock (what ``t_start``/``t_end`` of ``/observations`` and ``summary.json`` use). The
files of a resumed session are laid end to end (the new process's cart clock does not continue
the old one). Messages without a breath time (events, acks, device status) are placed at the
last breath logged before them.

The recommended setting is what the session itself recommends: ``HILOptimizer.best()`` (by the
optimizer's ``recommend``: with the default sound rule the lowest GP posterior mean + 1 SD over
the whole feasible set, or the confirmation's own measurement of it once the session's last
minutes measured it; with the seed's rules the GP's estimated minimum among the evaluated
settings, with that evaluation's estimate) of the last ``/optimizer_state`` snapshot, or of the
optimizer rebuilt by :func:`bridge.log.resume.rebuild_optimizer` when evaluations completed after
that snapshot; failing both, the lowest estimated mean.

A log damaged *inside* the file (garbage over a chunk, a bad CRC: not the cut-off tail a crash
leaves) is read around the damage (:mod:`bridge.log.reader` restarts at the next intact record);
the review is written, its events and notes say which byte ranges were skipped, ``hilbo review``
prints a warning naming them on stderr and exits with status 1, so a script notices. A log only
cut off at its end by a crash is reviewed up to the cut with status 0.

Bad input (a missing file, not MCAP, empty, another program's MCAP, a hilbo log with nothing
in it, files of different sessions) raises a :class:`~bridge.errors.BridgeError` whose one-line
message names the file and what was expected; ``hilbo`` turns it into exit status 1.
"""

from __future__ import annotations

import dataclasses
import itertools
import logging
import math
import os
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import msgspec
import numpy as np

from bridge.errors import ReviewError
from bridge.log import EventLevel, LogError, LogFormatError, Topic
from bridge.log import records as rec
from bridge.log.reader import LogContents, config_file_mode, read_log
from bridge.outcome import recommendation_method_text

__all__ = [
    "Breath",
    "CompareResult",
    "EstimateTrace",
    "EvaluationRow",
    "FeedbackData",
    "LogFile",
    "Recommendation",
    "ReviewResult",
    "Session",
    "ThresholdData",
    "TimelineEvent",
    "ZTrace",
    "load_session",
]

logger = logging.getLogger(__name__)


# ---------------------------------------------------------------------------------- data
@dataclass(frozen=True)
class LogFile:
    """One file of the session.

    Attributes:
        path: The file as given.
        session_id: Its session id.
        previous_log: The log it resumes (as stored), or None.
        complete: Closed normally (False: cut off by a crash).
        size_bytes: File size.
        unreadable_bytes: Bytes after the last intact record.
        stop_reason: Why reading stopped early ("" when complete).
        damage: Byte ranges damaged inside the file and skipped ("" when none).
        messages: Messages read.
        offset_s: Where its first breath lies on the merged session-time axis, s.
        duration_s: First to last breath, s.
    """

    path: str
    session_id: str | None
    previous_log: str | None
    complete: bool
    size_bytes: int
    unreadable_bytes: int
    stop_reason: str
    messages: int
    offset_s: float
    duration_s: float
    damage: str = ""

    @property
    def name(self) -> str:
        """The file name."""
        return Path(self.path).name


@dataclass(frozen=True)
class Breath:
    """One ``/breaths`` record, joined with the estimate it produced (if it was fed to the optimizer).

    Attributes:
        file: Index of its file in :attr:`Session.files`.
        t_s: Breath time on the cart's clock, s.
        time_s: Session time, s.
        vo2_ml_min, vco2_ml_min, ve_l_min, rer, hr_bpm: As the cart reported them (None if absent).
        watts: Metabolic power by Brockway's equation, W.
        evaluation: Index of the evaluation it was fed to, or None (warm-up, pause).
        breath: 0-based breath index within that evaluation, or None.
        mean_w: The estimate after it, W, or None.
        sd_w: Its standard deviation, W, or None.
    """

    file: int
    t_s: float
    time_s: float
    vo2_ml_min: float | None
    vco2_ml_min: float | None
    ve_l_min: float | None
    rer: float | None
    hr_bpm: float | None
    watts: float | None
    evaluation: int | None
    breath: int | None
    mean_w: float | None
    sd_w: float | None


@dataclass(frozen=True)
class EstimateTrace:
    """The estimator's output over one measured setting (one run of ``/estimator`` messages).

    Attributes:
        index: Evaluation index.
        file: Its file.
        phase: exploration or optimization.
        t_start_s: Session time when the setting was applied, s.
        time_s: Session time of each breath, s.
        watts: Power fed to the optimizer per breath, W.
        mean_w: Estimate after each breath, W.
        sd_w: Its standard deviation, W.
        completed: The run ended with a completed evaluation (False: abandoned or cut off).
    """

    index: int
    file: int
    phase: str
    t_start_s: float
    time_s: tuple[float, ...]
    watts: tuple[float, ...]
    mean_w: tuple[float, ...]
    sd_w: tuple[float, ...]
    completed: bool


@dataclass(frozen=True)
class EvaluationRow:
    """A completed evaluation.

    Attributes:
        index: 0-based evaluation number.
        params: The setting.
        mean_w: Estimated steady-state cost, W.
        var_w2: Its variance, W².
        breaths: Breaths measured.
        duration_s: Breath time from the setting's start to its last breath, s.
        phase: exploration or optimization.
        stopped_early: Stopped by the σ-scaled rule.
        reason: threshold, decided (the sound rule's accept stop), max_measurements, budget or told.
        t_start_s: Session time when the setting was applied, s (None if unknown).
        t_end_s: Session time of its last breath, s (None if unknown).
        file: Index of the file it completed in.
        source: ``observation`` (logged on ``/observations``) or ``snapshot`` (only in an
            ``/optimizer_state`` snapshot: completed by the resume's replay).
    """

    index: int
    params: Mapping[str, float]
    mean_w: float
    var_w2: float
    breaths: int
    duration_s: float
    phase: str
    stopped_early: bool
    reason: str
    t_start_s: float | None
    t_end_s: float | None
    file: int
    source: str = "observation"

    @property
    def sd_w(self) -> float:
        """Standard deviation of the estimate, W."""
        return math.sqrt(self.var_w2) if self.var_w2 >= 0 else math.nan


@dataclass(frozen=True)
class TimelineEvent:
    """An event, fault, nack or log condition, placed on the session-time axis.

    Attributes:
        time_s: Session time, s.
        file: Its file.
        level: info, warning, error...
        kind: Machine-readable kind (the ``/events`` kind, ``fault``, ``nack``, ``log_cut_off``...).
        message: Human-readable text.
    """

    time_s: float
    file: int
    level: str
    kind: str
    message: str


@dataclass(frozen=True)
class Recommendation:
    """The recommended setting.

    Attributes:
        params: The setting.
        mean_w: Its estimated cost, W.
        var_w2: The estimate's variance, W².
        index: The evaluation it comes from, or None.
        method: How it was obtained (for the report).
    """

    params: Mapping[str, float]
    mean_w: float
    var_w2: float
    index: int | None
    method: str

    @property
    def sd_w(self) -> float:
        """Standard deviation, W."""
        return math.sqrt(self.var_w2) if self.var_w2 >= 0 else math.nan


@dataclass(frozen=True)
class ZTrace:
    """The stopping rule's standardised distance z over one optimisation evaluation.

    Attributes:
        index: Evaluation index.
        breath: 0-based breath indices.
        z: (μ − μ*)/σ after each breath.
        stopped_early: The evaluation was stopped by the threshold.
    """

    index: int
    breath: tuple[int, ...]
    z: tuple[float, ...]
    stopped_early: bool


@dataclass(frozen=True)
class ThresholdData:
    """Algorithm 2's threshold schedule and what it was computed from.

    Attributes:
        thresholds: A over breath index (N,).
        traces: Standardised exploration traces X (n_explore, N),
            ``X_ij = (M_ij − M_iN)/sqrt(S_ij + S_iN)``.
        source: Where they came from (for the report).
        z_traces: The optimisation evaluations' z.
    """

    thresholds: np.ndarray
    traces: np.ndarray
    source: str
    z_traces: tuple[ZTrace, ...]


@dataclass(frozen=True)
class FeedbackData:
    """Force feedback recorded while one setting was measured.

    Attributes:
        index: The evaluation.
        version: Profile version on the bus.
        samples: ``{actuator: (gait_phase_pct, desired_n, measured_n)}`` arrays of the samples
            with a known gait phase whose desired force is the table sent (N).
        tables: ``{actuator: (joint, gait_pct, force_n)}``: the transmitted table per actuator.
        nearest: The recommended setting was never applied; this is the measured setting nearest
            to it.
    """

    index: int
    version: int
    samples: Mapping[int, tuple[np.ndarray, np.ndarray, np.ndarray]]
    tables: Mapping[int, tuple[str, np.ndarray, np.ndarray]]
    nearest: bool = False

    @property
    def n_samples(self) -> int:
        """Samples over all actuators."""
        return sum(len(s[0]) for s in self.samples.values())


@dataclass(frozen=True)
class Session:
    """Everything the review shows, read from the session's log file(s).

    Attributes:
        files: The files, in session order.
        session_id: The session id.
        config: The session config stored in ``/config`` of the first file.
        param_names: The optimised parameters.
        param_units: Their units.
        param_bounds: Their (lower, upper) bounds.
        breaths: Every breath.
        traces: Every measured setting's estimate trace (abandoned ones included).
        evaluations: Completed evaluations by index, each once.
        events: Events, faults and nacks in time order.
        rejects: ``{source: {reason: count}}`` summed over the files.
        thresholds: The threshold schedule, or None.
        recommended: The recommended setting, or None without evaluations.
        feedback: Force feedback of the recommended setting, or None.
        notes: Why something is missing or odd (for the report).
        optimizer_config: The optimizer's config (``OptimizerConfig.to_json`` of the last
            snapshot): its estimator, stopping rule and threshold floor.
        pauses: (start, end) session times (s) of each pause; end None when the log ends paused.
        walked_s: The session's own minutes walked (its end event's ``walking``), s; None when
            the log does not say (then the last breath's session time stands in).
        validation: A validation walk's result per condition (``hilbo validate``), or None.
        validation_plan: A validation walk's conditions in measuring order (``name``, ``kind``,
            ``params``; evaluation k measured condition k), or None for an optimisation session;
            a walk has no ``recommended`` setting.
        warnings: What ``hilbo review`` also says on stderr (each is in ``notes`` too): a log
            left out because another log given holds the same part of the session.
    """

    files: tuple[LogFile, ...]
    session_id: str | None
    config: Mapping[str, Any]
    param_names: tuple[str, ...]
    param_units: Mapping[str, str]
    param_bounds: Mapping[str, tuple[float, float]]
    breaths: tuple[Breath, ...]
    traces: tuple[EstimateTrace, ...]
    evaluations: tuple[EvaluationRow, ...]
    events: tuple[TimelineEvent, ...]
    rejects: Mapping[str, Mapping[str, int]]
    thresholds: ThresholdData | None
    recommended: Recommendation | None
    feedback: FeedbackData | None
    notes: tuple[str, ...]
    optimizer_config: Mapping[str, Any] = dataclasses.field(default_factory=dict)
    pauses: tuple[tuple[float, float | None], ...] = ()
    walked_s: float | None = None
    validation: tuple[Mapping[str, Any], ...] | None = None
    validation_plan: tuple[Mapping[str, Any], ...] | None = None
    warnings: tuple[str, ...] = ()

    def condition_of(self, index: int) -> Mapping[str, Any] | None:
        """The validation condition evaluation ``index`` measured, or None (not a walk)."""
        plan = self.validation_plan
        return plan[index] if plan is not None and 0 <= index < len(plan) else None

    @property
    def file_mode(self) -> int:
        """Permission bits of the review's files: the session's ``[session] file_mode`` (0o600
        unless the config says otherwise), since they hold the same health data as its log."""
        return config_file_mode(self.config)

    @property
    def minutes_walked(self) -> float:
        """Minutes walked as the session counted them (the summary's ``walking.session_s``);
        for a log that does not say, the session time of the last breath."""
        if self.walked_s is not None:
            return self.walked_s / 60.0
        return (self.breaths[-1].time_s / 60.0) if self.breaths else 0.0

    @property
    def estimator_label(self) -> str:
        """The estimator's name as the review labels it (the session's, not always the seed's UKF)."""
        kind = self.optimizer_config.get("estimator", "transition")
        return _ESTIMATOR_LABELS.get(str(kind), f"{kind} estimate")

    @property
    def threshold_floor(self) -> float | None:
        """The floor the sound stopping rule put under Algorithm 2's thresholds (σ), or None
        when the session's rule used the raw thresholds."""
        if str(self.optimizer_config.get("stopping", "sound")) not in ("sound", "sound-floor"):
            return None
        floor = _f(self.optimizer_config.get("a_floor"))
        return 1.0 if floor is None else floor

    @property
    def boundary_s(self) -> float | None:
        """Seconds in a setting before which the sound rule's thresholds were higher than the
        floored schedule (its sequential boundary, ``stopping = "sound"`` from log format 5), or
        None (the fixed-clock rules, and every log before format 5)."""
        if str(self.optimizer_config.get("stopping", "sound")) != "sound":
            return None
        return _f(self.optimizer_config.get("boundary_s"))

    @property
    def n_early_stops(self) -> int:
        """Evaluations stopped early."""
        return sum(e.stopped_early for e in self.evaluations)

    @property
    def resume_times_s(self) -> tuple[float, ...]:
        """Session times where a resumed file begins, s."""
        return tuple(f.offset_s for f in self.files[1:])

    @property
    def label(self) -> str:
        """A short name: the subject from the config and the first file's name."""
        sess = self.config.get("session") if isinstance(self.config.get("session"), Mapping) else {}
        subject = sess.get("subject") if isinstance(sess, Mapping) else None
        name = self.files[0].name
        return f"{subject} ({name})" if subject else name

    def best_so_far(self) -> list[tuple[float, float]]:
        """(minutes walked at the evaluation's end, best estimated mean so far in W) per evaluation."""
        out: list[tuple[float, float]] = []
        best = math.inf
        for e in self.evaluations:
            best = min(best, e.mean_w)
            t = e.t_end_s if e.t_end_s is not None else (out[-1][0] * 60.0 if out else 0.0)
            out.append((t / 60.0, best))
        return out


#: The review's name of each estimator (hilbo_core.estimation.EstimatorKind values).
_ESTIMATOR_LABELS = {
    "transition": "transition estimate (Bayesian first-order fit)",
    "seed_ukf": "UKF estimate (Kim et al. 2019 §II.C)",
}


def _pauses(events: Sequence[TimelineEvent]) -> tuple[tuple[float, float | None], ...]:
    """(start, end) of each pause: from a ``pause`` event to the next ``resume`` (or a resumed
    file's start, or the end of the log)."""
    out: list[tuple[float, float | None]] = []
    start: float | None = None
    for e in events:
        if e.kind == "pause" and start is None:
            start = e.time_s
        elif e.kind in ("resume", "resumed") and start is not None:
            out.append((start, e.time_s))
            start = None
    if start is not None:
        out.append((start, None))
    return tuple(out)


@dataclass(frozen=True)
class ReviewResult:
    """What :func:`review_session` wrote.

    Attributes:
        out_dir: The output directory.
        files: Every file written, in order.
        session: The data shown.
        skipped: ``{plot name: why}`` for plots not drawn.
    """

    out_dir: Path
    files: tuple[Path, ...]
    session: Session
    skipped: Mapping[str, str]


@dataclass(frozen=True)
class CompareResult:
    """What :func:`compare_sessions` wrote.

    Attributes:
        out_dir: The output directory.
        files: Every file written.
        sessions: The two sessions.
    """

    out_dir: Path
    files: tuple[Path, ...]
    sessions: tuple[Session, Session]


# ---------------------------------------------------------------------------------- loading
def _read(path: str | os.PathLike[str]) -> LogContents:
    p = Path(path)
    if not p.exists():
        raise ReviewError(f"{str(p)!r}: no such file; expected a hilbo session log (.mcap) such as "
                          "runs/sim/session.mcap")
    if p.is_dir():
        raise ReviewError(f"{str(p)!r} is a directory; expected a hilbo session log (.mcap) file")
    try:
        return read_log(p)
    except LogFormatError as err:
        text = str(err)
        if "expected" not in text:
            text += "; expected a hilbo session log (written by hilbo run or hilbo sim)"
        raise ReviewError(text) from err


def _has_data(c: LogContents) -> bool:
    if c.topic(Topic.BREATHS) or c.topic(Topic.ESTIMATOR) or c.topic(Topic.OBSERVATIONS):
        return True
    # A resumed session's file that crashed before its first breath still knows the old evaluations.
    return any(_snapshot_evaluations(s) for s in c.records(Topic.OPTIMIZER_STATE))


def _snapshot_evaluations(snap: rec.OptimizerState | None) -> list[rec.Evaluation]:
    """The completed evaluations inside an optimizer snapshot, as typed records."""
    if snap is None:
        return []
    try:
        return msgspec.convert(snap.state.get("evaluations") or [], list[rec.Evaluation])
    except msgspec.ValidationError:
        return []


def _same_file(a: str | Path, b: str | Path, base: Path) -> bool:
    pa, pb = Path(a), Path(b)
    if not pa.is_absolute() and not pa.exists():
        pa = base / pa
    try:
        return pa.exists() and pb.exists() and os.path.samefile(pa, pb)
    except OSError:
        return False


def _is_log(link: str, c: LogContents, base: Path) -> bool:
    """Whether a ``previous_log`` link (relative to ``base``) names ``c``, or the log that
    ``c`` is the ``hilbo log recover`` copy of (its ``hilbo.recovered`` source, or its name
    ``NAME.recovered.mcap``: the link was written before the copy was made)."""
    if _same_file(link, c.path, base):
        return True
    source = c.metadata.get("hilbo.recovered", {}).get("source")
    if source and _same_file(link, source, base):
        return True
    return Path(c.path).name == Path(link).name.removesuffix(".mcap") + ".recovered.mcap"


def _overlap(a: LogContents, b: LogContents) -> bool:
    """Whether two logs of one session hold the same stretch of it: their log times overlap.

    A log resumed with ``hilbo run --resume`` starts after the log it resumes ended, so two logs
    of a session overlap only when one is a copy of the other (``hilbo log recover``'s)."""
    ra, rb = a.time_range_ns, b.time_range_ns
    return (a.session_id == b.session_id and ra is not None and rb is not None
            and ra[0] <= rb[1] and rb[0] <= ra[1])


def _fuller(a: LogContents, b: LogContents) -> bool:
    """Whether ``a`` is the one to review of two copies: more breaths, more messages, closed
    normally, the recovered copy (in that order)."""
    def rank(c: LogContents) -> tuple[int, int, bool, bool]:
        return (len(c.topic(Topic.BREATHS)), len(c.messages), c.complete, "hilbo.recovered" in c.metadata)
    return rank(a) > rank(b)


def _drop_copies(contents: list[LogContents]) -> tuple[list[LogContents], list[str]]:
    """One of each set of logs that hold the same stretch of the session (a log and its
    recovered copy given together), and a warning naming each file left out.

    Reviewing both counted every breath and minute of that stretch twice.
    """
    kept: list[LogContents] = []
    warnings: list[str] = []
    for c in contents:
        twin = next((k for k in kept if _overlap(k, c)), None)
        if twin is None:
            kept.append(c)
            continue
        keep, drop = (c, twin) if _fuller(c, twin) else (twin, c)
        kept[kept.index(twin)] = keep
        warnings.append(f"{drop.path} and {keep.path} hold the same part of session {keep.session_id} "
                        f"(their log times overlap: one is a copy of the other, such as hilbo log "
                        f"recover writes); reviewed {keep.path} ({len(keep.topic(Topic.BREATHS))} breaths), "
                        f"left out {drop.path} ({len(drop.topic(Topic.BREATHS))} breaths)")
    return kept, warnings


def _order(contents: list[LogContents]) -> tuple[list[LogContents], list[str]]:
    """The files of one session in session order (by their ``previous_log`` links), and a
    warning for each file left out as a copy of another (:func:`_drop_copies`)."""
    ids = {c.session_id for c in contents if c.session_id}
    if len(ids) > 1:
        described = ", ".join(f"{c.path} is {c.session_id}" for c in contents)
        raise ReviewError(f"these logs belong to different sessions ({described}); expected the files of one "
                          "session (a log and its resumed continuation), or use --compare A.mcap B.mcap")
    seen: set[tuple[int, int]] = set()
    for c in contents:
        st = os.stat(c.path)
        key = (st.st_dev, st.st_ino)
        if key in seen:
            raise ReviewError(f"{c.path}: given twice; expected each file of the session once")
        seen.add(key)
    contents, warnings = _drop_copies(contents)
    if len(contents) == 1:
        return contents, warnings

    def parent(c: LogContents) -> LogContents | None:
        prev = c.previous_log
        if not prev:
            return None
        return next((o for o in contents if o is not c and _is_log(prev, o, Path(c.path).parent)), None)

    parents = {id(c): parent(c) for c in contents}
    roots = [c for c in contents if parents[id(c)] is None]
    if len(roots) != 1:
        return contents, warnings  # links absent or ambiguous: keep the order given
    ordered = [roots[0]]
    while len(ordered) < len(contents):
        nxt = [c for c in contents if parents[id(c)] is ordered[-1]]
        if len(nxt) != 1:
            return contents, warnings
        ordered.append(nxt[0])
    return ordered, warnings


def _f(value: Any) -> float | None:
    if isinstance(value, bool) or not isinstance(value, int | float):
        return None
    v = float(value)
    return v if math.isfinite(v) else None


def _i(value: Any) -> int | None:
    return value if isinstance(value, int) and not isinstance(value, bool) else None


@dataclass
class _Run:
    index: int
    phase: str
    t_start_s: float
    time_s: list[float]
    watts: list[float]
    mean_w: list[float]
    sd_w: list[float]

    def trace(self, file: int, completed: bool) -> EstimateTrace:
        return EstimateTrace(self.index, file, self.phase, self.t_start_s, tuple(self.time_s),
                             tuple(self.watts), tuple(self.mean_w), tuple(self.sd_w), completed)


@dataclass(frozen=True)
class _Observed:
    """A logged completed evaluation with its session times (s; None if unknown)."""

    pos: int
    record: rec.Evaluation
    t_start_s: float | None
    t_end_s: float | None


@dataclass
class _FileScan:
    """What one file contributes (filled by :func:`_scan_file`)."""

    breaths: list[Breath]
    traces: list[EstimateTrace]
    orphan_runs: list[EstimateTrace]
    observations: list[_Observed]
    events: list[TimelineEvent]
    rejects: dict[str, dict[str, int]]
    z_runs: dict[int, list[tuple[int, float, bool, str]]]
    profiles: list[tuple[int, rec.ProfileSent]]
    feedback: list[tuple[int, rec.ForceFeedback]]
    snapshots: list[rec.OptimizerState]
    end_s: float
    #: The session's own walked time (s) as its end event states it, or None (older logs).
    walked_s: float | None = None
    #: A validation walk's per-condition results (its ``validation_result`` event), or None.
    validation: list[Mapping[str, Any]] | None = None
    #: A validation walk's conditions in measuring order (its ``validation_plan`` event), or None.
    validation_plan: list[Mapping[str, Any]] | None = None


def _scan_file(c: LogContents, fi: int, offset: float) -> _FileScan:
    msgs = [m for m in c.messages if m.record is not None]
    first_t = next((m.record.t_s for m in msgs if m.topic == Topic.BREATHS and _f(m.record.t_s) is not None),
                   None)
    if first_t is None:
        first_t = next((m.record.t_s for m in msgs if m.topic == Topic.ESTIMATOR
                        and _f(m.record.t_s) is not None), 0.0)
    t0 = float(first_t if first_t is not None else 0.0)

    def session_time(t_s: float | None, default: float) -> float:
        t = _f(t_s)
        return default if t is None else offset + t - t0

    estimates_by_t: dict[float, rec.Estimate] = {}
    for m in msgs:
        if m.topic == Topic.ESTIMATOR and _f(m.record.t_s) is not None:
            estimates_by_t[float(m.record.t_s)] = m.record
    scan = _FileScan([], [], [], [], [], {}, {}, [], [], [], offset)
    runs: dict[int, _Run] = {}
    last = offset
    fault_state: dict[int, int] = {}
    # Format 2 logs carry the device's faults as /events; older ones only in /device_status.
    faults_as_events = any(m.topic == Topic.EVENTS and m.record.kind == "device_fault" for m in msgs)
    z_open: dict[int, list[tuple[int, float, bool, str]]] = {}
    for pos, m in enumerate(msgs):
        r = m.record
        topic = m.topic
        if topic == Topic.BREATHS:
            t = _f(r.t_s)
            if t is None:
                continue
            last = session_time(t, last)
            est = estimates_by_t.get(t)
            scan.breaths.append(Breath(
                fi, t, last, _f(r.vo2_ml_min), _f(r.vco2_ml_min), _f(r.ve_l_min), _f(r.rer), _f(r.hr_bpm),
                _f(r.watts), None if est is None else est.index, None if est is None else est.breath,
                None if est is None else _f(est.mean_w), None if est is None else _sd(est)))
        elif topic == Topic.ESTIMATOR:
            k, b, mean = r.index, r.breath, _f(r.mean_w)
            if mean is None:
                continue
            t = session_time(r.t_s, last)
            run = runs.get(k)
            if run is not None and (b == 0 or b != len(run.time_s)):
                # A new run of the same index: the old one was abandoned (pause, cancel, crash).
                scan.orphan_runs.append(run.trace(fi, completed=False))
                run = None
            if run is None:
                t_set = _f(r.t_setting_s) or 0.0
                run = runs[k] = _Run(k, r.phase or "", t - t_set, [], [], [], [])
            run.time_s.append(t)
            run.watts.append(_f(r.watts) or math.nan)
            run.mean_w.append(mean)
            run.sd_w.append(_sd(r) or math.nan)
        elif topic == Topic.STOPPING:
            k, b, z = r.index, r.breath, _f(r.z)
            if z is None:
                continue
            zr = z_open.get(k)
            if zr is None or b == 0 or (zr and b != zr[-1][0] + 1):
                zr = z_open[k] = []
            zr.append((b, z, r.stop, r.reason))
        elif topic == Topic.OBSERVATIONS:
            k = r.index
            run = runs.pop(k, None)
            trace = run.trace(fi, completed=True) if run is not None else None
            if trace is not None:
                scan.traces.append(trace)
            if k in z_open:
                scan.z_runs[k] = z_open.pop(k)
            if trace is not None and trace.time_s:
                obs = _Observed(pos, r, trace.t_start_s, trace.time_s[-1])
            else:
                # Only the logged times: session times of this file.
                ts, te = _f(r.t_start), _f(r.t_end)
                obs = _Observed(pos, r, None if ts is None else offset + ts,
                                None if te is None else offset + te)
            scan.observations.append(obs)
        elif topic == Topic.PROPOSALS:
            if r.index in runs:
                scan.orphan_runs.append(runs.pop(r.index).trace(fi, completed=False))
        elif topic == Topic.EVENTS:
            walking = (r.details or {}).get("walking") if r.kind == "session_end" else None
            if isinstance(walking, Mapping) and _f(walking.get("session_s")) is not None:
                scan.walked_s = float(walking["session_s"])
            if r.kind == "validation_result" and isinstance((r.details or {}).get("conditions"), list):
                scan.validation = [c for c in r.details["conditions"] if isinstance(c, Mapping)]
            if r.kind == "validation_plan" and isinstance((r.details or {}).get("conditions"), list):
                scan.validation_plan = [c for c in r.details["conditions"] if isinstance(c, Mapping)]
            scan.events.append(TimelineEvent(session_time(r.t_s, last), fi, _level_name(r.level), r.kind,
                                             r.message))
        elif topic == Topic.ACKS:
            if not r.accepted:
                why = r.error or r.reason or "nack"
                scan.events.append(TimelineEvent(last, fi, "warning", "nack",
                                                 f"profile version {r.version} not accepted: {why}"))
        elif topic == Topic.DEVICE_STATUS:
            act, faults = r.actuator, r.faults
            if faults != fault_state.get(act, 0) and not faults_as_events:
                what = ", ".join(r.fault_names or []) or hex(faults)
                text = (f"actuator {act}: faults {what} (mode {r.mode})" if faults
                        else f"actuator {act}: faults cleared")
                scan.events.append(TimelineEvent(last, fi, "error" if faults else "info",
                                                 "fault" if faults else "fault_cleared", text))
            fault_state[act] = faults
        elif topic == Topic.REJECTS:
            scan.rejects[r.source] = dict(r.counts)
        elif topic == Topic.OPTIMIZER_STATE:
            scan.snapshots.append(r)
        elif topic == Topic.PROFILES_SENT:
            scan.profiles.append((pos, r))
        elif topic == Topic.FORCE_FEEDBACK:
            scan.feedback.append((pos, r))
    scan.orphan_runs.extend(r.trace(fi, completed=False) for r in runs.values())
    scan.end_s = max(last, max((b.time_s for b in scan.breaths), default=offset))
    return scan


def _level_name(level: int) -> str:
    try:
        return EventLevel(level).name.lower()
    except ValueError:
        return "unknown"


def _sd(e: rec.Estimate) -> float | None:
    sd = _f(e.sd_w)
    if sd is None:
        var = _f(e.var_w2)
        sd = math.sqrt(var) if var is not None and var >= 0 else None
    return sd


def _space_info(snapshot: rec.OptimizerState | None, contents: LogContents
                ) -> tuple[tuple[str, ...], dict[str, str], dict[str, tuple[float, float]]]:
    # The parameter space is the optimizer's own JSON (ParameterSpace.to_json), or the config's.
    space: Any = snapshot.state.get("space") if snapshot is not None else None
    if not isinstance(space, Mapping):
        cfg_space = (contents.config or {}).get("space")
        space = cfg_space.get("definition") if isinstance(cfg_space, Mapping) else None
    names: list[str] = []
    units: dict[str, str] = {}
    bounds: dict[str, tuple[float, float]] = {}
    if isinstance(space, Mapping):
        for p in space.get("parameters") or []:
            if isinstance(p, Mapping) and "name" in p:
                n = str(p["name"])
                names.append(n)
                units[n] = str(p.get("unit", ""))
                lo, hi = _f(p.get("lower")), _f(p.get("upper"))
                if lo is not None and hi is not None:
                    bounds[n] = (lo, hi)
    if not names:
        cfg = c_cfg[0] if (c_cfg := contents.records(Topic.CONFIG)) else None
        names = list(cfg.param_names) if cfg is not None else []
    return tuple(names), units, bounds


def load_session(paths: Sequence[str | os.PathLike[str]]) -> Session:
    """Read the log file(s) of one session and gather what the review shows.

    Args:
        paths: One log, or the files of a session resumed after a crash (any order).

    Returns:
        The merged session: evaluations of the old file then the new, each once.

    Raises:
        ReviewError: A missing file, not an MCAP file, an empty file, another program's MCAP, a
            log without breaths or evaluations, or files of different sessions.
        LogError: A file that cannot be read.
    """
    if not paths:
        raise ReviewError("no log given; expected at least one hilbo session log (.mcap)")
    contents, warnings = _order([_read(p) for p in paths])
    if not any(_has_data(c) for c in contents):
        c = contents[0]
        raise ReviewError(f"{c.path}: a hilbo session log without breaths or evaluations ({len(c.messages)} "
                          "messages); expected a session that walked at least one breath")
    notes: list[str] = list(warnings)
    files: list[LogFile] = []
    scans: list[_FileScan] = []
    offset = 0.0
    for fi, c in enumerate(contents):
        scan = _scan_file(c, fi, offset)
        first = scan.breaths[0].time_s if scan.breaths else offset
        files.append(LogFile(c.path, c.session_id, c.previous_log, c.complete, c.size_bytes,
                             c.unreadable_bytes, c.stop_reason, len(c.messages), offset, scan.end_s - first,
                             c.damage_text()))
        scans.append(scan)
        if not c.complete:
            scan.events.append(TimelineEvent(
                scan.end_s, fi, "error", "log_cut_off",
                f"{Path(c.path).name} ends here: cut off, {c.unreadable_bytes:,} bytes unreadable "
                f"({c.stop_reason})"))
        if c.damaged:
            # Damage inside the file (not a crash's cut-off tail): say where, and that what lies
            # after it was read.
            text = (f"{Path(c.path).name} is damaged inside: {c.damage_text()}; the messages after the "
                    "damage were read, those inside it are lost")
            scan.events.append(TimelineEvent(offset, fi, "error", "log_damaged", text))
            notes.append(text)
        if fi > 0:
            scan.events.insert(0, TimelineEvent(offset, fi, "info", "resumed",
                                                f"session resumed in {Path(c.path).name}"))
        if c.undecodable:
            notes.append(f"{c.path}: {c.undecodable} messages could not be decoded and were skipped")
        offset = scan.end_s
    _check_breaths(contents, scans, notes)
    if contents[0].previous_log:
        notes.append(f"{contents[0].path} resumes {contents[0].previous_log}, which was not given: its "
                     "evaluations are counted (from the optimizer snapshot) but its breaths are not shown; "
                     "pass both files to review the whole session")
    for before, c in itertools.pairwise(contents):
        # A chain with a log missing in the middle (the first and the third of three): the same
        # note, for the part between the two given logs.
        if c.previous_log and not _is_log(c.previous_log, before, Path(c.path).parent):
            notes.append(f"{c.path} resumes {c.previous_log}, which was not given: the part of the session "
                         f"between {before.path} and it is missing (its evaluations are counted from the "
                         "optimizer snapshot, its breaths are not shown); pass every log of the session "
                         "to review all of it")

    # Evaluations: the old file's, then the new file's, each index once.
    evals: dict[int, EvaluationRow] = {}
    obs_pos: dict[int, tuple[int, int]] = {}
    for fi, scan in enumerate(scans):
        for obs in scan.observations:
            k = obs.record.index
            row = _eval_row(obs.record, fi, obs.t_start_s, obs.t_end_s, "observation")
            if k in evals:
                if not math.isclose(evals[k].mean_w, row.mean_w, rel_tol=1e-9):
                    notes.append(f"evaluation {k} is logged twice with different estimates "
                                 f"({evals[k].mean_w:.1f} W and {row.mean_w:.1f} W); the first is shown")
                continue
            evals[k] = row
            obs_pos[k] = (fi, obs.pos)
    snapshot, snap_file = None, None
    for fi in reversed(range(len(scans))):
        if scans[fi].snapshots:
            snapshot, snap_file = scans[fi].snapshots[-1], fi
            break
    # Evaluations only the optimizer knows (completed by a resume's replay, /observations lost).
    orphans = [t for s in scans for t in s.orphan_runs]
    for ev in _snapshot_evaluations(snapshot):
        k = ev.index
        if k in evals:
            continue
        match = next((t for t in reversed(orphans) if t.index == k and len(t.time_s) == ev.breaths), None)
        fi = match.file if match is not None else (snap_file or 0)
        evals[k] = _eval_row(ev, fi, match.t_start_s if match else None,
                             match.time_s[-1] if match else None, "snapshot")
        if match is not None:
            orphans.remove(match)
            scans[match.file].traces.append(dataclasses.replace(match, completed=True))
    evaluations = tuple(evals[k] for k in sorted(evals))
    if [e.index for e in evaluations] != list(range(len(evaluations))):
        missing = sorted(set(range(max(evals) + 1)) - set(evals)) if evals else []
        notes.append(f"evaluations {missing} are not in the log(s) (cut off, or in a file not given)")
    traces = sorted([t for s in scans for t in s.traces] + orphans, key=lambda t: t.t_start_s)
    n_abandoned = len(orphans)
    if n_abandoned:
        notes.append(f"{n_abandoned} measured setting(s) did not complete (paused, rejected or cut off by a "
                     "crash); their breaths are shown in grey and they are not in the evaluations")

    first = contents[0]
    names, units, bounds = _space_info(snapshot, first)
    config = first.config or {}
    breaths = tuple(b for s in scans for b in s.breaths)
    events = tuple(sorted((e for s in scans for e in s.events), key=lambda e: (e.time_s, e.file)))
    rejects: dict[str, dict[str, int]] = {}
    for s in scans:  # cumulative counters per process: the last message of each file, summed
        for source, counts in s.rejects.items():
            acc = rejects.setdefault(source, {})
            for reason, n in counts.items():
                acc[reason] = acc.get(reason, 0) + n
    z_traces = {k: v for s in scans for k, v in s.z_runs.items()}
    thresholds = _thresholds(scans, traces, evaluations, config, snapshot, z_traces, notes)
    plan = next((s.validation_plan for s in reversed(scans) if s.validation_plan is not None), None)
    if plan is None:
        recommended = _recommend(contents, snapshot, evaluations, notes)
    else:
        # A validation walk measures fixed conditions (its unassisted one with no setting
        # applied): a GP over them recommends nothing; OPT is its source session's recommendation.
        recommended = None
    feedback = None
    if recommended is not None:
        # Every logged evaluation of the recommended setting (a confirmation measures it several
        # times), latest first, until one has force feedback; a recommendation over the whole
        # feasible set may be a setting never applied (the GP's minimum moved after the last
        # one): then the measured setting nearest to it, said as such.
        own = [e.index for e in reversed(evaluations)
               if e.index in obs_pos and _same_params(e.params, recommended.params)]
        tried: list[str] = []
        for index in own:
            fi, pos = obs_pos[index]
            feedback = _feedback(scans[fi], index, pos, tried)
            if feedback is not None:
                break
        if feedback is None and not own:
            shown = _nearest_evaluation(evaluations, recommended.params, bounds, set(obs_pos))
            if shown is not None:
                notes.append(f"force tracking: the recommended setting was not measured itself; the plot "
                             f"shows evaluation {shown + 1}, the measured setting nearest to it")
                fi, pos = obs_pos[shown]
                feedback = _feedback(scans[fi], shown, pos, tried)
                if feedback is not None:
                    feedback = dataclasses.replace(feedback, nearest=True)
        if feedback is None:
            notes.extend(tried[-1:] or ["no force feedback plot: no evaluation on /observations to show"])
        else:
            notes.extend(n for n in tried if n.startswith("force tracking:"))
    opt_config = snapshot.state.get("config") if snapshot is not None else None
    return Session(
        files=tuple(files), session_id=first.session_id, config=config, param_names=names,
        param_units=units, param_bounds=bounds, breaths=breaths, traces=tuple(traces),
        evaluations=evaluations, events=events, rejects=rejects, thresholds=thresholds,
        recommended=recommended, feedback=feedback, notes=tuple(notes),
        optimizer_config=opt_config if isinstance(opt_config, Mapping) else {},
        pauses=_pauses(events), walked_s=scans[-1].walked_s,
        validation=next((tuple(s.validation) for s in reversed(scans) if s.validation is not None), None),
        validation_plan=None if plan is None else tuple(plan),
        warnings=tuple(warnings),
    )


def _check_breaths(contents: Sequence[LogContents], scans: Sequence[_FileScan], notes: list[str]) -> None:
    """Say how many logged breaths cannot be shown; refuse a session where that is all of them.

    A breath whose time, VO2 or VCO2 is NaN or infinite (a cart or parser fault) is not a
    measurement: a review of only such breaths would report "0 breaths" as if nothing had been
    walked, so it is an error naming the file and the count instead.

    Raises:
        ReviewError: Breaths were logged, none is finite, and no evaluation was completed.
    """
    logged = sum(len(c.topic(Topic.BREATHS)) for c in contents)
    shown = sum(len(s.breaths) for s in scans)
    if logged == shown:
        return
    has_evaluations = any(s.observations for s in scans) or any(
        _snapshot_evaluations(r) for c in contents for r in c.records(Topic.OPTIMIZER_STATE))
    if shown == 0 and not has_evaluations:
        raise ReviewError(f"{', '.join(c.path for c in contents)}: all {logged} logged breaths have a "
                          "non-finite or unreadable time, VO2 or VCO2 (NaN or infinite: a cart or parser "
                          "fault) and no evaluation was completed; nothing to review")
    notes.append(f"{logged - shown} of {logged} logged breaths have a non-finite or unreadable time, VO2 "
                 "or VCO2 and are not shown")


def _eval_row(e: rec.Evaluation, fi: int, t_start: float | None, t_end: float | None,
              source: str) -> EvaluationRow:
    return EvaluationRow(
        index=e.index, params=dict(e.params), mean_w=e.mean, var_w2=e.var, breaths=e.breaths,
        duration_s=e.duration_s, phase=e.phase, stopped_early=e.stopped_early, reason=e.reason,
        t_start_s=_f(t_start), t_end_s=_f(t_end), file=fi, source=source)


def _standardise(m: np.ndarray, s: np.ndarray) -> np.ndarray:
    return (m - m[:, -1:]) / np.sqrt(s + s[:, -1:])


def _thresholds(scans: list[_FileScan], traces: Sequence[EstimateTrace],
                evaluations: Sequence[EvaluationRow], config: Mapping[str, Any],
                snapshot: rec.OptimizerState | None,
                z_runs: Mapping[int, list[tuple[int, float, bool, str]]],
                notes: list[str]) -> ThresholdData | None:
    by_index = {e.index: e for e in evaluations}
    z_traces = tuple(
        ZTrace(k, tuple(r[0] for r in rows), tuple(r[1] for r in rows),
               by_index[k].stopped_early if k in by_index
               else any(r[2] and r[3] == "threshold" for r in rows))
        for k, rows in sorted(z_runs.items()) if rows)
    snaps = [s for scan in scans for s in scan.snapshots]
    for snap in snaps:
        a = snap.thresholds
        state = snap.state  # the optimizer's own JSON (HILOptimizer.to_json)
        if a:
            try:
                thr = np.asarray(a, dtype=float)
                m = np.asarray(state.get("traces_m"), dtype=float)
                s = np.asarray(state.get("traces_s"), dtype=float)
                x = _standardise(m, s) if m.ndim == 2 and m.shape == s.shape and m.shape[1] == thr.size \
                    else np.empty((0, thr.size))
            except (TypeError, ValueError):
                continue
            return ThresholdData(thr, x, "logged in /optimizer_state (thresholds, traces_m, traces_s)",
                                 z_traces)
    # No snapshot after exploration: compute Algorithm 2 from the exploration evaluations' estimates.
    from hilbo_core.errors import HilboError
    from hilbo_core.stopping import threshold_schedule

    state_cfg = snapshot.state.get("config") if snapshot is not None else None
    state_cfg = state_cfg if isinstance(state_cfg, Mapping) else {}
    proto = config.get("protocol") if isinstance(config.get("protocol"), Mapping) else {}
    n = _i(state_cfg.get("max_breaths")) or _i(proto.get("max_breaths"))
    n_explore = _i(state_cfg.get("n_explore")) or _i(proto.get("n_explore"))
    window = _i(state_cfg.get("window"))
    window = window if window is not None else _i(proto.get("window"))
    rows = [t for t in traces if t.completed and t.phase == "exploration" and n and len(t.mean_w) == n]
    if not n or not n_explore or window is None or len(rows) < n_explore:
        notes.append(f"no threshold plot: the log holds no threshold schedule and {len(rows)} of "
                     f"{n_explore or '?'} complete exploration traces")
        return None
    m = np.array([t.mean_w for t in rows[:n_explore]], dtype=float)
    s = np.array([t.sd_w for t in rows[:n_explore]], dtype=float) ** 2
    try:
        thr = threshold_schedule(m, s, window)
    except HilboError as err:
        notes.append(f"no threshold plot: the exploration traces give no schedule ({err})")
        return None
    return ThresholdData(thr, _standardise(m, s),
                         f"computed (Algorithm 2, W = {window}) from the /estimator messages of the "
                         "exploration evaluations", z_traces)


def _recommend(contents: Sequence[LogContents], snapshot: rec.OptimizerState | None,
               evaluations: Sequence[EvaluationRow], notes: list[str]) -> Recommendation | None:
    if not evaluations:
        return None
    from hilbo_core.errors import HilboError
    from hilbo_core.optimizer import HILOptimizer

    opt = None
    method = ""
    if snapshot is not None and len(_snapshot_evaluations(snapshot)) == len(evaluations):
        try:
            opt = HILOptimizer.from_json(snapshot.state)
            method = "HILOptimizer.best() of the last optimizer snapshot"
        except (HilboError, KeyError, TypeError, ValueError) as err:
            notes.append(f"the last optimizer snapshot cannot be loaded ({err})")
    if opt is None:
        from bridge.log.resume import rebuild_optimizer

        try:
            opt, _ = rebuild_optimizer(contents[-1])
            method = "HILOptimizer.best() of the optimizer rebuilt from the log"
        except (LogError, HilboError) as err:
            logger.info("rebuilding the optimizer for the recommendation failed: %s", err)
            opt = None
    params: Mapping[str, float]
    if opt is not None and len(opt.evaluations) == len(evaluations):
        try:
            params, mean, var = opt.best()
        except (HilboError, ValueError, np.linalg.LinAlgError) as err:
            notes.append(f"the optimizer's recommendation failed ({err}); showing the lowest estimate")
            opt = None
        if opt is not None:
            method += f" ({recommendation_method_text(opt.config.recommend.value, len(evaluations))})"
        conf = None if opt is None else opt.confirmation
        if conf is not None and conf.mean_w is not None and conf.sd_w is not None:
            # Measured in full at the session's end: its estimate is that measurement.
            method = (f"the session: recommended, confirmed at {conf.mean_w:.1f} ± {conf.sd_w:.1f} W "
                      f"({conf.breaths} breaths in its last minutes; the GP predicted "
                      f"{conf.predicted_mean_w:.1f} ± {conf.predicted_sd_w:.1f} W)")
    else:
        opt = None
    if opt is None:
        ev = min(evaluations, key=lambda e: e.mean_w)
        params, mean, var = ev.params, ev.mean_w, ev.var_w2
        method = "the lowest estimated mean (no optimizer state holds every evaluation)"
    index = next((e.index for e in evaluations if _same_params(e.params, params)), None)
    return Recommendation(dict(params), float(mean), float(var), index, method)


def _nearest_evaluation(evaluations: Sequence[EvaluationRow], params: Mapping[str, float],
                        bounds: Mapping[str, tuple[float, float]], logged: set[int]) -> int | None:
    """The index of the logged evaluation whose setting is nearest ``params`` (each parameter
    scaled by its range, the unit cube the optimizer searches), or None."""
    best: tuple[float, int] | None = None
    for e in evaluations:
        if e.index not in logged or set(e.params) != set(params):
            continue
        d = 0.0
        for k, v in params.items():
            lo, hi = bounds.get(k, (0.0, 1.0))
            d += ((e.params[k] - v) / ((hi - lo) or 1.0)) ** 2
        if best is None or d < best[0]:
            best = (d, e.index)
    return None if best is None else best[1]


def _same_params(a: Mapping[str, float], b: Mapping[str, float]) -> bool:
    return set(a) == set(b) and all(math.isclose(a[k], b[k], rel_tol=1e-9, abs_tol=1e-9) for k in a)


def _feedback(scan: _FileScan, index: int, obs_pos: int, notes: list[str]) -> FeedbackData | None:
    sent = [(pos, r) for pos, r in scan.profiles if r.index == index and pos < obs_pos]
    if not sent:
        notes.append(f"no force feedback plot: no /profiles_sent message for evaluation {index}")
        return None
    pos0, prof = sent[-1]
    version = prof.version
    samples: dict[int, tuple[list[float], list[float], list[float]]] = {}
    for pos, fb in scan.feedback:
        # Every batch stamped with this version, also those logged after the observation: a
        # setting stopped after a breath or two may end before its first batch is written (at
        # `hilbo sim` speed always). Samples of another table are filtered out below.
        if pos <= pos0 or fb.profile_version != version:
            continue
        gait = fb.gait_phase_pct
        if gait is None or not len(fb.desired_n) == len(fb.measured_n) == len(gait):
            continue
        acc = samples.setdefault(fb.actuator, ([], [], []))
        for g, de, me in zip(gait, fb.desired_n, fb.measured_n, strict=True):
            if _f(g) is not None and g >= 0 and _f(de) is not None and _f(me) is not None:
                acc[0].append(g)
                acc[1].append(de)
                acc[2].append(me)
    tables: dict[int, tuple[str, np.ndarray, np.ndarray]] = {}
    profiles = prof.profiles
    for act in samples:
        # One table per actuator, or one table every actuator executes (the hip suit's two legs).
        p = profiles[act] if len(profiles) > max(act, 1) else (profiles[0] if profiles else None)
        if p is not None:
            tables[act] = (p.actuator, np.asarray(p.gait_pct, dtype=float),
                           np.asarray(p.force_n, dtype=float))
    arrays: dict[int, tuple[np.ndarray, np.ndarray, np.ndarray]] = {}
    excluded = 0
    for act, (g_list, d_list, m_list) in sorted(samples.items()):
        g, des, mea = (np.asarray(v, dtype=float) for v in (g_list, d_list, m_list))
        if act in tables and tables[act][1].size == tables[act][2].size > 1:
            # A batch is stamped with the version active when it was logged: its first samples
            # may still be the old profile's (the device switches at a gait-cycle boundary).
            # Keep the samples whose desired force is this table's.
            _, gp, fp = tables[act]
            keep = np.abs(des - np.interp(g, gp, fp)) <= max(2.0, 0.05 * float(np.max(np.abs(fp))))
            excluded += int(np.count_nonzero(~keep))
            g, des, mea = g[keep], des[keep], mea[keep]
        if g.size:
            arrays[act] = (g, des, mea)
    if not arrays:
        notes.append(f"no force feedback plot: the log has no /force_feedback samples for profile version "
                     f"{version} of evaluation {index} (the recommended setting)")
        return None
    if excluded:
        notes.append(f"force tracking: {excluded} feedback samples of the recommended setting's batches "
                     "were left out: their desired force is not the table sent (the old profile, before "
                     "the switch at the gait-cycle boundary)")
    return FeedbackData(index, version, arrays, tables)


# ---------------------------------------------------------------------------------- outputs
