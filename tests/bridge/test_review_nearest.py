"""hilbo review's force-tracking plot when the recommendation is a setting never applied.

The recommendation over the whole feasible set can be a setting that was never measured (the
GP's minimum moved after the last evaluation); the plot then shows the measured setting nearest
to it, each parameter scaled by its range, and the notes say so.
"""

from __future__ import annotations

import types

from bridge.review.session import _nearest_evaluation

BOUNDS = {"a": (0.0, 100.0), "b": (0.0, 1.0)}


def _ev(index: int, a: float, b: float) -> types.SimpleNamespace:
    return types.SimpleNamespace(index=index, params={"a": a, "b": b})


def test_the_nearest_in_the_scaled_space_not_in_raw_units() -> None:
    # Raw distance would pick evaluation 0 (a differs by 5, b by 0.5); scaled, evaluation 1
    # (a differs by 0.2 of its range, b by 0.05) is nearer than 0 (0.05 and 0.5).
    evals = [_ev(0, 45.0, 0.0), _ev(1, 30.0, 0.45), _ev(2, 90.0, 0.9)]
    assert _nearest_evaluation(evals, {"a": 50.0, "b": 0.5}, BOUNDS, {0, 1, 2}) == 1


def test_only_logged_evaluations_with_the_same_parameters_count() -> None:
    evals = [_ev(0, 50.0, 0.5), _ev(1, 10.0, 0.1), types.SimpleNamespace(index=2, params={"a": 50.0})]
    assert _nearest_evaluation(evals, {"a": 50.0, "b": 0.5}, BOUNDS, {1, 2}) == 1
    assert _nearest_evaluation(evals, {"a": 50.0, "b": 0.5}, BOUNDS, set()) is None
