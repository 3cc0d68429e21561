"""The virtual devices and simulated wearers, for the rest of bridge.

The layer rule (shared/DESIGN.md): inside bridge only bridge.sim imports virtual_hw; the
benchmarks and the command line reach the virtual devices through this module.
"""

from __future__ import annotations

from virtual_hw.cli_cart import add_virtual_cart_parser
from virtual_hw.cli_exosuit import add_virtual_exosuit_parser
from virtual_hw.clock import ScaledClock
from virtual_hw.exosuit import SUIT_JOINTS, VirtualExosuit
from virtual_hw.wearer import (
    WEARER_CHOICES,
    SimulatedWearer,
    WearerConfig,
    WearerKind,
    make_wearer,
    wearer_kind,
)
from virtual_hw.wearer_realistic import RealisticWearerConfig

__all__ = [
    "SUIT_JOINTS",
    "WEARER_CHOICES",
    "RealisticWearerConfig",
    "ScaledClock",
    "SimulatedWearer",
    "VirtualExosuit",
    "WearerConfig",
    "WearerKind",
    "add_virtual_cart_parser",
    "add_virtual_exosuit_parser",
    "make_wearer",
    "wearer_kind",
]
