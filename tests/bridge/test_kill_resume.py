"""kill -9 at every await point of the session loop: the log resumes with nothing lost or doubled.

A session on the deterministic harness (supervision_harness.py: fake loop time, a model of the
exosuit, proposals and hyperparameter fits in the loop) is run once with a hook at every
suspension of the task that runs the session loop. There the process "dies": the log's bytes on
disk are taken as a kill -9 leaves them (every record but the high-rate channels is flushed when
written) together with the optimizer the process held. Each cut log is then rebuilt
(bridge/log/resume.py) and must give back that very optimizer:

* with ``ResumePolicy.RESUME`` (keep the breaths of a setting cut off), ``to_json()`` equal to the
  dying process's, the generator's state included; when the process had asked for a setting it
  had not logged yet, the rebuilt optimizer asks the same setting;
* with the default ``DISCARD``, the same completed evaluations (0 lost, 0 doubled); and the
  resumed session (``hilbo run --resume``'s path) re-proposes exactly what the uninterrupted one
  proposed next and ends with every evaluation once.

The sessions fit their GP hyperparameters ahead (``refit_lag`` 1, the bridge's default) and each
bout starts with a warm-up; one has the pause between the bouts, one a pause in the first setting
of the optimisation bout, the places where a fit made ahead was once applied after the last
snapshot and a resume refused the log.
"""

from __future__ import annotations

import asyncio
import json
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest
from supervision_harness import BREATH_S, SESSION_TASK, Outcome, run_session

from bridge.log import Topic
from bridge.log.reader import read_log
from bridge.log.resume import ResumeError, ResumePolicy, rebuild_optimizer
from bridge.runtime import BridgeSession
from hilbo_core import HILOptimizer

N_EXPLORE = 3
N_EVALUATIONS = 7
BASE = {"n_explore": N_EXPLORE, "warmup_s": 2 * BREATH_S, "refit_lag": 1,
        "n_evaluations": N_EVALUATIONS}
#: The first optimisation setting is pushed as profile version N_EXPLORE + 1.
FIRST_OPT_VERSION = N_EXPLORE + 1


T_PAUSE = object()  # stands for the loop time one breath into the first optimisation setting
VARIANTS: dict[str, dict[str, Any]] = {
    "plain": {},
    "bouts": {"pause_between_bouts": True, "auto_resume_s": 2.0},
    "pause": {"at_time_s": T_PAUSE, "fault": "pause", "resume_after_s": 5.0},
    # A fit made ahead that outlasts the setting: the session waits for it at the evaluation's
    # end and when the pause abandons the setting.
    "slow_fit": {"fit_s": 4 * BREATH_S, "at_time_s": T_PAUSE, "fault": "pause", "resume_after_s": 5.0},
}


@dataclass(frozen=True)
class Kill:
    """The process dies at the session loop's suspension ``k``."""

    k: int
    site: str  # the session loop's await: the innermost bridge/runtime.py function awaiting
    log: bytes  # the log file as kill -9 leaves it
    state: dict[str, Any]  # the optimizer the process held, HILOptimizer.to_json()


@dataclass
class Killed:
    """One uninterrupted session and the kills simulated along it."""

    outcome: Outcome
    kills: list[Kill] = field(default_factory=list)


def _loop_site(coro: Any) -> str:
    """Where in bridge/runtime.py the suspended coroutine ``coro`` awaits: its two innermost
    functions there (``"_measure>_collect_fit_ahead"``)."""
    names = ["", "run"]
    while coro is not None:
        frame = getattr(coro, "cr_frame", None) or getattr(coro, "gi_frame", None)
        if frame is None:
            break
        if frame.f_code.co_filename.endswith("bridge/runtime.py"):
            names.append(frame.f_code.co_name)
        coro = getattr(coro, "cr_await", None) or getattr(coro, "gi_yieldfrom", None)
    return ">".join(names[-2:])


def _frozen(opt: HILOptimizer) -> dict[str, Any]:
    return json.loads(json.dumps(opt.to_json()))


def killed_session(tmp: Path, name: str, **kw: Any) -> Killed:
    """Run a session; simulate a kill at every suspension of the session loop's task."""
    kills: list[Kill] = []

    def watch(k: int, session: BridgeSession, coro: Any) -> None:
        task = asyncio.current_task()
        if task is None or task.get_name() != SESSION_TASK:
            return
        kills.append(Kill(k, _loop_site(coro), session.log.path.read_bytes(), _frozen(session.opt)))

    out = run_session(tmp / name, watch=watch, **{**BASE, **kw})
    return Killed(out, kills)


def _pause_in_first_optimisation_setting(tmp: Path) -> float:
    """Loop time one breath into the first optimisation setting's measurement."""
    base = run_session(tmp, **BASE)
    return base.device.times_of("ack", FIRST_OPT_VERSION)[0] + BREATH_S


@pytest.fixture(scope="module")
def sessions(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Killed]:
    tmp = tmp_path_factory.mktemp("kills")
    for d in (*VARIANTS, "t"):
        (tmp / d).mkdir()
    t_pause = _pause_in_first_optimisation_setting(tmp / "t")
    return {name: killed_session(tmp, name, **{k: t_pause if v is T_PAUSE else v for k, v in kw.items()})
            for name, kw in VARIANTS.items()}


def check_rebuilt(kill: Kill, tmp: Path) -> Path:
    """The cut log gives back the dying process's optimizer; returns the cut log's path."""
    path = tmp / f"killed_{kill.k}.mcap"
    path.write_bytes(kill.log)
    where = f"kill at suspension {kill.k} in {kill.site}"
    try:
        kept, _ = rebuild_optimizer(path, policy=ResumePolicy.RESUME)
        discarded, info = rebuild_optimizer(path)
    except ResumeError as err:
        raise AssertionError(f"{where}: {err}") from err
    dying = kill.state
    if dying["current"] is not None and kept.current_params is None:
        # The process had asked for the setting but not logged it yet: asking reproduces it, as
        # the resumed session asks: the setting a pause abandoned once more, else a new one.
        again = kept.ask_again()
        assert (again if again is not None else kept.ask()) == dying["current"]["params"], where
    assert _frozen(kept) == dying, where
    # 0 evaluations lost or doubled (the cut-off setting is discarded by default).
    assert [e.to_json() for e in discarded.evaluations] == dying["evaluations"], where
    assert discarded.current_params is None and info.n_evaluations == len(dying["evaluations"])
    return path


def check_resumed(kill: Kill, crashed: Path, tmp: Path) -> None:
    """The resumed session re-proposes what the dying one proposed (or was about to propose)
    next and ends with every evaluation once."""
    where = f"kill at suspension {kill.k} in {kill.site}"
    n_done = len(kill.state["evaluations"])
    dying = HILOptimizer.from_json(kill.state)
    if dying.current_params is not None:
        expected = dying.current_params
    else:
        again = dying.ask_again()
        expected = again if again is not None else dying.ask()
    resumed = run_session(tmp, resume_from=crashed, **BASE)
    evs = [e.to_json() for e in resumed.session.opt.evaluations]
    assert evs[:n_done] == kill.state["evaluations"], where
    assert [e["index"] for e in evs] == list(range(len(evs))), where
    proposals = read_log(resumed.log, topics=[Topic.PROPOSALS]).records(Topic.PROPOSALS)
    if proposals:
        assert proposals[0].index == n_done, where
        assert proposals[0].params == expected, where


def sample(kills: list[Kill]) -> list[Kill]:
    """Every distinct await site at its first and last visit, and, between the end of the
    exploration bout and the end of the first optimisation setting (the warm-up, the proposal
    that uses the hyperparameters fitted ahead, its push, its measurement, a pause), the first
    kill at each site with each number of the setting's breaths measured."""
    by_site: dict[str, list[Kill]] = {}
    for kill in kills:
        by_site.setdefault(kill.site, []).append(kill)
    chosen = {k.k: k for ks in by_site.values() for k in (ks[0], ks[-1])}
    seen: set[tuple[str, int]] = set()
    for kill in kills:
        current = kill.state["current"]
        key = (kill.site, -1 if current is None else len(current["breaths"]))
        if len(kill.state["evaluations"]) == N_EXPLORE and key not in seen:
            seen.add(key)
            chosen[kill.k] = kill
    return [chosen[k] for k in sorted(chosen)]


@pytest.mark.parametrize("name", list(VARIANTS))
def test_a_kill_at_sampled_await_points_gives_back_the_optimizer(sessions, name: str,
                                                                  tmp_path: Path) -> None:
    run = sessions[name]
    assert run.outcome.summary["n_evaluations"] >= N_EXPLORE + 2
    for kill in sample(run.kills):
        check_rebuilt(kill, tmp_path)


def test_every_await_site_of_the_session_loop_is_visited(sessions) -> None:
    sites = {k.site for run in sessions.values() for k in run.kills}
    # The session loop's awaits: its start (the worker) and end, a warm-up's assistance-off, the
    # breath wait, the proposal, the push and its ack, the wait for the device to run the
    # setting, a fit made ahead that is still running at the evaluation's end or when a pause
    # abandons the setting, and the waits of a pause (between the bouts, an operator's).
    assert sites >= {
        "_run_tasks>_worker_started", "run>_run_tasks", "run>run", "_main>_step",
        "_step>_next_breath", "_step>_propose", "_propose>_push", "_propose>_wait_applied",
        "_measure>_collect_fit_ahead", "_abandon>_collect_fit_ahead", "_abandon>_wait_resumed",
        "_step>_bout_pause", "_bout_pause>_wait_resumed",
    }, sorted(sites)


def test_the_first_setting_after_the_warm_up_resumes(sessions, tmp_path: Path) -> None:
    """The kill that refused to resume: the first optimisation setting is being measured (the
    hyperparameters fitted ahead during the last exploration setting are in use)."""
    run = sessions["plain"]
    measuring = [k for k in run.kills if len(k.state["evaluations"]) == N_EXPLORE
                 and k.state["current"] is not None and k.state["current"]["breaths"]]
    assert measuring
    kill = measuring[0]
    crashed = check_rebuilt(kill, tmp_path)
    check_resumed(kill, crashed, tmp_path)


def test_the_resumed_session_continues_as_the_uninterrupted_one_at_each_site(
        sessions, tmp_path: Path) -> None:
    run = sessions["pause"]  # every site but those of the pause between the bouts
    seen: set[str] = set()
    for kill in run.kills:
        if kill.site in seen:
            continue
        seen.add(kill.site)
        check_resumed(kill, check_rebuilt(kill, tmp_path), tmp_path)


@pytest.mark.slow
@pytest.mark.parametrize("name", list(VARIANTS))
def test_a_kill_at_every_await_point_resumes_with_nothing_lost_or_doubled(
        sessions, name: str, tmp_path: Path) -> None:
    run = sessions[name]
    for kill in run.kills:
        check_resumed(kill, check_rebuilt(kill, tmp_path), tmp_path)
