"""The gate's zero-force tables (bridge/safety.py, ``SafeProfileGate.admit_zero_force``): the
suit's own tables with every force 0 N, through the same checks, and slack for the peak step."""

from __future__ import annotations

import math

import numpy as np
import pytest

from bridge.errors import UnsafeProfileError
from bridge.safety import ProfileLimits, SafeProfileGate, ViolationKind, check_profile
from hilbo_core.presets import hip_6d, hip_ankle_4d
from hilbo_core.profiles import ForceProfile

GRID = np.linspace(0.0, 100.0, 101)
# Kim et al. 2019 Fig. 4, subject 1: onset 2 %, peak 24 %, offset 40 %, 223 N, nodes 0.6 and 0.45.
S1 = {"t_on": 2.0, "t_p": 24.0, "t_off": 40.0, "F_p": 223.0, "F_r": 0.6, "F_f": 0.45}


def test_zero_force_tables_are_the_settings_tables_with_every_force_zero() -> None:
    gate = SafeProfileGate(hip_6d(), ProfileLimits())
    assisting = gate.admit(S1)
    zero = gate.admit_zero_force(S1)
    assert zero.serial == assisting.serial + 1 and dict(zero.params) == dict(assisting.params)
    ((a,), (z,)) = assisting.profiles, zero.profiles
    assert z.actuator == a.actuator == "hip" and np.array_equal(z.gait_pct, GRID)
    assert z.peak_n == 0.0 and a.peak_n == pytest.approx(223.0)
    with pytest.raises(ValueError):
        z.force_n[0] = 1.0  # read-only like every admitted table
    space = hip_ankle_4d()
    x = {"hip_t_peak": 25.0, "hip_t_offset": 45.0, "ankle_t1": 35.0, "ankle_t2": 55.0}
    both = SafeProfileGate(space, ProfileLimits(max_force_n=1000.0, max_offset_pct=100.0),
                           body_mass_kg=70.0).admit_zero_force(x)
    assert [p.actuator for p in both.profiles] == ["hip", "ankle"]
    assert all(not p.force_n.any() and len(p.force_n) == 101 for p in both.profiles)


def test_a_step_down_to_zero_force_and_up_from_it_are_not_peak_steps() -> None:
    # A peak step of 100 N at most: 223 N -> 0 N -> 223 N would break it twice if zero force
    # counted as a profile with a peak; it is slack, as after assistance-off.
    gate = SafeProfileGate(hip_6d(), ProfileLimits(max_peak_change_n=100.0))
    gate.acknowledge(gate.admit(S1))
    zero = gate.admit_zero_force(S1)
    gate.acknowledge(zero)
    assert gate.acknowledged is zero
    assert gate.admit(S1).profiles[0].peak_n == pytest.approx(223.0)
    # An assisting table after an assisting one still has its baseline.
    gate.acknowledge(gate.admit({**S1, "F_p": 60.0}))
    with pytest.raises(UnsafeProfileError) as info:
        gate.admit(S1)
    assert info.value.verdict.kinds == {ViolationKind.PEAK_CHANGE}


def test_check_profile_takes_an_all_zero_table_as_slack() -> None:
    limits = ProfileLimits(max_peak_change_n=50.0)
    peak = np.clip(200.0 * (1.0 - np.abs(GRID - 30.0) / 10.0), 0.0, None)
    assisting = [ForceProfile("hip", GRID, peak)]
    zero = [ForceProfile("hip", GRID, np.zeros(101))]
    assert check_profile(zero, limits, assisting).ok
    assert check_profile(assisting, limits, zero).ok
    below_resolution = [ForceProfile("hip", GRID, np.full(101, 0.04))]  # quantises to 0 on the wire
    assert check_profile(assisting, limits, below_resolution).ok
    small = [ForceProfile("hip", GRID, peak / 20.0)]  # 10 N: an assisting table, a baseline
    (v,) = check_profile(assisting, limits, small).violations
    assert v.kind is ViolationKind.PEAK_CHANGE and v.value == pytest.approx(190.0)


def test_zero_force_of_a_setting_outside_the_space_is_refused_and_counted() -> None:
    gate = SafeProfileGate(hip_6d(), ProfileLimits(max_consecutive_rejections=2))
    for i, bad in enumerate(({**S1, "t_p": 52.0}, {**S1, "F_p": math.nan}), start=1):
        with pytest.raises(UnsafeProfileError) as info:
            gate.admit_zero_force(bad)
        assert info.value.verdict.kinds == {ViolationKind.PARAMS}
        assert gate.consecutive_rejections == i
    assert gate.rejections_exhausted
    gate.admit_zero_force(S1)
    assert gate.consecutive_rejections == 0
