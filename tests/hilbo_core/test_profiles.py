"""Force profiles from assistance parameters."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hilbo_core.errors import ConfigError, InfeasibleError
from hilbo_core.presets import hip_6d, hip_ankle_4d
from hilbo_core.profiles import PROFILE_DOMAINS, build_profile, hip_ankle_profiles, hip_spline_profile


def test_hip_profile_passes_through_the_nodes() -> None:
    # Subject 1's optimum in Kim et al. 2019's Fig. 4: 2 %, 24 %, 40 %, 223 N, 0.6, 0.45.
    p = hip_spline_profile(2, 24, 40, 223, 0.6, 0.45)
    f = dict(zip(p.gait_pct.round(6), p.force_n, strict=True))
    assert p.gait_pct.shape == (101,) and p.force_n.shape == (101,)
    assert f[2.0] == pytest.approx(0.0, abs=1e-9)
    assert f[13.0] == pytest.approx(0.6 * 223)  # rising node at (2 + 24) / 2
    assert f[24.0] == pytest.approx(223.0)
    assert f[32.0] == pytest.approx(0.45 * 223)  # falling node at (24 + 40) / 2
    assert f[40.0] == pytest.approx(0.0, abs=1e-9)
    assert np.all(p.force_n[41:] == 0) and np.all(p.force_n[:2] == 0)
    assert p.peak_n == pytest.approx(223.0)


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**32 - 1))
def test_hip_profiles_bounded_for_every_feasible_point(seed: int) -> None:
    s = hip_6d()
    x = s.from_unit(s.sample_unit(1, np.random.default_rng(seed))[0])
    (p,) = build_profile("hip_6d", s.to_dict(x))
    assert np.all(p.force_n >= 0)
    assert p.force_n.max() <= x[3] + 1e-9
    # The peak falls between grid points of the 1 %GC table, so the table's max is close below.
    assert p.force_n.max() >= 0.95 * x[3]


@pytest.mark.parametrize(
    "args", [(24, 2, 40, 223, 0.6, 0.45), (2, 24, 40, -1, 0.6, 0.45), (2, 24, 40, 223, 1.2, 0.5),
             (2, 24, float("nan"), 223, 0.6, 0.45)]
)
def test_hip_profile_rejects_bad_parameters(args) -> None:
    with pytest.raises(InfeasibleError):
        hip_spline_profile(*args)


def test_hip_ankle_profiles_scale_with_body_weight() -> None:
    s = hip_ankle_4d()
    params = s.to_dict(np.array([25.0, 45.0, 35.0, 55.0]))
    hip, ankle = hip_ankle_profiles(params, body_mass_kg=80.0)
    assert hip.peak_n == pytest.approx(0.40 * 9.81 * 80)
    assert ankle.peak_n == pytest.approx(0.60 * 9.81 * 80)
    assert ankle.force_n[30] == 0.0 and ankle.force_n[60] == pytest.approx(ankle.peak_n)
    assert hip.force_n[25] == pytest.approx(hip.peak_n) and hip.force_n[50] == 0.0


def test_unknown_space_and_immutability() -> None:
    with pytest.raises(ConfigError, match="no force-profile builder"):
        build_profile("knee_3d", {})
    (p,) = build_profile("hip_6d", {"t_on": 2, "t_p": 24, "t_off": 40, "F_p": 223, "F_r": 0.6, "F_f": 0.45})
    with pytest.raises(ValueError):
        p.force_n[0] = 5.0


@pytest.mark.parametrize("name", sorted(PROFILE_DOMAINS))
def test_each_builders_domain_holds_its_preset_and_its_edges_build_or_fail_as_declared(name: str) -> None:
    from hilbo_core.presets import preset

    space = preset(name)
    domains = PROFILE_DOMAINS[name]
    assert set(domains) <= set(space.names)
    for par in space.parameters:
        if par.name in domains:
            assert domains[par.name].contains(par.lower, par.upper), par
    # A parameter just outside its domain (the others at the preset's centre) is not built.
    centre = space.to_dict(space.from_unit(np.full(space.dim, 0.5)))
    build_profile(name, centre)
    for pname, dom in domains.items():
        for outside in (dom.low - 1.0, dom.high + 1.0):
            if np.isfinite(outside):
                with pytest.raises((InfeasibleError, ConfigError)):
                    build_profile(name, {**centre, pname: outside})
