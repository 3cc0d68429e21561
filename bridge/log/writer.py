"""The session's MCAP log writer: one file per session, one typed JSON channel per kind of record.

Layout (shared/DESIGN.md "MCAP log"):

* Every channel carries one record type of :mod:`bridge.log.records` (a msgspec Struct), encoded
  with msgspec (about 3x faster than ``json.dumps`` of the dicts of format 1). Its draft-07 JSON
  schema (schema encoding ``jsonschema``) is generated from that type, so Foxglove can open the
  file and plot any numeric field, and the readers decode the same types. The schemas keep to
  what Foxglove's JSON-schema parser accepts: every property has one ``type`` (no
  ``["number", "null"]`` unions: an unknown value is *omitted*, not written as ``null``), every
  object lists ``properties``, arrays hold one item type. ``/events`` uses Foxglove's
  ``foxglove.Log`` schema (plus our fields) so the Log panel shows them.
* Timestamps are integer nanoseconds. ``log_time`` is the writer's clock when the message is
  written (wall clock by default; a simulation may pass its own ``clock_ns``).
  ``publish_time`` is the *breath-time base* (the cart's breath clock, ``t_s`` × 1e9) for
  messages tied to a breath (``/breaths``, ``/estimator``, ``/stopping``, and whatever the caller
  stamps with ``t_s``/``publish_time_ns``); for the others it equals ``log_time``. ``sequence`` is
  one counter over the whole file, so the write order survives readers that sort by time.
* ``/config`` (first message) and an MCAP metadata record ``hilbo.session`` carry the session id,
  the format version (:data:`bridge.log.records.FORMAT_VERSION`) and the path of the previous log
  when this session resumes a crashed one.
* ``/events`` levels come from the event kind (:func:`bridge.log.records.event_level`), and a
  change of a device's fault bits on ``/device_status`` is also an event (``device_fault``,
  ERROR; ``device_fault_cleared``, INFO).
* The file is created with mode 0600 (``file_mode``): it holds health data.

Crash safety. mcap's ``Writer`` keeps a chunk in memory until it reaches ``chunk_size`` (1 MiB
by default) and writes through a buffered file, so a process killed before then leaves nothing
(measured: a writer killed after 3 s left a 0-byte file). ``Writer.flush()`` (mcap >= 1.6) closes the open
chunk, writes it with its message indexes and flushes the file object. :class:`SessionLog` calls
it right after every message (``flush_immediately``) except on the high-rate ``/force_feedback``
and ``/device_status`` channels, and from a background thread every ``flush_interval_s`` (0.1 s)
when something is pending. So ``kill -9`` never loses a breath, estimate, decision or event whose
``log_*`` call returned (at most the one being written), and at most the last 100 ms of force
feedback and device status. ``flush()`` hands the bytes to the OS page cache, which outlives the
process; ``os.fsync`` (only needed against power loss or a kernel crash) runs every
``fsync_interval_s`` in the background thread and on close, never per message.

Measured here (a writer logging a breath every 2 ms, SIGKILL after 3 s, 6 runs each, read back
with :func:`bridge.log.reader.read_log`; machine under load):

* mcap defaults (1 MiB chunks, no flush): 0 % kept (0-byte files).
* 4 KiB chunks, no flush: 83 % kept; up to 98 messages lost per kill, some 0-byte files.
* chunks + 100 ms flush timer only: 94 % kept; up to 37 messages (≤ 100 ms) lost.
* unchunked + 100 ms file flush: 96 % kept; up to 26 messages lost.
* chunks + flush after every message (the default): 100 % kept; nothing lost.

File size for 5 000 breaths and 20 000 force-feedback batches: 0.67 MB with the timer only,
2.0 MB with the default, 18.3 MB unchunked (no compression).

The default costs ~60 µs per flushed message (vs ~40 µs) and a chunk per message on the
breath-rate channels (a few per breath), which is why the kilohertz channels stay on the timer.
Unchunked files have no chunk index and no compression; both kinds are read by the mcap package
and by :mod:`bridge.log.reader` (a cut-off file only by a front-to-back reader: mcap's seeking
reader needs the footer, which :func:`bridge.log.reader.recover` writes).

A file cut off by a crash is read by :mod:`bridge.log.reader` (``read_log``, ``recover``).
"""

from __future__ import annotations

import enum
import json
import logging
import math
import os
import threading
import time
import uuid
from collections import Counter
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from importlib.metadata import PackageNotFoundError, version
from pathlib import Path
from typing import TYPE_CHECKING, Any

import msgspec
import numpy as np
from mcap.well_known import MessageEncoding, SchemaEncoding
from mcap.writer import LIBRARY_IDENTIFIER, CompressionType, Writer

from bridge.log.errors import LogError, LogStateError, LogValueError, LogWriteError
from bridge.log.records import (
    CHANNELS,
    FORMAT_VERSION,
    METADATA_NAME,
    Breath,
    Config,
    DeviceStatus,
    Estimate,
    EventLevel,
    ForceFeedback,
    Incumbent,
    Log,
    OptimizerState,
    ProfileAck,
    ProfileSent,
    ProfileTable,
    Proposal,
    Rejects,
    Timestamp,
    Topic,
    event_level,
)
from bridge.log.records import Evaluation as EvaluationRecord
from bridge.log.records import StopDecision as StopRecord
from hilbo_core.optimizer import BreathStep, Evaluation, HILOptimizer
from hilbo_core.profiles import ForceProfile
from hilbo_core.stopping import StopDecision
from hilbo_core.types import BreathRecord

if TYPE_CHECKING:
    from bridge.live import LiveSink

__all__ = [
    "DEFAULT_FILE_MODE",
    "LogStats",
    "SessionLog",
    "check_message",
    "hilbo_version",
    "new_session_id",
]

logger = logging.getLogger(__name__)

DEFAULT_FILE_MODE = 0o600
"""Permission bits of a new session log (and summary): owner read/write only (health data)."""

_PROFILE = "hilbo"
_DEFAULT_CHUNK_SIZE = 256 * 1024


# High-rate channels: left to the flush timer (flushing each would make a chunk per frame batch).
# Everything else (breaths, estimates, decisions, proposals, profiles, acks, events) is at most a
# few messages per breath and is flushed as soon as it is written when flush_immediately is on.
_TIMER_TOPICS = frozenset({Topic.FORCE_FEEDBACK, Topic.DEVICE_STATUS})


# ---------------------------------------------------------------------------------- helpers
def new_session_id() -> str:
    """A fresh session id: UTC start time plus a random suffix (sortable, unique)."""
    return time.strftime("%Y%m%dT%H%M%SZ", time.gmtime()) + "-" + uuid.uuid4().hex[:8]


def hilbo_version() -> str:
    """The installed hilbo version (``"unknown"`` when running from an uninstalled tree)."""
    try:
        return version("hilbo")
    except PackageNotFoundError:
        return "unknown"


def _json_default(obj: Any) -> Any:
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, enum.Enum):
        return obj.name.lower() if isinstance(obj.value, int) else obj.value
    if isinstance(obj, Path):
        return str(obj)
    raise TypeError(f"{type(obj).__name__} is not JSON-serialisable")


def _finite_or_none(obj: Any) -> Any:
    """Copy of ``obj`` with NaN/±inf replaced by None (JSON has no NaN; Foxglove rejects it)."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, Mapping):
        return {k: _finite_or_none(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_finite_or_none(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _finite_or_none(obj.tolist())
    if isinstance(obj, np.floating):
        return _finite_or_none(float(obj))
    return obj


def _drop_none(d: Mapping[str, Any]) -> dict[str, Any]:
    # Optional fields are omitted rather than null: the schemas use one type per field.
    return {k: v for k, v in d.items() if v is not None}


def check_message(schema: Mapping[str, Any], message: Any, path: str = "") -> list[str]:
    """Problems of ``message`` against a channel schema (the subset our schemas use).

    Checks ``type`` (object, array, number, integer, string, boolean), ``required``,
    ``properties``, ``additionalProperties`` given as a schema, ``items``, ``minimum``,
    ``maximum`` and ``oneOf`` of constants. Not a general JSON-schema validator.

    Returns:
        Human-readable problems, empty when the message conforms.
    """
    where = path or "message"
    if "oneOf" in schema:
        consts = [alt.get("const") for alt in schema["oneOf"]]
        return [] if message in consts else [f"{where}={message!r} is not one of {consts}"]
    kind = schema.get("type")
    checks = {
        "object": lambda v: isinstance(v, dict),
        "array": lambda v: isinstance(v, list),
        "number": lambda v: isinstance(v, int | float) and not isinstance(v, bool),
        "integer": lambda v: isinstance(v, int) and not isinstance(v, bool),
        "string": lambda v: isinstance(v, str),
        "boolean": lambda v: isinstance(v, bool),
    }
    if kind is not None and not checks[kind](message):
        return [f"{where}={message!r} is not of type {kind}"]
    problems: list[str] = []
    if kind in ("number", "integer"):
        if "minimum" in schema and message < schema["minimum"]:
            problems.append(f"{where}={message!r} < minimum {schema['minimum']}")
        if "maximum" in schema and message > schema["maximum"]:
            problems.append(f"{where}={message!r} > maximum {schema['maximum']}")
    elif kind == "object":
        props = schema.get("properties", {})
        problems += [f"{where}: missing required key {k!r}" for k in schema.get("required", ())
                     if k not in message]
        extra = schema.get("additionalProperties")
        for k, v in message.items():
            if k in props:
                problems += check_message(props[k], v, f"{where}.{k}")
            elif isinstance(extra, Mapping):
                problems += check_message(extra, v, f"{where}.{k}")
    elif kind == "array" and "items" in schema:
        for i, v in enumerate(message):
            problems += check_message(schema["items"], v, f"{where}[{i}]")
    return problems


@dataclass
class LogStats:
    """What a :class:`SessionLog` has written so far.

    Attributes:
        messages: Messages written.
        per_topic: Messages per topic.
        flushes: Chunk flushes that wrote something.
        fsyncs: ``os.fsync`` calls.
    """

    messages: int = 0
    per_topic: Counter[str] = field(default_factory=Counter)
    flushes: int = 0
    fsyncs: int = 0


class SessionLog:
    """Writes one session's MCAP log; a context manager.

    Args:
        path: The file to create (``.mcap``). An existing file is never overwritten unless
            ``overwrite`` is True: a session log is data that cannot be re-collected.
        session_id: The session's id (:func:`new_session_id`; a resumed session keeps its id).
        config_json: The session config as a JSON-able mapping (or JSON text), stored in
            ``/config``.
        previous_log: Path of the log this session resumes, or None for a new session.
        flush_interval_s: Pending messages reach the file at least this often (s); None turns
            the background flusher off (then call :meth:`flush` yourself).
        fsync_interval_s: ``os.fsync`` at most this often (s) from the background flusher;
            None: only on close.
        flush_immediately: Flush right after every message except ``/force_feedback`` and
            ``/device_status`` (those wait for the timer), so a breath, estimate, decision or
            event is in the file when its ``log_*`` call returns.
        param_names: Names of the optimised parameters: the ``params`` objects of the schemas
            list them, so Foxglove offers them for plotting.
        chunk_size: A chunk is also closed when it grows past this many bytes.
        compression: ``"zstd"`` (default), ``"lz4"`` or ``"none"``.
        chunked: Group messages in chunks (indexed, compressed; the default). False writes each
            message as its own record and flushes the file object instead (what an mcap
            without ``Writer.flush()`` gets).
        clock_ns: The ``log_time`` clock in ns (wall clock by default).
        overwrite: Replace an existing file.
        file_mode: Permission bits of the file (default 0o600, owner read/write only: a session
            log holds health data such as VO2, heart rate and body mass). Set exactly, whatever
            the umask (``[session] file_mode`` in the config).
        started_unix_ns: The ``started_unix_ns`` stored in ``/config`` and the metadata (default
            the wall clock now; a fixed value makes the file reproducible, e.g. for tests).
        live: A live view (:class:`bridge.live.LiveServer`) that gets every record written, on
            the same topic with the same schema; None: no live view.

    Raises:
        LogValueError: A bad option.
        LogWriteError: The file cannot be created (or exists and ``overwrite`` is False).

    Example:
        >>> with SessionLog("run/session.mcap", session_id=new_session_id(), config_json=cfg) as log:
        ...     log.log_optimizer_state(opt, reason="start")
        ...     log.log_breath(record)
    """

    def __init__(
        self,
        path: str | os.PathLike[str],
        *,
        session_id: str,
        config_json: Mapping[str, Any] | str,
        previous_log: str | os.PathLike[str] | None = None,
        flush_interval_s: float | None = 0.1,
        fsync_interval_s: float | None = 2.0,
        flush_immediately: bool = True,
        param_names: Sequence[str] = (),
        chunk_size: int = _DEFAULT_CHUNK_SIZE,
        compression: str = "zstd",
        chunked: bool = True,
        clock_ns: Callable[[], int] = time.time_ns,
        overwrite: bool = False,
        file_mode: int = DEFAULT_FILE_MODE,
        started_unix_ns: int | None = None,
        live: LiveSink | None = None,
    ) -> None:
        if not isinstance(session_id, str) or not session_id.strip():
            raise LogValueError(f"session_id={session_id!r}; expected a non-empty string")
        for name, value in (("flush_interval_s", flush_interval_s), ("fsync_interval_s", fsync_interval_s)):
            if value is not None and not (isinstance(value, int | float) and 0 < value < math.inf):
                raise LogValueError(f"{name}={value!r}; expected a positive number of seconds or None")
        if isinstance(chunk_size, bool) or not isinstance(chunk_size, int) or chunk_size < 1024:
            raise LogValueError(f"chunk_size={chunk_size!r}; expected an integer >= 1024 bytes")
        codecs = {"zstd": CompressionType.ZSTD, "lz4": CompressionType.LZ4, "none": CompressionType.NONE}
        if compression not in codecs:
            raise LogValueError(f"compression={compression!r}; expected one of {sorted(codecs)}")
        if isinstance(file_mode, bool) or not isinstance(file_mode, int) or not 0 <= file_mode <= 0o777:
            raise LogValueError(f"file_mode={file_mode!r}; expected permission bits 0o000..0o777 "
                                "such as 0o600")
        if isinstance(config_json, str):
            try:
                config_json = json.loads(config_json)
            except json.JSONDecodeError as err:
                raise LogValueError(f"config_json is not valid JSON text: {err}") from err
        if not isinstance(config_json, Mapping):
            raise LogValueError(f"config_json must be a mapping, got {type(config_json).__name__}")
        self.path = Path(path)
        self.session_id = session_id
        self.previous_log = None if previous_log is None else str(previous_log)
        self.stats = LogStats()
        self._param_names = tuple(param_names)
        self._clock_ns = clock_ns
        self._flush_immediately = flush_immediately
        self._lock = threading.Lock()
        self._pending = False
        self._closed = False
        self._sequence = 0
        self._thread_error: BaseException | None = None
        self._live = live  # live view (bridge/live.py): mirrors every record in _write
        self._schemas: dict[str, tuple[str, Mapping[str, Any]]] = {}
        self._faults: dict[int, int] = {}
        self._file = _create(self.path, overwrite=overwrite, mode=file_mode)  # closed in close()
        # mcap < 1.6 has no Writer.flush() (no public way to close a chunk early): fall back to
        # unchunked records, which reach the file on every file flush.
        self._chunked = chunked and hasattr(Writer, "flush")
        if chunked and not self._chunked:
            logger.warning("this mcap package has no Writer.flush(); writing an unchunked log")
        try:
            self._writer = Writer(self._file, chunk_size=chunk_size, compression=codecs[compression],
                                  use_chunking=self._chunked)
            self._writer.start(profile=_PROFILE, library=f"hilbo {hilbo_version()}; {LIBRARY_IDENTIFIER}")
            started_ns = time.time_ns() if started_unix_ns is None else int(started_unix_ns)
            self._writer.add_metadata(METADATA_NAME, {
                "session_id": session_id,
                "previous_log": self.previous_log or "",
                "format_version": str(FORMAT_VERSION),
                "hilbo_version": hilbo_version(),
                "started_unix_ns": str(started_ns),
            })
            self._channel_ids: dict[str, int] = {}
            for spec in CHANNELS.values():
                self._register(spec.topic, spec.schema_name, spec.json_schema(self._param_names))
            self._write_record(Topic.CONFIG, Config(
                session_id=session_id, previous_log=self.previous_log,
                resumed=self.previous_log is not None, config=_config_builtins(config_json),
                param_names=list(self._param_names), hilbo_version=hilbo_version(),
                format_version=FORMAT_VERSION, started_unix_ns=started_ns), None, None)
            self._flush_locked()
        except (OSError, LogError) as err:
            # The file is ours and holds nothing yet: remove it so a corrected retry can create it.
            self._file.close()
            self.path.unlink(missing_ok=True)
            if isinstance(err, LogError):
                raise  # e.g. a config that is not JSON-able
            raise LogWriteError(f"cannot write the session log {str(self.path)!r}: {err}") from err
        self._fsync_interval_s = fsync_interval_s
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        if flush_interval_s is not None:
            self._thread = threading.Thread(target=self._flusher, args=(float(flush_interval_s),),
                                            name=f"SessionLog flusher {self.path.name}", daemon=True)
            self._thread.start()

    # ------------------------------------------------------------------ context manager
    def __enter__(self) -> SessionLog:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    @property
    def closed(self) -> bool:
        """True once :meth:`close` has run."""
        return self._closed

    def close(self) -> None:
        """Write the summary section (indexes, statistics) and close the file. Idempotent."""
        if self._closed:
            return
        if self._thread is not None:
            self._stop.set()
            self._thread.join()
        with self._lock:
            self._closed = True
            try:
                self._writer.add_metadata(METADATA_NAME + ".end", {
                    "messages": str(self.stats.messages), "clean_close": "true"})
                self._writer.finish()
                self._file.flush()
                os.fsync(self._file.fileno())
            except OSError as err:
                raise LogWriteError(f"cannot finish the session log {str(self.path)!r}: {err}") from err
            finally:
                self._file.close()

    # ------------------------------------------------------------------ writing
    def log(self, topic: str, message: Mapping[str, Any], publish_time_ns: int | None = None) -> None:
        """Write one JSON message on ``topic`` (any topic; unknown topics get a permissive schema).

        Top-level ``None`` values are dropped (optional fields are omitted, not null), NaN and
        infinities become absent/None, numpy values become numbers. On ``/events`` the
        ``foxglove.Log`` fields missing from ``message`` are filled in (``message`` from
        ``text``, level INFO, the log time as ``timestamp``).

        Args:
            topic: Channel topic (``/breaths``, ... or a new one).
            message: The message (a JSON object).
            publish_time_ns: Breath-time base in ns for breath-tied messages; None = log time.

        Raises:
            LogStateError: The log is closed.
            LogValueError: ``publish_time_ns`` is negative, or the message is not JSON-able.
            LogWriteError: The file could not be written.
        """
        if not isinstance(message, Mapping):
            raise LogValueError(f"log({topic!r}): message must be a mapping, got {type(message).__name__}")
        with self._lock:
            self._check_open()
            self._write(topic, message, publish_time_ns)
            if self._flush_immediately and topic not in _TIMER_TOPICS:
                self._flush_locked()

    def flush(self, *, fsync: bool = False) -> None:
        """Close the open chunk and hand everything to the OS now (optionally fsync too)."""
        with self._lock:
            self._check_open()
            self._flush_locked()
            if fsync:
                self._fsync()

    # typed helpers ------------------------------------------------------------------
    def log_record(self, topic: str, record: Any, publish_time_ns: int | None = None) -> None:
        """Write one typed record (a :mod:`bridge.log.records` struct) on ``topic``.

        Args:
            topic: The channel (its record type is ``RECORD_TYPES[topic]``).
            record: The struct.
            publish_time_ns: Breath-time base in ns for breath-tied messages; None = log time.

        Raises:
            LogStateError: The log is closed.
            LogValueError: ``publish_time_ns`` is negative, or the record cannot be encoded.
            LogWriteError: The file could not be written.
        """
        with self._lock:
            self._check_open()
            self._write_record(topic, record, publish_time_ns, None)
            if self._flush_immediately and topic not in _TIMER_TOPICS:
                self._flush_locked()

    def log_breath(self, record: BreathRecord) -> None:
        """``/breaths``: one breath as the cart reported it (publish_time = its breath time)."""
        self.log_record(Topic.BREATHS, Breath(
            t_s=record.t_s, vo2_ml_min=record.vo2_ml_min, vco2_ml_min=record.vco2_ml_min,
            ve_l_min=record.ve_l_min, rer=record.rer, hr_bpm=record.hr_bpm, watts=record.watts,
        ), _t_ns(record.t_s))

    def log_step(self, step: BreathStep, *, index: int, t_setting_s: float, watts: float,
                 t_s: float | None = None,
                 incumbent: tuple[Mapping[str, float], float, float] | None = None) -> None:
        """``/estimator`` and (when the rule decided) ``/stopping`` for one observed breath.

        Call right after ``HILOptimizer.observe_breath(t_setting_s, watts)`` returned ``step``,
        with the very ``t_setting_s`` and ``watts`` given to it: resume replays them.

        Args:
            step: What the breath did.
            index: The evaluation's index (``len(opt.evaluations)`` before the breath).
            t_setting_s: Seconds since the setting was applied, as given to the optimizer.
            watts: Metabolic power as given to the optimizer (W).
            t_s: The breath's time on the cart clock (publish_time), if known.
            incumbent: ``opt.incumbent`` (x*, μ*, σ*²), logged with the decision.
        """
        self.log_estimate(index=index, breath=step.index, t_setting_s=t_setting_s, watts=watts,
                          mean_w=step.mean, var_w2=step.var, phase=step.phase.value, t_s=t_s)
        if step.decision is not None:
            self.log_stopping(step.decision, index=index, t_s=t_s, stop=step.stop,
                              reason=step.evaluation.reason if step.evaluation else None,
                              incumbent=incumbent)

    def log_estimate(self, *, index: int, breath: int, t_setting_s: float, watts: float,
                     mean_w: float, var_w2: float, phase: str, t_s: float | None = None) -> None:
        """``/estimator``: a breath the optimizer consumed and the estimate after it."""
        mean_w, var_w2 = float(mean_w), float(var_w2)
        sd = math.sqrt(var_w2) if var_w2 >= 0 else math.nan
        finite = math.isfinite(sd) and math.isfinite(mean_w)
        self.log_record(Topic.ESTIMATOR, Estimate(
            index=int(index), breath=int(breath), t_s=t_s, t_setting_s=float(t_setting_s),
            watts=float(watts), mean_w=mean_w, var_w2=var_w2, sd_w=sd if finite else None,
            lo95_w=mean_w - 1.96 * sd if finite else None, hi95_w=mean_w + 1.96 * sd if finite else None,
            phase=phase), None if t_s is None else _t_ns(t_s))

    def log_stopping(self, decision: StopDecision, *, index: int, t_s: float | None = None,
                     stop: bool | None = None, reason: str | None = None,
                     incumbent: tuple[Mapping[str, float], float, float] | None = None) -> None:
        """``/stopping``: the rule's decision (``reason`` overrides it, e.g. ``budget``)."""
        self.log_record(Topic.STOPPING, StopRecord(
            index=int(index), breath=int(decision.index), t_s=t_s,
            stop=bool(decision.stop if stop is None else stop),
            reason=reason or decision.reason.value, z=_finite(decision.z),
            threshold=_finite(decision.threshold),
            incumbent_mean_w=None if incumbent is None else _finite(incumbent[1]),
            incumbent_var_w2=None if incumbent is None else _finite(incumbent[2]),
        ), None if t_s is None else _t_ns(t_s))

    def log_proposal(self, params: Mapping[str, float], *, index: int, phase: str,
                     t_s: float | None = None,
                     incumbent: tuple[Mapping[str, float], float, float] | None = None,
                     compute_ms: float | None = None, total_ms: float | None = None,
                     to_worker_ms: float | None = None, from_worker_ms: float | None = None,
                     worker: str | None = None) -> None:
        """``/proposals``: the setting ``ask()`` returned, logged right after every ask(), with
        how long it took (``compute_ms`` in the worker, ``total_ms`` as the session saw it)."""
        self.log_record(Topic.PROPOSALS, Proposal(
            index=int(index), params=_params(params), phase=str(phase), t_s=t_s,
            incumbent=None if incumbent is None else Incumbent(
                params=_params(incumbent[0]), mean=float(incumbent[1]), var=float(incumbent[2])),
            compute_ms=compute_ms, total_ms=total_ms, to_worker_ms=to_worker_ms,
            from_worker_ms=from_worker_ms, worker=worker))

    def log_observation(self, evaluation: Evaluation, *, t_start: float | None = None,
                        t_end: float | None = None, t_s: float | None = None) -> None:
        """``/observations``: a completed evaluation (session times ``t_start``/``t_end`` in s)."""
        e = evaluation
        self.log_record(Topic.OBSERVATIONS, EvaluationRecord(
            index=int(e.index), params=_params(e.params), mean=float(e.mean), var=float(e.var),
            breaths=int(e.breaths), duration_s=float(e.duration_s), phase=str(e.phase),
            stopped_early=bool(e.stopped_early), reason=str(e.reason), t_start=t_start, t_end=t_end,
            obs_mean=None if e.obs_mean is None else float(e.obs_mean),
            obs_var=None if e.obs_var is None else float(e.obs_var),
            drift_var=None if e.drift_var is None else float(e.drift_var),
        ), None if t_s is None else _t_ns(t_s))

    def log_optimizer_state(self, optimizer: HILOptimizer, *, reason: str,
                            t_s: float | None = None) -> None:
        """``/optimizer_state``: a full snapshot, the starting point of a resume.

        Log one at the start of a session (``reason="start"``; a resumed session logs its
        rebuilt optimizer with ``"resume"``), after every completed evaluation
        (``"evaluation"``), after ``cancel_current``/``set_budget`` (``"cancel"``,
        ``"budget"``), and at the session's end (``"end"``: the state its summary recommends from).
        """
        thresholds = optimizer.thresholds
        self.log_record(Topic.OPTIMIZER_STATE, OptimizerState(
            state=optimizer.to_json(), reason=reason, n_evaluations=len(optimizer.evaluations),
            thresholds=None if thresholds is None else thresholds.tolist(),
        ), None if t_s is None else _t_ns(t_s))

    def log_profile_sent(self, profiles: Sequence[ForceProfile], *, version: int,
                         crc32: int | None = None, index: int | None = None,
                         params: Mapping[str, float] | None = None, t_s: float | None = None) -> None:
        """``/profiles_sent``: the tables pushed to the device under ``version``."""
        tables = [ProfileTable(actuator=str(p.actuator), gait_pct=p.gait_pct.tolist(),
                               force_n=p.force_n.tolist()) for p in profiles]
        table = [f for t in tables for f in t.force_n]
        self.log_record(Topic.PROFILES_SENT, ProfileSent(
            version=int(version), n_points=len(table), crc32=crc32, index=index,
            params=None if params is None else _params(params), force_n=table, profiles=tables, t_s=t_s))

    def log_ack(self, *, version: int, accepted: bool, reason: str | enum.Enum = "none", detail: int = 0,
                attempts: int | None = None, elapsed_s: float | None = None,
                crc32: int | None = None, error: str | None = None) -> None:
        """``/acks``: the device's ack/nack of a commit, or why the push failed."""
        self.log_record(Topic.ACKS, ProfileAck(
            version=int(version), accepted=bool(accepted), reason=_name(reason), detail=int(detail),
            attempts=attempts, elapsed_s=elapsed_s, crc32=crc32, error=error))

    def log_force_feedback(self, *, actuator: int, desired_n: Sequence[float],
                           measured_n: Sequence[float],
                           gait_phase_pct: Sequence[float | None] | None = None,
                           profile_version: int | None = None) -> None:
        """``/force_feedback``: a batch of controller samples of one actuator.

        Unknown gait phases (None) are written as −1 (the schema has one number type).
        """
        desired = list(map(float, desired_n))
        measured = list(map(float, measured_n))
        n = len(desired)
        if n != len(measured):
            raise LogValueError(f"force feedback batch: {n} desired vs {len(measured)} "
                                "measured samples; expected equal lengths")
        gait = None if gait_phase_pct is None else [-1.0 if g is None else float(g) for g in gait_phase_pct]
        self.log_record(Topic.FORCE_FEEDBACK, ForceFeedback(
            actuator=int(actuator), n=n, desired_n=desired, measured_n=measured, gait_phase_pct=gait,
            profile_version=profile_version,
            desired_mean_n=math.fsum(desired) / n if n else None,
            measured_mean_n=math.fsum(measured) / n if n else None))

    def log_device_status(self, *, actuator: int, mode: str | enum.Enum, faults: int | enum.Flag,
                          gait_phase_pct: float | None = None, profile_version_active: int = 0,
                          profile_version_pending: int = 0) -> None:
        """``/device_status``: one actuator's status (``faults`` as bits or an enum.Flag).

        A change of the fault bits is also an ``/events`` message: ``device_fault`` (level
        ERROR, naming the faults) when a fault latches or changes, ``device_fault_cleared``
        (INFO) when the bits return to 0, so Foxglove's Log panel and the review show it.
        """
        names = ([m.name.lower() for m in type(faults) if m in faults and m.name]
                 if isinstance(faults, enum.Flag) else None)
        bits, act = int(faults), int(actuator)
        self.log_record(Topic.DEVICE_STATUS, DeviceStatus(
            actuator=act, mode=_name(mode), faults=bits, fault_names=names,
            gait_phase_pct=gait_phase_pct, profile_version_active=int(profile_version_active),
            profile_version_pending=int(profile_version_pending)))
        before = self._faults.get(act, 0)
        if bits == before:
            return
        self._faults[act] = bits
        what = ", ".join(names) if names else f"0x{bits:x}"
        if bits:
            self.log_event("device_fault", f"actuator {act}: device fault {what} (mode {_name(mode)})",
                           actuator=act, faults=bits, fault_names=names or [])
        else:
            self.log_event("device_fault_cleared", f"actuator {act}: device faults cleared",
                           actuator=act, faults=0, previous_faults=before)

    def log_event(self, kind: str, text: str, *, level: EventLevel | int | None = None,
                  t_s: float | None = None, **details: Any) -> None:
        """``/events``: a session event (Foxglove's Log panel shows ``text``).

        Args:
            kind: Machine-readable kind (``pause``, ``bus_error``...).
            text: Human-readable text.
            level: The ``foxglove.Log`` level; None (the default) takes it from the kind
                (:func:`bridge.log.records.event_level`: pauses and refusals WARNING, lost
                heartbeat, bus errors and faults ERROR, the rest INFO).
            t_s: Breath time of the event, if known.
            **details: Event-specific JSON-able values.
        """
        try:
            lv = event_level(str(kind)) if level is None else EventLevel(int(level))
        except ValueError as err:
            raise LogValueError(f"log_event({kind!r}): level={level!r}; expected a foxglove.LogLevel "
                                f"0..5 ({', '.join(m.name for m in EventLevel)})") from err
        with self._lock:
            self._check_open()
            log_ns = int(self._clock_ns())
            try:
                clean = _clean_details(details) or None
            except TypeError as err:
                raise LogValueError(f"log_event({kind!r}): details are not JSON-serialisable: {err}") from err
            record = Log(timestamp=Timestamp(sec=log_ns // 1_000_000_000, nsec=log_ns % 1_000_000_000),
                         level=lv, message=str(text), name="hilbo", file="", line=0, kind=str(kind),
                         t_s=t_s, details=clean)
            self._write_record(Topic.EVENTS, record, None, log_ns)
            if self._flush_immediately:
                self._flush_locked()

    def log_rejects(self, source: str, counts: Mapping[str, int], *, t_s: float | None = None) -> None:
        """``/rejects``: cumulative rejected records/frames of ``source`` by reason."""
        c = {str(k): int(v) for k, v in counts.items()}
        self.log_record(Topic.REJECTS, Rejects(source=str(source), counts=c, total=sum(c.values()), t_s=t_s))

    # ------------------------------------------------------------------ internals
    def _check_open(self) -> None:
        if self._closed:
            raise LogStateError(f"the session log {str(self.path)!r} is closed")
        if self._thread_error is not None:
            err = self._thread_error
            raise LogWriteError(f"the session log {str(self.path)!r} failed in the background: "
                                f"{err}") from err

    def _register(self, topic: str, schema_name: str, schema: Mapping[str, Any]) -> int:
        sid = self._writer.register_schema(schema_name, SchemaEncoding.JSONSchema,
                                           json.dumps(schema).encode())
        cid = self._writer.register_channel(topic, MessageEncoding.JSON, sid)
        self._channel_ids[topic] = cid
        self._schemas[topic] = (schema_name, schema)
        return cid

    def _times(self, topic: str, publish_time_ns: int | None, log_ns: int | None) -> tuple[int, int]:
        log_ns = int(self._clock_ns()) if log_ns is None else log_ns
        if log_ns < 0:
            raise LogValueError(f"clock_ns() returned {log_ns}; expected ns >= 0")
        if publish_time_ns is None:
            return log_ns, log_ns
        if isinstance(publish_time_ns, bool) or not isinstance(publish_time_ns, int | np.integer) \
                or publish_time_ns < 0:
            raise LogValueError(f"log({topic!r}): publish_time_ns={publish_time_ns!r}; expected an "
                                "integer >= 0 (breath time in ns)")
        return log_ns, int(publish_time_ns)

    def _write(self, topic: str, message: Mapping[str, Any], publish_time_ns: int | None) -> None:
        log_ns, publish_ns = self._times(topic, publish_time_ns, None)
        msg = _drop_none(message)
        if topic == Topic.EVENTS:
            msg = _complete_event(msg, log_ns)
        self._emit(topic, _encode(topic, msg), log_ns, publish_ns)

    def _write_record(self, topic: str, record: Any, publish_time_ns: int | None,
                      log_ns: int | None) -> None:
        log_ns, publish_ns = self._times(topic, publish_time_ns, log_ns)
        if topic == Topic.OPTIMIZER_STATE:
            # msgspec writes NaN as null; the snapshot must round-trip exactly for resume.
            data = _encode(topic, msgspec.to_builtins(record, enc_hook=_json_default))
        else:
            try:
                data = _ENCODER.encode(record)
                if b"null" in data:
                    # msgspec writes NaN/inf as null; Foxglove's schemas have one type per field.
                    # As before: a non-finite value is omitted (the reader names the missing field).
                    data = _encode(topic, _drop_none(_finite_or_none(
                        msgspec.to_builtins(record, enc_hook=_json_default))))
            except (TypeError, ValueError, OverflowError) as err:
                raise LogValueError(f"log({topic!r}): record is not JSON-serialisable: {err}") from err
        self._emit(topic, data, log_ns, publish_ns)

    def _emit(self, topic: str, data: bytes, log_ns: int, publish_ns: int) -> None:
        cid = self._channel_ids.get(topic)
        if cid is None:
            cid = self._register(topic, "hilbo.Generic" + topic.replace("/", "."),
                                 {"$schema": "http://json-schema.org/draft-07/schema#",
                                  "title": "hilbo.Generic", "type": "object", "properties": {}})
        try:
            self._writer.add_message(cid, log_time=log_ns, data=data, publish_time=publish_ns,
                                     sequence=self._sequence % 2**32)
        except OSError as err:
            raise LogWriteError(f"cannot write to the session log {str(self.path)!r}: {err}") from err
        self._sequence += 1
        self._pending = True
        self.stats.messages += 1
        self.stats.per_topic[topic] += 1
        if self._live is not None:  # live view: the same record, topic and schema (never raises)
            schema_name, schema = self._schemas[topic]
            self._live.publish(topic, schema_name, schema, data, log_ns)

    def _flush_locked(self) -> None:
        if not self._pending:
            return
        try:
            if self._chunked:
                self._writer.flush()  # closes the open chunk, writes it, flushes the file object
            else:
                self._file.flush()
        except OSError as err:
            raise LogWriteError(f"cannot flush the session log {str(self.path)!r}: {err}") from err
        self._pending = False
        self.stats.flushes += 1

    def _fsync(self) -> None:
        os.fsync(self._file.fileno())
        self.stats.fsyncs += 1

    def _flusher(self, interval_s: float) -> None:
        last_fsync = time.monotonic()
        while not self._stop.wait(interval_s):
            try:
                with self._lock:
                    if self._closed:
                        return
                    self._flush_locked()
                now = time.monotonic()
                if self._fsync_interval_s is not None and now - last_fsync >= self._fsync_interval_s:
                    # Outside the lock: an fsync can take long and must not block the loggers.
                    self._fsync()
                    last_fsync = now
            except (LogError, OSError, ValueError) as err:
                # Surfaced on the next log call (this thread has no caller to raise to).
                logger.error("session log %s: background flush failed: %s", self.path, err)
                self._thread_error = err
                return


def _t_ns(t_s: float) -> int:
    t = float(t_s)
    if not math.isfinite(t) or t < 0:
        raise LogValueError(f"breath time t_s={t_s!r}; expected a finite time >= 0 s")
    return round(t * 1e9)


def _name(value: str | enum.Enum) -> str:
    return value.name.lower() if isinstance(value, enum.Enum) and value.name else str(value)


def _complete_event(msg: dict[str, Any], log_ns: int) -> dict[str, Any]:
    out = dict(msg)
    out.setdefault("message", str(out.get("text", out.get("kind", ""))))
    out.setdefault("kind", "event")
    out.setdefault("level", int(EventLevel.INFO))
    out.setdefault("timestamp", {"sec": log_ns // 1_000_000_000, "nsec": log_ns % 1_000_000_000})
    out.setdefault("name", "hilbo")
    out.setdefault("file", "")
    out.setdefault("line", 0)
    return out


def _encode(topic: str, msg: Mapping[str, Any]) -> bytes:
    try:
        return json.dumps(msg, separators=(",", ":"), allow_nan=False, default=_json_default).encode()
    except ValueError:
        pass
    except TypeError as err:
        raise LogValueError(f"log({topic!r}): message is not JSON-serialisable: {err}") from err
    if topic == Topic.OPTIMIZER_STATE:
        # The snapshot must round-trip exactly for resume: keep Python's NaN/Infinity tokens
        # (json.loads reads them; only Foxglove's viewer would choke on this one message).
        logger.warning("optimizer snapshot contains a non-finite number; written as a JSON extension")
        return json.dumps(msg, separators=(",", ":"), default=_json_default).encode()
    return json.dumps(_drop_none(_finite_or_none(msg)), separators=(",", ":"), allow_nan=False,
                      default=_json_default).encode()


def _finite(value: float | None) -> float | None:
    if value is None:
        return None
    v = float(value)
    return v if math.isfinite(v) else None


def _params(params: Mapping[str, float]) -> dict[str, float]:
    return {str(k): float(v) for k, v in params.items()}


def _clean_details(details: Mapping[str, Any]) -> dict[str, Any]:
    return _drop_none(_finite_or_none(msgspec.to_builtins(dict(details), enc_hook=_json_default)))


_ENCODER = msgspec.json.Encoder(enc_hook=_json_default)


def _config_builtins(config: Mapping[str, Any]) -> dict[str, Any]:
    try:
        return json.loads(json.dumps(dict(config), allow_nan=False, default=_json_default))
    except (TypeError, ValueError) as err:
        raise LogValueError(f"config_json: the session config is not JSON-serialisable: {err}") from err


def _create(path: Path, *, overwrite: bool, mode: int) -> Any:
    """Open ``path`` for writing with exactly ``mode`` (never replacing a file unless ``overwrite``)."""
    flags = os.O_WRONLY | os.O_CREAT | (os.O_TRUNC if overwrite else os.O_EXCL) | getattr(os, "O_CLOEXEC", 0)
    try:
        fd = os.open(path, flags, mode)
    except OSError as err:
        raise LogWriteError(f"cannot create the session log {str(path)!r}: {err}") from err
    try:
        os.fchmod(fd, mode)  # the umask may have removed bits; an overwritten file keeps its old mode
        return os.fdopen(fd, "wb")
    except OSError as err:
        os.close(fd)
        raise LogWriteError(f"cannot create the session log {str(path)!r}: {err}") from err
