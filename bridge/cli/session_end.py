"""What ``hilbo run``, ``hilbo validate`` and ``hilbo sim`` share at a session's end: the last
lines, the exit status and its help text."""

from __future__ import annotations

from typing import Any

__all__ = ["EXIT_INTERRUPTED", "EXIT_NOTHING_MEASURED", "RUN_EXIT_STATUS", "VALIDATE_EXIT_STATUS",
           "ended_text", "run_exit_status"]


#: ``hilbo run``'s exit status for a session that ended without a completed evaluation.
EXIT_NOTHING_MEASURED = 3
#: Exit status of a session stopped by SIGINT or SIGTERM: 130 (128 + SIGINT, as shells report
#: Ctrl-C) for both.
EXIT_INTERRUPTED = 130

_EXIT_STATUS = """\
exit status: 0 the session ended with at least one completed evaluation; 1 an error (one line
naming it); 2 a wrong command line; 3 {three}; 130 stopped by Ctrl-C or SIGTERM. A session that
has started writes its log and its summary whatever its exit status."""

RUN_EXIT_STATUS = _EXIT_STATUS.format(
    three="the session ended without a completed evaluation (nothing to recommend)")
VALIDATE_EXIT_STATUS = _EXIT_STATUS.format(three="the walk ended before any condition was measured")


def ended_text(s: dict[str, Any]) -> str:
    """The last lines of ``hilbo run``: why the session ended, evaluations, minutes walked, and
    the recommended setting (parameters with units, estimate with its 95 % interval, how it was
    measured)."""
    from bridge.outcome import SessionEnd, recommendation_text

    reason = s.get("end_reason")
    why = SessionEnd(reason).text if reason in {e.value for e in SessionEnd} else str(reason)
    text = f"session ended: {why}; {s['n_evaluations']} evaluations ({s['n_early_stops']} early stops)"
    n_all = _n_session(s)
    if n_all > s["n_evaluations"]:  # a resumed session: the earlier logs' evaluations too
        text += f" in this run, {n_all} in the session"
    walking = s.get("walking") or {}
    if "session_s" in walking:
        text += f"; {walking['session_s'] / 60:.1f} min walked"
        if walking.get("optimization_s"):
            text += f", {walking['optimization_s'] / 60:.1f} of them in the optimisation bout"
    rec = s.get("recommendation")
    if rec is not None:
        text += "\n" + recommendation_text(rec)
    conf = s.get("confirmation") or {}
    if conf.get("mean_w") is not None and conf.get("sd_w") is not None:
        # The recommendation measured in full in the session's last minutes: its own breaths.
        text += f"\nrecommended, confirmed at {conf['mean_w']:.1f} ± {conf['sd_w']:.1f} W (SD)"
    elif not n_all:
        text += f"\nno evaluation completed: nothing to recommend (exit status {run_exit_status(s)})"
    return text


def run_exit_status(summary: dict[str, Any]) -> int:
    """0, or 130 for a signal's stop, or 3 for a session that measured nothing."""
    if summary.get("end_reason") == "interrupted":
        return EXIT_INTERRUPTED
    return 0 if _n_session(summary) else EXIT_NOTHING_MEASURED


def _n_session(summary: dict[str, Any]) -> int:
    """The session's evaluations: a resumed run's with its earlier logs' (summaries written
    before ``n_evaluations_session`` existed have only ``n_evaluations``)."""
    return int(summary.get("n_evaluations_session", summary["n_evaluations"]))
