"""The noisy wearer (WearerKind.NOISY): the realistic wearer with breath CV 15-25 % and 3 % outliers."""

from __future__ import annotations

import numpy as np
import pytest

from hilbo_core.presets import hip_6d
from virtual_hw.wearer import NOISY_BREATH_CV, WEARER_CHOICES, make_wearer


def test_noisy_is_a_wearer_choice_with_the_same_subjects_landscapes() -> None:
    assert "noisy" in WEARER_CHOICES
    space = hip_6d()
    for seed in range(4):
        noisy, plain = make_wearer("noisy", space, seed=seed), make_wearer("realistic", space, seed=seed)
        s = noisy.subject
        assert NOISY_BREATH_CV[0] <= s["noise_sd_frac"] <= NOISY_BREATH_CV[1]
        assert s["outlier_frac"] == pytest.approx(0.03)
        # Same person otherwise: the same landscape family and unassisted cost.
        assert s["family"] == plain.subject["family"]
        assert s["unassisted_cost_w"] == pytest.approx(plain.subject["unassisted_cost_w"])


def test_noisy_breaths_vary_by_15_to_25_percent_at_a_steady_state() -> None:
    space = hip_6d()
    for seed in range(3):
        w = make_wearer("noisy", space, seed=seed)
        watts = np.array([w.next_breath().watts for _ in range(1500)])[300:]  # unassisted steady state
        # Robust CV (the outliers aside): 1.4826 × MAD / median.
        cv = 1.4826 * np.median(np.abs(watts - np.median(watts))) / np.median(watts)
        assert 0.12 <= cv <= 0.28
