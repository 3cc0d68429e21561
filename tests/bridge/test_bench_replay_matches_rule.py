"""The pairs bench's vectorised replay decides as :class:`~hilbo_core.stopping.SoundRule` does."""

from __future__ import annotations

import numpy as np
import pytest

from bridge.bench.traces import BreathTrace
from bridge.bench.tune_sound import SoundReplay
from hilbo_core.stopping import SoundRule, StopReason

N = 30


def _replay(seed: int) -> SoundReplay:
    rng = np.random.default_rng(seed)
    n = 6
    times = [np.cumsum(rng.uniform(1.5, 4.0, N)) for _ in range(n)]
    traces = []
    for _ in range(n):
        level = rng.uniform(300.0, 400.0)
        sd = 40.0 * np.exp(-np.arange(N) / 10.0) + 8.0  # wide early, as a transition's
        traces.append(BreathTrace(level + sd * rng.normal(0.0, 1.0, N), sd**2))
    schedules = rng.normal(0.5, 0.8, (n, N))
    return SoundReplay(traces, times, schedules)


def _by_rule(replay: SoundReplay, j: int, k: int, rule: SoundRule) -> tuple[int, bool]:
    """Breaths used and whether the stop was a rejection, deciding breath by breath."""
    for i in range(N):
        d = rule.decide(i, replay.means[j, i], replay.vars[j, i], replay.means[k, -1], replay.vars[k, -1],
                        t_s=float(replay.times[j, i]))
        if d.stop:
            return i + 1, d.reason is StopReason.THRESHOLD
    raise AssertionError("the rule must stop at N")


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("min_decision_s, a_floor, accept_z, boundary_s", [
    (30.0, 1.0, 2.0, 60.0), (60.0, 1.0, 3.0, None), (10.0, 0.5, None, 45.0), (0.0, 0.0, 1.0, 80.0)])
def test_replay_outcomes_equal_the_rules_decisions(seed, min_decision_s, a_floor, accept_z,
                                                   boundary_s) -> None:
    replay = _replay(seed)
    for j in range(replay.n):
        rule = SoundRule(replay.schedules[j], min_decision_s=min_decision_s, a_floor=a_floor,
                         accept_z=accept_z, boundary_s=boundary_s)
        steps, rejected = replay.outcomes(j, min_decision_s, a_floor, accept_z, boundary_s)
        for k in range(replay.n):
            if k != j:
                assert (int(steps[k]), bool(rejected[k])) == _by_rule(replay, j, k, rule)
