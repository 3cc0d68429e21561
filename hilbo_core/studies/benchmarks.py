"""The simulation study of Kim et al. 2019 §III.2: test functions, measurement model, metric y_t.

* :data:`FUNCTIONS` — the four functions of Kim et al. 2019's Table I (Hartmann-6, Ackley-4, Levy-4,
  Branin) with their domains, global minima, known minimisers and the priors (μ̃, σ̃) Kim et al. 2019
  initialises every estimate with. Definitions follow Surjanovic & Bingham's Virtual Library of
  Simulation Experiments (the standard forms Kim et al. 2019's Table I values belong to).
* The measurement model: a measurement of x is ``z = f(x) + ε`` with ``ε ~ N(0, σ_z²)``; the
  estimate of x starts at (μ̃, σ̃²) and fuses every z by the product of Gaussians. Kim et al. 2019's
  estimator fuses every z with σ_z² (:class:`~hilbo_core.metabolic.GaussianProductEstimator`,
  ``noise_estimate="seed"``); the default learns the measurement variance from the trial's
  measurements with σ_z² as its prior (:class:`~hilbo_core.metabolic.PooledNoiseEstimator`,
  ``"pooled"``, :class:`NoiseEstimate`).
* :func:`stopping_trial` — one trial of one method: the same ``n_explore`` design points for every
  method (the design depends on the seed only), ``max_breaths`` (N) measurements each, then
  ``budget`` further measurements of Bayesian optimisation, and the metric

      y_t = (f(x_t) − f*) / (f(x_0) − f*)

  after every measurement t of the optimisation phase, where x_t is the GP's estimated minimum
  among the evaluated points (the definition of :meth:`HILOptimizer.best`, read from the
  incumbent the next ``ask()`` computes for the stopping rule, which saves a second GP fit per
  evaluation) and x_0 the recommendation at the end of exploration.

Noise levels. Kim et al. 2019 write ``σ_z = [σ̃²/10, σ̃², 10σ̃²]``: these are variances (they carry σ̃²),
so here ``noise`` is the factor ``σ_z² / σ̃²`` ∈ {0.1, 1, 10}. Two readings of Kim et al. 2019 exist and
both are offered (:class:`NoiseModel`): ``matched`` (default) — the measurements really have
variance σ_z² and the estimator knows it ("three different levels of measurement variation",
Fig. 2); ``assumed`` — the measurements have variance σ̃² and σ_z² is only what the estimator
assumes, i.e. under-/correctly/over-estimated noise (Kim et al. 2019's discussion of "inaccuracy in
the measurement noise").
"""

from __future__ import annotations

import enum
import functools
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any

import numpy as np
import numpy.typing as npt

from hilbo_core.errors import ConfigError, OptimizerStateError
from hilbo_core.metabolic import GaussianProductEstimator, MeasurementNoisePool, PooledNoiseEstimator
from hilbo_core.optimizer import HILOptimizer, OptimizerConfig, Phase
from hilbo_core.protocol import DEFAULT_BREATH_INTERVAL_S
from hilbo_core.space import DesignKind, Parameter, ParameterSpace

__all__ = [
    "FUNCTIONS",
    "MEASUREMENT_INTERVAL_S",
    "METHODS",
    "NOISE_LEVELS",
    "SOUND_STUDY_FLOOR_S",
    "NoiseEstimate",
    "NoiseModel",
    "StoppingMethod",
    "StoppingProtocol",
    "TestFunction",
    "ackley",
    "branin",
    "estimator_factory",
    "hartmann6",
    "levy",
    "measure",
    "stopping_trial",
    "study_optimizer",
    "y_metric",
]

NOISE_LEVELS: tuple[float, ...] = (0.1, 1.0, 10.0)
"""σ_z² / σ̃² of Kim et al. 2019 §III.2 (σ_z² = σ̃²/10, σ̃², 10σ̃²)."""

# Seeds the measurement-noise stream of a trial apart from the optimizer's own stream.
_NOISE_STREAM = 0x5EED

MEASUREMENT_INTERVAL_S = DEFAULT_BREATH_INTERVAL_S
"""Seconds between two measurements of the study: each measurement stands for one breath (the
seed's N = 45 measurements per evaluation are its 45 breaths), at a walking adult's mean breath
interval. The estimators of the study ignore time; the sound rules' times read it: the
default's ``boundary_s`` 60 s is 20 measurements here, ``sound-60s``'s floor 20 too."""

SOUND_STUDY_FLOOR_S = 0.0
"""The sound rule's time floor (``min_decision_s``) in this study: none. In the lab the floor
waits until the previous setting's level has faded from the breaths (the first-order transition,
:class:`~hilbo_core.stopping.SoundRule`). Kim et al. 2019 §III.2's measurements have no
transition (every z is f(x) + ε from the first one, and the estimate is unbiased after one), so
the same rationale gives no floor. The sequential boundary stays (its reason, repeated looks at
accumulating data, holds here too), as do the threshold floor, the GP-posterior incumbent and the
accept stop."""


# --------------------------------------------------------------------------------------------
# Test functions (vectorised: x of shape (..., d) -> values of shape (...))
# --------------------------------------------------------------------------------------------

_H6_ALPHA = np.array([1.0, 1.2, 3.0, 3.2])
_H6_A = np.array([
    [10.0, 3.0, 17.0, 3.5, 1.7, 8.0],
    [0.05, 10.0, 17.0, 0.1, 8.0, 14.0],
    [3.0, 3.5, 1.7, 10.0, 17.0, 8.0],
    [17.0, 8.0, 0.05, 10.0, 0.1, 14.0],
])
_H6_P = 1e-4 * np.array([
    [1312.0, 1696.0, 5569.0, 124.0, 8283.0, 5886.0],
    [2329.0, 4135.0, 8307.0, 3736.0, 1004.0, 9991.0],
    [2348.0, 1451.0, 3522.0, 2883.0, 3047.0, 6650.0],
    [4047.0, 8828.0, 8732.0, 5743.0, 1091.0, 381.0],
])


def _as_points(x: npt.ArrayLike, d: int, name: str) -> np.ndarray:
    arr = np.asarray(x, dtype=float)
    if arr.ndim == 0 or arr.shape[-1] != d:
        raise ConfigError(f"{name} takes points of dimension {d} (shape (..., {d})), got shape {arr.shape}")
    return arr


def hartmann6(x: npt.ArrayLike) -> np.ndarray:
    """Hartmann-6 on [0, 1]^6: ``−Σ_i α_i exp(−Σ_j A_ij (x_j − P_ij)²)``.

    Args:
        x: Points, shape (..., 6).

    Returns:
        Values, shape (...). Global minimum −3.32237 at
        (0.20169, 0.150011, 0.476874, 0.275332, 0.311652, 0.6573).
    """
    x = _as_points(x, 6, "hartmann6")
    inner = np.sum(_H6_A * (x[..., None, :] - _H6_P) ** 2, axis=-1)  # (..., 4)
    return -np.sum(_H6_ALPHA * np.exp(-inner), axis=-1)


def ackley(x: npt.ArrayLike, a: float = 20.0, b: float = 0.2, c: float = 2.0 * math.pi) -> np.ndarray:
    """Ackley in any dimension d: ``−a·exp(−b·√(mean x²)) − exp(mean cos(c·x)) + a + e``.

    Args:
        x: Points, shape (..., d).
        a, b, c: The usual constants (20, 0.2, 2π).

    Returns:
        Values, shape (...); global minimum 0 at the origin.
    """
    x = np.asarray(x, dtype=float)
    if x.ndim == 0:
        raise ConfigError(f"ackley takes points of shape (..., d), got shape {x.shape}")
    term1 = -a * np.exp(-b * np.sqrt(np.mean(x**2, axis=-1)))
    term2 = -np.exp(np.mean(np.cos(c * x), axis=-1))
    return term1 + term2 + a + math.e


def levy(x: npt.ArrayLike) -> np.ndarray:
    """Levy in any dimension d, with ``w = 1 + (x − 1)/4``.

    ``sin²(πw_1) + Σ_{i<d} (w_i − 1)²[1 + 10 sin²(πw_i + 1)] + (w_d − 1)²[1 + sin²(2πw_d)]``.

    Args:
        x: Points, shape (..., d).

    Returns:
        Values, shape (...); global minimum 0 at (1, ..., 1).
    """
    x = np.asarray(x, dtype=float)
    if x.ndim == 0:
        raise ConfigError(f"levy takes points of shape (..., d), got shape {x.shape}")
    w = 1.0 + (x - 1.0) / 4.0
    head = np.sin(math.pi * w[..., 0]) ** 2
    mid = np.sum((w[..., :-1] - 1.0) ** 2 * (1.0 + 10.0 * np.sin(math.pi * w[..., :-1] + 1.0) ** 2), axis=-1)
    wd = w[..., -1]
    tail = (wd - 1.0) ** 2 * (1.0 + np.sin(2.0 * math.pi * wd) ** 2)
    return head + mid + tail


def branin(x: npt.ArrayLike) -> np.ndarray:
    """Branin on [−5, 10] × [0, 15]: ``(x2 − b x1² + c x1 − r)² + s(1 − t) cos x1 + s``.

    With b = 5.1/(4π²), c = 5/π, r = 6, s = 10, t = 1/(8π).

    Args:
        x: Points, shape (..., 2).

    Returns:
        Values, shape (...); global minimum 5/(4π) ≈ 0.397887 at (−π, 12.275), (π, 2.275) and
        (3π, 2.475).
    """
    x = _as_points(x, 2, "branin")
    x1, x2 = x[..., 0], x[..., 1]
    b, c, r, s, t = 5.1 / (4.0 * math.pi**2), 5.0 / math.pi, 6.0, 10.0, 1.0 / (8.0 * math.pi)
    return (x2 - b * x1**2 + c * x1 - r) ** 2 + s * (1.0 - t) * np.cos(x1) + s


@dataclass(frozen=True)
class TestFunction:
    """A row of Kim et al. 2019 Table I.

    Attributes:
        name: Identifier used on the command line and in results.
        fn: Vectorised objective, (..., d) -> (...).
        lower: Lower bounds of the domain, length d.
        upper: Upper bounds of the domain, length d.
        f_min: Global minimum f* (full precision; Table I prints it rounded).
        minimizers: Known global minimisers, each of length d.
        prior_mean: μ̃ of Table I, the initial mean of every estimate.
        prior_std: σ̃ of Table I, the initial standard deviation of every estimate.
    """

    __test__ = False  # not a pytest test class despite the name

    name: str
    fn: Callable[[np.ndarray], np.ndarray]
    lower: tuple[float, ...]
    upper: tuple[float, ...]
    f_min: float
    minimizers: tuple[tuple[float, ...], ...]
    prior_mean: float
    prior_std: float

    @property
    def dim(self) -> int:
        """Dimension d."""
        return len(self.lower)

    def space(self) -> ParameterSpace:
        """The domain as a box :class:`ParameterSpace` with parameters x1..xd."""
        return ParameterSpace(
            [Parameter(f"x{i + 1}", lo, hi)
             for i, (lo, hi) in enumerate(zip(self.lower, self.upper, strict=True))],
            name=self.name,
        )

    def __call__(self, x: npt.ArrayLike) -> np.ndarray:
        """f(x) for points of shape (..., d)."""
        return self.fn(np.asarray(x, dtype=float))

    def value(self, params: Mapping[str, float]) -> float:
        """f at a parameter dict ``{"x1": ..., ...}`` (as the optimizer reports points)."""
        return float(self.fn(np.array([float(params[f"x{i + 1}"]) for i in range(self.dim)])))


# Table I of Kim et al. 2019 (μ̃, σ̃ as printed); the minima at full precision.
FUNCTIONS: Mapping[str, TestFunction] = MappingProxyType({
    "hartmann6": TestFunction(
        "hartmann6", hartmann6, (0.0,) * 6, (1.0,) * 6, -3.3223680114155156,
        ((0.20169, 0.150011, 0.476874, 0.275332, 0.311652, 0.6573),), -0.259, 0.383),
    "ackley": TestFunction(
        "ackley", ackley, (-32.768,) * 4, (32.768,) * 4, 0.0, ((0.0,) * 4,), 20.882, 1.027),
    "levy": TestFunction(
        "levy", levy, (-10.0,) * 4, (10.0,) * 4, 0.0, ((1.0,) * 4,), 42.544, 27.939),
    "branin": TestFunction(
        "branin", branin, (-5.0, 0.0), (10.0, 15.0), 5.0 / (4.0 * math.pi),
        ((-math.pi, 12.275), (math.pi, 2.275), (3.0 * math.pi, 2.475)), 54.452, 51.129),
})


def _lookup(kind: str, name: object, table: Mapping[str, Any]) -> Any:
    if not isinstance(name, str) or name not in table:
        raise ConfigError(f"unknown {kind} {name!r}; choose one of {sorted(table)}")
    return table[name]


# --------------------------------------------------------------------------------------------
# Measurement model and metric
# --------------------------------------------------------------------------------------------


class NoiseModel(enum.Enum):
    """How the noise level enters (see the module docstring)."""

    MATCHED = "matched"  # measurements have variance σ_z²; the estimator assumes σ_z²
    ASSUMED = "assumed"  # measurements have variance σ̃²; the estimator assumes σ_z²


class NoiseEstimate(enum.Enum):
    """What measurement variance the estimates fuse with.

    ``seed``: σ_z², always (Kim et al. 2019 §III.2's estimator). ``pooled`` (the default): σ_z² is the
    prior of a variance learnt from every measurement of the trial
    (:class:`~hilbo_core.metabolic.MeasurementNoisePool`, 3 pseudo-measurements), as hilbo's
    breath estimator learns a person's breath noise. Under ``assumed`` with σ_z² ≠ σ̃² Kim et al. 2019's
    estimator is over- or under-confident by the factor σ_z²/σ̃² at every measurement
    (docs/results.md, "Stopping benchmarks" and its git history); the pooled one learns σ̃² during exploration.
    """

    SEED = "seed"
    POOLED = "pooled"


def estimator_factory(fn: TestFunction, noise: float,
                      estimate: NoiseEstimate = NoiseEstimate.POOLED) -> Callable[[], Any]:
    """The estimator factory of one trial: (μ̃, σ̃²) priors, assumed measurement variance noise·σ̃².

    Call it once per trial: with ``pooled`` its estimators share one
    :class:`~hilbo_core.metabolic.MeasurementNoisePool`.
    """
    prior_var = fn.prior_std**2
    assumed_var = check_noise(noise) * prior_var
    if NoiseEstimate(estimate) is NoiseEstimate.SEED:
        return functools.partial(GaussianProductEstimator, fn.prior_mean, prior_var, assumed_var)
    pool = MeasurementNoisePool(assumed_var)
    return functools.partial(PooledNoiseEstimator, fn.prior_mean, prior_var, pool)


def measure(f_value: float, var: float, rng: np.random.Generator) -> float:
    """One noisy measurement ``z = f(x) + ε``, ``ε ~ N(0, var)`` (Kim et al. 2019 §III.2)."""
    return float(f_value + rng.normal(0.0, math.sqrt(var)))


def y_metric(f_x: float | npt.ArrayLike, f_x0: float, f_min: float) -> float | np.ndarray:
    """Kim et al. 2019 §III.2's ``y_t = (f(x_t) − f*) / (f(x_0) − f*)``.

    0 at the optimum, 1 at the post-exploration recommendation, above 1 when the recommendation
    got worse. If x_0 is already optimal (f(x_0) = f*), y is 0 where f(x_t) = f* and +inf
    elsewhere.
    """
    num = np.asarray(f_x, dtype=float) - f_min
    den = f_x0 - f_min
    if den <= 0.0:
        out = np.where(num <= 0.0, 0.0, np.inf)
    else:
        out = np.maximum(num, 0.0) / den
    return float(out) if out.ndim == 0 else out


# --------------------------------------------------------------------------------------------
# Methods and the trial
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class StoppingMethod:
    """A way to run the optimisation phase: :class:`HILOptimizer` options for one method.

    Attributes:
        name: Identifier on the command line and in results.
        description: One line for tables.
        options: :class:`~hilbo_core.optimizer.OptimizerConfig` overrides (e.g. ``stopping``).
    """

    name: str
    description: str
    options: Mapping[str, Any] = field(default_factory=dict)


METHODS: Mapping[str, StoppingMethod] = MappingProxyType({
    "fixed": StoppingMethod("fixed", "BO, every evaluation measured for the full N (the seed's baseline)",
                            MappingProxyType({"stopping": "fixed"})),
    "adaptive": StoppingMethod("adaptive", "BO with Algorithm 2 thresholds and the σ-scaled offset rule",
                               MappingProxyType({"stopping": "adaptive"})),
    "sound": StoppingMethod("sound", "BO with hilbo's default rule (sound: sequential boundary, threshold "
                            "floor, GP-posterior incumbent, accept stop; no time floor, the study has "
                            "no transition)",
                            MappingProxyType({"stopping": "sound", "min_decision_s": SOUND_STUDY_FLOOR_S})),
    "sound-60s": StoppingMethod("sound-60s", "the earlier sound rule (sound-floor): the lab's fixed 60 s "
                                "time floor read as 20 breath-long measurements, accept at 3 σ",
                                MappingProxyType({"stopping": "sound-floor"})),
})
"""The registry of methods ``stopping_trial`` accepts by name; pass a :class:`StoppingMethod`
object for anything else."""

_PROTECTED_OPTIONS = frozenset({"n_explore", "max_breaths", "window", "budget_breaths", "budget_s", "seed",
                                "design"})


@dataclass(frozen=True)
class StoppingProtocol:
    """The study's protocol (defaults: Kim et al. 2019 §III.2).

    Attributes:
        n_explore: Exploration points (6), each measured ``max_breaths`` times.
        max_breaths: N, the maximum measurements per evaluation (45).
        window: Algorithm 2's window W (2).
        budget: Measurements of the optimisation phase (630 = 14 fixed evaluations).
        noise_model: ``"matched"`` or ``"assumed"`` (:class:`NoiseModel`).
        noise_estimate: ``"pooled"`` or ``"seed"`` (:class:`NoiseEstimate`).
        n_candidates: Feasible Sobol candidates per EI maximisation.
        n_local: Candidates refined locally per EI maximisation.
        design: The exploration points (:class:`~hilbo_core.space.DesignKind`), the same for
            every method of a trial: ``sobol_only`` (default: scrambled Sobol points without a
            centre point, as the seed's Fig. 2 study; the domain's centre is Ackley's optimum and
            near Levy's), or a lab session's ``sobol``/``maximin`` (both start at the centre).
        prior_mean_sd: The GP's prior mean for every method, in SDs of the observations above
            their average (``OptimizerConfig.prior_mean_sd``): 0 (default) is Kim et al.
            2019's GP; 0.5 is a lab session's with the sound rules.
    """

    n_explore: int = 6
    max_breaths: int = 45
    window: int = 2
    budget: int = 630
    noise_model: NoiseModel = NoiseModel.MATCHED
    noise_estimate: NoiseEstimate = NoiseEstimate.POOLED
    n_candidates: int = 1024
    # OptimizerConfig's 3. One refinement makes the campaign 1.6x faster but changed the fixed
    # method's y_T beyond noise on the 6-D functions (docs/results.md's git history, "Campaign
    # time on 2026-12-05: 20 minutes"), so it is an option (--n-local 1), not the default.
    n_local: int = 3
    design: DesignKind = DesignKind.SOBOL_ONLY
    prior_mean_sd: float = 0.0

    def __post_init__(self) -> None:
        choice: type[enum.Enum]
        for name, choice in (("noise_model", NoiseModel), ("noise_estimate", NoiseEstimate),
                             ("design", DesignKind)):
            value = getattr(self, name)
            try:
                object.__setattr__(self, name, choice(value))
            except ValueError as err:
                raise ConfigError(f"{name}={value!r}; choose one of {[m.value for m in choice]}") from err
        for name, low in (("n_explore", 1), ("max_breaths", 2), ("window", 0), ("budget", 1),
                          ("n_candidates", 16), ("n_local", 0)):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < low:
                raise ConfigError(f"{name}={value!r}; expected an integer >= {low}")
        if self.budget < self.max_breaths:
            raise ConfigError(
                f"budget={self.budget} measurements is smaller than one full evaluation "
                f"(max_breaths N={self.max_breaths}); give budget >= {self.max_breaths}"
            )
        # The optimizer's own check (a number of SDs in [0, 3]) is the final word.
        OptimizerConfig(prior_mean_sd=self.prior_mean_sd)
        object.__setattr__(self, "prior_mean_sd", float(self.prior_mean_sd))

    def to_json(self) -> dict[str, Any]:
        """JSON-able form."""
        return {"n_explore": self.n_explore, "max_breaths": self.max_breaths, "window": self.window,
                "budget": self.budget, "noise_model": self.noise_model.value,
                "noise_estimate": self.noise_estimate.value,
                "n_candidates": self.n_candidates, "n_local": self.n_local,
                "design": self.design.value,
                # only when set, so the protocols of earlier campaigns read (and resume) as before
                **({"prior_mean_sd": self.prior_mean_sd} if self.prior_mean_sd else {})}


def resolve_function(function: str | TestFunction) -> TestFunction:
    """A :class:`TestFunction` by name (or the object itself); ConfigError naming the choices."""
    return function if isinstance(function, TestFunction) else _lookup("function", function, FUNCTIONS)


def resolve_method(method: str | StoppingMethod) -> StoppingMethod:
    """A :class:`StoppingMethod` by name (or the object itself); ConfigError naming the choices."""
    if isinstance(method, StoppingMethod):
        bad = sorted(set(method.options) & _PROTECTED_OPTIONS)
        if bad:
            raise ConfigError(f"method {method.name!r} may not override protocol option(s) {bad}")
        return method
    return _lookup("method", method, METHODS)


def check_noise(noise: float) -> float:
    """A noise factor σ_z²/σ̃² (finite, > 0); ConfigError otherwise."""
    expected = f"expected a positive factor such as {list(NOISE_LEVELS)}"
    try:
        value = float(noise)
    except (TypeError, ValueError) as err:
        raise ConfigError(f"noise={noise!r}; {expected}") from err
    if not (math.isfinite(value) and value > 0.0):
        raise ConfigError(f"noise={noise!r}; {expected}")
    return value


def study_optimizer(fn: TestFunction, proto: StoppingProtocol, seed: int,
                    estimator: Callable[[], Any],
                    options: Mapping[str, Any] = MappingProxyType({})) -> HILOptimizer:
    """The optimizer of one trial of the study, a method's ``options`` on top.

    Every method of a trial, and the exploration the Optuna peers start from, is built here, so
    they explore the same points with the same GP: the protocol's design, N, W, budget and
    candidates; as x_t the GP's estimated minimum among the evaluated points (§III.2); one GP
    for all (by default Kim et al.'s, its prior mean at the observations' average). x_0 is then
    the same for all of them, and they differ in their stopping.
    """
    return HILOptimizer(
        fn.space(), estimator_factory=estimator,
        n_explore=proto.n_explore, max_breaths=proto.max_breaths, window=proto.window,
        budget_breaths=proto.budget, seed=seed, n_candidates=proto.n_candidates,
        n_local=proto.n_local, design=proto.design,
        **{"recommend": "seed", "prior_mean_sd": proto.prior_mean_sd, **dict(options)},
    )


def stopping_trial(
    function: str | TestFunction,
    noise: float,
    method: str | StoppingMethod,
    seed: int,
    protocol: StoppingProtocol | None = None,
) -> dict[str, Any]:
    """One trial of Kim et al. 2019 §III.2 for one method.

    Deterministic in its arguments: the design (hence the exploration points) and the noise
    stream depend on ``seed`` only, so every method of a trial explores the same points with the
    same measurements and gets the same x_0.

    Args:
        function: A name in :data:`FUNCTIONS` or a :class:`TestFunction`.
        noise: σ_z² / σ̃² (Kim et al. 2019's levels are :data:`NOISE_LEVELS`).
        method: A name in :data:`METHODS` or a :class:`StoppingMethod`.
        seed: Trial seed (>= 0).
        protocol: The protocol (default: Kim et al. 2019's).

    Returns:
        JSON-able dict: ``function``, ``noise``, ``method``, ``seed``; ``y`` — list of
        ``budget + 1`` floats, y_t after t optimisation-phase measurements (y_0 = 1);
        ``evaluations`` and ``early_stops`` of the optimisation phase; ``measurements`` used
        (== budget); ``f_x0`` and ``f_final``, the true values of the first and last
        recommendation; ``x0`` and ``x_final`` as parameter dicts.

    Raises:
        ConfigError: Unknown function or method, bad noise, seed or protocol.
    """
    fn = resolve_function(function)
    meth = resolve_method(method)
    level = check_noise(noise)
    proto = protocol or StoppingProtocol()
    if isinstance(seed, bool) or not isinstance(seed, int | np.integer) or seed < 0:
        raise ConfigError(f"seed={seed!r}; expected an integer >= 0")
    prior_var = fn.prior_std**2
    true_var = level * prior_var if proto.noise_model is NoiseModel.MATCHED else prior_var
    opt = study_optimizer(fn, proto, int(seed), estimator_factory(fn, level, proto.noise_estimate),
                          meth.options)
    rng = np.random.default_rng([int(seed), _NOISE_STREAM])
    y = np.full(proto.budget + 1, np.nan)
    t = 0  # optimisation-phase measurements so far
    f_x0 = math.nan
    x0: dict[str, float] = {}
    rec: dict[str, float] = {}
    pending: int | None = None  # measurement whose evaluation just completed, y_t not yet known

    def recommend(params: dict[str, float]) -> float:
        nonlocal rec
        rec = params
        return float(y_metric(fn.value(params), f_x0, fn.f_min))

    while not opt.done:
        params = opt.ask()
        if pending is not None:
            # x_t, the GP's estimated minimum among the evaluated points, is exactly what
            # ask() has just computed for the stopping rule's incumbent (HILOptimizer.best()
            # would fit the same GP a second time). y_t holds from here to the next stop.
            incumbent = opt.incumbent
            if incumbent is None:
                raise OptimizerStateError("internal: no incumbent after an optimisation-phase ask()")
            y[pending] = recommend(incumbent[0])
            pending = None
        f_true = fn.value(params)
        i = 0
        while True:
            i += 1
            # One breath per measurement (MEASUREMENT_INTERVAL_S): what a time floor reads.
            step = opt.observe(i * MEASUREMENT_INTERVAL_S, measure(f_true, true_var, rng))
            if step.phase is Phase.OPTIMIZATION:
                t += 1
                y[t] = y[t - 1]
            if step.stop:
                break
        if step.phase is Phase.OPTIMIZATION:
            pending = t
        elif len(opt.evaluations) == proto.n_explore:
            # x_0: the recommendation the optimisation phase starts from (the same for every
            # method of a trial: same design, same measurements, same GP seed).
            x0 = opt.best()[0]
            rec = x0
            f_x0 = fn.value(x0)
            y[0] = 1.0
    if pending is not None:  # the budget ended with this evaluation: no ask() follows
        y[pending] = recommend(opt.best()[0])
    opt_evals = [e for e in opt.evaluations if e.phase == Phase.OPTIMIZATION.value]
    return {
        "function": fn.name,
        "noise": level,
        "method": meth.name,
        "seed": int(seed),
        "y": y.tolist(),
        "evaluations": len(opt_evals),
        "early_stops": sum(e.stopped_early for e in opt_evals),
        "measurements": t,
        "f_x0": f_x0,
        "f_final": fn.value(rec),
        "x0": x0,
        "x_final": rec,
    }
