"""bridge.log: the session log writer, its channels and JSON schemas."""

from __future__ import annotations

import json
import math
import shutil
import subprocess
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from mcap.decoder import DecoderFactory
from mcap.reader import make_reader
from mcap.records import Schema

from bridge.errors import BridgeError
from bridge.log import (
    CHANNELS,
    METADATA_NAME,
    EventLevel,
    LogError,
    LogStateError,
    LogValueError,
    LogWriteError,
    SessionLog,
    Topic,
    check_message,
    new_session_id,
)
from bridge.log.reader import read_log
from drivers.exosuit.codec import DeviceFault, DeviceMode, NackReason
from hilbo_core.metabolic import GaussianProductEstimator
from hilbo_core.optimizer import HILOptimizer
from hilbo_core.presets import hip_6d
from hilbo_core.profiles import build_profile
from hilbo_core.types import BreathRecord

PARAM_NAMES = list(hip_6d().names)


class _Clock:
    """A fake log-time clock: 1 ms per call from a fixed epoch."""

    def __init__(self) -> None:
        self.ns = 1_700_000_000_000_000_000

    def __call__(self) -> int:
        self.ns += 1_000_000
        return self.ns


class JsonDecoderFactory(DecoderFactory):
    """The decoder an mcap user would write for our channels."""

    def decoder_for(self, message_encoding: str, schema: Schema | None):  # type: ignore[override]
        return json.loads if message_encoding == "json" else None


def _optimizer() -> HILOptimizer:
    return HILOptimizer(hip_6d(), n_explore=2, max_breaths=3, window=1, budget_breaths=4, seed=1,
                        n_candidates=32, n_local=0,
                        estimator_factory=lambda: GaussianProductEstimator(400.0, 1e4, 1600.0))


def write_every_channel(path: Path) -> SessionLog:
    """A small session touching every channel through the typed methods; returns the closed log."""
    opt = _optimizer()
    space = hip_6d()
    with SessionLog(path, session_id="sess-1", config_json={"protocol": {"n_explore": 2}},
                    previous_log="/old/run.mcap", param_names=PARAM_NAMES, clock_ns=_Clock(),
                    flush_interval_s=None) as log:
        log.log_optimizer_state(opt, reason="start")
        for k in range(3):
            params = opt.ask()
            log.log_proposal(params, index=k, phase=opt.phase.value, t_s=10.0 * k,
                             incumbent=opt.incumbent)
            profiles = build_profile(space.name, params)
            log.log_profile_sent(profiles, version=k + 1, crc32=123456 + k, index=k, params=params)
            log.log_ack(version=k + 1, accepted=True, attempts=1, elapsed_s=0.012, crc32=123456 + k)
            b = 0
            while True:
                rec = BreathRecord(t_s=100.0 + 10 * k + b, vo2_ml_min=1000.0 + b, vco2_ml_min=900.0,
                                   hr_bpm=110.0 if b % 2 else None)
                log.log_breath(rec)
                t = 3.0 * (b + 1)
                step = opt.observe_breath(t, rec.watts)
                log.log_step(step, index=k, t_setting_s=t, watts=rec.watts, t_s=rec.t_s,
                             incumbent=opt.incumbent)
                b += 1
                if step.stop:
                    log.log_observation(step.evaluation, t_start=10.0 * k, t_end=10.0 * k + b, t_s=rec.t_s)
                    log.log_optimizer_state(opt, reason="evaluation", t_s=rec.t_s)
                    break
        log.log_ack(version=9, accepted=False, reason=NackReason.BAD_CRC, detail=3)
        log.log_force_feedback(actuator=0, desired_n=[10.0, 20.0], measured_n=[9.5, 21.0],
                               gait_phase_pct=[1.0, None], profile_version=1)
        log.log_device_status(actuator=1, mode=DeviceMode.ASSIST,
                              faults=DeviceFault.OVERCURRENT | DeviceFault.ENCODER, gait_phase_pct=40.5,
                              profile_version_active=1, profile_version_pending=2)
        log.log_event("pause", "operator pause", level=EventLevel.WARNING, t_s=123.0, by="operator")
        log.log_rejects("cart", {"bad_crc": 2, "impossible": 1}, t_s=124.0)
    return log


@pytest.fixture(scope="module")
def every_channel(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, SessionLog]:
    path = tmp_path_factory.mktemp("log") / "session.mcap"
    return path, write_every_channel(path)


def test_error_roots() -> None:
    assert issubclass(LogError, BridgeError)
    assert issubclass(LogValueError, ValueError) and issubclass(LogWriteError, OSError)
    assert issubclass(LogStateError, RuntimeError)


def test_every_channel_round_trips_and_matches_its_schema(every_channel) -> None:
    path, log = every_channel
    contents = read_log(path)
    assert contents.complete and contents.unreadable_bytes == 0
    assert set(contents.channels) == set(CHANNELS)
    counts = {t: len(contents.topic(t)) for t in CHANNELS}
    assert counts == dict(log.stats.per_topic)
    assert all(n > 0 for n in counts.values()), counts
    for topic, info in contents.channels.items():
        assert info.schema_name == CHANNELS[topic].schema_name and info.message_encoding == "json"
        for msg in contents.topic(topic):
            assert check_message(info.schema, msg.data) == [], (topic, msg.data)
    # The file order is the write order: one global sequence.
    assert [m.sequence for m in contents.messages] == list(range(len(contents.messages)))


def test_values_survive_exactly(every_channel) -> None:
    contents = read_log(every_channel[0])
    breaths = contents.data(Topic.BREATHS)
    assert breaths[0] == {"t_s": 100.0, "vo2_ml_min": 1000.0, "vco2_ml_min": 900.0,
                          "watts": BreathRecord(100.0, 1000.0, 900.0).watts}  # None fields omitted
    assert breaths[1]["hr_bpm"] == 110.0
    est = contents.data(Topic.ESTIMATOR)[0]
    assert est["sd_w"] == pytest.approx(math.sqrt(est["var_w2"]))
    assert est["lo95_w"] == pytest.approx(est["mean_w"] - 1.96 * est["sd_w"])
    fb = contents.data(Topic.FORCE_FEEDBACK)[0]
    assert fb["gait_phase_pct"] == [1.0, -1.0] and fb["desired_mean_n"] == 15.0
    st = contents.data(Topic.DEVICE_STATUS)[0]
    assert st["mode"] == "assist" and st["faults"] == 0b1001
    assert st["fault_names"] == ["overcurrent", "encoder"]
    nack = contents.data(Topic.ACKS)[-1]
    assert nack["accepted"] is False and nack["reason"] == "bad_crc" and nack["detail"] == 3
    fault, ev = contents.data(Topic.EVENTS)
    assert ev["kind"] == "pause" and ev["message"] == "operator pause" and ev["level"] == 3
    assert ev["details"] == {"by": "operator"} and ev["name"] == "hilbo"
    # A latched device fault is an /events ERROR naming the faults.
    assert fault["kind"] == "device_fault" and fault["level"] == int(EventLevel.ERROR)
    assert fault["details"]["fault_names"] == ["overcurrent", "encoder"] and "overcurrent" in fault["message"]
    assert contents.data(Topic.REJECTS)[0]["total"] == 3
    obs = contents.data(Topic.OBSERVATIONS)
    snap = contents.data(Topic.OPTIMIZER_STATE)[-1]
    assert [o["index"] for o in obs] == [0, 1, 2]
    # (the log leaves out fields at their default, None)
    assert snap["state"]["evaluations"] == [{k: o.get(k) for k in snap["state"]["evaluations"][0]}
                                            for o in obs]


def test_time_stamps(every_channel) -> None:
    contents = read_log(every_channel[0])
    for m in contents.topic(Topic.BREATHS):
        assert m.publish_time_ns == round(m.data["t_s"] * 1e9)  # the breath-time base
    for m in contents.topic(Topic.PROFILES_SENT):
        assert m.publish_time_ns == m.log_time_ns
    log_times = [m.log_time_ns for m in contents.messages]
    assert log_times == sorted(log_times) and len(set(log_times)) == len(log_times)
    ev = contents.topic(Topic.EVENTS)[-1]
    assert ev.data["timestamp"] == {"sec": ev.log_time_ns // 10**9, "nsec": ev.log_time_ns % 10**9}


def test_session_link_in_config_and_metadata(every_channel) -> None:
    contents = read_log(every_channel[0])
    cfg = contents.data(Topic.CONFIG)
    assert len(cfg) == 1 and contents.messages[0].topic == Topic.CONFIG
    assert cfg[0]["session_id"] == "sess-1" and cfg[0]["resumed"] is True
    assert cfg[0]["config"] == {"protocol": {"n_explore": 2}} and cfg[0]["param_names"] == PARAM_NAMES
    assert contents.metadata[METADATA_NAME]["previous_log"] == "/old/run.mcap"
    assert contents.session_id == "sess-1" and contents.previous_log == "/old/run.mcap"
    assert contents.metadata[METADATA_NAME + ".end"]["clean_close"] == "true"


def test_the_mcap_package_reads_it(every_channel) -> None:
    path, log = every_channel
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[JsonDecoderFactory()])
        summary = reader.get_summary()
        assert summary is not None and summary.statistics.message_count == log.stats.messages
        decoded = [(c.topic, m.sequence, d)
                   for _, c, m, d in reader.iter_decoded_messages(log_time_order=False)]
        assert {s.encoding for s in summary.schemas.values()} == {"jsonschema"}
        meta = {m.name: m.metadata for m in reader.iter_metadata()}
    ours = [(m.topic, m.sequence, m.data) for m in read_log(path).messages]
    assert decoded == ours
    assert meta[METADATA_NAME]["session_id"] == "sess-1"


def _foxglove_problems(schema: dict[str, Any], where: str = "") -> list[str]:
    """What Foxglove's JSON-schema parser (parseJsonSchema) would refuse: it needs one type per
    field, 'properties' on every object, and array items of one non-array type."""
    problems = []
    if schema.get("type") != "object" or not isinstance(schema.get("properties"), dict):
        return [f"{where or 'root'}: object without properties"]
    for name, field in schema["properties"].items():
        path = f"{where}.{name}"
        if "oneOf" in field:
            if not all(isinstance(alt.get("const"), int) for alt in field["oneOf"]):
                problems.append(f"{path}: oneOf of non-numbers")
            continue
        kind = field.get("type")
        if kind not in ("boolean", "string", "number", "integer", "object", "array"):
            problems.append(f"{path}: type {kind!r}")
        elif kind == "object":
            problems += _foxglove_problems(field, path)
        elif kind == "array":
            items = field.get("items", {})
            if items.get("type") == "object":
                problems += _foxglove_problems(items, path + "[]")
            elif items.get("type") not in ("boolean", "string", "number", "integer"):
                problems.append(f"{path}: array items of type {items.get('type')!r}")
    return problems


@pytest.mark.parametrize("topic", sorted(CHANNELS))
def test_schemas_are_draft7_objects_foxglove_can_parse(topic: str) -> None:
    schema = CHANNELS[topic].json_schema(PARAM_NAMES)
    assert schema["$schema"] == "http://json-schema.org/draft-07/schema#"
    assert schema["title"] == CHANNELS[topic].schema_name
    assert set(schema["required"]) <= set(schema["properties"])
    assert _foxglove_problems(schema) == []
    for name, field in schema["properties"].items():
        assert field.get("description"), f"{topic}.{name} has no description"
    json.dumps(schema)  # JSON-able


def test_events_use_the_foxglove_log_schema() -> None:
    spec = CHANNELS[Topic.EVENTS]
    assert spec.schema_name == "foxglove.Log"
    assert {"timestamp", "level", "message", "name", "file", "line"} <= set(spec.required)
    levels = spec.properties["level"]["oneOf"]
    assert [(lv["title"], lv["const"]) for lv in levels] == [
        ("UNKNOWN", 0), ("DEBUG", 1), ("INFO", 2), ("WARNING", 3), ("ERROR", 4), ("FATAL", 5)]


def test_param_names_become_plottable_properties() -> None:
    schema = CHANNELS[Topic.PROPOSALS].json_schema(["a", "b"])
    assert set(schema["properties"]["params"]["properties"]) == {"a", "b"}
    assert CHANNELS[Topic.PROPOSALS].json_schema()["properties"]["params"]["properties"] == {}


@pytest.mark.skipif(shutil.which("python3") is None, reason="no system python3")
def test_schemas_and_messages_pass_a_real_json_schema_validator(every_channel, tmp_path: Path) -> None:
    """The system python has the jsonschema package (the venv need not): validate there."""
    probe = subprocess.run(["python3", "-c", "import jsonschema"], capture_output=True, check=False)
    if probe.returncode != 0:
        pytest.skip("jsonschema is not installed in the system python")
    contents = read_log(every_channel[0])
    cases = [{"schema": contents.channels[t].schema, "messages": contents.data(t)} for t in CHANNELS]
    (tmp_path / "cases.json").write_text(json.dumps(cases))
    code = (
        "import json, sys, jsonschema\n"
        "bad = []\n"
        "for case in json.load(open(sys.argv[1])):\n"
        "    v = jsonschema.Draft7Validator(case['schema'])\n"
        "    jsonschema.Draft7Validator.check_schema(case['schema'])\n"
        "    bad += [e.message for m in case['messages'] for e in v.iter_errors(m)]\n"
        "print(json.dumps(bad))\n"
    )
    out = subprocess.run(["python3", "-c", code, str(tmp_path / "cases.json")], capture_output=True,
                         text=True, check=True, timeout=60)
    assert json.loads(out.stdout) == []


@pytest.mark.parametrize(("message", "expected"), [
    ({"t_s": 1.0, "vo2_ml_min": 1.0, "vco2_ml_min": 1.0, "watts": 1.0}, []),
    ({"t_s": 1.0, "vo2_ml_min": 1.0, "vco2_ml_min": 1.0}, ["message: missing required key 'watts'"]),
    ({"t_s": "1", "vo2_ml_min": 1.0, "vco2_ml_min": 1.0, "watts": 1.0},
     ["message.t_s='1' is not of type number"]),
    ({"t_s": 1.0, "vo2_ml_min": True, "vco2_ml_min": 1.0, "watts": 1.0},
     ["message.vo2_ml_min=True is not of type number"]),
    ({"t_s": 1.0, "vo2_ml_min": 1.0, "vco2_ml_min": 1.0, "watts": 1.0, "hr_bpm": None},
     ["message.hr_bpm=None is not of type number"]),
])
def test_check_message_reference_cases(message: dict, expected: list[str]) -> None:
    assert check_message(CHANNELS[Topic.BREATHS].json_schema(), message) == expected


def test_check_message_nested_and_bounds() -> None:
    schema = CHANNELS[Topic.EVENTS].json_schema()
    msg = {"timestamp": {"sec": 1, "nsec": 2_000_000_000}, "level": 9, "message": "m", "name": "n",
           "file": "", "line": 0, "kind": "k"}
    assert check_message(schema, msg) == [
        "message.timestamp.nsec=2000000000 > maximum 999999999",
        "message.level=9 is not one of [0, 1, 2, 3, 4, 5]",
    ]
    rej = CHANNELS[Topic.REJECTS].json_schema()
    assert check_message(rej, {"source": "cart", "counts": {"x": 1.5}, "total": 1}) == [
        "message.counts.x=1.5 is not of type integer"]


def test_generic_log_cleans_values(tmp_path: Path) -> None:
    path = tmp_path / "g.mcap"
    with SessionLog(path, session_id="g", config_json="{\"a\": 1}", flush_interval_s=None) as log:
        log.log("/custom/topic", {"x": np.float64(1.5), "n": np.int64(3), "arr": np.arange(3),
                                  "nan": float("nan"), "none": None, "ok": True})
        log.log(Topic.STOPPING, {"index": 0, "breath": 1, "stop": False, "reason": "continue",
                                 "z": float("inf")})
        log.log(Topic.EVENTS, {"kind": "bus_error", "text": "CAN bus failed"})
    c = read_log(path)
    assert c.data("/custom/topic") == [{"x": 1.5, "n": 3, "arr": [0, 1, 2], "ok": True}]
    assert c.data(Topic.STOPPING) == [{"index": 0, "breath": 1, "stop": False, "reason": "continue"}]
    ev = c.data(Topic.EVENTS)[0]
    assert ev["message"] == "CAN bus failed" and ev["level"] == int(EventLevel.INFO)
    assert check_message(c.channels[Topic.EVENTS].schema, ev) == []
    assert c.channels["/custom/topic"].schema_name == "hilbo.Generic.custom.topic"
    assert c.config == {"a": 1}


def test_non_finite_optimizer_state_round_trips(tmp_path: Path) -> None:
    # Resume needs the snapshot exactly; JSON's NaN extension keeps it (json.loads reads it).
    path = tmp_path / "s.mcap"
    with SessionLog(path, session_id="s", config_json={}, flush_interval_s=None) as log:
        log.log(Topic.OPTIMIZER_STATE, {"state": {"x": [1.0, float("-inf")]}})
    [snap] = read_log(path).data(Topic.OPTIMIZER_STATE)
    assert snap["state"]["x"] == [1.0, float("-inf")]


@pytest.mark.parametrize(("kwargs", "match"), [
    ({"session_id": ""}, "session_id"),
    ({"flush_interval_s": 0}, "flush_interval_s"),
    ({"fsync_interval_s": float("nan")}, "fsync_interval_s"),
    ({"chunk_size": 10}, "chunk_size"),
    ({"compression": "gzip"}, "compression"),
    ({"config_json": "{not json"}, "config_json"),
    ({"config_json": [1, 2]}, "config_json"),
    ({"config_json": {"path": object()}}, "not JSON-serialisable"),
])
def test_bad_options_are_named(tmp_path: Path, kwargs: dict, match: str) -> None:
    opts = {"session_id": "s", "config_json": {}} | kwargs
    with pytest.raises(LogValueError, match=match):
        SessionLog(tmp_path / "x.mcap", **opts)
    assert not (tmp_path / "x.mcap").exists()  # nothing left behind to block a corrected retry


def test_bad_values_and_states(tmp_path: Path) -> None:
    path = tmp_path / "v.mcap"
    log = SessionLog(path, session_id="v", config_json={}, flush_interval_s=None)
    with pytest.raises(LogValueError, match=r"t_s=-1\.0"):
        log.log_breath(BreathRecord(t_s=-1.0, vo2_ml_min=1.0, vco2_ml_min=1.0))
    with pytest.raises(LogValueError, match="publish_time_ns=-5"):
        log.log("/breaths", {"t_s": 1.0}, -5)
    with pytest.raises(LogValueError, match="not JSON-serialisable"):
        log.log("/x", {"obj": object()})
    with pytest.raises(LogValueError, match="equal lengths"):
        log.log_force_feedback(actuator=0, desired_n=[1.0], measured_n=[])
    log.close()
    log.close()  # idempotent
    with pytest.raises(LogStateError, match="closed"):
        log.log_event("x", "after close")
    assert read_log(path).complete


def test_an_existing_log_is_never_overwritten(tmp_path: Path) -> None:
    path = tmp_path / "keep.mcap"
    path.write_bytes(b"precious")
    with pytest.raises(LogWriteError, match="cannot create"):
        SessionLog(path, session_id="k", config_json={})
    assert path.read_bytes() == b"precious"
    with SessionLog(path, session_id="k", config_json={}, overwrite=True, flush_interval_s=None):
        pass
    assert read_log(path).session_id == "k"


def test_high_rate_messages_are_left_to_the_timer(tmp_path: Path) -> None:
    path = tmp_path / "h.mcap"
    # An hour between timer flushes: nothing but the call itself could write in this test.
    with SessionLog(path, session_id="h", config_json={}, flush_interval_s=3600.0) as log:
        size0, flushes0 = path.stat().st_size, log.stats.flushes
        log.log_force_feedback(actuator=0, desired_n=[1.0], measured_n=[1.0])
        assert path.stat().st_size == size0 and log.stats.flushes == flushes0


def test_the_timer_flushes_pending_messages(tmp_path: Path) -> None:
    path = tmp_path / "t.mcap"
    with SessionLog(path, session_id="t", config_json={}, flush_interval_s=0.02) as log:
        size0 = path.stat().st_size
        # Left to the timer (the test above: not written by the call; here the timer may
        # already have run by the next line on a busy machine, so only the timer's work is checked).
        log.log_force_feedback(actuator=0, desired_n=[1.0], measured_n=[1.0])
        deadline = time.monotonic() + 5.0
        # The timer thread writes the chunk, then counts the flush (under the log's lock): a
        # reader outside the lock can see the bytes before the count, so wait for both.
        while (path.stat().st_size == size0 or log.stats.flushes < 2) and time.monotonic() < deadline:
            time.sleep(0.005)  # the flush timer is a wall-time thread by design: bounded poll
        assert path.stat().st_size > size0
        assert log.stats.flushes >= 2
        # Read while the writer is still open: the flushed part is a readable (truncated) log.
        live = read_log(path)
        assert live.truncated and live.unreadable_bytes == 0
        assert len(live.topic(Topic.FORCE_FEEDBACK)) == 1


def test_breath_level_messages_are_on_disk_when_the_call_returns(tmp_path: Path) -> None:
    path = tmp_path / "b.mcap"
    with SessionLog(path, session_id="b", config_json={}, flush_interval_s=None) as log:
        for i in range(3):
            log.log_breath(BreathRecord(t_s=float(i), vo2_ml_min=1.0, vco2_ml_min=1.0))
            assert len(read_log(path).topic(Topic.BREATHS)) == i + 1


def test_unchunked_mode_is_readable(tmp_path: Path) -> None:
    path = tmp_path / "u.mcap"
    with SessionLog(path, session_id="u", config_json={}, chunked=False, flush_interval_s=None) as log:
        log.log_breath(BreathRecord(t_s=1.0, vo2_ml_min=1.0, vco2_ml_min=1.0))
        log.flush(fsync=True)
        assert read_log(path).data(Topic.BREATHS)[0]["t_s"] == 1.0
    assert read_log(path).complete and log.stats.fsyncs == 1


def test_new_session_ids_are_unique_and_sortable() -> None:
    ids = [new_session_id() for _ in range(50)]
    assert len(set(ids)) == 50
    assert all(len(i) == len("20240101T000000Z-0123abcd") for i in ids)
