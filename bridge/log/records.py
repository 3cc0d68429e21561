"""The typed records of a session log: one msgspec Struct per channel, shared by writer and readers.

Every channel of the MCAP log (shared/DESIGN.md "MCAP log") carries JSON messages of one record
type below. The writer (:class:`bridge.log.SessionLog`) builds these structs and encodes them with
msgspec; every reader (:func:`bridge.log.read_log`, review, resume, tune-stopping, the
benchmarks) decodes them back into the same structs and reads attributes, never dict keys.

The channels' JSON schemas are *generated* from these types (:func:`json_schema`, built on
``msgspec.json.schema``) and then shaped for Foxglove's JSON-schema parser, which needs one
``type`` per field (an optional field is *omitted* when unknown, so ``X | None`` becomes ``X``),
``properties`` on every object, no ``$ref`` and ``foxglove.LogLevel`` as ``oneOf`` constants.

Conventions: timestamps are integer nanoseconds (MCAP ``log_time``/``publish_time``); times in
records are seconds with ``_s`` in the name, powers ``_w``, forces ``_n``. An optional field
defaults to None and is left out of the JSON when None (``omit_defaults``); a required field is
always written. Unknown fields are ignored when reading, so a reader of this version opens the
logs of an older one as long as the fields it needs kept their names (see :data:`FORMAT_VERSION`).
"""

from __future__ import annotations

import copy
import enum
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Annotated, Any

import msgspec

__all__ = [
    "CHANNELS",
    "EVENT_LEVELS",
    "FORMAT_VERSION",
    "METADATA_NAME",
    "RECORD_TYPES",
    "Breath",
    "ChannelSpec",
    "Config",
    "DeviceStatus",
    "Estimate",
    "Evaluation",
    "EventLevel",
    "ForceFeedback",
    "Incumbent",
    "Log",
    "OptimizerState",
    "ProfileAck",
    "ProfileSent",
    "ProfileTable",
    "Proposal",
    "Record",
    "Rejects",
    "StopDecision",
    "Timestamp",
    "Topic",
    "event_level",
    "json_schema",
]

FORMAT_VERSION = 9
"""Version of the log format (channels, their records and schemas).

Stored in ``/config`` and the ``hilbo.session`` metadata. Bump it whenever the writer's output
changes (a field, a schema, what a value means); ``tests/bridge/test_log_golden.py`` fails
otherwise, and a golden file of the new version goes to ``tests/data/logs/v<N>/``.

* 1: hand-written JSON schemas; every event level INFO.
* 2: records and schemas generated from the msgspec types of this module; ``/events`` levels by
  kind (:data:`EVENT_LEVELS`); a device's latched fault and its clearing are ``/events``.
  The record fields are those of version 1, so version-1 logs decode into these types.
* 3: the optimizer state in ``/optimizer_state`` gains the sound rule's ``accept_z`` (None: off)
  and evaluations may end with reason ``"decided"``; ``/events`` has ``loop_stall`` (a warning);
  a session's last ``/optimizer_state`` has reason ``"end"`` (what its summary recommends from).
  Older states read with ``accept_z`` None.
* 4: the optimizer state gains the confirmation of the recommendation (``confirm``,
  ``confirm_from``, ``confirm_requested``), the config ``explore_rel_sd`` and ``ei_best``, and loses
  ``remeasure_best_s``; the recommendation may be ``"global"``; evaluations may end with reason
  ``"precise"``; ``/events`` has ``confirmation``. Older states read without a confirmation.
* 5: the optimizer config gains the sound rule's sequential boundary ``boundary_s`` (s) and the
  stopping rule may be ``"sound-floor"`` (the fixed-clock rule that ``"sound"`` was up to 4).
  Older states read with ``boundary_s`` 60 s, which leaves their rule as it was: their
  ``min_decision_s`` (60 s) is at or past the boundary, where its factor is 1.
* 6: the optimizer config gains the opt-in trust region for EI's candidates (``trust_region``,
  ``trust_region_alternate``). Older states read without one (None, False): as they ran.
* 7: evaluations (``/observations`` and the optimizer state's) gain ``drift_var``, the
  estimator's model-error share of their variance; the optimizer config gains the opt-in
  ``drift_corr_s``, ``acquisition`` (``"ei"``, the only one before, or a knowledge gradient) and
  ``kg_from_s``, and its state ``drift_now_w``. Older states read without them (None, "ei", 0):
  as they ran.
* 8: the optimizer config gains ``prior_mean_sd``, the GP's constant prior mean (0.5 SDs above
  the observations' average with the sound rules). Older states read with 0, the average: as
  they ran.
* 9: the optimizer config gains ``gp_prior_max_share``, the GP's largest share of the sound
  rule's stop decision (0.5). Older states read with 1, the plain product: as they ran.
"""

READABLE_VERSIONS = frozenset({1, 2, 3, 4, 5, 6, 7, 8, 9})
"""Format versions the readers open."""

METADATA_NAME = "hilbo.session"
"""Name of the MCAP metadata record that marks a hilbo session log."""


class Topic(enum.StrEnum):
    """The channels of a session log."""

    CONFIG = "/config"
    BREATHS = "/breaths"
    ESTIMATOR = "/estimator"
    STOPPING = "/stopping"
    PROPOSALS = "/proposals"
    OBSERVATIONS = "/observations"
    OPTIMIZER_STATE = "/optimizer_state"
    PROFILES_SENT = "/profiles_sent"
    ACKS = "/acks"
    FORCE_FEEDBACK = "/force_feedback"
    DEVICE_STATUS = "/device_status"
    EVENTS = "/events"
    REJECTS = "/rejects"


class EventLevel(enum.IntEnum):
    """Severity of an ``/events`` message (the values of ``foxglove.LogLevel``)."""

    UNKNOWN = 0
    DEBUG = 1
    INFO = 2
    WARNING = 3
    ERROR = 4
    FATAL = 5


# Levels by event kind (the runtime calls log_event(kind, text) and the log layer picks the level,
# so Foxglove's Log panel and the review colour pauses, refusals and faults). A kind not listed
# gets a level from its name (_LEVEL_WORDS), else INFO.
EVENT_LEVELS: Mapping[str, EventLevel] = {
    "session_start": EventLevel.INFO,
    "session_end": EventLevel.INFO,
    "resume": EventLevel.INFO,
    "auto_resume": EventLevel.INFO,
    "resumed": EventLevel.INFO,
    "bout_pause": EventLevel.INFO,
    "budget_spent": EventLevel.INFO,
    "prior": EventLevel.INFO,
    "gc": EventLevel.DEBUG,
    "fault_cleared": EventLevel.INFO,
    "device_fault_cleared": EventLevel.INFO,
    "pause": EventLevel.WARNING,
    "watchdog_pause": EventLevel.WARNING,
    "resume_refused": EventLevel.WARNING,
    "assistance_off": EventLevel.WARNING,
    "evaluation_cancelled": EventLevel.WARNING,
    "unsafe_proposal": EventLevel.WARNING,
    "profile_rejected": EventLevel.WARNING,
    "fit_ahead_failed": EventLevel.WARNING,
    "cart_ended": EventLevel.WARNING,
    "cart_stale": EventLevel.WARNING,
    "clock_reset": EventLevel.WARNING,
    "time_jump": EventLevel.WARNING,
    "stale_ack": EventLevel.WARNING,
    "early_ack": EventLevel.WARNING,
    "loop_stall": EventLevel.WARNING,
    "console_lost": EventLevel.WARNING,
    "heartbeat_lost": EventLevel.ERROR,
    "device_fault": EventLevel.ERROR,
    "fault": EventLevel.ERROR,
    "bus_error": EventLevel.ERROR,
    "assistance_off_failed": EventLevel.ERROR,
    "proposal_worker_lost": EventLevel.ERROR,
    "push_failed": EventLevel.ERROR,
    "emergency_stop": EventLevel.FATAL,
}
"""The ``foxglove.Log`` level of each known event kind."""

_LEVEL_WORDS = (
    (("fatal", "emergency"), EventLevel.FATAL),
    (("error", "failed", "failure", "lost", "fault"), EventLevel.ERROR),
    (("refused", "rejected", "pause", "cancel", "stale", "warning", "unsafe", "timeout"), EventLevel.WARNING),
)


def event_level(kind: str) -> EventLevel:
    """The level of an event kind: :data:`EVENT_LEVELS`, else by the words in it, else INFO.

    Args:
        kind: The machine-readable event kind (``pause``, ``bus_error``, ...).

    Returns:
        The ``foxglove.Log`` level.
    """
    level = EVENT_LEVELS.get(kind)
    if level is not None:
        return level
    low = kind.lower()
    for words, lv in _LEVEL_WORDS:
        if any(w in low for w in words):
            return lv
    return EventLevel.INFO


# ---------------------------------------------------------------------------------- field types
def _d(description: str, **constraints: Any) -> msgspec.Meta:
    return msgspec.Meta(description=description, **constraints)


_PARAMS_DESC = "The setting, {parameter name: value in its unit} (derived parameters included)"
# The params objects are marked so json_schema() can name the optimised parameters in them.
Params = Annotated[dict[str, float], msgspec.Meta(description=_PARAMS_DESC,
                                                  extra_json_schema={"x-hilbo-params": True})]
TS = Annotated[float, _d("Breath time in s on the cart's clock (the session's time base)")]
Index = Annotated[int, _d("0-based evaluation number (the index the evaluation gets when it completes)",
                          ge=0)]
BreathIndex = Annotated[int, _d("0-based breath index within the evaluation", ge=0)]
Phase = Annotated[str, _d("Phase of Algorithm 1: exploration, optimization or done")]
NonNegInt = Annotated[int, msgspec.Meta(ge=0)]


class _Record(msgspec.Struct, omit_defaults=True, kw_only=True):
    """Base of the channel records: optional fields (default None) are omitted from the JSON."""


class Config(_Record, kw_only=True):
    """The session's identity and configuration; the first message of the file."""

    session_id: Annotated[str, _d("Session id, the same in every file of a resumed session")]
    previous_log: Annotated[str | None, _d("Path of the log this session resumes (absent if new)")] = None
    resumed: Annotated[bool, _d("True when this file continues a crashed session")]
    config: Annotated[dict[str, Any], _d("The session config as loaded (TOML as JSON)")]
    param_names: Annotated[list[str], _d("Names of the optimised parameters")]
    hilbo_version: Annotated[str, _d("hilbo package version")]
    format_version: Annotated[int, _d("Version of the log format (bridge.log.FORMAT_VERSION)", ge=1)]
    started_unix_ns: Annotated[int, _d("Wall clock when the log was opened, ns since 1970", ge=0)]


class Breath(_Record, kw_only=True):
    """One breath as the cart reported it (every breath: warm-up, pauses and gaps included)."""

    t_s: TS
    vo2_ml_min: Annotated[float, _d("Oxygen uptake in ml/min")]
    vco2_ml_min: Annotated[float, _d("Carbon-dioxide output in ml/min")]
    ve_l_min: Annotated[float | None, _d("Minute ventilation in l/min (absent if not reported)")] = None
    rer: Annotated[float | None, _d("Respiratory exchange ratio (absent if not reported)")] = None
    hr_bpm: Annotated[float | None, _d("Heart rate in beats/min (absent if not reported)")] = None
    watts: Annotated[float, _d("Metabolic power in W by Brockway's equation")]


class Estimate(_Record, kw_only=True):
    """A breath fed to the optimizer and the estimator's state after it; resume replays these."""

    index: Index
    breath: BreathIndex
    t_s: Annotated[float | None, _d("Breath time in s on the cart's clock (absent if unknown)")] = None
    t_setting_s: Annotated[float, _d("Seconds since the setting was applied (what the optimizer got)")]
    watts: Annotated[float, _d("Metabolic power in W fed to the optimizer")]
    mean_w: Annotated[float, _d("Estimated steady-state cost of the setting in W")]
    var_w2: Annotated[float, _d("Variance of that estimate in W²")]
    sd_w: Annotated[float | None, _d("Standard deviation of that estimate in W")] = None
    lo95_w: Annotated[float | None, _d("mean − 1.96·sd in W (lower edge of the plotted band)")] = None
    hi95_w: Annotated[float | None, _d("mean + 1.96·sd in W (upper edge of the plotted band)")] = None
    phase: Annotated[str | None, _d("Phase of Algorithm 1: exploration, optimization or done")] = None


# Its docstring is the schema's description in every log ("seed 000" = Kim et al. 2019): it
# changes with FORMAT_VERSION only.
class StopDecision(_Record, kw_only=True):
    """The stopping rule's decision after a breath (optimisation phase, seed 000 §II.D)."""

    index: Index
    breath: BreathIndex
    t_s: Annotated[float | None, _d("Breath time in s on the cart's clock (absent if unknown)")] = None
    stop: Annotated[bool, _d("True when the evaluation ends with this breath")]
    reason: Annotated[str, _d("continue, threshold, max_measurements or budget")]
    z: Annotated[float | None, _d("(μ − μ*)/σ, standardised distance from the incumbent "
                                  "(positive = worse)")] = None
    threshold: Annotated[float | None, _d("A_i, the threshold at this breath (absent for the fixed "
                                          "rule)")] = None
    incumbent_mean_w: Annotated[float | None, _d("μ*, the incumbent's estimated cost in W")] = None
    incumbent_var_w2: Annotated[float | None, _d("σ*², the incumbent's variance in W²")] = None


class Incumbent(_Record, kw_only=True):
    """The stopping rule's x* when proposed."""

    params: Params
    mean: Annotated[float, _d("μ* in W")]
    var: Annotated[float, _d("σ*² in W²")]


class Proposal(_Record, kw_only=True):
    """A setting the optimizer asked for (one per ask(); a re-ask after a cancel repeats the index)."""

    index: Index
    params: Params
    phase: Phase
    t_s: Annotated[float | None, _d("Breath time in s of the last breath before the ask")] = None
    incumbent: Annotated[Incumbent | None, _d("The stopping rule's x* when proposed")] = None
    compute_ms: Annotated[float | None, _d("Wall time of ask() itself in the proposal worker, ms")] = None
    total_ms: Annotated[float | None, _d("Wall time of the whole ask as the session saw it (moving the "
                                         "optimizer to the worker and back included), ms")] = None
    to_worker_ms: Annotated[float | None, _d("From the start of the ask to the worker starting on it, "
                                             "ms")] = None
    from_worker_ms: Annotated[float | None, _d("From the worker's end of ask() to the result in the "
                                               "session's event loop, ms")] = None
    worker: Annotated[str | None, _d("Where ask() ran: process or thread")] = None


class Evaluation(_Record, kw_only=True):
    """A completed evaluation (what the GP is told)."""

    index: Index
    params: Params
    mean: Annotated[float, _d("Estimated steady-state cost at the end, W")]
    var: Annotated[float, _d("Its variance, W²")]
    breaths: Annotated[int, _d("Breaths measured", ge=0)]
    duration_s: Annotated[float, _d("Breath time from the setting's start to its last breath, s")]
    phase: Phase
    stopped_early: Annotated[bool, _d("Stopped by the σ-scaled rule before N breaths")]
    reason: Annotated[str, _d("threshold, max_measurements, budget or told")]
    t_start: Annotated[float | None, _d("Session time when the setting was applied, s")] = None
    t_end: Annotated[float | None, _d("Session time of its last breath, s")] = None
    obs_mean: Annotated[float | None, _d(
        "Data-only mean the GP is told (the posterior with the estimator's prior on c divided "
        "out), W; absent: mean")] = None
    obs_var: Annotated[float | None, _d("Its variance, W²; absent: var")] = None
    drift_var: Annotated[float | None, _d(
        "The estimator's model-error (steady-state drift) share of obs_var, W²; absent: "
        "none known")] = None


class OptimizerState(_Record, kw_only=True):
    """A full HILOptimizer.to_json() snapshot (after each evaluation and at start); resume starts here."""

    state: Annotated[dict[str, Any], _d("HILOptimizer.to_json(): space, config, RNG state, evaluations, "
                                        "traces, ...")]
    reason: Annotated[str | None, _d("Why the snapshot was taken: start, evaluation, cancel, budget, "
                                     "resume, end")] = None
    n_evaluations: Annotated[int, _d("Completed evaluations in the snapshot", ge=0)] | None = None
    thresholds: Annotated[list[float] | None, _d("Algorithm 2's threshold vector A over breath index "
                                                 "(after exploration)")] = None


class ProfileTable(_Record, kw_only=True):
    """One actuator's table."""

    actuator: Annotated[str, _d("Load path (hip, ankle)")]
    gait_pct: Annotated[list[float], _d("Gait-cycle positions, %")]
    force_n: Annotated[list[float], _d("Desired force, N")]


class ProfileSent(_Record, kw_only=True):
    """A force profile pushed to the device (after the safety limits admitted it)."""

    version: Annotated[int, _d("Profile version on the bus, 1..255", ge=0)]
    n_points: Annotated[int, _d("Points in the transmitted table", ge=0)]
    crc32: Annotated[int, _d("CRC-32 of the table as committed", ge=0)] | None = None
    index: Annotated[int, _d("0-based evaluation number the profile measures", ge=0)] | None = None
    params: Params | None = None
    force_n: Annotated[list[float], _d("The transmitted table (all actuators concatenated), N")]
    profiles: Annotated[list[ProfileTable], _d("Per-actuator tables")]
    t_s: Annotated[float | None, _d("Breath time in s of the last breath before the push")] = None


class ProfileAck(_Record, kw_only=True):
    """The device's answer to a profile commit (or the push's failure)."""

    version: Annotated[int, _d("Profile version answered", ge=0)]
    accepted: Annotated[bool, _d("True for an ack")]
    reason: Annotated[str, _d("Nack reason, lower case (none for an ack)")]
    detail: Annotated[int, _d("Reason-specific detail", ge=0)]
    attempts: Annotated[int, _d("Transfers needed", ge=0)] | None = None
    elapsed_s: Annotated[float | None, _d("Time from the first segment to the ack, s")] = None
    crc32: Annotated[int, _d("CRC-32 acknowledged", ge=0)] | None = None
    error: Annotated[str | None, _d("Why the push failed, if it did")] = None


class ForceFeedback(_Record, kw_only=True):
    """Desired vs measured force of one actuator; a batch of controller samples per message."""

    actuator: Annotated[int, _d("Actuator number", ge=0)]
    n: Annotated[int, _d("Samples in this batch", ge=0)]
    desired_n: Annotated[list[float], _d("Desired force of the active profile, N")]
    measured_n: Annotated[list[float], _d("Measured cable force, N")]
    gait_phase_pct: Annotated[list[float] | None, _d("Gait phase of each sample, % (−1 = unknown)")] = None
    profile_version: Annotated[int, _d("Active profile version", ge=0)] | None = None
    desired_mean_n: Annotated[float | None, _d("Mean desired force of the batch, N (for plotting)")] = None
    measured_mean_n: Annotated[float | None, _d("Mean measured force of the batch, N (for plotting)")] = None


class DeviceStatus(_Record, kw_only=True):
    """Device status/heartbeat of one actuator (logged on change and periodically)."""

    actuator: Annotated[int, _d("Actuator number", ge=0)]
    mode: Annotated[str, _d("Operating mode, lower case (off, assist, transparent, ...)")]
    faults: Annotated[int, _d("Active fault bits", ge=0)]
    fault_names: Annotated[list[str] | None, _d("Names of the active faults")] = None
    gait_phase_pct: Annotated[float | None, _d("Gait phase, % (absent if unknown)")] = None
    profile_version_active: Annotated[int, _d("Version being executed, 0 = none", ge=0)]
    profile_version_pending: Annotated[int, _d("Version waiting for the gait boundary", ge=0)]


class Timestamp(_Record, kw_only=True):
    """Log time of the event."""

    sec: Annotated[int, _d("seconds", ge=0)]
    nsec: Annotated[int, _d("nanoseconds", ge=0, le=999_999_999)]


class Log(_Record, kw_only=True):
    """A session event (pause, resume, assistance off, fault...), shown by Foxglove's Log panel."""

    timestamp: Annotated[Timestamp, _d("Log time of the event")]
    level: Annotated[EventLevel, _d("Severity")]
    message: Annotated[str, _d("Human-readable text")]
    name: Annotated[str, _d("Component (hilbo)")]
    file: Annotated[str, _d("Unused (empty)")]
    line: Annotated[int, _d("Unused (0)", ge=0)]
    kind: Annotated[str, _d("Machine-readable event kind (pause, resume, assistance_off...)")]
    t_s: Annotated[float | None, _d("Breath time in s on the cart's clock (absent if unknown)")] = None
    details: Annotated[dict[str, Any] | None, _d("Event-specific values")] = None


class Rejects(_Record, kw_only=True):
    """Cumulative counts of rejected records or frames by reason."""

    source: Annotated[str, _d("Where they were rejected: cart, can")]
    counts: Annotated[dict[str, int], _d("{reason: count}")]
    total: Annotated[int, _d("Sum of the counts", ge=0)]
    t_s: Annotated[float | None, _d("Breath time in s on the cart's clock (absent if unknown)")] = None


Record = (Config | Breath | Estimate | StopDecision | Proposal | Evaluation | OptimizerState | ProfileSent
          | ProfileAck | ForceFeedback | DeviceStatus | Log | Rejects)
"""Any channel record."""


# ---------------------------------------------------------------------------------- channels
@dataclass(frozen=True)
class ChannelSpec:
    """One channel: its topic, record type, schema name and time base.

    Attributes:
        topic: MCAP topic.
        record_type: The msgspec Struct of its messages.
        schema_name: Schema name (``hilbo.*``, or ``foxglove.Log`` for events).
        time_base: ``"breath"`` when publish_time is the breath-time base, else ``"log"``.
    """

    topic: str
    record_type: type[msgspec.Struct]
    schema_name: str
    time_base: str = "log"

    @property
    def description(self) -> str:
        """What one message is (the record type's docstring)."""
        return (self.record_type.__doc__ or "").strip().rstrip(".")

    def json_schema(self, param_names: Sequence[str] = ()) -> dict[str, Any]:
        """The draft-07 JSON schema (generated); ``params`` objects name ``param_names`` when given."""
        return json_schema(self, param_names)

    @property
    def properties(self) -> Mapping[str, Mapping[str, Any]]:
        """The JSON-schema properties of the message object."""
        return self.json_schema()["properties"]

    @property
    def required(self) -> tuple[str, ...]:
        """Keys every message has."""
        return tuple(self.json_schema()["required"])


_CHANNEL_LIST = (
    ChannelSpec(Topic.CONFIG, Config, "hilbo.Config"),
    ChannelSpec(Topic.BREATHS, Breath, "hilbo.Breath", "breath"),
    ChannelSpec(Topic.ESTIMATOR, Estimate, "hilbo.Estimate", "breath"),
    ChannelSpec(Topic.STOPPING, StopDecision, "hilbo.StopDecision", "breath"),
    ChannelSpec(Topic.PROPOSALS, Proposal, "hilbo.Proposal"),
    ChannelSpec(Topic.OBSERVATIONS, Evaluation, "hilbo.Evaluation", "breath"),
    ChannelSpec(Topic.OPTIMIZER_STATE, OptimizerState, "hilbo.OptimizerState", "breath"),
    ChannelSpec(Topic.PROFILES_SENT, ProfileSent, "hilbo.ProfileSent"),
    ChannelSpec(Topic.ACKS, ProfileAck, "hilbo.ProfileAck"),
    ChannelSpec(Topic.FORCE_FEEDBACK, ForceFeedback, "hilbo.ForceFeedback"),
    ChannelSpec(Topic.DEVICE_STATUS, DeviceStatus, "hilbo.DeviceStatus"),
    ChannelSpec(Topic.EVENTS, Log, "foxglove.Log"),
    ChannelSpec(Topic.REJECTS, Rejects, "hilbo.Rejects"),
)

CHANNELS: Mapping[str, ChannelSpec] = {spec.topic: spec for spec in _CHANNEL_LIST}
"""Every channel of a session log by topic."""

RECORD_TYPES: Mapping[str, type[msgspec.Struct]] = {spec.topic: spec.record_type for spec in _CHANNEL_LIST}
"""The record type of each channel by topic."""


# ---------------------------------------------------------------------------------- schemas
_INT_ENUMS = {EventLevel.__name__: (EventLevel, "foxglove.LogLevel")}
_SCHEMA_CACHE: dict[tuple[str, tuple[str, ...]], dict[str, Any]] = {}


def _shape(node: Any, defs: Mapping[str, Any], names: Sequence[str]) -> Any:
    """msgspec's schema → what Foxglove's parser accepts (see the module docstring)."""
    if isinstance(node, list):
        return [_shape(v, defs, names) for v in node]
    if not isinstance(node, dict):
        return node
    out = dict(node)
    out.pop("default", None)
    if "$ref" in out:
        name = out.pop("$ref").rsplit("/", 1)[-1]
        target = dict(defs[name])
        if name in _INT_ENUMS:
            enum_type, title = _INT_ENUMS[name]
            target = {"title": title, "oneOf": [{"title": m.name, "const": int(m)} for m in enum_type]}
        else:
            target.pop("title", None)
        if "description" in out:
            target.pop("description", None)
        out = {**target, **out}
    if "anyOf" in out:
        alts = [a for a in out.pop("anyOf") if a.get("type") != "null"]
        if len(alts) != 1:
            raise TypeError(f"a log record field has several non-null types: {alts}")
        out = {**_shape(alts[0], defs, names), **out}
    for key in ("items", "additionalProperties"):
        if isinstance(out.get(key), dict):
            out[key] = _shape(out[key], defs, names)
    if isinstance(out.get("properties"), dict):
        out["properties"] = {k: _shape(v, defs, names) for k, v in out["properties"].items()}
    if out.pop("x-hilbo-params", False):
        out["properties"] = {n: {"type": "number", "description": f"parameter {n}"} for n in names}
    if out.get("type") == "object" and "properties" not in out:
        # Foxglove's JSON-schema parser iterates "properties" of every object: always list it.
        out["properties"] = {}
    return out


def json_schema(spec: ChannelSpec, param_names: Sequence[str] = ()) -> dict[str, Any]:
    """The draft-07 JSON schema of a channel, generated from its record type.

    Args:
        spec: The channel.
        param_names: Names of the optimised parameters; the ``params`` objects list them so
            Foxglove offers them for plotting.

    Returns:
        A fresh JSON-able schema dict.
    """
    key = (spec.topic, tuple(param_names))
    cached = _SCHEMA_CACHE.get(key)
    if cached is None:
        (ref,), defs = msgspec.json.schema_components([spec.record_type],
                                                      ref_template="#/$defs/{name}")
        name = ref["$ref"].rsplit("/", 1)[-1]
        body = _shape(dict(defs[name]), defs, tuple(param_names))
        body.pop("title", None)
        body.pop("description", None)
        base = "breath-time base" if spec.time_base == "breath" else "log time"
        cached = {
            "$schema": "http://json-schema.org/draft-07/schema#",
            "title": spec.schema_name,
            "description": f"{spec.description} (publish_time: {base})",
            **body,
        }
        cached.setdefault("required", [])
        _SCHEMA_CACHE[key] = cached
    return copy.deepcopy(cached)
