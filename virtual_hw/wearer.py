"""The simulated wearer: a subject-specific metabolic landscape, its dynamics, and noisy breaths.

A pure model (no transport, no clock, no asyncio): the caller — a simulation loop or the virtual
metabolic cart — owns the clock and passes every time explicitly, in seconds on the breath clock.

Model
=====

**Landscape on the applied force tables.** The steady-state metabolic power is a function of the
force tables the exosuit *applies* (:class:`hilbo_core.profiles.ForceProfile`), not of the
optimizer's parameter vector, so a profile that is lost, refused or zeroed on the way shows up
in the metabolic data exactly as it would in a lab. For each actuator ``a`` the subject has a
useful timing window, a circular Gaussian over % gait cycle (in that actuator's own gait-event
convention: maximum hip flexion for the hip, heel strike for the ankle)
``w_a(g) = exp(-d(g, c_a)² / (2 s_a²))`` (centre ``c_a``, width ``s_a``, ``d`` the signed
distance on the 100 % cycle), and an ideal force ``F_a``: the assistance that fully offloads the
muscles is ``F_a·w_a(g)``. With the inner product ``<f, h> = ∫ f(g) h(g) dg`` over 0-100 %, the
applied table ``f`` (clipped at 0: a cable can only pull) scores::

    φ_a(f) = (2 <f, w_a> / F_a - <f, f> / F_a²) / <w_a, w_a>

``φ = 1`` for the ideal profile and 0 without assistance; it is a concave quadratic in the
force, so the best magnitude is interior (``f = a·h`` is best at ``a = F_a <h, w> / <h, h>``), the
best timing puts the force where the window is, and force at the wrong time is penalised
quadratically. The best profile of a given shape reaches ``φ = cos²`` of the angle between the
shape and the window, so node ratios, which only bend the shape slightly, matter much less than
timing and peak force (as in the hip-assistance literature, Kim et al. 2019 ref. [18]). Very poorly
timed assistance would make ``φ`` hugely negative; real wearers are hampered but not crippled, so
negative scores saturate smoothly (C¹ at 0): ``S(φ) = φ`` for ``φ >= 0`` and
``-L·tanh(-φ/L)`` below, with ``L = penalty_cap``. The steady-state cost is::

    cost = unassisted_cost · (1 - Σ_a β_a · S(φ_a))

with ``β_a`` the actuator's largest possible fractional saving.

**Dynamics** (Kim et al. 2019 §II.C; Selinger & Donelan 2014, their ref. [20]): after a change
of the applied assistance at ``t_c`` the metabolic rate relaxes first-order towards the new steady
state, ``m(t) = c_new + (m(t_c) - c_new)·exp(-(t - t_c)/τ)``. At ``t = 0`` the wearer walks at
the unassisted steady state (the protocol's warm-up is over).

**Breaths.** Intervals are gamma distributed with a subject-specific mean and a coefficient of
variation ``breath_interval_cv``, never shorter than ``min_breath_interval_s``. Each breath
reports ``P = m(t)·(1 + e)`` where ``e`` is AR(1) breath-to-breath noise with stationary SD
``noise_frac`` (a fraction of the level) and lag-one correlation ``noise_ar1``; the breath's RER
is the subject's mean plus white noise; VO2 and VCO2 (ml/min) are then solved from Brockway's
equation ``P[W] = 16.58·VO2[ml/s] + 4.51·VCO2[ml/s]`` with ``VCO2 = RER·VO2``, so
``BreathRecord.watts`` is exactly ``P`` (exactly ``m(t)`` when the noise is off). Optional VE is
``VCO2 × ve_per_vco2`` and optional HR is ``hr_rest + hr_gain·(m(t) - rest power)`` plus noise.

Constants (:class:`WearerConfig`; a range means "drawn uniformly per subject")
------------------------------------------------------------------------------
* ``gross_cost_w_per_kg = (4.7, 5.8)`` W/kg: unassisted gross (Brockway) power of treadmill
  walking at 1.25 m/s, Kim et al. 2019's protocol speed (§IV.A.3): ≈ 350-435 W at 75 kg, the range
  the project specifies for a 75 kg adult (350-450 W).
* ``tau_s = (30, 50)`` s: time constant of the first-order response; Selinger & Donelan (2014)
  report about 40 s (Kim et al. 2019 §II.C models the response with this first-order form).
* ``breath_interval_s = (2.7, 3.3)`` s mean, ``breath_interval_cv = 0.25``,
  ``min_breath_interval_s = 1.0`` s: ≈ 18-22 breaths/min while walking, irregular.
* ``noise_frac = (0.10, 0.15)``, ``noise_ar1 = 0.3``: breath-by-breath carts scatter by 10-15 %
  of the level (≈ 110-170 ml/min of VO2 at ≈ 1.1 l/min), with some carry-over between breaths;
  this is the noise the UKF of §II.C must see through (Kim et al. 2019 §III.1: 3 % error after 20 breaths).
* ``rer = (0.85, 0.90)``, ``rer_sd = 0.02``: moderate walking on a mixed diet.
* ``ve_per_vco2 = 28``: ventilatory equivalent for CO2 at moderate exercise (≈ 25-30).
* ``hr_rest_bpm = (60, 75)``, ``hr_gain_bpm_per_w = 0.15``, ``resting_w_per_kg = 1.3``,
  ``hr_sd_bpm = 2``: gives ≈ 100-125 bpm while walking, a plausible value; HR is
  informational only (the estimator uses VO2/VCO2).
* Hip window (``HIP_PRIOR``, %GC from maximum hip flexion): centre ``(20, 28)``, width
  ``(7, 11)``, ideal force ``(0.22, 0.32)`` body weight, ``β = (0.10, 0.20)``. Kim et al. 2019's optimal
  hip peaks are at 24 and 27 %GC with 223 N (85 kg, 0.27 BW) and 174 N (74 kg, 0.24 BW) (Fig. 4)
  and at 21-26 %GC in Table II. Over 40 seeds the best hip-only saving (``hip_6d``) is
  ≈ 10-20 %, inside Kim et al. 2019's 7-35 % (§IV.A.4) and the project's 5-25 %.
* Ankle window (``ANKLE_PRIOR``, %GC from heel strike): centre ``(52, 60)``, width ``(5, 8)``,
  ideal force ``(0.50, 0.75)`` BW, ``β = (0.05, 0.10)``: plantarflexion assistance helps around
  push-off (≈ 50-60 %GC_HS; Table II's optimal ankle peaks 56-60 %); Kim et al. 2019 apply 60 % BW.
  With the hip's fixed 40 % BW, the best ``hip_ankle_4d`` saving is ≈ 10-21 % over 40 seeds
  (Kim et al. 2019's Table II reports more, 33-39 %, for two experienced subjects).
* ``penalty_cap = 0.5``: badly timed assistance costs at most half of what a well-timed one can
  save per actuator (Kim et al. 2019's generic profile cost one subject 4 % where the optimum saved 7 %).
* ``n_optimum_candidates = 128``, ``n_optimum_starts = 2``: the numerical search for the true
  optimum (scrambled Sobol candidates, then SLSQP under the linear constraints). Over 20 seeds
  per preset, 64-256 candidates and 2-3 starts all found the same optimum, better than the best
  of 4096 random feasible points every time; this setting costs ≈ 0.1-0.3 s for ``hip_6d``
  (each hip table is two scipy cubic splines, ≈ 0.5 ms) and less for ``hip_ankle_4d``.
"""

from __future__ import annotations

import enum
import math
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass
from functools import cached_property
from typing import Any, Protocol, runtime_checkable

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
    _MIN_NOISE_FACTOR,
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
    timing_window,
)
from virtual_hw.wearer_realistic import RealisticWearer, RealisticWearerConfig

__all__ = [
    "ANKLE_PRIOR",
    "HIP_PRIOR",
    "NOISY_BREATH_CV",
    "NOISY_OUTLIER_FRAC",
    "SLOW_TAU_S",
    "WEARER_CHOICES",
    "ActuatorPrior",
    "AssistWindow",
    "SimulatedWearer",
    "Wearer",
    "WearerConfig",
    "WearerKind",
    "assistance_score",
    "check_profiles",
    "check_subject_args",
    "check_time",
    "find_optimum",
    "make_wearer",
    "relaxed_rate_w",
    "saturate_penalty",
    "timing_window",
    "wearer_kind",
]


# ---------------------------------------------------------------------------- pure functions
def relaxed_rate_w(t_s: float, t_change_s: float, rate_at_change_w: float, target_w: float,
                   tau_s: float) -> float:
    """First-order response after a change (Kim et al. 2019 §II.C; Selinger & Donelan 2014).

    ``m(t) = c + (m(t_c) - c)·exp(-(t - t_c)/τ)`` for ``t >= t_c``.
    """
    return target_w + (rate_at_change_w - target_w) * math.exp(-(t_s - t_change_s) / tau_s)


@dataclass(frozen=True)
class WearerConfig:
    """Population constants of the simulated wearer (sources in the module docstring).

    Pairs are ``(low, high)`` ranges drawn uniformly per subject; equal ends fix the value.

    Raises:
        ConfigError: A value outside its physiological or numerical range, naming the field.
    """

    gross_cost_w_per_kg: tuple[float, float] = (4.7, 5.8)
    tau_s: tuple[float, float] = (30.0, 50.0)
    breath_interval_s: tuple[float, float] = (2.7, 3.3)
    breath_interval_cv: float = 0.25
    min_breath_interval_s: float = 1.0
    noise_frac: tuple[float, float] = (0.10, 0.15)
    noise_ar1: float = 0.3
    rer: tuple[float, float] = (0.85, 0.90)
    rer_sd: float = 0.02
    ve_per_vco2: float = 28.0
    report_ve: bool = True
    report_hr: bool = True
    hr_rest_bpm: tuple[float, float] = (60.0, 75.0)
    hr_gain_bpm_per_w: float = 0.15
    resting_w_per_kg: float = 1.3
    hr_sd_bpm: float = 2.0
    actuators: tuple[ActuatorPrior, ...] = (HIP_PRIOR, ANKLE_PRIOR)
    penalty_cap: float = 0.5
    n_optimum_candidates: int = 128
    n_optimum_starts: int = 2

    def __post_init__(self) -> None:
        o = "WearerConfig"
        _check_range(o, "gross_cost_w_per_kg", self.gross_cost_w_per_kg, 1.5, 15.0)
        _check_range(o, "tau_s", self.tau_s, 1.0, 600.0)
        _check_range(o, "breath_interval_s", self.breath_interval_s, 0.5, 20.0)
        _check_value(o, "breath_interval_cv", self.breath_interval_cv, 0.0, 1.0)
        _check_value(o, "min_breath_interval_s", self.min_breath_interval_s, 0.05,
                     float(self.breath_interval_s[0]))
        _check_range(o, "noise_frac", self.noise_frac, 0.0, 0.5)
        _check_value(o, "noise_ar1", self.noise_ar1, 0.0, 0.95)
        _check_range(o, "rer", self.rer, _RER_LIMITS[0], _RER_LIMITS[1])
        _check_value(o, "rer_sd", self.rer_sd, 0.0, 0.2)
        _check_value(o, "ve_per_vco2", self.ve_per_vco2, 10.0, 60.0)
        _check_range(o, "hr_rest_bpm", self.hr_rest_bpm, 30.0, 120.0)
        _check_value(o, "hr_gain_bpm_per_w", self.hr_gain_bpm_per_w, 0.0, 2.0)
        _check_value(o, "resting_w_per_kg", self.resting_w_per_kg, 0.5, 3.0)
        _check_value(o, "hr_sd_bpm", self.hr_sd_bpm, 0.0, 30.0)
        _check_value(o, "penalty_cap", self.penalty_cap, 1e-3, 5.0)
        for name in ("report_ve", "report_hr"):
            if not isinstance(getattr(self, name), bool):
                raise ConfigError(f"{o}.{name}={getattr(self, name)!r} must be True or False")
        for name, lo in (("n_optimum_candidates", 8), ("n_optimum_starts", 1)):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or not lo <= v <= 100_000:
                raise ConfigError(f"{o}.{name}={v!r} must be an integer in [{lo}, 100000]")
        acts = tuple(self.actuators)
        if not all(isinstance(a, ActuatorPrior) for a in acts):
            raise ConfigError(f"{o}.actuators must hold ActuatorPrior values, got {acts!r}")
        names = [a.actuator for a in acts]
        if len(set(names)) != len(names):
            raise ConfigError(f"{o}.actuators has duplicate actuator names: {names}")
        object.__setattr__(self, "actuators", acts)

    @classmethod
    def noiseless(cls, **overrides: Any) -> WearerConfig:
        """The default population with measurement noise switched off (intervals stay irregular).

        Every breath then reports exactly the noiseless rate ``m(t)``; used by tests and by
        anyone who wants to see the model without the cart's scatter.
        """
        base = {"noise_frac": (0.0, 0.0), "rer_sd": 0.0, "hr_sd_bpm": 0.0}
        base.update(overrides)
        return cls(**base)


# ---------------------------------------------------------------------------- the wearer
class SimulatedWearer:
    """A seeded simulated subject walking in the exosuit (see the module docstring).

    The caller owns the clock: it reports what the exosuit applied and when
    (:meth:`apply_profiles`), and pulls breaths (:meth:`next_breath`, :meth:`breaths_until`).
    Same ``seed`` and config → the same subject and, for the same calls, the same breaths; the
    breath noise and intervals are drawn per breath, independently of the settings applied.

    Args:
        space: The parameter space whose force-profile builder maps settings to tables
            (``space.name`` must name a builder in ``hilbo_core.profiles.PROFILE_BUILDERS``).
        seed: Non-negative integer; fixes the subject and its breath stream.
        config: Population constants; ``WearerConfig()`` when omitted.
        body_mass_kg: The subject's mass in kg (sets costs, forces and the hip+ankle peaks).

    Raises:
        ConfigError: Unknown space builder, bad seed or body mass.
    """

    def __init__(self, space: ParameterSpace, seed: int, config: WearerConfig | None = None,
                 body_mass_kg: float = 75.0) -> None:
        check_subject_args(space, seed, body_mass_kg)
        cfg = WearerConfig() if config is None else config
        if not isinstance(cfg, WearerConfig):
            raise ConfigError(f"config must be a WearerConfig, got {type(cfg).__name__}")
        self.space = space
        self.seed = int(seed)
        self.config = cfg
        self.body_mass_kg = float(body_mass_kg)

        # Three independent streams: the subject, its breaths, and the optimum search, so that
        # e.g. changing the noise level never changes who the subject is.
        subj_ss, breath_ss, search_ss = np.random.SeedSequence(self.seed).spawn(3)
        self._draw_subject(np.random.default_rng(subj_ss))
        self._breath_rng = np.random.default_rng(breath_ss)
        self._search_ss = search_ss

        # Piecewise first-order history: (t_change_s, rate_at_change_w, target_w), by time.
        self._segments: list[tuple[float, float, float]] = [
            (0.0, self._baseline_w, self._baseline_w)
        ]
        self._applied: tuple[ForceProfile, ...] = ()
        self._t_last_s = 0.0
        self._n_breaths = 0
        self._noise = 0.0
        self._next_t_s = self._draw_interval()

    # ------------------------------------------------------------------ subject
    def _draw_subject(self, rng: np.random.Generator) -> None:
        cfg = self.config

        def u(pair: tuple[float, float]) -> float:
            return float(rng.uniform(pair[0], pair[1]))

        self._baseline_w = u(cfg.gross_cost_w_per_kg) * self.body_mass_kg
        self._tau_s = u(cfg.tau_s)
        self._interval_mean_s = u(cfg.breath_interval_s)
        self._noise_sd = u(cfg.noise_frac)
        self._rer_mean = u(cfg.rer)
        self._hr_rest = u(cfg.hr_rest_bpm)
        weight_n = _G * self.body_mass_kg
        self._windows: dict[str, AssistWindow] = {}
        for prior in cfg.actuators:  # all priors, used or not: same seed -> same hip window
            self._windows[prior.actuator] = AssistWindow(
                actuator=prior.actuator,
                centre_pct=u(prior.centre_pct),
                width_pct=u(prior.width_pct),
                ideal_force_n=u(prior.ideal_force_bw) * weight_n,
                max_benefit_frac=u(prior.max_benefit_frac),
            )

    @property
    def baseline_cost_w(self) -> float:
        """Unassisted steady-state metabolic power in W."""
        return self._baseline_w

    @property
    def tau_s(self) -> float:
        """This subject's metabolic time constant in s."""
        return self._tau_s

    @property
    def windows(self) -> dict[str, AssistWindow]:
        """The subject's useful window per actuator (a copy)."""
        return dict(self._windows)

    @property
    def subject(self) -> dict[str, Any]:
        """JSON-able summary of the subject for logs and summary.json."""
        return {
            "wearer": "legacy",
            "seed": self.seed,
            "space": self.space.name,
            "body_mass_kg": self.body_mass_kg,
            "unassisted_cost_w": self._baseline_w,
            "tau_s": self._tau_s,
            "breath_interval_mean_s": self._interval_mean_s,
            "noise_sd_frac": self._noise_sd,
            "noise_ar1": self.config.noise_ar1,
            "rer_mean": self._rer_mean,
            "hr_rest_bpm": self._hr_rest,
            "windows": {name: asdict(w) for name, w in self._windows.items()},
        }

    # ------------------------------------------------------------------ landscape
    def cost_of_profiles(self, profiles: Sequence[ForceProfile]) -> float:
        """Steady-state metabolic power in W while these force tables are applied.

        Args:
            profiles: What the exosuit applies, at most one table per actuator; ``()`` (or
                all-zero tables) means no assistance and gives :attr:`baseline_cost_w`.

        Raises:
            ConfigError: Not ForceProfiles, an actuator twice, or an actuator this subject has
                no window for.
        """
        profs = check_profiles(profiles, self._windows)
        saving = 0.0
        for p in profs:
            w = self._windows[p.actuator]
            score = assistance_score(p.gait_pct, p.force_n, w.centre_pct, w.width_pct,
                                     w.ideal_force_n)
            saving += w.max_benefit_frac * saturate_penalty(score, self.config.penalty_cap)
        return self._baseline_w * (1.0 - saving)

    def profiles_for(self, params: Mapping[str, float]) -> tuple[ForceProfile, ...]:
        """The force tables the exosuit would apply for a feasible setting.

        Raises:
            InfeasibleError: ``params`` is outside the space (names the violated bound/constraint).
            ConfigError: Unknown or missing parameter names.
        """
        vec = self.space.check(params)
        return build_profile(self.space.name, self.space.to_dict(vec),
                             body_mass_kg=self.body_mass_kg)

    def true_cost_w(self, params: Mapping[str, float], t_s: float | None = None) -> float:
        """Noiseless steady-state cost in W of a feasible setting (for regret and summaries).

        ``t_s`` is accepted for the interface shared with the realistic wearer; this wearer does
        not adapt, so the cost is the same at every time.
        """
        if t_s is not None:
            check_time("t_s", t_s)
        return self.cost_of_profiles(self.profiles_for(params))

    def adaptation_factor(self, t_s: float) -> float:
        """Every setting's cost at ``t_s`` over its cost at 0 s: always 1 (no adaptation)."""
        check_time("t_s", t_s)
        return 1.0

    def _cost_unit(self, u: np.ndarray) -> float:
        x = self.space.from_unit(np.clip(u, 0.0, 1.0))
        profs = build_profile(self.space.name, self.space.to_dict(x),
                              body_mass_kg=self.body_mass_kg)
        return self.cost_of_profiles(profs)

    @cached_property
    def true_optimum(self) -> tuple[dict[str, float], float]:
        """``(params, cost_w)`` of the best feasible setting, found numerically once.

        Scrambled-Sobol feasible candidates (``n_optimum_candidates``), then SLSQP in the unit
        cube under the space's linear constraints from the ``n_optimum_starts`` best of them;
        the best feasible result wins (a candidate itself if refinement never improves on it).
        """
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
        """The cost the rate is currently relaxing towards, in W."""
        return self._segments[-1][2]

    def metabolic_rate_w(self, t_s: float) -> float:
        """Noiseless instantaneous metabolic power in W at breath-clock time ``t_s`` (>= 0).

        Times before the last change use the history, so any ``t_s >= 0`` is answered.
        """
        t = check_time("t_s", t_s)
        seg = self._segments[0]
        for s in reversed(self._segments):
            if s[0] <= t:
                seg = s
                break
        t_c, m_c, target = seg
        return relaxed_rate_w(t, t_c, m_c, target, self._tau_s)

    def apply_profiles(self, profiles: Sequence[ForceProfile], t_s: float) -> float:
        """Record that the exosuit applies these tables from breath-clock time ``t_s`` on.

        Args:
            profiles: What the device actually applies (``()`` = assistance off).
            t_s: Time of the switch in s; not before the last breath nor the last change.

        Returns:
            The new steady-state cost in W.

        Raises:
            MeasurementError: ``t_s`` is not finite or goes backwards.
            ConfigError: Bad profiles (see :meth:`cost_of_profiles`).
        """
        t = check_time("t_s", t_s)
        latest = max(self._t_last_s, self._segments[-1][0])
        if t < latest:
            raise MeasurementError(
                f"apply time t_s={t!r} goes backwards; expected >= {latest!r} (the last breath "
                "or change)"
            )
        profs = check_profiles(profiles, self._windows)
        target = self.cost_of_profiles(profs)
        self._applied = profs
        t_c, m_c, old_target = self._segments[-1]
        if t == t_c:
            # Two switches at the same instant: the later one wins, from the same start rate.
            self._segments[-1] = (t_c, m_c, target)
        elif target != old_target:
            # An identical target would continue the same exponential: no new segment needed.
            self._segments.append((t, self.metabolic_rate_w(t), target))
        return target

    def apply_params(self, params: Mapping[str, float], t_s: float) -> float:
        """Apply the tables of a feasible setting (see :meth:`apply_profiles`).

        Raises:
            InfeasibleError: ``params`` outside the space.
            MeasurementError: Bad time.
        """
        return self.apply_profiles(self.profiles_for(params), t_s)

    # ------------------------------------------------------------------ breaths
    def _draw_interval(self) -> float:
        cv = self.config.breath_interval_cv
        if cv == 0.0:
            dt = self._interval_mean_s
        else:
            shape = 1.0 / cv**2
            dt = float(self._breath_rng.gamma(shape, self._interval_mean_s / shape))
        return self._t_last_s + max(dt, self.config.min_breath_interval_s)

    def next_breath(self) -> BreathRecord:
        """The next breath, advancing the breath clock by one irregular interval."""
        cfg = self.config
        rng = self._breath_rng
        t = self._next_t_s
        m = self.metabolic_rate_w(t)
        # AR(1) with stationary SD noise_sd: e_k = ρ e_{k-1} + sqrt(1-ρ²)·σ·ξ_k (the first breath
        # draws from the stationary law directly). Draw order is fixed so streams reproduce.
        xi, xi_rer, xi_hr = rng.standard_normal(3)
        rho = cfg.noise_ar1 if self._n_breaths else 0.0
        self._noise = rho * self._noise + math.sqrt(1.0 - rho * rho) * self._noise_sd * xi
        watts = m * max(1.0 + self._noise, _MIN_NOISE_FACTOR)
        rer = min(max(self._rer_mean + cfg.rer_sd * xi_rer, _RER_LIMITS[0]), _RER_LIMITS[1])
        # Brockway solved for VO2 with VCO2 = RER·VO2, so BreathRecord.watts == watts exactly.
        vo2 = _S_PER_MIN * watts / (_BROCKWAY_O2 + _BROCKWAY_CO2 * rer)
        vco2 = rer * vo2
        ve = vco2 * cfg.ve_per_vco2 / 1000.0 if cfg.report_ve else None
        hr = None
        if cfg.report_hr:
            rest_w = cfg.resting_w_per_kg * self.body_mass_kg
            hr = max(self._hr_rest + cfg.hr_gain_bpm_per_w * (m - rest_w)
                     + cfg.hr_sd_bpm * xi_hr, 30.0)
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
        horizon = (t - self._t_last_s) / self.config.min_breath_interval_s
        if horizon > _MAX_BREATHS_PER_CALL:
            raise MeasurementError(
                f"t_s={t!r} is {t - self._t_last_s:.3g} s ahead of the last breath; more than "
                f"{_MAX_BREATHS_PER_CALL} breaths in one call (times must be in seconds)"
            )
        out: list[BreathRecord] = []
        while self._next_t_s <= t:
            out.append(self.next_breath())
        return out


# ---------------------------------------------------------------------------- choosing a wearer
class WearerKind(enum.Enum):
    """Which simulated wearer a simulation uses (``--wearer``).

    * ``REALISTIC`` (the default of ``hilbo sim`` and ``hilbo bench hil``):
      :class:`virtual_hw.wearer_realistic.RealisticWearer` — breath noise and outliers as in real
      data, per-person τ 14-55 s, drift, slow adaptation, two landscape families.
    * ``NOISY``: the realistic wearer with noisier breaths: a per-person breath CV of 15-25 %
      (instead of 8-12 %) and 3 % outlier breaths: the robustness check of the method.
    * ``SLOW``: the realistic wearer with slower VO2 kinetics: a per-person τ of 30-60 s (the
      long end of the population: the unfit, older or ill, Poole & Jones 2012, Compr Physiol
      2:933-996; Selinger & Donelan 2014's ≈ 42 s for walking): the robustness check of the
      estimator's τ prior (median 25 s) and of the search when each setting says less.
    * ``LEGACY``: :class:`SimulatedWearer` — one landscape family, AR(1) Gaussian noise, no
      adaptation; kept for the results and tests that were measured on it.
    """

    REALISTIC = "realistic"
    NOISY = "noisy"
    SLOW = "slow"
    LEGACY = "legacy"


#: The noisy wearer's per-person breath CV range and share of outlier breaths (WearerKind.NOISY).
NOISY_BREATH_CV: tuple[float, float] = (0.15, 0.25)
NOISY_OUTLIER_FRAC: tuple[float, float] = (0.03, 0.03)
#: The slow wearer's per-person τ range in s (WearerKind.SLOW).
SLOW_TAU_S: tuple[float, float] = (30.0, 60.0)

#: What ``--wearer`` accepts.
WEARER_CHOICES: tuple[str, ...] = tuple(k.value for k in WearerKind)


@runtime_checkable
class Wearer(Protocol):
    """What a simulation (the virtual cart, the in-process loops, the summaries) uses of a wearer."""

    space: ParameterSpace
    seed: int
    body_mass_kg: float

    @property
    def t_s(self) -> float: ...

    @property
    def baseline_cost_w(self) -> float: ...

    @property
    def true_optimum(self) -> tuple[dict[str, float], float]: ...

    @property
    def subject(self) -> dict[str, Any]: ...

    def true_cost_w(self, params: Mapping[str, float], t_s: float | None = None) -> float: ...

    def adaptation_factor(self, t_s: float) -> float: ...

    def apply_profiles(self, profiles: Sequence[ForceProfile], t_s: float) -> float: ...

    def apply_params(self, params: Mapping[str, float], t_s: float) -> float: ...

    def next_breath(self) -> BreathRecord: ...

    def breaths_until(self, t_s: float) -> list[BreathRecord]: ...


def wearer_kind(kind: WearerKind | str) -> WearerKind:
    """``kind`` as a :class:`WearerKind`.

    Raises:
        ConfigError: Not a wearer kind (names the value and the choices).
    """
    if isinstance(kind, WearerKind):
        return kind
    try:
        return WearerKind(kind)
    except ValueError as err:
        raise ConfigError(f"wearer={kind!r}; expected one of {', '.join(WEARER_CHOICES)}") from err


def make_wearer(kind: WearerKind | str, space: ParameterSpace, seed: int,
                body_mass_kg: float = 75.0) -> Wearer:
    """A simulated wearer of ``kind`` with its default population constants.

    Args:
        kind: :class:`WearerKind` or its value (``"realistic"``, ``"noisy"``, ``"slow"``,
            ``"legacy"``).
        space: The parameter space.
        seed: The subject seed.
        body_mass_kg: The subject's mass in kg.

    Raises:
        ConfigError: Unknown kind, or bad space, seed or mass.
    """
    k = wearer_kind(kind)
    if k is WearerKind.LEGACY:
        return SimulatedWearer(space, seed=seed, body_mass_kg=body_mass_kg)
    # The realistic wearer's variants differ from it in their population ranges only.
    ranges: dict[WearerKind, dict[str, tuple[float, float]]] = {
        WearerKind.NOISY: {"noise_cv": NOISY_BREATH_CV, "outlier_frac": NOISY_OUTLIER_FRAC},
        WearerKind.SLOW: {"tau_s": SLOW_TAU_S},
    }
    config = RealisticWearerConfig(**ranges.get(k, {}))
    return RealisticWearer(space, seed=seed, config=config, body_mass_kg=body_mass_kg)
