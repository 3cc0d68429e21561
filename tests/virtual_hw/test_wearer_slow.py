"""The slow wearer (WearerKind.SLOW): the realistic wearer with τ 30-60 s."""

from __future__ import annotations

import pytest

from hilbo_core.presets import hip_6d
from virtual_hw.wearer import SLOW_TAU_S, WEARER_CHOICES, make_wearer


def test_slow_is_a_wearer_choice_with_the_same_subjects_but_slower_kinetics() -> None:
    assert "slow" in WEARER_CHOICES
    space = hip_6d()
    for seed in range(6):
        slow, plain = make_wearer("slow", space, seed=seed), make_wearer("realistic", space, seed=seed)
        s, p = slow.subject, plain.subject
        assert SLOW_TAU_S[0] <= s["tau_s"] <= SLOW_TAU_S[1]
        # Same person otherwise: landscape, breathing and drift.
        for key in ("family", "unassisted_cost_w", "noise_sd_frac", "drift_sd_frac"):
            assert s[key] == pytest.approx(p[key])
        assert slow.true_optimum[1] == pytest.approx(plain.true_optimum[1])

