"""bridge.log.records: typed records round-trip through the writer and reader; event levels; file mode."""

from __future__ import annotations

import os
import stat
from pathlib import Path
from typing import Any

import msgspec
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from bridge.log import (
    CHANNELS,
    DEFAULT_FILE_MODE,
    RECORD_TYPES,
    EventLevel,
    LogValueError,
    SessionLog,
    Topic,
    check_message,
    event_level,
)
from bridge.log.reader import read_log

_TEXT = st.text(alphabet=st.characters(blacklist_categories=("Cs",)), max_size=12)
_FLOAT = st.floats(allow_nan=False, allow_infinity=False, width=64)
_JSON_SCALAR = st.none() | st.booleans() | st.integers(-2**53, 2**53) | _FLOAT | _TEXT
_JSON = st.recursive(_JSON_SCALAR, lambda inner: st.lists(inner, max_size=3)
                     | st.dictionaries(_TEXT, inner, max_size=3), max_leaves=8)


def _strategy(t: msgspec.inspect.Type) -> st.SearchStrategy[Any]:
    """A strategy for one msgspec type (the subset the records use)."""
    mi = msgspec.inspect
    if isinstance(t, mi.Metadata):
        return _strategy(t.type)
    if isinstance(t, mi.FloatType):
        return _FLOAT
    if isinstance(t, mi.BoolType):
        return st.booleans()
    if isinstance(t, mi.IntType):
        return st.integers(t.ge if t.ge is not None else -2**53, t.le if t.le is not None else 2**53)
    if isinstance(t, mi.StrType):
        return _TEXT
    if isinstance(t, mi.EnumType):
        return st.sampled_from(list(t.cls))
    if isinstance(t, mi.ListType):
        return st.lists(_strategy(t.item_type), max_size=4)
    if isinstance(t, mi.DictType):
        return st.dictionaries(_TEXT, _strategy(t.value_type), max_size=3)
    if isinstance(t, mi.AnyType):
        return _JSON
    if isinstance(t, mi.NoneType):
        return st.none()
    if isinstance(t, mi.UnionType):
        return st.one_of(*(_strategy(u) for u in t.types))
    if isinstance(t, mi.StructType):
        return st.builds(t.cls, **{f.name: _strategy(f.type) for f in t.fields})
    raise TypeError(f"no strategy for {t!r}")


def records_of(kind: type[msgspec.Struct]) -> st.SearchStrategy[Any]:
    return _strategy(msgspec.inspect.type_info(kind))


_ALL = st.fixed_dictionaries({topic: records_of(kind) for topic, kind in RECORD_TYPES.items()})


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(records=_ALL)
def test_every_record_type_round_trips_through_the_log(tmp_path: Path, records: dict[str, Any]) -> None:
    path = tmp_path / "rt.mcap"
    path.unlink(missing_ok=True)
    with SessionLog(path, session_id="rt", config_json={}, flush_interval_s=None) as log:
        for topic, record in records.items():
            log.log_record(topic, record)
    c = read_log(path)
    assert c.invalid == 0
    for topic, record in records.items():
        assert c.records(topic)[-1] == record, topic
        # Every written message conforms to its channel's generated schema.
        assert check_message(c.channels[topic].schema, c.topic(topic)[-1].data) == [], topic


@pytest.mark.parametrize("topic", sorted(CHANNELS))
def test_the_schemas_are_generated_from_the_record_types(topic: str) -> None:
    schema = CHANNELS[topic].json_schema()
    fields = {f.encode_name: f for f in msgspec.structs.fields(RECORD_TYPES[topic])}
    assert set(schema["properties"]) == set(fields)
    assert set(schema["required"]) == {n for n, f in fields.items() if f.required}


@pytest.mark.parametrize(("kind", "level"), [
    ("pause", EventLevel.WARNING), ("resume_refused", EventLevel.WARNING),
    ("heartbeat_lost", EventLevel.ERROR), ("bus_error", EventLevel.ERROR),
    ("device_fault", EventLevel.ERROR), ("assistance_off_failed", EventLevel.ERROR),
    ("resume", EventLevel.INFO), ("session_start", EventLevel.INFO), ("gc", EventLevel.DEBUG),
    # Kinds the table does not list get a level from their words, else INFO.
    ("cart_restart_refused", EventLevel.WARNING), ("lsl_stream_lost", EventLevel.ERROR),
    ("something_new", EventLevel.INFO),
])
def test_event_levels_by_kind(kind: str, level: EventLevel) -> None:
    assert event_level(kind) is level


def test_log_event_takes_the_level_from_the_kind_unless_given(tmp_path: Path) -> None:
    path = tmp_path / "ev.mcap"
    with SessionLog(path, session_id="ev", config_json={}, flush_interval_s=None) as log:
        log.log_event("pause", "heartbeat lost: assistance off")
        log.log_event("heartbeat_lost", "device 0 heartbeat lost")
        log.log_event("pause", "explicit", level=EventLevel.FATAL)
        with pytest.raises(LogValueError, match="level=9"):
            log.log_event("x", "bad level", level=9)
    levels = [(e.kind, e.level) for e in read_log(path).records(Topic.EVENTS)]
    assert levels == [("pause", EventLevel.WARNING), ("heartbeat_lost", EventLevel.ERROR),
                      ("pause", EventLevel.FATAL)]


def test_a_latched_fault_and_its_clearing_are_events(tmp_path: Path) -> None:
    from drivers.exosuit.codec import DeviceFault

    path = tmp_path / "f.mcap"
    with SessionLog(path, session_id="f", config_json={}, flush_interval_s=None) as log:
        for faults in (0, DeviceFault.HEARTBEAT_LOST, DeviceFault.HEARTBEAT_LOST, DeviceFault(0)):
            log.log_device_status(actuator=1, mode="off", faults=faults)
    events = read_log(path).records(Topic.EVENTS)
    assert [(e.kind, e.level) for e in events] == [("device_fault", EventLevel.ERROR),
                                                   ("device_fault_cleared", EventLevel.INFO)]
    assert "heartbeat_lost" in events[0].message and events[0].details["fault_names"] == ["heartbeat_lost"]


@pytest.fixture
def umask_zero():
    old = os.umask(0)
    try:
        yield
    finally:
        os.umask(old)


def _mode(path: Path) -> int:
    return stat.S_IMODE(path.stat().st_mode)


def test_a_log_is_created_owner_only_whatever_the_umask(tmp_path: Path, umask_zero: None) -> None:
    assert DEFAULT_FILE_MODE == 0o600
    with SessionLog(tmp_path / "a.mcap", session_id="a", config_json={}, flush_interval_s=None):
        assert _mode(tmp_path / "a.mcap") == 0o600  # from the first byte, not at close
    with SessionLog(tmp_path / "b.mcap", session_id="b", config_json={}, flush_interval_s=None,
                    file_mode=0o640):
        pass
    assert _mode(tmp_path / "b.mcap") == 0o640
    old = tmp_path / "c.mcap"
    old.write_bytes(b"x")
    old.chmod(0o644)
    with SessionLog(old, session_id="c", config_json={}, flush_interval_s=None, overwrite=True):
        pass
    assert _mode(old) == 0o600


@pytest.mark.parametrize("mode", [0o1000, -1, "0600", True])
def test_a_bad_file_mode_is_named(tmp_path: Path, mode: Any) -> None:
    with pytest.raises(LogValueError, match="file_mode"):
        SessionLog(tmp_path / "x.mcap", session_id="x", config_json={}, file_mode=mode)
    assert not (tmp_path / "x.mcap").exists()


def test_session_file_mode_in_the_config_and_the_summary(tmp_path: Path, umask_zero: None) -> None:
    from bridge.config import BridgeConfigError, parse_config
    from bridge.run import write_json_atomic

    example = (Path(__file__).resolve().parents[2] / "bridge" / "config_example.toml").read_text()
    cfg = parse_config(example)
    assert cfg.session.file_mode == "0600" and cfg.session.file_mode_bits == 0o600
    cfg = parse_config(example.replace('file_mode = "0600"', 'file_mode = "0640"'))
    assert cfg.session.file_mode_bits == 0o640
    with pytest.raises(BridgeConfigError, match=r"session.file_mode = '0999'.*octal"):
        parse_config(example.replace('file_mode = "0600"', 'file_mode = "0999"'))
    write_json_atomic(tmp_path / "summary.json", {"vo2": 1})
    assert _mode(tmp_path / "summary.json") == 0o600
    write_json_atomic(tmp_path / "s2.json", {}, mode=0o640)
    assert _mode(tmp_path / "s2.json") == 0o640


def test_a_non_finite_value_is_omitted_and_the_reader_names_the_gap(tmp_path: Path) -> None:
    from hilbo_core.optimizer import Evaluation

    path = tmp_path / "nan.mcap"
    with SessionLog(path, session_id="n", config_json={}, flush_interval_s=None) as log:
        log.log_observation(Evaluation(0, {"a": 1.0}, 400.0, float("nan"), 3, 9.0, "exploration", False,
                                       "max_measurements"))
        log.log_estimate(index=0, breath=0, t_setting_s=3.0, watts=400.0, mean_w=400.0, var_w2=float("inf"),
                         phase="exploration")
    c = read_log(path)
    [obs] = c.topic(Topic.OBSERVATIONS)
    assert "var" not in obs.data and obs.record is None  # a required field missing: no typed record
    [est] = c.topic(Topic.ESTIMATOR)
    assert "var_w2" not in est.data and "sd_w" not in est.data and est.record is None
    assert c.invalid == 2 and c.records(Topic.OBSERVATIONS) == []
