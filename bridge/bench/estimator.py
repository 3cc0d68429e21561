"""``hilbo bench estimator``: accuracy and calibration of the breath-by-breath estimators.

For every transition (a setting change) and every horizon h (30/60/90/120/180 s after it) each
estimator sees the breaths of the new setting up to h and reports (mean, sd) of the steady-state
cost c. Against the truth c:

* accuracy: MAPE = mean |ĉ − c|/c and bias = mean (ĉ − c)/c, in %;
* calibration: z = (ĉ − c)/sd — its mean and SD (1 when sd describes the errors) and the share
  of |z| ≤ 1.96 (95 % interval coverage);

split by step size: *small* when the first breath of the setting is less than 50 % away from
the new steady state, *large* otherwise; and the horizons 60-180 s pooled (on one recording a
horizon has a handful of transitions: a coverage of 9 is 89 % or 100 %, nothing between).

Estimators:

* ``transition`` — :class:`~hilbo_core.estimation.TransitionEstimator`, the optimizer's default;
  like in the optimizer it starts each setting from the level it ended the previous one at;
  ``--transition-config KEY=VALUE,...`` sets fields of its
  :class:`~hilbo_core.estimation.TransitionConfig` (e.g. ``timing_sd_s=0`` for the fit without
  its timing term);
* ``seed_ukf`` — :class:`~hilbo_core.metabolic.MetabolicUKF` (Kim et al. 2019 §II.C);
* ``first_order_42`` — the lab's fit: least squares of y = c + (y0 − c)·e^{−t/42 s} in (c, y0),
  sd from the residual variance;
* ``full_ls`` — least squares of the full model y = c + (b0 − c)·e^{−t/τ} in (c, b0, τ)
  (profiled over a τ grid of 5–300 s), sd from the Jacobian at the optimum.

Data:

* synthetic (default): :func:`synthetic_people` — a small pure generator of breath trajectories
  (documented there). ``--wearer NAME`` picks a registered wearer (:data:`WEARERS`):
  ``synthetic`` or ``realistic`` (the simulated wearer of the virtual devices; it stands for a
  bout before the first setting and after every ``--rest-every`` settings, 3 by default, so
  that its large steps are scored beside the small steps of assistance changes).
* ``--replay FILE --transitions t1,t2,...`` (or ``--events FILE``, a CSV ``t_s,label`` of the
  changes): a recorded breath file (hilbo-line, a vendor export ``hilbo cart inspect``
  recognises, or a CSV with ``--csv-columns TIME,VO2,VCO2``) read with the cart driver's parsers
  and validator; the bouts are [t_k, t_{k+1}) (the last to the end of the file). The truth of a
  bout is the mean of its breaths from max(180 s, end − 180 s) to its end (at most its last
  3 minutes, none of the breaths an estimate at ≤ 180 s saw), reported with that mean's standard
  error. Scored: every bout after the first whose truth window spans ≥ 60 s, or those whose
  label ``--score LABELS`` names; the rest (rests, warm-ups, the first bout) only move the
  chained estimator on. ``estimator_bouts.md`` lists every bout, scored or not and why, its
  truth with its SE, and the breaths the default estimator flagged as implausible.
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools
import math
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from bridge.argtypes import nonnegative_int, positive_int
from bridge.bench.common import machine_info, markdown_table, round_sig, write_json
from bridge.sim.devices import WearerKind, make_wearer
from hilbo_core import brockway_watts
from hilbo_core.errors import ConfigError, EstimatorError, MeasurementError
from hilbo_core.estimation import StartState, TransitionConfig, TransitionEstimator
from hilbo_core.metabolic import MetabolicUKF
from hilbo_core.presets import hip_6d

__all__ = [
    "ESTIMATORS",
    "HORIZONS_S",
    "WEARERS",
    "Bout",
    "add_estimator_bench_parser",
    "chained_estimators",
    "comparison_table",
    "evaluate",
    "parse_transition_config",
    "parse_transitions",
    "realistic_people",
    "replay_people",
    "run_estimator_bench",
    "summarize",
    "synthetic_people",
]

HORIZONS_S: tuple[float, ...] = (30.0, 60.0, 90.0, 120.0, 180.0)
ESTIMATORS: tuple[str, ...] = ("transition", "seed_ukf", "first_order_42", "full_ls")
_LARGE_STEP = 0.5  # large: the first breath more than 50 % away from the new steady state
_Z95 = 1.959963984540054
_LAB_TAU_S = 42.0  # Selinger & Donelan (2014), the first-order fit labs use
_FULL_TAU_GRID_S = np.geomspace(5.0, 300.0, 80)
_TRUTH_WINDOW_S = 180.0  # a replay's truth: the mean of at most the bout's last 3 minutes...
_TRUTH_MIN_SPAN_S = 60.0  # ...after the last horizon, spanning at least a minute to be scored
_POOLED = (60.0, 180.0)  # the horizons pooled into one calibration figure
# The realistic wearer stands after every 3 settings: of 8 bouts, 3 large steps and 4 small scored.
_REST_EVERY = 3


@dataclass(frozen=True)
class Bout:
    """The breaths of one setting.

    Attributes:
        t_s: Breath times since the setting began, shape (n,), strictly increasing.
        watts: Breath powers in W, shape (n,).
        truth_w: The setting's steady-state cost in W.
        first_distance: |first-breath level − truth| / truth (noise-free level when known).
        evaluate: Whether this bout is a transition to score (the first bout of a person only
            starts the chained estimator).
        label: The bout's name (a replay's event label; "" when none).
        truth_se_w: The standard error of ``truth_w`` in W (0 when the truth is known, as in
            the simulations; a replay's truth is a mean of breaths).
        truth_n: Breaths the truth is the mean of (0 when it is known).
        note: Why a bout is not scored ("" when it is).
    """

    t_s: np.ndarray
    watts: np.ndarray
    truth_w: float
    first_distance: float
    evaluate: bool = True
    label: str = ""
    truth_se_w: float = 0.0
    truth_n: int = 0
    note: str = ""


# ------------------------------------------------------------------------------ synthetic data
def _check_bout_s(bout_s: float | None) -> None:
    if bout_s is not None and (isinstance(bout_s, bool) or not isinstance(bout_s, int | float)
                               or not (math.isfinite(bout_s) and bout_s > 0.0)):
        raise ConfigError(f"bout_s={bout_s!r}; expected a finite duration > 0 s")


def _duration(rng: np.random.Generator, bout_s: float | None) -> float:
    """A bout's length: ``bout_s``, else 45–120 s (an early stop) or 200–300 s, half each."""
    if bout_s is not None:
        return float(bout_s)
    return float(rng.uniform(45.0, 120.0) if rng.random() < 0.5 else rng.uniform(200.0, 300.0))


def synthetic_people(n: int, seed: int, *, bouts: int = 5, bout_s: float | None = None,
                     step_scale: float = 1.0) -> list[list[Bout]]:
    """Synthetic breath trajectories: ``n`` people, each walking ``bouts`` settings in a row.

    Per person: τ ~ U(30, 60) s and a steady-state breath CV ~ U(8, 12) % (facts of
    real data: τ 30–60 s between people, median CV ≈ 11 %), a starting level ~ U(250, 450) W.
    Per setting: the steady state c is the body's level at the setting's start divided by
    (1 + d), d ~ step_scale·U(−0.7, 0.8) (steps up to ±80 % of the distance from the new steady
    state at the default ``step_scale`` 1; c clipped to 120–1200 W); the body follows
    m(t) = c + (b0 − c)·e^{−t/τ} from the level b0 the previous setting left it at. Durations
    are 45–120 s (half the settings: early stops) or 200–300 s, or all ``bout_s`` when it is
    given. Breaths every U(2, 3.5) s; y = m·(1 + cv·ε) with ε an AR(1) of correlation
    e^{−Δt/1.5 s} (≤ 0.14 beyond 3 s: real breaths' is below 0.15 beyond 3 s), and 3 % outliers
    (swallows, coughs, talking) with an extra Student-t(2) error of scale 3·cv.

    ``step_scale`` < 1 makes the steps smaller and the pairs of ``hilbo bench pairs`` harder to
    rank. At 0.3 the seed UKF ranks 10.6–13.9 % of truly better candidates above their
    incumbent after 45 breaths (seeds 1–3, 40 people), near the 10.3 % measured on the real
    within-person pairs (docs/results.md).

    Pure: the same (n, seed, bouts, bout_s, step_scale) give the same data.

    Raises:
        ConfigError: ``bout_s`` not a duration > 0, or ``step_scale`` not a finite number >= 0.
    """
    _check_bout_s(bout_s)
    if isinstance(step_scale, bool) or not isinstance(step_scale, int | float) \
            or not (math.isfinite(step_scale) and step_scale >= 0.0):
        raise ConfigError(f"step_scale={step_scale!r}; expected a finite number >= 0")
    rng = np.random.default_rng([int(seed), 0xE57])
    people: list[list[Bout]] = []
    for _ in range(n):
        tau = rng.uniform(30.0, 60.0)
        cv = rng.uniform(0.08, 0.12)
        level = rng.uniform(250.0, 450.0)
        person: list[Bout] = []
        for k in range(bouts):
            d = step_scale * rng.uniform(-0.7, 0.8)
            c = float(np.clip(level / (1.0 + d), 120.0, 1200.0))
            dur = _duration(rng, bout_s)
            ts: list[float] = []
            t = rng.uniform(0.5, 3.5)
            while t <= dur:
                ts.append(t)
                t += rng.uniform(2.0, 3.5)
            t_arr = np.array(ts)
            m = c + (level - c) * np.exp(-t_arr / tau)
            eps = np.empty(t_arr.size)
            e = rng.normal()
            for i in range(t_arr.size):
                if i:
                    rho = math.exp(-(t_arr[i] - t_arr[i - 1]) / 1.5)
                    e = rho * e + math.sqrt(1.0 - rho**2) * rng.normal()
                eps[i] = e
            y = m * (1.0 + cv * eps)
            out = rng.random(t_arr.size) < 0.03
            y[out] += m[out] * 3.0 * cv * rng.standard_t(2.0, int(out.sum()))
            y = np.maximum(y, 0.05 * m)
            person.append(Bout(t_arr, y, c, abs(float(m[0]) - c) / c, evaluate=k > 0))
            level = float(c + (level - c) * math.exp(-dur / tau))
        people.append(person)
    return people


def realistic_people(n: int, seed: int, *, bouts: int = 6, bout_s: float | None = None,
                     rest_every: int = 0) -> list[list[Bout]]:
    """The realistic simulated wearer (bridge.sim.devices) walked through settings.

    Person k is the wearer of seed ``1000·seed + k`` in the ``hip_6d`` space; each of ``bouts``
    bouts applies a random feasible setting at the breath clock's current time and lasts as the
    synthetic bouts do (45–120 s or 200–300 s), so its transition starts wherever the previous
    one left the body; ``bout_s`` makes every bout last that long instead (``hilbo bench pairs``
    needs full-length evaluations). The truth of a bout is the setting's steady-state cost at the
    bout's end (the wearer adapts, 0–3 % over the hour), not the breaths' level: the wearer's
    steady state drifts (1.5–3.5 % SD), an error every estimate has, as on people; the first bout
    only starts the chained estimator.
    Steps between hip settings are small (5–25 % of the cost at most), unlike the walking /
    running transitions of the real recordings. ``rest_every`` K > 0 adds them: the person
    stands (:meth:`~virtual_hw.wearer_realistic.RealisticWearer.stand`, ≈ 3-4× below walking)
    for one bout before the first setting and after every K settings, so each rest is a large
    step down and the setting after it a large step up, both scored (the first rest only starts
    the chained estimator); its truth is the standing cost at the bout's end.

    Pure given (n, seed, bouts, bout_s, rest_every): the same people every time; with
    ``rest_every`` 0 the settings and breaths are those of earlier versions.
    """
    _check_bout_s(bout_s)
    if isinstance(rest_every, bool) or not isinstance(rest_every, int) or rest_every < 0:
        raise ConfigError(f"rest_every={rest_every!r}; expected an integer >= 0 (0: no rests)")
    space = hip_6d()
    rng = np.random.default_rng([int(seed), 0x5EA])
    people: list[list[Bout]] = []
    for k in range(n):
        wearer = make_wearer(WearerKind.REALISTIC, space, seed=1000 * int(seed) + k)
        person: list[Bout] = []
        plan: list[int | None] = []  # None: a standing bout
        for b in range(bouts):
            if rest_every and b % rest_every == 0:
                plan.append(None)
            plan.append(b)
        for b in plan:
            t0 = wearer.t_s
            if b is None:
                params = None
                wearer.stand(t0)
            else:
                params = space.to_dict(space.from_unit(space.sample_unit(1, rng))[0])
                wearer.apply_params(params, t0)
            dur = _duration(rng, bout_s)
            first_level = wearer.metabolic_rate_w(t0)
            ts: list[float] = []
            ys: list[float] = []
            while True:
                rec = wearer.next_breath()  # the one past the end is lost to the next setting
                if rec.t_s - t0 > dur:
                    break
                ts.append(rec.t_s - t0)
                ys.append(brockway_watts(rec.vo2_ml_min, rec.vco2_ml_min))
            if params is None:
                truth = wearer.standing_cost_w * wearer.adaptation_factor(t0 + dur)
            else:
                truth = wearer.true_cost_w(params, t0 + dur)
            person.append(Bout(np.array(ts), np.array(ys), truth, abs(first_level - truth) / truth,
                               evaluate=bool(person), label="standing" if params is None else ""))
        people.append(person)
    return people


WEARERS: dict[str, Callable[..., list[list[Bout]]]] = {
    "synthetic": synthetic_people, "realistic": realistic_people}
"""Wearers ``--wearer`` can name: ``name -> (n, seed, *, bouts, bout_s) -> people``."""


# ------------------------------------------------------------------------------ replay
def replay_people(path: str | Path, transitions_s: Sequence[float],
                  csv_columns: Sequence[str] | None = None, *, labels: Sequence[str] | None = None,
                  score: Sequence[str] | None = None) -> list[list[Bout]]:
    """The transitions of a recorded breath file, as one "person".

    The bouts are [t_k, t_{k+1}) (the last to the end of the file). The truth of a bout is the
    mean of its breaths from max(180 s, its end − 180 s) to its end: at most its last 3 minutes
    and none of the breaths any horizon sees (so truth and estimate share no breath), with that
    mean's standard error SD/√n (:attr:`Bout.truth_se_w`). Scored: every bout after the first
    whose truth window spans at least 60 s (a short rest or warm-up has no steady state to
    score), or, with ``score``, the bouts whose label is in it (each must have such a window).
    Breaths before t1 and unscored bouts only move the chained estimator on.

    Args:
        path: A hilbo-line recording or a vendor export (detected as ``hilbo cart inspect``
            does), or a CSV when ``csv_columns`` is given.
        transitions_s: Setting-change times on the file's clock (s), increasing.
        csv_columns: Header names of time (s), VO2 and VCO2 (ml/min) for a CSV.
        labels: One name per transition (the bout it starts), or None.
        score: Labels of the bouts to score (needs ``labels``), or None for the default rule.

    Returns:
        ``[[bout before t1 (not scored), bout t1..t2, ...]]`` (an empty first bout left out).

    Raises:
        ConfigError: Unreadable file, bad transition times or labels, a bout without breaths,
            or a bout named by ``score`` without a truth window.
    """
    from drivers.cart.csvmap import CsvMapping
    from drivers.cart.inspect import inspect_file
    from drivers.errors import DriverError

    ts = [float(t) for t in transitions_s]
    if not ts or any(not math.isfinite(t) for t in ts) or any(b <= a for a, b in itertools.pairwise(ts)):
        raise ConfigError(f"--transitions {ts}: expected increasing finite times in s")
    if csv_columns is not None and len(csv_columns) != 3:
        raise ConfigError(f"--csv-columns {list(csv_columns)}: expected TIME,VO2,VCO2")
    if labels is not None and len(labels) != len(ts):
        raise ConfigError(f"{len(labels)} labels for {len(ts)} transitions: expected one label per "
                          "transition")
    if score is not None:
        if labels is None:
            raise ConfigError("--score names bouts by label: give the labels (--events FILE)")
        unknown = sorted(set(score) - set(labels))
        if unknown:
            raise ConfigError(f"--score {','.join(score)}: no bout is labelled {unknown} "
                              f"(labels: {sorted(set(labels))})")
    try:
        # As a session reads it (``hilbo cart inspect``): the format detected (hilbo-line or a
        # vendor export), the breaths validated; a CSV by its column map.
        if csv_columns is not None:
            report = inspect_file(path, "csv", csv=CsvMapping(*csv_columns))
        else:
            report = inspect_file(path)
    except OSError as err:
        raise ConfigError(f"--replay {path}: cannot read breaths: {err}") from err
    except DriverError as err:
        # The driver's message speaks of the session's [cart.csv] map; here it is an option.
        hint = "" if csv_columns is not None else " (here: --csv-columns TIME,VO2,VCO2 is the column map)"
        raise ConfigError(f"--replay {path}: cannot read breaths: {err}{hint}") from err
    records = report.records
    if not records:
        raise ConfigError(f"--replay {path}: no breaths accepted ({report.n_rejected} rejected; "
                          "`hilbo cart inspect FILE` says why)")
    t_all = np.array([r.t_s for r in records], dtype=float)
    w_all = np.array([r.watts for r in records], dtype=float)
    edges = [-math.inf, *ts, math.inf]
    names = ["", *(labels if labels is not None else [""] * len(ts))]
    person: list[Bout] = []
    for k in range(len(edges) - 1):
        sel = (t_all >= edges[k]) & (t_all < edges[k + 1])
        if not sel.any():
            if k == 0:
                continue
            end = f"{edges[k + 1]:g} s" if math.isfinite(edges[k + 1]) else "the end of the file"
            raise ConfigError(f"--replay {path}: no breaths between {edges[k]:g} s and {end} (its breaths "
                              f"run from {t_all[0]:g} to {t_all[-1]:g} s)")
        # Time since the setting began; the warm-up bout before t1 starts at its first breath.
        t0 = edges[k] if k else float(t_all[sel][0])
        t, w = t_all[sel] - t0, w_all[sel]
        lo = max(HORIZONS_S[-1], float(t[-1]) - _TRUTH_WINDOW_S)
        tail = t > lo
        span = float(t[-1]) - lo
        if tail.sum() >= 2:
            truth = float(np.mean(w[tail]))
            se = float(np.std(w[tail], ddof=1)) / math.sqrt(int(tail.sum()))
        else:
            truth, se = float(np.mean(w[-3:])), math.nan
        has_truth = span >= _TRUTH_MIN_SPAN_S and tail.sum() >= 2
        first = not person
        if first:
            note = "first bout: starts the chained estimator"
        elif score is not None and names[k] not in score:
            note = f"label {names[k]!r} not in --score"
        elif not has_truth:
            if score is not None:
                raise ConfigError(f"--score {','.join(score)}: bout {names[k]!r} at {edges[k]:g} s lasts "
                                  f"{t[-1]:.0f} s, too short for a truth after {HORIZONS_S[-1]:g} s")
            note = (f"{t[-1]:.0f} s long: no truth window of {_TRUTH_MIN_SPAN_S:g} s after "
                    f"{HORIZONS_S[-1]:g} s")
        else:
            note = ""
        person.append(Bout(t, w, truth, abs(float(w[0]) - truth) / truth, evaluate=not note,
                           label=names[k], truth_se_w=se, truth_n=int(tail.sum()), note=note))
    return [person]


def read_events(path: str | Path) -> tuple[list[float], list[str]]:
    """``--events FILE``: a CSV with columns ``t_s`` and ``label``, one row per change.

    Returns:
        (times in s, labels), in the file's order.

    Raises:
        ConfigError: Unreadable file, missing columns or a time that is not a number.
    """
    import csv

    try:
        with open(path, newline="", encoding="utf-8") as fh:
            rows = list(csv.DictReader(fh))
    except OSError as err:
        raise ConfigError(f"--events {path}: cannot read: {err}") from err
    if not rows or not {"t_s", "label"} <= set(rows[0]):
        raise ConfigError(f"--events {path}: expected a CSV with columns t_s,label")
    try:
        return [float(r["t_s"]) for r in rows], [str(r["label"]) for r in rows]
    except (TypeError, ValueError) as err:
        raise ConfigError(f"--events {path}: a t_s that is not a number: {err}") from err


def bout_table(people: Sequence[list[Bout]], config: TransitionConfig | None = None,
               ) -> tuple[list[dict[str, Any]], str]:
    """Which bouts are scored and their truth: (JSON rows, Markdown table).

    Also the transition estimator's (``config``) breaths flagged as implausible for the level at
    each bout's end.
    """
    rows: list[dict[str, Any]] = []
    for i, person in enumerate(people):
        for k, (bout, est) in enumerate(chained_estimators(person, config)):
            for t, w in zip(bout.t_s, bout.watts, strict=True):
                try:
                    est.update(float(t), float(w))
                except (MeasurementError, EstimatorError):
                    continue
            rows.append({"person": i, "bout": k, "label": bout.label, "length_s": float(bout.t_s[-1]),
                         "breaths": int(bout.t_s.size), "scored": bout.evaluate, "note": bout.note,
                         "truth_w": bout.truth_w, "truth_se_w": bout.truth_se_w, "truth_n": bout.truth_n,
                         "flagged": est.n_flagged})

    def se(r: dict[str, Any]) -> str:
        v = r["truth_se_w"]
        return "–" if not math.isfinite(v) else f"{v:.1f} ({100.0 * v / r['truth_w']:.1f} %)"

    table = markdown_table(
        ["person", "bout", "label", "length s", "breaths", "scored", "truth W", "truth SE W (%)",
         "truth breaths", "flagged"],
        [[r["person"], r["bout"], r["label"] or "–", f"{r['length_s']:.0f}", r["breaths"],
          "yes" if r["scored"] else f"no: {r['note']}", f"{r['truth_w']:.1f}", se(r), r["truth_n"],
          r["flagged"]] for r in rows])
    return rows, table


# ------------------------------------------------------------------------------ estimators
def _ls_first_order(t: np.ndarray, y: np.ndarray) -> tuple[float, float]:
    """Least squares of y = c + (y0 − c)·e^{−t/42} in (c, y0); (c, sd) (sd NaN with n < 3)."""
    e = np.exp(-t / _LAB_TAU_S)
    H = np.column_stack([1.0 - e, e])
    theta, *_ = np.linalg.lstsq(H, y, rcond=None)
    n = y.size
    if n < 3:
        return float(theta[0]), math.nan
    rss = float(np.sum((y - H @ theta) ** 2))
    try:
        cov = rss / (n - 2) * np.linalg.inv(H.T @ H)
    except np.linalg.LinAlgError:
        return float(theta[0]), math.nan
    return float(theta[0]), math.sqrt(max(float(cov[0, 0]), 0.0))


def _ls_full(t: np.ndarray, y: np.ndarray) -> tuple[float, float]:
    """Least squares of the full model in (c, b0, τ), τ profiled on a grid; (c, sd)."""
    E = np.exp(-t[None, :] / _FULL_TAU_GRID_S[:, None])  # (G, n)
    best = (math.inf, 0, np.zeros(2))
    for g in range(_FULL_TAU_GRID_S.size):
        H = np.column_stack([1.0 - E[g], E[g]])
        theta, *_ = np.linalg.lstsq(H, y, rcond=None)
        rss = float(np.sum((y - H @ theta) ** 2))
        if rss < best[0]:
            best = (rss, g, theta)
    rss, g, (c, b0) = best
    n = y.size
    if n < 4:
        return float(c), math.nan
    tau = _FULL_TAU_GRID_S[g]
    e = E[g]
    J = np.column_stack([1.0 - e, e, (b0 - c) * e * t / tau**2])
    try:
        cov = rss / (n - 3) * np.linalg.pinv(J.T @ J)
    except np.linalg.LinAlgError:
        return float(c), math.nan
    return float(c), math.sqrt(max(float(cov[0, 0]), 0.0))


def chained_estimators(person: Sequence[Bout], config: TransitionConfig | None = None,
                       ) -> Iterator[tuple[Bout, TransitionEstimator]]:
    """For each non-empty bout of a person, a :class:`TransitionEstimator` (``config``, the
    default when None) started where the previous bout left the body, as the optimizer chains
    them; the caller feeds it the bout's breaths before asking for the next one. Every bout
    (scored or not) moves the chain on."""
    handover: StartState | None = None
    for bout in person:
        if bout.t_s.size == 0:
            continue
        est = TransitionEstimator(config)
        if handover is not None:
            est.start_from_state(handover)
        yield bout, est
        if est.n_updates:
            handover = est.handover()


def parse_transition_config(text: str | None) -> TransitionConfig | None:
    """``--transition-config KEY=VALUE,...``: a :class:`TransitionConfig` (None for none given).

    Values are numbers (``delays_s`` takes ``0;10;20``: delays separated by semicolons).

    Raises:
        ConfigError: Not KEY=VALUE pairs, an unknown field, or a value the config refuses.
    """
    if text is None or not text.strip():
        return None
    types = {f.name: f.type for f in dataclasses.fields(TransitionConfig)}
    known = set(types)
    kwargs: dict[str, Any] = {}
    for item in (x.strip() for x in text.split(",") if x.strip()):
        key, sep, value = item.partition("=")
        key = key.strip()
        if not sep or key not in known:
            raise ConfigError(f"--transition-config {item!r}: expected KEY=VALUE with KEY one of "
                              f"{sorted(known)}")
        try:
            if key == "delays_s":
                kwargs[key] = tuple(float(v) for v in value.split(";") if v.strip())
            else:
                num = float(value)
                kwargs[key] = int(num) if num.is_integer() and types[key] in ("int", int) else num
        except ValueError as err:
            raise ConfigError(f"--transition-config {item!r}: {value!r} is not a number") from err
    return TransitionConfig(**kwargs)


def parse_transitions(text: str) -> list[float]:
    """``--transitions t1,t2,...`` as seconds.

    Raises:
        ConfigError: A value that is not a number.
    """
    try:
        return [float(x) for x in text.split(",") if x.strip()]
    except ValueError as err:
        raise ConfigError(f"--transitions {text!r}: expected comma-separated seconds") from err


def _at_horizons(est: Any, bout: Bout, horizons: Sequence[float]) -> list[tuple[float, float]]:
    """Run a sequential estimator over the bout; (mean, sd) at the last breath <= each horizon."""
    out = [(math.nan, math.nan)] * len(horizons)
    mean = var = math.nan
    hi = 0
    for t, w in zip(bout.t_s, bout.watts, strict=True):
        while hi < len(horizons) and t > horizons[hi]:
            out[hi] = (mean, math.sqrt(var) if var > 0 else math.nan)
            hi += 1
        try:
            mean, var = est.update(float(t), float(w))
        except (MeasurementError, EstimatorError):
            continue  # counted as in the optimizer: a rejected breath leaves the estimate
    while hi < len(horizons):
        if bout.t_s[-1] >= horizons[hi]:
            out[hi] = (mean, math.sqrt(var) if var > 0 else math.nan)
        hi += 1
    return out


def evaluate(people: Iterable[list[Bout]], estimators: Sequence[str] = ESTIMATORS,
             horizons: Sequence[float] = HORIZONS_S,
             progress: Callable[[int], None] | None = None,
             config: TransitionConfig | None = None) -> list[dict[str, Any]]:
    """One row per scored transition, estimator and reached horizon.

    Row: ``estimator``, ``horizon_s``, ``step`` ("small"/"large"), ``truth``, ``mean``, ``sd``.
    A horizon counts only when the bout lasts at least that long. ``config`` configures the
    ``transition`` estimator (None: its defaults).
    """
    rows: list[dict[str, Any]] = []
    for i, person in enumerate(people):
        for bout, est in chained_estimators(person, config):
            trans = _at_horizons(est, bout, horizons)
            if not bout.evaluate:
                continue
            step = "large" if bout.first_distance >= _LARGE_STEP else "small"
            for name in estimators:
                if name == "transition":
                    res = trans
                elif name == "seed_ukf":
                    res = _at_horizons(MetabolicUKF(), bout, horizons)
                else:
                    fit = _ls_first_order if name == "first_order_42" else _ls_full
                    res = []
                    for h in horizons:
                        sel = bout.t_s <= h
                        if bout.t_s[-1] < h or sel.sum() < 2:
                            res.append((math.nan, math.nan))
                        else:
                            res.append(fit(bout.t_s[sel], bout.watts[sel]))
                for h, (mean, sd) in zip(horizons, res, strict=True):
                    if math.isfinite(mean):
                        rows.append({"estimator": name, "horizon_s": h, "step": step,
                                     "truth": bout.truth_w, "mean": mean, "sd": sd})
        if progress is not None:
            progress(i + 1)
    return rows


def summarize(rows: Sequence[dict[str, Any]], estimators: Sequence[str] = ESTIMATORS,
              horizons: Sequence[float] = HORIZONS_S,
              pooled: tuple[float, float] | None = None) -> list[dict[str, Any]]:
    """Per estimator × horizon × step (all/small/large): n, MAPE %, bias %, z mean/SD, coverage %.

    With ``pooled = (lo, hi)`` also one entry per estimator × step for every row with a horizon
    in [lo, hi] together (``horizon_s`` the string "lo-hi"): on a single recording a horizon has
    a handful of transitions, too few for a coverage in percent to mean much on its own.
    """
    groups: list[tuple[str, Any, Callable[[float], bool]]] = [
        (name, h, lambda x, h=h: x == h) for name in estimators for h in horizons]
    if pooled is not None:
        lo, hi = pooled
        groups += [(name, f"{lo:g}-{hi:g}", lambda x: lo <= x <= hi) for name in estimators]
    out = []
    for name, label, in_group in groups:
        for step in ("all", "small", "large"):
            sel = [r for r in rows if r["estimator"] == name and in_group(r["horizon_s"])
                   and (step == "all" or r["step"] == step)]
            if not sel:
                continue
            truth = np.array([r["truth"] for r in sel])
            mean = np.array([r["mean"] for r in sel])
            sd = np.array([r["sd"] for r in sel], dtype=float)
            rel = (mean - truth) / truth
            ok = np.isfinite(sd) & (sd > 0)
            z = (mean[ok] - truth[ok]) / sd[ok]
            out.append({
                "estimator": name, "horizon_s": label, "step": step, "n": len(sel),
                "mape_pct": 100.0 * float(np.mean(np.abs(rel))),
                "bias_pct": 100.0 * float(np.mean(rel)),
                "z_mean": float(np.mean(z)) if z.size else math.nan,
                "z_sd": float(np.std(z, ddof=1)) if z.size > 1 else math.nan,
                "coverage95_pct": 100.0 * float(np.mean(np.abs(z) <= _Z95)) if z.size else math.nan,
            })
    return out


def _horizon(h: float | str) -> str:
    return h if isinstance(h, str) else f"{h:g}"


def estimator_table(summary: Sequence[dict[str, Any]],
                    steps: Sequence[str] = ("all", "small", "large")) -> str:
    """Markdown: one row per estimator × horizon × step."""
    def f(v: float, fmt: str) -> str:
        return "–" if not math.isfinite(v) else format(v, fmt)

    rows = [[s["estimator"], f"{_horizon(s['horizon_s'])} s", s["step"], s["n"], f(s["mape_pct"], ".1f"),
             f(s["bias_pct"], "+.1f"), f(s["z_mean"], "+.2f"), f(s["z_sd"], ".2f"),
             f(s["coverage95_pct"], ".1f")]
            for s in summary if s["step"] in steps]
    return markdown_table(["estimator", "horizon", "step", "n", "MAPE %", "bias %", "z mean", "z SD",
                           "95 % cov. %"], rows)


def comparison_table(summary: Sequence[dict[str, Any]]) -> str:
    """Markdown: the default estimator's accuracy and calibration, with every estimator's MAPE.

    Needs ``transition`` in the summary; the other MAPE columns show "–" when not run.
    """
    by = {(s["estimator"], s["horizon_s"], s["step"]): s for s in summary}
    others = [e for e in ESTIMATORS if e != "transition"]
    rows = []
    for h in [*HORIZONS_S, f"{_POOLED[0]:g}-{_POOLED[1]:g}"]:
        for step in ("all", "small", "large"):
            t = by.get(("transition", h, step))
            if t is None:
                continue
            mape = [f"{by[(e, h, step)]['mape_pct']:.1f}" if (e, h, step) in by else "–" for e in others]
            rows.append([f"{_horizon(h)} s", step, t["n"], f"{t['mape_pct']:.1f}", *mape,
                         f"{t['bias_pct']:+.1f}", f"{t['z_mean']:+.2f}", f"{t['z_sd']:.2f}",
                         f"{t['coverage95_pct']:.1f}"])
    return markdown_table(["horizon", "step", "n", "MAPE % transition", *(f"MAPE % {e}" for e in others),
                           "bias %", "z mean", "z SD", "95 % cov. %"], rows)


# ------------------------------------------------------------------------------ command
def run_estimator_bench(people: Sequence[list[Bout]], estimators: Sequence[str] = ESTIMATORS,
                        progress: Callable[[int], None] | None = None,
                        config: TransitionConfig | None = None) -> dict[str, Any]:
    """Evaluate and summarise; the JSON document without command and machine.

    ``config`` configures the ``transition`` estimator (None: its defaults).
    """
    t0 = time.perf_counter()
    rows = evaluate(people, estimators, HORIZONS_S, progress, config)
    summary = summarize(rows, estimators, HORIZONS_S, pooled=_POOLED)
    return {"benchmark": "estimator", "transitions": sum(b.evaluate for p in people for b in p),
            "horizons_s": list(HORIZONS_S), "estimators": list(estimators), "summary": summary,
            "wall_s": time.perf_counter() - t0}


def _cmd_estimator(args: argparse.Namespace) -> int:
    from rich.console import Console

    from bridge.bench.common import choices, options

    console = Console(markup=False, highlight=False, soft_wrap=True)
    with options():  # the command line's values (exit status 2); the replay file's are 1
        estimators = choices(args.estimators, ESTIMATORS, "estimator", list(ESTIMATORS))
        if args.replay is not None and (args.transitions is None) == (args.events is None):
            raise ConfigError("--replay needs --transitions t1,t2,... or --events FILE (s on the file's "
                              "clock), one of them")
        if args.replay is None and any(v is not None for v in (args.transitions, args.csv_columns,
                                                                args.events, args.score)):
            raise ConfigError("--transitions, --events, --score and --csv-columns go with --replay")
        if args.score is not None and args.events is None:
            raise ConfigError("--score names bouts by label: it needs --events FILE")
        if args.replay is None and args.bout_s is not None and not (
                math.isfinite(args.bout_s) and args.bout_s > 0.0):
            raise ConfigError(f"--bout-s {args.bout_s}; expected a duration > 0 s")
        if args.replay is None and args.wearer not in WEARERS:
            raise ConfigError(f"--wearer {args.wearer!r}; expected one of {sorted(WEARERS)}")
        if args.replay is None and args.n < 1:
            raise ConfigError(f"--n {args.n}; expected an integer >= 1")
        if args.replay is None and args.seed < 0:
            raise ConfigError(f"--seed {args.seed}; expected an integer >= 0")
        if args.rest_every is not None and (args.replay is not None or args.wearer != "realistic"):
            raise ConfigError("--rest-every goes with --wearer realistic (the other data have their "
                              "own large steps)")
        if args.rest_every is not None and args.rest_every < 0:
            raise ConfigError(f"--rest-every {args.rest_every}; expected an integer >= 0 (0: no rests)")
        rest_every = _REST_EVERY if args.rest_every is None else args.rest_every
        if args.transitions is not None:
            trans = parse_transitions(args.transitions)
        score = [x for x in args.score.split(",") if x] if args.score is not None else None
        config = parse_transition_config(args.transition_config)
    if args.replay is not None:
        cols = args.csv_columns.split(",") if args.csv_columns else None
        labels = None
        if args.events is not None:
            trans, labels = read_events(args.events)
        people = replay_people(args.replay, trans, cols, labels=labels, score=score)
        source = f"--replay {args.replay} " + (
            f"--events {args.events}" if args.events is not None else f"--transitions {args.transitions}") + (
            f" --score {args.score}" if args.score is not None else "") + (
            f" --csv-columns {args.csv_columns}" if args.csv_columns else "")
    else:
        rests = {"rest_every": rest_every} if args.wearer == "realistic" else {}
        people = WEARERS[args.wearer](args.n, args.seed, bout_s=args.bout_s, **rests)
        source = f"--wearer {args.wearer} --n {args.n} --seed {args.seed}" + (
            f" --bout-s {args.bout_s:g}" if args.bout_s is not None else "") + (
            f" --rest-every {rest_every}" if rests else "")
    n_people = len(people)
    step = max(1, n_people // 10)

    def progress(i: int) -> None:
        if not args.no_progress and (i % step == 0 or i == n_people) and n_people > 1:
            console.print(f"  {i}/{n_people} people", style="dim")

    console.print(f"hilbo bench estimator: {sum(b.evaluate for p in people for b in p)} transitions, "
                  f"estimators {','.join(estimators)}")
    doc = run_estimator_bench(people, estimators, progress, config)
    tc = f" --transition-config {args.transition_config}" if args.transition_config else ""
    doc["command"] = (f"hilbo bench estimator {source} --estimators {','.join(estimators)}{tc} "
                      f"--out {args.out}")
    doc["machine"] = machine_info()
    out = Path(args.out)
    if args.replay is not None:
        # Which bouts are scored, and the truth of each with its own uncertainty.
        doc["bouts"], bouts_md = bout_table(people, config)
        out.mkdir(parents=True, exist_ok=True)
        (out / "estimator_bouts.md").write_text(bouts_md)
        console.print(bouts_md)
    write_json(out / "estimator.json", round_sig(doc))
    table = estimator_table(doc["summary"])
    (out / "estimator_table.md").write_text(table)
    console.print(table)
    if "transition" in estimators:
        compare = comparison_table(doc["summary"])
        (out / "estimator_compare.md").write_text(compare)
        console.print(compare)
    console.print(str(out / "estimator.json"))
    return 0


def add_estimator_bench_parser(bench_subparsers: Any) -> argparse.ArgumentParser:
    """Add ``estimator`` to the ``hilbo bench`` subcommands; returns its parser."""
    p = bench_subparsers.add_parser(
        "estimator", help="accuracy and calibration of the breath-by-breath estimators",
        description="MAPE, bias, z-score mean/SD and 95 % coverage of the steady-state estimate at "
                    "30/60/90/120/180 s after a setting change, split by step size, for the default "
                    "estimator, the seed UKF, the first-order tau = 42 s fit and a full-model least-"
                    "squares fit; on synthetic transitions or a recorded breath file (--replay).")
    p.add_argument("--n", type=positive_int, default=100,
                   help="synthetic people (100); 4 scored transitions each, more with the realistic "
                        "wearer's rests")
    p.add_argument("--seed", type=nonnegative_int, default=0, help="seed of the synthetic data (0)")
    p.add_argument("--wearer", default="synthetic",
                   help=f"synthetic data source, from {','.join(sorted(WEARERS))} (synthetic)")
    p.add_argument("--replay", default=None, metavar="FILE",
                   help="a recorded breath file instead (hilbo-line or a vendor export, detected as "
                        "`hilbo cart inspect` does)")
    p.add_argument("--transitions", default=None, metavar="T1,T2,...",
                   help="with --replay: setting-change times in s on the file's clock")
    p.add_argument("--events", default=None, metavar="FILE",
                   help="with --replay, instead of --transitions: a CSV of the changes with columns "
                        "t_s,label (labels name the bouts they start)")
    p.add_argument("--score", default=None, metavar="LABELS",
                   help="with --events: score only the bouts with these labels (comma-separated); "
                        "default: every bout after the first with at least 60 s of breaths after "
                        "180 s (rests and warm-ups too short for a truth are skipped, and listed)")
    p.add_argument("--bout-s", type=float, default=None,
                   help="synthetic data: every bout this long in s (default: 45-120 s or 200-300 s, "
                        "half each; 300 scores every horizon)")
    p.add_argument("--rest-every", type=nonnegative_int, default=None, metavar="K",
                   help=f"--wearer realistic: the person stands for one bout before the first "
                        f"setting and after every K settings, large steps down and up that "
                        f"assistance changes never make (default {_REST_EVERY}; 0: no rests, "
                        f"small steps only)")
    p.add_argument("--csv-columns", default=None, metavar="TIME,VO2,VCO2",
                   help="with --replay: the file is a CSV with these header names (s, ml/min)")
    p.add_argument("--estimators", default=None,
                   help=f"comma-separated, from {','.join(ESTIMATORS)} (default all)")
    p.add_argument("--transition-config", default=None, metavar="KEY=VALUE,...",
                   help="settings of the transition estimator, fields of TransitionConfig (e.g. "
                        "timing_sd_s=0,transition_error_rel=0.25 for the fit without its timing "
                        "term; default: its defaults)")
    p.add_argument("--out", default="runs/bench/estimator", help="output directory")
    p.add_argument("--no-progress", action="store_true", help="no progress lines")
    p.set_defaults(func=_cmd_estimator)
    return p
