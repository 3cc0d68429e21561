"""A breath-by-breath estimate of the steady-state cost whose variance describes its errors.

:class:`TransitionEstimator` is the default estimator of the optimizer. Per breath it makes a
small Bayesian fit of the first-order transition of one setting,

    m(t) = c + (b0 − c)·e^{−t/τ},   y_i = m(t_i)·(1 + ε_i),

where t is the time since the setting began, b0 the level the body is at when the setting begins
and c the steady-state cost wanted. It is the model of Kim et al. 2019 §II.C with c0 = b0 and
τ0 = τ (the body's level at the start *is* c0; one response time for both terms, as the lab's
first-order fit assumes). The steady state the optimizer wants is the setting's cost over the
whole bout, so the reported variance adds a model-error term for what the first-order model
leaves out (below).

Why a grid fit and not the UKF (:class:`~hilbo_core.metabolic.MetabolicUKF`, Kim et al. 2019,
kept selectable): for a fixed τ the model is linear in (c, b0), so the posterior of (c, b0)
given τ and the noise scale is an exact 2×2 Gaussian, and τ is one-dimensional, so its posterior
can be marginalised numerically on a grid. The UKF linearises the strongly non-linear trade-off
between c and τ early in a large transition (where the data cannot yet tell a large c reached
slowly from a smaller one reached quickly); there it was measured overconfident (z-score SD 3.3
after large steps). The grid mixture carries that trade-off into the reported variance.

* **τ has a physiological prior, wide enough for every person.** Log-normal, median 25 s,
  log-SD 0.4 (95 % of the prior in ≈ 11–55 s), on a log grid 5–200 s. The phase-II time
  constant of pulmonary VO2 in moderate exercise is ≈ 20–35 s in healthy adults, faster in the
  trained (≈ 10–20 s) and slower in the unfit, old or ill (40–60 s and more) (Poole & Jones 2012,
  "Oxygen uptake kinetics", Compr Physiol 2:933–996; Xu & Rhodes 1999, Sports Med 27:313–327;
  Whipp & Ward 1990, Med Sci Sports Exerc 22:62–71). A single exponential started at the change
  (no separate phase I / time delay, as here) fits an effective τ close to that range: on 156
  held-out real rest-to-exercise transitions its quartiles were 19 / 30 / 41 s, the median for
  walking 16 s. Selinger & Donelan 2014 (J Appl Physiol 117:1406–1415) measured ≈ 42 s for the
  whole metabolic response to a walking step, the long end, still inside the prior's 95 %. In the
  moderate domain the kinetics are linear (τ does not depend on the step's size, Whipp & Ward 1990;
  Poole & Jones 2012), so the same prior holds for the few-percent steps of an assistance change.
  τ is a trait of the person, so the settings of one person share it hierarchically: each
  setting's τ is the person's τ times e^δ, δ ~ N(0, 0.15²) (an assumed ≈ 15 % within-person
  variation between transitions, e.g. up- vs down-steps), and each setting hands on the
  accumulated likelihood of the person's τ (its data's τ evidence, convolved with that kernel).
  Settings too short to say anything about τ leave the prior at the population's.
* **No single breath can capture the fit.** Nothing is centred on one breath: without a
  starting level, b0's prior is centred on the median of the first five breaths and c's on the
  median of every breath so far; with one (:meth:`TransitionEstimator.start_from`, the previous
  setting's fitted level), both on it. The robust weights of every fit start from a running
  median of the breaths (five breaths wide), not from the previous fit, so a breath far from its
  neighbours gets a small weight from the first pass, wherever it sits in the setting, and a fit
  pulled once by a freak first breath is not carried on to the next.
* **Breaths implausible for the level are left out** (flagged and counted,
  :attr:`TransitionEstimator.n_flagged`): below 0.4× or above 2.2× the running median of their
  neighbours (before three breaths, of the starting level). Real breath-by-breath noise has a CV
  of ≈ 11 % with moderately heavy tails (kurtosis ≈ 4), so these are more than 5 SD off (a
  partial breath at a change, a swallow, a leak); the metabolic rate itself cannot move that
  far within two breaths (τ ≥ 10 s), and a monotone change, however fast, is its own running
  median, so real fast changes are never flagged.
* **A prior on c that is weak for any step:** N(centre, (3·centre)²). A session's largest steps
  (standing to walking, a warm-up) are 2–3× the level, rest to running 5–6×: at most ≈ 1.7 prior
  SDs. :meth:`TransitionEstimator.data_only` divides it out for the GP.
* **b0 starts from the body's level.** b0 ~ N(level, var + (0.05·level)²), the previous
  setting's fitted level at its last breath with its variance; the inflation is the body moving
  a little between that breath and this setting's start.
* **Robust, online breath noise.** ε_i is Student-t (ν = 4) with a relative scale (the CV)
  estimated from the breaths by iteratively reweighted least squares (the EM of the t model),
  with a scaled-inverse-χ² prior of median CV 11 % (the median steady-state CV of real breaths)
  and ν0 = 10 pseudo-breaths, so the first few breaths cannot collapse it. Breaths are treated as
  independent (the autocorrelation of real breaths is below 0.15 beyond 3 s, i.e. one breath).
* **A model-error term, so σ stops shrinking below what a real steady state allows.** The
  first-order model has a flat steady state; a real one is not flat: VO2 drifts by about ±1 %/min
  within a 6-minute bout (cardiovascular drift and the slow component: Poole & Jones 2012;
  Gaesser & Poole 1996, Exerc Sport Sci Rev 24:35–70; Coyle & González-Alonso 2001, Exerc Sport
  Sci Rev 29:88–92), and walking overshoots before it settles. On the held-out transitions even
  an oracle mean of the breaths at 120–180 s had a z-score SD of 2.1 against the bout's final
  level, and a model-error term of 3–4 % of the level made its σ hold there. A level drifting
  ≈ 1 %/min is ≈ 3 % away from where it was 3 minutes earlier (the time from a decision to the
  end of a bout), whatever the number of breaths, so c's reported variance is the fit's plus
  (model_error_rel·c)² with model_error_rel = 0.03. It is independent of the breath noise, so it
  goes to the GP as well (:meth:`TransitionEstimator.data_only`): it is an error of the
  observation of the setting's cost, not a prior.
* **The transition's shape is uncertain in time, so its steep part weighs less.** A single
  exponential started at the change is not the shape of a real transition: phase I (a fast
  cardiodynamic rise in the first ≈ 15–20 s) and the phase-II time delay (≈ 10–20 s, varying
  between people and between on- and off-transitions) put the real curve up to ≈ 10–20 s ahead of
  or behind the model (Whipp et al. 1982, J Appl Physiol 52:1506–1513; Whipp & Ward 1990;
  Özyener et al. 2001, J Physiol 533:891–902, time delays fitted for on- and off-transients alike),
  and a breath's gas exchange is time-stamped at its end (a breath lasts 2–3 s). An error δ in
  time moves the model at breath i by m'(t_i)·δ, so each breath's variance adds
  (timing_sd_s·m'(t_i))² (the effective-variance method for errors in the abscissa: Clutton-Brock
  1967, Technometrics 9:261–269; Orear 1982, Am J Phys 50:912–916), m' the mixture's slope from
  the previous reweighting pass (none in the first). With timing_sd_s = 10 s, where the curve is
  steep (early in a large step) the breaths say little about c, and a misfit of the transition's
  shape no longer drags c (the lab's practice of leaving phase I out of a kinetics fit, made
  gradual); on the plateau, and for the small steps of an assistance change, m' ≈ 0 and nothing
  changes. **It is on by default** (timing_sd_s = 10 s, with transition_error_rel 0.15 so that
  the phase-I misfit is not counted twice). Measured with ``hilbo bench estimator`` (docs/results.md)
  against the same estimator without it (timing_sd_s = 0, transition_error_rel 0.25): the 60-s
  error after the simulated wearer's steps to and from standing, which have a phase I, fell from
  9.7 to 7.6 % (its small steps 4.8 → 4.6 %), on the shared running recording from 8.6 to 7.4 %
  (60–180 s pooled 4.2 → 3.3 %); on the cycling recording it rose at 60 s (8.6 → 11.1 %, its
  down-steps, which start ≈ 15–20 s late) and fell at 90–120 s. In closed-loop sessions
  (``hilbo bench hil``, 100 subjects each of the realistic, noisy and slow wearers) the regret was
  level with and without it. It was off while the simulated wearer had no phase I: there it could
  only cost (30 of 40 subjects' final regret was higher, +1.4 W on average). Turn it off with
  ``TransitionConfig(timing_sd_s=0.0, transition_error_rel=0.25)``.
* **A transition-error term.** Early in a setting the single exponential also misses phase I
  (the first ≈ 15–20 s, Whipp & Ward 1990), overshoot and, in heavy exercise, the slow component
  (Poole & Jones 2012), all in proportion to the step: c's variance adds
  (transition_error_rel·|c − b0|·e^{−t/transition_error_s})², 0.15 and 60 s, mixed over τ: at
  60 s ≈ 5.5 % of the step, ≈ 0.7 % of the step at 3 minutes, and small for the small steps of an
  assistance change. The timing term above carries most of the phase-I misfit into the fit's own
  variance; without it this term alone must hold it, at 0.25 (≈ 9 % of the step at 60 s, sized
  on the steps of the shared running recording, whose 60-s estimates were up to 14 % off, mostly
  low).
  ``delays_s`` can marginalise a time delay as well (default none: on the shared recordings it
  helped the off-steps and cost the on-steps, whose phase I is a fast rise, not a delay; on the
  simulated wearer it raised the 60-s error from 4.5 to 5.4 %, and a delay for down-steps only,
  given the step's true direction, from 4.5 to 5.0 %).

The fit's variance of c is that of the τ mixture, with two corrections that make it describe
the errors rather than the model's conditional spread: a sandwich factor for the t weights (for
Gaussian breaths, IRLS-with-t-weights information understates the variance of the location by
a known factor, computed below by quadrature) and the Student-t inflation ν/(ν−2) for the
estimated CV (ν = ν0 + effective residual breaths).

Cost: every breath refits all breaths of the setting (n ≤ a few hundred) on a 33-point τ grid
with three reweighting passes, vectorised over the grid: ≈ 0.2 ms per breath at 200 breaths
(``hilbo bench perf`` times it inside the optimizer, with the stopping decision).
"""

from __future__ import annotations

import enum
import math
from dataclasses import asdict, dataclass, fields
from typing import Any

import numpy as np
import numpy.typing as npt
from scipy.ndimage import median_filter

from hilbo_core.errors import ConfigError, EstimatorError, MeasurementError
from hilbo_core.metabolic import divide_gaussian

__all__ = [
    "EstimatorKind",
    "StartState",
    "TransitionConfig",
    "TransitionEstimator",
]


_INTEGER_FIELDS = ("n_tau", "median_window", "start_breaths", "irls_passes")


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
    """Priors and numerics of :class:`TransitionEstimator` (sources in the module docstring).

    Attributes:
        tau_median_s: Median of the log-normal prior of τ in s (phase-II VO2 kinetics ≈ 20–35 s
            in moderate exercise, 16 s median in real walking transitions: 25 s).
        tau_log_sd: Its log-SD; 0.4 puts 95 % of the prior in ≈ 11–55 s.
        tau_min_s: Smallest τ of the grid in s.
        tau_max_s: Largest τ of the grid in s.
        n_tau: Grid points (log-spaced).
        delays_s: Time delays of the exponential in s (m(t) = b0 until the delay), marginalised
            with equal prior weights: phase I of the response lasts ≈ 15–20 s (module docstring).
        noise_cv: Prior median of the breath noise CV (median 11 % on real breaths).
        noise_prior_breaths: Weight ν0 of that prior in pseudo-breaths.
        t_dof: Degrees of freedom ν of the Student-t breath noise (4: heavy enough that a swallow
            at 5 SD gets about an eighth of an average breath's weight).
        c_rel_sd: Prior SD of c relative to its centre (weak for a 5× step; divided out for the GP).
        start_rel_sd: SD of b0 relative to its centre when no starting level is given.
        start_inflation_rel: Added SD of b0 relative to the starting level when one is given:
            the body moves a little between the previous setting's last breath and this
            setting's start (switching time, a breath or two).
        tau_person_log_sd: SD of a setting's log τ around the person's (within-person
            variation of τ, assumed ≈ 15 %).
        model_error_rel: SD of the model error of c relative to c (the steady state's drift
            and overshoot the first-order model leaves out, ≈ 3 %); added to c's variance.
        transition_error_rel: SD of the model error of c relative to the step |c − b0| at the
            start of a setting (the parts of a transition a single exponential misses: phase I,
            overshoot, a slow component), decaying as e^{−t/transition_error_s}.
        transition_error_s: That decay time in s.
        timing_sd_s: SD in s of the transition's timing against the model (phase I, the phase-II
            delay, breath time stamps): each breath's variance adds (timing_sd_s·m'(t))², m' the
            fitted slope (10 s, the default; 0 turns it off: module docstring).
        median_window: Breaths in the running median the robust weights start from (odd).
        implausible_low: A breath below this fraction of its running median is implausible for
            the level and left out of the fit (flagged, counted in :attr:`TransitionEstimator.n_flagged`).
        implausible_high: Likewise above this multiple of its running median.
        start_breaths: Breaths whose median centres b0 when no starting level is given.
        irls_passes: Reweighting passes per breath after the robust start.
        min_level_w: Floor in W on the level that scales the noise.
        max_watts: Breaths above this power in W are rejected as absurd.
    """

    tau_median_s: float = 25.0
    tau_log_sd: float = 0.4
    tau_min_s: float = 5.0
    tau_max_s: float = 200.0
    n_tau: int = 33
    delays_s: tuple[float, ...] = (0.0,)
    noise_cv: float = 0.11
    noise_prior_breaths: float = 10.0
    t_dof: float = 4.0
    c_rel_sd: float = 3.0
    start_rel_sd: float = 1.0
    start_inflation_rel: float = 0.05
    tau_person_log_sd: float = 0.15
    model_error_rel: float = 0.03
    transition_error_rel: float = 0.15
    transition_error_s: float = 60.0
    timing_sd_s: float = 10.0
    median_window: int = 5
    implausible_low: float = 0.4
    implausible_high: float = 2.2
    start_breaths: int = 5
    irls_passes: int = 3
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
            "model_error_rel": (0.0, 1.0),
            "transition_error_rel": (0.0, 10.0),
            "transition_error_s": (1.0, 3600.0),
            "timing_sd_s": (0.0, 120.0),
            "median_window": (1, 99),
            "implausible_low": (0.0, 1.0),
            "implausible_high": (1.0, 100.0),
            "start_breaths": (1, 100),
            "irls_passes": (1, 50),
            "min_level_w": (1e-3, 1e4),
            "max_watts": (1.0, 1e5),
        }
        d = self.delays_s
        if (not isinstance(d, tuple) or not 1 <= len(d) <= 10
                or not all(isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)
                           and 0.0 <= v <= 120.0 for v in d)):
            raise ConfigError(f"TransitionConfig.delays_s={d!r} must be a tuple of 1-10 delays in "
                              "[0, 120] s")
        for f in fields(self):
            if f.name == "delays_s":
                continue
            value = getattr(self, f.name)
            low, high = ranges[f.name]
            integer = f.name in _INTEGER_FIELDS
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
        if self.median_window % 2 == 0:
            raise ConfigError(f"TransitionConfig.median_window={self.median_window!r} must be odd")
        if not self.tau_min_s < self.tau_max_s:
            raise ConfigError(
                f"TransitionConfig.tau_min_s={self.tau_min_s!r} must be below "
                f"tau_max_s={self.tau_max_s!r}"
            )


class TransitionEstimator:
    """Bayesian fit of one setting's transition; the mean and variance of its steady state c.

    Create one per setting; call :meth:`start_from` before the first breath to start the
    transition from the level the previous setting left the body at (without it, b0 gets a
    weak prior centred on the median of the first five breaths). ``t_s`` is the time since the setting began.

    Args:
        config: Priors and numerics; ``TransitionConfig()`` when omitted.
    """

    def __init__(self, config: TransitionConfig | None = None) -> None:
        self._config = config if config is not None else TransitionConfig()
        cfg = self._config
        self._tau = np.geomspace(cfg.tau_min_s, cfg.tau_max_s, cfg.n_tau)
        self._n_delays = len(cfg.delays_s)
        self._tau_g = np.tile(self._tau, self._n_delays)
        self._delay_g = np.repeat(np.asarray(cfg.delays_s, dtype=float), cfg.n_tau)
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
        self._w: npt.NDArray[np.float64] = np.empty(0)
        self._mean = math.nan
        self._var = math.nan
        self._var_fit = math.nan
        self._n_flagged = 0
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
    def n_flagged(self) -> int:
        """Breaths of this setting now left out of the fit as implausible for the level.

        Re-decided at every breath (each breath is judged by its neighbours on both sides), so
        the count can go down as well as up; the breaths stay in :meth:`state_dict`.
        """
        return self._n_flagged

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

        The fit's posterior of c divided by its prior N(centre, (c_rel_sd·centre)²) (Gaussian
        division; :func:`~hilbo_core.metabolic.divide_gaussian`), plus the model-error variance
        (the steady state's drift is an error of this observation of the setting's cost, not a
        prior). The b0 prior stays in: it is what earlier breaths said about the starting level,
        not a prior on c.

        Raises:
            EstimatorError: No breath has been fused yet.
        """
        self._require_started()
        mean, var = divide_gaussian(self._mean, self._var_fit, *self._prior_c)
        return mean, var + self._model_error_var(mean)

    def model_error_var(self) -> float:
        """The model-error share of :meth:`data_only`'s variance, (model_error_rel·c)² in W²:
        the steady state's drift, which settings measured minutes apart share (the optimizer's
        ``drift_corr_s`` correlates it in time).

        Raises:
            EstimatorError: No breath has been fused yet.
        """
        self._require_started()
        mean, _ = divide_gaussian(self._mean, self._var_fit, *self._prior_c)
        return self._model_error_var(mean)

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
        snapshot = (self._cv2, self._w, self._mean, self._var, self._var_fit, self._level,
                    self._prior_c, self._pi, self._log_ev, self._n_flagged)
        self._t.append(t)
        self._y.append(z)
        try:
            self._fit()
        except (FloatingPointError, np.linalg.LinAlgError, EstimatorError) as err:
            self._t.pop()
            self._y.pop()
            (self._cv2, self._w, self._mean, self._var, self._var_fit, self._level,
             self._prior_c, self._pi, self._log_ev, self._n_flagged) = snapshot
            raise EstimatorError(f"transition fit at t_s={t!r} with watts={z!r} failed: {err}") from err
        return self._mean, self._var

    def state_dict(self) -> dict[str, Any]:
        """JSON-able snapshot: config, breaths, start level and the current estimate."""
        return {
            "config": asdict(self._config),
            "breaths": [[t, y] for t, y in zip(self._t, self._y, strict=True)],
            "start": None if self._start is None else list(self._start),
            "noise_cv": self.noise_cv,
            "n_flagged": self._n_flagged,
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
        # Priors centred on robust levels, never on one breath (module docstring).
        if self._start is not None:
            b_mean, b_var = self._start
            b_var = b_var + (cfg.start_inflation_rel * b_mean) ** 2
            c_mean = b_mean
        else:
            b_mean = float(np.median(y[: cfg.start_breaths]))
            b_var = (cfg.start_rel_sd * b_mean) ** 2
            c_mean = float(np.median(y))
        c_var = (cfg.c_rel_sd * c_mean) ** 2
        self._prior_c = (c_mean, c_var)
        lam_c = 1.0 / c_var
        lam_b = 1.0 / max(b_var, 1e-12 * b_mean**2)
        eta_c, eta_b = lam_c * c_mean, lam_b * b_mean

        # Design per τ: m = c·(1 − e) + b0·e, shape (G, n).
        # Grid g = (delay j, τ i), flattened j-major: G = n_delays·n_tau.
        e = np.exp(-np.maximum(t[None, :] - self._delay_g[:, None], 0.0) / self._tau_g[:, None])
        h0, h1 = 1.0 - e, e
        # Robust start: weights from the breaths' distance to their running median, so no
        # earlier fit (and no single breath) decides which breaths count.
        m_ref = np.maximum(_running_median(y, cfg.median_window), cfg.min_level_w)
        log_prior = np.tile(self._log_prior_tau, self._n_delays)
        nu, a, b = cfg.t_dof, self._a, self._b
        nu0, cv0_2 = cfg.noise_prior_breaths, self._noise_prior_cv**2
        cv2 = max(self._cv2, cv0_2)
        zres = (y - m_ref) / m_ref
        # Implausible for the level: a breath far outside its neighbours' median (or, before
        # three breaths, the starting level). A monotone change, however fast, is its own
        # running median (ratio 1), so real fast changes are never flagged; a flag is
        # re-decided at every breath, so a breath is judged by its neighbours on both sides.
        level_ref = m_ref if n >= 3 or self._start is None else np.full(n, b_mean)
        ratio = y / level_ref
        keep = (ratio >= cfg.implausible_low) & (ratio <= cfg.implausible_high)
        if not keep.any():
            keep[:] = True  # nothing to judge against: every breath is as plausible as any
        w = np.where(keep, (nu + 1.0) / (nu + zres**2 / (a * cv2)), 0.0)
        n_used = int(keep.sum())
        tim2 = np.zeros(n)  # timing error of each breath, relative variance (0 before a fit)
        for _ in range(cfg.irls_passes):
            # Precision of each breath: t weight / (sandwich factor · cv² · level²), the timing
            # error (σ_δ·dm/dt)² added as an effective variance.
            u = w / (b * (cv2 + tim2) * m_ref**2)
            uy = u * y
            s00 = (h0 * h0) @ u
            s01 = (h0 * h1) @ u
            s11 = (h1 * h1) @ u
            r0 = h0 @ uy
            r1 = h1 @ uy
            l00 = lam_c + s00
            l01 = s01
            l11 = lam_b + s11
            det = l00 * l11 - l01 * l01
            if not np.all(det > 0.0):
                raise EstimatorError("posterior precision not positive definite")
            e0 = eta_c + r0
            e1 = eta_b + r1
            mc = (l11 * e0 - l01 * e1) / det
            mb = (l00 * e1 - l01 * e0) / det
            pcc = l11 / det
            pbb = l00 / det
            pcb = -l01 / det
            # log evidence per τ (terms shared by every τ dropped).
            quad = mc * e0 + mb * e1  # μᵀΛμ
            log_ev = 0.5 * quad - 0.5 * np.log(det)
            log_post = log_ev + log_prior
            pi = np.exp(log_post - log_post.max())
            pi /= pi.sum()
            pred = pi @ (h0 * mc[:, None] + h1 * mb[:, None])  # mixture mean of m(t_i), (n,)
            m_ref = np.maximum(pred, cfg.min_level_w)
            zres = (y - pred) / m_ref
            if cfg.timing_sd_s > 0.0:
                # dm/dt = (c − b0)/τ·e^{−(t−d)/τ} after the delay d, 0 before; mixed over the grid.
                after = t[None, :] > self._delay_g[:, None]
                slope = pi @ (h1 * after * ((mc - mb) / self._tau_g)[:, None])
                tim2 = (cfg.timing_sd_s * slope / m_ref) ** 2
            # Effective parameters: trace of the hat matrix tr(Λ⁻¹A), mixed over τ.
            p_eff = float(pi @ (pcc * s00 + 2.0 * pcb * s01 + pbb * s11))
            n_eff = max(n_used - p_eff, 0.0)
            # EM of the t scale (σ_t² = a·cv²) with the scaled-inverse-χ² prior.
            zn2 = zres**2 * cv2 / (cv2 + tim2)  # residual² on the breath-noise scale
            w = np.where(keep, (nu + 1.0) / (nu + zn2 / (a * cv2)), 0.0)
            cv2 = (nu0 * cv0_2 + float(np.sum(w * zn2)) / a) / (nu0 + n_eff)
            w = np.where(keep, (nu + 1.0) / (nu + zres**2 / (a * (cv2 + tim2))), 0.0)
        # What this setting says about τ for the person (handover): the profile likelihood with
        # c free (no prior on c, and no log-det term). The marginal evidence would favour long
        # τ whenever the data say little (a long τ makes c's likelihood wider, so more of c's
        # broad prior fits): summed over many short, early-stopped settings, that drifted τ.
        det_f = s00 * l11 - l01 * l01
        with np.errstate(divide="ignore", invalid="ignore"):
            quad_f = (l11 * r0**2 - 2.0 * l01 * r0 * e1 + s00 * e1**2) / det_f
        quad_f = np.where(det_f > 0.0, quad_f, -np.inf)
        mean = float(pi @ mc)
        var = float(pi @ (pcc + mc**2)) - mean**2
        var = max(var, float(pi @ pcc) * 1e-9)
        dof = nu0 + n_eff
        var *= dof / (dof - 2.0)
        # The transition's model error: a fraction of the step, fading as the setting goes on.
        decay = math.exp(-t[-1] / cfg.transition_error_s)
        var += float(pi @ ((mc - mb) ** 2 + pcc + pbb)) * (cfg.transition_error_rel * decay) ** 2
        # Level at the last breath: m = c(1−e) + b e, mixed over τ.
        eh0, eh1 = h0[:, -1], h1[:, -1]
        lm = eh0 * mc + eh1 * mb
        lv = eh0**2 * pcc + 2.0 * eh0 * eh1 * pcb + eh1**2 * pbb
        level_mean = float(pi @ lm)
        level_var = (float(pi @ (lv + lm**2)) - level_mean**2) * dof / (dof - 2.0)
        if not all(math.isfinite(v) for v in (mean, var, level_mean, level_var, cv2)) or var <= 0.0:
            raise EstimatorError(f"non-finite estimate (mean {mean!r}, var {var!r})")
        self._cv2 = cv2
        self._pi = pi.reshape(self._n_delays, cfg.n_tau).sum(axis=0)
        if np.isfinite(quad_f).any():
            # τ's evidence for the person: the delays summed out (log-sum-exp).
            lf = 0.5 * (quad_f - quad_f.max()).reshape(self._n_delays, cfg.n_tau)
            lmax = lf.max(axis=0)
            ok = np.isfinite(lmax)
            ev = np.full(cfg.n_tau, -np.inf)
            ev[ok] = lmax[ok] + np.log(np.exp(lf[:, ok] - lmax[ok]).sum(axis=0))
            self._log_ev = np.maximum(ev - ev.max(), -700.0)
        else:
            self._log_ev = np.zeros(cfg.n_tau)
        self._w = w
        self._n_flagged = n - n_used
        self._mean, self._var_fit = mean, var
        self._var = var + self._model_error_var(mean)
        self._level = (max(level_mean, cfg.min_level_w), max(level_var, 0.0))

    def _model_error_var(self, mean: float) -> float:
        """(model_error_rel·c)² in W²: the steady state's drift the model leaves out."""
        cfg = self._config
        return (cfg.model_error_rel * max(abs(mean), cfg.min_level_w)) ** 2


def _running_median(y: npt.NDArray[np.float64], window: int) -> npt.NDArray[np.float64]:
    """Running median of ``window`` breaths (mirrored at the ends), shape (n,) like ``y``.

    Mirroring, not repeating, the end breaths: a freak first or last breath is outvoted by its
    neighbours instead of being copied into its own window.
    """
    n = y.size
    if n < 3 or window < 3:
        return np.full(n, float(np.median(y))) if window >= 3 else y.copy()
    return np.asarray(median_filter(y, size=min(window, 2 * n - 1), mode="mirror"), dtype=float)


def _finite(value: object, name: str) -> float:
    """A finite float, or MeasurementError naming the value."""
    try:
        v = float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError) as err:
        raise MeasurementError(f"{name}={value!r} is not a number") from err
    if not math.isfinite(v):
        raise MeasurementError(f"{name}={value!r} must be finite")
    return v
