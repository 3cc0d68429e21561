"""Figures of the benchmarks (matplotlib, Agg backend: no display needed)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # after use("Agg"): no display needed
import numpy as np

__all__ = ["plot_hil", "plot_stopping_function"]

_STYLE = {"fixed": ("tab:blue", "Fixed"), "adaptive": ("tab:red", "Adap"),
          "cmaes": ("tab:green", "CMA-ES"), "random": ("tab:gray", "Random")}


def _style(method: str, k: int) -> tuple[str, str]:
    return _STYLE.get(method, (f"C{k + 4}", method))


def _arr(values: Sequence[Any]) -> np.ndarray:
    return np.array([np.nan if v is None else v for v in values], dtype=float)


def plot_stopping_function(settings: Sequence[Mapping[str, Any]], function: str, path: Path) -> Path:
    """One function's panel row in the layout of seed 000 Fig. 2.

    One panel per noise level (left to right as given), y_t against the optimisation-phase
    measurement count for every method, mean line with a ±1 SE band.

    Args:
        settings: ``results.json`` settings (other functions are ignored).
        function: Which function to draw.
        path: PNG to write.

    Returns:
        ``path``.
    """
    rows = [s for s in settings if s["function"] == function]
    noises = list(dict.fromkeys(s["noise"] for s in rows))
    methods = list(dict.fromkeys(s["method"] for s in rows))
    fig, axes = plt.subplots(1, max(len(noises), 1), figsize=(4.2 * max(len(noises), 1), 3.4),
                             squeeze=False, sharey=False)
    for ax, noise in zip(axes[0], noises, strict=False):
        for k, method in enumerate(methods):
            match = [s for s in rows if s["noise"] == noise and s["method"] == method]
            if not match:
                continue
            s = match[0]
            t = np.asarray(s["t"], dtype=float)
            m, se = _arr(s["y_mean"]), _arr(s["y_se"])
            colour, label = _style(method, k)
            ax.plot(t, m, color=colour, label=f"{label} (n={s['n_trials']})", lw=1.4)
            if np.isfinite(se).any():
                ax.fill_between(t, m - se, m + se, color=colour, alpha=0.2, lw=0)
        ax.set_title(f"{function}, σ_z² = {noise:g}·σ̃²", fontsize=10)
        ax.set_xlabel("measurements after exploration")
        ax.grid(alpha=0.3)
        ax.set_ylim(bottom=0)
    axes[0][0].set_ylabel("y_t  (mean ± SE)")
    axes[0][0].legend(fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_hil(spaces: Mapping[str, Mapping[str, Mapping[str, Any]]], path: Path) -> Path:
    """Regret of the recommended setting against minutes walked, one panel per space.

    Args:
        spaces: ``{space: {method: entry}}`` with ``minutes``, ``regret_w_median`` and
            ``regret_w_p75`` lists (None where not every session has a recommendation).
        path: PNG to write.

    Returns:
        ``path``.
    """
    names = list(spaces)
    fig, axes = plt.subplots(1, max(len(names), 1), figsize=(5.0 * max(len(names), 1), 3.6),
                             squeeze=False)
    for ax, space in zip(axes[0], names, strict=False):
        for k, (method, e) in enumerate(spaces[space].items()):
            colour, label = _style(method, k)
            minutes = np.asarray(e["minutes"], dtype=float)
            med, p75 = _arr(e["regret_w_median"]), _arr(e["regret_w_p75"])
            ax.plot(minutes, med, color=colour, label=label, lw=1.5)
            ax.plot(minutes, p75, color=colour, lw=0.8, ls="--")
        ax.set_title(f"{space}: regret of the recommendation", fontsize=10)
        ax.set_xlabel("minutes walked (session clock)")
        ax.set_ylabel("true cost − optimum (W): median, p75 dashed")
        ax.set_ylim(bottom=0)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
