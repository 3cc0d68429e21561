"""What a resumed session has already walked (bridge.run._walked_lower_bound): it counts against
``[protocol] session_min``, so a crash and ``hilbo run --resume`` do not restart the hour."""

from __future__ import annotations

from pathlib import Path
from types import SimpleNamespace

from bridge.config import parse_config
from bridge.run import _walked_lower_bound
from bridge.sim.virtual import VirtualSimConfig, sim_config_text
from hilbo_core.protocol import SessionProtocol


def _ev(duration_s: float, phase: str) -> SimpleNamespace:
    return SimpleNamespace(duration_s=duration_s, phase=phase)


def test_the_evaluations_breath_time_and_one_warm_up_per_bout_begun() -> None:
    assert _walked_lower_bound([], 180.0) == 0.0
    explore = [_ev(130.0, "exploration"), _ev(125.0, "exploration")]
    assert _walked_lower_bound(explore, 180.0) == 180.0 + 255.0
    both = [*explore, _ev(60.0, "optimization")]
    assert _walked_lower_bound(both, 180.0) == 2 * 180.0 + 315.0


def test_a_resumed_protocol_ends_where_the_whole_session_reaches_session_min() -> None:
    # hilbo sim's config, as a lab would write it: session_min = 10.
    sim = VirtualSimConfig(minutes=10.0, n_explore=1, max_breaths=5, warmup_s=10.0)
    cfg = parse_config(sim_config_text(sim, Path("out")))
    assert cfg.protocol.session_min == 10.0
    used = _walked_lower_bound([_ev(200.0, "exploration"), _ev(50.0, "optimization")], 10.0)
    p = SessionProtocol.resumed(cfg.protocol.session_protocol_config(), n_explored=1, t_start_s=0.0,
                                session_used_s=used)
    # 600 s in all, 270 s walked before the crash: 330 s are left after the resume.
    assert p.expected_t_end_s() == 600.0 - 270.0
