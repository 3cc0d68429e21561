"""A breath-by-breath estimate of the steady-state cost whose variance describes its errors.

:class:`TransitionEstimator` is the default estimator of the optimizer. Per breath it
makes a small Bayesian fit of the first-order transition of one setting,

    m(t) = c + (b0 − c)·e^{−t/τ},   y_i = m(t_i)·(1 + ε_i),

where t is the time since the setting began, b0 the level the body is at when the setting begins
and c the steady-state cost wanted. It is the model of Kim et al. 2019 §II.C with c0 = b0 and τ0 = τ
(the body's level at the start *is* c0; one response time for both terms, as the lab's
first-order fit assumes).

Why a grid fit and not the UKF (:class:`~hilbo_core.metabolic.MetabolicUKF`): for a fixed τ the
model is linear in (c, b0), so the posterior of (c, b0) given τ and the noise scale is an exact
2×2 Gaussian, and τ is one-dimensional, so its posterior can be marginalised numerically on a
grid. The UKF linearises the strongly non-linear trade-off between c and τ early in a large
transition (where the data cannot yet tell a large c reached slowly from a smaller one reached
quickly); that is where it was measured overconfident on real breath-by-breath recordings (156
walking and running transitions of 24 people: z-score SD 3.3 after large steps).
The grid mixture carries that trade-off into the reported variance instead. It also makes the
other three requirements of an estimate that holds on real breaths direct:

* **The transition starts from the body's level.** b0 ~ N(level, var + inflation²), the previous
  setting's fitted level at its last breath with its variance (:meth:`TransitionEstimator.start_from`).
* **τ has a physiological prior:** log-normal, median 42 s (Selinger & Donelan 2014's step
  response in walking), log-SD 0.2 (95 % of the prior in ≈ 28–62 s: those recordings and
  shared/DESIGN.md give 30–60 s as the range of time constants between people), on a log grid
  12–150 s (wide enough that a person outside the range is still found). τ is a trait of the
  person (in those recordings it varies *between people*), so the settings of one person share it
  hierarchically: each setting's τ is the person's τ times e^δ, δ ~ N(0, 0.1²) (an assumed
  ≈ 10 % within-person variation between transitions, e.g. up- vs down-steps), and each setting
  hands on the accumulated likelihood of the person's τ (its data's τ evidence, convolved with
  that kernel). A setting's τ prior is the population prior times that likelihood, convolved
  again. Settings too short to say anything about τ leave the prior at the population's; after
  a few large steps the person's τ is known to ≈ ±10 %, never better. (A random walk of τ from
  setting to setting, tried first, drifted away on long runs of early-stopped settings.)
* **Robust, online breath noise.** ε_i is Student-t (ν = 4) with a relative scale (the CV)
  estimated from the breaths by iteratively reweighted least squares (the EM of the t model), with
  a scaled-inverse-χ² prior of median CV 11 % (the median steady-state CV of those real breaths)
  and ν0 = 10 pseudo-breaths, so the first few breaths cannot collapse it. Swallows and coughs get
  small weights instead of dragging c. Breaths are treated as independent (the
  autocorrelation of those real breaths is below 0.15 beyond 3 s, i.e. beyond one breath).

The reported variance of c is that of the τ mixture, with two corrections that make it describe
the errors rather than the model's conditional spread: a sandwich factor for the t weights (for
Gaussian breaths, IRLS-with-t-weights information understates the variance of the location by
a known factor, computed below by quadrature) and the Student-t inflation ν/(ν−2) for the
estimated CV (ν = ν0 + effective residual breaths).

c has only a weak prior (N(level, (1.0·level)²)); it keeps the first breaths' posterior proper.
:meth:`TransitionEstimator.data_only` divides it out for the GP (shared/DESIGN.md: data-only observations).

Cost: every breath refits all breaths of the setting (n ≤ a few hundred) on a 25-point τ grid
with two reweighting passes, vectorised over the grid: ≈ 100–300 µs per breath.
"""

from __future__ import annotations

import enum
import math
from dataclasses import asdict, dataclass, fields
from typing import Any

import numpy as np
import numpy.typing as npt

from hilbo_core.errors import ConfigError, EstimatorError, MeasurementError
from hilbo_core.metabolic import divide_gaussian

__all__ = [
    "EstimatorKind",
    "StartState",
    "TransitionConfig",
    "TransitionEstimator",
]


class EstimatorKind(enum.Enum):
    """Which breath-by-breath estimator the optimizer uses."""

    TRANSITION = "transition"  # TransitionEstimator (the default)
    SEED_UKF = "seed_ukf"  # MetabolicUKF (Kim et al. 2019 §II.C)


def _t_constants(nu: float) -> tuple[float, float]:
    """Consistency constants of Student-t(ν) IRLS on Gaussian residuals of unit variance.

    Returns (a, b): a = σ_t², the t-scale² the EM converges to (so cv² = σ_t²/a is the SD²);
    b = the variance of the location M-estimator per breath (sandwich E[ψ²]/E[ψ']², ψ = w·z),
    which the naive information Σw/σ_t² would put at a. Gauss–Hermite quadrature, deterministic.
    """
    x, wq = np.polynomial.hermite_e.hermegauss(120)
    wq = wq / wq.sum()
    s2 = 1.0
    for _ in range(500):
        w = (nu + 1.0) / (nu + x**2 / s2)
        s2_new = float(np.sum(wq * w * x**2))
        if abs(s2_new - s2) < 1e-14:
            break
        s2 = s2_new
    w = (nu + 1.0) / (nu + x**2 / s2)
    psi = w * x
    dpsi = (nu + 1.0) * (nu - x**2 / s2) / (nu + x**2 / s2) ** 2
    b = float(np.sum(wq * psi**2) / np.sum(wq * dpsi) ** 2)
    return s2, b


@dataclass(frozen=True)
class StartState:
    """What one setting's estimator hands to the next: where the body is and what is known.

    Attributes:
        level_w: Fitted body level at the last breath (W).
        level_var_w2: Its variance (W²).
        noise_cv: Estimated breath noise CV (the next setting's prior median), or None.
        tau_log_lik: Accumulated log-likelihood of the person's τ on the estimator's grid
            (from every earlier setting), or None for none yet.
    """

    level_w: float
    level_var_w2: float
    noise_cv: float | None = None
    tau_log_lik: tuple[float, ...] | None = None

    def to_json(self) -> dict[str, Any]:
        """JSON-able form."""
        return {"level_w": self.level_w, "level_var_w2": self.level_var_w2, "noise_cv": self.noise_cv,
                "tau_log_lik": None if self.tau_log_lik is None else list(self.tau_log_lik)}

    @classmethod
    def from_json(cls, data: Any) -> StartState:
        """Inverse of :meth:`to_json`."""
        try:
            tau = data.get("tau_log_lik")
            cv = data.get("noise_cv")
            return cls(float(data["level_w"]), float(data["level_var_w2"]),
                       None if cv is None else float(cv),
                       None if tau is None else tuple(float(v) for v in tau))
        except (AttributeError, KeyError, TypeError, ValueError) as err:
            raise ConfigError(f"invalid estimator start state {data!r}: {err!r}") from err


@dataclass(frozen=True)
class TransitionConfig:
    """Priors and numerics of :class:`TransitionEstimator`.

    Attributes:
        tau_median_s: Median of the log-normal prior of τ in s (Selinger & Donelan 2014: ≈ 42 s).
        tau_log_sd: Its log-SD; 0.2 puts 95 % of the prior in ≈ 28–62 s (real recordings:
            30–60 s between people).
        tau_min_s: Smallest τ of the grid in s.
        tau_max_s: Largest τ of the grid in s.
        n_tau: Grid points (log-spaced).
        noise_cv: Prior median of the breath noise CV (median 11 % on real breaths).
        noise_prior_breaths: Weight ν0 of that prior in pseudo-breaths.
        t_dof: Degrees of freedom ν of the Student-t breath noise (4: heavy enough that a swallow
            at 5 SD gets a fifth of a normal breath's weight).
        c_rel_sd: Prior SD of c relative to the starting level (weak; divided out for the GP).
        start_rel_sd: SD of b0 relative to the first breath when no starting level is given.
        start_inflation_rel: Added SD of b0 relative to the starting level when one is given:
            the body moves a little between the previous setting's last breath and this
            setting's start (switching time, a breath or two).
        tau_person_log_sd: SD of a setting's log τ around the person's (within-person
            variation of τ, assumed ≈ 10 %).
        irls_passes: Reweighting passes per breath (the previous breath's weights warm-start).
        min_level_w: Floor in W on the level that scales the noise.
        max_watts: Breaths above this power in W are rejected as absurd.
    """

    tau_median_s: float = 42.0
    tau_log_sd: float = 0.2
    tau_min_s: float = 12.0
    tau_max_s: float = 150.0
    n_tau: int = 25
    noise_cv: float = 0.11
    noise_prior_breaths: float = 10.0
    t_dof: float = 4.0
    c_rel_sd: float = 1.0
    start_rel_sd: float = 1.0
    start_inflation_rel: float = 0.05
    tau_person_log_sd: float = 0.1
    irls_passes: int = 2
    min_level_w: float = 10.0
    max_watts: float = 5000.0

    def __post_init__(self) -> None:
        """Validate every field (ConfigError names the field, its value and the range)."""
        ranges: dict[str, tuple[float, float]] = {
            "tau_median_s": (1.0, 1000.0),
            "tau_log_sd": (0.01, 3.0),
            "tau_min_s": (0.5, 1000.0),
            "tau_max_s": (1.0, 10000.0),
            "n_tau": (2, 400),
            "noise_cv": (0.001, 2.0),
            "noise_prior_breaths": (0.5, 1e4),
            "t_dof": (2.5, 1e6),
            "c_rel_sd": (0.01, 100.0),
            "start_rel_sd": (0.01, 100.0),
            "start_inflation_rel": (0.0, 10.0),
            "tau_person_log_sd": (0.0, 10.0),
            "irls_passes": (1, 50),
            "min_level_w": (1e-3, 1e4),
            "max_watts": (1.0, 1e5),
        }
        for f in fields(self):
            value = getattr(self, f.name)
            low, high = ranges[f.name]
            integer = f.name in ("n_tau", "irls_passes")
            ok = (
                not isinstance(value, bool)
                and isinstance(value, int if integer else int | float)
                and math.isfinite(value)
                and low <= value <= high
            )
            if not ok:
                kind = "an integer" if integer else "a number"
                raise ConfigError(
                    f"TransitionConfig.{f.name}={value!r} must be {kind} in [{low:g}, {high:g}]"
                )
        if not self.tau_min_s < self.tau_max_s:
            raise ConfigError(
                f"TransitionConfig.tau_min_s={self.tau_min_s!r} must be below "
                f"tau_max_s={self.tau_max_s!r}"
            )


class TransitionEstimator:
    """Bayesian fit of one setting's transition; the mean and variance of its steady state c.

    Create one per setting; call :meth:`start_from` before the first breath to start the
    transition from the level the previous setting left the body at (without it, b0 gets a
    weak prior around the first breath). ``t_s`` is the time since the setting began.

    Args:
        config: Priors and numerics; ``TransitionConfig()`` when omitted.
    """

    def __init__(self, config: TransitionConfig | None = None) -> None:
        self._config = config if config is not None else TransitionConfig()
        cfg = self._config
        self._tau = np.geomspace(cfg.tau_min_s, cfg.tau_max_s, cfg.n_tau)
        z = (np.log(self._tau) - math.log(cfg.tau_median_s)) / cfg.tau_log_sd
        self._log_pop_tau = -0.5 * z**2  # population prior of τ (log weights on the grid)
        self._log_prior_tau = self._log_pop_tau.copy()
        self._person_ll = np.zeros(cfg.n_tau)  # log-likelihood of the person's τ, earlier settings
        self._log_ev = np.zeros(cfg.n_tau)  # this setting's τ evidence (log, max 0)
        self._a, self._b = _t_constants(cfg.t_dof)
        self._t: list[float] = []
        self._y: list[float] = []
        self._start: tuple[float, float] | None = None
        self._noise_prior_cv = cfg.noise_cv
        self._cv2 = cfg.noise_cv**2
        self._m_ref: npt.NDArray[np.float64] = np.empty(0)
        self._w: npt.NDArray[np.float64] = np.empty(0)
        self._mean = math.nan
        self._var = math.nan
        self._level = (math.nan, math.nan)
        self._prior_c = (math.nan, math.nan)
        self._pi = np.exp(self._log_prior_tau - self._log_prior_tau.max())
        self._pi /= self._pi.sum()
        # K[i, p]: weight of a setting's τ_i given the person's τ_p (columns sum to 1).
        dlog = np.log(self._tau)[:, None] - np.log(self._tau)[None, :]
        if cfg.tau_person_log_sd > 0.0:
            kern = np.exp(-0.5 * (dlog / cfg.tau_person_log_sd) ** 2)
            self._kern = kern / kern.sum(axis=0, keepdims=True)
        else:
            self._kern = np.eye(cfg.n_tau)

    # ------------------------------------------------------------------ views
    @property
    def config(self) -> TransitionConfig:
        """The priors and numerics in use."""
        return self._config

    @property
    def mean(self) -> float:
        """Posterior mean of c in W. Raises EstimatorError before the first breath."""
        self._require_started()
        return self._mean

    @property
    def var(self) -> float:
        """Posterior variance of c in W². Raises EstimatorError before the first breath."""
        self._require_started()
        return self._var

    @property
    def n_updates(self) -> int:
        """Breaths fused."""
        return len(self._t)

    @property
    def last_t(self) -> float | None:
        """Time in s of the last accepted breath, or None."""
        return self._t[-1] if self._t else None

    @property
    def noise_cv(self) -> float:
        """Current estimate of the breath noise CV (the prior's median before any breath)."""
        return math.sqrt(self._cv2)

    def level(self) -> tuple[float, float]:
        """Fitted body level m(t) at the last breath: (mean W, variance W²).

        What the next setting's transition starts from (:meth:`start_from`).

        Raises:
            EstimatorError: No breath has been fused yet.
        """
        self._require_started()
        return self._level

    def tau_posterior(self) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]]:
        """(τ grid in s, posterior weights) — the prior's before the first breath."""
        return self._tau.copy(), self._pi.copy()

    def handover(self) -> StartState:
        """What the next setting's estimator starts from (:meth:`start_from_state`).

        The body level at the last breath, the noise CV, and the person's τ log-likelihood with
        this setting's evidence added (convolved with the within-person kernel).

        Raises:
            EstimatorError: No breath has been fused yet.
        """
        level, var = self.level()
        own = np.log(np.maximum(self._kern.T @ np.exp(self._log_ev), 1e-300))
        ll = self._person_ll + own
        return StartState(level, var, self.noise_cv, tuple(float(v) for v in ll - ll.max()))

    def start_from_state(self, state: StartState) -> None:
        """:meth:`start_from` with a :class:`StartState` (e.g. the previous :meth:`handover`)."""
        self.start_from(state.level_w, state.level_var_w2, state.noise_cv, state.tau_log_lik)

    def data_only(self) -> tuple[float, float]:
        """The information about c the breaths carry, without the prior on c (for the GP).

        The posterior of c divided by its prior N(level, (c_rel_sd·level)²) (Gaussian division;
        :func:`~hilbo_core.metabolic.divide_gaussian`). The b0 prior stays in: it is what earlier
        breaths said about the starting level, not a prior on c.

        Raises:
            EstimatorError: No breath has been fused yet.
        """
        self._require_started()
        return divide_gaussian(self._mean, self._var, *self._prior_c)

    # ------------------------------------------------------------------ inputs
    def start_from(self, level_w: float, level_var_w2: float, noise_cv: float | None = None,
                   tau_log_lik: Any = None) -> None:
        """Start the transition from the level the body is at when the setting begins.

        Args:
            level_w: The level in W (e.g. the previous setting's :meth:`level` mean).
            level_var_w2: Its variance in W² (>= 0).
            noise_cv: The previous setting's noise CV estimate, used as this setting's prior
                median (same person, same cart); None keeps the configured one.
            tau_log_lik: Log-likelihood of the person's τ from earlier settings on this
                estimator's grid (shape (n_tau,), from the previous :meth:`handover`); None:
                nothing known yet (the population prior).

        Raises:
            MeasurementError: A bad level, variance or CV (the estimator is unchanged).
            EstimatorError: Breaths have already been fused.
        """
        if self._t:
            raise EstimatorError("start_from() after the first breath; call it on a fresh estimator")
        level = _finite(level_w, "level_w")
        var = _finite(level_var_w2, "level_var_w2")
        if not 0.0 < level <= self._config.max_watts or var < 0.0:
            raise MeasurementError(
                f"start level {level_w!r} W (variance {level_var_w2!r} W²) must be a power in "
                f"(0, {self._config.max_watts:g}] W with a variance >= 0"
            )
        if noise_cv is not None:
            cv = _finite(noise_cv, "noise_cv")
            if not 0.001 <= cv <= 2.0:
                raise MeasurementError(f"noise_cv={noise_cv!r} must be in [0.001, 2]")
        lp = None
        if tau_log_lik is not None:
            try:
                lp = np.asarray(tau_log_lik, dtype=float).reshape(self._config.n_tau)
            except (TypeError, ValueError) as err:
                raise MeasurementError(
                    f"tau_log_lik must be {self._config.n_tau} log weights on the τ grid") from err
            if not np.isfinite(lp).all():
                raise MeasurementError("tau_log_lik must be finite log weights")
        if noise_cv is not None:
            self._noise_prior_cv = cv
            self._cv2 = cv**2
        if lp is not None:
            self._person_ll = lp - lp.max()
            person = self._log_pop_tau + self._person_ll
            prior = self._kern @ np.exp(person - person.max())
            self._log_prior_tau = np.log(np.maximum(prior, 1e-300))
            self._log_prior_tau -= self._log_prior_tau.max()
            self._pi = np.exp(self._log_prior_tau)
            self._pi /= self._pi.sum()
        self._start = (level, var)

    def update(self, t_s: float, watts: float) -> tuple[float, float]:
        """Fuse one breath.

        Args:
            t_s: Seconds since the setting began; finite, >= 0, strictly increasing. Gaps of
                any length are fine (the model is a function of t, not of breath count).
            watts: The breath's metabolic power in W.

        Returns:
            (mean of c in W, variance of c in W²) after this breath.

        Raises:
            MeasurementError: Bad ``t_s`` or ``watts``; the estimator is left unchanged.
            EstimatorError: The fit became non-finite; the estimator is left unchanged.
        """
        t = _finite(t_s, "t_s")
        if t < 0.0:
            raise MeasurementError(
                f"t_s={t_s!r} must be a finite, non-negative time since the setting began (s)"
            )
        if self._t and t <= self._t[-1]:
            raise MeasurementError(
                f"t_s={t_s!r} must be strictly after the previous measurement at t_s={self._t[-1]!r}"
            )
        z = _finite(watts, "watts")
        if not 0.0 < z <= self._config.max_watts:
            raise MeasurementError(
                f"watts={watts!r} at t_s={t_s!r} must be a finite power in "
                f"(0, {self._config.max_watts:g}] W"
            )
        snapshot = (self._cv2, self._m_ref, self._w, self._mean, self._var, self._level,
                    self._prior_c, self._pi, self._log_ev)
        self._t.append(t)
        self._y.append(z)
        try:
            self._fit()
        except (FloatingPointError, np.linalg.LinAlgError, EstimatorError) as err:
            self._t.pop()
            self._y.pop()
            (self._cv2, self._m_ref, self._w, self._mean, self._var, self._level,
             self._prior_c, self._pi, self._log_ev) = snapshot
            raise EstimatorError(f"transition fit at t_s={t!r} with watts={z!r} failed: {err}") from err
        return self._mean, self._var

    def state_dict(self) -> dict[str, Any]:
        """JSON-able snapshot: config, breaths, start level and the current estimate."""
        return {
            "config": asdict(self._config),
            "breaths": [[t, y] for t, y in zip(self._t, self._y, strict=True)],
            "start": None if self._start is None else list(self._start),
            "noise_cv": self.noise_cv,
            "mean": None if not self._t else self._mean,
            "var": None if not self._t else self._var,
        }

    # ------------------------------------------------------------------ the fit
    def _require_started(self) -> None:
        if not self._t:
            raise EstimatorError("no estimate before the first breath; call update() first")

    def _fit(self) -> None:
        cfg = self._config
        t = np.asarray(self._t)
        y = np.asarray(self._y)
        n = t.size
        if self._start is not None:
            b_mean, b_var = self._start
            ref = b_mean
            b_var = b_var + (cfg.start_inflation_rel * b_mean) ** 2
        else:
            ref = b_mean = float(y[0])
            b_var = (cfg.start_rel_sd * ref) ** 2
        c_mean, c_var = ref, (cfg.c_rel_sd * ref) ** 2
        self._prior_c = (c_mean, c_var)
        mu0 = np.array([c_mean, b_mean])
        lam0 = np.diag([1.0 / c_var, 1.0 / max(b_var, 1e-12 * ref**2)])
        eta0 = lam0 @ mu0

        # Design per τ: m = c·(1 − e) + b0·e, shape (G, n).
        e = np.exp(-t[None, :] / self._tau[:, None])
        h0, h1 = 1.0 - e, e
        # Warm start: last breath's levels and weights; the new breath at the last level.
        m_ref = np.empty(n)
        w = np.ones(n)
        k = self._m_ref.size
        m_ref[:k] = self._m_ref
        w[:k] = self._w
        m_ref[k:] = self._level[0] if k else b_mean
        m_ref = np.maximum(m_ref, cfg.min_level_w)
        nu, a, b = cfg.t_dof, self._a, self._b
        nu0, cv0_2 = cfg.noise_prior_breaths, self._noise_prior_cv**2
        cv2 = self._cv2
        for _ in range(cfg.irls_passes):
            # Precision of each breath: t weight / (sandwich factor · cv² · level²).
            u = w / (b * cv2 * m_ref**2)
            uy = u * y
            s00 = (h0 * h0) @ u
            s01 = (h0 * h1) @ u
            s11 = (h1 * h1) @ u
            r0 = h0 @ uy
            r1 = h1 @ uy
            l00 = lam0[0, 0] + s00
            l01 = lam0[0, 1] + s01
            l11 = lam0[1, 1] + s11
            det = l00 * l11 - l01 * l01
            if not np.all(det > 0.0):
                raise EstimatorError("posterior precision not positive definite")
            e0 = eta0[0] + r0
            e1 = eta0[1] + r1
            mc = (l11 * e0 - l01 * e1) / det
            mb = (l00 * e1 - l01 * e0) / det
            pcc = l11 / det
            pbb = l00 / det
            pcb = -l01 / det
            # log evidence per τ (terms shared by every τ dropped).
            quad = mc * e0 + mb * e1  # μᵀΛμ
            log_ev = 0.5 * quad - 0.5 * np.log(det)
            log_post = log_ev + self._log_prior_tau
            pi = np.exp(log_post - log_post.max())
            pi /= pi.sum()
            pred = pi @ (h0 * mc[:, None] + h1 * mb[:, None])  # mixture mean of m(t_i), (n,)
            m_ref = np.maximum(pred, cfg.min_level_w)
            zres = (y - pred) / m_ref
            # Effective parameters: trace of the hat matrix tr(Λ⁻¹A), mixed over τ.
            p_eff = float(pi @ (pcc * s00 + 2.0 * pcb * s01 + pbb * s11))
            n_eff = max(n - p_eff, 0.0)
            # EM of the t scale (σ_t² = a·cv²) with the scaled-inverse-χ² prior.
            w = (nu + 1.0) / (nu + zres**2 / (a * cv2))
            cv2 = (nu0 * cv0_2 + float(np.sum(w * zres**2)) / a) / (nu0 + n_eff)
            w = (nu + 1.0) / (nu + zres**2 / (a * cv2))
        # What this setting says about τ for the person (handover): the profile likelihood with
        # c free (no prior on c, and no log-det term). The marginal evidence would favour long
        # τ whenever the data say little (a long τ makes c's likelihood wider, so more of c's
        # broad prior fits): summed over many short, early-stopped settings, that drifted τ.
        det_f = s00 * l11 - l01 * l01
        e0_f = r0
        with np.errstate(divide="ignore", invalid="ignore"):
            quad_f = (l11 * e0_f**2 - 2.0 * l01 * e0_f * e1 + s00 * e1**2) / det_f
        quad_f = np.where(det_f > 0.0, quad_f, -np.inf)
        mean = float(pi @ mc)
        var = float(pi @ (pcc + mc**2)) - mean**2
        var = max(var, float(pi @ pcc) * 1e-9)
        dof = nu0 + n_eff
        var *= dof / (dof - 2.0)
        # Level at the last breath: m = c(1−e) + b e, mixed over τ.
        eh0, eh1 = h0[:, -1], h1[:, -1]
        lm = eh0 * mc + eh1 * mb
        lv = eh0**2 * pcc + 2.0 * eh0 * eh1 * pcb + eh1**2 * pbb
        level_mean = float(pi @ lm)
        level_var = (float(pi @ (lv + lm**2)) - level_mean**2) * dof / (dof - 2.0)
        if not all(math.isfinite(v) for v in (mean, var, level_mean, level_var, cv2)) or var <= 0.0:
            raise EstimatorError(f"non-finite estimate (mean {mean!r}, var {var!r})")
        self._cv2 = cv2
        self._pi = pi
        self._log_ev = 0.5 * (quad_f - quad_f.max()) if np.isfinite(quad_f).any() else np.zeros(cfg.n_tau)
        self._m_ref = m_ref
        self._w = w
        self._mean, self._var = mean, var
        self._level = (max(level_mean, cfg.min_level_w), max(level_var, 0.0))


def _finite(value: object, name: str) -> float:
    """A finite float, or MeasurementError naming the value."""
    try:
        v = float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError) as err:
        raise MeasurementError(f"{name}={value!r} is not a number") from err
    if not math.isfinite(v):
        raise MeasurementError(f"{name}={value!r} must be finite")
    return v
