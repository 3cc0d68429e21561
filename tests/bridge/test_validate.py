"""``hilbo validate`` (bridge/validate.py): the validation walk on the virtual devices measures
each condition with the session machinery, and its reductions against unassisted walking hold
the simulated wearer's truth within their 95 % intervals."""

from __future__ import annotations

import asyncio
import dataclasses
import itertools
import uuid
from pathlib import Path
from typing import Any

import msgspec
import numpy as np
import pytest
from supervision_harness import run_session as harness_session

from bridge.config import parse_config
from bridge.log.reader import read_log
from bridge.review.command import review_session
from bridge.run import run_session
from bridge.safety import SafeProfileGate
from bridge.sim.virtual import VirtualSimConfig, sim_config_text
from bridge.validate import ConditionGate, ConditionKind, ValidationPlan, condition_results, plan_conditions
from drivers.exosuit import CanBusConfig
from virtual_hw.cart import CartLink, LinkKind, VirtualCart
from virtual_hw.clock import ScaledClock
from virtual_hw.exosuit import SUIT_JOINTS, VirtualExosuit
from virtual_hw.wearer import make_wearer

GENERIC = {"t_on": 10.0, "t_p": 27.0, "t_off": 45.0, "F_p": 120.0, "F_r": 0.5, "F_f": 0.5}


def test_the_order_is_randomised_by_the_seed_and_complete() -> None:
    rec = {"t_on": 5.0, "t_p": 30.0, "t_off": 50.0, "F_p": 200.0, "F_r": 0.5, "F_f": 0.5}
    orders = {tuple(c.name for c in plan_conditions(rec, GENERIC, seed)) for seed in range(12)}
    assert all(sorted(o) == ["FIX", "OPT", "unassisted"] for o in orders)
    assert len(orders) > 2  # the seed changes the order
    again = [c.name for c in plan_conditions(rec, GENERIC, 3)]
    assert [c.name for c in plan_conditions(rec, GENERIC, 3)] == again
    assert [c.name for c in plan_conditions(rec, None, 0)] in (["OPT", "unassisted"], ["unassisted", "OPT"])


def test_zero_force_is_a_condition_only_when_asked_and_takes_its_place_in_the_random_order() -> None:
    rec = {"t_on": 5.0, "t_p": 30.0, "t_off": 50.0, "F_p": 200.0, "F_r": 0.5, "F_f": 0.5}
    assert all("zero-force" not in [c.name for c in plan_conditions(rec, GENERIC, seed)] for seed in range(6))
    plans = [plan_conditions(rec, GENERIC, seed, zero_force=True) for seed in range(12)]
    assert all(sorted(c.name for c in p) == ["FIX", "OPT", "unassisted", "zero-force"] for p in plans)
    assert len({[c.name for c in p].index("zero-force") for p in plans}) > 2  # not always in one place
    (zero,) = [c for c in plans[0] if c.kind is ConditionKind.ZERO_FORCE]
    assert zero.params == rec  # the tables' actuators and grid; every force is 0 N (the gate)
    assert [c.name for c in plan_conditions(rec, None, 5, zero_force=True)] in (
        [list(p) for p in itertools.permutations(["OPT", "unassisted", "zero-force"])])


def test_the_zero_force_condition_passes_the_safety_gate_as_an_all_zero_table() -> None:
    _, cfg = validation_config(Path("/tmp"), zero_force=True)
    gate = SafeProfileGate(cfg.space.space, cfg.limits)
    rec = {"t_on": 5.0, "t_p": 30.0, "t_off": 50.0, "F_p": 200.0, "F_r": 0.5, "F_f": 0.5}
    conditions = plan_conditions(rec, GENERIC, 0, zero_force=True)
    current = [0]
    cgate = ConditionGate(gate, conditions, lambda: current[0])
    by_kind = {}
    for k, c in enumerate(conditions):
        current[0] = k  # the condition being proposed
        by_kind[c.kind] = cgate.admit(dict(c.params))
    assert by_kind[ConditionKind.UNASSISTED] is None  # assistance off: nothing pushed
    zero = by_kind[ConditionKind.ZERO_FORCE]
    opt = by_kind[ConditionKind.RECOMMENDED]
    assert zero is not None and opt is not None
    assert [p.actuator for p in zero.profiles] == [p.actuator for p in opt.profiles]
    for z, o in zip(zero.profiles, opt.profiles, strict=True):
        assert np.array_equal(z.gait_pct, o.gait_pct) and not z.force_n.any() and o.peak_n > 100.0


def test_the_reduction_and_its_interval_by_the_delta_method() -> None:
    rec = {"t_on": 5.0}
    conditions = plan_conditions(rec, None, 0)
    records = [{"index": k, "mean": 300.0 if c.kind is ConditionKind.RECOMMENDED else 400.0,
                "var": 16.0 if c.kind is ConditionKind.RECOMMENDED else 25.0, "breaths": 100}
               for k, c in enumerate(conditions)]
    (opt,) = [r for r in condition_results(conditions, records) if r["name"] == "OPT"]
    assert opt["reduction"] == pytest.approx(0.25)
    sd = 0.75 * (16.0 / 300.0**2 + 25.0 / 400.0**2) ** 0.5
    assert opt["reduction_ci95"] == pytest.approx([0.25 - 1.959964 * sd, 0.25 + 1.959964 * sd], rel=1e-5)
    assert opt["ci95_w"] == pytest.approx([300.0 - 1.959964 * 4.0, 300.0 + 1.959964 * 4.0], rel=1e-6)


def validation_config(tmp_path: Path, *, zero_force: bool = False) -> tuple[VirtualSimConfig, Any]:
    sim = VirtualSimConfig(minutes=30.0, seed=4, warmup_s=60.0, wearer="legacy")
    text = sim_config_text(sim, tmp_path) + (
        "\n[validation]\ngeneric = { " + ", ".join(f"{k} = {v}" for k, v in GENERIC.items())
        + " }\ncondition_min = 4.0\nseed = 2\n" + ("zero_force = true\n" if zero_force else ""))
    return sim, parse_config(text, source="<test>")


def run_validation(tmp_path: Path, sim: VirtualSimConfig, cfg: Any, plan: ValidationPlan, wearer: Any, *,
                   name: str = "validate", resume: Path | None = None,
                   on_session: Any = None) -> dict[str, Any]:
    """The validation walk over the virtual exosuit and cart (in this process, 100x)."""
    channel = f"hilbo-validate-{uuid.uuid4().hex[:8]}"

    async def run() -> dict[str, Any]:
        clock = ScaledClock(100.0)
        async with VirtualCart(wearer, clock, link=CartLink(kind=LinkKind.TCP)) as cart:
            bus = CanBusConfig("virtual", channel)
            run_cfg = dataclasses.replace(cfg, cart=cart.client_config(),
                                          can=msgspec.structs.replace(cfg.can, bus=bus))
            async with VirtualExosuit(bus, clock, joints=SUIT_JOINTS[sim.preset],
                                      seed=1, on_applied=cart.on_profile_applied):
                result = await run_session(run_cfg, log_path=tmp_path / f"{name}.mcap", auto_resume_s=0.0,
                                           operator_view=False, n_actuators=len(SUIT_JOINTS[sim.preset]),
                                           validation=plan, resume=resume, on_session=on_session)
        return result.summary

    return asyncio.run(run())


@pytest.mark.slow
@pytest.mark.timeout(240)
def test_validate_on_the_virtual_devices_matches_the_wearers_truth(tmp_path: Path) -> None:
    # The optimisation session to validate: a short one (its recommendation is what matters).
    # With the zero-force condition, so all four kinds of condition are measured in one walk.
    source = harness_session(tmp_path, n_evaluations=4).log
    sim, cfg = validation_config(tmp_path, zero_force=True)
    wearer = make_wearer(sim.wearer, cfg.space.space, seed=sim.seed, body_mass_kg=sim.body_mass_kg)
    plan = ValidationPlan.new(cfg, source)
    summary = run_validation(tmp_path, sim, cfg, plan, wearer)
    assert summary["end_reason"] == "conditions_done"
    results = {r["name"]: r for r in summary["validation"]}
    assert set(results) == {"OPT", "FIX", "unassisted", "zero-force"}
    assert all(r["measured"] for r in results.values())
    assert [r["name"] for r in summary["validation"]] == [c.name for c in plan.conditions]
    baseline = wearer.baseline_cost_w
    lo, hi = results["unassisted"]["ci95_w"]
    assert lo <= baseline <= hi, (baseline, results["unassisted"])
    for name in ("OPT", "FIX"):
        r = results[name]
        truth = 1.0 - wearer.true_cost_w(r["params"]) / baseline
        rlo, rhi = r["reduction_ci95"]
        assert rlo <= truth <= rhi, (name, truth, r)
        assert r["breaths"] == cfg.validation.condition_breaths
    # Zero force: the simulated wearer has no suit mass or friction, so an all-zero table costs
    # what unassisted walking costs (virtual_hw/wearer.py, cost_of_profiles) and the truth is 0.
    zero = results["zero-force"]
    assert zero["params"] is None and zero["breaths"] == cfg.validation.condition_breaths
    zlo, zhi = zero["ci95_w"]
    assert zlo <= wearer.cost_of_profiles(()) == baseline <= zhi, zero
    rlo, rhi = zero["reduction_ci95"]
    assert rlo <= 0.0 <= rhi, zero
    # What reached the device for it: the suit's tables, every force 0 N.
    k = [c.name for c in plan.conditions].index("zero-force")
    sent = [p for p in read_log(tmp_path / "validate.mcap").records("/profiles_sent") if p.index == k]
    assert sent and all(not any(p.force_n) and p.profiles for p in sent)
    # The log holds the plan and the result, and hilbo review reports them.
    kinds = [e.kind for e in read_log(tmp_path / "validate.mcap").records("/events")]
    assert "validation_plan" in kinds and "validation_result" in kinds
    review = review_session([tmp_path / "validate.mcap"], tmp_path / "review")
    s = review.session
    assert s.validation is not None and [r["name"] for r in s.validation] == [c.name for c in plan.conditions]
    md = (review.out_dir / "report.md").read_text()
    assert "## Validation walk" in md
    section = md.split("## Validation walk")[1].split("\n## ")[0]
    assert f"{100 * results['OPT']['reduction']:.1f}" in section
    (row,) = [line for line in section.splitlines() if "| zero-force |" in line]
    assert "zero force" in row and f"{100 * zero['reduction']:.1f}" in row
    assert "zero-force: the suit actuated" in section
    # The walk applies its conditions and nothing else: no setting is asked or pushed after
    # the last one, and nothing is recommended from a GP over fixed conditions.
    log = read_log(tmp_path / "validate.mcap")
    assert summary["n_evaluations"] == len(plan.conditions)
    assert {p.index for p in log.records("/profiles_sent")} <= set(range(len(plan.conditions)))
    assert [p.index for p in log.records("/proposals")] == list(range(len(plan.conditions)))
    assert "confirmation" not in kinds
    assert summary["recommendation"] is None and summary["best_params"] is None
    assert summary["validated_log"] == str(source)
    for ev, c in zip(summary["evaluations"], plan.conditions, strict=True):
        assert ev["condition"] == c.name
        assert (ev["params"] is None) == (c.name in ("unassisted", "zero-force"))
    assert "A validation walk recommends nothing" in md and s.recommended is None
    assert {"best_so_far", "parameters", "thresholds"} <= set(review.skipped)
    assert "a validation walk measures fixed conditions" in md
    evaluations_md = md.split("## Evaluations")[1].splitlines()
    (ev_row,) = [line for line in evaluations_md if "| validation: unassisted |" in line]
    assert "| – |" in ev_row


def test_validate_needs_one_source(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from bridge.cli.main import main

    config = tmp_path / "s.toml"
    config.write_text(sim_config_text(VirtualSimConfig(minutes=30.0), tmp_path))
    assert main(["validate", str(config)]) == 2
    err = capsys.readouterr().err
    assert "give --from LOG" in err and "neither was given" in err
    assert main(["validate", str(config), "--from", "a.mcap", "--resume", "b.mcap"]) == 2
    assert "both were given" in capsys.readouterr().err
    source = harness_session(tmp_path, n_evaluations=4).log
    # An optimisation log is not a validation walk to resume.
    assert main(["validate", str(config), "--resume", str(source)]) == 1
    assert "is not a validation walk's log" in capsys.readouterr().err


def test_config_check_says_what_the_validation_walk_will_measure() -> None:
    from bridge.config import summarize

    text = sim_config_text(VirtualSimConfig(minutes=30.0), Path("/tmp")) + "\n[validation]\n"
    (line,) = [ln for ln in summarize(parse_config(text)).splitlines() if ln.startswith("validate  ")]
    assert "OPT (the session's recommendation), unassisted; 5 min (100 breaths) each" in line
    assert "no [validation] generic" in line
    given = text + ("generic = { t_on = 10.0, t_p = 27.0, t_off = 45.0, F_p = 120.0, F_r = 0.5, F_f = 0.5 }\n"
                    "zero_force = true\ncondition_min = 2.0\nseed = 7\n")
    (line,) = [ln for ln in summarize(parse_config(given)).splitlines() if ln.startswith("validate  ")]
    assert "FIX (t_on = " in line and "F_p = 120" in line
    assert ", unassisted, zero-force; 2 min (40 breaths)" in line
    assert "seeded by 7" in line and "no [validation] generic" not in line


def test_the_zero_force_key_of_the_config() -> None:
    from bridge.errors import BridgeConfigError

    text = sim_config_text(VirtualSimConfig(minutes=30.0), Path("/tmp")) + "\n[validation]\n"
    assert parse_config(text).validation.zero_force is False
    assert parse_config(text + "zero_force = true\n").validation.zero_force is True
    for bad in ('"yes"', "1"):
        with pytest.raises(BridgeConfigError, match=r"validation\.zero_force = .*: expected true or false"):
            parse_config(text + f"zero_force = {bad}\n")
    with pytest.raises(BridgeConfigError, match=r"unknown key validation\.zeroforce = True "
                                                r"\(did you mean 'zero_force'\?\)"):
        parse_config(text + "zeroforce = true\n")


def test_a_generic_setting_outside_the_space_is_refused_by_the_config() -> None:
    from bridge.errors import BridgeConfigError

    text = sim_config_text(VirtualSimConfig(minutes=30.0), Path("/tmp")) + (
        "\n[validation]\ngeneric = { t_on = 10.0, t_p = 52.0, t_off = 45.0, F_p = 120.0, F_r = 0.5, "
        "F_f = 0.5 }\n")
    with pytest.raises(BridgeConfigError, match=r"generic is not a feasible setting: parameter t_p"):
        parse_config(text)
    with pytest.raises(BridgeConfigError, match=r"generic: expected every parameter .*missing F_f"):
        parse_config(text.replace(", F_f = 0.5", "").replace("t_p = 52.0", "t_p = 27.0"))
    # In the space but above [limits]: the gate would refuse FIX during the walk.
    over = text.replace("t_p = 52.0", "t_p = 27.0").replace("F_p = 120.0", "F_p = 240.0")
    assert "[limits]" not in over
    over += "\n[limits]\nmax_force_n = 200.0\n"
    with pytest.raises(BridgeConfigError, match=r"validation.generic = \{t_on = 10, t_p = 27, .*F_p = 240.*"
                                                r"expected a setting \[limits\] lets through, but it is "
                                                r"refused: .*exceeds max_force_n = 200 N"):
        parse_config(over)


@pytest.mark.slow
@pytest.mark.timeout(300)
def test_a_stopped_validation_walk_resumes_with_its_measured_conditions(tmp_path: Path) -> None:
    from bridge.outcome import SessionEnd

    source = harness_session(tmp_path, n_evaluations=4).log
    sim, cfg = validation_config(tmp_path)

    def wearer() -> Any:
        return make_wearer(sim.wearer, cfg.space.space, seed=sim.seed, body_mass_kg=sim.body_mass_kg)

    def stop_after_the_first(session: Any) -> None:
        def check(_rec: Any) -> None:
            if len(session.opt.evaluations) == 1 and session.end_reason is None:
                session.finish(SessionEnd.OPERATOR_STOP)
        session.breath_listeners.append(check)

    plan = ValidationPlan.new(cfg, source)
    first = run_validation(tmp_path, sim, cfg, plan, wearer(), name="first", on_session=stop_after_the_first)
    assert first["end_reason"] == "operator_stop"
    assert [r["measured"] for r in first["validation"]] == [True, False, False]
    again = ValidationPlan.resumed(cfg, tmp_path / "first.mcap")
    assert [c.to_json() for c in again.conditions] == [c.to_json() for c in plan.conditions]
    assert again.source_log == str(source)
    second = run_validation(tmp_path, sim, cfg, again, wearer(), name="second",
                            resume=tmp_path / "first.mcap")
    assert second["end_reason"] == "conditions_done"
    assert all(r["measured"] for r in second["validation"])
    assert second["validation"][0]["mean_w"] == first["validation"][0]["mean_w"]  # kept, not re-measured
    with pytest.raises(Exception, match="every condition of this validation walk was measured"):
        ValidationPlan.resumed(cfg, tmp_path / "second.mcap")
