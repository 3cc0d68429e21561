"""[protocol] protocol, confirm_min and explore_rel_sd: the named walking protocols in the config."""

from __future__ import annotations

import pytest

from bridge.config import example_config_text, parse_config
from bridge.errors import BridgeConfigError
from hilbo_core.protocol import ProtocolKind


def _cfg(extra: str):
    return parse_config(example_config_text().replace("[protocol]", "[protocol]\n" + extra, 1))


def test_the_example_runs_the_fast_protocol() -> None:
    pr = parse_config(example_config_text()).protocol
    assert pr.protocol_kind is ProtocolKind.FAST
    sp = pr.session_protocol_config()
    assert sp.confirm_s == 240.0 and not sp.warmup_without_pause and not sp.pause_between_bouts
    assert sp.n_explore == pr.optimizer_config().n_explore == 3
    assert pr.optimizer_config().explore_rel_sd is None


def test_the_seed_protocol_by_name_and_by_the_seeds_rules() -> None:
    # The protocol's values where the config does not give them (the example leaves them to the
    # rule's defaults: changing the rule there changes the protocol with it).
    example = example_config_text()
    assert not any(line.startswith(("protocol =", "n_explore", "pause_between_bouts"))
                   for line in example.splitlines())
    for extra in ('protocol = "seed"', ''):
        text = example.replace("[protocol]\n", f"[protocol]\n{extra}\n")
        if not extra:
            text = text.replace('stopping = "sound"', 'stopping = "adaptive"')
        pr = parse_config(text).protocol
        assert pr.protocol_kind is ProtocolKind.SEED
        sp = pr.session_protocol_config()
        assert sp.confirm_s is None and sp.warmup_without_pause and sp.pause_between_bouts
        assert sp.n_explore == pr.optimizer_config().n_explore == 6
        assert pr.optimizer_config().explore_rel_sd is None


def test_keys_override_the_protocols_values_and_zero_switches_them_off() -> None:
    pr = _cfg("confirm_min = 2.5\nexplore_rel_sd = 0.05\n").protocol
    assert pr.session_protocol_config().confirm_s == 150.0
    assert pr.optimizer_config().explore_rel_sd == 0.05
    pr = _cfg("confirm_min = 0\nexplore_rel_sd = 0\n").protocol
    assert pr.session_protocol_config().confirm_s is None
    assert pr.optimizer_config().explore_rel_sd is None


@pytest.mark.parametrize("extra, match", [
    ('protocol = "quick"\n', "protocol"),
    ("confirm_min = -1\n", "confirm_min"),
    ("explore_rel_sd = 0.9\n", "explore_rel_sd"),
])
def test_bad_values_name_the_key(extra: str, match: str) -> None:
    text = example_config_text().replace('protocol = "fast"', "")
    text = text.replace("[protocol]", "[protocol]\n" + extra, 1)
    with pytest.raises(BridgeConfigError, match=match):
        parse_config(text)


def test_the_gp_prior_mean_follows_the_rule_unless_given() -> None:
    assert parse_config(example_config_text()).protocol.optimizer_config().prior_mean_sd == 0.5
    seed_rule = example_config_text().replace('stopping = "sound"', 'stopping = "adaptive"')
    assert parse_config(seed_rule).protocol.optimizer_config().prior_mean_sd == 0.0
    assert _cfg("prior_mean_sd = 0\n").protocol.optimizer_config().prior_mean_sd == 0.0
    assert _cfg("prior_mean_sd = 1.5\n").protocol.optimizer_config().prior_mean_sd == 1.5


@pytest.mark.parametrize("bad", ["-0.5", "4", '"high"'])
def test_a_bad_gp_prior_mean_names_the_key_and_its_range(bad: str) -> None:
    with pytest.raises(BridgeConfigError, match="prior_mean_sd"):
        _cfg(f"prior_mean_sd = {bad}\n")


@pytest.mark.parametrize(("extra", "needle"), [
    ("session_min = 2.5\n", "protocol.session_min = 2.5: expected more minutes than the warm-up "
                            "(warmup_s = 180 s)"),
    ("confirm_min = 40\n", "protocol.confirm_min = 40: expected fewer minutes than budget_min = 40"),
    ("confirm_min = 20\nsession_min = 15\n", "protocol.confirm_min = 20: expected fewer minutes than "
                                            "session_min = 15"),
])
def test_protocol_times_that_leave_no_session_are_refused(extra: str, needle: str) -> None:
    with pytest.raises(BridgeConfigError) as exc:
        _cfg(extra)
    assert needle in str(exc.value)


@pytest.mark.parametrize(("bounds", "needle"), [
    ("F_p = [-50.0, 250.0]", "space.bounds.F_p = [-50, 250]: expected 0 < F_p (what the 'hip_6d' "
                             "force-profile builder can build"),
    ("t_on = [-2.0, 25.0]", "space.bounds.t_on = [-2, 25]: expected 0 <= t_on < 100"),
    ("F_r = [0.3, 1.0]", "space.bounds.F_r = [0.3, 1]: expected 0 < F_r < 1"),
])
def test_space_bounds_the_profile_builder_cannot_build_are_refused(bounds: str, needle: str) -> None:
    text = example_config_text().replace("F_p = [50.0, 250.0]", bounds, 1)
    with pytest.raises(BridgeConfigError) as exc:
        parse_config(text)
    assert needle in str(exc.value)
