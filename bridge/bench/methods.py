"""The method names of ``hilbo bench hil`` (light: the command line lists them in its help
without importing the benchmark)."""

from __future__ import annotations

__all__ = ["ABLATION_METHODS", "DEFAULT_HIL_METHODS", "HIL_METHODS", "PRIOR_METHODS", "THESIS_METHODS"]

DEFAULT_HIL_METHODS: tuple[str, ...] = ("sound", "adaptive", "fixed", "cmaes", "random")
"""What ``hilbo bench hil`` runs without ``--methods``."""
PRIOR_METHODS: tuple[str, ...] = ("adaptive-prior", "adaptive-prior-e3")
THESIS_METHODS: tuple[str, ...] = ("adaptive-day2", *PRIOR_METHODS, "adaptive-features",
                                   "adaptive-features-only", "adaptive-tuned-k")
"""The Antonova 2016 methods (bridge/bench/hil.py's docstring)."""
#: The ablations of the default ("sound"), each one change away from its neighbour
#: (bridge/bench/hil.py, ``_BO_VARIANTS``); not run by default.
ABLATION_METHODS: tuple[str, ...] = ("sound-seed", "sound-seed-global", "sound-seed-confirm",
                                     "sound-fast-noconfirm", "sound-e6", "sound-e4",
                                     "sound-explore-sd", "sound-nei", "sound-floor", "sound-tr25",
                                     "sound-tr40", "sound-tr40-alt", "sound-drift", "sound-kg",
                                     "sound-kg-global", "sound-ei-kg", "sound-mean0",
                                     "sound-prior-full")
HIL_METHODS: tuple[str, ...] = (*DEFAULT_HIL_METHODS, "adaptive-ahead", *THESIS_METHODS,
                                *ABLATION_METHODS)
"""Every method ``hilbo bench hil --methods`` accepts."""
