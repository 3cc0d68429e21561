"""Vyntus CPX (Vyaire SentrySuite): the tab-separated text export.

Layout (checked against ``shared/data/cart-exports/vyntus_test.txt``, a Scandinavian-locale export
of 1-min averages): an ``ID-nummer:`` line and a blank line, the header (``Tid``, ``Last``,
``V'O2``, ``V'CO2``, ``RER``, ``V'E``, ``HF``, ...), a units row (``min``, ``mL/min``, ``L/min``)
and the rows, times as ``mm:ss`` (with a leading space). Other locales name the time ``Zeit`` or
``Time`` and may write a decimal comma. Being text, the same lines can be read live.
"""

from __future__ import annotations

from drivers.cart.vendors._table import VendorSpec

__all__ = ["VYNTUS"]

VYNTUS = VendorSpec(
    name="vyntus",
    title="Vyntus CPX SentrySuite text export",
    aliases={
        "t_s": ("tid", "zeit", "time", "t", "tijd", "temps", "tempo"),
        "vo2_ml_min": ("vo2",),
        "vco2_ml_min": ("vco2",),
        "ve_l_min": ("ve",),
        "rer": ("rer", "rq"),
        "hr_bpm": ("hf", "hr", "fc"),
    },
    default_units={"t_s": "s", "vo2_ml_min": "ml/min", "vco2_ml_min": "ml/min"},
    delimiters=("\t", ";"),
    markers=("id-nummer", "sentrysuite", "vyntus", "v'o2"),
)
