"""``hilbo run --resume`` and ``hilbo validate --from`` refuse a log they would misread, before
anything is written: a validation walk's log, a log a later one continues, a config whose
parameter space does not hold the session's; an output directory that cannot be made is said as
``hilbo review`` says it. Another subject is allowed, with a warning in the log and on stderr."""

from __future__ import annotations

import asyncio
import dataclasses
import logging
import os
import uuid
from pathlib import Path
from typing import Any

import msgspec
import pytest
from test_resume import drive, make
from test_session_end import SIM, replay_config, write_recording

from bridge.cli.main import main
from bridge.config import HilboConfig, parse_config
from bridge.log import EventLevel, SessionLog
from bridge.log.reader import read_log
from bridge.log.resume import ResumeError, rebuild_optimizer
from bridge.run import RunResult, resume_config_warnings, run_session
from bridge.sim.virtual import VirtualSimConfig, sim_config_text
from bridge.validate import ValidationPlan
from drivers.exosuit import CanBusConfig
from hilbo_core.presets import hip_ankle_4d
from virtual_hw.clock import ScaledClock
from virtual_hw.exosuit import SUIT_JOINTS, VirtualExosuit

pytestmark = pytest.mark.timeout(120)


def config_text(tmp: Path, space: str = "") -> str:
    """A config with a [validation] table whose out_dir is ``tmp``; ``space`` is appended to
    its [space] table."""
    text = sim_config_text(VirtualSimConfig(minutes=30.0), tmp) + "\n[validation]\n"
    return text.replace('preset = "hip_6d"\n', 'preset = "hip_6d"\n' + space, 1)


def config_file(tmp: Path, space: str = "") -> Path:
    path = tmp / "s.toml"
    path.write_text(config_text(tmp, space))
    return path


def config(tmp: Path, space: str = "") -> HilboConfig:
    return parse_config(config_text(tmp, space), source="<test>")


def optimisation_log(path: Path, cfg: HilboConfig) -> Path:
    """A whole optimisation session (test_resume's), logged with ``cfg`` as its config."""
    opt = make()
    with SessionLog(path, session_id="sess", config_json=cfg.to_json(), flush_interval_s=None) as log:
        log.log_optimizer_state(opt, reason="start")
        drive(opt, log)
    return path


def continuation(path: Path, previous: Path, cfg: HilboConfig) -> Path:
    """A log that continues ``previous`` (hilbo run --resume's new log, cut off after its start)."""
    opt, info = rebuild_optimizer(previous)
    with SessionLog(path, session_id=info.session_id or "sess", config_json=cfg.to_json(),
                    previous_log=previous, flush_interval_s=None) as log:
        log.log_optimizer_state(opt, reason="resume")
    return path


def validation_log(path: Path, source: Path, cfg: HilboConfig) -> Path:
    """A validation walk's log (hilbo validate --from source), cut off after its start."""
    plan = ValidationPlan.new(cfg, source)
    with SessionLog(path, session_id="walk", config_json=cfg.to_json(), flush_interval_s=None) as log:
        log.log_optimizer_state(plan.optimizer, reason="start")
        log.log_event("validation_plan", "validation walk", conditions=[c.to_json() for c in plan.conditions],
                      source_log=plan.source_log)
    return path


@pytest.fixture(scope="module")
def logs(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Path]:
    """An optimisation session a.mcap continued by b.mcap then c.mcap, and a walk validating c."""
    tmp = tmp_path_factory.mktemp("refusals")
    cfg = config(tmp)
    a = optimisation_log(tmp / "a.mcap", cfg)
    b = continuation(tmp / "b.mcap", a, cfg)
    c = continuation(tmp / "c.mcap", b, cfg)
    return {"a": a, "b": b, "c": c, "walk": validation_log(tmp / "walk.mcap", c, cfg)}


def refused(tmp: Path, cfg: HilboConfig, resume: Path, match: str) -> None:
    """run_session refuses to resume ``resume`` with ``cfg``, and writes nothing."""
    with pytest.raises(ResumeError, match=match):
        asyncio.run(run_session(cfg, resume=resume, log_path=tmp / "new.mcap", operator_view=False))
    assert not (tmp / "new.mcap").exists() and not (tmp / "new.summary.json").exists()


def one_error(err: str, prefix: str) -> str:
    """The one error line of ``err`` (hilbo run says its config and subject first)."""
    assert "Traceback" not in err
    lines = [line for line in err.splitlines() if ": error: " in line]
    assert len(lines) == 1 and lines[0].startswith(prefix), err
    return lines[0]


# --- 1. a validation walk's log is not an optimisation to resume ---------------------------


def test_run_resume_refuses_a_validation_walks_log(logs: dict[str, Path], tmp_path: Path,
                                                  capsys: pytest.CaptureFixture[str]) -> None:
    walk = logs["walk"]
    refused(tmp_path, config(tmp_path), walk,
            rf"{walk} is a validation walk's log \(hilbo validate\); continue it with hilbo validate "
            rf"CONFIG --resume {walk}, or resume the optimisation session's newest log "
            rf"\(this walk validated {logs['c']}\)")
    out = tmp_path / "out"
    argv = ["run", "--no-view", "--out", str(out), str(config_file(tmp_path)), "--resume", str(walk)]
    assert main(argv) == 1
    assert "is a validation walk's log" in one_error(capsys.readouterr().err, "hilbo run: error:")
    assert not list(out.glob("*"))


# --- 2. validate --from takes the optimisation session's newest log --------------------------


def test_validate_from_a_log_continued_later_names_the_newest(logs: dict[str, Path], tmp_path: Path,
                                                              capsys: pytest.CaptureFixture[str]) -> None:
    cfg = config_file(tmp_path)
    for old, later in (("a", "b"), ("b", "c")):
        assert main(["validate", str(cfg), "--from", str(logs[old]), "--no-view"]) == 1
        line = one_error(capsys.readouterr().err, "hilbo validate: error:")
        assert (f"{logs[old]} was continued by {logs[later]} (hilbo run --resume)" in line
                and f"hilbo validate CONFIG --from {logs['c']}" in line), line
    assert not list(tmp_path.glob("*.mcap"))
    # hilbo run --resume names the newest log of the chain too, not only the next one.
    refused(tmp_path, config(tmp_path), logs["a"],
            rf"{logs['a']} was already continued by {logs['b']}.*--resume {logs['c']}$")


def test_validate_from_a_validation_walks_log_is_refused(logs: dict[str, Path], tmp_path: Path,
                                                          capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["validate", str(config_file(tmp_path)), "--from", str(logs["walk"]), "--no-view"]) == 1
    line = one_error(capsys.readouterr().err, "hilbo validate: error:")
    assert (f"{logs['walk']} is a validation walk's log (hilbo validate); --from takes the optimisation "
            f"session's log (this walk validated {logs['c']})") in line
    assert not list(tmp_path.glob("*.mcap"))


# --- 3. the resumed config's space holds the session's ---------------------------------------


def test_narrower_bounds_are_refused_naming_the_key(logs: dict[str, Path], tmp_path: Path,
                                                    capsys: pytest.CaptureFixture[str]) -> None:
    space = "bounds = { F_p = [50, 130], t_on = [5, 25] }\n"
    refused(tmp_path, config(tmp_path, space), logs["c"],
            r"this config's \[space\] does not hold the session's: space\.bounds\.t_on: the log's session "
            r"used \[0, 25\], this config has \[5, 25\]; space\.bounds\.F_p: the log's session used "
            r"\[50, 250\], this config has \[50, 130\]\. Resume with the session's bounds")
    assert main(["run", "--no-view", str(config_file(tmp_path, space)), "--resume", str(logs["c"])]) == 1
    assert "space.bounds.F_p: the log's session used [50, 250]" in one_error(
        capsys.readouterr().err, "hilbo run: error:")


def test_other_parameters_are_refused(logs: dict[str, Path], tmp_path: Path) -> None:
    cfg = config(tmp_path)
    other = dataclasses.replace(cfg, space=dataclasses.replace(cfg.space, space=hip_ankle_4d(),
                                                               preset="hip_ankle_4d"))
    refused(tmp_path, other, logs["c"], r"space: the session of .*c\.mcap optimised t_on, t_p, t_off, F_p, "
                                        r"F_r, F_f; this config has .*resume with the session's \[space\]")


def test_an_evaluation_outside_a_new_constraint_is_refused(logs: dict[str, Path], tmp_path: Path) -> None:
    opt, _ = rebuild_optimizer(logs["c"])
    k = next(k for k, e in enumerate(opt.evaluations) if e.params["F_p"] > 100.0)
    refused(tmp_path, config(tmp_path, 'constraints = ["F_p <= 100"]\n'), logs["c"],
            rf"evaluation {k} \(t_on = .*\) is outside this config's space: constraint 'F_p <= 100' is "
            r"violated")


def test_wider_bounds_and_another_subject_are_warnings(logs: dict[str, Path], tmp_path: Path) -> None:
    opt, info = rebuild_optimizer(logs["c"])
    assert resume_config_warnings(config(tmp_path), opt, info) == []
    wide = config(tmp_path, "bounds = { F_p = [40, 250] }\n")
    wide = dataclasses.replace(wide, session=msgspec.structs.replace(wide.session, subject="S02"))
    assert resume_config_warnings(wide, opt, info) == [
        "space.bounds.F_p: this config has [40, 250], the log's session used [50, 250]; the resumed "
        "session keeps searching [50, 250]",
        "session.subject: the log's session is subject 'sim1', this config has 'S02'; the new log "
        "continues that session under 'S02''s name"]


def run_replay(tmp: Path, cfg: HilboConfig, channel: str, name: str,
               resume: Path | None = None) -> RunResult:
    """test_session_end's replayed session over the virtual exosuit, with ``cfg``."""
    async def run() -> RunResult:
        async with VirtualExosuit(CanBusConfig("virtual", channel), ScaledClock(1.0),
                                  joints=SUIT_JOINTS[SIM.preset], seed=1):
            return await run_session(cfg, log_path=tmp / f"{name}.mcap", auto_resume_s=0.0, resume=resume,
                                     operator_view=False, n_actuators=len(SUIT_JOINTS[SIM.preset]))
    return asyncio.run(run())


def test_another_subject_is_warned_in_the_log_and_on_stderr(tmp_path: Path,
                                                            caplog: pytest.LogCaptureFixture) -> None:
    cfg, channel = replay_config(tmp_path, write_recording(tmp_path / "breaths.hbr", 60))
    first = run_replay(tmp_path, cfg, channel, "a")
    assert first.summary["end_reason"] == "cart_ended"
    other = dataclasses.replace(cfg, session=msgspec.structs.replace(cfg.session, subject="S02"))
    with caplog.at_level(logging.WARNING, logger="bridge.run"):
        second = run_replay(tmp_path, other, f"hilbo-subject-{uuid.uuid4().hex[:8]}", "b",
                            resume=first.log_path)
    assert second.summary["previous_log"] == str(first.log_path)
    text = f"the log's session is subject {cfg.session.subject!r}, this config has 'S02'"
    assert any(text in r.getMessage() for r in caplog.records if r.name == "bridge.run")
    events: list[Any] = [e for e in read_log(second.log_path).records("/events") if e.kind == "resume_config"]
    assert len(events) == 1 and text in events[0].message and events[0].level == EventLevel.WARNING


# --- 4. an output directory that cannot be made ----------------------------------------------


@pytest.mark.parametrize("command", ["run", "validate"])
@pytest.mark.parametrize("where", ["long", "proc"])
def test_an_out_dir_that_cannot_be_made_is_said_like_review(
        command: str, where: str, logs: dict[str, Path], tmp_path: Path,
        capsys: pytest.CaptureFixture[str]) -> None:
    out = str(tmp_path / ("x" * 300)) if where == "long" else "/proc/hilbo_out"
    argv = [command, "--no-view", "--out", out, str(config_file(tmp_path))]
    argv += ["--from", str(logs["c"])] if command == "validate" else []
    assert main(argv) == 1
    line = one_error(capsys.readouterr().err, f"hilbo {command}: error: --out")
    assert out in line
    if where == "long":
        assert line.endswith("cannot create the output directory: File name too long"), line
    elif os.geteuid() == 0:  # otherwise check_out_dir says /proc is not writable
        assert line.endswith("cannot create the output directory: No such file or directory"), line
    assert not list(tmp_path.glob("*.mcap"))
