"""The session config: golden parse, the shipped example, and errors that name key, value, range."""

from __future__ import annotations

import argparse
import io
import json
import re
import subprocess
import sys
from pathlib import Path

import pytest

from bridge.collector import GcMode
from bridge.config import (
    ALLOWED_KEYS,
    TABLES,
    BusErrorPolicy,
    CanConfig,
    HilboConfig,
    PriorConfig,
    ProtocolConfig,
    RefitMode,
    SessionConfig,
    WatchdogConfig,
    add_config_parser,
    example_config_text,
    load_config,
    parse_config,
    summarize,
)
from bridge.errors import BridgeConfigError, BridgeError
from bridge.proposals import WorkerKind
from bridge.safety import ActuatorLimits, ProfileLimits, SafeProfileGate
from drivers.cart import CartConfig
from drivers.exosuit.endpoint import CanBusConfig
from hilbo_core.gp import KernelKind
from hilbo_core.optimizer import OptimizerConfig, StoppingKind
from hilbo_core.presets import hip_6d
from hilbo_core.space import Parameter, ParameterSpace

EXAMPLE = Path(__file__).resolve().parents[2] / "bridge" / "config_example.toml"

GOLDEN = """\
[session]
subject = "S07"
body_mass_kg = 82.5
out_dir = "runs/s07"
notes = "pilot"

[space]
preset = "hip_6d"
constraints = ["F_r <= F_f + 0.2"]

[space.bounds]
F_p = [60, 200.0]

[protocol]
warmup_s = 120
n_explore = 8
max_breaths = 40
window = 3
budget_breaths = 500
stopping = "fixed"
seed = 11
xi = 0.01
kernel = "se"
n_candidates = 256
n_local = 2
pause_between_bouts = false
refit = "at_proposal"
proposal_worker = "thread"
gc = "automatic"

[cart]
transport = "udp"
[cart.options]
port = 6000

[can]
interface = "virtual"
channel = "bench"
bitrate = 500000
heartbeat_period_ms = 10
push_timeout_ms = 300
push_retries = 1
segment_pace_ms = 0
[can.options]
receive_own_messages = true

[limits]
max_force_n = 220.0
min_onset_pct = 0.0
max_offset_pct = 58.0
max_slope_n_per_pct = 35
max_peak_change_n = 120
n_points = 101
max_consecutive_rejections = 5
[limits.actuators.hip]
max_force_n = 210.0

[watchdog]
device_heartbeat_timeout_ms = 150
cart_data_timeout_s = 30
bus_error = "stop"

[prior]
observations = []
logs = []
"""


def test_golden_config_parses_to_the_expected_dataclasses():
    cfg = parse_config(GOLDEN, source="golden.toml")
    assert cfg.source == "golden.toml" and cfg.text == GOLDEN
    assert cfg.session == SessionConfig("S07", 82.5, Path("runs/s07"), "pilot")
    base = hip_6d()
    params = [p if p.name != "F_p" else Parameter("F_p", 60.0, 200.0, p.unit, p.description)
              for p in base.parameters]
    assert cfg.space.preset == "hip_6d"
    assert cfg.space.space == ParameterSpace(params, [*base.constraints, "F_r <= F_f + 0.2"], name="hip_6d")
    assert cfg.protocol == ProtocolConfig(
        warmup_s=120.0, n_explore=8, max_breaths=40, window=3, budget_min=None, budget_breaths=500,
        stopping=StoppingKind.FIXED, seed=11, xi=0.01, kernel=KernelKind.SE, n_candidates=256,
        n_local=2, pause_between_bouts=False, refit=RefitMode.AT_PROPOSAL,
        proposal_worker=WorkerKind.THREAD, gc=GcMode.AUTOMATIC,
    )
    assert cfg.protocol.optimizer_config() == OptimizerConfig(
        n_explore=8, max_breaths=40, window=3, budget_s=None, budget_breaths=500, stopping="fixed",
        seed=11, xi=0.01, kernel="se", n_candidates=256, n_local=2,
    )
    assert cfg.cart == CartConfig.from_dict({"transport": "udp", "options": {"port": 6000}})
    assert cfg.can == CanConfig(
        bus=CanBusConfig("virtual", "bench", 500_000, {"receive_own_messages": True}),
        heartbeat_period_ms=10.0, push_timeout_ms=300.0, push_retries=1, segment_pace_ms=0.0,
    )
    assert cfg.can.push_kwargs() == {"timeout_s": 0.3, "retries": 1, "pace_s": 0.0}
    assert cfg.can.heartbeat_period_s == 0.01
    assert cfg.limits == ProfileLimits(
        max_force_n=220.0, max_offset_pct=58.0, max_slope_n_per_pct=35.0, max_peak_change_n=120.0,
        max_consecutive_rejections=5,
        actuators={"hip": ActuatorLimits(210.0, 0.0, 58.0, 35.0, 120.0)},  # the rest from [limits]
    )
    assert cfg.watchdog == WatchdogConfig(150.0, 30.0, BusErrorPolicy.STOP)
    assert cfg.prior == PriorConfig()
    assert isinstance(cfg.make_gate(), SafeProfileGate)


def test_defaults_of_the_optional_tables():
    text = GOLDEN.split("[protocol]")[0] + GOLDEN[GOLDEN.index("[cart]"):GOLDEN.index("[limits]")]
    cfg = parse_config(text)
    assert cfg.protocol == ProtocolConfig()
    assert cfg.protocol.budget_s == 2400.0  # Kim et al. 2019's 40-minute optimisation bout
    assert cfg.limits == ProfileLimits() and cfg.watchdog == WatchdogConfig() and cfg.prior == PriorConfig()


def test_the_session_protocol_and_its_expected_end_in_the_summary():
    cfg = parse_config(GOLDEN)
    sp = cfg.protocol.session_protocol_config()
    assert (sp.warmup_s, sp.n_explore, sp.max_breaths, sp.budget_s, sp.budget_breaths) == (
        120.0, 8, 40, None, 500)
    assert cfg.protocol.optimizer_config(with_budget=False).budget_breaths is None
    # 2 x 2-min warm-ups + 8 x 40 breaths x 3 s + 500 breaths x 3 s = 45 min of walking
    assert "expected end about 45 min of walking after the first breath" in summarize(cfg)


def test_the_sound_rules_accept_stop_is_on_at_the_rules_margin_and_can_be_turned_off():
    sound = GOLDEN.replace('stopping = "fixed"', 'stopping = "sound"')
    opt = parse_config(sound).protocol.optimizer_config()
    assert (opt.accept_z, opt.min_decision_s, opt.boundary_s) == (2.0, 30.0, 60.0)
    text = summarize(parse_config(sound))
    assert "no decision before 30 s, sequential boundaries until 60 s, then reject above 1 σ at least, " \
        "accept at 2 σ" in text
    floor = parse_config(GOLDEN.replace('stopping = "fixed"', 'stopping = "sound-floor"'))
    floor_opt = floor.protocol.optimizer_config()
    assert (floor_opt.accept_z, floor_opt.min_decision_s) == (3.0, 60.0)
    assert "no decision before 60 s, reject above 1 σ at least, accept at 3 σ" in summarize(floor)
    off = parse_config(sound.replace("budget_breaths = 500", "budget_breaths = 500\naccept_stop = false"))
    assert off.protocol.optimizer_config().accept_z is None
    assert "no accept stop" in summarize(off)
    two = parse_config(GOLDEN.replace("budget_breaths = 500", "budget_breaths = 500\naccept_z = 2.5"))
    assert two.protocol.optimizer_config().accept_z == 2.5
    with pytest.raises(BridgeConfigError, match="accept_z"):
        parse_config(GOLDEN.replace("budget_breaths = 500", "budget_breaths = 500\naccept_z = -1"))
    with pytest.raises(BridgeConfigError, match="boundary_s"):
        parse_config(GOLDEN.replace("budget_breaths = 500", "budget_breaths = 500\nboundary_s = 0"))


def test_both_budgets_can_be_given():
    cfg = parse_config(GOLDEN.replace("budget_breaths = 500", "budget_breaths = 500\nbudget_min = 30"))
    assert (cfg.protocol.budget_min, cfg.protocol.budget_breaths) == (30.0, 500)


def test_session_min_limits_the_whole_session_and_the_summary_says_so():
    cfg = parse_config(GOLDEN.replace("budget_breaths = 500", "budget_breaths = 500\nsession_min = 30"))
    assert cfg.protocol.session_min == 30.0
    assert cfg.protocol.session_protocol_config().session_s == 1800.0
    # 30 min ends before the budget would (45 min, above): the summary gives the session's end.
    assert "expected end at the first breath past 30 min of walking after the first breath" in summarize(cfg)
    # A budget that ends first keeps the budget's expected end.
    long = parse_config(GOLDEN.replace("budget_breaths = 500", "budget_breaths = 500\nsession_min = 90"))
    assert "expected end about 45 min of walking" in summarize(long)
    assert "at the latest at the first breath past 90 min (session_min)" in summarize(long)
    assert parse_config(GOLDEN).protocol.session_protocol_config().session_s is None  # absent: no limit
    for bad in ("0", "-5", '"60"', "2000"):
        with pytest.raises(BridgeConfigError, match=r"protocol\.session_min = "):
            parse_config(GOLDEN.replace("budget_breaths = 500", f"budget_breaths = 500\nsession_min = {bad}"))


def test_the_example_config_loads_and_is_what_the_command_prints():
    cfg = load_config(EXAMPLE)
    assert isinstance(cfg, HilboConfig) and cfg.source == str(EXAMPLE)
    assert cfg.space.preset == "hip_6d" and cfg.can.bus.interface == "socketcan"
    assert example_config_text() == EXAMPLE.read_text(encoding="utf-8")


@pytest.mark.parametrize("table", [t for t in TABLES if t != "cart"])
def test_the_example_documents_every_key(table):
    text = example_config_text()
    for key in ALLOWED_KEYS[table]:
        assert re.search(rf"^#?\s*{key}\s*=|^#?\s*\[+{table}\.{key}[.\]]", text, re.M), f"{table}.{key}"


def test_to_json_is_strict_json_and_round_trips_through_the_logged_toml():
    cfg = load_config(EXAMPLE)
    data = json.loads(json.dumps(cfg.to_json(), allow_nan=False))
    assert data["limits"]["max_force_n"] == 250.0 and data["protocol"]["stopping"] == "sound"
    assert data["space"]["definition"]["name"] == "hip_6d" and data["can"]["channel"] == "vcan0"
    assert data["cart"]["options"]["port"] == 5050
    assert parse_config(data["toml"]) == cfg
    replay_cart = 'transport = "replay"\n[cart.options]\npath = "b.txt"\nspeed = "max"'
    replay = parse_config(GOLDEN.replace('transport = "udp"\n[cart.options]\nport = 6000', replay_cart))
    assert json.loads(json.dumps(replay.to_json(), allow_nan=False))["cart"]["options"]["speed"] == "inf"


def test_inline_space_definition():
    inline = """
[space]
profile = "hip_6d"
constraints = ["t_on <= t_p - 15", "t_p + 15 <= t_off"]
derived = ["F_sum = F_r + F_f"]
""" + "".join(
        f'[[space.parameters]]\nname = "{p.name}"\nlower = {p.lower}\nupper = {p.upper}\nunit = "{p.unit}"\n'
        for p in hip_6d().parameters
    )
    text = GOLDEN[:GOLDEN.index("[space]")] + inline + GOLDEN[GOLDEN.index("[protocol]"):]
    cfg = parse_config(text)
    assert cfg.space.preset is None
    assert cfg.space.space.names == hip_6d().names and cfg.space.space.name == "hip_6d"
    assert [d.name for d in cfg.space.space.derived] == ["F_sum"]
    # an inline space the builder cannot use is caught on load
    broken = text.replace('name = "F_f"', 'name = "F_x"').replace("F_r + F_f", "F_r + F_x")
    with pytest.raises(BridgeConfigError, match=r"space: the 'hip_6d' force-profile builder cannot build"):
        parse_config(broken)


def _with(table: str, line: str, text: str = GOLDEN) -> str:
    """GOLDEN with ``line`` added at the top of ``[table]``."""
    header = f"[{table}]\n"
    assert header in text
    return text.replace(header, header + line + "\n", 1)


@pytest.mark.parametrize(("table", "line", "suggestion"), [
    ("session", "subjcet = 'x'", "subject"),
    ("space", "constraint = []", "constraints"),
    ("space.bounds", "F_pp = [60, 200]", "F_p"),
    ("protocol", "max_breath = 30", "max_breaths"),
    ("cart", "fromat = 'csv'", "format"),
    ("cart.options", "prot = 1", "port"),
    ("can", "bitrat = 500000", "bitrate"),
    ("can.options", "recieve_own_messages = true", "receive_own_messages"),
    ("limits", "max_force = 100.0", "max_force_n"),
    ("limits.actuators.hip", "max_slope = 1.0", "max_slope_n_per_pct"),
    ("watchdog", "bus_eror = 'stop'", "bus_error"),
    ("prior", "log = []", "logs"),
])
def test_every_table_rejects_an_unknown_key_with_a_suggestion(table, line, suggestion):
    key = line.split("=", 1)[0].strip()
    with pytest.raises(BridgeConfigError) as info:
        parse_config(_with(table, line))
    msg = str(info.value)
    assert f"unknown key {table}.{key} = " in msg
    assert f"(did you mean {suggestion!r}?)" in msg
    assert f"allowed keys in [{table}]:" in msg and suggestion in msg.split("allowed keys")[1]


def test_unknown_key_without_a_close_match_lists_the_allowed_keys():
    expected = r"unknown key can\.zzz = 1; allowed keys in \[can\]: bitrate, "
    with pytest.raises(BridgeConfigError, match=expected):
        parse_config(_with("can", "zzz = 1"))


def test_unknown_and_missing_tables():
    with pytest.raises(BridgeConfigError, match=r"unknown table \[sesion\] \(did you mean \[session\]\?\)"):
        parse_config(GOLDEN + "\n[sesion]\nx = 1\n")
    with pytest.raises(BridgeConfigError, match=r"missing table\(s\) \[can\]"):
        parse_config(GOLDEN[:GOLDEN.index("[can]")])
    with pytest.raises(BridgeConfigError, match=r"top-level key subject = 'x' outside any table"):
        parse_config('subject = "x"\n' + GOLDEN)
    with pytest.raises(BridgeConfigError, match=r"session\.subject is missing"):
        parse_config(GOLDEN.replace('subject = "S07"\n', ""))


@pytest.mark.parametrize(("table", "old", "new", "needles"), [
    ("session", "body_mass_kg = 82.5", "body_mass_kg = 300", ["session.body_mass_kg = 300", "[20, 250]"]),
    ("session", 'subject = "S07"', 'subject = "S 07"', ["session.subject = 'S 07'", "letters, digits"]),
    ("space", "F_p = [60, 200.0]", "F_p = [200, 60]", ["space.bounds.F_p = [200, 60]", "lower bound"]),
    ("space", "F_p = [60, 200.0]", "F_p = 60", ["space.bounds.F_p = 60", "[lower, upper]"]),
    ("space", '"F_r <= F_f + 0.2"', '"F_r <= F_f +"', ["space.constraints[0] = 'F_r <= F_f +'"]),
    ("space", '"F_r <= F_f + 0.2"', '"F_r >= 0.9"', ["space:", "no feasible point"]),
    ("space", 'preset = "hip_6d"', 'preset = "hip6d"', ["space.preset = 'hip6d'", "did you mean 'hip_6d'"]),
    ("protocol", "n_explore = 8", "n_explore = 0", ["protocol.n_explore = 0", "[1, 200]"]),
    ("protocol", "window = 3", "window = 40", ["protocol.window = 40", "[0, 39]"]),
    ("protocol", "budget_breaths = 500", "budget_breaths = 0",
     ["protocol.budget_breaths = 0", "[1, 100000]"]),
    ("protocol", "stopping = \"fixed\"", "stopping = \"early\"", ["protocol.stopping = 'early'",
                                                                 "'adaptive', 'fixed'"]),
    ("protocol", "n_local = 2", "n_local = 2.5", ["protocol.n_local = 2.5", "an integer"]),
    ("protocol", "pause_between_bouts = false", "pause_between_bouts = 0",
     ["protocol.pause_between_bouts = 0", "true or false"]),
    ("protocol", 'refit = "at_proposal"', 'refit = "later"', ["protocol.refit = 'later'",
                                                              "'ahead', 'at_proposal'"]),
    ("protocol", 'proposal_worker = "thread"', 'proposal_worker = "gpu"',
     ["protocol.proposal_worker = 'gpu'", "'process', 'thread'"]),
    ("protocol", 'gc = "automatic"', 'gc = "never"', ["protocol.gc = 'never'", "'automatic', 'freeze'"]),
    ("cart", "port = 6000", "port = 70000", ["cart.options.port = 70000", "65535]"]),
    ("can", 'interface = "virtual"', 'interface = "virtal"', ["can.interface = 'virtal'",
                                                              "did you mean 'virtual'", "socketcan"]),
    ("can", "bitrate = 500000", "bitrate = 5", ["can.bitrate = 5", "[10000, 8000000]"]),
    ("can", "heartbeat_period_ms = 10", "heartbeat_period_ms = 100", ["can.heartbeat_period_ms = 100",
                                                                      "[5, 50]"]),
    ("can", "push_retries = 1", "push_retries = true", ["can.push_retries = True", "an integer"]),
    ("can", 'channel = "bench"', 'channel = ""', ["can.channel = ''", "non-empty"]),
    ("limits", "max_force_n = 220.0", "max_force_n = nan", ["limits.max_force_n = nan", "(0, 6553.5]"]),
    ("limits", "max_force_n = 220.0", "max_force_n = inf", ["limits.max_force_n = inf", "finite"]),
    ("limits", "max_force_n = 220.0", "max_force_n = 0", ["limits.max_force_n = 0", "(0, 6553.5]"]),
    ("limits", "max_force_n = 220.0", 'max_force_n = "220"', ["limits.max_force_n = '220'"]),
    ("limits", "max_offset_pct = 58.0", "max_offset_pct = 101", ["limits.max_offset_pct = 101", "[0, 100]"]),
    ("limits", "min_onset_pct = 0.0", "min_onset_pct = 70.0", ["limits.min_onset_pct = 70",
                                                               "must be below", "max_offset_pct = 58"]),
    ("limits", "n_points = 101", "n_points = 1000", ["limits.n_points = 1000", "[2, 768]"]),
    ("limits", "max_force_n = 210.0", "max_force_n = -5", ["limits.actuators.hip.max_force_n = -5"]),
    ("watchdog", "bus_error = \"stop\"", "bus_error = \"ignore\"", ["watchdog.bus_error = 'ignore'",
                                                                     "'pause', 'stop'"]),
    ("watchdog", "cart_data_timeout_s = 30", "cart_data_timeout_s = 1", ["watchdog.cart_data_timeout_s = 1",
                                                                         "[2, 300]"]),
    ("prior", "observations = []", "observations = [{x = 1}]",
     ["unknown key prior.observations[0].x = 1", "mean_w, note, params, sd_w, source, var_w2"]),
])
def test_bad_values_name_the_key_the_value_and_what_is_allowed(table, old, new, needles):
    assert GOLDEN.count(old) == 1, old
    with pytest.raises(BridgeConfigError) as info:
        parse_config(GOLDEN.replace(old, new))
    for needle in needles:
        assert needle in str(info.value), (needle, str(info.value))


def test_cross_checks_on_actuators_and_limits_that_refuse_the_space():
    with pytest.raises(BridgeConfigError, match=r"limits\.actuators\.hipp: .* \(did you mean 'hip'\?\)"):
        parse_config(GOLDEN.replace("[limits.actuators.hip]", "[limits.actuators.hipp]"))
    with pytest.raises(BridgeConfigError, match=r"limits: even the centre of .* max_force_n = 100 N"):
        parse_config(GOLDEN.replace("max_force_n = 210.0", "max_force_n = 100.0"))
    with pytest.raises(BridgeConfigError, match=r"limits: even the centre .* expected 51 points"):
        parse_config(GOLDEN.replace("n_points = 101", "n_points = 51"))


def test_space_needs_exactly_one_definition():
    with pytest.raises(BridgeConfigError, match="not both"):
        parse_config(_with("space", 'profile = "hip_6d"\nparameters = [{name = "a", lower = 0, upper = 1}]'))
    with pytest.raises(BridgeConfigError, match="found neither"):
        parse_config(GOLDEN.replace('preset = "hip_6d"\n', ""))
    with pytest.raises(BridgeConfigError, match=r"space\.profile = .*only for an inline definition"):
        parse_config(_with("space", 'profile = "hip_6d"'))


def test_toml_syntax_error_shows_line_and_column():
    lines = GOLDEN.splitlines()
    n = lines.index("window = 3") + 1
    text = GOLDEN.replace("window = 3", "window = = 3")
    with pytest.raises(BridgeConfigError) as info:
        parse_config(text, source="s.toml")
    msg = str(info.value)
    assert msg.startswith(f"s.toml:{n}:") and f"line {n}" in msg and "window = = 3" in msg
    assert isinstance(info.value, BridgeError) and isinstance(info.value, ValueError)


def test_load_config_file_errors(tmp_path):
    with pytest.raises(BridgeConfigError, match="cannot read config"):
        load_config(tmp_path / "missing.toml")
    bad = tmp_path / "latin1.toml"
    bad.write_bytes('notes = "caf\xe9"'.encode("latin-1"))
    with pytest.raises(BridgeConfigError, match="not UTF-8"):
        load_config(bad)


def test_summary_mentions_every_table():
    text = summarize(parse_config(GOLDEN))
    for word in ("subject S07", "F_p [60, 200] N", "500 breaths", "udp", "virtual:bench",
                 "hip: force <= 210 N", "bus error -> assistance-off and the session ends"):
        assert word in text, word


# --------------------------------------------------------------------------------------------
# hilbo config example / check
# --------------------------------------------------------------------------------------------


def _parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="hilbo")
    add_config_parser(parser.add_subparsers(dest="command", required=True))
    return parser


def _run(argv: list[str], stdin: str | None = None, monkeypatch=None) -> tuple[int, str, str]:
    args = _parser().parse_args(argv)
    out, err = io.StringIO(), io.StringIO()
    if stdin is not None:
        monkeypatch.setattr(sys, "stdin", io.StringIO(stdin))
    if args.config_action == "example":
        return args.func(args, out=out), out.getvalue(), ""
    return args.func(args, out=out, err=err), out.getvalue(), err.getvalue()


def test_example_piped_into_check_round_trips(monkeypatch):
    code, example, _ = _run(["config", "example"])
    assert code == 0 and example == example_config_text()
    code, out, err = _run(["config", "check", "-"], stdin=example, monkeypatch=monkeypatch)
    assert code == 0 and err == ""
    assert out.startswith("config OK: <stdin>\n") and "pre-flight 256 sampled settings: 0 refused" in out


def test_check_exit_1_with_the_reason(tmp_path):
    path = tmp_path / "bad.toml"
    path.write_text(_with("can", "bitrat = 1"))
    code, out, err = _run(["config", "check", str(path)])
    assert code == 1 and out == "" and "did you mean 'bitrate'" in err
    code, _, err = _run(["config", "check", str(tmp_path / "nope.toml")])
    assert code == 1 and "cannot read config" in err


def test_check_warns_when_the_limits_refuse_part_of_the_space(tmp_path):
    path = tmp_path / "wide.toml"
    path.write_text(GOLDEN.replace("F_p = [60, 200.0]", "F_p = [60, 250.0]"))
    code, out, err = _run(["config", "check", str(path), "--samples", "64"])
    assert code == 0 and "max_force" in out and "warning:" in err and "would be refused" in err
    code, out, _ = _run(["config", "check", str(path), "--samples", "0"])
    assert code == 0 and "pre-flight" not in out


@pytest.mark.slow  # two interpreter start-ups importing scipy: several seconds on a loaded 2-core box
def test_shell_pipe_example_into_check():
    """`hilbo config example | hilbo config check -` across two real processes."""
    script = ("import argparse, sys\nfrom bridge.config import add_config_parser\n"
              "p = argparse.ArgumentParser(prog='hilbo')\n"
              "add_config_parser(p.add_subparsers(dest='command', required=True))\n"
              "a = p.parse_args(sys.argv[1:])\nsys.exit(a.func(a))\n")
    example = subprocess.run([sys.executable, "-c", script, "config", "example"],
                             capture_output=True, text=True, timeout=60, check=True)
    check = subprocess.run([sys.executable, "-c", script, "config", "check", "-", "--samples", "16"],
                           input=example.stdout, capture_output=True, text=True, timeout=60)
    assert check.returncode == 0, check.stderr
    assert check.stdout.startswith("config OK: <stdin>")
