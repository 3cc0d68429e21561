"""Tests for hilbo_core.features: feature maps for feature kernels (Antonova 2016 §3.4.2)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from hilbo_core import presets
from hilbo_core.errors import ConfigError
from hilbo_core.features import (
    DEFAULT_PROFILE_FEATURES,
    CallableFeatureMap,
    ConcatFeatureMap,
    FeatureMap,
    Lookup,
    ProfileFeatureMap,
    RawFeatureMap,
    TableFeatureMap,
    profile_features,
    with_raw,
)
from hilbo_core.gp import GaussianProcess
from hilbo_core.profiles import ForceProfile

# ---- callables and the cache -------------------------------------------------------------------


def test_callable_map_caches_points_already_seen() -> None:
    calls: list[np.ndarray] = []

    def fn(u: np.ndarray) -> np.ndarray:
        calls.append(u)
        return np.array([u.sum(), u[0] * u[1]])

    fm = CallableFeatureMap(fn, 2)
    assert isinstance(fm, FeatureMap)
    U = np.array([[0.1, 0.2], [0.3, 0.4], [0.1, 0.2]])
    F = fm(U)
    assert F == pytest.approx(np.array([[0.3, 0.02], [0.7, 0.12], [0.3, 0.02]]))
    assert len(calls) == 2  # the repeated row inside one call is not recomputed
    fm(U[::-1])
    assert len(calls) == 2
    assert fm.cache_info == {"hits": 4, "misses": 2, "size": 2}


def test_cache_is_bounded() -> None:
    fm = CallableFeatureMap(lambda u: u[:1], 1, cache_size=3)
    fm(np.linspace(0, 1, 10)[:, None])
    assert fm.cache_info["size"] == 3


def test_callable_map_normalises_over_reference() -> None:
    ref = np.linspace(0.0, 1.0, 11)[:, None]
    fm = CallableFeatureMap(lambda u: [10.0 + 4.0 * u[0]], 1, reference=ref)
    assert fm(np.array([[0.0], [0.5], [1.0]]))[:, 0] == pytest.approx([0.0, 0.5, 1.0])


def test_callable_map_errors_name_the_row() -> None:
    fm = CallableFeatureMap(lambda u: [1.0 / u[0]] if u[0] else [math.nan], 1)
    with pytest.raises(ConfigError, match="row 1"):
        fm(np.array([[0.5], [0.0]]))
    fm2 = CallableFeatureMap(lambda u: np.ones(1 + int(u[0] > 0.5)), 1)
    with pytest.raises(ConfigError, match="row 1"):
        fm2(np.array([[0.2], [0.9]]))
    with pytest.raises(ConfigError, match="shape"):
        fm2(np.zeros((2, 3)))


def test_concat_with_raw() -> None:
    fm = with_raw(CallableFeatureMap(lambda u: [u[0] + u[1]], 2), 2, raw_scale=2.0)
    assert fm(np.array([[0.25, 0.5]])) == pytest.approx(np.array([[0.5, 1.0, 0.75]]))
    assert RawFeatureMap(2)(np.array([[0.1, 0.2]])) == pytest.approx(np.array([[0.1, 0.2]]))
    with pytest.raises(ConfigError):
        ConcatFeatureMap()


# ---- tables ------------------------------------------------------------------------------------


def test_table_nearest_lookup() -> None:
    P = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]])
    F = np.array([1.0, 2.0, 3.0])
    fm = TableFeatureMap(P, F, normalize=False)
    assert fm(np.array([[0.9, 0.1], [0.1, 0.2], [0.2, 0.8]]))[:, 0] == pytest.approx([2.0, 1.0, 3.0])
    fm(np.array([[0.9, 0.1]]))
    assert fm.cache_info["hits"] == 1


def test_table_interpolation_is_exact_at_nodes_and_bounded_between() -> None:
    rng = np.random.default_rng(0)
    P = rng.random((60, 2))
    F = (P[:, 0] + 2 * P[:, 1])[:, None]
    fm = TableFeatureMap(P, F, lookup=Lookup.INTERPOLATE, normalize=False)
    assert fm(P[:5]) == pytest.approx(F[:5], abs=1e-8)
    Q = rng.random((20, 2)) * 0.6 + 0.2
    got = fm(Q)[:, 0]
    want = Q[:, 0] + 2 * Q[:, 1]
    assert np.max(np.abs(got - want)) < 0.15  # close to the smooth function it tabulates


def test_table_precompute_on_space_and_normalise() -> None:
    space = presets.hip_6d()
    fm = TableFeatureMap.precompute(space, lambda p: [p["t_p"]], 128, np.random.default_rng(1))
    assert fm.points.shape == (128, 6)
    assert space.feasible_mask(space.from_unit(fm.points)).all()
    F = fm(fm.points)
    assert F.min() == pytest.approx(0.0) and F.max() == pytest.approx(1.0)


@pytest.mark.parametrize(
    ("points", "features", "match"),
    [
        (np.zeros((3, 5)), np.zeros(3), "5 columns but the space"),
        (np.zeros((3, 6)), np.zeros(4), r"shape \(3, k\)"),
        (np.vstack([np.full((2, 6), 0.5), [[0.5] * 5 + [1.5]]]), np.zeros(3), "row 2.*unit cube"),
        (np.full((3, 6), 0.5), np.array([0.0, np.nan, 1.0]), "row 1.*not finite"),
        (np.vstack([np.full((1, 6), 0.5), [[1.0, 0.0, 0.5, 0.5, 0.5, 0.5]]]), np.zeros(2),
         "row 1.*outside the space"),
    ],
)
def test_table_that_does_not_match_the_space(points, features, match) -> None:
    with pytest.raises(ConfigError, match=match):
        TableFeatureMap(points, features, space=presets.hip_6d())


def test_table_from_rows() -> None:
    space = presets.hip_6d()
    good = {"t_on": 5, "t_p": 25, "t_off": 45, "F_p": 150, "F_r": 0.5, "F_f": 0.5, "dog": 3}
    fm = TableFeatureMap.from_rows(space, [good, {**good, "F_p": 200, "dog": 5}], ["dog"],
                                   normalize=False)
    x = space.from_dict({k: v for k, v in good.items() if k != "dog"})
    assert fm(space.to_unit(x)[None, :])[0, 0] == 3.0
    with pytest.raises(ConfigError, match="row 1: missing"):
        TableFeatureMap.from_rows(space, [good, {k: v for k, v in good.items() if k != "dog"}], ["dog"])
    with pytest.raises(ConfigError, match=r"row 1.*outside the space"):
        TableFeatureMap.from_rows(space, [good, {**good, "t_off": 80}], ["dog"])
    with pytest.raises(ConfigError, match="row 0: unknown"):
        TableFeatureMap.from_rows(space, [{**good, "speed": 1}], ["dog"])
    with pytest.raises(ConfigError, match="row 0: non-numeric"):
        TableFeatureMap.from_rows(space, [{**good, "dog": "x"}], ["dog"])


# ---- exosuit profile features ---------------------------------------------------------------


def _triangle(actuator: str, start: float, peak: float, end: float, f_max: float) -> ForceProfile:
    g = np.linspace(0.0, 100.0, 101)
    f = np.interp(g, [0, start, peak, end, 100], [0, 0, f_max, 0, 0])
    return ForceProfile(actuator, g, f)


def test_profile_features_of_a_triangle() -> None:
    feats = profile_features(_triangle("hip", 10, 30, 50, 100.0))
    assert feats["impulse"] == pytest.approx(2000.0)  # ½ · 40 %GC · 100 N, exact for kinks on the grid
    assert feats["peak_timing"] == 30.0
    assert feats["rise"] == 18.0  # onset: first point above 5 N is 12 %GC (f(11) = 5 exactly)
    assert feats["fall"] == 18.0  # offset: last point above 5 N is 48 %GC
    assert feats["centroid"] == pytest.approx(30.0)
    # ∫ f² over the triangle = 2 · ∫_0^20 (5x)² dx = 400000/3 N²·%; trapezoid is close.
    assert feats["rms_force"] == pytest.approx(math.sqrt(400000 / 3 / 100), rel=2e-3)
    # During hip extension (0-55 %) the nominal velocity is positive, < 1: 0 < work < impulse.
    assert 0 < feats["positive_work"] < feats["impulse"]


def test_profile_force_during_flexion_does_no_positive_work() -> None:
    feats = profile_features(_triangle("hip", 60, 75, 90, 100.0))
    assert feats["positive_work"] == 0.0
    assert profile_features(ForceProfile("hip", np.linspace(0, 100, 101), np.zeros(101)))["impulse"] == 0.0


def test_profile_feature_map_hip() -> None:
    space = presets.hip_6d()
    fm = ProfileFeatureMap(space, n_reference=64)
    assert fm.names == tuple(f"hip.{f}" for f in DEFAULT_PROFILE_FEATURES)
    U = space.sample_unit(50, np.random.default_rng(2))
    F = fm(U)
    assert F.shape == (50, 5)
    assert F.min() > -0.5 and F.max() < 1.5  # normalised to about [0, 1]
    # Peak timing feature is monotone in t_p (the profile peaks at t_p).
    order = np.argsort(U[:, 1])
    assert np.all(np.diff(F[order, 2]) >= -1e-9)
    # Impulse grows with peak force for an otherwise fixed profile.
    u = U[0].copy()
    lo, hi = u.copy(), u.copy()
    lo[3], hi[3] = 0.1, 0.9
    assert fm(hi[None, :])[0, 0] > fm(lo[None, :])[0, 0]


def test_profile_feature_map_handles_points_just_outside_the_constraints() -> None:
    space = presets.hip_6d()
    fm = ProfileFeatureMap(space, n_reference=16)
    bad = np.array([[1.0, 0.0, 0.5, 0.5, 0.5, 0.5]])  # t_on = 25 > t_p − 15 = 0
    assert not space.is_feasible(space.from_unit(bad[0]))
    assert np.all(np.isfinite(fm(bad)))


def test_profile_feature_map_two_actuators_and_bad_names() -> None:
    space = presets.hip_ankle_4d()
    fm = ProfileFeatureMap(space, features=("impulse", "peak_timing"), n_reference=16)
    assert fm.names == ("hip.impulse", "hip.peak_timing", "ankle.impulse", "ankle.peak_timing")
    assert fm(space.sample_unit(3, np.random.default_rng(0))).shape == (3, 4)
    with pytest.raises(ConfigError, match="unknown profile feature"):
        ProfileFeatureMap(space, features=("speed",))


# ---- with the GP -----------------------------------------------------------------------------


def test_feature_kernel_helps_when_the_cost_depends_on_the_feature() -> None:
    """A cost that is smooth in φ but wiggly in x is learnt better with k(φ(x), φ(x'))."""

    def phi(u: np.ndarray) -> np.ndarray:
        return np.array([np.sin(6 * u[0]) * np.cos(5 * u[1])])

    def cost(U: np.ndarray) -> np.ndarray:
        return np.array([(phi(u)[0] - 0.3) ** 2 for u in U])

    rng = np.random.default_rng(0)
    X, Q = rng.random((25, 2)), rng.random((200, 2))
    y = cost(X)
    raw = GaussianProcess().fit(X, y, rng=np.random.default_rng(1))
    feat = GaussianProcess(feature_map=CallableFeatureMap(phi, 2)).fit(X, y, rng=np.random.default_rng(1))
    err_raw = np.sqrt(np.mean((raw.predict(Q)[0] - cost(Q)) ** 2))
    err_feat = np.sqrt(np.mean((feat.predict(Q)[0] - cost(Q)) ** 2))
    assert err_feat < 0.5 * err_raw


def test_gp_with_profile_features_and_raw_parameters_fits() -> None:
    space = presets.hip_6d()
    fm = with_raw(ProfileFeatureMap(space, n_reference=32), space.dim)
    rng = np.random.default_rng(3)
    U = space.sample_unit(12, rng)
    y = 400.0 - 30.0 * U[:, 3] + rng.normal(0, 1, 12)
    gp = GaussianProcess(feature_map=fm).fit(U, y, np.full(12, 1.0), rng=rng)
    assert gp.hyperparameters.dim == 6 + 5
    mean, var = gp.predict(U[:3])
    assert np.all(np.isfinite(mean)) and np.all(var > 0)
