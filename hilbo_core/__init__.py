"""hilbo_core: the pure algorithms of hilbo (no I/O, no asyncio, no clocks).

Kim et al. 2019 (the estimator stopping process): parameter spaces and presets, force profiles, the
Gaussian process, Expected Improvement, Brockway's equation and the UKF metabolic estimator, the
stopping rules (Algorithm 2 and the σ-scaled offset rule) and :class:`HILOptimizer`
(Algorithm 1 as an ask/tell state machine).
"""

from hilbo_core import presets
from hilbo_core.acquisition import expected_improvement, log_expected_improvement, maximize_ei
from hilbo_core.errors import (
    ConfigError,
    EstimatorError,
    HilboError,
    InfeasibleError,
    MeasurementError,
    OptimizerStateError,
)
from hilbo_core.gp import GaussianProcess, GPHyperparameters, KernelKind
from hilbo_core.metabolic import (
    GaussianProductEstimator,
    MeasurementNoisePool,
    MetabolicUKF,
    PooledNoiseEstimator,
    UKFConfig,
    brockway_watts,
)
from hilbo_core.optimizer import (
    BreathStep,
    Evaluation,
    HILOptimizer,
    HyperparameterFit,
    OptimizerConfig,
    Phase,
    PriorObservation,
    StoppingKind,
    fit_hyperparameters,
)
from hilbo_core.profiles import ForceProfile, build_profile, hip_ankle_profiles, hip_spline_profile
from hilbo_core.space import DerivedParameter, LinearConstraint, Parameter, ParameterSpace
from hilbo_core.stopping import (
    FixedIntervalRule,
    SigmaScaledRule,
    StopDecision,
    StopReason,
    threshold_schedule,
)
from hilbo_core.types import BreathRecord

__all__ = [
    "BreathRecord",
    "BreathStep",
    "ConfigError",
    "DerivedParameter",
    "EstimatorError",
    "Evaluation",
    "FixedIntervalRule",
    "ForceProfile",
    "GPHyperparameters",
    "GaussianProcess",
    "GaussianProductEstimator",
    "HILOptimizer",
    "HilboError",
    "HyperparameterFit",
    "InfeasibleError",
    "KernelKind",
    "LinearConstraint",
    "MeasurementError",
    "MeasurementNoisePool",
    "MetabolicUKF",
    "OptimizerConfig",
    "OptimizerStateError",
    "Parameter",
    "ParameterSpace",
    "Phase",
    "PooledNoiseEstimator",
    "PriorObservation",
    "SigmaScaledRule",
    "StopDecision",
    "StopReason",
    "StoppingKind",
    "UKFConfig",
    "brockway_watts",
    "build_profile",
    "expected_improvement",
    "fit_hyperparameters",
    "hip_ankle_profiles",
    "hip_spline_profile",
    "log_expected_improvement",
    "maximize_ei",
    "presets",
    "threshold_schedule",
]
