"""Gaussian-process regression with per-observation noise for HIL Bayesian optimisation.

The surrogate of Kim et al. 2019 §II.B: a GP on standardised targets with an ARD
squared-exponential or Matérn-5/2 kernel and a constant prior mean, zero (the targets' average)
as Kim et al.'s or ``prior_mean_sd`` standard deviations above it (:meth:`GaussianProcess.fit`).
Unlike Kim et al. 2019's single σ_n², every observation carries its own noise variance (an
early-stopped estimate is noisier than a full one, a fast-prior point of Antonova 2016 noisier
still), and a learned homoscedastic term is added on top:

    K_y = K(X, X) + diag(noise_var_i / std_y²) + σ_n² I.

Hyperparameters are fitted by maximising the log marginal likelihood plus weak log-normal priors
(multi-start L-BFGS-B on log-parameters with analytic gradients, Rasmussen & Williams §5.4.1), so
that 6–10 points do not produce absurd length-scales. Posterior mean and variance follow
Rasmussen & Williams eq. 2.25–2.26 (Algorithm 2.1, Cholesky based).

Inputs live in the unit cube [0, 1]^d (the parameter space normalises them). A ``feature_map``
hook applies φ(x) before the kernel, k(φ(x_i), φ(x_j)), for the feature kernels of Antonova 2016
§3.4.2.
"""

from __future__ import annotations

import enum
import logging
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.linalg import cho_solve, solve_triangular
from scipy.linalg.lapack import dpotrf, dpotri, dpotrs
from scipy.optimize import minimize
from scipy.spatial.distance import cdist

from hilbo_core.errors import ConfigError, EstimatorError, MeasurementError, OptimizerStateError

__all__ = [
    "GPHyperparameters",
    "GaussianProcess",
    "KernelKind",
    "LogNormalPrior",
    "kernel_matrix",
    "log_marginal_likelihood",
    "matern52_kernel",
    "se_kernel",
]

_log = logging.getLogger(__name__)

FeatureMap = Callable[[np.ndarray], np.ndarray]

_SQRT5 = math.sqrt(5.0)
_LOG_2PI = math.log(2.0 * math.pi)
# Posterior variances (standardised units) are clipped here so std = sqrt(var) stays > 0.
_VAR_FLOOR = 1e-12
# Jitter ladder for the Cholesky factorisation, relative to the mean of the diagonal.
_JITTERS = (0.0, 1e-10, 1e-9, 1e-8, 1e-7, 1e-6, 1e-5, 1e-4)
# Returned by the MLL objective where K_y cannot be factorised; L-BFGS-B then backtracks.
_BAD_OBJECTIVE = 1e25
# Tolerance on the unit-cube check of the training inputs.
_CUBE_TOL = 1e-9


class KernelKind(enum.Enum):
    """Stationary ARD covariance kernels."""

    SE = "se"
    MATERN52 = "matern52"


# --------------------------------------------------------------------------------------------
# Kernels
# --------------------------------------------------------------------------------------------


def _check_kernel_args(
    X1: np.ndarray, X2: np.ndarray, lengthscales: np.ndarray, signal_var: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    X1 = np.asarray(X1, dtype=float)
    X2 = np.asarray(X2, dtype=float)
    ls = np.asarray(lengthscales, dtype=float).reshape(-1)
    if X1.ndim != 2 or X2.ndim != 2 or X1.shape[1] != X2.shape[1] or X1.shape[1] != ls.size:
        raise ConfigError(
            f"kernel inputs must be (n, d) and (m, d) with d = len(lengthscales) = {ls.size}; "
            f"got {X1.shape} and {X2.shape}"
        )
    if not (np.all(np.isfinite(ls)) and np.all(ls > 0.0)):
        raise ConfigError(f"lengthscales must be finite and > 0, got {ls.tolist()}")
    if not (math.isfinite(signal_var) and signal_var > 0.0):
        raise ConfigError(f"signal_var must be finite and > 0, got {signal_var!r}")
    return X1, X2, ls


def _scaled_sqdist(X1: np.ndarray, X2: np.ndarray, ls: np.ndarray) -> np.ndarray:
    # cdist computes each pair from the coordinate differences, so r²(x, x) is exactly 0 and the
    # matrix of X with itself is exactly symmetric (no a² + b² − 2ab cancellation).
    return cdist(X1 / ls, X2 / ls, "sqeuclidean")


def _matern52_from_r2(r2: np.ndarray, signal_var: float) -> np.ndarray:
    # σ²(1 + √5 r + 5r²/3)·e^{−√5 r}, the same operations in the same order as the one-line
    # expression (bit for bit), but in place: for the (1024 candidates × n) block of every EI
    # maximisation the fresh temporaries (each one a new, page-faulting multi-MB allocation)
    # cost more than sqrt and exp themselves (measured 8.0 → 4.8 ms at n = 600).
    r = np.sqrt(r2)
    e = np.multiply(r, -_SQRT5)
    np.exp(e, out=e)
    poly = np.multiply(r, _SQRT5, out=r)
    poly += 1.0
    poly += np.multiply(r2, 5.0 / 3.0)
    poly *= signal_var
    poly *= e
    return poly


def se_kernel(
    X1: np.ndarray, X2: np.ndarray, lengthscales: np.ndarray, signal_var: float
) -> np.ndarray:
    """ARD squared-exponential kernel of Kim et al. 2019 §II.B.

    k(x, x') = σ_f² · exp(−½ Σ_k (x_k − x'_k)² / l_k²).

    Args:
        X1: Inputs, shape (n, d).
        X2: Inputs, shape (m, d).
        lengthscales: Length-scales l_k > 0, shape (d,), in input units.
        signal_var: Signal variance σ_f² > 0.

    Returns:
        Covariance matrix, shape (n, m).
    """
    X1, X2, ls = _check_kernel_args(X1, X2, lengthscales, signal_var)
    return signal_var * np.exp(-0.5 * _scaled_sqdist(X1, X2, ls))


def matern52_kernel(
    X1: np.ndarray, X2: np.ndarray, lengthscales: np.ndarray, signal_var: float
) -> np.ndarray:
    """ARD Matérn-5/2 kernel (Rasmussen & Williams eq. 4.17 with ARD distance).

    k(x, x') = σ_f² · (1 + √5 r + 5r²/3) · exp(−√5 r),  r² = Σ_k (x_k − x'_k)² / l_k².

    Args:
        X1: Inputs, shape (n, d).
        X2: Inputs, shape (m, d).
        lengthscales: Length-scales l_k > 0, shape (d,), in input units.
        signal_var: Signal variance σ_f² > 0.

    Returns:
        Covariance matrix, shape (n, m).
    """
    X1, X2, ls = _check_kernel_args(X1, X2, lengthscales, signal_var)
    return _matern52_from_r2(_scaled_sqdist(X1, X2, ls), signal_var)


def kernel_matrix(
    kind: KernelKind,
    X1: np.ndarray,
    X2: np.ndarray,
    lengthscales: np.ndarray,
    signal_var: float,
) -> np.ndarray:
    """Dispatch to :func:`se_kernel` or :func:`matern52_kernel`; shapes as there."""
    if kind is KernelKind.SE:
        return se_kernel(X1, X2, lengthscales, signal_var)
    if kind is KernelKind.MATERN52:
        return matern52_kernel(X1, X2, lengthscales, signal_var)
    raise ConfigError(f"unknown kernel {kind!r}; expected a KernelKind")


def _dk_dr2(kind: KernelKind, r2: np.ndarray, K: np.ndarray, signal_var: float) -> np.ndarray:
    """∂k/∂(r²) elementwise, used by the length-scale and input gradients."""
    if kind is KernelKind.SE:
        return -0.5 * K
    r = np.sqrt(r2)
    # d/d(r²) of σ²(1 + √5 r + 5r²/3)e^{−√5 r} = −(5/6)σ²(1 + √5 r)e^{−√5 r}; finite at r = 0.
    return -(5.0 / 6.0) * signal_var * (1.0 + _SQRT5 * r) * np.exp(-_SQRT5 * r)


# --------------------------------------------------------------------------------------------
# Hyperparameters and priors
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class GPHyperparameters:
    """Kernel and noise hyperparameters of a :class:`GaussianProcess`.

    Attributes:
        lengthscales: ARD length-scales, one per (feature) dimension, in unit-cube units.
        signal_var: Signal variance σ_f² of the standardised targets (dimensionless).
        noise_var: Learned homoscedastic noise variance σ_n², in standardised-y units; it is added
            to the per-observation variances given to :meth:`GaussianProcess.fit`.
    """

    lengthscales: tuple[float, ...]
    signal_var: float
    noise_var: float

    def __post_init__(self) -> None:
        try:
            ls = tuple(float(v) for v in np.asarray(self.lengthscales, dtype=float).reshape(-1))
        except (TypeError, ValueError) as err:
            raise ConfigError(
                f"lengthscales must be a sequence of numbers, got {self.lengthscales!r}"
            ) from err
        object.__setattr__(self, "lengthscales", ls)
        if not ls or not all(math.isfinite(v) and v > 0.0 for v in ls):
            raise ConfigError(f"lengthscales must be non-empty, finite and > 0, got {list(ls)}")
        for name in ("signal_var", "noise_var"):
            value = getattr(self, name)
            try:
                value = float(value)
            except (TypeError, ValueError) as err:
                raise ConfigError(f"{name} must be a number, got {value!r}") from err
            if not (math.isfinite(value) and value > 0.0):
                raise ConfigError(f"{name} must be finite and > 0, got {value!r}")
            object.__setattr__(self, name, value)

    @property
    def dim(self) -> int:
        """Number of length-scales (input or feature dimension)."""
        return len(self.lengthscales)

    def to_log_params(self) -> np.ndarray:
        """[log l_1, …, log l_d, log σ_f², log σ_n²], shape (d + 2,)."""
        return np.log(np.array([*self.lengthscales, self.signal_var, self.noise_var]))

    @classmethod
    def from_log_params(cls, theta: np.ndarray) -> GPHyperparameters:
        """Inverse of :meth:`to_log_params`."""
        p = np.exp(np.asarray(theta, dtype=float))
        return cls(tuple(p[:-2]), float(p[-2]), float(p[-1]))

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dict ``{"lengthscales": [...], "signal_var": ..., "noise_var": ...}``."""
        return {
            "lengthscales": list(self.lengthscales),
            "signal_var": self.signal_var,
            "noise_var": self.noise_var,
        }

    @classmethod
    def from_dict(cls, data: Mapping[str, Any]) -> GPHyperparameters:
        """Rebuild from :meth:`to_dict` output; missing keys raise :class:`ConfigError`."""
        missing = {"lengthscales", "signal_var", "noise_var"} - set(data)
        if missing:
            raise ConfigError(f"GP hyperparameters dict lacks keys {sorted(missing)}")
        return cls(tuple(data["lengthscales"]), data["signal_var"], data["noise_var"])


@dataclass(frozen=True, slots=True)
class LogNormalPrior:
    """Log-normal prior on a positive hyperparameter: log p ~ N(log median, log_sd²).

    Attributes:
        median: Median of the prior (same units as the hyperparameter), > 0.
        log_sd: Standard deviation of the log of the hyperparameter, > 0.
    """

    median: float
    log_sd: float

    def __post_init__(self) -> None:
        if not (math.isfinite(self.median) and self.median > 0.0):
            raise ConfigError(f"prior median must be finite and > 0, got {self.median!r}")
        if not (math.isfinite(self.log_sd) and self.log_sd > 0.0):
            raise ConfigError(f"prior log_sd must be finite and > 0, got {self.log_sd!r}")


_SIGNAL_PRIOR = LogNormalPrior(median=1.0, log_sd=1.0)
_NOISE_PRIOR = LogNormalPrior(median=1e-2, log_sd=2.0)


def _default_lengthscale_prior(dim: int) -> LogNormalPrior:
    # Typical distances between points of the unit cube grow like √d, so a fixed median would
    # make higher-dimensional models needlessly wiggly (cf. the dimension-scaled priors of
    # Hvarfner et al., 2024). √d/4: 0.25 in 1-D, 0.61 in 6-D.
    return LogNormalPrior(median=0.25 * math.sqrt(dim), log_sd=1.0)


# --------------------------------------------------------------------------------------------
# Marginal likelihood
# --------------------------------------------------------------------------------------------


def _cholesky(K: np.ndarray) -> np.ndarray | None:
    """Lower Cholesky factor of K with escalating diagonal jitter; None if every rung fails."""
    scale = float(np.mean(np.diag(K)))
    if not math.isfinite(scale) or scale <= 0.0:
        return None
    for jitter in _JITTERS:
        Kj = K
        if jitter:
            Kj = K.copy()
            Kj[np.diag_indices_from(Kj)] += jitter * scale
        L, info = dpotrf(Kj, lower=1, clean=1, overwrite_a=0)
        if info == 0:
            return L
    return None


def _sq_diffs(X: np.ndarray) -> np.ndarray:
    """Per-dimension squared differences (x_ik − x_jk)², shape (n, n, d)."""
    return (X[:, None, :] - X[None, :, :]) ** 2


def _mll_terms(
    sq_diffs: np.ndarray,
    y: np.ndarray,
    extra_noise: np.ndarray,
    theta: np.ndarray,
    kind: KernelKind,
    want_grad: bool,
) -> tuple[float, np.ndarray] | None:
    """Log marginal likelihood and gradient w.r.t. θ; None where K_y is not factorisable.

    ``sq_diffs`` is :func:`_sq_diffs` of the kernel inputs, computed once per fit;
    ``extra_noise`` the known observation noise: variances (n,) or a covariance matrix (n, n).
    """
    n, _, d = sq_diffs.shape
    inv_ls2 = np.exp(-2.0 * theta[:d])
    signal_var = math.exp(theta[d])
    noise_var = math.exp(theta[d + 1])
    r2 = sq_diffs @ inv_ls2  # ARD r² = Σ_k D_k,  D_k = (x_ik − x_jk)² / l_k²
    if kind is KernelKind.SE:
        Kf = signal_var * np.exp(-0.5 * r2)
    else:
        Kf = _matern52_from_r2(r2, signal_var)
    Ky = _add_noise(Kf.copy(), extra_noise, noise_var)
    L = _cholesky(Ky)
    if L is None:
        return None
    alpha = cho_solve((L, True), y, check_finite=False)
    # R&W eq. 5.8: log p(y|X,θ) = −½ yᵀα − Σ log L_ii − n/2 log 2π.
    mll = -0.5 * float(y @ alpha) - float(np.sum(np.log(np.diag(L)))) - 0.5 * n * _LOG_2PI
    if not want_grad:
        return mll, np.empty(0)
    # R&W eq. 5.9: ∂/∂θ_j = ½ tr((ααᵀ − K_y⁻¹) ∂K_y/∂θ_j); both factors are symmetric, so the
    # trace is the sum of the elementwise product.
    K_inv, info = dpotri(L, lower=1)
    if info != 0:
        return None
    K_inv = np.tril(K_inv) + np.tril(K_inv, -1).T  # dpotri fills only the lower triangle
    W = np.outer(alpha, alpha) - K_inv
    # ∂k/∂log l_k = ∂k/∂r² · ∂r²/∂log l_k = ∂k/∂r² · (−2 D_k).
    G = -2.0 * _dk_dr2(kind, r2, Kf, signal_var)
    grad = np.empty(d + 2)
    grad[:d] = 0.5 * ((W * G).reshape(-1) @ sq_diffs.reshape(n * n, d)) * inv_ls2
    grad[d] = 0.5 * float(np.sum(W * Kf))
    grad[d + 1] = 0.5 * noise_var * float(np.trace(W))
    return mll, grad


def _neg_log_posterior(
    theta: np.ndarray,
    sq_diffs: np.ndarray,
    y: np.ndarray,
    extra_noise: np.ndarray,
    kind: KernelKind,
    prior_mu: np.ndarray,
    prior_sd: np.ndarray,
) -> tuple[float, np.ndarray]:
    """−(log marginal likelihood + log-normal log priors) and its gradient, for L-BFGS-B."""
    out = _mll_terms(sq_diffs, y, extra_noise, theta, kind, True)
    if out is None:
        return _BAD_OBJECTIVE, np.zeros_like(theta)
    value, grad = out
    # A log-normal prior on p is a normal prior on θ = log p (no Jacobian term needed).
    zp = (theta - prior_mu) / prior_sd
    return -(value - 0.5 * float(zp @ zp)), -(grad - zp / prior_sd)


def log_marginal_likelihood(
    X: np.ndarray,
    y: np.ndarray,
    noise_var: np.ndarray | None,
    hyperparameters: GPHyperparameters,
    kernel: KernelKind = KernelKind.MATERN52,
    *,
    return_grad: bool = False,
    noise_corr: np.ndarray | None = None,
) -> float | tuple[float, np.ndarray]:
    """Log marginal likelihood of a zero-mean GP, R&W eq. 5.8, with per-observation noise.

    The data are used as given (no standardisation): K_y = K(X, X) + Σ + hyperparameters.noise_var
    · I, with Σ = diag(noise_var), or S·noise_corr·S (S = diag(√noise_var)) when errors are
    correlated.

    Args:
        X: Kernel inputs, shape (n, d) with d = hyperparameters.dim.
        y: Targets, shape (n,).
        noise_var: Per-observation noise variances in the units of y², shape (n,), or None.
        hyperparameters: Kernel and homoscedastic-noise hyperparameters.
        kernel: Kernel kind.
        return_grad: Also return the gradient w.r.t. θ = [log l_1..d, log σ_f², log σ_n²].
        noise_corr: Correlation matrix of the observations' errors, shape (n, n), or None
            (independent errors); needs ``noise_var``.

    Returns:
        log p(y | X, θ), or (log p, gradient of shape (d + 2,)) when ``return_grad``.

    Raises:
        ConfigError: Inconsistent shapes.
        EstimatorError: K_y is not positive definite even with jitter.
    """
    X = np.asarray(X, dtype=float)
    y = np.asarray(y, dtype=float)
    if X.ndim != 2 or X.shape[1] != hyperparameters.dim or y.shape != (X.shape[0],):
        raise ConfigError(
            f"expected X (n, {hyperparameters.dim}) and y (n,), got {X.shape} and {y.shape}"
        )
    if noise_var is not None and np.shape(noise_var) != y.shape:
        raise ConfigError(f"noise_var must have shape {y.shape}, got {np.shape(noise_var)}")
    if noise_corr is not None:
        noise_corr = _check_corr(noise_corr, y.shape[0])
    extra = _known_noise(noise_var, noise_corr, y.shape[0])
    theta = hyperparameters.to_log_params()
    out = _mll_terms(_sq_diffs(X), y, extra, theta, kernel, return_grad)
    if out is None:
        raise EstimatorError(f"K_y is not positive definite for hyperparameters {hyperparameters}")
    return out if return_grad else out[0]


def _known_noise(noise_var: np.ndarray | None, noise_corr: np.ndarray | None, n: int,
                 scale: float = 1.0) -> np.ndarray:
    """The known observation noise divided by ``scale``: variances (n,) (zeros without
    ``noise_var``), or their covariance S·noise_corr·S (n, n), S = diag(√variances), with
    ``noise_corr`` checked by :func:`_check_corr`."""
    if noise_corr is None:
        return np.zeros(n) if noise_var is None else np.asarray(noise_var, dtype=float) / scale
    if noise_var is None:
        raise ConfigError("noise_corr needs noise_var (the errors' variances)")
    s = np.sqrt(np.asarray(noise_var, dtype=float) / scale)
    return noise_corr * np.outer(s, s)


def _add_noise(K: np.ndarray, extra: np.ndarray, noise_var: float) -> np.ndarray:
    """K + the known noise ``extra`` (variances (n,) or a covariance (n, n)) + noise_var·I, in
    place."""
    if extra.ndim == 2:
        K += extra
        K[np.diag_indices(K.shape[0])] += noise_var
    else:
        K[np.diag_indices(K.shape[0])] += extra + noise_var
    return K


def _check_corr(noise_corr: np.ndarray, n: int) -> np.ndarray:
    """``noise_corr`` as a float (n, n) correlation matrix, else ConfigError."""
    R = np.asarray(noise_corr, dtype=float)
    if R.shape != (n, n):
        raise ConfigError(f"noise_corr must have shape ({n}, {n}), got {R.shape}")
    if not np.isfinite(R).all() or not np.allclose(R, R.T) or np.any(np.abs(R) > 1.0 + 1e-12):
        raise ConfigError("noise_corr must be a finite symmetric matrix with entries in [-1, 1]")
    if not np.allclose(np.diag(R), 1.0):
        raise ConfigError("noise_corr must have a unit diagonal (it is a correlation matrix)")
    return R


# --------------------------------------------------------------------------------------------
# Gaussian process
# --------------------------------------------------------------------------------------------


def _check_bounds(name: str, bounds: tuple[float, float]) -> tuple[float, float]:
    try:
        lo, hi = (float(b) for b in bounds)
    except (TypeError, ValueError) as err:
        raise ConfigError(f"{name} must be a (low, high) pair, got {bounds!r}") from err
    if not (math.isfinite(lo) and math.isfinite(hi) and 0.0 < lo < hi):
        raise ConfigError(f"{name} must satisfy 0 < low < high (finite), got {bounds!r}")
    return lo, hi


@dataclass(frozen=True, slots=True)
class _Posterior:
    """Everything a fitted GP needs to predict (standardised units)."""

    X: np.ndarray  # (n, d) unit-cube inputs as given
    F: np.ndarray  # (n, k) kernel inputs φ(X)
    y: np.ndarray  # (n,) original units
    noise_var: np.ndarray | None  # (n,) original units
    noise_corr: np.ndarray | None  # (n, n) correlation of the errors, or None (independent)
    y_mean: float  # the prior mean, original units
    y_std: float
    hyper: GPHyperparameters
    L: np.ndarray  # (n, n) Cholesky factor of K_y
    alpha: np.ndarray  # (n,) K_y⁻¹ y_standardised
    # Cached per fit for the predictions (the EI maximisation predicts ~50 times per fit):
    ls: np.ndarray  # (k,) length-scales
    F_ls: np.ndarray  # (n, k) F / ls, exactly what _scaled_sqdist would compute each time


class GaussianProcess:
    """GP surrogate with per-observation noise; hyperparameters by maximum a-posteriori MLL.

    Args:
        kernel: Kernel kind (Matérn-5/2 by default; SE is Kim et al. 2019's choice).
        lengthscale_bounds: (low, high) of every length-scale, unit-cube units.
        signal_var_bounds: (low, high) of σ_f² of the standardised targets.
        noise_var_bounds: (low, high) of the learned σ_n², standardised-y units.
        n_restarts: Random L-BFGS-B starts drawn from the priors, in addition to ``init`` (or the
            prior medians when no ``init`` is given).
        feature_map: Optional φ: (n, d) → (n, k) applied to inputs before the kernel (Antonova 2016
            §3.4.2 feature kernels); length-scales then live in feature space.
        lengthscale_prior: Log-normal prior on each length-scale; None → median √k/4, log-sd 1.
        signal_var_prior: Log-normal prior on σ_f² (default median 1, log-sd 1).
        noise_var_prior: Log-normal prior on σ_n² (default median 0.01, log-sd 2).
    """

    def __init__(
        self,
        kernel: KernelKind = KernelKind.MATERN52,
        *,
        lengthscale_bounds: tuple[float, float] = (0.05, 5.0),
        signal_var_bounds: tuple[float, float] = (0.05, 20.0),
        noise_var_bounds: tuple[float, float] = (1e-6, 2.0),
        n_restarts: int = 2,
        feature_map: FeatureMap | None = None,
        lengthscale_prior: LogNormalPrior | None = None,
        signal_var_prior: LogNormalPrior = _SIGNAL_PRIOR,
        noise_var_prior: LogNormalPrior = _NOISE_PRIOR,
    ) -> None:
        if not isinstance(kernel, KernelKind):
            raise ConfigError(f"kernel must be a KernelKind, got {kernel!r}")
        if isinstance(n_restarts, bool) or not isinstance(n_restarts, int) or n_restarts < 0:
            raise ConfigError(f"n_restarts must be an int >= 0, got {n_restarts!r}")
        if feature_map is not None and not callable(feature_map):
            raise ConfigError(f"feature_map must be callable or None, got {feature_map!r}")
        self._kernel = kernel
        self._ls_bounds = _check_bounds("lengthscale_bounds", lengthscale_bounds)
        self._sv_bounds = _check_bounds("signal_var_bounds", signal_var_bounds)
        self._nv_bounds = _check_bounds("noise_var_bounds", noise_var_bounds)
        self._n_restarts = n_restarts
        self._feature_map = feature_map
        self._ls_prior = lengthscale_prior
        self._sv_prior = signal_var_prior
        self._nv_prior = noise_var_prior
        self._post: _Posterior | None = None

    # ---- properties --------------------------------------------------------------------------

    @property
    def kernel(self) -> KernelKind:
        """Kernel kind."""
        return self._kernel

    @property
    def is_fitted(self) -> bool:
        """True once :meth:`fit` has succeeded."""
        return self._post is not None

    def _posterior(self) -> _Posterior:
        if self._post is None:
            raise OptimizerStateError("GaussianProcess is not fitted; call fit(X, y, ...) first")
        return self._post

    @property
    def hyperparameters(self) -> GPHyperparameters:
        """Fitted hyperparameters."""
        return self._posterior().hyper

    @property
    def n_obs(self) -> int:
        """Number of training observations (0 before fit)."""
        return 0 if self._post is None else int(self._post.y.size)

    @property
    def X(self) -> np.ndarray:
        """Training inputs, shape (n, d) (a copy)."""
        return self._posterior().X.copy()

    @property
    def y(self) -> np.ndarray:
        """Training targets in original units, shape (n,) (a copy)."""
        return self._posterior().y.copy()

    @property
    def noise_var(self) -> np.ndarray | None:
        """Per-observation noise variances in original units, shape (n,), or None."""
        nv = self._posterior().noise_var
        return None if nv is None else nv.copy()

    @property
    def y_mean(self) -> float:
        """Mean subtracted from the targets: the constant prior mean (original units)."""
        return self._posterior().y_mean

    @property
    def y_std(self) -> float:
        """Scale the targets were divided by."""
        return self._posterior().y_std

    # ---- fitting -----------------------------------------------------------------------------

    def _features(self, X: np.ndarray, what: str) -> np.ndarray:
        if self._feature_map is None:
            return X
        F = np.asarray(self._feature_map(X), dtype=float)
        if F.ndim != 2 or F.shape[0] != X.shape[0]:
            raise ConfigError(
                f"feature_map must map {what} of shape {X.shape} to (n, k), got {F.shape}"
            )
        bad = np.flatnonzero(~np.all(np.isfinite(F), axis=1))
        if bad.size:
            raise ConfigError(f"feature_map returned non-finite features for {what} row {bad[0]}")
        return F

    def _validate(
        self, X: np.ndarray, y: np.ndarray, noise_var: np.ndarray | None
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        X = np.asarray(X, dtype=float)
        y = np.asarray(y, dtype=float)
        if X.ndim != 2 or X.shape[0] < 1 or X.shape[1] < 1:
            raise ConfigError(f"X must have shape (n, d) with n, d >= 1, got {X.shape}")
        if y.shape != (X.shape[0],):
            raise ConfigError(f"y must have shape ({X.shape[0]},) to match X, got {y.shape}")
        bad = np.flatnonzero(~np.all(np.isfinite(X), axis=1))
        if bad.size:
            raise ConfigError(f"X row {bad[0]} is not finite: {X[bad[0]].tolist()}")
        if self._feature_map is None:
            out = np.flatnonzero(np.any((X < -_CUBE_TOL) | (X > 1.0 + _CUBE_TOL), axis=1))
            if out.size:
                raise ConfigError(
                    f"X row {out[0]} = {X[out[0]].tolist()} is outside the unit cube [0, 1]^d; "
                    "normalise inputs with the parameter space first"
                )
        bad = np.flatnonzero(~np.isfinite(y))
        if bad.size:
            raise MeasurementError(f"y[{bad[0]}] = {y[bad[0]]!r} is not finite")
        if noise_var is not None:
            noise_var = np.asarray(noise_var, dtype=float)
            if noise_var.shape != y.shape:
                raise ConfigError(f"noise_var must have shape {y.shape}, got {noise_var.shape}")
            bad = np.flatnonzero(~(np.isfinite(noise_var) & (noise_var > 0.0)))
            if bad.size:
                raise MeasurementError(
                    f"noise_var[{bad[0]}] = {noise_var[bad[0]]!r}; expected a finite variance > 0"
                )
        return X, y, noise_var

    def _prior_for_ls(self, dim: int) -> LogNormalPrior:
        return self._ls_prior if self._ls_prior is not None else _default_lengthscale_prior(dim)

    def _log_bounds(self, dim: int) -> np.ndarray:
        return np.log(np.array([self._ls_bounds] * dim + [self._sv_bounds, self._nv_bounds]))

    def _clip_to_bounds(self, theta: np.ndarray, dim: int) -> np.ndarray:
        lb = self._log_bounds(dim)
        return np.clip(theta, lb[:, 0], lb[:, 1])

    def _default_hyperparameters(self, dim: int) -> GPHyperparameters:
        """Prior medians clipped into the bounds."""
        theta = np.log(
            np.array(
                [self._prior_for_ls(dim).median] * dim
                + [self._sv_prior.median, self._nv_prior.median]
            )
        )
        return GPHyperparameters.from_log_params(self._clip_to_bounds(theta, dim))

    def fit(
        self,
        X: np.ndarray,
        y: np.ndarray,
        noise_var: np.ndarray | None = None,
        *,
        rng: np.random.Generator,
        init: GPHyperparameters | None = None,
        optimize: bool = True,
        noise_corr: np.ndarray | None = None,
        prior_mean_sd: float = 0.0,
    ) -> GaussianProcess:
        """Condition on data and (optionally) fit hyperparameters by MAP marginal likelihood.

        Targets are standardised (y − m)/std, m = mean(y) + prior_mean_sd·std the constant prior
        mean. With one observation or constant targets std is replaced by √mean(noise_var) (or 1
        without noise variances) so the model stays usable.

        Args:
            X: Inputs in the unit cube, shape (n, d).
            y: Observed costs in original units (e.g. W), shape (n,).
            noise_var: Per-observation noise variance of each y in original units² (e.g. the
                estimator's σ² of an early-stopped or fast-prior point), shape (n,), all > 0; or
                None for only the learned homoscedastic term.
            rng: Source of the random restarts.
            init: Warm start (e.g. the previous fit's hyperparameters); with ``optimize=False``
                these are used as they are.
            optimize: False to skip the likelihood optimisation (fixed hyperparameters: ``init``
                or, without it, the prior medians).
            noise_corr: Correlation matrix of the observations' errors, shape (n, n), unit
                diagonal; None (default) for independent errors. With it the errors' covariance
                is S·noise_corr·S, S = diag(√noise_var) (e.g. a drift shared by settings measured
                close in time), and :meth:`predict` is still the latent f, without it.
            prior_mean_sd: The constant prior mean, in standard deviations of the targets above
                their average (0, the default: at the average, Kim et al. 2019's zero-mean GP on
                standardised targets). Far from every observation the posterior mean returns to
                it, so a positive value says that an unmeasured input is expected to be worse
                than the average of the measured ones (see ``OptimizerConfig.prior_mean_sd``).

        Returns:
            self.

        Raises:
            ConfigError: Bad shapes, non-finite or out-of-cube X, ``init`` of the wrong
                dimension, a ``prior_mean_sd`` that is not a finite number.
            MeasurementError: Non-finite y or non-positive/non-finite noise variances.
            EstimatorError: No hyperparameters give a positive-definite K_y.
        """
        X, y, noise_var = self._validate(X, y, noise_var)
        if (isinstance(prior_mean_sd, bool) or not isinstance(prior_mean_sd, int | float | np.floating)
                or not math.isfinite(prior_mean_sd)):
            raise ConfigError(f"prior_mean_sd={prior_mean_sd!r}; expected a finite number of SDs")
        if noise_corr is not None:
            if noise_var is None:
                raise ConfigError("noise_corr needs noise_var (the errors' variances)")
            noise_corr = _check_corr(noise_corr, y.shape[0])
        F = self._features(X, "X")
        n, dim = F.shape
        if init is not None and init.dim != dim:
            raise ConfigError(
                f"init has {init.dim} length-scales but the kernel inputs have {dim} dimensions"
            )

        y_mean = float(np.mean(y))
        y_std = float(np.std(y)) if n > 1 else 0.0
        if not y_std > 1e-12 * max(1.0, abs(y_mean)):
            # One point or constant targets: fall back to the measurement noise as the scale.
            y_std = math.sqrt(float(np.mean(noise_var))) if noise_var is not None else 1.0
        # The prior mean: the posterior is y_mean + y_std·(GP posterior of ys), and far from the
        # data that GP posterior is 0.
        y_mean += float(prior_mean_sd) * y_std
        ys = (y - y_mean) / y_std
        extra = _known_noise(noise_var, noise_corr, n, y_std**2)

        if init is None:
            theta0 = self._default_hyperparameters(dim).to_log_params()
        else:
            theta0 = self._clip_to_bounds(init.to_log_params(), dim)

        if optimize:
            hyper = GPHyperparameters.from_log_params(self._optimize(theta0, F, ys, extra, rng))
        else:
            hyper = init if init is not None else GPHyperparameters.from_log_params(theta0)

        ls = np.asarray(hyper.lengthscales)
        Ky = _add_noise(kernel_matrix(self._kernel, F, F, ls, hyper.signal_var), extra,
                        hyper.noise_var)
        L = _cholesky(Ky)
        if L is None:
            raise EstimatorError(
                f"K_y of {n} observations is not positive definite for {hyper} even with jitter"
            )
        alpha = cho_solve((L, True), ys, check_finite=False)
        self._post = _Posterior(
            X=X.copy(),
            F=F,
            y=y.copy(),
            noise_var=None if noise_var is None else noise_var.copy(),
            noise_corr=None if noise_corr is None else noise_corr.copy(),
            y_mean=y_mean,
            y_std=y_std,
            hyper=hyper,
            L=L,
            alpha=alpha,
            ls=ls,
            F_ls=F / ls,
        )
        return self

    def _optimize(
        self,
        theta0: np.ndarray,
        F: np.ndarray,
        ys: np.ndarray,
        extra: np.ndarray,
        rng: np.random.Generator,
    ) -> np.ndarray:
        dim = F.shape[1]
        log_bounds = self._log_bounds(dim)
        priors = [self._prior_for_ls(dim)] * dim + [self._sv_prior, self._nv_prior]
        mu = np.array([math.log(p.median) for p in priors])
        sd = np.array([p.log_sd for p in priors])
        starts = [theta0]
        for _ in range(self._n_restarts):
            starts.append(np.clip(rng.normal(mu, sd), log_bounds[:, 0], log_bounds[:, 1]))

        best_theta: np.ndarray | None = None
        best_value = math.inf
        sq_diffs = _sq_diffs(F)
        for start in starts:
            res = minimize(
                _neg_log_posterior,
                start,
                args=(sq_diffs, ys, extra, self._kernel, mu, sd),
                jac=True,
                method="L-BFGS-B",
                bounds=log_bounds,
                options={"maxiter": 200},
            )
            value = float(res.fun)
            if math.isfinite(value) and value < _BAD_OBJECTIVE and value < best_value:
                best_value, best_theta = value, np.asarray(res.x, dtype=float)
        if best_theta is None:
            raise EstimatorError(
                f"marginal-likelihood optimisation failed from all {len(starts)} starts "
                f"(n = {F.shape[0]}, d = {dim}): K_y never positive definite"
            )
        _log.debug("GP fit: -log posterior %.4g at theta %s", best_value, best_theta)
        return best_theta

    # ---- prediction --------------------------------------------------------------------------

    def _check_query(self, Xs: np.ndarray, post: _Posterior) -> np.ndarray:
        Xs = np.asarray(Xs, dtype=float)
        if Xs.ndim != 2 or Xs.shape[1] != post.X.shape[1]:
            raise ConfigError(f"Xs must have shape (m, {post.X.shape[1]}), got {Xs.shape}")
        if not np.isfinite(Xs).all():  # one reduction in the common case; find the row only if bad
            bad = np.flatnonzero(~np.all(np.isfinite(Xs), axis=1))
            raise ConfigError(f"Xs row {bad[0]} is not finite: {Xs[bad[0]].tolist()}")
        return Xs

    def _cross_kernel(self, Fs: np.ndarray, post: _Posterior, r2: np.ndarray | None = None) -> np.ndarray:
        """k(Fs, F) with the fitted hyperparameters, shape (m, n): :func:`kernel_matrix` bit for
        bit, without re-validating the fitted hyperparameters and re-scaling F at every call."""
        if r2 is None:
            r2 = cdist(Fs / post.ls, post.F_ls, "sqeuclidean")
        if self._kernel is KernelKind.SE:
            return post.hyper.signal_var * np.exp(-0.5 * r2)
        return _matern52_from_r2(r2, post.hyper.signal_var)

    def predict(self, Xs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Posterior of the latent f (R&W eq. 2.25–2.26) in original y units.

        Args:
            Xs: Query points in the unit cube, shape (m, d).

        Returns:
            (mean (m,), var (m,)); var excludes observation noise and is clipped at a tiny
            positive floor so that √var is always > 0.
        """
        post = self._posterior()
        Xs = self._check_query(Xs, post)
        Ks = self._cross_kernel(self._features(Xs, "Xs"), post)
        hp = post.hyper
        mean = Ks @ post.alpha
        v = solve_triangular(post.L, Ks.T, lower=True, check_finite=False)
        var = np.maximum(hp.signal_var - np.einsum("ij,ij->j", v, v), _VAR_FLOOR)
        return post.y_mean + post.y_std * mean, post.y_std**2 * var

    def predict_mean(self, Xs: np.ndarray) -> np.ndarray:
        """Posterior mean of the latent f only (R&W eq. 2.25) in original y units.

        The mean of :meth:`predict`, bit for bit, without its variance: that triangular solve
        costs O(n²m), which for m = n (the GP's estimated minimum among its own n training
        points, HILOptimizer's incumbent) is a second O(n³) step after the fit.

        Args:
            Xs: Query points in the unit cube, shape (m, d).

        Returns:
            Mean, shape (m,).
        """
        post = self._posterior()
        Xs = self._check_query(Xs, post)
        Ks = self._cross_kernel(self._features(Xs, "Xs"), post)
        return post.y_mean + post.y_std * (Ks @ post.alpha)

    def predict_cov(self, Xa: np.ndarray, Xb: np.ndarray) -> np.ndarray:
        """Posterior covariance of the latent f between two sets of points (R&W eq. 2.24):
        k(a, b) − k(a, X) K_y⁻¹ k(X, b), in original y units².

        Args:
            Xa: Query points in the unit cube, shape (m_a, d).
            Xb: Query points in the unit cube, shape (m_b, d).

        Returns:
            Covariance, shape (m_a, m_b).
        """
        post = self._posterior()
        Xa, Xb = self._check_query(Xa, post), self._check_query(Xb, post)
        Fa, Fb = self._features(Xa, "Xa"), self._features(Xb, "Xb")
        Va = solve_triangular(post.L, self._cross_kernel(Fa, post).T, lower=True, check_finite=False)
        Vb = solve_triangular(post.L, self._cross_kernel(Fb, post).T, lower=True, check_finite=False)
        hp = post.hyper
        Kab = kernel_matrix(self._kernel, Fa, Fb, post.ls, hp.signal_var)
        return post.y_std**2 * (Kab - Va.T @ Vb)

    def predict_error(self, cross_cov: np.ndarray) -> np.ndarray:
        """Posterior mean of errors correlated with the observations' errors (R&W eq. 2.25
        with the error's cross-covariance in place of k*): E[e* | y] = C* K_y⁻¹ (y − m), m the
        prior mean (:attr:`y_mean`).

        Args:
            cross_cov: Covariance of each new error with each observation's error in original
                y units², shape (m, n) (e.g. the drift now against the drift at each
                evaluation).

        Returns:
            The errors' posterior means in original y units, shape (m,).
        """
        post = self._posterior()
        C = np.asarray(cross_cov, dtype=float)
        if C.ndim != 2 or C.shape[1] != post.y.shape[0] or not np.isfinite(C).all():
            raise ConfigError(
                f"cross_cov must be finite with shape (m, {post.y.shape[0]}), got {C.shape}")
        return (C / post.y_std) @ post.alpha

    def predict_with_grad(
        self, Xs: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Posterior mean and variance with their input gradients (no feature map).

        Args:
            Xs: Query points in the unit cube, shape (m, d).

        Returns:
            (mean (m,), var (m,), dmean/dx (m, d), dvar/dx (m, d)) in original y units; the
            variance gradient is 0 where the variance sits at its floor.

        Raises:
            ConfigError: The GP has a feature map (its Jacobian is unknown).
        """
        if self._feature_map is not None:
            raise ConfigError("predict_with_grad needs feature_map=None (φ has no Jacobian)")
        post = self._posterior()
        Xs = self._check_query(Xs, post)
        hp = post.hyper
        ls = post.ls
        if Xs.shape[0] == 1:
            # SLSQP's one point per call: cdist's per-call checks cost more than the distances.
            # Σ_k (a_k − b_k)² accumulated over k in order, as cdist's C loop does (same bits;
            # numpy's sum() would switch to pairwise summation from 8 terms on).
            diff_ls = Xs / ls - post.F_ls  # (n, k)
            acc = diff_ls[:, 0] * diff_ls[:, 0]
            for k in range(1, diff_ls.shape[1]):
                acc += diff_ls[:, k] * diff_ls[:, k]
            r2 = acc[None, :]
        else:
            r2 = cdist(Xs / ls, post.F_ls, "sqeuclidean")
        sv = hp.signal_var
        if self._kernel is KernelKind.SE:
            Ks = sv * np.exp(-0.5 * r2)
            dk = -0.5 * Ks
        else:
            # _matern52_from_r2 and _dk_dr2 sharing r and e^{−√5 r} (same operations, same bits).
            r = np.sqrt(r2)
            e = np.exp(-_SQRT5 * r)
            sr = _SQRT5 * r
            Ks = sv * (1.0 + sr + (5.0 / 3.0) * r2) * e
            dk = -(5.0 / 6.0) * sv * (1.0 + sr) * e  # (m, n)
        mean = Ks @ post.alpha
        # K_y⁻¹ k*, (n, m): LAPACK's potrs as scipy's cho_solve calls it, minus its wrappers.
        B, info = dpotrs(post.L, Ks.T, lower=1)
        if info != 0:
            raise EstimatorError(f"internal: potrs failed with info={info}")
        var_raw = hp.signal_var - np.einsum("ij,ji->i", Ks, B)
        # ∂k(x, x_i)/∂x = ∂k/∂r² · 2 (x − x_i) / l².
        diff = (Xs[:, None, :] - post.F[None, :, :]) / (ls * ls)  # (m, n, d)
        dK = 2.0 * dk[:, :, None] * diff
        dmean = np.einsum("mnd,n->md", dK, post.alpha)
        dvar = -2.0 * np.einsum("mnd,nm->md", dK, B)
        floored = var_raw <= _VAR_FLOOR
        dvar[floored] = 0.0
        var = np.maximum(var_raw, _VAR_FLOOR)
        s = post.y_std
        return post.y_mean + s * mean, s * s * var, s * dmean, s * s * dvar

    def log_marginal_likelihood(
        self, hyperparameters: GPHyperparameters | None = None, *, return_grad: bool = False
    ) -> float | tuple[float, np.ndarray]:
        """Log marginal likelihood of the standardised training data (no priors).

        Args:
            hyperparameters: Where to evaluate it; default the fitted ones.
            return_grad: Also return the gradient w.r.t. the log-parameters.

        Returns:
            As :func:`log_marginal_likelihood` on ((y − y_mean)/y_std, noise_var/y_std²).
        """
        post = self._posterior()
        hp = post.hyper if hyperparameters is None else hyperparameters
        extra = None if post.noise_var is None else post.noise_var / post.y_std**2
        ys = (post.y - post.y_mean) / post.y_std
        return log_marginal_likelihood(
            post.F, ys, extra, hp, self._kernel, return_grad=return_grad,
            noise_corr=post.noise_corr,
        )
