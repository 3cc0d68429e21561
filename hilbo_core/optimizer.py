"""HILOptimizer: Algorithm 1 of Kim et al. 2019 as an ask/tell state machine driven one breath at a time.

Phases (Kim et al. 2019 §II.A, Algorithm 1):

1. **Exploration** — ``n_explore`` space-filling points, each measured for the full
   ``max_breaths`` (N) breaths; their estimate traces (M, Σ) are kept.
2. **Thresholds** — Algorithm 2 turns the traces into the threshold vector A (window W).
3. **Optimisation** — until the budget is spent: fit the GP to every evaluation's (μ, σ²), take
   x_t = argmax EI, then after every breath compare the running estimate with the incumbent x*
   and stop early when μ − μ* > A_i·σ (the σ-scaled offset rule, §II.D), or at N breaths.
   The default ``stopping = "sound"`` (hilbo's rule) makes three changes: the incumbent's (μ*, σ*²) is
   the GP posterior at x* (not its raw, optimistically biased estimate), no decision is made
   before ``min_decision_s`` in the setting, and the threshold is floored at ``a_floor`` ≥ 0,
   with sequential reject and accept boundaries that are strict early and reach their late
   levels at ``boundary_s`` (:class:`~hilbo_core.stopping.SoundRule`); the candidate's estimate
   starts from the GP's predictive at x_t (``gp_prior_stopping``), which carries at most half of
   the decision's weight (``gp_prior_max_share``). ``"sound-floor"`` is the same
   rule on a fixed 60 s clock (the earlier default); ``"adaptive"`` is Kim et al. 2019's rule
   unchanged.

The GP is told each evaluation's estimator mean *and* variance: an early-stopped estimate is
noisier, and the model must know (shared/DESIGN.md). It is told the *data-only* part
(``Evaluation.obs_mean``/``obs_var``: the estimator's posterior with its own prior on c divided
out), because the GP has its own prior and must not count the estimator's a
second time. The stopping rule and :meth:`HILOptimizer.best` keep the posterior
(``Evaluation.mean``/``var``): they compare what the estimator believes.

Estimators: ``OptimizerConfig.estimator`` picks the default
:class:`~hilbo_core.estimation.TransitionEstimator` (its docstring says why) or Kim et al. 2019's
:class:`~hilbo_core.metabolic.MetabolicUKF`; an explicit ``estimator_factory`` overrides both.
Each setting's estimator starts from the body level the previous setting's estimator ended at
(when both support it: ``handover()`` / ``start_from_state()``: the level, the noise CV and the
person's τ), since the body does not reset between settings.

Budget: like Algorithm 1's counter t, the budget counts only the optimisation phase (the
exploration bout is a separate walking bout). It may be given in breaths, in seconds of breath
time, or both; it is checked after every breath, and an evaluation still running when the budget
runs out is closed with the estimate it has (reason ``"budget"``). This budget counts breath
time *inside* evaluations only; a session's walking time (setting changes, pauses and warm-ups
included: a lab has the hour it has) is :class:`hilbo_core.protocol.SessionProtocol`'s, which
ends a session with :meth:`HILOptimizer.close_current` on an optimizer without a budget of its own.

Hyperparameter refits: by default the GP's hyperparameters are refitted (multi-start L-BFGS-B
on the marginal likelihood) at every proposal. With ``refit_growth`` G > 1 they are refitted only
once the number of training observations has grown by the factor G since the last fit; in between,
the GP is re-conditioned on all observations with the last hyperparameters. A session of hundreds
of one-measurement evaluations (Kim et al. 2019 §III.2 at high noise) then costs a few dozen fits instead
of one per evaluation, and each new observation still enters the posterior at once. With
``refit_lag`` L >= 1 a proposal reuses hyperparameters fitted on up to L fewer observations; the
caller fits them *ahead*, off the proposal's critical path: :meth:`HILOptimizer.hyperparameter_fit`
describes the fit on the completed evaluations, the free function :func:`fit_hyperparameters`
runs it (anywhere: it is pure and picklable, the bridge runs it in a worker process while the
next setting is measured), and :meth:`HILOptimizer.apply_hyperparameters` keeps the result.

Determinism: every random choice (design, GP restarts, candidate sets) comes from one
``np.random.default_rng(seed)``, so the same seed and the same breaths give the same proposals.
``to_json``/``from_json`` round-trip the whole state, the generator's included.
"""

from __future__ import annotations

import enum
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, dataclass, field, replace
from typing import Any

import numpy as np

from hilbo_core.acquisition import maximize_ei, minimize_lcb
from hilbo_core.errors import ConfigError, MeasurementError, OptimizerStateError
from hilbo_core.estimation import EstimatorKind, StartState, TransitionEstimator
from hilbo_core.gp import GaussianProcess, GPHyperparameters, KernelKind
from hilbo_core.knowledge_gradient import knowledge_gradient_min
from hilbo_core.metabolic import DataOnlyEstimator, DriftAwareEstimator, Estimator, MetabolicUKF
from hilbo_core.space import DesignKind, ParameterSpace
from hilbo_core.stopping import (
    FixedIntervalRule,
    SigmaScaledRule,
    SoundRule,
    StopDecision,
    StoppingRule,
    StopReason,
    threshold_schedule,
)

__all__ = [
    "DEFAULT_ACCEPT_Z",
    "FLOOR_ACCEPT_Z",
    "SOUND_PRIOR_MEAN_SD",
    "AcquisitionKind",
    "BreathStep",
    "Confirmation",
    "EIBestKind",
    "EstimatorKind",
    "Evaluation",
    "HILOptimizer",
    "HyperparameterFit",
    "OptimizerConfig",
    "Phase",
    "PriorObservation",
    "RecommendKind",
    "StoppingKind",
    "fit_hyperparameters",
]

_STATE_VERSION = 1
# Feasible Sobol points added to the knowledge gradient's reference set with "kg-global".
_KG_GLOBAL_REFERENCE = 128
# Generator stream of fits made ahead (HyperparameterFit.seed), apart from the optimizer's own.
_FIT_AHEAD_STREAM = 0xF17
_MAX_WATTS = 5000.0
# The sound rule's accept stop: the late level of its sequential accept boundary. A candidate
# 2 σ better than the incumbent has beaten it at the conventional two-sided 95 % (one-sided
# 2.3 % at one look, if the σ is calibrated); the boundary is 2.8 σ at 30 s and reaches 2 σ at
# boundary_s (SoundRule: the O'Brien-Fleming shape at most doubles the one-look error). Chosen
# as the conventional margin, not tuned (docs/results.md, "Stopping on pairs").
DEFAULT_ACCEPT_Z = 2.0
# The floor rule's (stopping "sound-floor", the earlier default) accept stop: 3 σ at one look
# after its fixed 60 s clock, where no sequential boundary guards the earlier looks.
FLOOR_ACCEPT_Z = 3.0
# Seconds before any decision, by rule: the sequential boundary guards 30-60 s itself, so its
# hard floor is where the first breaths stop being mostly the previous setting's (SoundRule);
# the floor rule has only its clock.
SEQUENTIAL_MIN_DECISION_S = 30.0
FLOOR_MIN_DECISION_S = 60.0
# The GP's prior mean with the sound rules, in SDs of the observed costs above their average
# (OptimizerConfig.prior_mean_sd argues it). A round, mild value, not tuned: 0.25-1.0 all beat
# the average on the simulated wearers (docs/hour_answer.md).
SOUND_PRIOR_MEAN_SD = 0.5


class Phase(enum.Enum):
    """Where Algorithm 1 is."""

    EXPLORATION = "exploration"
    OPTIMIZATION = "optimization"
    DONE = "done"


class StoppingKind(enum.Enum):
    """Which rule ends an evaluation in the optimisation phase."""

    SOUND = "sound"  # the default: SoundRule with sequential boundaries, GP-posterior incumbent
    SOUND_FLOOR = "sound-floor"  # the same on a fixed 60 s clock (the earlier default)
    ADAPTIVE = "adaptive"  # Algorithm 2 thresholds + σ-scaled offset rule (Kim et al. 2019 §II.D)
    FIXED = "fixed"  # always N breaths (fixed-interval BO, Kim et al. 2019's baseline)

    @property
    def is_sound(self) -> bool:
        """hilbo's rule (GP-posterior incumbent, floors), with either clock."""
        return self in (StoppingKind.SOUND, StoppingKind.SOUND_FLOOR)


class EIBestKind(enum.Enum):
    """The incumbent value Expected Improvement improves on."""

    OBSERVED = "observed"  # min(S): the lowest estimate (Kim et al. 2019 §II.B)
    POSTERIOR = "posterior"  # the lowest GP posterior mean among the evaluated settings (noisy EI)


class AcquisitionKind(enum.Enum):
    """How the optimizer chooses the next setting to measure."""

    EI = "ei"  # Expected Improvement (Kim et al. 2019 §II.B)
    # The knowledge gradient over the measured settings and the candidate (KGCP; Scott, Frazier
    # & Powell 2011; hilbo_core/knowledge_gradient.py): the expected fall of the lowest posterior
    # mean after one measurement, with that measurement's noise.
    KG = "kg"
    # The same over the measured settings and feasible Sobol points as well: the minimum it
    # values is then the recommendation's, over the whole feasible set (RecommendKind.GLOBAL).
    KG_GLOBAL = "kg-global"
    # EI until the optimizer's clock reaches OptimizerConfig.kg_from_s, then "kg-global": EI's
    # exploration to find the basin first, then measurements where they improve the
    # recommendation.
    EI_THEN_KG = "ei-then-kg"


class RecommendKind(enum.Enum):
    """How :meth:`HILOptimizer.best` picks the recommended setting."""

    # The default with the sound rule: over the whole feasible set, the lowest GP posterior mean
    # plus recommend_beta posterior SDs (acquisition.minimize_lcb), reported with the GP
    # posterior there. Restricting the choice to measured settings costs the most: among ~30
    # settings measured once with SD 7-10 W, where the good ones differ by 5-15 W, the one that
    # looks best is mostly the luckiest (the winner's curse); the GP pools every measurement.
    GLOBAL = "global"
    # Among the evaluated settings, the lowest GP posterior mean plus recommend_beta posterior
    # SDs, reported with the GP posterior there.
    POSTERIOR = "posterior"
    # Kim et al. 2019's: the lowest GP posterior mean, reported with that evaluation's own estimate.
    SEED = "seed"


@dataclass(frozen=True)
class OptimizerConfig:
    """Everything that defines an optimizer run besides the space.

    Attributes:
        n_explore: Exploration points E (>= 1).
        max_breaths: Maximum measurements per evaluation N (>= 2).
        window: Algorithm 2's window W (>= 0).
        budget_s: Optimisation-phase budget in seconds of breath time, or None.
        budget_breaths: Optimisation-phase budget in breaths, or None.
        stopping: ``"sound"`` (the default, :class:`~hilbo_core.stopping.SoundRule` with
            sequential boundaries and the incumbent from the GP posterior), ``"sound-floor"`` (the
            same rule on a fixed clock, the earlier default), ``"adaptive"`` (Kim et al. 2019's
            Algorithm 1/2) or ``"fixed"``.
        min_decision_s: The sound rule's time in a setting before any stop decision (s, >= 0);
            None (default): 30 s with ``"sound"`` (the first 30 s are mostly the previous
            setting's breaths; the boundary guards the rest), 60 s with the other rules (the floor
            rule's clock ≈ 1.5 × the 42 s of Selinger & Donelan 2014, see SoundRule).
        boundary_s: ``"sound"``'s seconds in a setting at which its sequential boundaries reach
            their late levels ``a_floor`` and ``accept_z`` (> 0; default 60 s, the floor rule's
            clock); before it they are ``sqrt(boundary_s / t)`` times higher (SoundRule).
        a_floor: The sound rule's threshold floor in σ (>= 0; default 1.0).
        accept_z: The sound rule's accept stop in σ (>= 0; default 2, :data:`DEFAULT_ACCEPT_Z`;
            the floor rule's was 3, :data:`FLOOR_ACCEPT_Z`), or None (off): after
            ``min_decision_s``, end an evaluation whose candidate is already ``accept_z`` σ (times
            the boundary's factor) better than the incumbent (reason ``"decided"``; not an early
            rejection, see SoundRule). The candidate has beaten the incumbent, so its remaining breaths are
            better spent on the next setting (the project's target is ≥ 25 % fewer breaths than N
            on pairs of transitions where half the candidates are better; docs/results.md).
        gp_prior_stopping: With the sound rule, the candidate's estimate for the stop decision
            is the estimator's data-only estimate times the GP's predictive at x_t (the Bayesian
            early decision); the GP is still told the data-only part.
        gp_prior_max_share: With ``gp_prior_stopping``, the largest share of the decision's
            precision the GP's predictive may carry, in (0, 1] (default 0.5: at most as much as
            the setting's own breaths; 1: the plain Gaussian product). Late in a session EI
            proposes settings the GP already rates well above the incumbent with an SD of
            30-40 W, and 30 s of noisy breaths carry an SD of 75-150 W: the plain product
            then rejects at the first look on the GP's word alone, and a noisy wearer saw 20
            settings in a row, truly better ones among them, cut after 11 breaths that told
            nothing (docs/hour_answer.md). A reject must rest on the setting's own breaths.
        recommend: ``"global"``, ``"posterior"`` or ``"seed"``, see :class:`RecommendKind`;
            None (default) means ``"global"`` with the sound rule and ``"seed"`` with the seed's
            rules.
        recommend_beta: The posterior recommendation's penalty in posterior SDs (>= 0): a
            setting measured for a few breaths only (or not at all) has a wide posterior and is
            not recommended on the strength of a lucky estimate.
        explore_rel_sd: Exploration settings end once their estimate's SD is at most this
            fraction of the estimate, after ``min_decision_s`` in the setting (or at N breaths);
            None (default): every exploration setting is measured for N breaths (the seed's
            Algorithm 1). Algorithm 2 then reads each shorter trace as if its last estimate had
            held to N.
        acquisition: ``"ei"`` (default, Expected Improvement), ``"kg"`` (the knowledge
            gradient, :mod:`hilbo_core.knowledge_gradient`: the value of one more measurement to
            the recommendation, with that measurement's noise; the measured settings are
            candidates too, so a promising setting may be measured again), ``"kg-global"`` (the
            same over the feasible set) or ``"ei-then-kg"``, see :class:`AcquisitionKind`
            (docs/noisy_wearer.md measures them).
        kg_from_s: With ``"ei-then-kg"``, the optimizer's clock (s of breath time in its
            evaluations, exploration included) from which it proposes by the knowledge gradient
            (> 0; default 1620 s: minute 30 of a session that starts with a 3-minute warm-up).
        prior_mean_sd: The GP's constant prior mean, in standard deviations of the observed
            costs above their average (:meth:`GaussianProcess.fit
            <hilbo_core.gp.GaussianProcess.fit>`); None (default): 0.5 with the sound rules, 0
            with the seed's (Kim et al. 2019's GP: the average). Far from every measurement the
            posterior returns to this mean. At the average, an unmeasured region looks as good
            as the settings measured so far and, with the largest posterior SD, EI's best bet:
            in 6-D the search then spends its first proposals at the cube's boundary (the
            known boundary over-exploration of GP-BO with stationary kernels, Siivola et al.
            2018, IEEE MLSP); on the simulated wearers those proposals were worse than random
            feasible settings (docs/noisy_wearer.md, "Diagnosis"). But the
            settings measured are not a random sample: the exploration design covers the space
            and every later one was chosen as promising, so an unmeasured setting is expected to
            cost more than their average. Half an SD of the observed costs says so mildly: the
            posterior SD far away (≈ 1 SD of the costs) still leaves EI room to go there.
            docs/hour_answer.md measures it.
        ei_best: The value EI improves on: ``"observed"`` (default: min(S), the seed's) or
            ``"posterior"`` (the lowest posterior mean among the evaluated settings: noisy EI's
            plug-in incumbent).
        drift_hours: Adaptation drift (the cost of every setting falls slowly over the hour as the
            wearer adapts; virtual_hw/wearer_realistic.py): with a number, the GP gets the
            session time of each evaluation as an extra input, with a length-scale prior of
            median ``drift_hours`` h (long relative to the session: the cost drifts slowly), and
            predicts every setting (x*, the recommendation, EI) *now*; None (default) ignores
            time. The clock is the optimizer's: breath time of all evaluations so far.
        drift_corr_s: Correlation time in s of the estimator's model error (its share of each
            observation's variance, :class:`~hilbo_core.metabolic.DriftAwareEstimator`): the drift
            of a real steady state is one error that settings measured minutes apart share, not
            an independent error per setting. With a number the GP's errors are correlated as
            exp(−Δt²/(2·drift_corr_s²)) in the drift's share (Δt on the optimizer's clock, between
            the evaluations' ends), the GP's f is the landscape without the drift, and the stop
            decision compares the candidate with the incumbent plus the drift inferred now. A
            steady state drifts by about ±1 %/min with an SD of about 3 % within minutes
            (docs/results.md, the estimator's model error): a smooth process of SD s and RMS rate
            r has a time scale s/r ≈ 3 min, hence 180 s. None: independent errors (the earlier
            model).
        trust_region: Half-width (unit cube, in (0, 1]) of a box around the sound rule's
            incumbent (the evaluated setting of lowest posterior mean) inside which EI's candidates
            are drawn, without local refinement, so no proposal leaves the box; None (default):
            the whole feasible set. Under breath noise the GP of a 6-D landscape can stay nearly
            flat (length-scales at their prior), and EI then goes where the posterior SD is
            largest, the boundary of the cube (Eriksson et al. 2019, TuRBO, NeurIPS: a local
            model's region keeps the search where the data are).
        trust_region_alternate: With ``trust_region``, every other proposal (those after an
            odd number of evaluations) is over the whole feasible set, so the box cannot trap
            the search near a mediocre incumbent.
        seed: Seed of the run's random generator.
        xi: EI's ξ (Kim et al. 2019 §II.B sign convention).
        kernel: ``"matern52"`` or ``"se"``.
        n_candidates: Feasible Sobol candidates per EI maximisation.
        n_local: Candidates refined locally per EI maximisation.
        refit_growth: Refit the GP hyperparameters when the number of training observations
            (evaluations + fast-prior points) has grown by at least this factor since the last
            fit (finite, >= 1). 1.0, the default, refits at every proposal; in between refits the
            GP is re-conditioned on all observations with the last fitted hyperparameters. The
            stopping rule's incumbent uses the proposal's model; between refits, so does the
            recommendation (:meth:`HILOptimizer.best`).
        refit_lag: With L >= 1, a proposal refits the hyperparameters only when the stored ones
            were fitted on more than L fewer observations than it conditions on; the caller keeps
            them fresh with :meth:`HILOptimizer.hyperparameter_fit` + :func:`fit_hyperparameters`
            + :meth:`HILOptimizer.apply_hyperparameters` (fitting *ahead*, e.g. while the next
            setting is measured, so no proposal waits for a fit). 0, the default, leaves refits to
            ``refit_growth``. The two are exclusive: L >= 1 needs ``refit_growth`` = 1.
        estimator: ``"transition"`` (the default, :class:`~hilbo_core.estimation.TransitionEstimator`)
            or ``"seed_ukf"`` (Kim et al. 2019's :class:`~hilbo_core.metabolic.MetabolicUKF`). Ignored
            when the optimizer is given an ``estimator_factory``.
        design: The exploration bout's settings (:class:`~hilbo_core.space.DesignKind`):
            ``"sobol"`` (the centre, then scrambled Sobol points) or ``"maximin"`` (the centre,
            then greedy maximin: the design of earlier versions, which pushes the other points to
            the boundary of the feasible set). None (default): ``sobol`` with the sound rule,
            ``maximin`` with Kim et al. 2019's rules, so ``adaptive`` and ``fixed`` stay the methods
            they were (like ``recommend``).
    """

    n_explore: int = 6
    max_breaths: int = 45
    window: int = 2
    budget_s: float | None = None
    budget_breaths: int | None = None
    stopping: StoppingKind = StoppingKind.SOUND
    min_decision_s: float | None = None
    boundary_s: float = 60.0
    a_floor: float = 1.0
    accept_z: float | None = DEFAULT_ACCEPT_Z
    gp_prior_stopping: bool = True
    gp_prior_max_share: float = 0.5
    recommend: RecommendKind | None = None
    recommend_beta: float = 1.0
    explore_rel_sd: float | None = None
    acquisition: AcquisitionKind = AcquisitionKind.EI
    kg_from_s: float = 1620.0
    ei_best: EIBestKind = EIBestKind.OBSERVED
    prior_mean_sd: float | None = None
    drift_hours: float | None = None
    drift_corr_s: float | None = None
    trust_region: float | None = None
    trust_region_alternate: bool = False
    seed: int = 0
    xi: float = 0.0
    kernel: KernelKind = KernelKind.MATERN52
    n_candidates: int = 1024
    n_local: int = 3
    refit_growth: float = 1.0
    refit_lag: int = 0
    estimator: EstimatorKind = EstimatorKind.TRANSITION
    design: DesignKind | None = None

    def _enum(self, name: str, enum_cls: type[enum.Enum]) -> None:
        """Convert field ``name`` to ``enum_cls`` (from a member or its value), else ConfigError."""
        value = getattr(self, name)
        try:
            object.__setattr__(self, name, enum_cls(value))
        except ValueError as err:
            raise ConfigError(
                f"{name}={value!r}; expected one of {[k.value for k in enum_cls]}") from err

    def __post_init__(self) -> None:
        self._enum("estimator", EstimatorKind)
        self._enum("stopping", StoppingKind)
        # The sound rule comes with the posterior recommendation and the Sobol design; Kim et
        # al. 2019's rules keep their recommendation and the maximin design, so "adaptive" and
        # "fixed" stay the methods they were.
        sound = self.stopping.is_sound
        if self.min_decision_s is None:
            object.__setattr__(self, "min_decision_s", SEQUENTIAL_MIN_DECISION_S
                               if self.stopping is StoppingKind.SOUND else FLOOR_MIN_DECISION_S)
        if self.recommend is None:
            object.__setattr__(self, "recommend", RecommendKind.GLOBAL if sound else RecommendKind.SEED)
        if self.design is None:
            object.__setattr__(self, "design", DesignKind.SOBOL if sound else DesignKind.MAXIMIN)
        if self.prior_mean_sd is None:
            object.__setattr__(self, "prior_mean_sd", SOUND_PRIOR_MEAN_SD if sound else 0.0)
        object.__setattr__(self, "prior_mean_sd", _number(
            "prior_mean_sd", self.prior_mean_sd, lambda v: 0.0 <= v <= 3.0,
            "a number of SDs in [0, 3] or None"))
        self._enum("design", DesignKind)
        self._enum("recommend", RecommendKind)
        self._enum("ei_best", EIBestKind)
        self._enum("acquisition", AcquisitionKind)
        for name in ("min_decision_s", "a_floor", "recommend_beta"):
            object.__setattr__(self, name, _number(name, getattr(self, name), lambda v: v >= 0.0,
                                                   "a finite number >= 0"))
        object.__setattr__(self, "boundary_s", _number(
            "boundary_s", self.boundary_s, lambda v: v > 0.0, "a finite number of seconds > 0"))
        if self.accept_z is not None:
            object.__setattr__(self, "accept_z", _number(
                "accept_z", self.accept_z, lambda v: v >= 0.0, "a finite number >= 0 or None"))
        if not isinstance(self.gp_prior_stopping, bool):
            raise ConfigError(f"gp_prior_stopping={self.gp_prior_stopping!r}; expected true or false")
        object.__setattr__(self, "gp_prior_max_share", _number(
            "gp_prior_max_share", self.gp_prior_max_share, lambda v: 0.0 < v <= 1.0,
            "a share in (0, 1]"))
        r = self.explore_rel_sd
        if r is not None and (isinstance(r, bool) or not isinstance(r, int | float)
                              or not (math.isfinite(r) and 0 < r < 1)):
            raise ConfigError(f"explore_rel_sd={r!r}; expected a fraction in (0, 1) or None")
        _positive("drift_hours", self.drift_hours, "hours", optional=True)
        _positive("kg_from_s", self.kg_from_s, "seconds", optional=False)
        _positive("drift_corr_s", self.drift_corr_s, "seconds", optional=True)
        tr = self.trust_region
        if tr is not None:
            if (isinstance(tr, bool) or not isinstance(tr, int | float | np.integer | np.floating)
                    or not (math.isfinite(tr) and 0.0 < tr <= 1.0)):
                raise ConfigError(
                    f"trust_region={tr!r}; expected a half-width in (0, 1] of the unit cube or None")
            object.__setattr__(self, "trust_region", float(tr))
        if not isinstance(self.trust_region_alternate, bool):
            raise ConfigError(
                f"trust_region_alternate={self.trust_region_alternate!r}; expected true or false")
        try:
            object.__setattr__(self, "kernel", KernelKind(self.kernel))
        except ValueError as err:
            raise ConfigError(
                f"kernel={self.kernel!r}; expected one of {[k.value for k in KernelKind]}"
            ) from err
        _int_at_least("n_explore", self.n_explore, 1)
        _int_at_least("max_breaths", self.max_breaths, 2)
        _int_at_least("window", self.window, 0)
        _int_at_least("seed", self.seed, 0)
        _int_at_least("n_candidates", self.n_candidates, 16)
        _int_at_least("n_local", self.n_local, 0)
        if self.budget_s is not None and not (math.isfinite(self.budget_s) and self.budget_s > 0):
            raise ConfigError(f"budget_s={self.budget_s!r}; expected a positive number of seconds or None")
        if self.budget_breaths is not None:
            _int_at_least("budget_breaths", self.budget_breaths, 1)
        if not math.isfinite(self.xi):
            raise ConfigError(f"xi={self.xi!r}; expected a finite number")
        growth = self.refit_growth
        if (isinstance(growth, bool) or not isinstance(growth, int | float | np.integer | np.floating)
                or not (math.isfinite(growth) and growth >= 1.0)):
            raise ConfigError(
                f"refit_growth={growth!r}; expected a finite factor >= 1.0 (1.0 = refit at every proposal)"
            )
        object.__setattr__(self, "refit_growth", float(growth))
        _int_at_least("refit_lag", self.refit_lag, 0)
        if self.refit_lag and self.refit_growth != 1.0:
            raise ConfigError(
                f"refit_lag={self.refit_lag!r} with refit_growth={self.refit_growth!r}; expected one "
                "of them only (refit_lag >= 1 needs refit_growth = 1.0)"
            )

    def to_json(self) -> dict[str, Any]:
        """JSON-able form."""
        d = asdict(self)
        d["stopping"] = self.stopping.value
        d["recommend"] = RecommendKind(self.recommend).value
        d["kernel"] = self.kernel.value
        d["estimator"] = self.estimator.value
        d["design"] = DesignKind(self.design).value
        d["ei_best"] = self.ei_best.value
        d["acquisition"] = self.acquisition.value
        return d

    @classmethod
    def from_json(cls, data: Mapping[str, Any]) -> OptimizerConfig:
        """Inverse of :meth:`to_json`; unknown keys are an error."""
        allowed = set(cls.__dataclass_fields__)
        unknown = sorted(set(data) - allowed)
        if unknown:
            raise ConfigError(f"unknown optimizer option(s) {unknown}; allowed: {sorted(allowed)}")
        return cls(**data)


def _number(name: str, value: object, ok: Callable[[float], bool], expected: str) -> float:
    """``value`` as a float if it is a finite real number (not a bool) for which ``ok`` holds,
    else ConfigError naming ``name`` and what was ``expected``."""
    if (isinstance(value, bool) or not isinstance(value, int | float | np.integer | np.floating)
            or not (math.isfinite(value) and ok(float(value)))):
        raise ConfigError(f"{name}={value!r}; expected {expected}")
    return float(value)


def _positive(name: str, value: object, unit: str, *, optional: bool) -> None:
    """ConfigError unless ``value`` is a finite number > 0 (or None when ``optional``)."""
    if optional and value is None:
        return
    if (isinstance(value, bool) or not isinstance(value, int | float)
            or not (math.isfinite(value) and value > 0)):
        raise ConfigError(f"{name}={value!r}; expected a positive number of {unit}"
                          + (" or None" if optional else ""))


def _int_at_least(name: str, value: object, low: int) -> None:
    if isinstance(value, bool) or not isinstance(value, int | np.integer) or value < low:
        raise ConfigError(f"{name}={value!r}; expected an integer >= {low}")


@dataclass(frozen=True)
class PriorObservation:
    """A cheap observation that enters the GP with its own (inflated) noise (Antonova 2016 §3.3).

    Attributes:
        params: The point, ``{name: value}``.
        mean: Observed cost (W).
        var: Its noise variance (W²) — make it large for cheap sources.
        source: Where it came from (for the log).
    """

    params: Mapping[str, float]
    mean: float
    var: float
    source: str = "prior"


@dataclass(frozen=True)
class Evaluation:
    """One completed evaluation of a setting.

    Attributes:
        index: 0-based evaluation number.
        params: The setting, derived parameters included.
        mean: Estimator mean of the steady-state cost at the end (W).
        var: Its variance (W²).
        breaths: Breaths measured.
        duration_s: Breath time from the setting's start to its last breath (s).
        phase: ``"exploration"`` or ``"optimization"``.
        stopped_early: True when the stopping rule rejected it before N breaths (reason
            ``"threshold"``); an accept stop, a ``"precise"`` or a ``"budget"`` end is False.
        reason: ``"threshold"``, ``"max_measurements"``, ``"decided"`` (the sound rule's accept
            stop), ``"precise"`` (an exploration setting ended by ``explore_rel_sd``),
            ``"budget"`` or ``"told"``.
        obs_mean: The data-only mean the GP is told (W): the posterior with the estimator's
            prior on c divided out; None means ``mean`` (estimators without ``data_only()``,
            :meth:`HILOptimizer.tell`, states written before the data-only observations existed).
        obs_var: Its variance (W²); None means ``var``.
        drift_var: The model error's share of ``obs_var`` (W²,
            :class:`~hilbo_core.metabolic.DriftAwareEstimator`); None: none known.
    """

    index: int
    params: dict[str, float]
    mean: float
    var: float
    breaths: int
    duration_s: float
    phase: str
    stopped_early: bool
    reason: str
    obs_mean: float | None = None
    obs_var: float | None = None
    drift_var: float | None = None

    @property
    def gp_observation(self) -> tuple[float, float]:
        """(mean, var) the GP is told: the data-only pair, else the posterior."""
        if self.obs_mean is None or self.obs_var is None:
            return self.mean, self.var
        return self.obs_mean, self.obs_var

    def to_json(self) -> dict[str, Any]:
        """JSON-able form."""
        return asdict(self)


@dataclass(frozen=True)
class BreathStep:
    """What one breath did.

    Attributes:
        stop: The current evaluation ended with this breath; the next ``ask()`` moves on.
        mean: Estimator mean of the current setting's steady-state cost (W).
        var: Its variance (W²).
        index: 0-based breath index within the evaluation.
        phase: Phase the breath belonged to.
        decision: The stopping rule's decision (None while exploring).
        evaluation: The completed evaluation when ``stop`` is True.
    """

    stop: bool
    mean: float
    var: float
    index: int
    phase: Phase
    decision: StopDecision | None = None
    evaluation: Evaluation | None = None


@dataclass(frozen=True)
class Confirmation:
    """The recommendation measured in full at the session's end (:meth:`HILOptimizer.begin_confirmation`).

    Its estimate comes from the confirmation's own breaths only, which were not chosen for
    looking good, so it is an unbiased measurement of the recommendation (the recommendation's
    GP estimate is the best bet but, like any minimum, optimistic).

    Attributes:
        params: The recommended setting (frozen when the confirmation began).
        predicted_mean_w: The GP posterior mean of its cost when it was chosen (W).
        predicted_sd_w: Its posterior SD (W).
        mean_w: The confirmation's estimate (W; the data-only estimates of its completed
            evaluations pooled by inverse variance), or None before one completed.
        sd_w: Its SD (W), or None.
        breaths: Breaths measured in the completed confirmation evaluations.
        n_evaluations: Completed confirmation evaluations.
    """

    params: dict[str, float]
    predicted_mean_w: float
    predicted_sd_w: float
    mean_w: float | None
    sd_w: float | None
    breaths: int
    n_evaluations: int

    def to_json(self) -> dict[str, Any]:
        """JSON-able form."""
        return asdict(self)

    def describe(self) -> str:
        """One line: "recommended, confirmed at X ± Y W (n breaths)" or "... not yet confirmed"."""
        if self.mean_w is None or self.sd_w is None:
            return (f"recommended (predicted {self.predicted_mean_w:.0f} ± {self.predicted_sd_w:.0f} W), "
                    "confirmation not completed")
        return (f"recommended, confirmed at {self.mean_w:.0f} ± {self.sd_w:.0f} W "
                f"({self.breaths} breaths; predicted {self.predicted_mean_w:.0f} ± "
                f"{self.predicted_sd_w:.0f} W)")


@dataclass
class _Current:
    params: dict[str, float]
    x: np.ndarray
    phase: Phase
    breaths: list[tuple[float, float]] = field(default_factory=list)
    means: list[float] = field(default_factory=list)
    vars: list[float] = field(default_factory=list)
    # The GP's predictive (mean, var) of the setting's cost when it was proposed (the sound
    # rule's prior for the candidate), or None.
    prior: tuple[float, float] | None = None
    # A confirmation of the recommended setting (begin_confirmation): never stopped early.
    remeasure: bool = False


@dataclass(frozen=True, eq=False)
class HyperparameterFit:
    """One GP hyperparameter fit, described completely (picklable: it may run in another process).

    Made by :meth:`HILOptimizer.hyperparameter_fit`, run by :func:`fit_hyperparameters`, its
    result kept by :meth:`HILOptimizer.apply_hyperparameters`.

    Attributes:
        kernel: The GP's kernel.
        X_unit: Training points in the unit cube, shape (n, d).
        y: Their estimated costs (W), shape (n,).
        var: Their variances (W²), shape (n,).
        init: Warm start (the last fitted hyperparameters), or None.
        seed: Entropy of the fit's own generator (the multi-start points), derived from the
            optimizer's seed and n, so a fit gives the same result wherever and whenever it runs.
        noise_corr: The observations' error correlation (``OptimizerConfig.drift_corr_s``),
            shape (n, n), or None: the fit's likelihood is the proposals'.
        prior_mean_sd: The GP's prior mean (``OptimizerConfig.prior_mean_sd``).
    """

    kernel: KernelKind
    X_unit: np.ndarray
    y: np.ndarray
    var: np.ndarray
    init: GPHyperparameters | None
    seed: tuple[int, ...]
    noise_corr: np.ndarray | None = None
    prior_mean_sd: float = 0.0

    @property
    def n_obs(self) -> int:
        """Training observations n."""
        return int(self.y.size)


def fit_hyperparameters(fit: HyperparameterFit) -> GPHyperparameters:
    """Run a :class:`HyperparameterFit`: MAP marginal likelihood, multi-start L-BFGS-B (gp.py).

    Pure: the same ``fit`` gives the same hyperparameters in any process.
    """
    gp = GaussianProcess(fit.kernel)
    gp.fit(fit.X_unit, fit.y, fit.var, rng=np.random.default_rng(fit.seed), init=fit.init,
           optimize=True, noise_corr=fit.noise_corr, prior_mean_sd=fit.prior_mean_sd)
    return gp.hyperparameters


class HILOptimizer:
    """Human-in-the-loop Bayesian optimisation with the estimator stopping process.

    Args:
        space: The feasible parameter space.
        n_explore, max_breaths, window, budget_s, budget_breaths, stopping, seed, xi, kernel,
            n_candidates, n_local, refit_growth: See :class:`OptimizerConfig`.
        config: A whole :class:`OptimizerConfig` instead of the keywords.
        estimator_factory: Returns a fresh estimator per evaluation (default: the one
            ``config.estimator`` names). Benchmarks pass the Gaussian-product model of §III.2.
        prior_observations: Fast-prior observations (Antonova 2016 §3.3) added to the GP.

    Example:
        >>> opt = HILOptimizer(presets.hip_6d(), n_explore=6, max_breaths=45, budget_s=2400)
        >>> params = opt.ask()
        >>> step = opt.observe_breath(t=3.1, watts=412.0)
    """

    def __init__(
        self,
        space: ParameterSpace,
        *,
        config: OptimizerConfig | None = None,
        estimator_factory: Callable[[], Estimator] | None = None,
        prior_observations: Sequence[PriorObservation] = (),
        **options: Any,
    ) -> None:
        if config is not None and options:
            raise ConfigError(f"pass either config= or keyword options, not both (got {sorted(options)})")
        if config is None:
            try:
                config = OptimizerConfig(**options)
            except TypeError as err:
                raise ConfigError(
                    f"unknown optimizer option in {sorted(options)}; allowed: "
                    f"{sorted(OptimizerConfig.__dataclass_fields__)}"
                ) from err
        self.space = space
        self.config = config
        self._estimator_factory: Callable[[], Estimator] = (
            estimator_factory if estimator_factory is not None else _ESTIMATORS[config.estimator])
        # What the last setting's estimator handed over (body level, noise CV, τ), which the
        # next setting's transition starts from (the body does not reset between settings).
        self._handover: StartState | None = None
        self._priors: list[PriorObservation] = []
        for p in prior_observations:
            self.add_prior(p)
        self._rng = np.random.default_rng(config.seed)
        self._design = space.design(config.n_explore, self._rng, kind=DesignKind(config.design))
        self._evaluations: list[Evaluation] = []
        self._traces_m: list[list[float]] = []
        self._traces_s: list[list[float]] = []
        self._thresholds: np.ndarray | None = None
        self._current: _Current | None = None
        # The setting cancel_current() abandoned, until the next ask() (ask_again() restarts it).
        self._cancelled: _Current | None = None
        self._estimator: Estimator | None = None
        # Breaths the estimators left out as implausible for the level, in settings already
        # ended (this process's; TransitionEstimator.n_flagged).
        self._flagged_done = 0
        self._hyp: GPHyperparameters | None = None
        # Training observations when self._hyp was fitted (None: never, or unknown after loading
        # an older state; either way the next proposal refits).
        self._n_at_fit: int | None = None
        # Unit-cube points of the first len(_units) evaluations, and the last of them (see
        # _evaluation_units): one array, so a pickled optimizer (the bridge's proposal worker
        # receives one per proposal) carries one array, not one small array per evaluation.
        self._units: np.ndarray = np.empty((0, space.dim))
        self._units_last: Evaluation | None = None
        self._incumbent: tuple[dict[str, float], float, float] | None = None
        # The drift inferred when the current candidate was proposed (W, drift_corr_s): the
        # stop decision's incumbent reads this much higher now.
        self._drift_now_w = 0.0
        # Set by _propose for the setting ask() is about to start (see _Current).
        self._pending: tuple[tuple[float, float] | None, bool] = (None, False)
        # The confirmation (begin_confirmation): (params, predicted mean, predicted var) and the
        # index of its first evaluation; None before.
        self._confirm: tuple[dict[str, float], float, float] | None = None
        self._confirm_from = 0
        self._confirm_requested = False
        self._opt_breaths = 0
        self._opt_seconds = 0.0

    # ------------------------------------------------------------------ read-only views
    @property
    def phase(self) -> Phase:
        """Current phase of Algorithm 1."""
        if len(self._evaluations) < self.config.n_explore:
            return Phase.EXPLORATION
        if self._budget_spent():
            return Phase.DONE
        return Phase.OPTIMIZATION

    @property
    def done(self) -> bool:
        """The optimisation budget is spent."""
        return self.phase is Phase.DONE

    @property
    def evaluations(self) -> tuple[Evaluation, ...]:
        """Completed evaluations, in order."""
        return tuple(self._evaluations)

    @property
    def thresholds(self) -> np.ndarray | None:
        """Algorithm 2's threshold vector A (N,), once exploration is complete."""
        return None if self._thresholds is None else self._thresholds.copy()

    @property
    def exploration_traces(self) -> tuple[np.ndarray, np.ndarray]:
        """The (M, Σ) matrices of exploration (completed rows only)."""
        n = self.config.max_breaths
        return (np.array(self._traces_m, dtype=float).reshape(-1, n),
                np.array(self._traces_s, dtype=float).reshape(-1, n))

    @property
    def current_params(self) -> dict[str, float] | None:
        """The setting being measured, or None between evaluations."""
        return None if self._current is None else dict(self._current.params)

    @property
    def incumbent(self) -> tuple[dict[str, float], float, float] | None:
        """The stopping rule's x* with its (μ*, σ*²), during the optimisation phase."""
        return self._incumbent

    @property
    def budget_used(self) -> dict[str, float]:
        """Optimisation-phase breaths and seconds used so far (current evaluation included)."""
        return {"breaths": self._opt_breaths, "seconds": self._opt_seconds}

    def best(self) -> tuple[dict[str, float], float, float]:
        """The recommended setting and its estimated cost ``(params, mean_w, var_w2)``.

        Once the confirmed setting is frozen (the first :meth:`ask` after
        :meth:`begin_confirmation`), that setting with the confirmation's own estimate (its
        prediction until an evaluation of it completes).
        Before that, by ``OptimizerConfig.recommend``: ``"global"`` (the default with the sound
        rule): over the whole feasible set, the setting with the lowest GP posterior mean +
        ``recommend_beta`` posterior SDs, reported with the GP posterior (mean, variance of the
        latent cost) there; ``"posterior"``: the same among the evaluated settings. A raw
        estimate is optimistically biased for the setting that looks best (the winner's curse),
        and a setting measured for a few breaths, or not at all, has a wide posterior, so it is
        not recommended on the strength of one lucky estimate. ``"seed"`` (the default with the
        seed's rules): the GP's estimated minimum among the evaluated points (Kim et al. 2019
        §III.2: "x_t be the GP's estimated minimum point"), reported with that evaluation's own
        estimate. Before any GP can be fitted, the lowest estimated mean.
        """
        if not self._evaluations:
            raise OptimizerStateError("no evaluation has completed yet; nothing to recommend")
        conf = self.confirmation
        if conf is not None:
            if conf.mean_w is not None and conf.sd_w is not None:
                return dict(conf.params), conf.mean_w, conf.sd_w**2
            return dict(conf.params), conf.predicted_mean_w, conf.predicted_sd_w**2
        if len(self._evaluations) + len(self._priors) < 2:
            ev = min(self._evaluations, key=lambda e: e.mean)
            return dict(ev.params), ev.mean, ev.var
        # A private generator and no stored hyperparameters: asking for the recommendation
        # (e.g. for a status display) must not change the proposals that follow. Between
        # hyperparameter refits (refit_growth > 1) the generator is unused and the GP is the one
        # the next proposal will condition.
        rng = np.random.default_rng([self.config.seed, len(self._evaluations)])
        gp = self._fit_gp(rng, store=False)
        if self.config.recommend is RecommendKind.SEED:
            return self._gp_best(gp)
        if self.config.recommend is RecommendKind.GLOBAL:
            return self._global_best(gp, rng)
        return self._posterior_best(gp)

    @property
    def confirmation(self) -> Confirmation | None:
        """The confirmation of the recommendation, once :meth:`begin_confirmation` was called."""
        if self._confirm is None:
            return None
        params, p_mean, p_var = self._confirm
        evs = [e for e in self._evaluations[self._confirm_from:] if e.params == params]
        mean = sd = None
        if evs:
            obs = np.array([e.gp_observation for e in evs], dtype=float)
            w = 1.0 / obs[:, 1]
            mean, sd = float(np.sum(w * obs[:, 0]) / np.sum(w)), float(math.sqrt(1.0 / np.sum(w)))
        return Confirmation(params=dict(params), predicted_mean_w=p_mean,
                            predicted_sd_w=math.sqrt(max(p_var, 0.0)), mean_w=mean, sd_w=sd,
                            breaths=sum(e.breaths for e in evs), n_evaluations=len(evs))

    @property
    def confirming(self) -> bool:
        """:meth:`begin_confirmation` has been called (and was not refused)."""
        return self._confirm_requested

    def begin_confirmation(self) -> bool:
        """From the next :meth:`ask` on, measure the recommended setting in full (the session's
        last minutes).

        That ask freezes the recommendation (:meth:`best`: the GP work happens there, in the
        bridge's proposal worker, not here), returns it, and so does every ask after it; its
        evaluations run to N breaths (no early stop; the session's end may cut the last one).
        :attr:`confirmation` then reports it with its own measurement, which :meth:`best`
        returns too. Idempotent and cheap. The driver calls it when the protocol says the
        confirmation is due (:attr:`hilbo_core.protocol.SessionProtocol.confirm_due`).

        Returns:
            True when the confirmation is on; False during exploration (nothing to confirm yet).
        """
        if self._confirm is not None or self._confirm_requested:
            return True
        if len(self._evaluations) < self.config.n_explore or not self._evaluations:
            return False
        self._confirm_requested = True
        return True

    def _freeze_confirmation(self) -> dict[str, float]:
        """The confirmed setting, chosen now if it has not been (:meth:`begin_confirmation`)."""
        if self._confirm is None:
            params, mean, var = self.best()
            self._confirm = (dict(params), float(mean), float(var))
            self._confirm_from = len(self._evaluations)
        return self._confirm[0]

    # ------------------------------------------------------------------ ask / observe / tell
    def ask(self) -> dict[str, float]:
        """The setting to measure now (the same one until its evaluation stops).

        Returns:
            ``{name: value}`` including derived parameters; always feasible.

        Raises:
            OptimizerStateError: The budget is spent.
        """
        if self._current is not None:
            return dict(self._current.params)
        self._cancelled = None
        phase = self.phase
        if phase is Phase.DONE:
            raise OptimizerStateError(
                f"the optimisation budget is spent ({self._opt_breaths} breaths, "
                f"{self._opt_seconds:.0f} s); nothing more to ask"
            )
        if phase is Phase.EXPLORATION:
            x = self._design[len(self._evaluations)]
        elif self._confirm_requested:
            x = self.space.from_dict(self._freeze_confirmation())
            self._pending = (None, True)
        else:
            x = self._propose()
        x = self.space.check(x)
        prior, remeasure = self._pending if phase is Phase.OPTIMIZATION else (None, False)
        self._pending = (None, False)
        self._current = _Current(params=self.space.to_dict(x), x=x, phase=phase, prior=prior,
                                 remeasure=remeasure)
        self._estimator = self._new_estimator()
        return dict(self._current.params)

    def observe_breath(self, t: float, watts: float) -> BreathStep:
        """Feed one breath of the current setting.

        Args:
            t: Seconds since the current setting began (strictly increasing within a setting).
            watts: Metabolic power of this breath in W (e.g. :func:`brockway_watts`).

        Returns:
            The step: running estimate and whether the evaluation stopped.

        Raises:
            OptimizerStateError: No setting is being measured (call ``ask()`` first).
            MeasurementError: Bad t or watts; the optimizer's state is unchanged.
        """
        watts = float(watts)
        if not math.isfinite(watts) or not 0 < watts <= _MAX_WATTS:
            raise MeasurementError(f"watts={watts!r}; expected a finite power in (0, {_MAX_WATTS:g}] W")
        return self.observe(t, watts)

    def observe(self, t: float, value: float) -> BreathStep:
        """Feed one measurement of any objective (benchmarks); no physiological range check.

        Same as :meth:`observe_breath` except that ``value`` only has to be finite, so test
        functions with negative values (Hartmann-6) can be optimised.
        """
        cur = self._current
        if cur is None or self._estimator is None:
            raise OptimizerStateError("observe_breath() before ask(): no setting is being measured")
        t = float(t)
        watts = float(value)
        if not math.isfinite(t) or t < 0:
            raise MeasurementError(
                f"breath time t={t!r}; expected a finite time >= 0 s since the setting began"
            )
        if cur.breaths and t <= cur.breaths[-1][0]:
            raise MeasurementError(
                f"breath time t={t!r} s does not increase (previous breath at {cur.breaths[-1][0]!r} s)"
            )
        if not math.isfinite(watts):
            raise MeasurementError(f"value={watts!r}; expected a finite measurement")
        mean, var = self._estimator.update(t, watts)
        prev_t = cur.breaths[-1][0] if cur.breaths else 0.0
        cur.breaths.append((t, watts))
        cur.means.append(float(mean))
        cur.vars.append(float(var))
        i = len(cur.breaths) - 1
        if cur.phase is Phase.EXPLORATION:
            if i == self.config.max_breaths - 1:
                return self._step(True, "max_measurements", None)
            rel = self.config.explore_rel_sd
            precise = (rel is not None and t >= self.config.min_decision_s
                       and math.sqrt(float(var)) <= rel * abs(float(mean)))
            return self._step(precise, "precise", None)
        self._opt_breaths += 1
        self._opt_seconds += t - prev_t
        rule = self._rule()
        if isinstance(rule, SoundRule):
            c_mean, c_var = self._candidate_estimate(float(mean), float(var))
            decision = rule.decide(i, c_mean, c_var, *self._incumbent_stats(), t_s=t)
        else:
            decision = rule.decide(i, float(mean), float(var), *self._incumbent_stats())
        if decision.stop:
            if decision.reason is StopReason.DECIDED:
                reason = "decided"
            else:
                reason = "threshold" if decision.index < self.config.max_breaths - 1 else "max_measurements"
            return self._step(True, reason, decision)
        if self._budget_spent():
            return self._step(True, "budget", decision)
        return self._step(False, "", decision)

    def tell(self, params: Mapping[str, float], mean: float, var: float, *,
             breaths: int = 0, duration_s: float = 0.0,
             drift_var: float | None = None) -> Evaluation:
        """Add a completed evaluation measured outside the breath loop.

        Only allowed between evaluations. Counts as an optimisation-phase observation for the
        GP; it does not consume budget. ``duration_s`` advances the optimizer's clock of
        ``drift_corr_s``; ``drift_var`` (W², at most ``var``) is the drift's share of ``var``.
        """
        if self._current is not None:
            raise OptimizerStateError("tell() while a setting is being measured; finish it first")
        x = self.space.check(params)
        _check_mean_var(mean, var, "tell")
        if drift_var is not None and not (math.isfinite(drift_var) and 0.0 <= drift_var <= var):
            raise MeasurementError(f"tell: drift_var={drift_var!r}; expected a variance in [0, var={var!r}]")
        ev = Evaluation(len(self._evaluations), self.space.to_dict(x), float(mean), float(var),
                        int(breaths), float(duration_s), Phase.OPTIMIZATION.value, False, "told",
                        drift_var=None if drift_var is None else float(drift_var))
        self._evaluations.append(ev)
        return ev

    def add_prior(self, prior: PriorObservation) -> None:
        """Add a fast-prior observation (Antonova 2016 §3.3); validated against the space."""
        try:
            self.space.check(prior.params)
        except ValueError as err:
            raise ConfigError(f"prior observation {dict(prior.params)} from {prior.source!r}: {err}") from err
        _check_mean_var(prior.mean, prior.var, f"prior observation from {prior.source!r}")
        self._priors.append(prior)

    def set_budget(self, *, budget_s: float | None, budget_breaths: int | None) -> None:
        """Change the optimisation budget (e.g. once the exploration bout's length is known, or
        when the participant needs to stop sooner). Validated like the constructor's."""
        self.config = replace(self.config, budget_s=budget_s, budget_breaths=budget_breaths)

    def close_current(self) -> Evaluation | None:
        """Close the setting being measured now, with its breaths so far: the session's time is up
        (:class:`hilbo_core.protocol.SessionProtocol`, a MEASURE action with ``final``).

        An optimisation evaluation with at least one breath is completed with its current
        estimate, reason ``"budget"`` (not an early stop of the rule; the GP weighs it by its
        variance), as the optimizer's own budget does. An exploration evaluation, or one without
        breaths, is dropped instead (:meth:`cancel_current`): Algorithm 2 needs full-length traces.

        Returns:
            The completed evaluation, or None when there was nothing to close or it was dropped.
        """
        cur = self._current
        if cur is None:
            return None
        if cur.phase is not Phase.OPTIMIZATION or not cur.breaths:
            self.cancel_current()
            return None
        return self._step(True, "budget", None).evaluation

    def cancel_current(self, *, again: bool = True) -> dict[str, float] | None:
        """Abandon the setting being measured (e.g. the device refused it); returns it.

        Its breaths are discarded and count against no budget; the next ``ask()`` proposes
        afresh (exploration points are asked again).

        Args:
            again: Keep it for :meth:`ask_again` (a pause: the same setting is measured once
                more); False for a setting that must not come back (the safety limits refused it).
        """
        cur = self._current
        if cur is None:
            return None
        if cur.phase is Phase.OPTIMIZATION:
            self._opt_breaths -= len(cur.breaths)
            self._opt_seconds -= cur.breaths[-1][0] if cur.breaths else 0.0
        self._keep_body_level()  # the breaths are discarded, but the body did walk them
        self._current = None
        self._cancelled = cur if again else None
        self._flagged_done += _flagged(self._estimator)
        self._estimator = None
        return dict(cur.params)

    @property
    def flagged_breaths(self) -> int:
        """Breaths the estimators left out as physiologically implausible for the level (below
        0.4x or above 2.2x the running median of their neighbours; hilbo_core/estimation.py),
        counted over this process's settings."""
        return self._flagged_done + _flagged(self._estimator)

    @property
    def cancelled_params(self) -> dict[str, float] | None:
        """The setting :meth:`cancel_current` abandoned and :meth:`ask_again` would measure
        once more, or None."""
        cur = self._cancelled
        return None if cur is None else dict(cur.params)

    def ask_again(self) -> dict[str, float] | None:
        """Measure the setting :meth:`cancel_current` abandoned once more, instead of a new
        proposal (after a short pause: the body is near where that setting left it).

        Same parameters, same phase, same prior for the stopping rule as when it was proposed;
        its breaths start from zero, with an estimator started from the body's level where the
        cancelled measurement left it (as for any setting change). Nothing is fitted or
        proposed, so it costs no GP work.

        Returns:
            The setting, or None when there is none to measure again (nothing was cancelled, an
            ``ask()`` came since, a setting is being measured, or the phase changed).
        """
        cur = self._cancelled
        if cur is None or self._current is not None or cur.phase is not self.phase:
            return None
        self._cancelled = None
        self._current = _Current(params=dict(cur.params), x=cur.x.copy(), phase=cur.phase,
                                 prior=cur.prior, remeasure=cur.remeasure)
        self._estimator = self._new_estimator()
        return dict(self._current.params)

    # ------------------------------------------------------------------ internals
    def _new_estimator(self) -> Estimator:
        """A fresh estimator for the next setting, started from the body level when it can be."""
        est = self._estimator_factory()
        start = getattr(est, "start_from_state", None)
        if self._handover is not None and callable(start):
            start(self._handover)
        return est

    def _keep_body_level(self) -> None:
        """Remember where the current estimator leaves the body (for the next setting)."""
        est = self._estimator
        handover = getattr(est, "handover", None)
        if est is None or not callable(handover) or est.n_updates == 0:
            return
        self._handover = handover()

    def hyperparameter_fit(self) -> HyperparameterFit | None:
        """The hyperparameter fit on every observation so far, to run ahead of the next proposal.

        Returns:
            The fit (a snapshot: later breaths and evaluations do not change it), or None when
            fewer than 2 observations exist or the stored hyperparameters already cover them all.
        """
        n = self._n_obs()
        if n < 2 or (self._hyp is not None and self._n_at_fit == n):
            return None
        U, y, v = self._training_set()
        return HyperparameterFit(kernel=self.config.kernel, X_unit=U, y=y, var=v, init=self._hyp,
                                 seed=(self.config.seed, n, _FIT_AHEAD_STREAM),
                                 noise_corr=self._noise_corr(v),
                                 prior_mean_sd=float(self.config.prior_mean_sd or 0.0))

    def apply_hyperparameters(self, fit: HyperparameterFit, hyp: GPHyperparameters) -> bool:
        """Keep the result of ``fit`` (from :meth:`hyperparameter_fit`) for the next proposals.

        Args:
            fit: The fit that was run.
            hyp: Its result, :func:`fit_hyperparameters` (``fit``).

        Returns:
            True if kept; False when the stored hyperparameters are as recent or more recent.

        Raises:
            OptimizerStateError: ``fit`` has more observations than this optimizer (it belongs
                to another optimizer).
        """
        n = self._n_obs()
        if fit.n_obs > n:
            raise OptimizerStateError(
                f"a hyperparameter fit on {fit.n_obs} observations; this optimizer has {n}"
            )
        if not isinstance(hyp, GPHyperparameters) or len(hyp.lengthscales) != fit.X_unit.shape[1]:
            raise OptimizerStateError(f"hyperparameters {hyp!r} do not fit a {fit.X_unit.shape[1]}-D GP")
        if self._hyp is not None and self._n_at_fit is not None and self._n_at_fit >= fit.n_obs:
            return False
        self._hyp, self._n_at_fit = hyp, fit.n_obs
        return True

    def _step(self, stop: bool, reason: str, decision: StopDecision | None) -> BreathStep:
        cur = self._current
        if cur is None:
            raise OptimizerStateError("internal: no current evaluation to step")
        mean, var = cur.means[-1], cur.vars[-1]
        i = len(cur.breaths) - 1
        if not stop:
            return BreathStep(False, mean, var, i, cur.phase, decision)
        obs_mean: float | None = None
        obs_var: float | None = None
        drift_var: float | None = None
        if isinstance(self._estimator, DataOnlyEstimator):
            obs_mean, obs_var = self._estimator.data_only()
            if isinstance(self._estimator, DriftAwareEstimator):
                drift_var = min(float(self._estimator.model_error_var()), obs_var)
        ev = Evaluation(
            index=len(self._evaluations), params=dict(cur.params), mean=mean, var=var,
            breaths=len(cur.breaths), duration_s=cur.breaths[-1][0], phase=cur.phase.value,
            stopped_early=reason == "threshold", reason=reason, obs_mean=obs_mean, obs_var=obs_var,
            drift_var=drift_var,
        )
        self._keep_body_level()
        self._evaluations.append(ev)
        if cur.phase is Phase.EXPLORATION:
            # A setting ended once precise enough (explore_rel_sd): its trace continues with its
            # last estimate up to N, as if measured on without change (Algorithm 2 needs N columns).
            pad = self.config.max_breaths - len(cur.means)
            self._traces_m.append(list(cur.means) + [cur.means[-1]] * pad)
            self._traces_s.append(list(cur.vars) + [cur.vars[-1]] * pad)
            if len(self._traces_m) == self.config.n_explore:
                M, S = self.exploration_traces
                self._thresholds = threshold_schedule(M, S, self.config.window)
        self._current = None
        self._flagged_done += _flagged(self._estimator)
        self._estimator = None
        return BreathStep(True, mean, var, i, cur.phase, decision, ev)

    def _rule(self) -> StoppingRule:
        c = self.config
        cur = self._current
        if c.stopping is StoppingKind.FIXED or (cur is not None and cur.remeasure):
            return FixedIntervalRule(c.max_breaths)
        if c.stopping.is_sound:
            # Without exploration traces (told evaluations), A = 0 and the floor decides.
            a = self._thresholds if self._thresholds is not None else np.zeros(c.max_breaths)
            boundary = c.boundary_s if c.stopping is StoppingKind.SOUND else None
            return SoundRule(a, min_decision_s=float(c.min_decision_s or 0.0), a_floor=c.a_floor,
                             accept_z=c.accept_z, boundary_s=boundary)
        if self._thresholds is None:
            return FixedIntervalRule(c.max_breaths)
        return SigmaScaledRule(self._thresholds)

    def _candidate_estimate(self, mean: float, var: float) -> tuple[float, float]:
        """The sound rule's (mean, var) of the current candidate's cost.

        With ``gp_prior_stopping`` and an estimator that can say what its breaths alone carry:
        the data-only estimate times the GP's predictive at x_t (a Gaussian product; the
        Bayesian early decision). The estimator's own weak prior on c is
        divided out first, so no prior is counted twice; the GP is told the data-only part
        (:meth:`_step`) as always. Otherwise the estimator's posterior.
        """
        cur = self._current
        if (not self.config.gp_prior_stopping or cur is None or cur.prior is None
                or not isinstance(self._estimator, DataOnlyEstimator)):
            return mean, var
        d_mean, d_var = self._estimator.data_only()
        p_mean, p_var = cur.prior
        share = self.config.gp_prior_max_share
        p_prec = 1.0 / p_var
        if share < 1.0:
            p_prec = min(p_prec, share / (1.0 - share) / d_var)
        prec = 1.0 / d_var + p_prec
        return (d_mean / d_var + p_mean * p_prec) / prec, 1.0 / prec

    def _incumbent_stats(self) -> tuple[float, float]:
        if self._incumbent is None:
            ev = min(self._evaluations, key=lambda e: e.mean)
            return ev.mean, ev.var
        return self._incumbent[1] + self._drift_now_w, self._incumbent[2]

    def _budget_spent(self) -> bool:
        c = self.config
        return (c.budget_breaths is not None and self._opt_breaths >= c.budget_breaths) or (
            c.budget_s is not None and self._opt_seconds >= c.budget_s
        )

    def _evaluation_units(self) -> np.ndarray:
        """Unit-cube points of the evaluations, shape (n_evaluations, d).

        Cached: evaluations are append-only, and converting every evaluation's parameter dict
        again at every proposal (twice: training set and incumbent) took ≈ 10 % of a profiled
        586-evaluation stopping trial once hyperparameters were no longer refitted every time.
        """
        evals, n, d = self._evaluations, len(self._units), self.space.dim
        if n > len(evals) or (n and self._units_last is not evals[n - 1]):
            # the evaluation list was replaced (never in normal use)
            self._units, self._units_last, n = np.empty((0, d)), None, 0
        if len(evals) > n:
            new = np.array([self.space.to_unit(self.space.from_dict(e.params)) for e in evals[n:]],
                           dtype=float).reshape(len(evals) - n, d)
            self._units, self._units_last = np.concatenate([self._units, new]), evals[-1]
        return self._units.copy()

    def _training_set(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        xs = np.array([self.space.from_dict(p.params) for p in self._priors], dtype=float)
        U = np.concatenate([self._evaluation_units(), self.space.to_unit(xs.reshape(-1, self.space.dim))])
        if self.config.drift_hours is not None:
            # Session time of each evaluation (its end), fast priors at time 0 (they came first).
            ends_h = self._evaluation_ends_s() / 3600.0
            t_h = np.concatenate([ends_h, np.zeros(len(self._priors))])
            U = np.column_stack([U, self._time_column(t_h)])
        # Data-only observations: the GP has its own prior.
        obs = [e.gp_observation for e in self._evaluations]
        y = [m for m, _ in obs] + [p.mean for p in self._priors]
        v = [s for _, s in obs] + [p.var for p in self._priors]
        return U, np.array(y), np.array(v)

    def _evaluation_ends_s(self) -> np.ndarray:
        """Each evaluation's end on the optimizer's clock (breath time of the evaluations so
        far, s), shape (n_evaluations,)."""
        return np.cumsum([e.duration_s for e in self._evaluations], dtype=float)

    def _drift_terms(self) -> tuple[np.ndarray, np.ndarray] | None:
        """Each GP observation's drift SD (W; 0 for fast priors and evaluations without one) and
        its time on the optimizer's clock (s, the evaluation's end), or None without
        ``drift_corr_s`` or without any drift."""
        if self.config.drift_corr_s is None:
            return None
        sd = np.sqrt([e.drift_var or 0.0 for e in self._evaluations] + [0.0] * len(self._priors))
        if not np.any(sd > 0.0):
            return None
        return sd, np.concatenate([self._evaluation_ends_s(), np.zeros(len(self._priors))])

    def _clock_s(self) -> float:
        """The optimizer's clock at the end of the last evaluation (s of breath time)."""
        return float(sum(e.duration_s for e in self._evaluations))

    def _drift_cov(self, sd_a: np.ndarray, t_a: np.ndarray, sd_b: np.ndarray,
                   t_b: np.ndarray) -> np.ndarray:
        """Covariance (W²) of the drift at times t_a against t_b, shape (len(a), len(b))."""
        ell = float(self.config.drift_corr_s or 1.0)
        rho = np.exp(-0.5 * ((t_a[:, None] - t_b[None, :]) / ell) ** 2)
        return rho * np.outer(sd_a, sd_b)

    def _noise_corr(self, v: np.ndarray) -> np.ndarray | None:
        """The correlation matrix of the GP observations' errors (variances v, W²): the drift's
        share correlated in time, the rest independent; None without drift terms."""
        terms = self._drift_terms()
        if terms is None:
            return None
        sd, t = terms
        C = self._drift_cov(sd, t, sd, t)
        np.fill_diagonal(C, v)
        s = np.sqrt(v)
        R = C / np.outer(s, s)
        np.fill_diagonal(R, 1.0)
        return R

    def _drift_now(self, gp: GaussianProcess) -> float:
        """The drift inferred at the optimizer's present time (W; 0 without drift terms): what a
        setting measured now reads above its landscape cost."""
        terms = self._drift_terms()
        if terms is None:
            return 0.0
        sd, t = terms
        now = self._clock_s()
        known = sd[: len(self._evaluations)]
        sd_now = np.array([float(np.sqrt(np.mean(known[known > 0.0] ** 2)))])
        C = self._drift_cov(sd_now, np.array([now]), sd, t)
        return float(gp.predict_error(C)[0])

    def _n_obs(self) -> int:
        return len(self._evaluations) + len(self._priors)

    def _refit_due(self) -> bool:
        """Whether the next GP must refit its hyperparameters (see ``refit_growth``)."""
        if self._hyp is None or self._n_at_fit is None:
            return True
        if self.config.refit_lag:
            return self._n_obs() - self._n_at_fit > self.config.refit_lag
        # The smallest count >= G·n_fit; the 1e-9 keeps round-off (1.1·10 = 11.000000000000002)
        # from postponing a refit by one observation.
        return self._n_obs() >= math.ceil(self.config.refit_growth * self._n_at_fit - 1e-9)

    def _fit_gp(self, rng: np.random.Generator, *, store: bool) -> GaussianProcess:
        """The GP on every observation: hyperparameters refitted when :meth:`_refit_due`, else
        the last ones re-conditioned on all observations (``rng`` unused then).

        Every GP of the optimizer (proposal, incumbent, :meth:`best`) comes from here, so all of
        them follow ``refit_growth`` alike. ``store`` keeps a refit's hyperparameters.
        """
        U, y, v = self._training_set()
        gp = GaussianProcess(self.config.kernel)
        refit = self._refit_due()
        gp.fit(U, y, v, rng=rng, init=self._hyp, optimize=refit, noise_corr=self._noise_corr(v),
               prior_mean_sd=float(self.config.prior_mean_sd or 0.0))
        if store and refit:
            self._hyp = gp.hyperparameters  # warm start of the next fit
            self._n_at_fit = int(y.size)
        return gp

    def _time_column(self, t_h: np.ndarray) -> np.ndarray:
        """The GP's time input: hours scaled so that the default length-scale prior's median
        (√(d+1)/4 in the unit cube, gp.py) corresponds to ``drift_hours`` hours; clipped to the
        cube, so times beyond drift_hours/(√(d+1)/4) hours (3 h for 6-D and 2 h) share one value."""
        h = self.config.drift_hours
        scale = 0.25 * math.sqrt(self.space.dim + 1) / float(h if h is not None else 1.0)
        return np.clip(np.asarray(t_h, dtype=float) * scale, 0.0, 1.0)

    def _now(self, U: np.ndarray) -> np.ndarray:
        """GP query points for unit-cube settings U (m, d): with drift, at the present time."""
        if self.config.drift_hours is None:
            return U
        now_h = self._clock_s() / 3600.0
        cur = self._current
        if cur is not None and cur.breaths:
            now_h += cur.breaths[-1][0] / 3600.0
        return np.column_stack([U, np.full(U.shape[0], float(self._time_column(np.array(now_h))))])

    def _posterior_best(self, gp: GaussianProcess) -> tuple[dict[str, float], float, float]:
        """The evaluated setting of lowest posterior mean + β·SD, with the GP posterior there."""
        post_mean, post_var = gp.predict(self._now(self._evaluation_units()))
        score = post_mean + self.config.recommend_beta * np.sqrt(post_var)
        k = int(np.argmin(score))
        return dict(self._evaluations[k].params), float(post_mean[k]), float(post_var[k])

    def _gp_incumbent(self, gp: GaussianProcess) -> tuple[dict[str, float], float, float]:
        """The sound rule's x*: the evaluated setting of lowest posterior mean, with the GP
        posterior of its cost (mean, variance; the model's noise accounted for), not the raw
        estimate (which is optimistically biased for the setting that looks best: the winner's
        curse)."""
        post_mean, post_var = gp.predict(self._now(self._evaluation_units()))
        k = int(np.argmin(post_mean))
        return dict(self._evaluations[k].params), float(post_mean[k]), float(post_var[k])

    def _global_best(self, gp: GaussianProcess,
                     rng: np.random.Generator) -> tuple[dict[str, float], float, float]:
        """Over the whole feasible set (feasible Sobol candidates and every evaluated setting, the
        best few refined locally): the lowest posterior mean + β·SD, with the GP posterior there."""
        A_u, b_u = self.space.unit_constraints()
        cand = np.concatenate([self._evaluation_units(),
                               self.space.sample_unit(self.config.n_candidates, rng)])
        d = self.space.dim

        def predict(U: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            return gp.predict(self._now(U))

        def predict_grad(U: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
            m, v, dm, dv = gp.predict_with_grad(self._now(U))
            return m, v, dm[:, :d], dv[:, :d]

        u = minimize_lcb(predict, self.config.recommend_beta, candidates=np.clip(cand, 0.0, 1.0),
                         A_ub=A_u, b_ub=b_u, n_local=self.config.n_local, predict_grad=predict_grad)
        x = self.space.from_unit(u)
        if not self.space.is_feasible(x):  # round-off at a constraint: the best evaluated setting
            return self._posterior_best(gp)
        m, v = gp.predict(self._now(u.reshape(1, -1)))
        return self.space.to_dict(x), float(m[0]), float(v[0])

    def _gp_best(self, gp: GaussianProcess) -> tuple[dict[str, float], float, float]:
        post_mean = gp.predict_mean(self._now(self._evaluation_units()))  # the variance is not needed here
        ev = self._evaluations[int(np.argmin(post_mean))]
        return dict(ev.params), ev.mean, ev.var

    def _propose(self) -> np.ndarray:
        gp = self._fit_gp(self._rng, store=True)
        # x* for the stopping rule: with the sound rules the GP posterior at the evaluated setting
        # of lowest posterior mean; with Kim et al.'s rules the GP's best evaluated setting with
        # its own estimate (§II.D: "the best parameter setting found thus far as defined by the GP").
        sound = self.config.stopping.is_sound
        self._incumbent = self._gp_incumbent(gp) if sound else self._gp_best(gp)
        # The candidate is measured now, with today's drift in its breaths: the stop decision
        # compares it with the incumbent as it would read now (drift_corr_s).
        drift_now = self._drift_now(gp) if sound else 0.0
        self._drift_now_w = drift_now
        n_local = self.config.n_local
        local = self.config.trust_region is not None and not (
            self.config.trust_region_alternate and len(self._evaluations) % 2)
        if not local:
            cand = self.space.sample_unit(self.config.n_candidates, self._rng)
        else:
            cand = self._trust_region_candidates(self.space.to_unit(
                self.space.from_dict(self._incumbent[0])))
            n_local = 0  # a refinement could leave the box
        acq = self.config.acquisition
        if acq is AcquisitionKind.EI_THEN_KG:
            late = self._clock_s() >= self.config.kg_from_s
            acq = AcquisitionKind.KG_GLOBAL if late else AcquisitionKind.EI
        if acq is AcquisitionKind.EI:
            u = self._maximize_ei(gp, cand, n_local)
        else:
            u = self._maximize_kg(gp, cand, acq)
        x = self.space.from_unit(np.clip(u, 0.0, 1.0))
        if not self.space.is_feasible(x):
            # Local refinement should never leave the set; if round-off does, the best
            # candidate is feasible by construction.
            x = self.space.from_unit(cand[0])
        prior = None
        if sound:
            m, v = gp.predict(self._now(self.space.to_unit(x).reshape(1, -1)))
            # The candidate's cost is f(x_t) plus the GP's learned homoscedastic term (what
            # varies between measurements of one setting beyond the estimator's own noise).
            nugget = gp.hyperparameters.noise_var * gp.y_std**2
            prior = (float(m[0]) + drift_now, float(v[0]) + float(nugget))
        self._pending = (prior, False)
        return x

    def _maximize_ei(self, gp: GaussianProcess, cand: np.ndarray, n_local: int) -> np.ndarray:
        """EI's maximiser over the candidates, the best ``n_local`` refined, unit cube (d,)."""
        if self.config.ei_best is EIBestKind.POSTERIOR:
            # Noisy EI's plug-in incumbent: the lowest posterior mean among the evaluated
            # settings. min(S) of noisy estimates is optimistic (the luckiest estimate), so EI
            # against it undervalues settings near the real best.
            best_observed = float(np.min(gp.predict_mean(self._now(self._evaluation_units()))))
        else:
            best_observed = min(e.mean for e in self._evaluations)  # min(S), Kim et al. 2019 §II.B
        A_u, b_u = self.space.unit_constraints()
        d = self.space.dim

        def predict(U: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            return gp.predict(self._now(U))

        def predict_grad(U: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
            m, v, dm, dv = gp.predict_with_grad(self._now(U))
            return m, v, dm[:, :d], dv[:, :d]  # time is not a decision variable

        u, _ = maximize_ei(predict, best_observed, candidates=cand, A_ub=A_u, b_ub=b_u,
                           rng=self._rng, xi=self.config.xi, n_local=n_local,
                           predict_grad=predict_grad)
        return np.asarray(u, dtype=float)

    def _maximize_kg(self, gp: GaussianProcess, cand: np.ndarray,
                     kind: AcquisitionKind = AcquisitionKind.KG) -> np.ndarray:
        """The candidate (or measured setting) of highest knowledge gradient, unit cube (d,).

        The reference set is the measured settings (KGCP, Scott et al. 2011); the measurement to
        come has the median variance of the GP's observations of full-length evaluations (all of
        them before any ran to N) plus the GP's homoscedastic term. No local refinement: KG is
        evaluated on the feasible candidates only (the space's Sobol set, as EI's first stage).
        """
        ref = self._evaluation_units()
        pool = np.concatenate([np.clip(cand, 0.0, 1.0), ref])
        if kind is AcquisitionKind.KG_GLOBAL:
            ref = np.concatenate([ref, self.space.sample_unit(_KG_GLOBAL_REFERENCE, self._rng)])
        ref_q, pool_q = self._now(ref), self._now(pool)
        mean_ref, _ = gp.predict(ref_q)
        mean_c, var_c = gp.predict(pool_q)
        cov = gp.predict_cov(ref_q, pool_q)
        full = [e for e in self._evaluations if e.reason == "max_measurements"] or self._evaluations
        noise = float(np.median([e.gp_observation[1] for e in full]))
        noise += gp.hyperparameters.noise_var * gp.y_std**2
        kg = knowledge_gradient_min(mean_ref, cov, mean_c, var_c, noise)
        return pool[int(np.argmax(kg))]

    def _trust_region_candidates(self, centre: np.ndarray) -> np.ndarray:
        """Feasible unit-cube points in the box ``centre ± trust_region`` (clipped to the cube):
        the centre (feasible: an evaluated setting) and up to ``n_candidates - 1`` uniform draws
        that satisfy the constraints, shape (m, d), 1 <= m <= n_candidates."""
        hw = float(self.config.trust_region or 1.0)
        lo, hi = np.clip(centre - hw, 0.0, 1.0), np.clip(centre + hw, 0.0, 1.0)
        A_u, b_u = self.space.unit_constraints()
        n = self.config.n_candidates
        # Four rounds of n draws at most: the box around a feasible point is mostly feasible
        # unless it sits on a constraint, and fewer candidates only make the search coarser.
        kept = [centre.reshape(1, -1)]
        have = 1
        for _ in range(4):
            u = lo + self._rng.random((n, centre.size)) * (hi - lo)
            if len(b_u):
                u = u[np.all(u @ A_u.T <= b_u + 1e-12, axis=1)]
            kept.append(u[: n - have])
            have += len(kept[-1])
            if have >= n:
                break
        return np.concatenate(kept)

    # ------------------------------------------------------------------ serialisation
    def to_json(self) -> dict[str, Any]:
        """The whole state as a JSON-able dict (round-trips with :meth:`from_json`)."""
        cur = self._current
        return {
            "version": _STATE_VERSION,
            "space": self.space.to_json(),
            "config": self.config.to_json(),
            "rng": self._rng.bit_generator.state,
            "design": self._design.tolist(),
            "evaluations": [e.to_json() for e in self._evaluations],
            "priors": [{"params": dict(p.params), "mean": p.mean, "var": p.var, "source": p.source}
                       for p in self._priors],
            "traces_m": self._traces_m,
            "traces_s": self._traces_s,
            "thresholds": None if self._thresholds is None else self._thresholds.tolist(),
            "current": None if cur is None else {
                "params": cur.params, "x": cur.x.tolist(), "phase": cur.phase.value,
                "breaths": cur.breaths, "prior": None if cur.prior is None else list(cur.prior),
                "remeasure": cur.remeasure,
            },
            # The setting a pause abandoned, which ask_again() measures once more: a resume from
            # a snapshot taken between the cancel and the re-proposal must be able to as well.
            "cancelled": None if self._cancelled is None else {
                "params": self._cancelled.params, "x": self._cancelled.x.tolist(),
                "phase": self._cancelled.phase.value,
                "prior": None if self._cancelled.prior is None else list(self._cancelled.prior),
                "remeasure": self._cancelled.remeasure,
            },
            "confirm": None if self._confirm is None else list(self._confirm),
            "confirm_from": self._confirm_from,
            "confirm_requested": self._confirm_requested,
            "hyp": None if self._hyp is None else self._hyp.to_dict(),
            "n_at_fit": self._n_at_fit,
            "incumbent": None if self._incumbent is None else list(self._incumbent),
            "drift_now_w": self._drift_now_w,
            "opt_breaths": self._opt_breaths,
            "opt_seconds": self._opt_seconds,
            "handover": None if self._handover is None else self._handover.to_json(),
        }

    @classmethod
    def from_json(cls, data: Mapping[str, Any], *,
                  estimator_factory: Callable[[], Estimator] | None = None) -> HILOptimizer:
        """Rebuild an optimizer from :meth:`to_json` output.

        The current evaluation's estimator is rebuilt by replaying its breaths, so the next
        breath and the next proposal are exactly those the original would have produced.
        """
        if data.get("version") != _STATE_VERSION:
            raise ConfigError(f"optimizer state version {data.get('version')!r}; expected {_STATE_VERSION}")
        try:
            space = ParameterSpace.from_json(data["space"])
            config_data = dict(data["config"])
            # States written before the transition estimator come from sessions that ran Kim et al.'s UKF.
            config_data.setdefault("estimator", EstimatorKind.SEED_UKF.value)
            # ... and states written before the posterior recommendation recommended Kim et al.'s way.
            config_data.setdefault("recommend", RecommendKind.SEED.value)
            # States written before the exploration design became a choice used maximin.
            config_data.setdefault("design", DesignKind.MAXIMIN.value)
            # States written before the GP's prior mean became a choice had it at the average.
            config_data.setdefault("prior_mean_sd", 0.0)
            # ... and before its share of a stop decision was capped, the plain product.
            config_data.setdefault("gp_prior_max_share", 1.0)
            # remeasure_best_s never acted (no session gave the optimizer a budget of its own):
            # the confirmation replaced it.
            config_data.pop("remeasure_best_s", None)
            opt = cls(space, config=OptimizerConfig.from_json(config_data),
                      estimator_factory=estimator_factory,
                      prior_observations=[PriorObservation(**p) for p in data["priors"]])
            opt._rng.bit_generator.state = data["rng"]
            opt._design = np.array(data["design"], dtype=float).reshape(-1, space.dim)
            opt._evaluations = [Evaluation(**e) for e in data["evaluations"]]
            opt._traces_m = [list(map(float, r)) for r in data["traces_m"]]
            opt._traces_s = [list(map(float, r)) for r in data["traces_s"]]
            if data["thresholds"] is not None:
                opt._thresholds = np.array(data["thresholds"], dtype=float)
            if data["hyp"] is not None:
                opt._hyp = GPHyperparameters.from_dict(data["hyp"])
                # States written before refit_growth existed lack the key: they come from
                # sessions that refitted at every proposal, so the next proposal refits.
                n_at_fit = data.get("n_at_fit")
                opt._n_at_fit = None if n_at_fit is None else int(n_at_fit)
            if data["incumbent"] is not None:
                p, m, v = data["incumbent"]
                opt._incumbent = (dict(p), float(m), float(v))
            opt._drift_now_w = float(data.get("drift_now_w", 0.0))  # absent before drift_corr_s
            opt._confirm_requested = bool(data.get("confirm_requested", False))
            confirm = data.get("confirm")  # absent in states written before the confirmation
            if confirm is not None:
                p, m, v = confirm
                opt._confirm = (dict(p), float(m), float(v))
                opt._confirm_from = int(data["confirm_from"])
            opt._opt_breaths = int(data["opt_breaths"])
            opt._opt_seconds = float(data["opt_seconds"])
            handover = data.get("handover")  # absent in states written before the hand-over existed
            if handover is not None:
                opt._handover = StartState.from_json(handover)
            cur = data["current"]
        except (KeyError, TypeError, ValueError) as err:
            raise ConfigError(f"invalid optimizer state: {err!r}") from err
        gone = data.get("cancelled")  # absent in states written before ask_again existed
        if gone is not None:
            prior = gone.get("prior")
            opt._cancelled = _Current(params=dict(gone["params"]), x=np.array(gone["x"], dtype=float),
                                      phase=Phase(gone["phase"]),
                                      prior=None if prior is None else (float(prior[0]), float(prior[1])),
                                      remeasure=bool(gone.get("remeasure", False)))
        if cur is not None:
            prior = cur.get("prior")
            opt._current = _Current(params=dict(cur["params"]), x=np.array(cur["x"], dtype=float),
                                    phase=Phase(cur["phase"]),
                                    prior=None if prior is None else (float(prior[0]), float(prior[1])),
                                    remeasure=bool(cur.get("remeasure", False)))
            opt._estimator = opt._new_estimator()
            for t, w in cur["breaths"]:
                mean, var = opt._estimator.update(float(t), float(w))
                opt._current.breaths.append((float(t), float(w)))
                opt._current.means.append(float(mean))
                opt._current.vars.append(float(var))
        return opt


_ESTIMATORS: dict[EstimatorKind, Callable[[], Estimator]] = {
    EstimatorKind.TRANSITION: TransitionEstimator,
    EstimatorKind.SEED_UKF: MetabolicUKF,
}


def _flagged(est: Estimator | None) -> int:
    """The breaths ``est`` left out as implausible (0 for an estimator that flags none)."""
    n = getattr(est, "n_flagged", 0)
    return int(n) if isinstance(n, int) else 0


def _check_mean_var(mean: float, var: float, what: str) -> None:
    if not math.isfinite(mean):
        raise MeasurementError(f"{what}: mean={mean!r}; expected a finite cost")
    if not (math.isfinite(var) and var > 0):
        raise MeasurementError(f"{what}: var={var!r}; expected a finite variance > 0")
