"""bridge.bench.perf: latency measurements at toy size and the target table."""

from __future__ import annotations

import pytest

from bridge.bench.perf import (
    PerfConfig,
    breath_latency,
    perf_table,
    proposal_ahead_latency,
    proposal_latency,
)
from hilbo_core.errors import ConfigError


def test_breath_latency_times_every_optimisation_breath() -> None:
    q = breath_latency(breaths=25, seed=2)
    assert q["n"] == 25
    assert 0 < q["median"] <= q["p99"] <= q["max"]
    assert 0 < q["cpu_median"] <= q["cpu_p99"]


def test_proposal_latency_per_size_and_a_profile() -> None:
    q, prof = proposal_latency(sizes=(5, 8), reps=2, seed=1)
    assert set(q) == {"5", "8"}
    for v in q.values():
        assert v["n"] == 2 and 0 < v["median"] <= v["p95"] <= v["max"]
    assert prof["observations"] == 8
    assert 0 < prof["gp_fit_ms"] <= prof["total_ms"] and 0 < prof["maximize_ei_ms"] <= prof["total_ms"]


def test_proposal_ahead_latency_times_proposals_that_do_not_fit(optimize_calls: list[int]) -> None:
    q = proposal_ahead_latency(sizes=(5, 8), reps=2, seed=1)
    assert set(q) == {"5", "8"}
    for v in q.values():
        assert v["n"] == 2 and 0 < v["median"] <= v["p95"] <= v["max"]
    # Only the untimed warm-up proposals fitted, each on the n - 1 earlier evaluations.
    assert optimize_calls == [4, 4, 7, 7]


def test_perf_config_rejects_bad_sizes() -> None:
    with pytest.raises(ConfigError, match="sizes="):
        PerfConfig(sizes=(10, 2))
    with pytest.raises(ConfigError, match="reps=0"):
        PerfConfig(reps=0)


def test_table_marks_targets_met_and_missed() -> None:
    result = {
        "breath_latency_ms": {"median": 0.4, "p99": 1.5},
        "proposal_latency_ms": {"10": {"median": 20.0, "p95": 30.0}, "60": {"median": 90.0, "p95": 140.0}},
        "session_60min_wall_s": 12.0, "sessions": [{}, {}], "config": {"session_minutes": 60.0},
    }
    table = perf_table(result)
    assert ("| breath (estimator update + stopping decision) | median 0.400 ms, p99 1.500 ms | – "
            "| p99 < 2 ms | yes |") in table
    assert ("| proposal, 60 observations (GP fit + EI) | median 90.0 ms, p95 140.0 ms | – "
            "| p95 < 100 ms | no |") in table
    assert "| 60-minute simulated session (median of 2) | 12.0 s | – | < 20 s | yes |" in table
