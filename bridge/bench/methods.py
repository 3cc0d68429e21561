"""The method names of ``hilbo bench hil`` (light: the command line lists them in its help
without importing the benchmark)."""

from __future__ import annotations

__all__ = ["DEFAULT_HIL_METHODS", "HIL_METHODS", "PRIOR_METHODS", "THESIS_METHODS"]

DEFAULT_HIL_METHODS: tuple[str, ...] = ("sound", "adaptive", "fixed", "cmaes", "random")
"""What ``hilbo bench hil`` runs without ``--methods``."""
PRIOR_METHODS: tuple[str, ...] = ("adaptive-prior", "adaptive-prior-e3")
THESIS_METHODS: tuple[str, ...] = ("adaptive-day2", *PRIOR_METHODS, "adaptive-features",
                                   "adaptive-features-only", "adaptive-tuned-k")
"""The Antonova 2016 methods (bridge/bench/hil.py's docstring)."""
HIL_METHODS: tuple[str, ...] = (*DEFAULT_HIL_METHODS, "adaptive-ahead", *THESIS_METHODS)
"""Every method ``hilbo bench hil --methods`` accepts."""
