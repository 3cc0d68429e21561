"""bridge.log.resume: a session cut off by kill -9 at any byte resumes with every evaluation once."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest

from bridge.log import LogFormatError, SessionLog, Topic
from bridge.log.reader import read_log
from bridge.log.resume import ResumeError, ResumePolicy, rebuild_optimizer
from hilbo_core.metabolic import GaussianProductEstimator
from hilbo_core.optimizer import HILOptimizer
from hilbo_core.presets import hip_6d
from hilbo_core.types import BreathRecord

SPACE = hip_6d()
OPT_U = np.array([0.2, 0.5, 0.7, 0.6, 0.5, 0.5])
N_EXPLORE = 3


def cost(params: dict[str, float]) -> float:
    """Synthetic cost (W), minimum 300 W at OPT_U."""
    u = SPACE.to_unit(SPACE.from_dict(params))
    return 300.0 + 400.0 * float(np.sum((u - OPT_U) ** 2))


def estimator() -> GaussianProductEstimator:
    return GaussianProductEstimator(prior_mean=400.0, prior_var=100.0**2, meas_var=40.0**2)


def make() -> HILOptimizer:
    # seed 6 (was 5): with data-only GP observations seed 5's session has no
    # optimisation evaluation of 2+ breaths for the mid-evaluation cuts.
    return HILOptimizer(SPACE, estimator_factory=estimator, n_explore=N_EXPLORE, max_breaths=5, window=1,
                        budget_breaths=14, seed=6, n_candidates=64, n_local=1,
                        stopping="adaptive")  # Kim et al. 2019's rule: early stops within 5 breaths


def breath_watts(k: int, b: int, params: dict[str, float]) -> float:
    """Breath b of evaluation k: the same noise whether or not the session was interrupted."""
    return cost(params) + float(np.random.default_rng([11, k, b]).normal(0.0, 40.0))


@dataclass
class Run:
    """What a driven session did, and the file size after each logged step."""

    marks: list[tuple[str, int, int, int]] = field(default_factory=list)  # (kind, index, breath, bytes)
    proposals: list[tuple[int, dict[str, float]]] = field(default_factory=list)


def drive(opt: HILOptimizer, log: SessionLog, run: Run | None = None, *,
          cancel: tuple[int, int] | None = None) -> HILOptimizer:
    """Run the session to the end the way the bridge does, logging every step.

    ``cancel=(k, b)``: abandon evaluation k after b breaths (a pause) and ask again.
    """
    run = run or Run()

    def mark(kind: str, k: int, b: int) -> None:
        run.marks.append((kind, k, b, log.path.stat().st_size))

    t_cart = 1000.0
    while not opt.done:
        k = len(opt.evaluations)
        params = opt.ask()
        log.log_proposal(params, index=k, phase=opt.phase.value, incumbent=opt.incumbent)
        run.proposals.append((k, params))
        mark("proposal", k, 0)
        b, t0 = 0, t_cart
        while True:
            if cancel == (k, b):
                cancel = None
                opt.cancel_current()
                log.log_event("evaluation_cancelled", "paused; the setting is re-measured")
                break
            t_cart += 3.0
            w = breath_watts(k, b, params)
            log.log_breath(BreathRecord(t_s=t_cart, vo2_ml_min=w * 3.0, vco2_ml_min=w * 0.5))
            step = opt.observe_breath(t_cart - t0, w)
            log.log_step(step, index=k, t_setting_s=t_cart - t0, watts=w, t_s=t_cart, incumbent=opt.incumbent)
            b += 1
            mark("breath", k, b)
            if step.stop:
                log.log_observation(step.evaluation, t_start=t0, t_end=t_cart, t_s=t_cart)
                mark("observation", k, b)
                log.log_optimizer_state(opt, reason="evaluation", t_s=t_cart)
                mark("snapshot", k, b)
                break
    return opt


def session_log(path: Path, *, previous: Path | None = None) -> SessionLog:
    return SessionLog(path, session_id="sess", config_json={"seed": 5}, previous_log=previous,
                      flush_interval_s=None, overwrite=True)


def record(opt: HILOptimizer) -> list[dict]:
    return [e.to_json() for e in opt.evaluations]


@pytest.fixture(scope="module")
def full(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Run, list[dict]]:
    """The uninterrupted session: its log, its marks and its evaluations."""
    path = tmp_path_factory.mktemp("resume") / "full.mcap"
    run = Run()
    opt = make()
    with session_log(path) as log:
        log.log_optimizer_state(opt, reason="start")
        drive(opt, log, run)
    evs = record(opt)
    assert len(evs) > N_EXPLORE + 3 and any(e["stopped_early"] for e in evs)
    return path, run, evs


def offset(run: Run, kind: str, k: int, b: int | None = None) -> int:
    return next(m[3] for m in run.marks if m[0] == kind and m[1] == k and (b is None or m[2] == b))


def cut(src: Path, dst: Path, n: int) -> Path:
    dst.write_bytes(src.read_bytes()[:n])
    return dst


def resume_and_finish(crashed: Path, tmp_path: Path, **kw) -> tuple[HILOptimizer, object, HILOptimizer]:
    """Rebuild from ``crashed``, continue in a new linked log; returns (rebuilt copy, info, final)."""
    opt, info = rebuild_optimizer(crashed, estimator_factory=estimator, **kw)
    snapshot = HILOptimizer.from_json(opt.to_json(), estimator_factory=estimator)
    new = tmp_path / "resumed.mcap"
    with session_log(new, previous=crashed) as log:
        log.log_optimizer_state(opt, reason="resume")
        drive(opt, log)
    linked = read_log(new)
    assert linked.previous_log == str(crashed) and linked.session_id == info.session_id == "sess"
    return snapshot, info, opt


# Where kill -9 lands: (mark kind, evaluation, breath, extra bytes into the next write, what the
# rebuild must do). "long" = the first optimisation evaluation with >= 2 breaths.
CUTS = {
    "after the start snapshot": ("proposal", 0, 0, 0, "discard"),
    "mid exploration point": ("breath", 1, 2, 0, "discard"),
    "between exploration and optimisation": ("snapshot", N_EXPLORE - 1, None, 0, "none"),
    "between two optimisation evaluations": ("snapshot", N_EXPLORE + 1, None, 0, "none"),
    "torn chunk mid optimisation evaluation": ("breath", "long", 1, 40, "discard"),
    "observation written, snapshot not": ("observation", N_EXPLORE + 2, None, 0, "replay"),
    "snapshot torn": ("observation", N_EXPLORE + 3, None, 150, "replay"),
}


def long_optimisation_evaluation(evs: list[dict]) -> int:
    """An optimisation-phase evaluation of at least 2 breaths (so a cut can fall inside it)."""
    return next(e["index"] for e in evs[N_EXPLORE:] if e["breaths"] >= 2)


@pytest.mark.parametrize("where", list(CUTS))
def test_every_completed_evaluation_exactly_once_and_the_session_ends_identically(
        full, tmp_path: Path, where: str) -> None:
    path, run, evs = full
    kind, k, b, extra, expect = CUTS[where]
    k = long_optimisation_evaluation(evs) if k == "long" else k
    crashed = cut(path, tmp_path / "crashed.mcap", offset(run, kind, k, b) + extra)
    before = read_log(crashed, topics=[Topic.OBSERVATIONS]).data(Topic.OBSERVATIONS)
    rebuilt, info, final = resume_and_finish(crashed, tmp_path)
    # Nothing completed before the crash is lost or doubled ...
    # (the log leaves out fields at their default, None)
    assert record(rebuilt)[: len(before)] == [{k2: o.get(k2) for k2 in evs[0]} for o in before]
    assert info.n_evaluations == len(rebuilt.evaluations) == info.n_from_snapshot + info.n_replayed
    assert [e.index for e in rebuilt.evaluations] == list(range(info.n_evaluations))
    assert (info.n_replayed == 1) == (expect == "replay")
    assert (info.discarded_params is not None) == (expect == "discard")
    assert info.unreadable_bytes == extra
    # ... and, the breaths being the same, the resumed session is the uninterrupted one.
    assert record(final) == evs
    assert info.truncated and info.session_id == "sess" and info.log_path == str(crashed)


@pytest.mark.parametrize("k", [0, N_EXPLORE - 1, N_EXPLORE, N_EXPLORE + 2])
def test_cut_between_evaluations_next_proposal_is_the_uninterrupted_one(full, tmp_path: Path, k: int) -> None:
    path, run, evs = full
    crashed = cut(path, tmp_path / "c.mcap", offset(run, "snapshot", k))
    opt, info = rebuild_optimizer(crashed, estimator_factory=estimator)
    assert record(opt) == evs[: k + 1]
    assert info.n_from_snapshot == k + 1 and info.n_replayed == 0 and info.discarded_params is None
    assert opt.ask() == dict(run.proposals[k + 1][1])
    assert [o.index for o in info.observations] == list(range(k + 1))
    assert info.observations[k].t_end == info.last_breath_t_s


def test_cut_mid_evaluation_discards_it_and_reproposes_the_same_setting(full, tmp_path: Path) -> None:
    path, run, evs = full
    k = long_optimisation_evaluation(evs)
    crashed = cut(path, tmp_path / "mid.mcap", offset(run, "breath", k, 1) + 60)
    opt, info = rebuild_optimizer(crashed, estimator_factory=estimator)
    assert record(opt) == evs[:k]
    assert info.discarded_params == run.proposals[k][1] and info.discarded_breaths >= 1
    assert opt.current_params is None
    assert opt.ask() == run.proposals[k][1]  # re-measured from scratch
    assert opt.budget_used == {"breaths": sum(e["breaths"] for e in evs[N_EXPLORE:k]),
                               "seconds": pytest.approx(sum(e["duration_s"] for e in evs[N_EXPLORE:k]))}


def test_resume_policy_keeps_the_breaths_of_the_setting_in_progress(full, tmp_path: Path) -> None:
    path, run, evs = full
    k = long_optimisation_evaluation(evs)
    b = 1
    crashed = cut(path, tmp_path / "keep.mcap", offset(run, "breath", k, b))
    opt, info = rebuild_optimizer(crashed, estimator_factory=estimator, policy=ResumePolicy.RESUME)
    assert info.in_progress_params == run.proposals[k][1] and info.discarded_params is None
    assert opt.current_params == run.proposals[k][1]
    # Feeding the rest of the same breaths completes the same evaluation.
    while True:
        step = opt.observe_breath(3.0 * (b + 1), breath_watts(k, b, opt.current_params))
        b += 1
        if step.stop:
            break
    assert record(opt) == evs[: k + 1]


def test_a_cancelled_and_reasked_setting_replays_like_the_session(full, tmp_path: Path) -> None:
    path, run = tmp_path / "cancel.mcap", Run()
    k = long_optimisation_evaluation(full[2])  # identical to the full run up to there
    opt = make()
    with session_log(path) as log:
        log.log_optimizer_state(opt, reason="start")
        drive(opt, log, run, cancel=(k, 1))  # abandoned after its first breath, no snapshot
    evs = record(opt)
    asked = [p for i, p in run.proposals if i == k]
    assert len(asked) == 2 and asked[0] != asked[1]  # the re-ask proposes afresh
    crashed = cut(path, tmp_path / "c.mcap", offset(run, "observation", k))  # no snapshot after it
    rebuilt, info = rebuild_optimizer(crashed, estimator_factory=estimator)
    assert info.n_replayed == 1 and record(rebuilt) == evs[: k + 1]
    assert rebuilt.ask() == run.proposals[[i for i, _ in run.proposals].index(k + 1)][1]


def test_a_different_estimator_is_detected(full, tmp_path: Path) -> None:
    path, run, _ = full
    crashed = cut(path, tmp_path / "e.mcap", offset(run, "observation", N_EXPLORE))
    other = lambda: GaussianProductEstimator(prior_mean=300.0, prior_var=50.0**2, meas_var=10.0**2)  # noqa: E731
    with pytest.raises(ResumeError, match=f"evaluation {N_EXPLORE} in the log .* another estimator"):
        rebuild_optimizer(crashed, estimator_factory=other)


def test_a_log_without_a_snapshot_cannot_be_resumed(tmp_path: Path) -> None:
    path = tmp_path / "nosnap.mcap"
    with session_log(path) as log:
        log.log_breath(BreathRecord(t_s=1.0, vo2_ml_min=1000.0, vco2_ml_min=800.0))
    with pytest.raises(ResumeError, match="no /optimizer_state snapshot") as err:
        rebuild_optimizer(path)
    # Tells the user what to do, in the user's words: no internal function names.
    assert "without --resume" in str(err.value) and "SessionLog" not in str(err.value)
    assert "log_optimizer_state" not in str(err.value)


def test_a_resumed_log_that_crashed_before_its_snapshot_falls_back_to_the_previous_one(
        full, tmp_path: Path) -> None:
    path, run, evs = full
    k = N_EXPLORE
    first = cut(path, tmp_path / "first.mcap", offset(run, "snapshot", k))
    second = tmp_path / "second.mcap"
    with session_log(second, previous=first):
        pass  # the new process died before logging its "resume" snapshot
    opt, info = rebuild_optimizer(second, estimator_factory=estimator)
    assert record(opt) == evs[: k + 1]
    assert info.previous_log == str(first) and any("previous log" in w for w in info.warnings)


def test_a_log_that_is_not_ours_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "x.mcap"
    path.write_bytes(b"not mcap at all")
    with pytest.raises(LogFormatError, match="not an MCAP file"):
        rebuild_optimizer(path)


def test_breaths_missing_from_the_log_are_an_error(full, tmp_path: Path) -> None:
    path, run, evs = full
    k = long_optimisation_evaluation(evs)
    crashed = cut(path, tmp_path / "g.mcap", offset(run, "observation", k))
    contents = read_log(crashed)
    # Drop breath 0 of evaluation k (as if it had never been logged).
    kept = tuple(m for m in contents.messages
                 if not (m.topic == Topic.ESTIMATOR and m.data["index"] == k and m.data["breath"] == 0))
    damaged = dataclasses.replace(contents, messages=kept)
    with pytest.raises(ResumeError, match=f"evaluation {k} needs breath 0 next, but the log has breath 1"):
        rebuild_optimizer(damaged, estimator_factory=estimator)


def test_an_unknown_policy_is_named(full) -> None:
    with pytest.raises(ResumeError, match="policy='later'; expected one of"):
        rebuild_optimizer(full[0], estimator_factory=estimator, policy="later")  # type: ignore[arg-type]
