"""virtual_hw: the simulated wearer, virtual metabolic cart and virtual exosuit node.

Exports are loaded lazily: the wearer pulls in scipy, and ``hilbo --help`` should stay fast.
"""

from __future__ import annotations

import importlib
from typing import Any

_EXPORTS = {
    "ANKLE_PRIOR": "virtual_hw.wearer",
    "HIP_PRIOR": "virtual_hw.wearer",
    "ActuatorPrior": "virtual_hw.wearer",
    "AssistWindow": "virtual_hw.wearer",
    "SimulatedWearer": "virtual_hw.wearer",
    "WearerConfig": "virtual_hw.wearer",
    "BreathFate": "virtual_hw.cart",
    "CART_FAULTS": "virtual_hw.cart",
    "CartLink": "virtual_hw.cart",
    "LinkKind": "virtual_hw.cart",
    "VIRTUAL_CSV_MAPPING": "virtual_hw.cart",
    "VirtualCart": "virtual_hw.cart",
    "ScaledClock": "virtual_hw.clock",
    "SimClock": "virtual_hw.clock",
    "VirtualClock": "virtual_hw.clock",
    "make_clock": "virtual_hw.clock",
    "FaultCatalog": "virtual_hw.faults",
    "FaultSchedule": "virtual_hw.faults",
    "FaultSpec": "virtual_hw.faults",
    "AppliedProfileListener": "virtual_hw.exosuit",
    "DeviceLimits": "virtual_hw.exosuit",
    "EXOSUIT_FAULTS": "virtual_hw.exosuit",
    "SUIT_JOINTS": "virtual_hw.exosuit",
    "VirtualExosuit": "virtual_hw.exosuit",
    "applied_profile_feed": "virtual_hw.exosuit",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str) -> Any:
    try:
        module = _EXPORTS[name]
    except KeyError:
        raise AttributeError(f"module 'virtual_hw' has no attribute {name!r}") from None
    return getattr(importlib.import_module(module), name)
