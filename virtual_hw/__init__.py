"""virtual_hw: the simulated wearer, virtual metabolic cart and virtual exosuit node."""

from virtual_hw.wearer import (
    ANKLE_PRIOR,
    HIP_PRIOR,
    ActuatorPrior,
    AssistWindow,
    SimulatedWearer,
    WearerConfig,
)

__all__ = ["ANKLE_PRIOR", "HIP_PRIOR", "ActuatorPrior", "AssistWindow", "SimulatedWearer", "WearerConfig"]
