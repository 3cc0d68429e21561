"""The named walking protocols (fast, seed) and the confirmation of the recommendation."""

from __future__ import annotations

import numpy as np
import pytest

from hilbo_core.errors import ConfigError
from hilbo_core.metabolic import GaussianProductEstimator
from hilbo_core.optimizer import HILOptimizer
from hilbo_core.presets import hip_6d
from hilbo_core.protocol import (
    ActionKind,
    ProtocolKind,
    SessionPhase,
    SessionProtocol,
    SessionProtocolConfig,
    drive,
    expected_end_s,
    protocol_preset,
)

SPACE = hip_6d()
OPT_U = np.array([0.2, 0.5, 0.7, 0.6, 0.5, 0.5])


def _config(kind: str, **kw) -> SessionProtocolConfig:
    # The protocol's values, then the test's (no pause: a simulation walks on).
    opts = {**protocol_preset(kind)[0], "warmup_s": 30.0, "n_explore": 2, "max_breaths": 5,
            "session_s": 600.0, "budget_s": None, "pause_between_bouts": False}
    opts.update(kw)
    return SessionProtocolConfig(**opts)


def _phases_until_optimisation(cfg: SessionProtocolConfig) -> list[SessionPhase]:
    """Walk the protocol with 3 s breaths and 5-breath evaluations; the phases seen."""
    proto = SessionProtocol(cfg, t_start_s=0.0)
    act, t, seen = proto.start(), 0.0, []
    while proto.phase is not SessionPhase.OPTIMIZATION:
        if act.kind is ActionKind.PROPOSE:
            proto.on_setting_applied(t)
        t += 3.0
        act = proto.on_breath(t)
        seen.append(proto.phase)
        if act.kind is ActionKind.MEASURE and proto._setting_breaths == cfg.max_breaths:
            act = proto.on_evaluation_done()
    return seen


def test_the_fast_protocol_walks_on_into_the_optimisation_without_a_second_warm_up() -> None:
    fast = _phases_until_optimisation(_config("fast"))
    seed = _phases_until_optimisation(_config("seed"))
    assert SessionPhase.WARM_UP_OPTIMIZATION not in fast
    # 30 s of 3 s breaths: the 10th breath ends the warm-up (and is the warm-up's).
    assert seed.count(SessionPhase.WARM_UP_OPTIMIZATION) == 9
    assert len(seed) - len(fast) == 10
    # After a pause between the bouts there is a warm-up either way.
    assert not _config("fast", pause_between_bouts=True).warmup_without_pause
    assert expected_end_s(_config("seed", session_s=None, budget_s=60.0), breath_interval_s=3.0) \
        - expected_end_s(_config("fast", session_s=None, budget_s=60.0), breath_interval_s=3.0) == 30.0


def test_protocol_presets_and_a_bad_name() -> None:
    assert protocol_preset("fast") == (
        {"n_explore": 3, "pause_between_bouts": False, "warmup_without_pause": False, "confirm_s": 240.0},
        {"n_explore": 3, "explore_rel_sd": None})
    # Kim et al. 2019 §IV.A.3: 6 exploration settings, a pause and a warm-up before each bout.
    assert protocol_preset(ProtocolKind.SEED) == (
        {"n_explore": 6, "pause_between_bouts": True, "warmup_without_pause": True, "confirm_s": None},
        {"n_explore": 6, "explore_rel_sd": None})
    with pytest.raises(ConfigError, match=r"protocol='quick'; expected one of \['fast', 'seed'\]"):
        protocol_preset("quick")
    with pytest.raises(ConfigError, match="confirm_s"):
        SessionProtocolConfig(confirm_s=0.0)


def _cost(params: dict[str, float]) -> float:
    u = SPACE.to_unit(SPACE.from_dict(params))
    return 300.0 + 400.0 * float(np.sum((u - OPT_U) ** 2))


def _session(confirm_s: float | None) -> tuple[HILOptimizer, list, SessionProtocol]:
    opt = HILOptimizer(SPACE, n_explore=3, max_breaths=10, seed=1, n_candidates=128, n_local=1,
                       min_decision_s=9.0,
                       estimator_factory=lambda: GaussianProductEstimator(400.0, 200.0**2, 20.0**2))
    proto = SessionProtocol(SessionProtocolConfig(warmup_s=9.0, n_explore=3, max_breaths=10, session_s=300.0,
                                                  budget_s=None, pause_between_bouts=False,
                                                  warmup_without_pause=False, confirm_s=confirm_s),
                            t_start_s=0.0)
    rng = np.random.default_rng(4)
    state = {"t": 0.0, "params": None}
    evals = []

    def next_breath() -> tuple[float, float]:
        state["t"] += 3.0
        watts = 400.0 if state["params"] is None else _cost(state["params"])
        return state["t"], watts + rng.normal(0.0, 20.0)

    def apply(params, t_s) -> None:
        state["params"] = params

    drive(proto, opt, next_breath, apply, on_evaluation=lambda ev, t0, t1: evals.append((ev, t0, t1)))
    return opt, evals, proto


def test_drive_confirms_the_recommendation_in_the_last_minutes() -> None:
    opt, evals, _proto = _session(confirm_s=60.0)
    conf = opt.confirmation
    assert conf is not None and conf.n_evaluations >= 1 and conf.mean_w is not None
    confirming = [(ev, t0) for ev, t0, _ in evals if ev.index >= len(evals) - conf.n_evaluations]
    for ev, t0 in confirming:
        assert ev.params == conf.params and not ev.stopped_early
        assert t0 >= 300.0 - 60.0 - 3.0 * 10  # began in the last minute (or its last setting)
    # Every evaluation before began before the confirmation was due.
    assert all(t0 < 300.0 - 60.0 for ev, t0, _ in evals[:len(evals) - conf.n_evaluations])
    # The summary's recommendation is the confirmed setting with its own measurement.
    assert opt.best() == (conf.params, conf.mean_w, conf.sd_w**2)
    assert abs(conf.mean_w - _cost(conf.params)) < 4 * conf.sd_w


def test_no_confirmation_without_confirm_s() -> None:
    opt, _evals, proto = _session(confirm_s=None)
    assert opt.confirmation is None and not proto.confirm_due
