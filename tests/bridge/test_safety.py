"""The limits layer: hand-made reference tables, the gate, and property tests against an oracle."""

from __future__ import annotations

import copy
import math
import pickle

import numpy as np
import pytest
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st

from bridge.errors import BridgeConfigError, BridgeError, UnsafeProfileError
from bridge.safety import (
    ActuatorLimits,
    AdmittedProfile,
    ProfileLimits,
    SafeProfileGate,
    ViolationKind,
    check_params,
    check_profile,
    make_actuator_limits,
    preflight,
)
from hilbo_core.presets import hip_6d, hip_ankle_4d
from hilbo_core.profiles import ForceProfile, build_profile

GRID = np.linspace(0.0, 100.0, 101)
# Kim et al. 2019 Fig. 4, subject 1: onset 2 %, peak 24 %, offset 40 %, 223 N, nodes 0.6 and 0.45.
S1 = {"t_on": 2.0, "t_p": 24.0, "t_off": 40.0, "F_p": 223.0, "F_r": 0.6, "F_f": 0.45}


def triangle(peak_n: float = 100.0, centre: float = 30.0, half_width: float = 10.0) -> np.ndarray:
    """Force rising linearly from centre-half_width to the peak and back: slope peak/half_width."""
    return np.clip(peak_n * (1.0 - np.abs(GRID - centre) / half_width), 0.0, None)


def raw_profile(actuator: str, gait: object, force: object) -> ForceProfile:
    """A ForceProfile that skips its own validation (to feed the checks NaN, bad shapes...)."""
    p = object.__new__(ForceProfile)
    object.__setattr__(p, "actuator", actuator)
    object.__setattr__(p, "gait_pct", gait)
    object.__setattr__(p, "force_n", force)
    return p


def kinds(verdict) -> set[ViolationKind]:
    return set(verdict.kinds)


# --------------------------------------------------------------------------------------------
# check_profile: reference cases by hand
# --------------------------------------------------------------------------------------------

LIM = ProfileLimits()  # 250 N, window [0, 60] %GC, 40 N/%GC, 200 N peak step, 101 points


def test_triangle_within_limits_is_ok():
    v = check_profile([ForceProfile("hip", GRID, triangle())], LIM)
    assert v.ok and v.violations == () and v.describe() == "within limits"


def test_force_exactly_at_the_limit_is_ok_and_just_above_is_not():
    assert check_profile([ForceProfile("hip", GRID, triangle(250.0, half_width=10.0))], LIM).ok
    v = check_profile([ForceProfile("hip", GRID, triangle(250.5, half_width=10.0))],
                      ProfileLimits(max_slope_n_per_pct=100.0))
    (viol,) = v.violations
    assert viol.kind is ViolationKind.MAX_FORCE
    assert (viol.actuator, viol.index, viol.gait_pct) == ("hip", 30, 30.0)
    assert (viol.value, viol.limit) == (250.5, 250.0)
    assert "250.5 N at 30 %GC" in viol.message and "max_force_n = 250 N" in viol.message


def test_negative_force_names_the_most_negative_point():
    f = triangle()
    f[5], f[80] = -1.0, -3.0
    v = check_profile([ForceProfile("hip", GRID, f)], ProfileLimits(max_offset_pct=100.0))
    neg = [x for x in v.violations if x.kind is ViolationKind.NEGATIVE_FORCE]
    assert len(neg) == 1 and neg[0].index == 80 and neg[0].value == -3.0 and neg[0].limit == 0.0


@pytest.mark.parametrize("bad", [math.nan, math.inf, -math.inf])
def test_non_finite_force_is_reported_and_stops_the_other_checks(bad):
    f = triangle(1000.0)  # also far above the force limit, but that must not be reported
    f[7] = bad
    v = check_profile([raw_profile("hip", GRID, f)], LIM)
    (viol,) = v.violations
    assert viol.kind is ViolationKind.NON_FINITE and viol.index == 7 and viol.gait_pct == 7.0


def test_non_finite_gait_position_is_reported():
    g = GRID.copy()
    g[3] = math.nan
    (viol,) = check_profile([raw_profile("hip", g, triangle())], LIM).violations
    assert viol.kind is ViolationKind.NON_FINITE and viol.index == 3


@pytest.mark.parametrize("n", [100, 102, 2])
def test_wrong_length_is_refused(n):
    g = np.linspace(0, 100, n)
    (viol,) = check_profile([ForceProfile("hip", g, np.zeros(n))], LIM).violations
    assert viol.kind is ViolationKind.LENGTH and viol.value == n and viol.limit == 101


def test_mismatched_or_2d_tables_are_refused():
    (viol,) = check_profile([raw_profile("hip", GRID, np.zeros((101, 1)))], LIM).violations
    assert viol.kind is ViolationKind.LENGTH
    (viol,) = check_profile([raw_profile("hip", GRID[:-1], np.zeros(101))], LIM).violations
    assert viol.kind is ViolationKind.LENGTH


def test_wrong_grid_is_refused():
    g = np.linspace(0.0, 99.0, 101)  # right length, wrong spacing
    (viol,) = check_profile([ForceProfile("hip", g, triangle())], LIM).violations
    assert viol.kind is ViolationKind.GRID and viol.index == 1 and viol.limit == pytest.approx(1.0)


def test_slope_between_neighbours():
    f = np.zeros(101)
    f[41:50] = 50.0  # a step of 50 N between 40 % and 41 %, and back down between 49 % and 50 %
    v = check_profile([ForceProfile("hip", GRID, f)], LIM)
    (viol,) = v.violations
    assert viol.kind is ViolationKind.SLOPE
    assert (viol.index, viol.value, viol.limit) == (40, 50.0, 40.0)
    assert "between 40 and 41 %GC" in viol.message


def test_slope_exactly_at_the_limit_is_ok():
    f = np.zeros(101)
    f[25:36] = [0, 40, 80, 120, 160, 200, 160, 120, 80, 40, 0]  # exactly 40 N/%GC, no round-off
    assert check_profile([ForceProfile("hip", GRID, f.copy())], LIM).ok
    f[30] = 200.5
    assert kinds(check_profile([ForceProfile("hip", GRID, f)], LIM)) == {ViolationKind.SLOPE}


def test_slope_counts_the_seam_from_100_to_0_percent():
    f = np.zeros(101)
    f[100] = 45.0  # 0 % of the next stride follows 100 %: a 45 N jump in one step
    f[99] = 30.0
    limits = ProfileLimits(max_offset_pct=100.0)
    (viol,) = check_profile([ForceProfile("hip", GRID, f)], limits).violations
    assert viol.kind is ViolationKind.SLOPE and viol.index == 100 and viol.value == 45.0
    assert "seam" in viol.message


def test_assistance_window():
    limits = ProfileLimits(min_onset_pct=25.0, max_offset_pct=35.0)
    f = triangle(100.0, centre=30.0, half_width=10.0)  # non-zero on 21..39 %
    v = check_profile([ForceProfile("hip", GRID, f)], limits)
    by_kind = {x.kind: x for x in v.violations}
    assert set(by_kind) == {ViolationKind.ONSET, ViolationKind.OFFSET}
    assert by_kind[ViolationKind.ONSET].index == 21 and by_kind[ViolationKind.ONSET].limit == 25.0
    assert by_kind[ViolationKind.OFFSET].index == 36 and by_kind[ViolationKind.OFFSET].limit == 35.0


def test_force_below_wire_resolution_counts_as_zero_outside_the_window():
    f = triangle()
    f[90] = 0.04  # quantises to 0 raw counts of 0.1 N
    assert check_profile([ForceProfile("hip", GRID, f.copy())], LIM).ok
    f[90] = 0.05
    assert kinds(check_profile([ForceProfile("hip", GRID, f)], LIM)) == {ViolationKind.OFFSET}


def test_peak_change_against_the_previous_profile():
    limits = ProfileLimits(max_peak_change_n=100.0, max_slope_n_per_pct=100.0)
    prev = [ForceProfile("hip", GRID, triangle(100.0))]
    ok = [ForceProfile("hip", GRID, triangle(200.0))]
    bad = [ForceProfile("hip", GRID, triangle(200.5))]
    assert check_profile(ok, limits, prev).ok
    (viol,) = check_profile(bad, limits, prev).violations
    assert viol.kind is ViolationKind.PEAK_CHANGE and viol.value == 100.5 and viol.limit == 100.0
    assert check_profile(bad, limits, None).ok  # no baseline at start / after assistance-off
    assert check_profile(bad, limits, [ForceProfile("ankle", GRID, triangle(10.0))]).ok  # other actuator


def test_per_actuator_limits():
    limits = ProfileLimits(actuators={"ankle": make_actuator_limits("limits.actuators.ankle",
                                                                    max_force_n=500.0, max_offset_pct=90.0)})
    hip = ForceProfile("hip", GRID, triangle(300.0, centre=30.0, half_width=10.0))
    ankle = ForceProfile("ankle", GRID, triangle(300.0, centre=70.0, half_width=10.0))
    v = check_profile([hip, ankle], limits)
    assert [(x.actuator, x.kind) for x in v.violations] == [("hip", ViolationKind.MAX_FORCE)]


@pytest.mark.parametrize("profiles", [[], (), "hip", None, 42])
def test_no_profile(profiles):
    (viol,) = check_profile(profiles, LIM).violations
    assert viol.kind is ViolationKind.NO_PROFILE


def test_duplicate_actuator_and_non_profiles():
    p = ForceProfile("hip", GRID, triangle())
    assert kinds(check_profile([p, p], LIM)) == {ViolationKind.DUPLICATE_ACTUATOR}
    assert kinds(check_profile([object()], LIM)) == {ViolationKind.NO_PROFILE}
    assert kinds(check_profile([raw_profile("hip", GRID, ["a"] * 101)], LIM)) == {ViolationKind.NO_PROFILE}


def test_every_violation_is_listed_and_serialises():
    f = triangle(300.0, centre=80.0, half_width=2.0)
    v = check_profile([ForceProfile("hip", GRID, f)], LIM)
    assert kinds(v) == {ViolationKind.MAX_FORCE, ViolationKind.OFFSET, ViolationKind.SLOPE}
    js = v.to_json()
    assert js["ok"] is False and {x["kind"] for x in js["violations"]} == {"max_force", "offset", "slope"}
    nan = check_profile([raw_profile("hip", GRID, np.full(101, math.nan))], LIM).to_json()
    assert nan["violations"][0]["value"] == "nan"  # strict JSON has no NaN


def test_seed_profile_of_subject_1_is_within_the_default_limits():
    (p,) = build_profile("hip_6d", S1)
    assert p.peak_n == pytest.approx(223.0) and int(np.argmax(p.force_n)) == 24
    assert check_profile([p], LIM).ok


# --------------------------------------------------------------------------------------------
# Limits validation
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize(("key", "value"), [
    ("max_force_n", 0.0), ("max_force_n", -5.0), ("max_force_n", math.nan), ("max_force_n", math.inf),
    ("max_force_n", 7000.0), ("max_force_n", True), ("max_force_n", "250"),
    ("max_slope_n_per_pct", 0.0), ("max_peak_change_n", math.nan), ("min_onset_pct", -1.0),
    ("max_offset_pct", 101.0),
])
def test_limits_reject_bad_values_naming_the_key(key, value):
    with pytest.raises(BridgeConfigError, match=rf"limits\.{key} = "):
        ProfileLimits(**{key: value})


def test_limits_reject_an_empty_window_and_bad_counts():
    with pytest.raises(BridgeConfigError, match=r"min_onset_pct = 60 must be below"):
        ProfileLimits(min_onset_pct=60.0, max_offset_pct=60.0)
    with pytest.raises(BridgeConfigError, match=r"limits\.n_points = 1: expected an integer in \[2, 768\]"):
        ProfileLimits(n_points=1)
    with pytest.raises(BridgeConfigError, match=r"max_consecutive_rejections = 0"):
        ProfileLimits(max_consecutive_rejections=0)
    with pytest.raises(BridgeConfigError, match=r"limits\.actuators\.ankle\.max_force_n = -1"):
        make_actuator_limits("limits.actuators.ankle", max_force_n=-1)
    with pytest.raises(BridgeConfigError, match=r"expected ActuatorLimits"):
        ProfileLimits(actuators={"hip": {"max_force_n": 1.0}})


def test_for_actuator_falls_back_to_the_top_level_limits():
    ankle = ActuatorLimits(max_force_n=500.0)
    limits = ProfileLimits(max_force_n=200.0, actuators={"ankle": ankle})
    assert limits.for_actuator("ankle") is ankle
    assert limits.for_actuator("hip") == ActuatorLimits(max_force_n=200.0)
    assert limits.to_json()["actuators"]["ankle"]["max_force_n"] == 500.0


# --------------------------------------------------------------------------------------------
# check_params
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize(("change", "needle"), [
    ({"F_p": math.nan}, "F_p=nan"),
    ({"F_p": math.inf}, "F_p=inf"),
    ({"F_p": 260.0}, "F_p=260 is outside its bounds [50, 250]"),
    ({"t_on": 20.0}, "t_on <= t_p - 15"),
    ({"F_pp": 1.0}, "unknown parameter"),
    ({"F_p": "lots"}, "lots"),
])
def test_check_params_refuses_bad_settings(change, needle):
    v = check_params(hip_6d(), {**S1, **change})
    (viol,) = v.violations
    assert viol.kind is ViolationKind.PARAMS and needle in viol.message


def test_check_params_accepts_feasible_points_and_vectors():
    space = hip_6d()
    assert check_params(space, S1).ok
    assert check_params(space, np.array(list(S1.values()))).ok
    assert not check_params(space, np.array([1.0, 2.0])).ok
    missing = dict(S1)
    del missing["F_f"]
    assert "missing parameter" in check_params(space, missing).describe()


def test_check_params_refuses_a_derived_value_that_disagrees():
    space = hip_ankle_4d()
    x = {"hip_t_peak": 25.0, "hip_t_offset": 45.0, "ankle_t1": 35.0, "ankle_t2": 55.0}
    assert check_params(space, x).ok
    assert check_params(space, {**x, "ankle_t3": 65.0}).ok
    for bad in (99.0, math.nan, "x"):
        v = check_params(space, {**x, "ankle_t3": bad})
        assert not v.ok and "ankle_t3" in v.describe()


# --------------------------------------------------------------------------------------------
# The gate
# --------------------------------------------------------------------------------------------


def test_gate_admits_the_seed_profile_with_recomputed_derived_parameters():
    gate = SafeProfileGate(hip_6d(), LIM)
    a = gate.admit(S1)
    assert isinstance(a, AdmittedProfile) and a.serial == 1 and gate.admitted_count == 1
    assert dict(a.params) == S1
    np.testing.assert_array_equal(a.forces_n("hip"), build_profile("hip_6d", S1)[0].force_n)
    assert not a.forces_n("hip").flags.writeable
    assert a.to_json()["profiles"][0]["actuator"] == "hip"
    with pytest.raises(KeyError, match="ankle"):
        a.forces_n("ankle")


def test_admitted_profile_cannot_be_made_changed_or_copied_outside_the_gate():
    (p,) = build_profile("hip_6d", S1)
    with pytest.raises(TypeError, match=r"only by SafeProfileGate\.admit"):
        AdmittedProfile(object(), S1, (p,), 1)
    a = SafeProfileGate(hip_6d(), LIM).admit(S1)
    with pytest.raises(AttributeError):
        a._profiles = ()  # type: ignore[misc]
    with pytest.raises(AttributeError):
        del a._serial
    with pytest.raises(TypeError):
        a.params["F_p"] = 1000.0  # type: ignore[index]
    for clone in (copy.copy, copy.deepcopy, pickle.dumps):
        with pytest.raises(TypeError):
            clone(a)


def test_gate_rejects_with_a_verdict_and_counts_consecutive_rejections():
    gate = SafeProfileGate(hip_6d(), ProfileLimits(max_force_n=200.0, max_consecutive_rejections=2))
    for i in (1, 2):
        with pytest.raises(UnsafeProfileError) as info:
            gate.admit(S1)  # 223 N > 200 N
        assert isinstance(info.value, BridgeError) and isinstance(info.value, ValueError)
        assert info.value.verdict.kinds == {ViolationKind.MAX_FORCE} and info.value.params == S1
        assert gate.consecutive_rejections == i
    assert gate.rejections_exhausted and gate.rejected_count == 2
    gate.admit({**S1, "F_p": 150.0})
    assert gate.consecutive_rejections == 0 and not gate.rejections_exhausted


def test_peak_step_is_measured_from_the_acknowledged_profile():
    gate = SafeProfileGate(hip_6d(), ProfileLimits(max_peak_change_n=100.0))
    low = gate.admit({**S1, "F_p": 60.0})
    high = {**S1, "F_p": 240.0}
    gate.admit(high)  # nothing acknowledged yet: no baseline
    gate.acknowledge(low)
    assert gate.acknowledged is low
    with pytest.raises(UnsafeProfileError) as info:
        gate.admit(high)
    assert info.value.verdict.kinds == {ViolationKind.PEAK_CHANGE}
    assert not gate.verdict(high).ok
    gate.admit({**S1, "F_p": 155.0})
    gate.assistance_off()
    assert gate.acknowledged is None
    gate.admit(high)


def test_acknowledge_accepts_only_profiles_this_gate_admitted():
    gate, other = SafeProfileGate(hip_6d(), LIM), SafeProfileGate(hip_6d(), LIM)
    foreign = other.admit(S1)
    with pytest.raises(UnsafeProfileError, match="not admitted by this gate"):
        gate.acknowledge(foreign)
    with pytest.raises(UnsafeProfileError):
        gate.acknowledge("hip")  # type: ignore[arg-type]


def test_builder_failures_and_bad_tables_are_rejected_not_raised():
    def raises(params):
        raise RuntimeError("spline exploded")

    gate = SafeProfileGate(hip_6d(), LIM, builder=raises)
    with pytest.raises(UnsafeProfileError, match="spline exploded") as info:
        gate.admit(S1)
    assert info.value.verdict.kinds == {ViolationKind.BUILD}

    def nan_table(params):
        return [raw_profile("hip", GRID, np.full(101, math.nan))]

    with pytest.raises(UnsafeProfileError, match="non-finite"):
        SafeProfileGate(hip_6d(), LIM, builder=nan_table).admit(S1)


def test_gate_keeps_a_private_copy_of_what_it_checked():
    force = triangle()
    gate = SafeProfileGate(hip_6d(), LIM, builder=lambda params: [raw_profile("hip", GRID, force)])
    a = gate.admit(S1)
    force[30] = 10_000.0  # the builder's array changes after the check
    assert a.profiles[0].peak_n == 100.0


def test_gate_passes_body_mass_to_the_builder():
    space = hip_ankle_4d()
    x = {"hip_t_peak": 25.0, "hip_t_offset": 45.0, "ankle_t1": 35.0, "ankle_t2": 55.0}
    limits = ProfileLimits(max_force_n=1000.0, max_offset_pct=100.0, max_slope_n_per_pct=100.0)
    a = SafeProfileGate(space, limits, body_mass_kg=50.0).admit(x)
    assert a.params["ankle_t3"] == 65.0
    assert a.profiles[1].actuator == "ankle" and a.profiles[1].peak_n == pytest.approx(0.6 * 9.81 * 50.0)


def test_gate_refuses_bad_construction():
    with pytest.raises(BridgeConfigError):
        SafeProfileGate("hip_6d", LIM)  # type: ignore[arg-type]
    with pytest.raises(BridgeConfigError):
        SafeProfileGate(hip_6d(), {"max_force_n": 250})  # type: ignore[arg-type]


def test_preflight_counts_refused_settings():
    assert preflight(hip_6d(), LIM, n=64).n_rejected == 0
    report = preflight(hip_6d(), ProfileLimits(max_force_n=150.0), n=64)
    assert 0 < report.n_rejected < 64 and set(report.by_kind) == {"max_force"}
    assert "max_force_n = 150 N" in report.example and report.to_json()["n_checked"] == 64


# --------------------------------------------------------------------------------------------
# Property tests against an independent oracle
# --------------------------------------------------------------------------------------------


def oracle_ok(tables, limits: ProfileLimits, previous_peaks: dict[str, float]) -> bool:
    """The limits written out point by point, independently of bridge.safety's numpy code."""
    if not tables:
        return False
    seen = set()
    for actuator, g, f in tables:
        if actuator in seen:
            return False
        seen.add(actuator)
        lim = limits.for_actuator(actuator)
        n = limits.n_points
        if np.ndim(f) != 1 or np.ndim(g) != 1 or len(f) != n or len(g) != n:
            return False
        g, f = [float(v) for v in g], [float(v) for v in f]
        for k in range(n):
            if not (math.isfinite(f[k]) and math.isfinite(g[k])):
                return False
            if abs(g[k] - 100.0 * k / (n - 1)) > 1e-6:
                return False
            if f[k] < 0.0 or f[k] > lim.max_force_n:
                return False
            if f[k] >= 0.05 and not lim.min_onset_pct <= g[k] <= lim.max_offset_pct:
                return False
        for k in range(n - 1):
            if abs(f[k + 1] - f[k]) / (g[k + 1] - g[k]) > lim.max_slope_n_per_pct:
                return False
        if abs(f[0] - f[n - 1]) / (g[1] - g[0]) > lim.max_slope_n_per_pct:
            return False
        if actuator in previous_peaks and abs(max(f) - previous_peaks[actuator]) > lim.max_peak_change_n:
            return False
    return True


SPACE = hip_6d()
finite_or_not = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True),
    st.sampled_from([math.nan, math.inf, -math.inf, -1.0, 0.0, 1e9]),
)


@st.composite
def limits_strategy(draw) -> ProfileLimits:
    """Each limit either generous (so the others decide) or anywhere in a plausible range."""
    def pick(generous: float, lo: float, hi: float) -> float:
        return draw(st.one_of(st.just(generous), st.floats(lo, hi)))

    onset = pick(0.0, 0.0, 40.0)
    return ProfileLimits(
        max_force_n=pick(400.0, 1.0, 400.0),
        min_onset_pct=onset,
        max_offset_pct=pick(100.0, onset + 1.0, 100.0),
        max_slope_n_per_pct=pick(80.0, 1.0, 80.0),
        max_peak_change_n=pick(300.0, 1.0, 300.0),
    )


@st.composite
def feasible_params(draw) -> dict[str, float]:
    u = np.array([draw(st.floats(0.0, 1.0)) for _ in range(SPACE.dim)])
    x = SPACE.from_unit(u)
    # Repair the two timing constraints deterministically instead of filtering (keeps it fast).
    x[0] = min(x[0], x[1] - 15.0)
    x[2] = max(x[2], x[1] + 15.0)
    return SPACE.to_dict(x)


@st.composite
def hip_params(draw) -> dict[str, float]:
    """Hip settings: feasible ones, feasible ones with one or two values spoilt (NaN, infinite,
    out of bounds, breaking a constraint), and values anywhere."""
    kind = draw(st.sampled_from(["feasible", "spoilt", "spoilt", "anywhere"]))
    if kind == "anywhere":
        return {p.name: draw(finite_or_not) for p in SPACE.parameters}
    out = draw(feasible_params())
    if kind == "spoilt":
        for _ in range(draw(st.integers(1, 2))):
            p = draw(st.sampled_from(SPACE.parameters))
            span = p.upper - p.lower
            out[p.name] = draw(st.one_of(finite_or_not, st.floats(p.lower - span, p.upper + span)))
    return out


def _peaks(admitted: AdmittedProfile | None) -> dict[str, float]:
    return {} if admitted is None else {p.actuator: p.peak_n for p in admitted.profiles}


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(params=hip_params(), limits=limits_strategy(), baseline=st.none() | feasible_params())
def test_no_setting_that_violates_the_limits_is_ever_admitted(params, limits, baseline):
    gate = SafeProfileGate(SPACE, limits)
    if baseline is not None:
        try:
            gate.acknowledge(gate.admit(baseline))
        except UnsafeProfileError:
            pass
    previous = _peaks(gate.acknowledged)
    try:
        admitted = gate.admit(params)
    except UnsafeProfileError as err:
        assert not err.verdict.ok
        for k in err.verdict.kinds:
            event(f"rejected: {k.value}")
        return
    event("admitted")
    # Admitted: the setting was feasible and every table passes the oracle.
    assert SPACE.is_feasible(params)
    tables = [(p.actuator, p.gait_pct, p.force_n) for p in admitted.profiles]
    assert oracle_ok(tables, limits, previous)


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(params=feasible_params(), limits=limits_strategy(), baseline=st.none() | feasible_params())
def test_every_feasible_setting_within_the_limits_is_admitted(params, limits, baseline):
    gate = SafeProfileGate(SPACE, limits)
    if baseline is not None:
        try:
            gate.acknowledge(gate.admit(baseline))
        except UnsafeProfileError:
            pass
    previous = _peaks(gate.acknowledged)
    tables = [(p.actuator, p.gait_pct, p.force_n) for p in build_profile("hip_6d", params)]
    expected = oracle_ok(tables, limits, previous)
    event(f"within limits: {expected}")
    try:
        gate.admit(params)
        admitted = True
    except UnsafeProfileError:
        admitted = False
    assert admitted == expected


table_values = st.one_of(st.floats(-10.0, 500.0), finite_or_not)


@st.composite
def fuzzed_tables(draw):
    """What a broken builder might return: any lengths, grids, values, duplicate actuators."""
    out = []
    names = ["hip", "ankle", "knee"]
    for i in range(draw(st.sampled_from([1, 1, 2, 0, 3]))):
        n = draw(st.sampled_from([101, 101, 101, 100, 2]))
        g = np.linspace(0.0, 100.0, n)
        if draw(st.integers(0, 4)) == 0:
            g = g + draw(st.floats(-1.0, 1.0))
        base = draw(st.sampled_from(["zeros", "triangle", "triangle", "random"]))
        if base == "random":
            f = np.array(draw(st.lists(table_values, min_size=n, max_size=n)))
        else:
            f = np.zeros(n) if base == "zeros" or n != 101 else triangle(draw(st.floats(0.0, 400.0)),
                                                                        draw(st.floats(0.0, 100.0)),
                                                                        draw(st.floats(1.0, 30.0)))
            for _ in range(draw(st.sampled_from([0, 0, 1, 2]))):
                f[draw(st.integers(0, n - 1))] = draw(table_values)
        duplicate = i > 0 and draw(st.integers(0, 4)) == 0
        out.append(raw_profile(names[0 if duplicate else i], g, f))
    return out


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(tables=fuzzed_tables(), limits=limits_strategy())
def test_a_broken_builder_never_gets_a_bad_table_through(tables, limits):
    gate = SafeProfileGate(SPACE, limits, builder=lambda params: tables)
    snapshot = [(p.actuator, np.array(p.gait_pct, dtype=float), np.array(p.force_n, dtype=float))
                for p in tables]
    expected = oracle_ok(snapshot, limits, {})
    event(f"within limits: {expected}")
    try:
        admitted = gate.admit(S1)
    except UnsafeProfileError:
        assert not expected
        return
    assert expected
    assert [p.actuator for p in admitted.profiles] == [t[0] for t in snapshot]
