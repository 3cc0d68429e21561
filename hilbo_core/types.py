"""Value types shared by every layer (drivers and virtual_hw import these, never the reverse)."""

from __future__ import annotations

import math
from dataclasses import dataclass

__all__ = ["BreathRecord"]


@dataclass(frozen=True, slots=True)
class BreathRecord:
    """One breath as reported by a metabolic cart.

    Attributes:
        t_s: Breath time in seconds on the cart's clock (the session's time base).
        vo2_ml_min: Oxygen uptake in ml/min.
        vco2_ml_min: Carbon-dioxide output in ml/min.
        ve_l_min: Minute ventilation in l/min, if the cart reports it.
        rer: Respiratory exchange ratio VCO2/VO2, if reported.
        hr_bpm: Heart rate in beats per minute, if reported.
    """

    t_s: float
    vo2_ml_min: float
    vco2_ml_min: float
    ve_l_min: float | None = None
    rer: float | None = None
    hr_bpm: float | None = None

    @property
    def watts(self) -> float:
        """Metabolic power by Brockway's equation, in W (see :func:`hilbo_core.brockway_watts`)."""
        # Kept here as the one-line formula so the value type has no import cycle with metabolic.
        return 16.58 * self.vo2_ml_min / 60.0 + 4.51 * self.vco2_ml_min / 60.0

    def is_finite(self) -> bool:
        """True when every reported number is finite."""
        values = [self.t_s, self.vo2_ml_min, self.vco2_ml_min, self.ve_l_min, self.rer, self.hr_bpm]
        return all(math.isfinite(v) for v in values if v is not None)
