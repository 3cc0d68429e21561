"""The PNG plots of ``hilbo review`` (matplotlib's Agg canvas; no display, no pyplot state).

Every figure has a fixed size in pixels (:data:`PLOT_SIZES_PX`, at :data:`DPI`); they are saved
without tight bounding boxes so the files have exactly that size. matplotlib is imported inside
the functions, so importing this module (and ``hilbo --help``) stays fast.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from drivers.files import create_private_file

if TYPE_CHECKING:
    from matplotlib.figure import Figure

    from bridge.review.session import Session

__all__ = ["DPI", "PLOT_FILES", "PLOT_SIZES_PX", "compare_plot", "session_plots"]

DPI = 100
"""Dots per inch of every figure."""

PLOT_FILES: Mapping[str, str] = {
    "timeline": "timeline.png",
    "best_so_far": "best_so_far.png",
    "parameters": "parameters.png",
    "thresholds": "thresholds.png",
    "force_tracking": "force_tracking.png",
}
"""File name of each plot of a session review."""

PLOT_SIZES_PX: Mapping[str, tuple[int, int]] = {
    "timeline": (1400, 700),
    "best_so_far": (900, 500),
    "parameters": (1200, 800),
    "thresholds": (900, 500),
    "force_tracking": (1200, 500),
    "compare": (1300, 500),
}
"""(width, height) in pixels of each plot."""

_PHASE_COLOURS = {"exploration": "tab:blue", "optimization": "tab:orange"}
_EARLY = {"marker": "x", "color": "tab:red", "s": 60, "zorder": 5, "linewidths": 2}


def _figure(name: str) -> Figure:
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    w, h = PLOT_SIZES_PX[name]
    fig = Figure(figsize=(w / DPI, h / DPI), dpi=DPI)
    FigureCanvasAgg(fig)
    return fig


def _save(fig: Figure, path: Path, mode: int) -> Path:
    with create_private_file(path, mode) as f:  # the plots show health data: the session's mode
        fig.savefig(f, dpi=DPI, format="png")
    return path


def _mark_resumes(ax: Any, session: Session, minutes: bool = True) -> None:
    for t in session.resume_times_s:
        ax.axvline(t / 60.0 if minutes else t, color="tab:red", ls="--", lw=1.2)
        ax.annotate("resumed", (t / 60.0 if minutes else t, 1.0), xycoords=("data", "axes fraction"),
                    xytext=(3, -12), textcoords="offset points", color="tab:red", fontsize=8)


_OPTIMISATION_PLOTS = frozenset({"best_so_far", "parameters", "thresholds"})


def session_plots(session: Session, out: Path) -> tuple[dict[str, Path], dict[str, str]]:
    """Draw every plot of a session review into ``out``.

    Args:
        session: The session.
        out: Output directory (exists).

    Returns:
        ``({plot name: path}, {plot name: why it was skipped})``. A skipped plot's stale file from
        an earlier review is removed.
    """
    drawn: dict[str, Path] = {}
    skipped: dict[str, str] = {}
    makers = {
        "timeline": _timeline, "best_so_far": _best_so_far, "parameters": _parameters,
        "thresholds": _thresholds, "force_tracking": _force_tracking,
    }
    for name, make in makers.items():
        path = out / PLOT_FILES[name]
        if session.validation_plan is not None and name in _OPTIMISATION_PLOTS:
            # A validation walk's conditions are not an optimisation's settings (its unassisted
            # one applies no setting at all): best-so-far, parameters and thresholds mean nothing.
            why: str | None = ("a validation walk measures fixed conditions, not an optimisation "
                               "(their results are in the Validation walk section)")
        else:
            why = make(session, path)
        if why is None:
            drawn[name] = path
        else:
            skipped[name] = why
            path.unlink(missing_ok=True)
    return drawn, skipped


def _mark_pauses(ax: Any, session: Session, *, label: bool) -> None:
    """Shade each pause (assistance off: the operator's, a fault's, the one between the bouts)."""
    end_s = session.breaths[-1].time_s if session.breaths else 0.0
    for k, (t0, t1) in enumerate(session.pauses):
        ax.axvspan(t0 / 60.0, (end_s if t1 is None else t1) / 60.0, color="tab:red", alpha=0.08, lw=0,
                   label="paused (assistance off)" if label and k == 0 else None)


def _timeline(session: Session, path: Path) -> str | None:
    """(a) breath-by-breath power, the session's estimate with its ±1 σ band, setting changes
    and pauses (Kim et al. 2019 Fig. 1)."""
    if not session.breaths:
        return "the log holds no breaths"
    fig = _figure("timeline")
    ax, ax_sd = fig.subplots(2, 1, sharex=True, gridspec_kw={"height_ratios": [3, 1]})
    t = np.array([b.time_s for b in session.breaths]) / 60.0
    w = np.array([np.nan if b.watts is None else b.watts for b in session.breaths])
    ax.plot(t, w, ".", color="0.55", ms=3, label="breath (Brockway)")
    labelled: set[str] = set()
    for tr in session.traces:
        x = np.asarray(tr.time_s) / 60.0
        mean, sd = np.asarray(tr.mean_w), np.asarray(tr.sd_w)
        colour = _PHASE_COLOURS.get(tr.phase, "tab:green") if tr.completed else "0.4"
        label = (f"{session.estimator_label} ({tr.phase})" if tr.completed else "abandoned setting") \
            if (tr.phase if tr.completed else "abandoned") not in labelled else None
        labelled.add(tr.phase if tr.completed else "abandoned")
        ax.plot(x, mean, color=colour, lw=1.6, ls="-" if tr.completed else ":", marker=".", ms=4,
                label=label)
        ax.fill_between(x, mean - sd, mean + sd, color=colour, alpha=0.15, lw=0)
        ax_sd.plot(x, sd, color=colour, lw=1.2, ls="-" if tr.completed else ":")
        for a in (ax, ax_sd):
            a.axvline(tr.t_start_s / 60.0, color="0.75", lw=0.8, zorder=0)
    if len(session.evaluations) <= 60:
        for e in session.evaluations:
            if e.t_start_s is not None:
                ax.annotate(str(e.index + 1), (e.t_start_s / 60.0, 1.0), xycoords=("data", "axes fraction"),
                            xytext=(2, -10), textcoords="offset points", fontsize=7, color="0.3")
    band = "±1 σ band of the estimate"
    ax.fill_between([], [], [], color="0.5", alpha=0.15, label=band)
    finite = w[np.isfinite(w)]
    if finite.size:
        lo, hi = np.percentile(finite, [1, 99])
        pad = 0.25 * max(hi - lo, 1.0)
        ax.set_ylim(lo - pad, hi + pad)
    _mark_resumes(ax, session)
    _mark_resumes(ax_sd, session)
    _mark_pauses(ax, session, label=True)
    _mark_pauses(ax_sd, session, label=False)
    ax.set_ylabel("metabolic power (W)")
    ax.set_title(f"{session.label}: breath-by-breath power and the estimate of each setting "
                 "(grey lines: setting changes, numbers: evaluations, red: paused)", fontsize=10)
    ax.legend(loc="lower center", fontsize=8, ncol=5, framealpha=0.8)
    ax.grid(alpha=0.3)
    ax_sd.set_ylabel("estimate σ (W)")
    ax_sd.set_xlabel("session time (min)")
    ax_sd.grid(alpha=0.3)
    fig.subplots_adjust(left=0.07, right=0.98, top=0.94, bottom=0.09, hspace=0.08)
    _save(fig, path, session.file_mode)
    return None


def _best_so_far(session: Session, path: Path) -> str | None:
    """(b) best estimated cost so far against minutes walked."""
    if not session.evaluations:
        return "no evaluation completed"
    fig = _figure("best_so_far")
    ax = fig.subplots()
    pts = session.best_so_far()
    t = np.array([p[0] for p in pts])
    ax.step(t, [p[1] for p in pts], where="post", color="k", lw=2,
            label="best so far (lowest raw estimate)")
    for phase, colour in _PHASE_COLOURS.items():
        es = [(tt, e) for tt, e in zip(t, session.evaluations, strict=True) if e.phase == phase]
        if es:
            ax.errorbar([x for x, _ in es], [e.mean_w for _, e in es], yerr=[e.sd_w for _, e in es], fmt="o",
                        color=colour, ms=4, alpha=0.7, elinewidth=0.8, capsize=2, label=f"{phase} (±1σ)")
    early = [(tt, e.mean_w) for tt, e in zip(t, session.evaluations, strict=True) if e.stopped_early]
    if early:
        ax.scatter(*zip(*early, strict=True), label="stopped early", **_EARLY)
    rec = session.recommended
    if rec is not None:
        label = f"recommended: {rec.mean_w:.1f} W"
        if not math.isclose(rec.mean_w, pts[-1][1], rel_tol=1e-9):
            # The recommendation is the GP's estimate over every evaluation, not the lowest raw
            # estimate (the winner's curse biases that one low): the two lines differ on purpose.
            label += " (GP posterior; differs from the best raw estimate)"
        ax.axhline(rec.mean_w, color="tab:green", ls="--", lw=1.2, label=label)
    _mark_resumes(ax, session)
    ax.set_xlabel("minutes walked (end of each evaluation)")
    ax.set_ylabel("estimated cost (W)")
    ax.set_title(f"{session.label}: best estimated cost so far", fontsize=10)
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    fig.subplots_adjust(left=0.1, right=0.97, top=0.92, bottom=0.11)
    _save(fig, path, session.file_mode)
    return None


def _parameters(session: Session, path: Path) -> str | None:
    """(c) each parameter against evaluation number, early stops marked."""
    if not session.evaluations:
        return "no evaluation completed"
    names = list(session.param_names) or sorted(session.evaluations[0].params)
    fig = _figure("parameters")
    ncols = 2 if len(names) <= 4 else 3
    nrows = max(1, math.ceil(len(names) / ncols))
    axes = np.atleast_1d(fig.subplots(nrows, ncols, sharex=True, squeeze=False)).ravel()
    n = np.array([e.index + 1 for e in session.evaluations])
    n_explore = sum(e.phase == "exploration" for e in session.evaluations)
    rec = session.recommended
    for ax, name in zip(axes, names, strict=False):
        v = np.array([e.params.get(name, np.nan) for e in session.evaluations])
        ax.plot(n, v, "-", color="0.7", lw=0.8)
        for phase, colour in _PHASE_COLOURS.items():
            sel = np.array([e.phase == phase for e in session.evaluations])
            if sel.any():
                ax.plot(n[sel], v[sel], "o", color=colour, ms=4, label=phase)
        early = np.array([e.stopped_early for e in session.evaluations])
        if early.any():
            ax.scatter(n[early], v[early], label="stopped early", **_EARLY)
        if rec is not None and rec.index is not None:
            ax.scatter([rec.index + 1], [rec.params.get(name, np.nan)], s=160, facecolors="none",
                       edgecolors="tab:green", linewidths=2, zorder=6, label="recommended")
        if n_explore:
            ax.axvspan(0.5, n_explore + 0.5, color="tab:blue", alpha=0.06)
        if name in session.param_bounds:
            lo, hi = session.param_bounds[name]
            pad = 0.05 * (hi - lo)
            ax.set_ylim(lo - pad, hi + pad)
        unit = session.param_units.get(name, "")
        ax.set_ylabel(f"{name} ({unit})" if unit else name, fontsize=9)
        ax.grid(alpha=0.3)
    for ax in axes[len(names):]:
        ax.set_visible(False)
    for ax in axes[max(0, len(names) - ncols):len(names)]:
        ax.set_xlabel("evaluation")
        ax.tick_params(labelbottom=True)
    axes[0].legend(fontsize=7, loc="best")
    fig.suptitle(f"{session.label}: parameters per evaluation (shaded: exploration)", fontsize=10)
    fig.subplots_adjust(left=0.07, right=0.98, top=0.93, bottom=0.08, hspace=0.25, wspace=0.3)
    _save(fig, path, session.file_mode)
    return None


def _thresholds(session: Session, path: Path) -> str | None:
    """(d) the threshold schedule A against breath index, the exploration traces behind it."""
    th = session.thresholds
    if th is None:
        return "the log holds no threshold schedule and too few complete exploration traces to compute one"
    fig = _figure("thresholds")
    ax = fig.subplots()
    i = np.arange(1, th.thresholds.size + 1)
    for k, row in enumerate(th.traces):
        ax.plot(i, row, "-", color="0.6", lw=1, label="exploration traces X" if k == 0 else None)
    for k, z in enumerate(th.z_traces):
        b = np.asarray(z.breath) + 1
        ax.plot(b, z.z, "-", color="tab:orange", lw=0.7, alpha=0.5,
                label="optimisation z = (μ − μ*)/σ" if k == 0 else None)
        if z.stopped_early:
            ax.scatter([b[-1]], [z.z[-1]], **_EARLY)
    if any(z.stopped_early for z in th.z_traces):
        ax.scatter([], [], label="stopped early", **_EARLY)
    floor = session.threshold_floor
    if floor is None:
        ax.plot(i, th.thresholds, "o-", color="k", lw=2, ms=4, label="threshold A (used as is)")
        title = "threshold schedule (Algorithm 2); stop when z > A_i"
    else:
        # The session's sound rule stops on max(A_i, a_floor): the floored schedule is what it used.
        ax.plot(i, th.thresholds, "--", color="0.35", lw=1, label="Algorithm 2's A (before the floor)")
        ax.plot(i, np.maximum(th.thresholds, floor), "o-", color="k", lw=2, ms=4,
                label=f"threshold used: max(A_i, {floor:g})")
        title = f"threshold schedule used (Algorithm 2 floored at {floor:g} σ); stop when z > it"
    ax.axhline(0.0, color="0.3", lw=0.6)
    finite = np.concatenate([th.thresholds, th.traces.ravel()] + [np.asarray(z.z) for z in th.z_traces])
    finite = finite[np.isfinite(finite)]
    if finite.size:
        lo, hi = np.percentile(finite, [1, 99])
        pad = 0.15 * max(hi - lo, 0.5)
        ax.set_ylim(min(lo, 0.0) - pad, hi + pad)
    ax.set_xlabel("breath index i (within an evaluation)")
    ax.set_ylabel("standardised distance")
    ax.set_title(f"{session.label}: {title}", fontsize=10)
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    fig.subplots_adjust(left=0.1, right=0.97, top=0.92, bottom=0.11)
    _save(fig, path, session.file_mode)
    return None


def _binned(phase: np.ndarray, values: np.ndarray, width: float = 2.0) -> tuple[np.ndarray, np.ndarray]:
    edges = np.arange(0.0, 100.0 + width, width)
    idx = np.clip(np.digitize(phase, edges) - 1, 0, edges.size - 2)
    centres, means = [], []
    for b in range(edges.size - 1):
        sel = idx == b
        if sel.any():
            centres.append(0.5 * (edges[b] + edges[b + 1]))
            means.append(float(values[sel].mean()))
    return np.array(centres), np.array(means)


def _force_tracking(session: Session, path: Path) -> str | None:
    """(e) desired vs measured force over the gait cycle, recommended setting (Kim et al. 2019 Fig. 4)."""
    fb = session.feedback
    if fb is None:
        return "the log has no force feedback for the recommended setting"
    fig = _figure("force_tracking")
    acts = sorted(fb.samples)
    axes = np.atleast_1d(fig.subplots(1, len(acts), squeeze=False)).ravel()
    for ax, act in zip(axes, acts, strict=True):
        g, des, mea = fb.samples[act]
        joint = fb.tables[act][0] if act in fb.tables else ""
        if act in fb.tables:
            ax.plot(fb.tables[act][1], fb.tables[act][2], "-", color="k", lw=2, label="desired (table sent)")
        else:
            gc, dc = _binned(g, des)
            ax.plot(gc, dc, "-", color="k", lw=2, label="desired (feedback)")
        ax.plot(g, mea, ".", color="tab:blue", ms=3, alpha=0.5, label="measured samples")
        gc, mc = _binned(g, mea)
        ax.plot(gc, mc, "-", color="tab:blue", lw=1.4, label="measured (2 % bins)")
        peak = max(float(np.max(des)), 1e-9)
        rms = float(np.sqrt(np.mean((mea - des) ** 2)))
        ax.set_title(f"actuator {act}{f' ({joint})' if joint else ''}: RMS error {rms:.1f} N "
                     f"= {100 * rms / peak:.1f} % of peak, {g.size} samples", fontsize=9)
        ax.set_xlabel("gait cycle (%)")
        ax.set_ylabel("force (N)")
        ax.set_xlim(0, 100)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    what = "the measured setting nearest the recommendation" if fb.nearest else "recommended setting"
    fig.suptitle(f"{session.label}: desired vs measured force, {what} "
                 f"(evaluation {fb.index + 1}, profile version {fb.version})", fontsize=10)
    fig.subplots_adjust(left=0.06, right=0.98, top=0.86, bottom=0.11, wspace=0.2)
    _save(fig, path, session.file_mode)
    return None


def compare_plot(sessions: Sequence[Session], path: Path) -> Path:
    """Best so far against minutes for each session, and their evaluation counts.

    Args:
        sessions: The sessions (labelled A, B, ...).
        path: The PNG to write.

    Returns:
        ``path``.
    """
    fig = _figure("compare")
    ax, ax_n = fig.subplots(1, 2, gridspec_kw={"width_ratios": [2.2, 1]})
    colours = ["tab:blue", "tab:orange", "tab:green", "tab:purple"]
    for k, s in enumerate(sessions):
        tag = chr(ord("A") + k)
        c = colours[k % len(colours)]
        pts = s.best_so_far()
        if pts:
            ax.step([p[0] for p in pts], [p[1] for p in pts], where="post", color=c, lw=2,
                    label=f"{tag}: {s.label}")
            early = [(p[0], e.mean_w) for p, e in zip(pts, s.evaluations, strict=True) if e.stopped_early]
            ax.plot([p[0] for p in pts], [e.mean_w for e in s.evaluations], "o", color=c, ms=3, alpha=0.5)
            if early:
                ax.plot(*zip(*early, strict=True), "x", color=c, ms=7, mew=2)
        if s.recommended is not None:
            ax.axhline(s.recommended.mean_w, color=c, ls="--", lw=1)
    ax.set_xlabel("minutes walked")
    ax.set_ylabel("estimated cost (W)")
    ax.set_title("best estimated cost so far (dots: evaluations, x: early stops, dashed: recommended)",
                 fontsize=9)
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    groups = ["evaluations", "exploration", "optimisation", "early stops"]
    width = 0.8 / max(len(sessions), 1)
    for k, s in enumerate(sessions):
        n_exp = sum(e.phase == "exploration" for e in s.evaluations)
        counts = [len(s.evaluations), n_exp, len(s.evaluations) - n_exp, s.n_early_stops]
        x = np.arange(len(groups)) + (k - (len(sessions) - 1) / 2) * width
        bars = ax_n.bar(x, counts, width, color=colours[k % len(colours)], label=chr(ord("A") + k))
        ax_n.bar_label(bars, fontsize=8)
    ax_n.set_xticks(np.arange(len(groups)), groups, fontsize=8)
    ax_n.set_title("evaluation counts", fontsize=9)
    ax_n.legend(fontsize=8)
    ax_n.grid(alpha=0.3, axis="y")
    fig.subplots_adjust(left=0.06, right=0.98, top=0.9, bottom=0.11, wspace=0.18)
    return _save(fig, path, sessions[0].file_mode & sessions[-1].file_mode)
