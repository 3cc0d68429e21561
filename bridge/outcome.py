"""How a session ended and what it recommends, in the words a lab writes down.

The end of a session is the lab's product (shared/DESIGN.md "Recommendation"): why it ended,
the recommended setting with its units, its estimate with a labelled interval and how that was
measured, and the minutes walked. The summary, the last line of ``hilbo run``, the operator
view's last frame and ``hilbo validate`` all say it with the functions here.
"""

from __future__ import annotations

import enum
import math
from collections.abc import Mapping, Sequence
from typing import Any

from hilbo_core.protocol import EndReason as ProtocolEndReason

__all__ = [
    "Z95",
    "SessionEnd",
    "format_params",
    "format_value",
    "recommendation",
    "recommendation_method_text",
    "recommendation_text",
    "session_end",
]

#: The normal quantile of a two-sided 95 % interval.
Z95 = 1.959963984540054


class SessionEnd(enum.Enum):
    """Why a session ended (the summary's ``end_reason``; never null)."""

    SESSION = "session"  # [protocol] session_min walked
    BUDGET = "budget"  # the optimisation bout's budget_min walked
    BUDGET_BREATHS = "budget_breaths"  # the optimisation bout's budget in breaths
    CONDITIONS_DONE = "conditions_done"  # hilbo validate: every condition measured
    OPERATOR_STOP = "operator_stop"  # q in the operator view
    INTERRUPTED = "interrupted"  # Ctrl-C (SIGINT) or SIGTERM
    CART_ENDED = "cart_ended"  # the cart's stream ended (a replay's file, a closed link)
    RESUME_BUDGET = "resume_budget"  # [watchdog] max_auto_resumes used; stopped, not waiting
    PERSON_REQUIRED = "person_required"  # a fault only a person may resume from, and no keyboard
    BUS_FAILED = "bus_failed"  # the CAN bus failed
    ERROR = "error"  # an error ended the session (its message is in the log's events)

    @property
    def text(self) -> str:
        """The reason in a sentence fragment ("ended: ...")."""
        return _END_TEXT[self]


_END_TEXT = {
    SessionEnd.SESSION: "the session's walking time ([protocol] session_min) was spent",
    SessionEnd.BUDGET: "the optimisation bout's budget ([protocol] budget_min) was spent",
    SessionEnd.BUDGET_BREATHS: "the optimisation bout's budget in breaths was spent",
    SessionEnd.CONDITIONS_DONE: "every validation condition was measured",
    SessionEnd.OPERATOR_STOP: "stopped by the operator",
    SessionEnd.PERSON_REQUIRED: ("a fault only a person may resume from (an emergency stop), and no "
                                 "operator keyboard in this run; hilbo run --resume continues"),
    SessionEnd.INTERRUPTED: "interrupted (Ctrl-C or SIGTERM)",
    SessionEnd.CART_ENDED: "the cart's data ended",
    SessionEnd.RESUME_BUDGET: "the automatic resumes ([watchdog] max_auto_resumes) were used up",
    SessionEnd.BUS_FAILED: "the CAN bus failed",
    SessionEnd.ERROR: "an error (see the log's events)",
}

_FROM_PROTOCOL = {
    ProtocolEndReason.SESSION: SessionEnd.SESSION,
    ProtocolEndReason.BUDGET: SessionEnd.BUDGET,
    ProtocolEndReason.BUDGET_BREATHS: SessionEnd.BUDGET_BREATHS,
    ProtocolEndReason.STOPPED: SessionEnd.OPERATOR_STOP,
}


def session_end(reason: ProtocolEndReason) -> SessionEnd:
    """The session's end reason for the protocol's."""
    return _FROM_PROTOCOL[reason]


def format_value(value: float, unit: str = "") -> str:
    """A parameter value as a lab reads it: at most one decimal (two below 10), no exponent.

    ``1.66e-11`` (a bound reached in floating point) prints as ``0.00``; ``52.37`` as ``52.4``.
    """
    if not math.isfinite(value):
        text = str(value)
    else:
        text = f"{value:.2f}" if abs(value) < 10 else f"{value:.1f}"
        if text in ("-0.00", "-0.0"):
            text = text[1:]
    unit = unit.strip()
    return f"{text} {unit}" if unit else text


def format_params(params: Mapping[str, float], units: Mapping[str, str] | None = None) -> str:
    """``name = value unit`` for every parameter, comma separated."""
    units = units or {}
    return ", ".join(f"{k} = {format_value(float(v), units.get(k, ''))}" for k, v in params.items())


def recommendation(params: Mapping[str, float], mean_w: float, var_w2: float, *,
                   evaluations: Sequence[Mapping[str, Any]], method: str,
                   units: Mapping[str, str] | None = None) -> dict[str, Any]:
    """The summary's ``recommendation``: the setting, its estimate with a 95 % interval, how it
    was measured.

    Args:
        params: The recommended setting (``HILOptimizer.best()``).
        mean_w, var_w2: Its estimated cost (W) and variance (W²).
        evaluations: The session's evaluations (``params``, ``breaths``) as in the summary.
        method: How the estimate is made (``OptimizerConfig.recommend``: ``posterior`` or ``seed``).
        units: Parameter units.
    """
    same = [e for e in evaluations if _same_setting(e["params"], params)]
    sd = math.sqrt(max(var_w2, 0.0))
    return {
        "params": dict(params),
        "units": {k: (units or {}).get(k, "") for k in params},
        "mean_w": mean_w,
        "var_w2": var_w2,
        "ci95_w": [mean_w - Z95 * sd, mean_w + Z95 * sd],
        "method": method,
        "n_evaluations_at_setting": len(same),
        "n_breaths_at_setting": int(sum(int(e.get("breaths", 0)) for e in same)),
        "n_evaluations": len(evaluations),
    }


def _same_setting(a: Mapping[str, float], b: Mapping[str, float]) -> bool:
    return a.keys() == b.keys() and all(math.isclose(float(a[k]), float(b[k]), rel_tol=1e-9, abs_tol=1e-9)
                                        for k in a)


_METHOD_TEXT = {
    "global": "lowest GP posterior mean + 1 SD over the whole feasible set, from all {n} evaluations",
    "posterior": "GP posterior over all {n} evaluations",
    "seed": "the evaluation's own estimate at the GP's estimated minimum ({n} evaluations)",
}


def recommendation_method_text(method: str, n_evaluations: int) -> str:
    """How a recommendation of ``OptimizerConfig.recommend`` = ``method`` was chosen, in words."""
    return _METHOD_TEXT.get(method, method + " ({n} evaluations)").format(n=n_evaluations)


def recommendation_text(rec: Mapping[str, Any]) -> str:
    """The recommended setting in one line: parameters with units, estimate with its labelled
    interval, and how it was measured."""
    lo, hi = rec["ci95_w"]
    how = recommendation_method_text(rec["method"], rec["n_evaluations"])
    n_ev, n_br = rec["n_evaluations_at_setting"], rec["n_breaths_at_setting"]
    return (f"recommended setting: {format_params(rec['params'], rec['units'])}; estimated "
            f"{rec['mean_w']:.1f} W (95 % CI {lo:.1f} to {hi:.1f} W; {how}; this setting measured "
            f"{n_ev} time{'s' if n_ev != 1 else ''}, {n_br} breaths)")
