"""Metabolic power from gas exchange and breath-by-breath estimation of the steady-state cost.

* :func:`brockway_watts` turns VO2/VCO2 into watts (Brockway's equation).
* :class:`MetabolicUKF` is the Unscented Kalman Filter of Kim et al. 2019 §II.C: it fits the first-order
  model ``m_t = c(1 - e^{-t/τ}) + c0·e^{-t/τ0}`` to the breaths of one assistance setting and
  reports, after every breath, the mean and variance of the steady-state cost ``c``.
* :class:`GaussianProductEstimator` is the measurement model of the simulation study (Kim et al. 2019
  §III.2): a Gaussian state fused with each measurement by the product of Gaussians.
  :class:`PooledNoiseEstimator` is the same with the measurement variance learnt from the run's
  data (:class:`MeasurementNoisePool`), the assumed σ_z² being only its prior.

All satisfy the :class:`Estimator` protocol. The optimizer takes an *estimator factory* (a
callable returning a fresh estimator for each setting) so benchmarks can swap the model. The
default estimator, :class:`~hilbo_core.estimation.TransitionEstimator`, lives in
``hilbo_core.estimation``.

Data-only observations (shared/DESIGN.md "Observations to the GP are
data-only"): every estimator here starts from a prior on c, and the GP has its own prior, so the
observation handed to the GP is the posterior with the estimator's prior on c divided out
(:func:`divide_gaussian`, each estimator's ``data_only()``). The stopping rule keeps using the
posterior (``mean``/``var``): it compares estimates, and the prior is part of what the estimator
believes.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import asdict, dataclass, fields
from typing import Any, Protocol, runtime_checkable

import numpy as np
import numpy.typing as npt
from filterpy.kalman import MerweScaledSigmaPoints, UnscentedKalmanFilter

from hilbo_core.errors import ConfigError, EstimatorError, MeasurementError

__all__ = [
    "DataOnlyEstimator",
    "DriftAwareEstimator",
    "Estimator",
    "EstimatorFactory",
    "GaussianProductEstimator",
    "MeasurementNoisePool",
    "MetabolicUKF",
    "PooledNoiseEstimator",
    "UKFConfig",
    "brockway_watts",
    "divide_gaussian",
]

# Data-only division: an observation whose data precision is below this fraction of the prior's
# carries ~no information; it goes to the GP with the variance below (times the prior's).
_MIN_DATA_PRECISION_FRAC = 1e-6
_UNINFORMATIVE_VAR_FACTOR = 1e6

# Brockway (1987): P[W] = 16.58·VO2[ml/s] + 4.51·VCO2[ml/s]; inputs arrive in ml/min.
_BROCKWAY_O2_J_PER_ML = 16.58
_BROCKWAY_CO2_J_PER_ML = 4.51
_S_PER_MIN = 60.0

# State layout of the UKF (Kim et al. 2019 §II.C, with the time constants as logs).
_I_C0, _I_C, _I_LOG_TAU0, _I_LOG_TAU = 0, 1, 2, 3
_DIM_X = 4
# Numerical guard only: time constants are clipped to [0.1 s, 1e5 s] inside the measurement
# model so an extreme sigma point cannot overflow exp(); physiological values are 20–80 s.
_LOG_TAU_MIN = math.log(0.1)
_LOG_TAU_MAX = math.log(1e5)


def brockway_watts(
    vo2_ml_min: float | npt.ArrayLike, vco2_ml_min: float | npt.ArrayLike
) -> float | npt.NDArray[np.float64]:
    """Metabolic power by Brockway's equation.

    ``P[W] = 16.58·VO2[ml/s] + 4.51·VCO2[ml/s]`` with VO2 and VCO2 given in ml/min.

    Args:
        vo2_ml_min: Oxygen uptake in ml/min; a scalar or an array.
        vco2_ml_min: Carbon-dioxide output in ml/min; broadcastable against ``vo2_ml_min``.

    Returns:
        Power in W: a float for scalar inputs, else an array of the broadcast shape.

    Raises:
        MeasurementError: An input is NaN, infinite or negative, or the shapes don't broadcast.
    """
    vo2 = np.asarray(vo2_ml_min, dtype=float)
    vco2 = np.asarray(vco2_ml_min, dtype=float)
    for name, arr in (("vo2_ml_min", vo2), ("vco2_ml_min", vco2)):
        bad = ~np.isfinite(arr) | (arr < 0)
        if bad.any():
            value = arr[bad].flat[0]
            raise MeasurementError(
                f"{name}={value!r} is not a finite, non-negative gas-exchange rate in ml/min"
            )
    try:
        watts = (_BROCKWAY_O2_J_PER_ML * vo2 + _BROCKWAY_CO2_J_PER_ML * vco2) / _S_PER_MIN
    except ValueError as err:
        raise MeasurementError(
            f"vo2_ml_min shape {vo2.shape} and vco2_ml_min shape {vco2.shape} do not broadcast"
        ) from err
    if watts.ndim == 0:
        return float(watts)
    return watts


class Estimator(Protocol):
    """Breath-by-breath estimator of the steady-state cost of one setting.

    A static protocol (not runtime-checkable): :class:`MetabolicUKF` has no estimate before its
    first breath and raises from ``mean``/``var`` then, which ``isinstance`` would trip over.

    ``update`` takes the time since the setting began (s, strictly increasing) and one
    measurement, and returns the (mean, variance) of the steady-state cost after fusing it.
    Arguments are positional so implementations may name them with their units.
    """

    def update(self, t: float, value: float, /) -> tuple[float, float]:
        """Fuse one measurement taken ``t`` seconds into the setting; return (mean, var)."""
        ...

    @property
    def mean(self) -> float:
        """Current mean of the steady-state cost."""
        ...

    @property
    def var(self) -> float:
        """Current variance of the steady-state cost."""
        ...

    @property
    def n_updates(self) -> int:
        """Number of measurements fused so far."""
        ...


@runtime_checkable
class DataOnlyEstimator(Protocol):
    """An estimator that can report its data-only information about c (for the GP)."""

    def data_only(self) -> tuple[float, float]:
        """(mean, variance) of c from the measurements alone: the posterior ÷ the prior on c."""
        ...


@runtime_checkable
class DriftAwareEstimator(Protocol):
    """An estimator whose :meth:`DataOnlyEstimator.data_only` variance includes a model error for
    the drift of a real steady state, and can say how much of it that is."""

    def model_error_var(self) -> float:
        """The drift's share of ``data_only()``'s variance (W²): an error that settings measured
        close in time share, unlike the breath noise."""
        ...


def divide_gaussian(
    post_mean: float, post_var: float, prior_mean: float, prior_var: float
) -> tuple[float, float]:
    """Gaussian division: the likelihood N(m_d, v_d) with posterior = prior × likelihood.

    ``1/v_d = 1/post_var − 1/prior_var`` and ``m_d = v_d·(post_mean/post_var −
    prior_mean/prior_var)``. When the data carry almost no information (data precision at most
    1e-6 of the prior's, or negative from round-off or an approximate filter), the result is
    (post_mean, 1e6·prior_var): a GP observation that changes nothing, at a sane location.

    Args:
        post_mean: Posterior mean.
        post_var: Posterior variance (> 0).
        prior_mean: Prior mean.
        prior_var: Prior variance (> 0).

    Returns:
        (data-only mean, data-only variance > 0).

    Raises:
        EstimatorError: A non-finite argument or a non-positive variance.
    """
    vals = (post_mean, post_var, prior_mean, prior_var)
    if not all(math.isfinite(v) for v in vals) or post_var <= 0.0 or prior_var <= 0.0:
        raise EstimatorError(
            f"divide_gaussian(post_mean={post_mean!r}, post_var={post_var!r}, "
            f"prior_mean={prior_mean!r}, prior_var={prior_var!r}): expected finite values "
            "and variances > 0"
        )
    prec_prior = 1.0 / prior_var
    prec_data = 1.0 / post_var - prec_prior
    if not prec_data > _MIN_DATA_PRECISION_FRAC * prec_prior:
        return float(post_mean), _UNINFORMATIVE_VAR_FACTOR * float(prior_var)
    var = 1.0 / prec_data
    mean = var * (post_mean / post_var - prior_mean * prec_prior)
    return float(mean), float(var)


EstimatorFactory = Callable[[], Estimator]
"""A callable returning a fresh :class:`Estimator` (one per evaluated setting)."""


def _as_float(value: object, name: str) -> float:
    """``float(value)``, or MeasurementError naming the value if it is not a number."""
    try:
        return float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError) as err:
        raise MeasurementError(f"{name}={value!r} is not a number") from err


def _check_gaussian_args(owner: str, **args: float) -> None:
    """ConfigError unless every argument is finite and every ``*_var`` one is > 0."""
    for name, value in args.items():
        v = float(value)
        positive = name.endswith("_var")
        if not math.isfinite(v) or (positive and v <= 0.0):
            what = "a finite variance > 0" if positive else "finite"
            raise ConfigError(f"{owner} {name}={value!r} must be {what}")


def _check_measurement(t_s: float, value: object, last_t_s: float | None) -> tuple[float, float]:
    """(t, z) of a measurement of the Gaussian-product estimators: a valid time, a finite z."""
    t = _check_time(t_s, last_t_s)
    z = _as_float(value, "value")
    if not math.isfinite(z):
        raise MeasurementError(f"value={value!r} at t_s={t_s!r} must be finite")
    return t, z


def _check_time(t_s: float, last_t_s: float | None) -> float:
    """Validate a measurement time: finite, non-negative, strictly after the previous one."""
    t = _as_float(t_s, "t_s")
    if not math.isfinite(t) or t < 0.0:
        raise MeasurementError(
            f"t_s={t_s!r} must be a finite, non-negative time since the setting began (s)"
        )
    if last_t_s is not None and t <= last_t_s:
        raise MeasurementError(
            f"t_s={t_s!r} must be strictly after the previous measurement at t_s={last_t_s!r}"
        )
    return t


@dataclass(frozen=True)
class UKFConfig:
    """Tuning of :class:`MetabolicUKF`.

    Attributes:
        tau0_init_s: Initial guess of τ0, the decay time of the initial cost c0, in s. Selinger &
            Donelan (2014) report ≈42 s for the metabolic response to a step in walking condition.
        tau_init_s: Initial guess of τ, the rise time towards the steady-state cost c, in s
            (same source).
        log_tau_std: Prior standard deviation of log τ0 and log τ (dimensionless). 0.3 puts the
            2σ range of a 40 s guess at about 22–73 s, the usual spread of walking time
            constants; a looser prior lets c and τ trade off and costs accuracy at 2 minutes.
        c0_rel_std: Prior standard deviation of c0 as a fraction of the first breath's power.
            c0 is what the first breaths measure, so the breath noise sets this scale.
        c_rel_std: Prior standard deviation of c as a fraction of the first breath's power. A new
            setting can move the steady state far from where the previous one left it.
        meas_noise_rel: Breath measurement noise (standard deviation) as a fraction of the
            predicted level; breath-by-breath metabolic power is noisy, typically 10–20 %.
        min_level_w: Floor in W on the level used to scale the measurement noise, so a tiny
            prediction cannot make a breath look noise-free.
        process_rel_std_per_sqrt_s: Random-walk standard deviation of c0 and c per √s, as a
            fraction of the first breath's power. The parameters are constant (§II.C); this small
            noise only keeps the covariance well conditioned and allows slow drift.
        process_log_tau_std_per_sqrt_s: Random-walk standard deviation of log τ0 and log τ per √s.
        alpha: Spread of the sigma points (Van der Merwe's scaled UT), in (0, 1].
        beta: Prior-knowledge parameter of the scaled UT; 2 is optimal for Gaussians.
        kappa: Secondary scaling of the scaled UT; must keep ``alpha²·(4 + kappa) > 0``. With the
            defaults (alpha 1, kappa 0) every sigma-point weight is non-negative, which keeps the
            covariance positive definite.
        max_watts: Breaths above this power in W are rejected as absurd.
    """

    tau0_init_s: float = 40.0
    tau_init_s: float = 40.0
    log_tau_std: float = 0.3
    c0_rel_std: float = 0.25
    c_rel_std: float = 0.5
    meas_noise_rel: float = 0.15
    min_level_w: float = 10.0
    process_rel_std_per_sqrt_s: float = 1e-3
    process_log_tau_std_per_sqrt_s: float = 1e-3
    alpha: float = 1.0
    beta: float = 2.0
    kappa: float = 0.0
    max_watts: float = 5000.0

    def __post_init__(self) -> None:
        """Validate every field (ConfigError names the field, its value and the allowed range)."""
        # (field, low, high, low inclusive?) — high is always inclusive.
        ranges: dict[str, tuple[float, float, bool]] = {
            "tau0_init_s": (0.0, 3600.0, False),
            "tau_init_s": (0.0, 3600.0, False),
            "log_tau_std": (0.0, 5.0, False),
            "c0_rel_std": (0.0, 10.0, False),
            "c_rel_std": (0.0, 10.0, False),
            "meas_noise_rel": (0.0, 2.0, False),
            "min_level_w": (0.0, 1e4, False),
            "process_rel_std_per_sqrt_s": (0.0, 1.0, True),
            "process_log_tau_std_per_sqrt_s": (0.0, 1.0, True),
            "alpha": (0.0, 1.0, False),
            "beta": (0.0, 10.0, True),
            "kappa": (-float(_DIM_X), 100.0, False),
            "max_watts": (0.0, 1e5, False),
        }
        for f in fields(self):
            value = getattr(self, f.name)
            low, high, low_inclusive = ranges[f.name]
            ok = (
                isinstance(value, int | float)
                and not isinstance(value, bool)
                and math.isfinite(value)
                and (value >= low if low_inclusive else value > low)
                and value <= high
            )
            if not ok:
                bracket = "[" if low_inclusive else "("
                raise ConfigError(
                    f"UKFConfig.{f.name}={value!r} must be a number in {bracket}{low:g}, {high:g}]"
                )


def _hx(state: npt.NDArray[np.float64], t_s: float) -> npt.NDArray[np.float64]:
    """Measurement model of Kim et al. 2019 §II.C: m_t = c(1 - e^{-t/τ}) + c0·e^{-t/τ0}.

    Args:
        state: Shape (4,): [c0 (W), c (W), log τ0 (log s), log τ (log s)].
        t_s: Seconds since the setting began.

    Returns:
        Shape (1,): the predicted breath power in W.
    """
    log_tau0 = min(max(float(state[_I_LOG_TAU0]), _LOG_TAU_MIN), _LOG_TAU_MAX)
    log_tau = min(max(float(state[_I_LOG_TAU]), _LOG_TAU_MIN), _LOG_TAU_MAX)
    decay0 = math.exp(-t_s * math.exp(-log_tau0))
    decay = math.exp(-t_s * math.exp(-log_tau))
    return np.array([state[_I_C] * (1.0 - decay) + state[_I_C0] * decay0])


def _fx(state: npt.NDArray[np.float64], dt: float) -> npt.NDArray[np.float64]:
    """Process model F(o) = o (+ v, added by the filter as Q): the parameters are constant."""
    return state


class MetabolicUKF:
    """UKF estimate of the steady-state metabolic cost of one setting (Kim et al. 2019 §II.C).

    The state is o = [c0, c, log τ0, log τ]; the process is a random walk o' = o + v (the
    parameters are constant up to slow drift) and a breath at time t measures
    ``m_t = c(1 - e^{-t/τ}) + c0·e^{-t/τ0} + w``. Estimating the logs of the time constants
    keeps them positive. The first breath sets the prior (c0 = c = its power, with the configured
    relative uncertainties, τ0 and τ at their guesses); every later breath is a predict step over
    the elapsed time followed by a measurement update.

    Create one per setting; ``t_s`` is the time since the setting began, on the cart's clock.

    Args:
        config: Tuning constants; ``UKFConfig()`` when omitted.
    """

    def __init__(self, config: UKFConfig | None = None) -> None:
        self._config = config if config is not None else UKFConfig()
        cfg = self._config
        points = MerweScaledSigmaPoints(_DIM_X, alpha=cfg.alpha, beta=cfg.beta, kappa=cfg.kappa)
        self._ukf = UnscentedKalmanFilter(
            dim_x=_DIM_X, dim_z=1, dt=1.0, hx=_hx, fx=_fx, points=points
        )
        self._q_rate = np.zeros((_DIM_X, _DIM_X))  # process-noise variance per second
        self._z = np.zeros(1)
        self._n_updates = 0
        self._last_t_s: float | None = None
        self._prior_c = (math.nan, math.nan)

    @property
    def config(self) -> UKFConfig:
        """The tuning constants in use."""
        return self._config

    @property
    def mean(self) -> float:
        """Posterior mean of the steady-state cost c, in W.

        Raises:
            EstimatorError: No breath has been fused yet.
        """
        self._require_started()
        return float(self._ukf.x[_I_C])

    @property
    def var(self) -> float:
        """Posterior variance of c, in W².

        Raises:
            EstimatorError: No breath has been fused yet.
        """
        self._require_started()
        return float(self._ukf.P[_I_C, _I_C])

    @property
    def n_updates(self) -> int:
        """Number of breaths fused (the first breath, which sets the prior, counts)."""
        return self._n_updates

    def data_only(self) -> tuple[float, float]:
        """The breaths' information about c without the prior on c (for the GP).

        The posterior marginal of c divided by its prior N(first breath, (c_rel_std·first)²)
        (:func:`divide_gaussian`). The prior of c is independent of the other state components
        (diagonal P0), so dividing the marginal removes it exactly in the linear-Gaussian
        limit; the first breath's own information stays (it lives in the prior of c0).

        Raises:
            EstimatorError: No breath has been fused yet.
        """
        self._require_started()
        return divide_gaussian(self.mean, self.var, self._prior_c[0], self._prior_c[1])

    @property
    def last_t(self) -> float | None:
        """Time in s (since the setting began) of the last accepted breath, or None."""
        return self._last_t_s

    def update(self, t_s: float, watts: float) -> tuple[float, float]:
        """Fuse one breath.

        Args:
            t_s: Seconds since the setting began; non-negative and strictly increasing.
            watts: The breath's metabolic power in W (e.g. from :func:`brockway_watts`).

        Returns:
            (mean of c in W, variance of c in W²) after this breath.

        Raises:
            MeasurementError: ``t_s`` or ``watts`` is invalid; the filter is left unchanged.
            EstimatorError: The covariance stopped being positive definite or the state became
                non-finite; the filter is left as it was before this breath.
        """
        t = _check_time(t_s, self._last_t_s)
        z = _as_float(watts, "watts")
        if not math.isfinite(z) or z <= 0.0 or z > self._config.max_watts:
            raise MeasurementError(
                f"watts={watts!r} at t_s={t_s!r} must be a finite power in "
                f"(0, {self._config.max_watts:g}] W"
            )
        if self._last_t_s is None:
            self._initialise(z)
        else:
            self._step(t, t - self._last_t_s, z)
        self._last_t_s = t
        self._n_updates += 1
        return float(self._ukf.x[_I_C]), float(self._ukf.P[_I_C, _I_C])

    def state_dict(self) -> dict[str, Any]:
        """JSON-able snapshot: config, counters and the filter's x (shape (4,)) and P (4×4).

        x is [c0 (W), c (W), log τ0, log τ] and P its covariance; both are None before the
        first breath.
        """
        started = self._n_updates > 0
        return {
            "config": asdict(self._config),
            "n_updates": self._n_updates,
            "last_t": self._last_t_s,
            "x": self._ukf.x.tolist() if started else None,
            "P": self._ukf.P.tolist() if started else None,
        }

    def _require_started(self) -> None:
        if self._n_updates == 0:
            raise EstimatorError("no estimate before the first breath; call update() first")

    def _initialise(self, z: float) -> None:
        """Prior from the first breath (its information lives in the prior of c0)."""
        cfg = self._config
        self._ukf.x = np.array([z, z, math.log(cfg.tau0_init_s), math.log(cfg.tau_init_s)])
        self._ukf.P = np.diag(
            [
                (cfg.c0_rel_std * z) ** 2,
                (cfg.c_rel_std * z) ** 2,
                cfg.log_tau_std**2,
                cfg.log_tau_std**2,
            ]
        )
        self._prior_c = (z, (cfg.c_rel_std * z) ** 2)
        q_c = (cfg.process_rel_std_per_sqrt_s * z) ** 2
        q_tau = cfg.process_log_tau_std_per_sqrt_s**2
        np.fill_diagonal(self._q_rate, [q_c, q_c, q_tau, q_tau])

    def _step(self, t: float, dt: float, z: float) -> None:
        """Predict over ``dt`` seconds, then update with the breath ``z`` taken at ``t``."""
        cfg = self._config
        ukf = self._ukf
        x_before, p_before = ukf.x.copy(), ukf.P.copy()
        try:
            ukf.Q = self._q_rate * dt  # random walk: variance grows linearly with time
            ukf.predict(dt=dt)
            # Noise scales with the level the model predicts (not the breath itself, which
            # would down-weight high breaths and bias the estimate low).
            level = max(abs(float(_hx(ukf.x, t)[0])), cfg.min_level_w)
            self._z[0] = z
            ukf.update(self._z, R=(cfg.meas_noise_rel * level) ** 2, t_s=t)
            p = 0.5 * (ukf.P + ukf.P.T)  # P - K S Kᵀ loses symmetry to rounding
            np.linalg.cholesky(p)  # raises LinAlgError unless positive definite
            if not np.isfinite(ukf.x).all():
                raise np.linalg.LinAlgError(f"non-finite state {ukf.x.tolist()}")
            ukf.P = p
        except (np.linalg.LinAlgError, ValueError, FloatingPointError) as err:
            ukf.x, ukf.P = x_before, p_before
            raise EstimatorError(
                f"UKF update at t_s={t!r} with watts={z!r} failed numerically "
                f"(covariance not positive definite or state not finite): {err}"
            ) from err


class GaussianProductEstimator:
    """Gaussian state fused with each measurement by the product of Gaussians (Kim et al. 2019 §III.2).

    Starting from (prior_mean, prior_var), a measurement z with variance ``meas_var`` gives
    ``var' = 1/(1/var + 1/meas_var)`` and ``mean' = var'·(mean/var + z/meas_var)``.

    Args:
        prior_mean: Initial mean (the benchmark uses the function's mean μ̃).
        prior_var: Initial variance (> 0; the benchmark uses σ̃²).
        meas_var: Variance of every measurement (> 0).

    Raises:
        ConfigError: A non-finite argument or a non-positive variance.
    """

    def __init__(self, prior_mean: float, prior_var: float, meas_var: float) -> None:
        _check_gaussian_args("GaussianProductEstimator", prior_mean=prior_mean, prior_var=prior_var,
                             meas_var=meas_var)
        self._mean = float(prior_mean)
        self._var = float(prior_var)
        self._prior = (self._mean, self._var)
        self._meas_var = float(meas_var)
        self._n_updates = 0
        self._last_t_s: float | None = None

    @property
    def mean(self) -> float:
        """Current mean of the state."""
        return self._mean

    @property
    def var(self) -> float:
        """Current variance of the state."""
        return self._var

    @property
    def n_updates(self) -> int:
        """Number of measurements fused."""
        return self._n_updates

    @property
    def last_t(self) -> float | None:
        """Time of the last accepted measurement, or None."""
        return self._last_t_s

    def data_only(self) -> tuple[float, float]:
        """The measurements' information without the prior (for the GP): (mean, variance).

        The posterior divided by the prior (μ̃, σ̃²) (:func:`divide_gaussian`): after n
        measurements, (mean of the z, meas_var/n). Before any measurement the data carry no
        information: (μ̃, 1e6·σ̃²).
        """
        return divide_gaussian(self._mean, self._var, *self._prior)

    def update(self, t_s: float, value: float) -> tuple[float, float]:
        """Fuse one measurement.

        Args:
            t_s: Measurement time; only checked (finite, ≥ 0, strictly increasing).
            value: The measurement z (any finite number).

        Returns:
            (mean, variance) after fusing.

        Raises:
            MeasurementError: Bad time or non-finite value; the state is left unchanged.
        """
        t, z = _check_measurement(t_s, value, self._last_t_s)
        var = 1.0 / (1.0 / self._var + 1.0 / self._meas_var)
        self._mean = var * (self._mean / self._var + z / self._meas_var)
        self._var = var
        self._n_updates += 1
        self._last_t_s = t
        return self._mean, self._var


class MeasurementNoisePool:
    """One measurement variance shared by the estimators of one run, learnt from their data.

    Kim et al. 2019 §III.2 gives every measurement the variance σ_z² the study assumes. When that
    assumption is wrong (the study's ``assumed`` reading, or a person whose breaths are noisier
    than expected), every estimate's variance is off by the same factor, and the stopping rule
    trusts (or distrusts) single measurements accordingly. Here σ_z² is only the prior: a
    scaled-inverse-χ² with ``prior_dof`` pseudo-measurements (the form of the breath noise of
    :class:`~hilbo_core.estimation.TransitionEstimator`), updated with every setting's sum of
    squares about its own mean (n − 1 degrees of freedom for n measurements: the setting's true
    value is unknown, so the noise is measured around its mean). The settings of one run share
    the noise because they are one person on one instrument.

    The default weight is the weakest proper one, ν0 = 3 (the smallest with a finite Student-t
    variance below). The TransitionEstimator's ν0 = 10 belongs to a prior measured on real
    breaths (their median CV); an assumed σ_z² may be 10× off, and a run pools hundreds of
    measurements, so the prior only has to carry the first breaths. With ν0 = 10 a prior 10×
    too high still weighed 100 measurements' worth after exploration (measured: docs/results.md's
    git history, "Learning the measurement variance").

    The variance an estimate uses is the Student-t's, ``s²·ν/(ν − 2)`` with ν the degrees of
    freedom, so it describes the errors while ν is small (the same inflation as the
    TransitionEstimator's).

    Args:
        assumed_var: The assumed measurement variance σ_z² (> 0), the prior's scale.
        prior_dof: Its weight ν0 in pseudo-measurements (> 2, so the inflation is finite;
            default 3).

    Raises:
        ConfigError: A non-finite or out-of-range argument.
    """

    def __init__(self, assumed_var: float, prior_dof: float = 3.0) -> None:
        for name, value, low in (("assumed_var", assumed_var, 0.0), ("prior_dof", prior_dof, 2.0)):
            v = float(value)
            if not (math.isfinite(v) and v > low):
                raise ConfigError(f"MeasurementNoisePool {name}={value!r} must be a finite number > {low:g}")
        self._prior_ss = float(prior_dof) * float(assumed_var)
        self._prior_dof = float(prior_dof)
        self._ss = 0.0
        self._dof = 0

    @property
    def dof(self) -> float:
        """ν: prior pseudo-measurements plus the measured degrees of freedom."""
        return self._prior_dof + self._dof

    @property
    def scale_var(self) -> float:
        """s², the posterior scale of the measurement variance."""
        return (self._prior_ss + self._ss) / self.dof

    @property
    def meas_var(self) -> float:
        """The variance one measurement is fused with: s²·ν/(ν − 2)."""
        nu = self.dof
        return self.scale_var * nu / (nu - 2.0)

    def add(self, sum_squares: float, dof: int) -> None:
        """Add a setting's new sum of squares about its mean and its new degrees of freedom."""
        self._ss += max(float(sum_squares), 0.0)  # round-off can make a Welford step -1e-17
        self._dof += int(dof)


class PooledNoiseEstimator:
    """:class:`GaussianProductEstimator` whose measurement variance is a :class:`MeasurementNoisePool`'s.

    After n measurements with mean z̄ and the pool's variance v: ``var = 1/(1/prior_var + n/v)``
    and ``mean = var·(prior_mean/prior_var + n·z̄/v)``, recomputed from (n, z̄) whenever read, so
    every estimate of the run uses the variance learnt so far. Each measurement also adds its
    part of the setting's sum of squares to the pool (Welford's update).

    Args:
        prior_mean: Initial mean (the benchmark uses the function's mean μ̃).
        prior_var: Initial variance (> 0; the benchmark uses σ̃²).
        pool: The run's shared measurement variance.

    Raises:
        ConfigError: A non-finite prior or a non-positive prior variance.
    """

    def __init__(self, prior_mean: float, prior_var: float, pool: MeasurementNoisePool) -> None:
        _check_gaussian_args("PooledNoiseEstimator", prior_mean=prior_mean, prior_var=prior_var)
        self._prior = (float(prior_mean), float(prior_var))
        self._pool = pool
        self._n = 0
        self._zbar = 0.0
        self._last_t_s: float | None = None

    def _state(self) -> tuple[float, float]:
        m0, v0 = self._prior
        if self._n == 0:
            return m0, v0
        v = self._pool.meas_var
        var = 1.0 / (1.0 / v0 + self._n / v)
        return var * (m0 / v0 + self._n * self._zbar / v), var

    @property
    def mean(self) -> float:
        """Current mean of the state."""
        return self._state()[0]

    @property
    def var(self) -> float:
        """Current variance of the state."""
        return self._state()[1]

    @property
    def n_updates(self) -> int:
        """Number of measurements fused."""
        return self._n

    @property
    def last_t(self) -> float | None:
        """Time of the last accepted measurement, or None."""
        return self._last_t_s

    def data_only(self) -> tuple[float, float]:
        """The measurements' information without the prior (for the GP): (mean, variance).

        After n measurements, (z̄, v/n) with the pool's current v; before any, (μ̃, 1e6·σ̃²)
        (:func:`divide_gaussian`).
        """
        return divide_gaussian(*self._state(), *self._prior)

    def update(self, t_s: float, value: float) -> tuple[float, float]:
        """Fuse one measurement (and add it to the pool).

        Args:
            t_s: Measurement time; only checked (finite, ≥ 0, strictly increasing).
            value: The measurement z (any finite number).

        Returns:
            (mean, variance) after fusing.

        Raises:
            MeasurementError: Bad time or non-finite value; the state is left unchanged.
        """
        t, z = _check_measurement(t_s, value, self._last_t_s)
        self._n += 1
        delta = z - self._zbar
        self._zbar += delta / self._n
        # Welford: the setting's sum of squares about its mean grows by delta·(z − new mean).
        self._pool.add(delta * (z - self._zbar), 1 if self._n >= 2 else 0)
        self._last_t_s = t
        return self._state()
