"""Expected Improvement for minimisation (Kim et al. 2019 §II.B), computed stably, and its maximiser.

    EI(x) = σ̄(x) · (z Φ(z) + φ(z)),   z = (min(S) − μ̄(x) + ξ) / σ̄(x).

Far in the lower tail (z ≪ 0) the direct formula cancels to 0 or goes negative; here
h(z) = z Φ(z) + φ(z) is evaluated in log space: directly for z > −1, as
log φ(z) + log(1 + z·Φ(z)/φ(z)) with the Mills ratio Φ(z)/φ(z) = √(π/2)·erfcx(−z/√2) for
−40 ≤ z ≤ −1, and by the asymptotic series h(z) = φ(z)/z² · (1 − 3/z² + 15/z⁴ − …) below −40
(cf. Ament et al., "Unexpected improvements to expected improvement", NeurIPS 2023).

:func:`maximize_ei` evaluates log EI on many feasible candidates (the space's scrambled-Sobol set),
then refines the best few with SLSQP under the box and the linear constraints A u ≤ b;
:func:`minimize_lcb` finds the recommendation (lowest posterior mean + β·SD) the same way.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np
from scipy.optimize import minimize
from scipy.special import erfcx, log_ndtr, ndtr

from hilbo_core.errors import ConfigError, EstimatorError, InfeasibleError

__all__ = [
    "PredictFn",
    "PredictGradFn",
    "expected_improvement",
    "log_expected_improvement",
    "maximize_ei",
    "minimize_lcb",
]

_log = logging.getLogger(__name__)

PredictFn = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]
PredictGradFn = Callable[[np.ndarray], tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]]

_LOG_SQRT_2PI = 0.5 * math.log(2.0 * math.pi)
_SQRT_HALF_PI = math.sqrt(0.5 * math.pi)
_Z_DIRECT = -1.0  # above: direct formula (no cancellation)
_Z_SERIES = -40.0  # below: asymptotic series (Mills-ratio form loses ~log10(z²) digits)
# Asymptotic series of h(z)·z²/φ(z) for z → −∞: Σ_k (−1)^k (2k+1)!! / z^{2k}; truncation error
# below z = −40 is < 135135/40^12 ≈ 1e-14 (relative).
_SERIES = (1.0, -3.0, 15.0, -105.0, 945.0, -10395.0)
_FEAS_TOL = 1e-9


def _log_phi(z: np.ndarray) -> np.ndarray:
    return -0.5 * z * z - _LOG_SQRT_2PI


def _log_h(z: np.ndarray) -> np.ndarray:
    """log(z Φ(z) + φ(z)) for finite z, stable for z ≪ 0."""
    z = np.asarray(z, dtype=float)
    if z.size == 1:
        # The SLSQP objective's case (one point per call): the same ufuncs on the same
        # one-element array as the masked branches below, hence the same bits, without the
        # three boolean masks and fancy-index copies (a third of the objective's time).
        zf = float(z.reshape(-1)[0])
        if zf > _Z_DIRECT:
            return np.log(z * ndtr(z) + np.exp(_log_phi(z)))
        if zf >= _Z_SERIES:
            return _log_phi(z) + np.log1p(z * _SQRT_HALF_PI * erfcx(-z / math.sqrt(2.0)))
    out = np.empty_like(z)
    hi = z > _Z_DIRECT
    lo = z < _Z_SERIES
    mid = ~(hi | lo)
    zh = z[hi]
    out[hi] = np.log(zh * ndtr(zh) + np.exp(_log_phi(zh)))
    zm = z[mid]
    out[mid] = _log_phi(zm) + np.log1p(zm * _SQRT_HALF_PI * erfcx(-zm / math.sqrt(2.0)))
    zl = z[lo]
    inv2 = 1.0 / (zl * zl)
    series = np.zeros_like(zl)
    for c in reversed(_SERIES):  # Horner in 1/z²
        series = series * inv2 + c
    out[lo] = _log_phi(zl) + np.log(inv2) + np.log(series)
    return out


def _broadcast(
    mean: np.ndarray | float, std: np.ndarray | float, best: np.ndarray | float, xi: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    m, s, b, x = np.broadcast_arrays(
        np.asarray(mean, dtype=float),
        np.asarray(std, dtype=float),
        np.asarray(best, dtype=float),
        np.asarray(xi, dtype=float),
    )
    for name, arr in (("mean", m), ("std", s), ("best", b), ("xi", x)):
        if not np.all(np.isfinite(arr)):
            bad = arr[~np.isfinite(arr)].flat[0]
            raise ConfigError(f"{name} must be finite, got {bad!r}")
    if np.any(s < 0.0):
        raise ConfigError(f"std must be >= 0, got {s[s < 0.0].flat[0]!r}")
    return m, s, b + x


def log_expected_improvement(
    mean: np.ndarray | float,
    std: np.ndarray | float,
    best: np.ndarray | float,
    xi: float = 0.0,
) -> np.ndarray:
    """Natural log of :func:`expected_improvement`, finite wherever EI > 0 mathematically.

    Used for optimisation in flat regions where EI itself underflows (z below about −38).

    Args:
        mean: Posterior mean μ̄ (cost units), broadcastable.
        std: Posterior standard deviation σ̄ >= 0 (cost units), broadcastable.
        best: Incumbent min(S) (cost units), broadcastable.
        xi: Kim et al. 2019's ξ (see :func:`expected_improvement` for its sign).

    Returns:
        log EI, broadcast shape; −inf only where std = 0 and best − mean + ξ <= 0.
    """
    m, s, target = _broadcast(mean, std, best, xi)
    out = np.empty(m.shape)
    pos = s > 0.0
    z = (target[pos] - m[pos]) / s[pos]
    out[pos] = np.log(s[pos]) + _log_h(z)
    gap = target[~pos] - m[~pos]
    with np.errstate(divide="ignore"):
        out[~pos] = np.where(gap > 0.0, np.log(np.where(gap > 0.0, gap, 1.0)), -np.inf)
    return out


def expected_improvement(
    mean: np.ndarray | float,
    std: np.ndarray | float,
    best: np.ndarray | float,
    xi: float = 0.0,
) -> np.ndarray:
    """Expected Improvement for MINIMISATION, exactly Kim et al. 2019 §II.B.

    EI = σ̄ (z Φ(z) + φ(z)),  z = (best − μ̄ + ξ) / σ̄;  for σ̄ = 0, EI = max(best − μ̄ + ξ, 0).

    Sign of ξ: Kim et al. 2019 *add* ξ to the incumbent, so ξ > 0 raises the target and moves EI
    toward exploitation (points whose mean is slightly worse than the best still score). Callers
    wanting the usual exploration margin ("improve by at least ξ") pass a negative ξ.

    Never negative or NaN; positive wherever the true EI is representable in float64 (far in the
    tail, z < about −38, the true value underflows—use :func:`log_expected_improvement`).

    Args:
        mean: Posterior mean μ̄ (cost units), broadcastable.
        std: Posterior standard deviation σ̄ >= 0 (cost units), broadcastable.
        best: Incumbent min(S) (cost units), broadcastable.
        xi: Exploration-exploitation parameter ξ (cost units).

    Returns:
        EI in cost units, broadcast shape.

    Raises:
        ConfigError: Non-finite inputs or negative std.
    """
    m, s, target = _broadcast(mean, std, best, xi)
    out = np.empty(m.shape)
    pos = s > 0.0
    z = (target[pos] - m[pos]) / s[pos]
    sp = s[pos]
    direct = z > _Z_DIRECT
    vals = np.empty(z.shape)
    zd = z[direct]
    vals[direct] = sp[direct] * (zd * ndtr(zd) + np.exp(_log_phi(zd)))
    vals[~direct] = np.exp(np.log(sp[~direct]) + _log_h(z[~direct]))
    out[pos] = vals
    out[~pos] = np.maximum(target[~pos] - m[~pos], 0.0)
    return out


def _log_ei_grad(
    mean: np.ndarray, var: np.ndarray, target: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """log EI and its derivatives w.r.t. mean and var (var > 0), elementwise."""
    s = np.sqrt(var)
    z = (target - mean) / s
    lh = _log_h(z)
    # dEI/dμ = −Φ(z), dEI/dσ = φ(z); divide by EI = σ h(z) through logs for stability.
    d_mean = -np.exp(log_ndtr(z) - lh) / s
    d_std = np.exp(_log_phi(z) - lh) / s
    return np.log(s) + lh, d_mean, d_std / (2.0 * s)


def _check_predict(mean: np.ndarray, var: np.ndarray, m: int) -> tuple[np.ndarray, np.ndarray]:
    mean = np.asarray(mean, dtype=float).reshape(-1)
    var = np.asarray(var, dtype=float).reshape(-1)
    if mean.shape != (m,) or var.shape != (m,):
        raise ConfigError(
            f"predict must return mean and var of shape ({m},), got {mean.shape} and {var.shape}"
        )
    if m == 1:  # the SLSQP objective's case: scalar checks, no temporary arrays
        mf, vf = float(mean[0]), float(var[0])
        if not (math.isfinite(mf) and math.isfinite(vf) and vf >= 0.0):
            raise EstimatorError("predict returned a non-finite mean or a negative/non-finite variance")
        return mean, var
    if not (np.all(np.isfinite(mean)) and np.all(np.isfinite(var)) and np.all(var >= 0.0)):
        raise EstimatorError("predict returned a non-finite mean or a negative/non-finite variance")
    return mean, var


def _search_set(
    candidates: np.ndarray, A_ub: np.ndarray | None, b_ub: np.ndarray | None, n_local: object,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, Callable[[np.ndarray], np.ndarray]]:
    """Validated (candidates (n, d), A (k, d), b (k,), feasibility test) of a constrained search.

    Raises:
        ConfigError: Bad shapes or arguments.
        InfeasibleError: A candidate violates the box or the constraints.
    """
    U = np.asarray(candidates, dtype=float)
    if U.ndim != 2 or U.shape[0] < 1 or U.shape[1] < 1:
        raise ConfigError(f"candidates must have shape (n, d) with n, d >= 1, got {U.shape}")
    d = U.shape[1]
    if not np.all(np.isfinite(U)):
        raise ConfigError("candidates contain non-finite values")
    if (A_ub is None) != (b_ub is None):
        raise ConfigError("A_ub and b_ub must both be given or both be None")
    A = np.zeros((0, d)) if A_ub is None else np.asarray(A_ub, dtype=float).reshape(-1, d)
    b = np.zeros(0) if b_ub is None else np.asarray(b_ub, dtype=float).reshape(-1)
    if A.shape[0] != b.size:
        raise ConfigError(f"A_ub has {A.shape[0]} rows but b_ub has {b.size} entries")
    if not (np.all(np.isfinite(A)) and np.all(np.isfinite(b))):
        raise ConfigError("A_ub and b_ub must be finite")
    if isinstance(n_local, bool) or not isinstance(n_local, int) or n_local < 0:
        raise ConfigError(f"n_local must be an int >= 0, got {n_local!r}")

    def feasible(V: np.ndarray) -> np.ndarray:
        ok = np.all((V >= 0.0) & (V <= 1.0), axis=-1)
        if A.shape[0]:
            ok &= np.all(V @ A.T <= b + _FEAS_TOL, axis=-1)
        return ok

    bad = np.flatnonzero(~feasible(U))
    if bad.size:
        raise InfeasibleError(
            f"candidate row {bad[0]} = {U[bad[0]].tolist()} is outside the unit cube or violates "
            "A_ub u <= b_ub"
        )
    return U, A, b, feasible


def maximize_ei(
    predict: PredictFn,
    best: float,
    *,
    candidates: np.ndarray,
    A_ub: np.ndarray | None,
    b_ub: np.ndarray | None,
    rng: np.random.Generator,
    xi: float = 0.0,
    n_local: int = 4,
    predict_grad: PredictGradFn | None = None,
) -> tuple[np.ndarray, float]:
    """Maximise EI over {u ∈ [0, 1]^d : A_ub u <= b_ub} (Algorithm 1 line 10 of Kim et al. 2019).

    Log EI is evaluated on every candidate; the ``n_local`` best are refined by SLSQP on −log EI
    with the box and the linear constraints. A refined point replaces the incumbent only if it
    is feasible (after clipping to the box, A u <= b + 1e-9) and strictly better, so the result
    is always feasible and never worse than the best candidate.

    Args:
        predict: U (m, d) → (mean (m,), var (m,)) of the latent cost (e.g. ``gp.predict``).
        best: Incumbent min(S) in cost units.
        candidates: Feasible unit-cube points, shape (n, d), n >= 1.
        A_ub: Constraint matrix in unit-cube coordinates, shape (k, d) (k may be 0), or None.
        b_ub: Right-hand sides, shape (k,), or None.
        rng: Breaks ties between equally good candidates.
        xi: Kim et al. 2019's ξ (see :func:`expected_improvement`).
        n_local: Number of candidates refined locally (0 = candidates only).
        predict_grad: Optional U (m, d) → (mean, var, dmean (m, d), dvar (m, d)) (e.g.
            ``gp.predict_with_grad``) for analytic SLSQP gradients; finite differences otherwise.

    Returns:
        (u (d,), EI at u in cost units).

    Raises:
        ConfigError: Bad shapes or arguments.
        InfeasibleError: A candidate violates the box or the constraints.
        EstimatorError: ``predict`` returned non-finite values.
    """
    U, A, b, feasible = _search_set(candidates, A_ub, b_ub, n_local)
    n, d = U.shape
    if not math.isfinite(best):
        raise ConfigError(f"best must be finite, got {best!r}")

    mean, var = _check_predict(*predict(U), n)
    log_ei = log_expected_improvement(mean, np.sqrt(var), best, xi)
    # Random order + stable sort: ties (e.g. a flat EI) are broken by rng, not by position.
    order = rng.permutation(n)
    ranked = order[np.argsort(-log_ei[order], kind="stable")]
    best_idx = int(ranked[0])
    best_u = U[best_idx].copy()
    best_log = float(log_ei[best_idx])
    target = float(best) + float(xi)

    def objective(u: np.ndarray) -> tuple[float, np.ndarray] | float:
        x = np.clip(u, 0.0, 1.0)[None, :]
        if predict_grad is None:
            m, v = _check_predict(*predict(x), 1)
            if v[0] <= 0.0:
                return 1e10
            return -float(log_expected_improvement(m, np.sqrt(v), target)[0])
        m, v, dm, dv = predict_grad(x)
        m, v = _check_predict(m, v, 1)
        if v[0] <= 0.0:
            return 1e10, np.zeros(d)
        lei, g_m, g_v = _log_ei_grad(m, v, target)
        grad = g_m[0] * np.asarray(dm, dtype=float).reshape(d) + g_v[0] * np.asarray(
            dv, dtype=float
        ).reshape(d)
        return -float(lei[0]), -grad

    def neg_log_ei(u: np.ndarray) -> float:
        m, v = _check_predict(*predict(u[None, :]), 1)
        return -float(log_expected_improvement(m, np.sqrt(v), best, xi)[0])

    starts = [U[idx] for idx in ranked[:n_local] if math.isfinite(log_ei[idx])]
    best_u, neg_best = _refine_locally(objective, starts, neg_log_ei, best_u, -best_log, A=A, b=b,
                                       feasible=feasible, jac=predict_grad is not None)
    best_log = -neg_best
    _log.debug("maximize_ei: log EI %.4g at %s", best_log, best_u)
    m, v = _check_predict(*predict(best_u[None, :]), 1)
    ei = float(expected_improvement(m, np.sqrt(v), best, xi)[0])
    return best_u, ei


def minimize_lcb(
    predict: PredictFn,
    beta: float,
    *,
    candidates: np.ndarray,
    A_ub: np.ndarray | None,
    b_ub: np.ndarray | None,
    n_local: int = 3,
    predict_grad: PredictGradFn | None = None,
) -> np.ndarray:
    """The feasible point of lowest ``μ̄(u) + β·σ̄(u)`` (a pessimistic bound on the cost).

    The recommendation's criterion: the setting whose cost is, with the model's uncertainty, the
    best bet (β = 0: the posterior mean's minimiser; β > 0 avoids settings the model knows
    little about). Evaluated on every candidate; the ``n_local`` best are refined by SLSQP under
    the box and the linear constraints, a refined point kept only if feasible and lower.

    Args:
        predict: U (m, d) → (mean (m,), var (m,)) of the latent cost.
        beta: β >= 0, in posterior SDs.
        candidates: Feasible unit-cube points, shape (n, d), n >= 1.
        A_ub: Constraint matrix in unit-cube coordinates, shape (k, d), or None.
        b_ub: Right-hand sides, shape (k,), or None.
        n_local: Number of candidates refined locally (0 = candidates only).
        predict_grad: Optional U → (mean, var, dmean (m, d), dvar (m, d)) for SLSQP gradients.

    Returns:
        u, shape (d,).

    Raises:
        ConfigError: Bad shapes or arguments (β negative or not finite).
        InfeasibleError: A candidate violates the box or the constraints.
        EstimatorError: ``predict`` returned non-finite values.
    """
    U, A, b, feasible = _search_set(candidates, A_ub, b_ub, n_local)
    n, d = U.shape
    if isinstance(beta, bool) or not (isinstance(beta, int | float) and math.isfinite(beta) and beta >= 0):
        raise ConfigError(f"beta={beta!r}; expected a finite number >= 0")
    mean, var = _check_predict(*predict(U), n)
    score = mean + beta * np.sqrt(var)
    ranked = np.argsort(score, kind="stable")
    best_u, best_score = U[int(ranked[0])].copy(), float(score[int(ranked[0])])

    def objective(u: np.ndarray) -> tuple[float, np.ndarray] | float:
        x = np.clip(u, 0.0, 1.0)[None, :]
        if predict_grad is None:
            m, v = _check_predict(*predict(x), 1)
            return float(m[0] + beta * math.sqrt(v[0]))
        m, v, dm, dv = predict_grad(x)
        m, v = _check_predict(m, v, 1)
        sd = math.sqrt(max(float(v[0]), 1e-300))
        grad = (np.asarray(dm, dtype=float).reshape(d)
                + beta * np.asarray(dv, dtype=float).reshape(d) / (2.0 * sd))
        return float(m[0]) + beta * sd, grad

    def lcb(u: np.ndarray) -> float:
        m, v = _check_predict(*predict(u[None, :]), 1)
        return float(m[0] + beta * math.sqrt(v[0]))

    best_u, _ = _refine_locally(objective, [U[idx] for idx in ranked[:n_local]], lcb, best_u,
                                best_score, A=A, b=b, feasible=feasible, jac=predict_grad is not None)
    return best_u


def _refine_locally(
    objective: Callable[[np.ndarray], Any],
    starts: Sequence[np.ndarray],
    value: Callable[[np.ndarray], float],
    best_u: np.ndarray,
    best_value: float,
    *,
    A: np.ndarray,
    b: np.ndarray,
    feasible: Callable[[np.ndarray], bool],
    jac: bool,
) -> tuple[np.ndarray, float]:
    """SLSQP on ``objective`` from each start, under the box and ``A u <= b``; a refined point
    (clipped to the box) replaces ``best_u`` only if it is feasible and its ``value`` is lower.
    Returns the best point (d,) and its value."""
    d = best_u.shape[0]
    constraints = (
        [{"type": "ineq", "fun": lambda u: b - A @ u, "jac": lambda u: -A}] if A.shape[0] else []
    )
    for start in starts:
        res = minimize(objective, start, jac=jac, method="SLSQP", bounds=[(0.0, 1.0)] * d,
                       constraints=constraints, options={"maxiter": 100, "ftol": 1e-7})
        u = np.clip(np.asarray(res.x, dtype=float), 0.0, 1.0)
        if not (np.all(np.isfinite(u)) and feasible(u)):
            continue
        val = value(u)
        if val < best_value:
            best_u, best_value = u, val
    return best_u, best_value
