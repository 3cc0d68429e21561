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


def _save(fig: Any, path: Path) -> Path:
    """Lay out, write the PNG (creating its folder) and close the figure; returns ``path``."""
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def _arr(values: Sequence[Any]) -> np.ndarray:
    return np.array([np.nan if v is None else v for v in values], dtype=float)


def plot_stopping_function(settings: Sequence[Mapping[str, Any]], function: str, path: Path) -> Path:
    """One function's panel row in the layout of Kim et al. 2019 Fig. 2.

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
    return _save(fig, path)


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
    return _save(fig, path)


def plot_pairs(grid: Sequence[Mapping[str, Any]], chosen: Mapping[str, Any], path: Path, *,
               n_max: int, max_rejected_pct: float, max_breath_fraction: float) -> Path:
    """The sound rule's trade-off on pairs of transitions: breaths against wrong rejections.

    Args:
        grid: Entries with ``min_decision_s``, ``a_floor``, ``mean_breaths`` and
            ``pct_rejected_better`` (None without truly better candidates: not drawn).
        chosen: The rule the command ran (same keys), marked.
        path: PNG to write.
        n_max: N, for the breath target's line.
        max_rejected_pct: The rejection target (%), a line.
        max_breath_fraction: The breath target as a fraction of N, a line.

    Returns:
        ``path``.
    """
    fig, ax = plt.subplots(figsize=(6.0, 4.2))
    times = sorted({float(g["min_decision_s"]) for g in grid})
    for k, t in enumerate(times):
        pts = sorted((g for g in grid if float(g["min_decision_s"]) == t
                      and g["pct_rejected_better"] is not None), key=lambda g: float(g["a_floor"]))
        if not pts:
            continue
        x = [float(g["mean_breaths"]) for g in pts]
        y = [float(g["pct_rejected_better"]) for g in pts]
        ax.plot(x, y, marker="o", ms=3, lw=1.0, color=f"C{k}", label=f"no decision before {t:g} s")
        for g, xi, yi in zip(pts, x, y, strict=True):
            ax.annotate(f"{float(g['a_floor']):g}σ", (xi, yi), fontsize=6, xytext=(2, 2),
                        textcoords="offset points")
    if chosen.get("pct_rejected_better") is not None:
        ax.plot([chosen["mean_breaths"]], [chosen["pct_rejected_better"]], marker="*", ms=12,
                color="k", ls="none", label="the rule run (table)")
    ax.axvline(max_breath_fraction * n_max, color="grey", ls="--", lw=0.8)
    ax.axhline(max_rejected_pct, color="grey", ls="--", lw=0.8)
    ax.set_xlabel(f"mean breaths per evaluation (N = {n_max}); target left of the dashed line")
    ax.set_ylabel("truly better candidates rejected (%); target below")
    ax.set_title("sound rule on within-person pairs: threshold floor a (labels) × time floor", fontsize=9)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    return _save(fig, path)
