"""The knowledge gradient: what one more noisy measurement is worth to the recommendation.

The recommendation at the end of a session is the setting of lowest posterior mean (give or take
its uncertainty); the knowledge gradient of a candidate x is how much one more measurement at x
is expected to lower that minimum (Frazier, Powell & Dayanik 2009, "The knowledge-gradient policy
for correlated normal beliefs", INFORMS J. Computing 21:599-613; for a GP over a continuous space,
with the minimum taken over the measured settings and x itself, Scott, Frazier & Powell 2011,
"The correlated knowledge gradient for simulation optimization of continuous parameters using
Gaussian process regression", SIAM J. Optim. 21:996-1026, the "KGCP").

After a measurement y at x with noise variance σ²_n, the posterior mean at any point a moves by
σ̃(a, x)·Z, Z ~ N(0, 1), with σ̃(a, x) = Σ(a, x) / √(Σ(x, x) + σ²_n) (Σ the posterior covariance).
So, for minimisation,

    KG(x) = E[max_a (−μ(a) + σ̃(a, x)·Z)] − max_a (−μ(a)),

the expectation of the maximum of lines in Z, computed exactly from their upper envelope
(Frazier et al. 2009, Algorithm 1): KG = Σ_j (b_{j+1} − b_j)·f(−|c_j|), f(z) = zΦ(z) + φ(z), over
the envelope's lines sorted by slope b and their breakpoints c_j.

Unlike expected improvement, the noise of the *next* measurement enters: where one measurement
cannot move the posterior mean much (σ̃ small: the breath noise is large against what the model
does not know), it is worth little; and a measured setting is a candidate like any other, so
measuring a promising one again can be worth more than a new one.
"""

from __future__ import annotations

import numpy as np
from scipy.special import ndtr

from hilbo_core.errors import ConfigError

__all__ = ["knowledge_gradient", "knowledge_gradient_min"]

_INV_SQRT_2PI = 1.0 / np.sqrt(2.0 * np.pi)


def _f(z: np.ndarray) -> np.ndarray:
    """z Φ(z) + φ(z) (z <= 0 here: no cancellation worth guarding against at these sizes)."""
    return z * ndtr(z) + _INV_SQRT_2PI * np.exp(-0.5 * z * z)


def _kg_one(a: np.ndarray, b: np.ndarray) -> float:
    """E[max_j a_j + b_j Z] − max_j a_j for one set of lines (Frazier et al. 2009, Algorithm 1)."""
    order = np.lexsort((a, b))  # by slope, ties by intercept
    a, b = a[order], b[order]
    keep = np.append(b[1:] != b[:-1], True)  # equal slopes: only the highest line can matter
    a, b = a[keep], b[keep]
    if a.size == 1:
        return 0.0
    env = [0]  # indices of the upper envelope's lines, slopes increasing
    cuts = [-np.inf]  # cuts[i]: where env[i] takes over from env[i - 1]
    for i in range(1, a.size):
        while True:
            j = env[-1]
            z = (a[j] - a[i]) / (b[i] - b[j])
            if len(env) > 1 and z <= cuts[-1]:
                env.pop()
                cuts.pop()
                continue
            env.append(i)
            cuts.append(z)
            break
    bs = b[env]
    c = np.asarray(cuts[1:])
    return float(np.sum((bs[1:] - bs[:-1]) * _f(-np.abs(c))))


def knowledge_gradient(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """E[max_j (a_j + b_j·Z)] − max_j a_j, Z ~ N(0, 1), for each row: exact, >= 0.

    Args:
        a: Intercepts, shape (m, k), finite.
        b: Slopes, shape (m, k), finite.

    Returns:
        Shape (m,).

    Raises:
        ConfigError: Shapes differ, k < 1 or non-finite values.
    """
    a = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float)
    if a.ndim != 2 or a.shape != b.shape or a.shape[1] < 1:
        raise ConfigError(f"a and b must have the same shape (m, k >= 1), got {a.shape} and {b.shape}")
    if not (np.isfinite(a).all() and np.isfinite(b).all()):
        raise ConfigError("a and b must be finite")
    return np.array([max(_kg_one(a[i], b[i]), 0.0) for i in range(a.shape[0])])


def knowledge_gradient_min(mean_ref: np.ndarray, cov_ref: np.ndarray, mean_cand: np.ndarray,
                           var_cand: np.ndarray, noise_var: np.ndarray | float) -> np.ndarray:
    """The KGCP of candidates for minimisation: the expected fall of the lowest posterior mean
    over the reference points and the candidate itself after one measurement at the candidate.

    Args:
        mean_ref: Posterior mean at the reference points (the measured settings), shape (k,).
        cov_ref: Posterior covariance between them and each candidate, shape (k, m).
        mean_cand: Posterior mean at the candidates, shape (m,).
        var_cand: Posterior variance at the candidates, shape (m,), >= 0.
        noise_var: Variance of the measurement to come at each candidate, shape (m,) or scalar,
            > 0.

    Returns:
        KG, shape (m,), in the units of the means (e.g. W), >= 0.

    Raises:
        ConfigError: Inconsistent shapes, negative variances or a non-positive noise variance.
    """
    mean_ref = np.asarray(mean_ref, dtype=float).reshape(-1)
    mean_cand = np.asarray(mean_cand, dtype=float).reshape(-1)
    var_cand = np.asarray(var_cand, dtype=float).reshape(-1)
    cov_ref = np.asarray(cov_ref, dtype=float)
    k, m = mean_ref.size, mean_cand.size
    if cov_ref.shape != (k, m) or var_cand.shape != (m,):
        raise ConfigError(f"cov_ref must be ({k}, {m}) and var_cand ({m},), got {cov_ref.shape} "
                          f"and {var_cand.shape}")
    noise = np.broadcast_to(np.asarray(noise_var, dtype=float), (m,))
    if np.any(var_cand < 0.0) or not np.all(noise > 0.0):
        raise ConfigError("var_cand must be >= 0 and noise_var > 0")
    scale = 1.0 / np.sqrt(var_cand + noise)  # (m,)
    a = -np.concatenate([np.broadcast_to(mean_ref, (m, k)), mean_cand[:, None]], axis=1)
    b = np.concatenate([cov_ref.T, var_cand[:, None]], axis=1) * scale[:, None]
    return knowledge_gradient(a, b)
