"""A pause proportionate to its length: a short one (``short_pause_s``, breath time) ends without
a warm-up and the abandoned setting is proposed again at once; a long one ends with the bout's
warm-up; the pause between the bouts always ends with the optimisation bout's warm-up."""

from __future__ import annotations

import pytest
from hypothesis import given
from hypothesis import strategies as st

from hilbo_core.errors import ConfigError
from hilbo_core.protocol import ActionKind, SessionPhase, SessionProtocol, SessionProtocolConfig

K, P = ActionKind, SessionPhase


def measuring(short_pause_s: float = 15.0) -> SessionProtocol:
    """A session measuring its first exploration setting since t = 6 s, last breath at 12 s."""
    p = SessionProtocol(SessionProtocolConfig(warmup_s=6.0, n_explore=2, budget_s=600.0,
                                              short_pause_s=short_pause_s), t_start_s=0.0)
    p.start()
    p.on_breath(3.0)
    assert p.on_breath(6.0).kind is K.PROPOSE
    p.on_setting_applied(6.0)
    p.on_breath(9.0)
    assert p.on_breath(12.0).kind is K.MEASURE
    return p


def test_the_default_short_pause_is_15_s() -> None:
    assert SessionProtocolConfig().short_pause_s == 30.0


@given(st.floats(0.0, 15.0))
def test_a_short_pause_while_measuring_proposes_again_at_once(pause_s: float) -> None:
    p = measuring()
    assert p.on_pause().starts
    a = p.on_resume(12.0 + pause_s)
    assert (a.kind, a.phase) == (K.PROPOSE, P.EXPLORATION)  # no warm-up: measure it again now
    assert p.last_pause_s == pytest.approx(pause_s)
    p.on_setting_applied(12.0 + pause_s)  # pushed at the resume
    b = p.on_breath(12.0 + pause_s + 3.0)
    assert b.kind is K.MEASURE and b.t_setting_s == pytest.approx(3.0)  # measured from zero again
    assert p.walking.warm_up_s == 6.0  # only the bout's own warm-up


def test_breaths_during_a_short_pause_count_as_paused_walking() -> None:
    p = measuring()
    p.on_pause()
    assert p.on_breath(15.0).kind is K.PAUSED
    assert p.on_breath(18.0).kind is K.PAUSED
    assert p.on_resume().kind is K.PROPOSE  # 6 s of breaths since the pause began
    assert p.last_pause_s == 6.0 and p.walking.paused_s == 6.0


def test_a_long_pause_while_measuring_ends_with_the_bouts_warm_up() -> None:
    p = measuring()
    p.on_pause()
    for t in (15.0, 18.0, 21.0, 24.0, 27.0, 30.0):
        p.on_breath(t)
    a = p.on_resume()  # 18 s > 15 s
    assert (a.kind, a.phase) == (K.WARM_UP, P.WARM_UP_EXPLORATION) and a.starts
    assert p.last_pause_s == 18.0
    assert p.on_breath(33.0).kind is K.WARM_UP
    assert p.on_breath(36.0).kind is K.PROPOSE  # the full 6 s warm-up


def test_short_pause_s_zero_warms_up_after_every_pause() -> None:
    p = measuring(short_pause_s=0.0)
    p.on_pause()
    a = p.on_resume(12.0)  # not a breath paused, still a warm-up
    assert (a.kind, a.starts) == (K.WARM_UP, True)


def test_a_short_pause_during_a_warm_up_lets_the_warm_up_go_on_where_it_was() -> None:
    p = SessionProtocol(SessionProtocolConfig(warmup_s=9.0, n_explore=1, budget_s=600.0),
                        t_start_s=0.0)
    p.start()
    p.on_breath(3.0)
    p.on_pause()
    p.on_breath(6.0)
    a = p.on_resume()
    assert (a.kind, a.phase, a.starts) == (K.WARM_UP, P.WARM_UP_EXPLORATION, False)
    assert p.on_breath(9.0).kind is K.PROPOSE  # 9 s after the warm-up's own start, not the resume


def test_the_pause_between_the_bouts_always_ends_with_the_optimisation_warm_up() -> None:
    p = SessionProtocol(SessionProtocolConfig(warmup_s=3.0, n_explore=1, budget_s=600.0),
                        t_start_s=0.0)
    p.start()
    assert p.on_breath(3.0).kind is K.PROPOSE
    p.on_setting_applied()
    p.on_breath(6.0)
    assert p.on_evaluation_done().kind is K.PAUSE_BETWEEN_BOUTS
    a = p.on_resume(7.0)  # 1 s: short, yet the bout's warm-up opens the optimisation bout
    assert (a.kind, a.phase, a.starts) == (K.WARM_UP, P.WARM_UP_OPTIMIZATION, True)


@pytest.mark.parametrize("bad", [-1.0, float("nan"), float("inf"), "15", True])
def test_a_bad_short_pause_is_refused(bad: object) -> None:
    with pytest.raises(ConfigError, match="short_pause_s"):
        SessionProtocolConfig(short_pause_s=bad)  # type: ignore[arg-type]
