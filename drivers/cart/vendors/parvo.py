"""Parvo Medics TrueOne 2400: the CSV export.

Layout (from the vendor's export as read by the open-source readers of Parvo files, e.g. the R
function ``read_parvo`` of jemarnold/epl; no real file was available, so the preset is tested on
synthetic files, ``tests/data/cart/parvo_trueone.csv``): a metadata block (``Parvo Medics TrueOne
2400``, the date, ``Name``, ``Age``/``Sex``, ``Height``/``Weight``, barometric pressure, gains),
then the header over *several* rows — ``TIME,VO2,VO2/kg,VCO2,RER,RR,Vt,VE,...,HR`` then
``,STPD,STPD,STPD,...`` then the units ``min,L/min,ml/kg/m,L/min,...`` and a ``-----`` rule —
and the rows: ``TIME`` in decimal minutes (or ``mm:ss``), VO2 and VCO2 in L/min STPD. An
``Events`` block may follow the table. Being text, the same lines can be read live.
"""

from __future__ import annotations

from drivers.cart.vendors._table import VendorSpec

__all__ = ["PARVO"]

PARVO = VendorSpec(
    name="parvo",
    title="Parvo Medics TrueOne 2400 CSV export",
    aliases={
        "t_s": ("time",),
        "vo2_ml_min": ("vo2",),
        "vco2_ml_min": ("vco2",),
        "ve_l_min": ("ve",),
        "rer": ("rer", "rq"),
        "hr_bpm": ("hr",),
    },
    default_units={"t_s": "min", "vo2_ml_min": "l/min", "vco2_ml_min": "l/min"},
    delimiters=(",", ";"),
    mass_labels=("weight", "weight(kg)", "wt", "bodymass"),
    end_markers=("events",),
    markers=("parvo", "trueone"),
)
