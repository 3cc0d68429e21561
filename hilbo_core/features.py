"""Feature kernels (Antonova 2016 §3.4.2): k(φ(x_i), φ(x_j)) over a map φ of the parameters.

Antonova 2016 replaced the Euclidean distance between 16-D controller parameters by the distance
between "Determinants of Gait" scores φ(x) that short simulations had precomputed for 100 000
Sobol points, looked up during BO, with "a hashmap to store DoG scores of the points sampled
during optimization". The GP (:class:`hilbo_core.gp.GaussianProcess`, argument ``feature_map``)
already applies any φ: (n, d) → (n, k) to its unit-cube inputs before the ARD kernel; this module
provides the maps:

* :class:`CallableFeatureMap` — φ computed point by point by any callable, with a bounded cache
  of points already seen (Antonova 2016's hashmap).
* :class:`TableFeatureMap` — φ precomputed on a Sobol set of the space (:meth:`TableFeatureMap.precompute`)
  or read from a table (:meth:`TableFeatureMap.from_rows`) and looked up by nearest neighbour
  (``scipy.spatial.cKDTree``) or interpolated (``scipy.interpolate.RBFInterpolator`` over the
  nearest table points), with the same cache.
* :class:`ProfileFeatureMap` — an exosuit map that needs no wearer data: features of the force
  profile itself (:func:`profile_features`: impulse, a positive-work proxy, peak timing, rise and
  fall durations), built with :func:`hilbo_core.profiles.build_profile`.
* :class:`ConcatFeatureMap` with :class:`RawFeatureMap` — composition with the ARD kernel on raw
  parameters: the GP's ARD kernel over [u, φ(u)] has one length-scale per raw parameter *and* per
  feature, so the data decide how much each matters (for the squared-exponential kernel this is
  exactly the product of an ARD kernel on u and one on φ(u)). No change to gp.py is needed.

Features are normalised to about [0, 1] (min–max over the table, or over a Sobol reference set
of the space for callables) so the GP's length-scale bounds and priors, which assume unit-cube
inputs, stay sensible.

Note: a GP with a feature map has no input gradient (``predict_with_grad`` refuses), so EI
maximisation must use finite differences (``maximize_ei(..., predict_grad=None)``).
"""

from __future__ import annotations

import enum
import math
from collections.abc import Callable, Mapping, Sequence
from typing import Any, Protocol, runtime_checkable

import numpy as np
from scipy.interpolate import RBFInterpolator
from scipy.optimize import minimize
from scipy.spatial import cKDTree

from hilbo_core.errors import ConfigError, InfeasibleError
from hilbo_core.profiles import ForceProfile, build_profile
from hilbo_core.space import ParameterSpace

__all__ = [
    "DEFAULT_PROFILE_FEATURES",
    "PROFILE_FEATURES",
    "CallableFeatureMap",
    "ConcatFeatureMap",
    "FeatureMap",
    "Lookup",
    "ProfileFeatureMap",
    "RawFeatureMap",
    "TableFeatureMap",
    "nominal_velocity",
    "profile_features",
    "with_raw",
]

_CUBE_TOL = 1e-9
# Onset/offset of a profile: where the force first/last exceeds this fraction of its peak
# (the tables start and end with slow clamped-spline tails).
_ONSET_FRACTION = 0.05


@runtime_checkable
class FeatureMap(Protocol):
    """φ: unit-cube points (n, d) → features (n, k) with finite values."""

    def __call__(self, U: np.ndarray) -> np.ndarray:
        """Features of the rows of ``U``, shape (n, k)."""
        ...


def _check_points(U: Any, d: int | None, what: str) -> np.ndarray:
    U = np.asarray(U, dtype=float)
    if U.ndim == 1 and d is not None and U.shape[0] == d:
        U = U[None, :]
    if U.ndim != 2 or (d is not None and U.shape[1] != d):
        raise ConfigError(f"{what} must have shape (n, {d if d is not None else 'd'}), got {U.shape}")
    bad = np.flatnonzero(~np.all(np.isfinite(U), axis=1))
    if bad.size:
        raise ConfigError(f"{what} row {bad[0]} is not finite: {U[bad[0]].tolist()}")
    return U


class _RowCache:
    """Bounded map from a point's exact float64 bytes to its feature row (oldest dropped first)."""

    def __init__(self, max_size: int) -> None:
        if isinstance(max_size, bool) or not isinstance(max_size, int) or max_size < 0:
            raise ConfigError(f"cache_size={max_size!r}; expected an integer >= 0")
        self.max_size = max_size
        self._rows: dict[bytes, np.ndarray] = {}
        self.hits = 0
        self.misses = 0

    def lookup(self, U: np.ndarray, compute: Callable[[np.ndarray], np.ndarray]) -> np.ndarray:
        keys = [np.ascontiguousarray(u).tobytes() for u in U]
        first: dict[bytes, int] = {}  # missing key -> first row holding it (duplicates computed once)
        for i, k in enumerate(keys):
            if k not in self._rows and k not in first:
                first[k] = i
        self.misses += len(first)
        self.hits += len(keys) - len(first)
        fresh: dict[bytes, np.ndarray] = {}
        if first:
            F = compute(U[list(first.values())])
            fresh = {k: F[j] for j, k in enumerate(first)}
        out = np.array([fresh[k] if k in fresh else self._rows[k] for k in keys], dtype=float)
        if self.max_size:
            for k, row in fresh.items():
                if len(self._rows) >= self.max_size:
                    del self._rows[next(iter(self._rows))]
                self._rows[k] = row
        return out.reshape(len(keys), -1)

    def __len__(self) -> int:
        return len(self._rows)


class _Normaliser:
    """Affine map of each feature to [0, 1] over a reference set (constant features → 0)."""

    def __init__(self, F: np.ndarray) -> None:
        self.lo = F.min(axis=0)
        span = F.max(axis=0) - self.lo
        self.scale = np.where(span > 0.0, span, 1.0)

    def __call__(self, F: np.ndarray) -> np.ndarray:
        return (F - self.lo) / self.scale


# --------------------------------------------------------------------------------------------
# Callable maps
# --------------------------------------------------------------------------------------------


class CallableFeatureMap:
    """φ computed point by point by a callable, with a cache of points already seen.

    Args:
        fn: One unit-cube point (d,) → its features (k,) (or a scalar for k = 1).
        dim: d, the input dimension (checked on every call).
        cache_size: Points remembered (0 disables the cache).
        reference: Optional unit-cube points (m, d) over which each feature is min–max
            normalised to [0, 1]; None leaves features as ``fn`` returns them.

    Raises:
        ConfigError: ``fn`` is not callable, bad dimension or reference set, or (on call) ``fn``
            returns non-finite or inconsistently shaped features (naming the row).
    """

    def __init__(self, fn: Callable[[np.ndarray], Any], dim: int, *, cache_size: int = 100_000,
                 reference: np.ndarray | None = None) -> None:
        if not callable(fn):
            raise ConfigError(f"fn must be callable, got {fn!r}")
        if isinstance(dim, bool) or not isinstance(dim, int) or dim < 1:
            raise ConfigError(f"dim={dim!r}; expected an integer >= 1")
        self._fn = fn
        self._dim = dim
        self._k: int | None = None
        self._cache = _RowCache(cache_size)
        self._norm: _Normaliser | None = None
        if reference is not None:
            R = _check_points(reference, dim, "reference")
            if R.shape[0] < 2:
                raise ConfigError(f"reference needs at least 2 points, got {R.shape[0]}")
            self._norm = _Normaliser(self._compute(R))

    @property
    def dim(self) -> int:
        """Input dimension d."""
        return self._dim

    @property
    def n_features(self) -> int | None:
        """k, once known (after the first evaluation)."""
        return self._k

    @property
    def cache_info(self) -> dict[str, int]:
        """``{"hits", "misses", "size"}`` of the point cache."""
        return {"hits": self._cache.hits, "misses": self._cache.misses, "size": len(self._cache)}

    def _compute(self, U: np.ndarray) -> np.ndarray:
        rows = []
        for i, u in enumerate(U):
            f = np.atleast_1d(np.asarray(self._fn(u.copy()), dtype=float)).reshape(-1)
            if self._k is None:
                self._k = f.size
            if f.size != self._k:
                raise ConfigError(
                    f"feature function returned {f.size} features for row {i} ({u.tolist()}); "
                    f"expected {self._k}"
                )
            if not np.all(np.isfinite(f)):
                raise ConfigError(f"feature function returned non-finite features {f.tolist()} "
                                  f"for row {i} ({u.tolist()})")
            rows.append(f)
        return np.array(rows, dtype=float).reshape(len(rows), -1)

    def _raw(self, U: np.ndarray) -> np.ndarray:
        return self._cache.lookup(U, self._compute)

    def __call__(self, U: np.ndarray) -> np.ndarray:
        """Features of unit-cube points ``U`` (n, d) → (n, k)."""
        U = _check_points(U, self._dim, "U")
        F = self._raw(U)
        return F if self._norm is None else self._norm(F)


class RawFeatureMap:
    """The identity on unit-cube parameters, optionally scaled: φ(u) = u · scale.

    Used with :class:`ConcatFeatureMap` to keep the ARD kernel on raw parameters next to the
    features.
    """

    def __init__(self, dim: int, scale: float = 1.0) -> None:
        if isinstance(dim, bool) or not isinstance(dim, int) or dim < 1:
            raise ConfigError(f"dim={dim!r}; expected an integer >= 1")
        if not (math.isfinite(scale) and scale > 0):
            raise ConfigError(f"scale={scale!r}; expected a positive number")
        self.dim = dim
        self.scale = float(scale)

    def __call__(self, U: np.ndarray) -> np.ndarray:
        """``U · scale``, shape (n, d)."""
        return _check_points(U, self.dim, "U") * self.scale


class ConcatFeatureMap:
    """φ(u) = [φ_1(u), φ_2(u), …]: several maps side by side (e.g. raw parameters and features).

    With the GP's ARD kernel every column gets its own length-scale.
    """

    def __init__(self, *maps: FeatureMap) -> None:
        if not maps:
            raise ConfigError("ConcatFeatureMap needs at least one feature map")
        for m in maps:
            if not callable(m):
                raise ConfigError(f"expected feature maps (callables), got {m!r}")
        self.maps = tuple(maps)

    def __call__(self, U: np.ndarray) -> np.ndarray:
        """Concatenated features, shape (n, Σ k_i)."""
        parts = [np.asarray(m(U), dtype=float) for m in self.maps]
        n = parts[0].shape[0]
        for i, p in enumerate(parts):
            if p.ndim != 2 or p.shape[0] != n:
                raise ConfigError(f"feature map {i} returned shape {p.shape}; expected ({n}, k)")
        return np.hstack(parts)


def with_raw(feature_map: FeatureMap, dim: int, raw_scale: float = 1.0) -> ConcatFeatureMap:
    """[u · raw_scale, φ(u)]: the feature kernel combined with the ARD kernel on raw parameters."""
    return ConcatFeatureMap(RawFeatureMap(dim, raw_scale), feature_map)


# --------------------------------------------------------------------------------------------
# Tables
# --------------------------------------------------------------------------------------------


class Lookup(enum.Enum):
    """How a :class:`TableFeatureMap` answers points not in its table."""

    NEAREST = "nearest"  # value of the nearest table point (cKDTree)
    INTERPOLATE = "interpolate"  # RBF interpolation over the nearest table points


class TableFeatureMap:
    """φ precomputed at table points and looked up (Antonova 2016 §3.4.2).

    Args:
        points: Table points in the unit cube, shape (m, d).
        features: Their features, shape (m, k) (or (m,) for k = 1).
        lookup: :class:`Lookup` (``"nearest"`` or ``"interpolate"``).
        space: If given, every table point must be feasible in it (d must match).
        normalize: Min–max normalise each feature over the table to [0, 1].
        neighbors: Table points used per interpolation (``INTERPOLATE`` only).
        cache_size: Points remembered (0 disables the cache).

    Raises:
        ConfigError: Shapes that don't match (table vs space, points vs features), a row that is
            not finite, outside the unit cube or infeasible — naming the row.
    """

    def __init__(self, points: np.ndarray, features: np.ndarray, *, lookup: Lookup | str = Lookup.NEAREST,
                 space: ParameterSpace | None = None, normalize: bool = True, neighbors: int = 32,
                 cache_size: int = 100_000) -> None:
        try:
            self.lookup = Lookup(lookup)
        except ValueError as err:
            raise ConfigError(f"lookup={lookup!r}; expected one of {[m.value for m in Lookup]}") from err
        P = np.asarray(points, dtype=float)
        if P.ndim != 2 or P.shape[0] < 1:
            raise ConfigError(f"table points must have shape (m >= 1, d), got {P.shape}")
        if space is not None and P.shape[1] != space.dim:
            raise ConfigError(
                f"table points have {P.shape[1]} columns but the space {space.name!r} has "
                f"{space.dim} parameters {list(space.names)}"
            )
        F = np.asarray(features, dtype=float)
        if F.ndim == 1:
            F = F[:, None]
        if F.ndim != 2 or F.shape[0] != P.shape[0] or F.shape[1] < 1:
            raise ConfigError(
                f"table features must have shape ({P.shape[0]}, k) to match the points, got {F.shape}"
            )
        for i in range(P.shape[0]):
            if not np.all(np.isfinite(P[i])):
                raise ConfigError(f"feature table row {i}: point {P[i].tolist()} is not finite")
            if np.any((P[i] < -_CUBE_TOL) | (P[i] > 1 + _CUBE_TOL)):
                raise ConfigError(f"feature table row {i}: point {P[i].tolist()} is outside the unit cube")
            if not np.all(np.isfinite(F[i])):
                raise ConfigError(f"feature table row {i}: features {F[i].tolist()} are not finite")
        if space is not None:
            bad = np.flatnonzero(~space.feasible_mask(space.from_unit(P)))
            if bad.size:
                i = int(bad[0])
                raise ConfigError(
                    f"feature table row {i}: {space.to_dict(space.from_unit(P[i]))} is outside the "
                    f"space {space.name!r} (bounds or constraints)"
                )
        if isinstance(neighbors, bool) or not isinstance(neighbors, int) or neighbors < 1:
            raise ConfigError(f"neighbors={neighbors!r}; expected an integer >= 1")
        self.points = P
        self.features = F
        self.dim = P.shape[1]
        self.n_features = F.shape[1]
        self._norm = _Normaliser(F) if normalize else None
        self._cache = _RowCache(cache_size)
        if self.lookup is Lookup.NEAREST:
            self._tree = cKDTree(P)
        else:
            self._rbf = RBFInterpolator(P, F, neighbors=min(neighbors, P.shape[0]), kernel="linear",
                                        degree=0)

    @classmethod
    def precompute(cls, space: ParameterSpace, fn: Callable[[dict[str, float]], Any], n_points: int,
                   rng: np.random.Generator, **options: Any) -> TableFeatureMap:
        """Evaluate ``fn`` on ``n_points`` feasible scrambled-Sobol points of ``space``.

        Args:
            space: The parameter space.
            fn: Raw parameters ``{name: value}`` (derived included) → features (k,).
            n_points: Table size.
            rng: Seeds the Sobol scrambling.
            **options: Passed to the constructor (``lookup``, ``normalize``, …).
        """
        U = space.sample_unit(n_points, rng)
        rows = []
        for i, u in enumerate(U):
            f = np.atleast_1d(np.asarray(fn(space.to_dict(space.from_unit(u))), dtype=float)).reshape(-1)
            if rows and f.size != rows[0].size:
                raise ConfigError(f"fn returned {f.size} features at table row {i}; expected {rows[0].size}")
            rows.append(f)
        return cls(U, np.array(rows), space=space, **options)

    @classmethod
    def from_rows(cls, space: ParameterSpace, rows: Sequence[Mapping[str, Any]],
                  feature_columns: Sequence[str], **options: Any) -> TableFeatureMap:
        """A table from rows of raw parameters and feature columns (e.g. ``csv.DictReader``).

        Raises:
            ConfigError: A row with a missing or unknown column, a non-numeric value, or a point
                outside the space — naming the row index (0-based).
        """
        cols = list(feature_columns)
        if not cols:
            raise ConfigError("feature_columns must name at least one column")
        known = set(space.names) | {d.name for d in space.derived} | set(cols)
        P, F = [], []
        for i, row in enumerate(rows):
            where = f"feature table row {i}"
            unknown = sorted(set(row) - known)
            if unknown:
                raise ConfigError(f"{where}: unknown column(s) {unknown}; expected parameters "
                                  f"{list(space.names)} and features {cols}")
            missing = [c for c in (*space.names, *cols) if c not in row]
            if missing:
                raise ConfigError(f"{where}: missing column(s) {missing}")
            try:
                x = np.array([float(row[n]) for n in space.names])
                f = np.array([float(row[c]) for c in cols])
            except (TypeError, ValueError) as err:
                raise ConfigError(f"{where}: non-numeric value ({err})") from err
            if not space.is_feasible(x):
                raise ConfigError(f"{where}: {space.to_dict(x) if np.all(np.isfinite(x)) else x.tolist()} "
                                  f"is outside the space {space.name!r}")
            P.append(space.to_unit(x))
            F.append(f)
        if not P:
            raise ConfigError("the feature table has no rows")
        return cls(np.array(P), np.array(F), space=space, **options)

    @property
    def cache_info(self) -> dict[str, int]:
        """``{"hits", "misses", "size"}`` of the point cache."""
        return {"hits": self._cache.hits, "misses": self._cache.misses, "size": len(self._cache)}

    def _look(self, U: np.ndarray) -> np.ndarray:
        if self.lookup is Lookup.NEAREST:
            _, idx = self._tree.query(U)
            return self.features[np.asarray(idx, dtype=int)]
        return np.asarray(self._rbf(U), dtype=float).reshape(U.shape[0], -1)

    def __call__(self, U: np.ndarray) -> np.ndarray:
        """Features of unit-cube points ``U`` (n, d) → (n, k)."""
        U = _check_points(U, self.dim, "U")
        F = self._cache.lookup(U, self._look)
        return F if self._norm is None else self._norm(F)


# --------------------------------------------------------------------------------------------
# Exosuit: features of the force profile itself
# --------------------------------------------------------------------------------------------


def nominal_velocity(actuator: str, gait_pct: np.ndarray) -> np.ndarray:
    """A nominal, wearer-independent joint-velocity *shape* (dimensionless, peak 1) in the
    direction the actuator assists, over the actuator's own gait-cycle convention.

    * ``"hip"`` (%GC from maximum hip flexion): the hip extends from 0 % to maximum extension
      near 55 % (positive half-sine), then flexes (negative half-sine).
    * ``"ankle"`` (%GC from heel strike): plantarflexion at push-off, 45–62 % (positive
      half-sine); dorsiflexion during mid-stance, 10–45 % (negative, 0.3 peak); zero otherwise.

    Textbook gait shapes, used only to weight force by "when it can do positive work"; not
    measured from anyone.
    """
    g = np.asarray(gait_pct, dtype=float)
    if actuator == "hip":
        return np.where(g <= 55.0, np.sin(np.pi * g / 55.0), -np.sin(np.pi * (g - 55.0) / 45.0))
    if actuator == "ankle":
        push = (g >= 45.0) & (g <= 62.0)
        dorsi = (g >= 10.0) & (g < 45.0)
        return np.where(push, np.sin(np.pi * (g - 45.0) / 17.0),
                        np.where(dorsi, -0.3 * np.sin(np.pi * (g - 10.0) / 35.0), 0.0))
    raise ConfigError(f"no nominal velocity for actuator {actuator!r}; known: hip, ankle")


def profile_features(profile: ForceProfile) -> dict[str, float]:
    """Wearer-independent features of one force table.

    Returns:
        ``impulse`` — ∫ F dg (N·%GC); ``positive_work`` — ∫ F · max(v, 0) dg with the nominal
        velocity shape v (:func:`nominal_velocity`; N·%GC); ``peak_timing`` — where F peaks (%GC);
        ``rise`` / ``fall`` — from onset to peak / peak to offset (%GC), onset and offset where F
        crosses 5 % of its peak; ``centroid`` — ∫ g F / ∫ F (%GC); ``rms_force`` — the RMS force
        over the cycle (N). A zero table has every feature 0.
    """
    g = profile.gait_pct
    f = np.clip(profile.force_n, 0.0, None)
    peak = float(f.max())
    if peak <= 0.0:
        return dict.fromkeys(PROFILE_FEATURES, 0.0)
    i_peak = int(np.argmax(f))
    above = np.flatnonzero(f > _ONSET_FRACTION * peak)
    onset, offset = float(g[above[0]]), float(g[above[-1]])
    impulse = float(np.trapezoid(f, g))
    v = nominal_velocity(profile.actuator, g)
    span = float(g[-1] - g[0])
    return {
        "impulse": impulse,
        "positive_work": float(np.trapezoid(f * np.clip(v, 0.0, None), g)),
        "peak_timing": float(g[i_peak]),
        "rise": float(g[i_peak]) - onset,
        "fall": offset - float(g[i_peak]),
        "centroid": float(np.trapezoid(g * f, g)) / impulse,
        "rms_force": math.sqrt(float(np.trapezoid(f * f, g)) / span),
    }


PROFILE_FEATURES: tuple[str, ...] = (
    "impulse", "positive_work", "peak_timing", "rise", "fall", "centroid", "rms_force",
)
"""Every feature :func:`profile_features` computes."""
DEFAULT_PROFILE_FEATURES: tuple[str, ...] = ("impulse", "positive_work", "peak_timing", "rise", "fall")
"""The default selection of :class:`ProfileFeatureMap`."""


class ProfileFeatureMap(CallableFeatureMap):
    """φ(u) = features of the force profile(s) of the setting u (no wearer data needed).

    Builds the tables with :func:`hilbo_core.profiles.build_profile` for the space's preset and
    computes :func:`profile_features` for each actuator; features are named
    ``"<actuator>.<feature>"`` and min–max normalised over a scrambled-Sobol reference set of the
    space.

    Args:
        space: A preset space with a force-profile builder (``space.name``).
        features: Which of :data:`PROFILE_FEATURES`.
        n_reference: Size of the normalisation reference set.
        seed: Seeds the reference set.
        cache_size: Points remembered.
        **profile_options: Passed to ``build_profile`` (e.g. ``body_mass_kg``).

    Raises:
        ConfigError: Unknown feature names, or a space without a profile builder.
    """

    def __init__(self, space: ParameterSpace, features: Sequence[str] = DEFAULT_PROFILE_FEATURES, *,
                 n_reference: int = 256, seed: int = 0, cache_size: int = 100_000,
                 **profile_options: Any) -> None:
        feats = tuple(features)
        unknown = [f for f in feats if f not in PROFILE_FEATURES]
        if unknown or not feats:
            raise ConfigError(
                f"unknown profile feature(s) {unknown or feats}; choose from {list(PROFILE_FEATURES)}"
            )
        self.space = space
        self.selected = feats
        self._options = dict(profile_options)
        reference = space.sample_unit(n_reference, np.random.default_rng(seed))
        probe = build_profile(space.name, space.to_dict(space.from_unit(reference[0])), **self._options)
        self.names = tuple(f"{p.actuator}.{f}" for p in probe for f in feats)
        super().__init__(self._features_of, space.dim, cache_size=cache_size, reference=reference)

    def _features_of(self, u: np.ndarray) -> np.ndarray:
        x = self.space.from_unit(np.clip(u, 0.0, 1.0))
        try:
            profiles = build_profile(self.space.name, self.space.to_dict(x), **self._options)
        except InfeasibleError:
            # EI refinement may probe outside the linear constraints (finite-difference steps,
            # SLSQP line searches). Most such points still make a profile (e.g. t_on > t_p − 15);
            # where none can be built (t_on >= t_p), use the nearest feasible point's features,
            # which keeps φ continuous across the boundary.
            x = _project_feasible(self.space, x)
            profiles = build_profile(self.space.name, self.space.to_dict(x), **self._options)
        out: list[float] = []
        for prof in profiles:
            feats = profile_features(prof)
            out.extend(feats[f] for f in self.selected)
        return np.array(out)


def _project_feasible(space: ParameterSpace, x: np.ndarray) -> np.ndarray:
    """Nearest feasible point (unit-cube Euclidean) to raw ``x``: a small QP solved by SLSQP."""
    A_u, b_u = space.unit_constraints()
    u0 = np.clip(space.to_unit(x), 0.0, 1.0)
    # Aim slightly inside the constraints: SLSQP meets them only to ~1e-7.
    margin = 1e-6
    res = minimize(lambda v: float(np.sum((v - u0) ** 2)), u0, jac=lambda v: 2.0 * (v - u0),
                   method="SLSQP", bounds=[(0.0, 1.0)] * space.dim,
                   constraints=[{"type": "ineq", "fun": lambda v: b_u - margin - A_u @ v,
                                 "jac": lambda v: -A_u}])
    x_new = space.from_unit(np.clip(res.x, 0.0, 1.0))
    if not space.is_feasible(x_new):
        raise ConfigError(f"cannot project {space.to_dict(x)} onto the feasible set of {space.name!r}")
    return x_new
