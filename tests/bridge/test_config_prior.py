"""The [prior] table: inline points, previous sessions' logs, a population CSV; errors that name the row."""

from __future__ import annotations

import asyncio
import io
import json
import math
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

import bridge.sim.virtual
from bridge.config import _cmd_check, parse_config, summarize
from bridge.errors import BridgeConfigError
from bridge.log import SessionLog
from bridge.log.reader import read_log
from bridge.log.resume import rebuild_optimizer
from hilbo_core.optimizer import Evaluation, PriorObservation
from hilbo_core.presets import hip_6d

SPACE = hip_6d()
BASE = """\
[session]
subject = "S01"
body_mass_kg = 75.0

[space]
preset = "hip_6d"

[cart]
transport = "udp"
[cart.options]
port = 6000

[can]
interface = "virtual"
channel = "test"
"""
GOOD = {"t_on": 10.0, "t_p": 30.0, "t_off": 50.0, "F_p": 150.0, "F_r": 0.5, "F_f": 0.5}


def _params_toml(params: dict[str, float]) -> str:
    return "{ " + ", ".join(f"{k} = {v}" for k, v in params.items()) + " }"


def _settings(n: int, seed: int = 0) -> list[dict[str, float]]:
    rng = np.random.default_rng(seed)
    return [SPACE.to_dict(SPACE.from_unit(u)) for u in SPACE.sample_unit(n, rng)]


def write_session_log(path: Path, evaluations: list[dict]) -> Path:
    """A small session log holding only /observations (what a previous day's prior needs)."""
    with SessionLog(path, session_id="day-1", config_json={"space": "hip_6d"}, flush_interval_s=None,
                    param_names=SPACE.names) as log:
        for i, ev in enumerate(evaluations):
            e = Evaluation(index=i, params=ev["params"], mean=ev["mean"], var=ev["var"],
                           breaths=ev.get("breaths", 45), duration_s=120.0, phase="exploration",
                           stopped_early=ev.get("stopped_early", False),
                           reason="threshold" if ev.get("stopped_early") else "max_measurements")
            log.log_observation(e, t_start=200.0 * i, t_end=200.0 * i + 120.0)
    return path


@pytest.fixture(scope="module")
def day1_log(tmp_path_factory: pytest.TempPathFactory) -> Path:
    evs = [{"params": p, "mean": 380.0 + 5 * i, "var": 25.0 + i, "stopped_early": i == 2}
           for i, p in enumerate(_settings(5))]
    return write_session_log(tmp_path_factory.mktemp("prior") / "day1.mcap", evs)


def with_prior(prior: str) -> str:
    return BASE + "\n[prior]\n" + prior


# --------------------------------------------------------------------------------------------
# The three sources
# --------------------------------------------------------------------------------------------


def test_no_prior_table_means_no_priors() -> None:
    cfg = parse_config(BASE)
    assert cfg.prior.priors == () and cfg.prior.describe() == "none"
    assert "prior     none" in summarize(cfg)


def test_inline_observations_are_validated_and_inflated_per_source() -> None:
    cfg = parse_config(with_prior(
        f"observations = [{{ params = {_params_toml(GOOD)}, mean_w = 395.0, var_w2 = 150.0 }},\n"
        f"  {{ params = {_params_toml(GOOD | {'F_p': 120.0})}, mean_w = 401, sd_w = 10, "
        f"source = \"population\", note = \"lab mean\" }}]\n"))
    a, b = cfg.prior.observations
    assert a == PriorObservation(GOOD, 395.0, 4.0 * 150.0, "short_bout:inline 0")  # default: short bout
    assert b.params["F_p"] == 120.0 and b.source == "population:inline 1"
    assert b.var == pytest.approx(1.0 * 100.0 + 900.0)  # population: ×1 + (30 W)²
    assert cfg.prior.priors == (a, b)
    assert cfg.prior.describe() == "2 prior observations: 2 inline (population, short_bout)"
    json.dumps(cfg.to_json())  # the log's config channel


def test_array_of_tables_form_and_inflation_overrides() -> None:
    cfg = parse_config(with_prior(
        "[[prior.observations]]\n"
        f"params = {_params_toml(GOOD)}\nmean_w = 390.0\nvar_w2 = 100.0\n"
        "[prior.inflation.short_bout]\nextra_var_w2 = 50.0\n"))
    (p,) = cfg.prior.priors
    assert p.var == 4.0 * 100.0 + 50.0  # factor kept at its default, extra overridden
    assert cfg.prior.inflation["short_bout"].factor == 4.0
    assert cfg.prior.inflation["previous_session"].extra_var_w2 == 100.0
    assert "short_bout x 4 + 50 W²" in summarize(cfg)


def test_a_previous_sessions_log_becomes_previous_session_priors(day1_log: Path) -> None:
    cfg = parse_config(with_prior(f'logs = ["{day1_log.as_posix()}"]\n'
                                  "[prior.inflation.previous_session]\nfactor = 3.0\n"))
    evs = read_log(day1_log).data("/observations")
    assert len(cfg.prior.from_logs) == len(evs) == 5 and cfg.prior.log_counts == (5,)
    for p, e in zip(cfg.prior.from_logs, evs, strict=True):
        assert p.params == e["params"] and p.mean == e["mean"]
        assert p.var == pytest.approx(3.0 * e["var"] + 100.0)
        assert p.source.startswith("day1.mcap:previous_session:evaluation ")
    assert f"5 from log {day1_log}" in cfg.prior.describe()
    details = cfg.prior.event_details()
    assert details["n_priors"] == 5 and details["by_source"] == {"previous_session": 5}
    assert details["logs"] == {str(day1_log): 5}


def test_a_population_table_absolute_and_relative(tmp_path: Path) -> None:
    rows = _settings(3, seed=4)
    header = [*SPACE.names, "mean", "sd", "subject"]
    text = ",".join(header) + "\n" + "".join(
        ",".join([*(f"{r[n]:.6g}" for n in SPACE.names), f"{0.9 + 0.01 * i}", "0.02", f"P{i}"]) + "\n"
        for i, r in enumerate(rows))
    (tmp_path / "pop.csv").write_text(text)
    pop = (tmp_path / "pop.csv").as_posix()
    cfg = parse_config(with_prior(f'table = "{pop}"\ntable_baseline_w = 400.0\n'))
    assert len(cfg.prior.from_table) == 3
    first = cfg.prior.from_table[0]
    assert first.mean == pytest.approx(0.9 * 400.0)
    assert first.var == pytest.approx((0.02 * 400.0) ** 2 + 900.0)
    assert first.source == "population:row 0"
    assert "3 from table" in cfg.prior.describe() and "relative to 400 W" in cfg.prior.describe()
    # Absolute: var column in W².
    (tmp_path / "abs.csv").write_text(",".join([*SPACE.names, "mean", "var"]) + "\n"
                                      + ",".join([*(str(GOOD[n]) for n in SPACE.names), "410", "400"]) + "\n")
    cfg = parse_config(with_prior(f'table = "{(tmp_path / "abs.csv").as_posix()}"\n'))
    (p,) = cfg.prior.from_table
    assert (p.mean, p.var) == (410.0, 400.0 + 900.0)


def test_all_sources_together_and_config_check_reports_them(day1_log: Path, tmp_path: Path) -> None:
    (tmp_path / "abs.csv").write_text(",".join([*SPACE.names, "mean", "var"]) + "\n"
                                      + ",".join([*(str(GOOD[n]) for n in SPACE.names), "410", "400"]) + "\n")
    text = with_prior(f"observations = [{{ params = {_params_toml(GOOD)}, mean_w = 395.0, var_w2 = 150 }}]\n"
                      f'logs = ["{day1_log.as_posix()}"]\ntable = "{(tmp_path / "abs.csv").as_posix()}"\n')
    path = tmp_path / "s.toml"
    path.write_text(text)
    cfg = parse_config(text)
    kinds = [p.source.split(":")[0] for p in cfg.prior.priors]
    assert kinds == ["short_bout", *["day1.mcap"] * 5, "population"]
    assert cfg.prior.sources_used == ("population", "previous_session", "short_bout")
    out, err = io.StringIO(), io.StringIO()
    assert _cmd_check(SimpleNamespace(config=str(path), samples=0), out, err) == 0
    assert "prior     7 prior observations: 1 inline (short_bout); 5 from log" in out.getvalue()
    assert "1 from table" in out.getvalue() and "previous_session x 2 + 100 W²" in out.getvalue()


# --------------------------------------------------------------------------------------------
# Bad input: the error names the row (or path), the value and what was expected
# --------------------------------------------------------------------------------------------


def _inline(params: dict, rest: str = "mean_w = 395.0, var_w2 = 150.0") -> str:
    body = ", ".join(f"{k} = {v}" for k, v in params.items())
    return f"observations = [{{ params = {{ {body} }}, {rest} }}, {{ params = {{ {body} }}, {rest} }}]\n"


@pytest.mark.parametrize(("prior", "needles"), [
    (_inline(GOOD | {"F_p": 400.0}), ["prior.observations[0].params", "outside the space",
                                      "F_p=400 is outside its bounds [50, 250]"]),
    (_inline(GOOD | {"t_on": 20.0, "t_p": 25.0}), ["prior.observations[0].params", "outside the space",
                                                   "t_on <= t_p - 15"]),
    (_inline(GOOD | {"t_on": "nan"}), ["prior.observations[0].params.t_on = nan", "finite number"]),
    (_inline(GOOD, "mean_w = nan, var_w2 = 1.0"), ["prior.observations[0].mean_w = nan", "finite"]),
    (_inline(GOOD, "mean_w = 390.0, var_w2 = 0.0"), ["prior.observations[0].var_w2 = 0.0", "(0, "]),
    (_inline(GOOD, "mean_w = 390.0, var_w2 = -4.0"), ["prior.observations[0].var_w2 = -4.0", "(0, "]),
    (_inline(GOOD, "mean_w = 390.0, var_w2 = nan"), ["prior.observations[0].var_w2 = nan"]),
    (_inline(GOOD, "mean_w = 390.0, sd_w = 0"), ["prior.observations[0].sd_w = 0", "(0, "]),
    (_inline(GOOD, "mean_w = 390.0"), ["prior.observations[0]: give the uncertainty", "found neither"]),
    (_inline(GOOD, "mean_w = 390.0, var_w2 = 1.0, sd_w = 1.0"), ["not both"]),
    (_inline(GOOD, "var_w2 = 1.0"), ["prior.observations[0].mean_w is missing"]),
    (_inline(GOOD, 'mean_w = 390.0, var_w2 = 1.0, source = "yesterday"'),
     ["prior.observations[0].source = 'yesterday'", "'population', 'previous_session', 'short_bout'"]),
    (_inline({**{k: v for k, v in GOOD.items() if k != "t_on"}, "t_onn": 10.0}),
     ["unknown key prior.observations[0].params.t_onn", "did you mean 't_on'", "t_off, t_on, t_p"]),
    (_inline({k: v for k, v in GOOD.items() if k != "F_f"}),
     ["prior.observations[0].params", "missing parameter(s) ['F_f']"]),
    ("observations = [1]\n", ["prior.observations[0] = 1: expected a table"]),
    ("observations = {}\n", ["prior.observations = {}", "expected a list"]),
    ("logs = \"day1.mcap\"\n", ["prior.logs = 'day1.mcap'", "a list of strings"]),
    ("table_baseline_w = 400.0\n", ["prior.table_baseline_w = 400", "only with prior.table"]),
    ("[prior.inflation.short_bout]\nfactor = 0.5\n", ["prior.inflation.short_bout.factor = 0.5", "[1, "]),
    ("[prior.inflation.population]\nextra_var_w2 = -1\n", ["prior.inflation.population.extra_var_w2 = -1"]),
    ("[prior.inflation.day_before]\nfactor = 2\n",
     ["unknown key prior.inflation.day_before", "population, previous_session, short_bout"]),
    ("colour = 1\n", ["unknown key prior.colour", "inflation, logs, observations, table, table_baseline_w"]),
])
def test_bad_inline_priors_name_the_row_the_value_and_what_was_expected(prior: str,
                                                                        needles: list[str]) -> None:
    with pytest.raises(BridgeConfigError) as info:
        parse_config(with_prior(prior))
    for needle in needles:
        assert needle in str(info.value), (needle, str(info.value))


def test_the_second_bad_row_is_named_as_such() -> None:
    ok = f"{{ params = {_params_toml(GOOD)}, mean_w = 395.0, var_w2 = 150.0 }}"
    bad = f"{{ params = {_params_toml(GOOD)}, mean_w = 395.0, var_w2 = -1.0 }}"
    with pytest.raises(BridgeConfigError, match=r"prior\.observations\[1\]\.var_w2 = -1\.0"):
        parse_config(with_prior(f"observations = [{ok}, {bad}]\n"))


def _csv(tmp_path: Path, rows: list[list[str]], header: list[str] | None = None) -> str:
    header = header or [*SPACE.names, "mean", "var"]
    path = tmp_path / "pop.csv"
    path.write_text("\n".join(",".join(r) for r in [header, *rows]) + "\n")
    return f'table = "{path.as_posix()}"\n'


def _row(**over: str) -> list[str]:
    values = {k: str(v) for k, v in GOOD.items()} | {"mean": "400", "var": "100"} | over
    return [values[k] for k in [*SPACE.names, "mean", "var"]]


@pytest.mark.parametrize(("rows", "needles"), [
    ([_row(), _row(), _row(mean="nan")], ["prior row 2 mean='nan'", "finite number"]),
    ([_row(), _row(var="0")], ["prior row 1 var='0'", "variance > 0"]),
    ([_row(), _row(var="-3")], ["prior row 1 var='-3'", "variance > 0"]),
    ([_row(F_p="300")], ["prior row 0", "F_p=300 is outside its bounds"]),
    ([_row(t_off="35")], ["prior row 0", "constraint 't_p + 15 <= t_off' is violated"]),
    ([_row(F_r="x")], ["prior row 0 parameter F_r='x' is not a number"]),
    ([[*_row(), "7"]], ["prior row 0 (line 2) has more fields than the header"]),
])
def test_bad_table_rows_are_named(tmp_path: Path, rows: list[list[str]], needles: list[str]) -> None:
    with pytest.raises(BridgeConfigError) as info:
        parse_config(with_prior(_csv(tmp_path, rows)))
    msg = str(info.value)
    assert f"prior.table = '{(tmp_path / 'pop.csv').as_posix()}'" in msg
    for needle in needles:
        assert needle in msg, (needle, msg)


def test_table_header_problems(tmp_path: Path) -> None:
    with pytest.raises(BridgeConfigError, match=r"prior row 0: unknown column\(s\) \['t_onn'\]"):
        parse_config(with_prior(_csv(tmp_path, [_row()], ["t_onn", *SPACE.names[1:], "mean", "var"])))
    with pytest.raises(BridgeConfigError, match="no data rows"):
        parse_config(with_prior(_csv(tmp_path, [])))
    with pytest.raises(BridgeConfigError, match=r"prior\.table = 'nowhere\.csv': no such file"):
        parse_config(with_prior('table = "nowhere.csv"\n'))


def test_bad_logs_name_the_path(tmp_path: Path) -> None:
    with pytest.raises(BridgeConfigError, match=r"prior\.logs\[1\] = 'missing\.mcap': no such file"):
        ok = write_session_log(tmp_path / "a.mcap", [{"params": GOOD, "mean": 390.0, "var": 9.0}])
        parse_config(with_prior(f'logs = ["{ok.as_posix()}", "missing.mcap"]\n'))
    with pytest.raises(BridgeConfigError, match=r"prior\.logs\[1\] = .*: the same log as prior\.logs\[0\]"):
        parse_config(with_prior(f'logs = ["{ok.as_posix()}", "{ok.parent.as_posix()}/./a.mcap"]\n'))
    (tmp_path / "notes.mcap").write_text("not a log")
    with pytest.raises(BridgeConfigError, match=r"prior\.logs\[0\] = '.*notes\.mcap': cannot read it"):
        parse_config(with_prior(f'logs = ["{(tmp_path / "notes.mcap").as_posix()}"]\n'))
    empty = write_session_log(tmp_path / "empty.mcap", [])
    with pytest.raises(BridgeConfigError, match="holds no completed evaluation"):
        parse_config(with_prior(f'logs = ["{empty.as_posix()}"]\n'))
    # A log of another space (or bounds the config narrowed): the evaluation is named.
    wide = write_session_log(tmp_path / "wide.mcap", [{"params": GOOD, "mean": 390.0, "var": 9.0},
                                                      {"params": GOOD | {"F_p": 240.0}, "mean": 390.0,
                                                       "var": 9.0}])
    narrowed = BASE.replace('preset = "hip_6d"\n', 'preset = "hip_6d"\n[space.bounds]\nF_p = [50, 200]\n')
    with pytest.raises(BridgeConfigError, match=r"wide\.mcap'.*prior evaluation 1: .*F_p=240 is outside"):
        parse_config(narrowed + f'\n[prior]\nlogs = ["{wide.as_posix()}"]\n')
    nan_var = write_session_log(tmp_path / "nan.mcap", [{"params": GOOD, "mean": 390.0, "var": math.nan}])
    # (the log cannot hold a NaN variance: the writer drops it, and the reader names the gap)
    with pytest.raises(BridgeConfigError, match=r"nan\.mcap': prior evaluation 0: missing key\(s\) \['var"):
        parse_config(with_prior(f'logs = ["{nan_var.as_posix()}"]\n'))


# --------------------------------------------------------------------------------------------
# Applied by `hilbo run` to a new session, carried by the optimizer state on resume
# --------------------------------------------------------------------------------------------


@pytest.mark.slow  # a whole (short) session over the virtual devices: ~10 s
def test_run_session_starts_with_the_priors_and_the_log_keeps_them(day1_log: Path, tmp_path: Path,
                                                                   monkeypatch: pytest.MonkeyPatch) -> None:
    prior = f'\n[prior]\nlogs = ["{day1_log.as_posix()}"]\n'
    real = bridge.sim.virtual.parse_config
    monkeypatch.setattr(bridge.sim.virtual, "parse_config", lambda text, source: real(text + prior, source))
    cfg = bridge.sim.virtual.VirtualSimConfig(minutes=5.0, seed=2, n_explore=3, max_breaths=10, warmup_s=20.0)
    asyncio.run(bridge.sim.virtual.run_virtual_sim(cfg, tmp_path))
    log = read_log(tmp_path / "session.mcap")
    (event,) = [e for e in log.data("/events") if e["kind"] == "prior"]
    assert event["message"].startswith("5 prior observations: 5 from log")
    assert event["details"]["by_source"] == {"previous_session": 5}
    start = next(s for s in log.data("/optimizer_state") if s["reason"] == "start")
    assert len(start["state"]["priors"]) == 5
    assert [p["mean"] for p in start["state"]["priors"]] == [p["mean"] for p in read_log(day1_log).data(
        "/observations")]
    # The optimizer state carries the priors, so a resume needs no [prior] table.
    opt, _ = rebuild_optimizer(tmp_path / "session.mcap")
    assert len(opt.to_json()["priors"]) == 5
