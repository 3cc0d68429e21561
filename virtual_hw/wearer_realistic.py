"""A simulated wearer that breathes like a person: the default of ``hilbo sim``.

A pure model, like :class:`virtual_hw.wearer.SimulatedWearer` (the ``legacy`` wearer, kept as a
named option) and with the same interface: the caller owns the clock, reports what the exosuit
applies and when (:meth:`RealisticWearer.apply_profiles`) and pulls breaths
(:meth:`RealisticWearer.next_breath`, :meth:`RealisticWearer.breaths_until`). What differs is what
real breath-by-breath data look like, and that the landscape is not always the same shape.

Sources: "the real recordings" are a measurement made for this project of 156 real walking/running
transitions of 24 people (breath-by-breath, resampled at 2-3.5 s); the rest are cited where they are used.

Landscape families (drawn per subject seed)
===========================================
The steady-state cost is a function of the force tables the exosuit *applies* (a lost or zeroed
profile shows in the metabolic data as in a lab), ``cost = unassisted · (1 - Σ_a β_a·S(φ_a))``
with the saturation ``S`` of the legacy wearer (:func:`~virtual_hw.wearer.saturate_penalty`), so
no assistance costs exactly the unassisted power. The score ``φ_a`` of one actuator's table comes
from one of two families, chosen per subject with probability ``p_bumps`` so that nothing is tuned
to one shape:

* :attr:`LandscapeFamily.WINDOW` — the legacy wearer's model: a Gaussian timing window per
  actuator, ``φ`` a concave quadratic in the force table (one optimum, curvature set by the
  window's width; :func:`~virtual_hw.wearer.assistance_score`).
* :attr:`LandscapeFamily.BUMPS` — a sum of anisotropic bumps over smooth moments of the table
  (:func:`profile_moments`): its force-weighted timing centroid ``μ`` (%GC), its force-weighted
  spread ``σ`` (%GC, a duration) and its effective force ``q = ∫f²/∫f`` (N)::

      φ = Σ_k a_k·G_k(μ, σ)·m(q / F_k) - λ·min(q / F_1, 2)·(1 - max_k G_k)

  ``G_k`` a correlated (rotated) 2-D Gaussian in (μ, σ), ``m(r) = r·e^{1-r}`` (0 without force,
  1 at the bump's ideal effective force ``F_k``, a gentle decline above it rather than the
  window's quadratic), a primary bump (``a_1 = 1``) and a weaker secondary bump 7-12 %GC (hip; ankle 4-7 %GC)
  earlier or later, so there are two local optima, the best one may sit on a force bound (``F_1`` can
  exceed the largest force the space allows), and timing and duration trade off along a tilted
  ridge (the correlation). The last term is the cost of force at the wrong time (as the window
  family's negative scores; Kim et al. 2019's generic profile cost one subject 4 %). The bump priors
  are placed inside the range the presets' tables reach (hip centroid 17-38 %GC, spread 5-12 %GC;
  ankle centroid 52-62 %GC) around the hip-extension and push-off timings of Kim et al. 2019's Table II
  and Fig. 4, and ``β`` is drawn so the best saving is 5-25 % of unassisted walking, the range the
  project specifies (Kim et al. 2019 report 7-35 %; hip-exosuit reports are mostly 5-20 %). Over
  seeds 0-39 (both families): best saving 9.4-20.7 % in ``hip_6d``, 7.4-24.4 % in
  ``hip_ankle_4d``; 23 window and 17 bump subjects.

Dynamics
========
First-order dynamics of the *actual* metabolic rate (Selinger & Donelan 2014, Kim et al. 2019 ref. [20];
Kim et al. 2019 §II.C): ``dm/dt = (c(t) - m)/τ``. The state ``m`` is carried across every change of the
applied assistance, so a new setting's transition starts from wherever the body is when it begins
(on the real recordings transitions of more than 50 % are common), never from a reset. ``τ`` is drawn per
person log-uniformly in 14-55 s (median ≈ 28 s). The phase-II time constant of VO2 in moderate
exercise is ≈ 20-35 s in healthy adults, faster in the trained and slower in the unfit (Poole &
Jones 2012, "Oxygen uptake kinetics", Compr Physiol 2:933-996; Xu & Rhodes 1999, Sports Med
27:313-327); a single exponential fitted from the change on real transitions gave quartiles of
19 / 30 / 41 s and a median of 16 s for walking (the project's held-out measurement of 156
transitions); Selinger & Donelan 2014 report ≈ 42 s for the whole response to a walking step.
(The range was 30-60 s before: slower than most people.)

**Drift.** A real steady state is not flat: it drifts by about ±1 %/min within a 6-minute bout
(the held-out measurement; cardiovascular drift and, above the lactate threshold, the slow
component: Poole & Jones 2012; Coyle & González-Alonso 2001, Exerc Sport Sci Rev 29:88-92). The
rate is the first-order solution times ``1 + d(t)``, ``d(t) = s·√(2/6)·Σ_k sin(2π t/P_k + φ_k)``
over six sinusoids: ``s`` per person in 1.5-3.5 % of the level (the stationary SD of d),
periods ``P_k`` log-uniform in 6-30 min and phases uniform per person. Over subjects 0-39 its RMS
rate of change is 0.6-2.7 %/min (median 1.3) and its change over 3 minutes has a median SD of
3.3 %: the size of the model error that made the breath estimate's σ hold on the held-out
transitions (3-4 %; at 1-2.5 % the wearer was gentler than people and the estimate looked
over-cautious on it). It is smooth and deterministic per subject (``metabolic_rate_w`` stays a
function of time), continuous across changes (it is the body, not the setting), and not part of
the truth: ``true_cost_w`` is the landscape, and the drift is an error every evaluation has.

**First breaths.** The first breath after a change of the applied assistance is, with a
per-person probability of 0-10 %, a partial breath at 20-60 % of the level (on real data: a run
whose first breaths were 43-56 W for a level of 789 W, in the held-out measurement; the first
breath of the first run of the shared ZAN recording, 92 W after standing at ≈ 195 W).
The probability and factor range are model choices; the draws come from a stream of their own,
so every other breath is what it was without them.

**Standing.** :meth:`RealisticWearer.stand` stops the walking: the rate relaxes, with the
person's τ, to ``standing_w_per_kg`` × body mass (1.5 W/kg: quiet standing is 1.3 MET in the
Compendium of Physical Activities, Ainsworth et al. 2011, Med Sci Sports Exerc 43:1575, code
07040, and 1 MET ≈ 3.5 ml O2/kg/min ≈ 1.17 W/kg), and the next setting walks from there: the
large steps (≈ 3-4× up, as a rest-to-walking transition, and down) of the recordings' rests and
starts, which assistance changes never make. The standing level adapts like every level (at most
3 %, a simplification).

**Phase I.** A step from or to standing is not first-order. At the onset of exercise from rest
the pulmonary VO2 first rises fast, for ≈ 15-20 s, as pulmonary blood flow rises with cardiac
output (the cardiodynamic phase I), and only then follows the muscles' exponential (phase II,
delayed by phase I's duration); from a raised baseline (one walking setting to the next) phase I
is smaller (Whipp et al. 1982, J Appl Physiol 52:1506-1513; Poole & Jones 2012). The
wearer's transitions to and from standing have one: per person a duration ``δ`` in 12-22 s and
a share of the step in 10-30 % (``phase1_s``, ``phase1_share``: the share is a model choice)
covered within ``δ`` (time constant ``δ/4``), the rest following the person's ``τ`` from ``δ``
on; changes between walking settings stay first-order. A single exponential fitted from the
change misses the shape, as it does on people (on the shared ZAN recording the transition
estimator's 60-s coverage is 78 %); before, the wearer's large steps were exactly first-order
and the estimator's σ for them looked over-cautious.

**Slow adaptation.** The steady-state cost of every setting (unassisted walking included) falls
with time on the breath clock, ``c(x, t) = c(x)·D(t)``,
``D(t) = 1 - α·(1 - e^{-t/T}) / (1 - e^{-3600/T})``: by exactly ``α`` after one hour, fastest at
first. ``α`` is drawn per person in 0-3 % (continued reductions of metabolic cost over
sessions with the same assistance are reported by the Collins lab: Poggensee & Collins 2021,
Sci. Robot. 6:eabf1078, and Slade et al. 2022, Nature 610:277), ``T`` in 15-40 min (a model
choice: most of the change within the session). The ODE with this target has a closed form
(:meth:`RealisticWearer.metabolic_rate_w`), continuous at every change.

**Truth and regret.** ``true_cost_w(params)``, :attr:`RealisticWearer.true_optimum` and
:attr:`RealisticWearer.baseline_cost_w` are the *unadapted* landscape (``D = 1``, time 0);
``true_cost_w(params, t_s)`` is the adapted cost at breath-clock time ``t_s`` (=
``true_cost_w(params)·adaptation_factor(t_s)``). Because adaptation scales every setting by the
same factor the optimum's location never moves and regret as a % of the available reduction is
the same at every time; the regret in W of every summary (``hilbo sim``, ``hilbo bench hil``) is
the unadapted one, and ``hilbo sim`` adds ``regret_w_at_end`` (× ``D`` at the session's end).

Breaths
=======
* Intervals: gamma with a per-person mean in 2.0-3.5 s (17-30 breaths/min, the usual breathing
  rate in walking; the real recordings were resampled at 2-3.5 s) and a per-person jitter CV of
  10-20 %, each interval clipped to [0.5, 2] × the person's mean.
* Noise: ``P = m(t)·(1 + e)``. The core ``e`` is AR(1) with a per-person stationary SD of
  8-12 % of the level and a per-person lag-one correlation of 0-0.12 (the real recordings: median
  coefficient of variation of about 11 %, autocorrelation below 0.15 beyond 3 s; at ≥ 2 s per
  breath the correlation at two breaths is ≤ 0.02).
* Outliers (swallows, coughs, talking; the real recordings have some): each breath is,
  with a per-person probability of 1-4 %, off by an extra ``outlier_scale·t_3`` (Student t, 3 degrees
  of freedom: heavy-tailed), the breath's factor clipped to [0.2, 3]. The share and the width are
  model choices (no published distribution); they lift the raw CV of a steady state by about
  0.5-2.5 points above the core CV (measured over 8 subjects), to about the 11 % median of the
  real data.
* RER, VO2/VCO2 (Brockway), VE and HR as the legacy wearer (its module docstring), so
  ``BreathRecord.watts`` is exactly ``P``.

Determinism: the same seed and config give the same subject, landscape family and, for the same
calls, the same breaths (``np.random.default_rng`` on four spawned streams: subject, breaths,
optimum search and the first-breath draws); every breath draws the same numbers whatever happens.
"""

from __future__ import annotations

import enum
import math
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass
from functools import cached_property
from typing import Any

import numpy as np

from hilbo_core.errors import ConfigError, MeasurementError
from hilbo_core.profiles import ForceProfile, build_profile
from hilbo_core.space import ParameterSpace
from hilbo_core.types import BreathRecord
from virtual_hw.wearer_common import (
    _BROCKWAY_CO2,
    _BROCKWAY_O2,
    _G,
    _MAX_BREATHS_PER_CALL,
    _RER_LIMITS,
    _S_PER_MIN,
    ANKLE_PRIOR,
    HIP_PRIOR,
    ActuatorPrior,
    AssistWindow,
    _check_range,
    _check_value,
    assistance_score,
    check_profiles,
    check_subject_args,
    check_time,
    find_optimum,
    saturate_penalty,
)

__all__ = [
    "ANKLE_BUMPS",
    "ANKLE_WINDOW",
    "HIP_BUMPS",
    "Bump",
    "BumpLandscape",
    "BumpPrior",
    "LandscapeFamily",
    "RealisticWearer",
    "RealisticWearerConfig",
    "adaptation_factor",
    "bump_score",
    "profile_moments",
]

_ONE_HOUR_S = 3600.0
# A breath's factor (1 + e) is kept in this range: a freak draw can never make a negative gas
# exchange, and an outlier stays "a few times the level" at most (a cough, not a sensor fault).
_FACTOR_LIMITS = (0.2, 3.0)
_OUTLIER_DF = 3.0  # Student t degrees of freedom of the outliers: heavy tails, finite variance
_INTERVAL_CLIP = (0.5, 2.0)  # each breath interval within these multiples of the person's mean
_N_DRIFT = 6  # sinusoids of the steady state's drift (module docstring, "Drift")


class LandscapeFamily(enum.Enum):
    """The shape of a subject's metabolic landscape (module docstring)."""

    WINDOW = "window"
    BUMPS = "bumps"


# ---------------------------------------------------------------------------- pure functions
def profile_moments(gait_pct: np.ndarray, force_n: np.ndarray) -> tuple[float, float, float]:
    """Smooth moments of a force table: its force-weighted timing centroid, spread and force.

    Args:
        gait_pct: Gait-cycle positions in %, shape (n,), increasing.
        force_n: Force in N, shape (n,); negative values are clipped to 0.

    Returns:
        ``(centroid_pct, spread_pct, effective_force_n)``: ``∫g f / ∫f``, the force-weighted SD
        of ``g`` and ``∫f² / ∫f`` (trapezoidal integrals); ``(0, 0, 0)`` for a zero table.
    """
    g = np.asarray(gait_pct, dtype=float)
    f = np.clip(np.asarray(force_n, dtype=float), 0.0, None)
    impulse = float(np.trapezoid(f, g))
    if impulse <= 0.0:
        return 0.0, 0.0, 0.0
    mu = float(np.trapezoid(g * f, g)) / impulse
    var = float(np.trapezoid((g - mu) ** 2 * f, g)) / impulse
    q = float(np.trapezoid(f * f, g)) / impulse
    return mu, math.sqrt(max(var, 0.0)), q


def adaptation_factor(t_s: float, adaptation_frac: float, adaptation_tau_s: float) -> float:
    """``D(t) = 1 - α·(1 - e^{-t/T}) / (1 - e^{-3600/T})``: the cost multiplier after ``t_s`` s.

    ``D(0) = 1`` and ``D(3600 s) = 1 - α`` exactly (module docstring, "Slow adaptation").
    """
    k = -math.expm1(-_ONE_HOUR_S / adaptation_tau_s)
    return 1.0 + adaptation_frac * math.expm1(-t_s / adaptation_tau_s) / k


@dataclass(frozen=True)
class Bump:
    """One anisotropic bump of a :class:`BumpLandscape`.

    Attributes:
        centre_pct: Centre of the timing centroid ``μ``, %GC.
        spread_pct: Centre of the spread ``σ``, %GC.
        centre_sd_pct: The bump's SD along ``μ``, %GC.
        spread_sd_pct: The bump's SD along ``σ``, %GC.
        correlation: Correlation of the bump's (μ, σ) Gaussian, in (-1, 1): the tilt of the ridge.
        amplitude: ``a_k`` (1 for the primary bump).
        ideal_force_n: ``F_k``, the effective force ``∫f²/∫f`` this bump rewards most, N.
    """

    centre_pct: float
    spread_pct: float
    centre_sd_pct: float
    spread_sd_pct: float
    correlation: float
    amplitude: float
    ideal_force_n: float

    def weight(self, mu: float, sigma: float) -> float:
        """``G_k(μ, σ)`` in (0, 1], 1 at the centre."""
        x = (mu - self.centre_pct) / self.centre_sd_pct
        y = (sigma - self.spread_pct) / self.spread_sd_pct
        r = self.correlation
        return math.exp(-0.5 * (x * x - 2.0 * r * x * y + y * y) / (1.0 - r * r))


@dataclass(frozen=True)
class BumpLandscape:
    """One subject's bump landscape for one actuator (drawn from a :class:`BumpPrior`).

    Attributes:
        actuator: Load path name.
        bumps: The primary bump first.
        max_benefit_frac: β, the largest fractional saving of the unassisted cost.
        mistiming_penalty: λ, the cost of force away from every bump (in units of β).
    """

    actuator: str
    bumps: tuple[Bump, ...]
    max_benefit_frac: float
    mistiming_penalty: float


def bump_score(gait_pct: np.ndarray, force_n: np.ndarray, landscape: BumpLandscape) -> float:
    """``φ`` of a force table under a bump landscape (module docstring; 0 for no force)."""
    mu, sigma, q = profile_moments(gait_pct, force_n)
    if q <= 0.0:
        return 0.0
    score = 0.0
    g_max = 0.0
    for b in landscape.bumps:
        gk = b.weight(mu, sigma)
        r = q / b.ideal_force_n
        score += b.amplitude * gk * r * math.exp(1.0 - r)
        g_max = max(g_max, gk)
    r1 = q / landscape.bumps[0].ideal_force_n
    return score - landscape.mistiming_penalty * min(r1, 2.0) * (1.0 - g_max)


# ---------------------------------------------------------------------------- configuration
@dataclass(frozen=True)
class BumpPrior:
    """Population ranges of one actuator's bump landscape (drawn uniformly per subject).

    Attributes:
        actuator: The load path (``"hip"``, ``"ankle"``).
        centre_pct: Range of the primary bump's timing centroid, %GC.
        spread_pct: Range of the bumps' spread centre, %GC.
        centre_sd_pct: Range of a bump's SD along the centroid, %GC.
        spread_sd_pct: Range of a bump's SD along the spread, %GC.
        correlation: Range of a bump's (μ, σ) correlation.
        ideal_force_bw: Range of a bump's ideal effective force, fraction of body weight.
        max_benefit_frac: Range of β.
        second_offset_pct: Range of the secondary bump's distance from the primary (%GC; the side
            is drawn too).
        second_amplitude: Range of the secondary bump's amplitude.
        mistiming_penalty: Range of λ.
    """

    actuator: str
    centre_pct: tuple[float, float]
    spread_pct: tuple[float, float]
    centre_sd_pct: tuple[float, float]
    spread_sd_pct: tuple[float, float]
    correlation: tuple[float, float]
    ideal_force_bw: tuple[float, float]
    max_benefit_frac: tuple[float, float]
    second_offset_pct: tuple[float, float]
    second_amplitude: tuple[float, float]
    mistiming_penalty: tuple[float, float]

    def __post_init__(self) -> None:
        o = f"BumpPrior({self.actuator!r})"
        if not isinstance(self.actuator, str) or not self.actuator:
            raise ConfigError(f"BumpPrior.actuator={self.actuator!r} must be a non-empty name")
        _check_range(o, "centre_pct", self.centre_pct, 0.0, 100.0)
        _check_range(o, "spread_pct", self.spread_pct, 0.5, 50.0)
        _check_range(o, "centre_sd_pct", self.centre_sd_pct, 0.5, 50.0)
        _check_range(o, "spread_sd_pct", self.spread_sd_pct, 0.2, 50.0)
        _check_range(o, "correlation", self.correlation, -0.9, 0.9)
        _check_range(o, "ideal_force_bw", self.ideal_force_bw, 1e-3, 5.0)
        _check_range(o, "max_benefit_frac", self.max_benefit_frac, 0.0, 0.6)
        _check_range(o, "second_offset_pct", self.second_offset_pct, 0.0, 50.0)
        _check_range(o, "second_amplitude", self.second_amplitude, 0.0, 1.0)
        _check_range(o, "mistiming_penalty", self.mistiming_penalty, 0.0, 2.0)


# Hip: hip-extension assistance peaking at 21-27 %GC (Kim et al. 2019 Table II, Fig. 4) has its
# force centroid at about 22-32 %GC for the presets' tables; ideal effective forces 0.12-0.30 BW
# (the hip_6d tables reach 0.05-0.27 BW, so the best force is sometimes the largest allowed).
HIP_BUMPS = BumpPrior("hip", centre_pct=(22.0, 32.0), spread_pct=(6.0, 10.0),
                      centre_sd_pct=(3.0, 6.0), spread_sd_pct=(1.5, 3.5), correlation=(-0.6, 0.6),
                      ideal_force_bw=(0.12, 0.30), max_benefit_frac=(0.07, 0.19),
                      second_offset_pct=(7.0, 12.0), second_amplitude=(0.4, 0.8),
                      mistiming_penalty=(0.1, 0.3))
# Ankle: plantarflexion around push-off (52-62 %GC_HS, Table II's optimal ankle peaks 56-60 %);
# the hip_ankle_4d ankle table's effective force is ≈ 0.48 BW.
ANKLE_BUMPS = BumpPrior("ankle", centre_pct=(54.0, 60.0), spread_pct=(7.0, 10.0),
                        centre_sd_pct=(2.0, 4.0), spread_sd_pct=(1.0, 2.5), correlation=(-0.6, 0.6),
                        ideal_force_bw=(0.35, 0.70), max_benefit_frac=(0.03, 0.07),
                        second_offset_pct=(4.0, 7.0), second_amplitude=(0.4, 0.8),
                        mistiming_penalty=(0.1, 0.3))

# The window family's ankle: the legacy ANKLE_PRIOR with β at most 9 % instead of 10 %, so that with
# the hip the best hip_ankle_4d saving stays within the project's 5-25 % (25.3 % for one of 40
# subjects with 10 %).
ANKLE_WINDOW = ActuatorPrior("ankle", ANKLE_PRIOR.centre_pct, ANKLE_PRIOR.width_pct,
                             ANKLE_PRIOR.ideal_force_bw, (0.05, 0.09))


@dataclass(frozen=True)
class RealisticWearerConfig:
    """Population constants of the realistic wearer (sources in the module docstring).

    Pairs are ``(low, high)`` ranges drawn uniformly per subject (``tau_s`` and
    ``drift_period_s`` log-uniformly); equal ends fix the value.

    Raises:
        ConfigError: A value outside its physiological or numerical range, naming the field.
    """

    gross_cost_w_per_kg: tuple[float, float] = (4.7, 5.8)
    tau_s: tuple[float, float] = (14.0, 55.0)
    breath_interval_s: tuple[float, float] = (2.0, 3.5)
    breath_interval_cv: tuple[float, float] = (0.10, 0.20)
    noise_cv: tuple[float, float] = (0.08, 0.12)
    noise_ar1: tuple[float, float] = (0.0, 0.12)
    outlier_frac: tuple[float, float] = (0.01, 0.04)
    outlier_scale: float = 0.3
    adaptation_frac: tuple[float, float] = (0.0, 0.03)
    adaptation_tau_s: tuple[float, float] = (900.0, 2400.0)
    drift_sd: tuple[float, float] = (0.015, 0.035)
    drift_period_s: tuple[float, float] = (360.0, 1800.0)
    first_breath_p: tuple[float, float] = (0.0, 0.1)
    first_breath_factor: tuple[float, float] = (0.2, 0.6)
    phase1_s: tuple[float, float] = (12.0, 22.0)
    phase1_share: tuple[float, float] = (0.1, 0.3)
    p_bumps: float = 0.5
    rer: tuple[float, float] = (0.85, 0.90)
    rer_sd: float = 0.02
    ve_per_vco2: float = 28.0
    report_ve: bool = True
    report_hr: bool = True
    hr_rest_bpm: tuple[float, float] = (60.0, 75.0)
    hr_gain_bpm_per_w: float = 0.15
    resting_w_per_kg: float = 1.3
    standing_w_per_kg: float = 1.5
    hr_sd_bpm: float = 2.0
    windows: tuple[ActuatorPrior, ...] = (HIP_PRIOR, ANKLE_WINDOW)
    bumps: tuple[BumpPrior, ...] = (HIP_BUMPS, ANKLE_BUMPS)
    penalty_cap: float = 0.5
    n_optimum_candidates: int = 128
    n_optimum_starts: int = 2

    def __post_init__(self) -> None:
        o = "RealisticWearerConfig"
        _check_range(o, "gross_cost_w_per_kg", self.gross_cost_w_per_kg, 1.5, 15.0)
        _check_range(o, "tau_s", self.tau_s, 1.0, 600.0)
        _check_range(o, "breath_interval_s", self.breath_interval_s, 0.5, 20.0)
        _check_range(o, "breath_interval_cv", self.breath_interval_cv, 0.0, 0.5)
        _check_range(o, "noise_cv", self.noise_cv, 0.0, 0.5)
        _check_range(o, "noise_ar1", self.noise_ar1, 0.0, 0.95)
        _check_range(o, "outlier_frac", self.outlier_frac, 0.0, 0.5)
        _check_value(o, "outlier_scale", self.outlier_scale, 0.0, 2.0)
        _check_range(o, "adaptation_frac", self.adaptation_frac, 0.0, 0.3)
        # T must stay far from τ: the closed-form transition divides by 1 - τ/T.
        _check_range(o, "adaptation_tau_s", self.adaptation_tau_s, 10.0 * self.tau_s[1], 1e6)
        _check_range(o, "drift_sd", self.drift_sd, 0.0, 0.2)
        _check_range(o, "drift_period_s", self.drift_period_s, 10.0, 1e5)
        _check_range(o, "first_breath_p", self.first_breath_p, 0.0, 1.0)
        _check_range(o, "first_breath_factor", self.first_breath_factor, 0.05, 1.0)
        _check_range(o, "phase1_s", self.phase1_s, 0.0, 60.0)
        _check_range(o, "phase1_share", self.phase1_share, 0.0, 0.9)
        _check_value(o, "p_bumps", self.p_bumps, 0.0, 1.0)
        _check_range(o, "rer", self.rer, _RER_LIMITS[0], _RER_LIMITS[1])
        _check_value(o, "rer_sd", self.rer_sd, 0.0, 0.2)
        _check_value(o, "ve_per_vco2", self.ve_per_vco2, 10.0, 60.0)
        _check_range(o, "hr_rest_bpm", self.hr_rest_bpm, 30.0, 120.0)
        _check_value(o, "hr_gain_bpm_per_w", self.hr_gain_bpm_per_w, 0.0, 2.0)
        _check_value(o, "resting_w_per_kg", self.resting_w_per_kg, 0.5, 3.0)
        _check_value(o, "standing_w_per_kg", self.standing_w_per_kg, 0.5, 3.0)
        _check_value(o, "hr_sd_bpm", self.hr_sd_bpm, 0.0, 30.0)
        _check_value(o, "penalty_cap", self.penalty_cap, 1e-3, 5.0)
        for name in ("report_ve", "report_hr"):
            if not isinstance(getattr(self, name), bool):
                raise ConfigError(f"{o}.{name}={getattr(self, name)!r} must be True or False")
        for name, lo in (("n_optimum_candidates", 8), ("n_optimum_starts", 1)):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or not lo <= v <= 100_000:
                raise ConfigError(f"{o}.{name}={v!r} must be an integer in [{lo}, 100000]")
        for name, kind in (("windows", ActuatorPrior), ("bumps", BumpPrior)):
            priors = tuple(getattr(self, name))
            if not all(isinstance(p, kind) for p in priors):
                raise ConfigError(f"{o}.{name} must hold {kind.__name__} values, got {priors!r}")
            names = [p.actuator for p in priors]
            if len(set(names)) != len(names):
                raise ConfigError(f"{o}.{name} has duplicate actuator names: {names}")
            object.__setattr__(self, name, priors)
        if {p.actuator for p in self.windows} != {p.actuator for p in self.bumps}:
            raise ConfigError(f"{o}: windows and bumps must cover the same actuators, got "
                              f"{sorted(p.actuator for p in self.windows)} and "
                              f"{sorted(p.actuator for p in self.bumps)}")

    @classmethod
    def noiseless(cls, **overrides: Any) -> RealisticWearerConfig:
        """The default population without breath noise, outliers, adaptation, drift, odd first
        breaths or phase I (intervals stay irregular): every breath reports exactly the
        first-order rate ``m(t)``."""
        base: dict[str, Any] = {"noise_cv": (0.0, 0.0), "outlier_frac": (0.0, 0.0),
                                "adaptation_frac": (0.0, 0.0), "rer_sd": 0.0, "hr_sd_bpm": 0.0,
                                "drift_sd": (0.0, 0.0), "first_breath_p": (0.0, 0.0),
                                "phase1_s": (0.0, 0.0)}
        base.update(overrides)
        return cls(**base)


# ---------------------------------------------------------------------------- the wearer
class RealisticWearer:
    """A seeded simulated subject that breathes like a person (see the module docstring).

    Same interface as :class:`virtual_hw.wearer.SimulatedWearer`, plus the landscape family,
    the adaptation (:meth:`adaptation_factor`, ``true_cost_w(params, t_s)``) and the outliers.

    Args:
        space: The parameter space (``space.name`` must name a builder in
            ``hilbo_core.profiles.PROFILE_BUILDERS``).
        seed: Non-negative integer; fixes the subject, its landscape family and breath stream.
        config: Population constants; ``RealisticWearerConfig()`` when omitted.
        body_mass_kg: The subject's mass in kg.

    Raises:
        ConfigError: Unknown space builder, bad seed, body mass or config.
    """

    def __init__(self, space: ParameterSpace, seed: int, config: RealisticWearerConfig | None = None,
                 body_mass_kg: float = 75.0) -> None:
        check_subject_args(space, seed, body_mass_kg)
        cfg = RealisticWearerConfig() if config is None else config
        if not isinstance(cfg, RealisticWearerConfig):
            raise ConfigError(f"config must be a RealisticWearerConfig, got {type(cfg).__name__}")
        self.space = space
        self.seed = int(seed)
        self.config = cfg
        self.body_mass_kg = float(body_mass_kg)
        # A fourth stream for the first-breath draws, so the first three (and every breath's
        # noise) are what they were before it existed.
        subj_ss, breath_ss, search_ss, first_ss = np.random.SeedSequence(self.seed).spawn(4)
        self._draw_subject(np.random.default_rng(subj_ss))
        self._breath_rng = np.random.default_rng(breath_ss)
        self._first_rng = np.random.default_rng(first_ss)
        self._first_pending = False
        self._n_first_odd = 0
        self._search_ss = search_ss
        # The state at each change: (t_change_s, rate_at_change_w, unadapted target, whether the
        # target is standing, whether the transition starts or ends standing: a phase I).
        self._segments: list[tuple[float, float, float, bool, bool]] = [
            (0.0, self._baseline_w, self._baseline_w, False, False)
        ]
        self._applied: tuple[ForceProfile, ...] = ()
        self._t_last_s = 0.0
        self._n_breaths = 0
        self._n_outliers = 0
        self._noise = 0.0
        self._next_t_s = self._draw_interval()

    # ------------------------------------------------------------------ subject
    def _draw_subject(self, rng: np.random.Generator) -> None:
        cfg = self.config

        def u(pair: tuple[float, float]) -> float:
            return float(rng.uniform(pair[0], pair[1]))

        # Fixed draw order (every prior, used or not), so a seed is always the same person.
        self._baseline_w = u(cfg.gross_cost_w_per_kg) * self.body_mass_kg
        # τ log-uniform over the range (the same single draw as before: u in [0, 1) mapped).
        lo_tau, hi_tau = cfg.tau_s
        self._tau_s = lo_tau * (hi_tau / lo_tau) ** float(rng.uniform(0.0, 1.0))
        self._interval_mean_s = u(cfg.breath_interval_s)
        self._interval_cv = u(cfg.breath_interval_cv)
        self._noise_sd = u(cfg.noise_cv)
        self._noise_ar1 = u(cfg.noise_ar1)
        self._outlier_p = u(cfg.outlier_frac)
        self._adapt_frac = u(cfg.adaptation_frac)
        self._adapt_tau_s = u(cfg.adaptation_tau_s)
        self._rer_mean = u(cfg.rer)
        self._hr_rest = u(cfg.hr_rest_bpm)
        self._family = (LandscapeFamily.BUMPS if rng.uniform() < cfg.p_bumps
                        else LandscapeFamily.WINDOW)
        weight_n = _G * self.body_mass_kg
        self._windows: dict[str, AssistWindow] = {}
        for prior in cfg.windows:
            self._windows[prior.actuator] = AssistWindow(
                actuator=prior.actuator, centre_pct=u(prior.centre_pct), width_pct=u(prior.width_pct),
                ideal_force_n=u(prior.ideal_force_bw) * weight_n,
                max_benefit_frac=u(prior.max_benefit_frac),
            )
        self._bumps: dict[str, BumpLandscape] = {}
        for bp in cfg.bumps:
            centre = u(bp.centre_pct)
            side = 1.0 if rng.uniform() < 0.5 else -1.0
            bumps = []
            for k in range(2):
                bumps.append(Bump(
                    centre_pct=centre if k == 0 else centre + side * u(bp.second_offset_pct),
                    spread_pct=u(bp.spread_pct), centre_sd_pct=u(bp.centre_sd_pct),
                    spread_sd_pct=u(bp.spread_sd_pct), correlation=u(bp.correlation),
                    amplitude=1.0 if k == 0 else u(bp.second_amplitude),
                    ideal_force_n=u(bp.ideal_force_bw) * weight_n,
                ))
            self._bumps[bp.actuator] = BumpLandscape(
                actuator=bp.actuator, bumps=tuple(bumps), max_benefit_frac=u(bp.max_benefit_frac),
                mistiming_penalty=u(bp.mistiming_penalty),
            )
        # Drawn last, so every earlier draw (the subject as it was) is unchanged.
        self._drift_sd = u(cfg.drift_sd)
        lo_p, hi_p = cfg.drift_period_s
        periods = lo_p * (hi_p / lo_p) ** rng.uniform(0.0, 1.0, _N_DRIFT)
        self._drift_omega = 2.0 * math.pi / periods
        self._drift_phase = rng.uniform(0.0, 2.0 * math.pi, _N_DRIFT)
        self._first_p = u(cfg.first_breath_p)
        self._phase1_s = u(cfg.phase1_s)
        self._phase1_share = u(cfg.phase1_share)

    @property
    def family(self) -> LandscapeFamily:
        """This subject's landscape family."""
        return self._family

    @property
    def baseline_cost_w(self) -> float:
        """Unassisted steady-state metabolic power in W, before any adaptation (time 0)."""
        return self._baseline_w

    @property
    def tau_s(self) -> float:
        """This subject's metabolic time constant in s."""
        return self._tau_s

    @property
    def breath_interval_mean_s(self) -> float:
        """This subject's mean breath interval in s."""
        return self._interval_mean_s

    @property
    def noise_cv(self) -> float:
        """The stationary SD of the core breath noise, as a fraction of the level."""
        return self._noise_sd

    @property
    def outlier_frac(self) -> float:
        """This subject's probability that a breath is an outlier."""
        return self._outlier_p

    @property
    def adaptation_frac(self) -> float:
        """α: how much every setting's cost falls over the first hour (fraction)."""
        return self._adapt_frac

    @property
    def n_outliers(self) -> int:
        """Outlier breaths produced so far."""
        return self._n_outliers

    @property
    def n_partial_first_breaths(self) -> int:
        """First breaths after a change that came out partial (a fraction of the level)."""
        return self._n_first_odd

    @property
    def drift_sd(self) -> float:
        """This subject's SD of the steady state's drift, as a fraction of the level."""
        return self._drift_sd

    @property
    def windows(self) -> dict[str, AssistWindow]:
        """The window-family landscape per actuator (a copy; drawn for every subject)."""
        return dict(self._windows)

    @property
    def bumps(self) -> dict[str, BumpLandscape]:
        """The bump-family landscape per actuator (a copy; drawn for every subject)."""
        return dict(self._bumps)

    @property
    def subject(self) -> dict[str, Any]:
        """JSON-able summary of the subject for logs and summary.json."""
        landscape: dict[str, Any] = (
            {name: asdict(w) for name, w in self._windows.items()}
            if self._family is LandscapeFamily.WINDOW
            else {name: asdict(b) for name, b in self._bumps.items()}
        )
        return {
            "wearer": "realistic",
            "seed": self.seed,
            "space": self.space.name,
            "body_mass_kg": self.body_mass_kg,
            "family": self._family.value,
            "unassisted_cost_w": self._baseline_w,
            "tau_s": self._tau_s,
            "breath_interval_mean_s": self._interval_mean_s,
            "breath_interval_cv": self._interval_cv,
            "noise_sd_frac": self._noise_sd,
            "noise_ar1": self._noise_ar1,
            "outlier_frac": self._outlier_p,
            "outlier_scale": self.config.outlier_scale,
            "adaptation_frac_per_hour": self._adapt_frac,
            "adaptation_tau_s": self._adapt_tau_s,
            "drift_sd_frac": self._drift_sd,
            "drift_periods_s": [float(2.0 * math.pi / w) for w in self._drift_omega],
            "first_breath_partial_p": self._first_p,
            "phase1_s": self._phase1_s,
            "phase1_share": self._phase1_share,
            "rer_mean": self._rer_mean,
            "hr_rest_bpm": self._hr_rest,
            "landscape": landscape,
        }

    # ------------------------------------------------------------------ landscape
    def adaptation_factor(self, t_s: float) -> float:
        """``D(t)``: every setting's steady-state cost at breath-clock time ``t_s`` over its
        unadapted cost (1 at 0 s, ``1 - adaptation_frac`` after an hour)."""
        t = check_time("t_s", t_s)
        return adaptation_factor(t, self._adapt_frac, self._adapt_tau_s)

    def cost_of_profiles(self, profiles: Sequence[ForceProfile]) -> float:
        """Unadapted steady-state metabolic power in W while these tables are applied.

        Raises:
            ConfigError: Not ForceProfiles, an actuator twice, or one this subject has no model for.
        """
        profs = check_profiles(profiles, self._windows)
        saving = 0.0
        cap = self.config.penalty_cap
        for p in profs:
            if self._family is LandscapeFamily.WINDOW:
                w = self._windows[p.actuator]
                score = assistance_score(p.gait_pct, p.force_n, w.centre_pct, w.width_pct,
                                         w.ideal_force_n)
                beta = w.max_benefit_frac
            else:
                b = self._bumps[p.actuator]
                score = bump_score(p.gait_pct, p.force_n, b)
                beta = b.max_benefit_frac
            saving += beta * saturate_penalty(score, cap)
        return self._baseline_w * (1.0 - saving)

    def profiles_for(self, params: Mapping[str, float]) -> tuple[ForceProfile, ...]:
        """The force tables the exosuit would apply for a feasible setting.

        Raises:
            InfeasibleError: ``params`` is outside the space.
            ConfigError: Unknown or missing parameter names.
        """
        vec = self.space.check(params)
        return build_profile(self.space.name, self.space.to_dict(vec), body_mass_kg=self.body_mass_kg)

    def true_cost_w(self, params: Mapping[str, float], t_s: float | None = None) -> float:
        """Noiseless steady-state cost in W of a feasible setting.

        Args:
            params: The setting.
            t_s: ``None`` (default): the unadapted landscape, what regret uses (module
                docstring); a time: the adapted cost at that breath-clock time.
        """
        cost = self.cost_of_profiles(self.profiles_for(params))
        return cost if t_s is None else cost * self.adaptation_factor(t_s)

    def _cost_unit(self, u: np.ndarray) -> float:
        x = self.space.from_unit(np.clip(u, 0.0, 1.0))
        return self.cost_of_profiles(build_profile(self.space.name, self.space.to_dict(x),
                                                   body_mass_kg=self.body_mass_kg))

    @cached_property
    def true_optimum(self) -> tuple[dict[str, float], float]:
        """``(params, cost_w)`` of the best feasible setting of the unadapted landscape (its
        location never moves with adaptation), found numerically once
        (:func:`virtual_hw.wearer.find_optimum`)."""
        return find_optimum(self.space, self._cost_unit, self._search_ss,
                            self.config.n_optimum_candidates, self.config.n_optimum_starts)

    # ------------------------------------------------------------------ dynamics
    @property
    def t_s(self) -> float:
        """Breath-clock time of the last breath in s (0.0 before the first)."""
        return self._t_last_s

    @property
    def n_breaths(self) -> int:
        """Number of breaths produced so far."""
        return self._n_breaths

    @property
    def applied_profiles(self) -> tuple[ForceProfile, ...]:
        """The force tables currently applied (``()`` = no assistance)."""
        return self._applied

    @property
    def steady_state_cost_w(self) -> float:
        """The unadapted cost the rate is currently relaxing towards, in W."""
        return self._segments[-1][2]

    def _particular(self, t: float) -> float:
        # The particular solution of dm/dt = (c·D(t) - m)/τ per unit c, with
        # D(t) = A + B·e^{-t/T}:  P(t) = A + B·e^{-t/T} / (1 - τ/T)   (T > 10 τ by the config).
        k = -math.expm1(-_ONE_HOUR_S / self._adapt_tau_s)
        b = self._adapt_frac / k
        return 1.0 - b + b * math.exp(-t / self._adapt_tau_s) / (1.0 - self._tau_s / self._adapt_tau_s)

    def drift_factor(self, t_s: float) -> float:
        """``1 + d(t)``: the steady state's slow drift at breath-clock time ``t_s`` (module
        docstring, "Drift"); 1 when the person's drift SD is 0."""
        t = check_time("t_s", t_s)
        if self._drift_sd == 0.0:
            return 1.0
        d = float(np.sum(np.sin(self._drift_omega * t + self._drift_phase)))
        return 1.0 + self._drift_sd * math.sqrt(2.0 / _N_DRIFT) * d

    def metabolic_rate_w(self, t_s: float) -> float:
        """Noiseless instantaneous metabolic power in W at breath-clock time ``t_s`` (>= 0).

        The first-order rate ``m(t) = c·P(t) + (m(t_c) - c·P(t_c))·e^{-(t - t_c)/τ}`` on the
        segment of the last change ``t_c`` before ``t`` (the exact solution of the first-order
        ODE with the adapting target; continuous at every change), with a phase I in place of
        the exponential on a step to or from standing (module docstring, "Phase I"), times the
        drift :meth:`drift_factor`.
        """
        return self._first_order_w(t_s) * self.drift_factor(t_s)

    def _first_order_w(self, t_s: float) -> float:
        t = check_time("t_s", t_s)
        seg = self._segments[0]
        for s in reversed(self._segments):
            if s[0] <= t:
                seg = s
                break
        t_c, m_c, c, _, phase1 = seg
        return c * self._particular(t) + (m_c - c * self._particular(t_c)) * self._remaining(
            t - t_c, phase1)

    def _remaining(self, s: float, phase1: bool) -> float:
        # The share of a step still to come s seconds after it: e^{-s/τ}, or with a phase I
        # (module docstring, "Phase I") a fast rise by the phase-I share within its duration δ
        # (time constant δ/4: 98 % of it by δ), then phase II with the person's τ from δ on.
        delta = self._phase1_s
        if not phase1 or delta <= 0.0:
            return math.exp(-s / self._tau_s)
        share = self._phase1_share
        if s < delta:
            return 1.0 - share * -math.expm1(-4.0 * s / delta)
        return (1.0 - share * -math.expm1(-4.0)) * math.exp(-(s - delta) / self._tau_s)

    def apply_profiles(self, profiles: Sequence[ForceProfile], t_s: float) -> float:
        """Record that the exosuit applies these tables from breath-clock time ``t_s`` on.

        Returns:
            The new (unadapted) steady-state cost in W.

        Raises:
            MeasurementError: ``t_s`` is not finite or goes backwards.
            ConfigError: Bad profiles.
        """
        t = self._check_change_time(t_s)
        profs = check_profiles(profiles, self._windows)
        target = self.cost_of_profiles(profs)
        self._applied = profs
        self._change_target(t, target, standing=False)
        return target

    def apply_params(self, params: Mapping[str, float], t_s: float) -> float:
        """Apply the tables of a feasible setting (see :meth:`apply_profiles`)."""
        return self.apply_profiles(self.profiles_for(params), t_s)

    @property
    def standing_cost_w(self) -> float:
        """The unadapted cost of standing still on the treadmill, in W
        (``standing_w_per_kg`` × body mass; module docstring, "Standing")."""
        return self.config.standing_w_per_kg * self.body_mass_kg

    def stand(self, t_s: float) -> float:
        """The person stops walking and stands from breath-clock time ``t_s`` on (the exosuit
        applies nothing): the rate relaxes to :attr:`standing_cost_w`, and the next
        :meth:`apply_profiles` walks again from wherever the body is (large steps, as the
        recordings' rests and starts).

        Returns:
            The standing cost in W.

        Raises:
            MeasurementError: ``t_s`` is not finite or goes backwards.
        """
        t = self._check_change_time(t_s)
        self._applied = ()
        self._change_target(t, self.standing_cost_w, standing=True)
        return self.standing_cost_w

    def _check_change_time(self, t_s: float) -> float:
        t = check_time("t_s", t_s)
        latest = max(self._t_last_s, self._segments[-1][0])
        if t < latest:
            raise MeasurementError(
                f"apply time t_s={t!r} goes backwards; expected >= {latest!r} (the last breath "
                "or change)"
            )
        return t

    def _change_target(self, t: float, target: float, *, standing: bool) -> None:
        t_c, m_c, old_target, old_standing, _ = self._segments[-1]
        if t == t_c:
            # A second change at the same instant replaces the first: the step is from what the
            # body did before both (a stand and a walk at once is a walking step, no phase I).
            before = self._segments[-2][3] if len(self._segments) > 1 else False
            self._segments[-1] = (t_c, m_c, target, standing, before or standing)
        elif target != old_target or standing != old_standing:
            # The new transition starts from the rate the body is at now (module docstring).
            self._segments.append((t, self._first_order_w(t), target, standing,
                                   old_standing or standing))
            self._first_pending = True

    # ------------------------------------------------------------------ breaths
    def _draw_interval(self) -> float:
        mean, cv = self._interval_mean_s, self._interval_cv
        # Always one draw, so the stream does not depend on whether the CV is 0.
        g = float(self._breath_rng.standard_gamma(1.0 / cv**2 if cv > 0.0 else 1.0))
        z = g * cv**2 if cv > 0.0 else 1.0
        dt = min(max(mean * z, _INTERVAL_CLIP[0] * mean), _INTERVAL_CLIP[1] * mean)
        return self._t_last_s + dt

    def next_breath(self) -> BreathRecord:
        """The next breath, advancing the breath clock by one irregular interval."""
        cfg = self.config
        rng = self._breath_rng
        t = self._next_t_s
        m = self.metabolic_rate_w(t)
        # Fixed draws per breath (order matters for reproducibility).
        xi, xi_rer, xi_hr = rng.standard_normal(3)
        u_out = float(rng.uniform())
        t_out = float(rng.standard_t(_OUTLIER_DF))
        rho = self._noise_ar1 if self._n_breaths else 0.0
        self._noise = rho * self._noise + math.sqrt(1.0 - rho * rho) * self._noise_sd * xi
        e = self._noise
        if u_out < self._outlier_p:
            # An outlier (swallow, cough, talking) sits on top of the breath and does not carry
            # over to the next one.
            e += cfg.outlier_scale * t_out
            self._n_outliers += 1
        watts = m * min(max(1.0 + e, _FACTOR_LIMITS[0]), _FACTOR_LIMITS[1])
        # The first breath after a change: with the person's probability a partial breath (a
        # fraction of the level), drawn from its own stream, two draws every breath.
        u_first, f_first = self._first_rng.uniform(size=2)
        if self._first_pending:
            self._first_pending = False
            if u_first < self._first_p:
                lo, hi = cfg.first_breath_factor
                watts = m * (lo + (hi - lo) * float(f_first))
                self._n_first_odd += 1
        rer = min(max(self._rer_mean + cfg.rer_sd * xi_rer, _RER_LIMITS[0]), _RER_LIMITS[1])
        vo2 = _S_PER_MIN * watts / (_BROCKWAY_O2 + _BROCKWAY_CO2 * rer)
        vco2 = rer * vo2
        ve = vco2 * cfg.ve_per_vco2 / 1000.0 if cfg.report_ve else None
        hr = None
        if cfg.report_hr:
            rest_w = cfg.resting_w_per_kg * self.body_mass_kg
            hr = max(self._hr_rest + cfg.hr_gain_bpm_per_w * (m - rest_w) + cfg.hr_sd_bpm * xi_hr,
                     30.0)
        self._t_last_s = t
        self._n_breaths += 1
        self._next_t_s = self._draw_interval()
        return BreathRecord(t_s=t, vo2_ml_min=vo2, vco2_ml_min=vco2, ve_l_min=ve, rer=rer,
                            hr_bpm=hr)

    def breaths_until(self, t_s: float) -> list[BreathRecord]:
        """Every breath with a time ``<= t_s`` not produced yet, in order.

        Raises:
            MeasurementError: ``t_s`` not finite, before the last breath, or absurdly far ahead.
        """
        t = check_time("t_s", t_s)
        if t < self._t_last_s:
            raise MeasurementError(
                f"t_s={t!r} goes backwards; expected >= {self._t_last_s!r} (the last breath)"
            )
        min_interval = _INTERVAL_CLIP[0] * self._interval_mean_s
        if (t - self._t_last_s) / min_interval > _MAX_BREATHS_PER_CALL:
            raise MeasurementError(
                f"t_s={t!r} is {t - self._t_last_s:.3g} s ahead of the last breath; more than "
                f"{_MAX_BREATHS_PER_CALL} breaths in one call (times must be in seconds)"
            )
        out: list[BreathRecord] = []
        while self._next_t_s <= t:
            out.append(self.next_breath())
        return out
