"""bridge.bench.estimator (``hilbo bench estimator``) at toy size."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from bridge.bench.cli import bench_main
from bridge.bench.estimator import (
    ESTIMATORS,
    HORIZONS_S,
    evaluate,
    parse_transition_config,
    realistic_people,
    replay_people,
    summarize,
    synthetic_people,
)
from drivers.cart.line import encode_line
from hilbo_core.errors import ConfigError
from hilbo_core.types import BreathRecord

# Brockway at RER 0.9: W = VO2·(16.58 + 0.9·4.51)/60 with VO2 in ml/min.
_W_PER_ML_MIN = (16.58 + 0.9 * 4.51) / 60.0


def test_synthetic_people_are_pure_and_follow_the_stated_model() -> None:
    a, b = synthetic_people(4, 7), synthetic_people(4, 7)
    assert all(np.array_equal(x.watts, y.watts) for p, q in zip(a, b, strict=True)
               for x, y in zip(p, q, strict=True))
    assert not np.array_equal(a[0][0].watts, synthetic_people(4, 8)[0][0].watts)
    for person in a:
        assert [bout.evaluate for bout in person] == [False, True, True, True, True]
        for bout in person:
            dt = np.diff(bout.t_s)
            assert np.all(dt >= 2.0) and np.all(dt <= 3.5)
            assert np.all(bout.watts > 0) and 120.0 <= bout.truth_w <= 1200.0


def test_realistic_people_walk_the_wearer_through_settings_in_a_row() -> None:
    a, b = realistic_people(2, 3, bouts=3), realistic_people(2, 3, bouts=3)
    assert all(np.array_equal(x.watts, y.watts) for p, q in zip(a, b, strict=True)
               for x, y in zip(p, q, strict=True))
    for person in a:
        assert [bout.evaluate for bout in person] == [False, True, True]
        for bout in person:
            assert np.all(np.diff(bout.t_s) > 0) and bout.t_s[0] > 0
            assert np.all(bout.watts > 0) and 150.0 < bout.truth_w < 1000.0
            assert 0.0 <= bout.first_distance < 0.5  # hip settings change the cost by < 25 %
    # The people are different subjects.
    assert a[0][0].truth_w != a[1][0].truth_w


def test_realistic_people_stand_between_settings_for_large_steps() -> None:
    base = realistic_people(2, 3, bouts=4)
    rested = realistic_people(2, 3, bouts=4, rest_every=2)
    # Without rests (the default, and what bench pairs uses), the people of earlier versions:
    # reference values from the version before the rests existed.
    assert base[1][3].watts[:2] == pytest.approx([287.60354972, 348.49644039], rel=1e-9)
    assert base[1][3].truth_w == pytest.approx(340.6157516889224, rel=1e-12)
    for person in rested:
        # Stand, 2 settings, stand, 2 settings: the first rest starts the chain, the rest scored.
        assert [b.label for b in person] == ["standing", "", "", "standing", "", ""]
        assert [b.evaluate for b in person] == [False, True, True, True, True, True]
        large = [b.first_distance >= 0.5 for b in person[1:]]
        assert large == [True, False, True, True, False]  # up from rest, down to rest, up again
        assert 80.0 < person[3].truth_w < 160.0 < person[1].truth_w
    with pytest.raises(ConfigError, match="rest_every=-1"):
        realistic_people(1, 0, rest_every=-1)


def test_evaluate_and_summarize_toy() -> None:
    people = synthetic_people(3, 1)
    rows = evaluate(people)
    assert {r["estimator"] for r in rows} == set(ESTIMATORS)
    assert {r["horizon_s"] for r in rows} <= set(HORIZONS_S)
    summary = summarize(rows)
    keys = {"estimator", "horizon_s", "step", "n", "mape_pct", "bias_pct", "z_mean", "z_sd", "coverage95_pct"}
    assert all(set(s) == keys for s in summary)
    every = [s for s in summary if s["step"] == "all" and s["horizon_s"] == 30.0]
    assert {s["n"] for s in every} == {12}  # 3 people × 4 scored transitions, all ≥ 45 s long
    assert all(s["mape_pct"] >= 0 for s in summary)


def test_summary_hand_computed() -> None:
    rows = [{"estimator": "transition", "horizon_s": 60.0, "step": "small", "truth": 100.0, "mean": 110.0,
             "sd": 10.0},
            {"estimator": "transition", "horizon_s": 60.0, "step": "large", "truth": 200.0, "mean": 150.0,
             "sd": 10.0}]
    s = {x["step"]: x for x in summarize(rows, ["transition"], [60.0])}
    assert s["all"]["mape_pct"] == pytest.approx(17.5)  # (10 % + 25 %) / 2
    assert s["all"]["bias_pct"] == pytest.approx(-7.5)
    assert s["all"]["z_mean"] == pytest.approx(-2.0)  # z = +1 and −5
    assert s["all"]["z_sd"] == pytest.approx(math.sqrt(18.0))
    assert s["all"]["coverage95_pct"] == pytest.approx(50.0)
    assert s["small"]["n"] == s["large"]["n"] == 1


def _write_recording(path: Path) -> list[float]:
    """Three 300-s bouts: 300 W, then 500 W and 350 W steady states, τ = 40 s, every 2.5 s."""
    rng = np.random.default_rng(0)
    levels, starts = [300.0, 500.0, 350.0], [0.0, 300.0, 600.0]
    lines, seq, body = [b"# hilbo-line recording\n"], 0, 300.0
    for c, t0 in zip(levels, starts, strict=True):
        b0 = body
        for t in np.arange(1.0, 300.0, 2.5):
            body = c + (b0 - c) * math.exp(-t / 40.0)
            w = body * (1.0 + 0.05 * rng.normal())
            vo2 = w / _W_PER_ML_MIN
            rec = BreathRecord(t_s=t0 + float(t), vo2_ml_min=vo2, vco2_ml_min=0.9 * vo2)
            lines.append(encode_line(rec, seq))
            seq += 1
    path.write_bytes(b"".join(lines))
    return starts[1:]


def test_replay_reads_a_recording_and_takes_the_truth_after_the_last_horizon(tmp_path: Path) -> None:
    f = tmp_path / "rec.hbr"
    transitions = _write_recording(f)
    (person,) = replay_people(f, transitions)
    assert [b.evaluate for b in person] == [False, True, True]
    assert person[1].truth_w == pytest.approx(500.0, rel=0.03)
    assert person[2].truth_w == pytest.approx(350.0, rel=0.03)
    assert person[1].t_s[0] == pytest.approx(1.0)
    # The truth: the breaths after 180 s (181, 183.5, ..., 298.5 s: 48), with the SE of their mean
    # (5 % noise: ≈ 0.05·500/√48 ≈ 3.6 W).
    tail = person[1].watts[person[1].t_s > 180.0]
    assert person[1].truth_n == tail.size == 48
    assert person[1].truth_w == pytest.approx(float(tail.mean()), rel=1e-12)
    assert person[1].truth_se_w == pytest.approx(float(tail.std(ddof=1)) / math.sqrt(48), rel=1e-12)
    assert 2.0 < person[1].truth_se_w < 6.0
    with pytest.raises(ConfigError, match="increasing"):
        replay_people(f, [300.0, 200.0])
    with pytest.raises(ConfigError, match="cannot read"):
        replay_people(tmp_path / "missing.hbr", [10.0])
    with pytest.raises(ConfigError, match=r"no breaths between 5000 s and the end of the file \(its breaths "
                                          r"run from 1 to 89\d\.\d+ s\)"):
        replay_people(f, [300.0, 5000.0])
    f.with_suffix(".csv").write_text("time,oxygen,co2\n1,300,270\n")
    with pytest.raises(ConfigError, match="here: --csv-columns TIME,VO2,VCO2"):
        replay_people(f.with_suffix(".csv"), [10.0])


def test_replay_scores_by_label_or_skips_bouts_too_short_for_a_truth(tmp_path: Path) -> None:
    f = tmp_path / "rec.hbr"
    _write_recording(f)
    # A 30-s "rest" inside the second bout: too short for a truth after 180 s, so not scored by
    # default; the bout it interrupts is scored from 330 s on.
    (person,) = replay_people(f, [300.0, 330.0, 600.0], labels=["rest", "walk", "walk"])
    assert [(b.label, b.evaluate) for b in person] == [("", False), ("rest", False), ("walk", True),
                                                        ("walk", True)]
    assert "no truth window" in person[1].note and person[0].note.startswith("first bout")
    (person,) = replay_people(f, [300.0, 600.0], labels=["up", "down"], score=["down"])
    assert [b.evaluate for b in person] == [False, False, True]
    assert person[1].note == "label 'up' not in --score"
    with pytest.raises(ConfigError, match="too short for a truth"):
        replay_people(f, [300.0, 330.0, 600.0], labels=["rest", "walk", "walk"], score=["rest"])
    with pytest.raises(ConfigError, match=r"no bout is labelled \['run'\]"):
        replay_people(f, [300.0, 600.0], labels=["up", "down"], score=["run"])
    with pytest.raises(ConfigError, match="one label per transition"):
        replay_people(f, [300.0, 600.0], labels=["up"])


def test_summary_pools_the_horizons_it_is_asked_to() -> None:
    rows = [{"estimator": "transition", "horizon_s": h, "step": "small", "truth": 100.0, "mean": 100.0 + d,
             "sd": 1.0} for h, d in ((30.0, 9.0), (60.0, 1.0), (180.0, -1.0))]
    pooled = [x for x in summarize(rows, ["transition"], [30.0, 60.0, 180.0], pooled=(60.0, 180.0))
              if x["horizon_s"] == "60-180" and x["step"] == "all"]
    assert len(pooled) == 1 and pooled[0]["n"] == 2  # 30 s left out
    assert pooled[0]["z_mean"] == pytest.approx(0.0) and pooled[0]["mape_pct"] == pytest.approx(1.0)


def test_replay_reads_a_vendor_export_as_a_session_would() -> None:
    # A COSMED CSV export (format detected as `hilbo cart inspect` does): 4 breaths, 3–62.5 s.
    data = Path(__file__).resolve().parents[1] / "data" / "cart" / "cosmed_k5.csv"
    (person,) = replay_people(data, [30.0])
    # Read and split; too short to be scored (its second bout ends 32.5 s in: no truth window).
    assert [b.evaluate for b in person] == [False, False]
    assert "no truth window" in person[1].note
    assert sum(b.t_s.size for b in person) == 4
    assert np.all(np.concatenate([b.watts for b in person]) > 0)


def test_cli_synthetic_and_replay(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "syn"
    assert bench_main(["estimator", "--n", "2", "--seed", "3", "--out", str(out)]) == 0
    doc = json.loads((out / "estimator.json").read_text())
    assert doc["benchmark"] == "estimator" and doc["transitions"] == 8
    assert doc["command"].startswith("hilbo bench estimator --wearer synthetic --n 2 --seed 3")
    assert (out / "estimator_table.md").read_text().startswith("| estimator |")
    f = tmp_path / "rec.hbr"
    transitions = _write_recording(f)
    out2 = tmp_path / "rep"
    assert bench_main(["estimator", "--replay", str(f), "--transitions", ",".join(map(str, transitions)),
                       "--estimators", "transition,first_order_42", "--out", str(out2)]) == 0
    doc = json.loads((out2 / "estimator.json").read_text())
    assert doc["transitions"] == 2
    assert {s["estimator"] for s in doc["summary"]} == {"transition", "first_order_42"}
    assert [b["scored"] for b in doc["bouts"]] == [False, True, True]
    assert "MAPE" in capsys.readouterr().out
    events = tmp_path / "events.csv"
    events.write_text("t_s,label\n300,up\n600,down\n")
    out3 = tmp_path / "ev"
    assert bench_main(["estimator", "--replay", str(f), "--events", str(events), "--score", "down",
                       "--estimators", "transition", "--out", str(out3)]) == 0
    doc = json.loads((out3 / "estimator.json").read_text())
    assert doc["transitions"] == 1 and "--events" in doc["command"] and "--score down" in doc["command"]
    assert "not in --score" in (out3 / "estimator_bouts.md").read_text()


@pytest.mark.parametrize("argv, message", [
    (["--replay", "x.hbr"], "needs --transitions"),
    (["--transitions", "10"], "go with --replay"),
    (["--replay", "x.hbr", "--transitions", "10", "--score", "run"], "needs --events"),
    (["--bout-s", "-5"], "--bout-s -5"),
    (["--wearer", "nobody"], "--wearer 'nobody'"),
    (["--rest-every", "2"], "--rest-every goes with --wearer realistic"),
    (["--estimators", "kalman"], "kalman"),
    (["--transition-config", "timing=10"], "timing=10"),
    (["--transition-config", "timing_sd_s=ten"], "'ten' is not a number"),
    (["--transition-config", "timing_sd_s=-1"], "timing_sd_s=-1"),
])
def test_cli_bad_input_exits_2(argv: list[str], message: str, tmp_path: Path,
                               capsys: pytest.CaptureFixture[str]) -> None:
    assert bench_main(["estimator", *argv, "--out", str(tmp_path)]) == 2
    assert message in capsys.readouterr().err


@pytest.mark.parametrize("argv, message", [
    (["--n", "0"], "argument --n: expected a whole number >= 1, got '0'"),
    (["--wearer", "realistic", "--rest-every", "-1"], "argument --rest-every: expected an integer >= 0"),
    (["--seed", "x"], "argument --seed: expected an integer >= 0, got 'x'"),
])
def test_cli_bad_numbers_are_argparse_usage_errors(argv: list[str], message: str, tmp_path: Path,
                                                   capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exc:
        bench_main(["estimator", *argv, "--out", str(tmp_path)])
    assert exc.value.code == 2 and message in capsys.readouterr().err


def test_transition_config_option_sets_the_estimator_it_names(tmp_path: Path) -> None:
    # The option's fields reach the estimator: integers stay integers, delays are ';'-separated,
    # and a non-default config gives different estimates from the default on the same bouts.
    cfg = parse_transition_config("timing_sd_s=10, n_tau=17, delays_s=0;10")
    assert cfg is not None and cfg.timing_sd_s == 10.0 and cfg.n_tau == 17 and cfg.delays_s == (0.0, 10.0)
    assert parse_transition_config(None) is None and parse_transition_config(" ") is None
    people = synthetic_people(2, 4, bout_s=120.0)
    base = evaluate(people, ("transition",), (60.0,))
    other = evaluate(people, ("transition",), (60.0,), config=parse_transition_config("timing_sd_s=20"))
    assert [r["truth"] for r in base] == [r["truth"] for r in other]
    assert any(abs(a["mean"] - b["mean"]) > 1e-6 * a["mean"] for a, b in zip(base, other, strict=True))
    out = tmp_path / "tc"
    assert bench_main(["estimator", "--n", "1", "--seed", "3", "--estimators", "transition",
                       "--transition-config", "timing_sd_s=10", "--out", str(out)]) == 0
    assert "--transition-config timing_sd_s=10" in json.loads((out / "estimator.json").read_text())["command"]
