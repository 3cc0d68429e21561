"""The in-process simulated session behind ``hilbo sim``."""

from __future__ import annotations

import json

import pytest

from bridge.cli.main import main
from bridge.sim.core import SimConfig, run_insim
from hilbo_core.errors import ConfigError
from hilbo_core.presets import hip_6d


def small(**kw) -> SimConfig:
    opts = {"minutes": 7.0, "seed": 2, "n_explore": 4, "max_breaths": 10, "window": 2, "warmup_s": 30.0}
    opts.update(kw)
    return SimConfig(**opts)


def test_session_summary_is_complete_and_consistent() -> None:
    seen = []
    s = run_insim(small(), on_evaluation=lambda rec, opt: seen.append(rec))
    assert s["n_evaluations"] == len(s["evaluations"]) == len(seen) > 3
    assert s["n_early_stops"] == sum(e["stopped_early"] for e in s["evaluations"])
    space = hip_6d()
    for e in s["evaluations"]:
        assert space.is_feasible(e["params"])
        assert e["t_end"] > e["t_start"] and e["var"] > 0 and 1 <= e["breaths"] <= 10
    starts = [e["t_start"] for e in s["evaluations"]]
    assert starts == sorted(starts)
    # The session never runs past its minutes by more than one breath.
    assert s["evaluations"][-1]["t_end"] <= 7 * 60 + 10
    assert s["true_cost_of_best"] >= s["true_optimum"]["cost_w"] - 1e-9
    assert s["regret_w"] == pytest.approx(s["true_cost_of_best"] - s["true_optimum"]["cost_w"])
    assert s["best_params"] in [e["params"] for e in s["evaluations"]]


def test_same_seed_same_session() -> None:
    a, b = run_insim(small(seed=4)), run_insim(small(seed=4))
    assert a["evaluations"] == b["evaluations"]


def test_too_short_session_is_a_clear_error() -> None:
    with pytest.raises(ConfigError, match="minutes=2"):
        run_insim(small(minutes=2))


def test_fitting_ahead_takes_the_fits_off_the_proposals(optimize_calls: list[int]) -> None:
    a = run_insim(small(seed=5, refit="ahead"))
    n = a["n_evaluations"]
    # One fit ahead after each ask from 2 completed evaluations on (on 2, 3, ..., n - 1), one
    # for the final recommendation at most; no proposal fitted by itself.
    assert optimize_calls[: n - 2] == list(range(2, n))
    assert len(optimize_calls) <= n - 1
    assert a["evaluations"] == run_insim(small(seed=5, refit="ahead"))["evaluations"]


@pytest.mark.parametrize(("kw", "match"), [({"minutes": 0}, "minutes"), ({"speed": -1.0}, "speed"),
                                           ({"refit": "never"}, "refit='never'; expected")])
def test_bad_sim_config(kw, match) -> None:
    with pytest.raises(ConfigError, match=match):
        small(**kw)


@pytest.mark.slow
def test_cli_writes_summary(tmp_path, capsys) -> None:
    out = tmp_path / "run"
    assert main(["sim", "--engine", "core", "--minutes", "22", "--seed", "3", "--out", str(out)]) == 0
    summary = json.loads((out / "summary.json").read_text())
    for key in ("n_evaluations", "n_early_stops", "evaluations", "best_params", "best_mean",
                "true_optimum", "true_cost_of_best"):
        assert key in summary
    assert summary["n_evaluations"] > 6
    assert str(out / "summary.json") in capsys.readouterr().out


def test_cli_rejects_bad_speed(capsys) -> None:
    with pytest.raises(SystemExit) as exc:
        main(["sim", "--speed", "fast"])
    assert exc.value.code == 2
    assert "speed must be 'max' or a positive number, got 'fast'" in capsys.readouterr().err


def test_the_walking_protocol_follows_the_rule_unless_named() -> None:
    # The sound rule walks the fast protocol (3 exploration settings, a confirmation), the seed's
    # rules Kim et al. 2019's (6 settings, none), as [protocol] protocol does.
    assert small().walking_protocol.value == "fast"
    assert small(stopping="adaptive").walking_protocol.value == "seed"
    assert small(protocol="seed").walking_protocol.value == "seed"
    assert SimConfig(stopping="fixed").explore_points == 6 and SimConfig().explore_points == 3
    assert small().protocol_config().confirm_s == 240.0
    assert small(stopping="adaptive").protocol_config().confirm_s is None
    with pytest.raises(ConfigError, match="protocol='quick'"):
        small(protocol="quick")
