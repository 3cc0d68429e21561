"""``hilbo bench pairs``: the stopping rules on within-person pairs of transitions.

The project's targets are stop statistics on *real* breath data, measured on within-person pairs of
transitions: ≤ 10 % of truly better candidates rejected, ≥ 25 % fewer breaths than N = 45 per
evaluation, ≤ 5 % of evaluations ending within the first 30 s. This command measures them on a
lab's own recordings (``--replay FILE --transitions ...``, one person per file, the option pair
repeated per person) or on simulated people (``--wearer realistic``: the realistic wearer's hip
settings, whose costs differ by 5–25 %; ``--wearer synthetic``: the synthetic transitions of
``hilbo bench estimator``, steps up to ±80 %, closer to the walking/running transitions of real recordings).

For every person the chained :class:`~hilbo_core.estimation.TransitionEstimator` (the
optimizer's default; each setting starts from where the previous one left the body, as in a
session) runs over every bout. Every scored bout with at least N breaths is a *candidate*
against every other such bout of the same person as the *incumbent* (that bout's N-breath
estimate) whose true cost is 2-20 % away from the candidate's (``--diff-pct LOW,HIGH``, % of the
incumbent's; ``0,inf`` for every pair): the differences an assistance change makes. Pooling every
pair would mostly score easy ones (walk against run) and overstate what holds. "Truly better":
the candidate's truth below the incumbent's. A recording's truth is the mean of the bout's
breaths after 180 s (at most its last 3 minutes; :func:`bridge.bench.estimator.replay_people`),
so its bouts should last 4 minutes or more; a simulated wearer's is the setting's true cost.

Rules (replayed by :class:`bridge.bench.tune_sound.SoundReplay`, on Algorithm 2's W = 2 schedule
built from up to 6 *other* bouts of the same person, standing in for a session's exploration):

* ``sound`` — :class:`~hilbo_core.stopping.SoundRule` with the optimizer's defaults
  (``min_decision_s``, ``boundary_s``, ``a_floor``, ``accept_z``; ``--min-decision-s``,
  ``--boundary-s``, ``--a-floor`` and ``--accept-z`` change them);
* ``sound-floor`` — the same rule on the fixed clock (the earlier default: no decision before
  60 s, then ``a_floor`` and an accept stop at 3 σ, no sequential boundary);
* ``adaptive`` — Kim et al. 2019's rule (their Algorithm 1/2: the same schedule, no floors);
* ``fixed`` — N breaths every time. Its row also gives the share of truly better candidates
  whose N-breath estimate is above the incumbent's: the measurement's own error, which no rule
  that decides on these estimates can beat.

How hard the pairs are to rank (``measurement_error`` in ``pairs.json``, and a line of the
output): the share of truly better candidates still ranked above their incumbent after N
breaths, by the transition estimator and by a fresh seed UKF per setting, on the same pairs as
the rules (a figure from another set of pairs depends on how far apart their costs are, and is
not printed beside it).

What a replay leaves out (as :mod:`bridge.bench.tune_sound` says): in a session the candidate's
estimate is fused with the GP's predictive at x_t and the incumbent is the GP posterior at x\\*;
here both are the estimator's data-only estimates. ``hilbo bench hil`` measures whole sessions.
"""

from __future__ import annotations

import argparse
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from bridge.argtypes import nonnegative_int, positive_int
from bridge.bench.common import machine_info, markdown_table, round_sig, write_json
from bridge.bench.estimator import WEARERS, Bout, chained_estimators, parse_transitions, replay_people
from bridge.bench.traces import BreathTrace, exploration_groups, threshold_schedules
from bridge.bench.tune_sound import SoundReplay
from hilbo_core.errors import ConfigError, EstimatorError, MeasurementError
from hilbo_core.metabolic import MetabolicUKF
from hilbo_core.optimizer import FLOOR_ACCEPT_Z, FLOOR_MIN_DECISION_S, OptimizerConfig

__all__ = ["DEFAULT_DIFF_PCT", "GRID_A_FLOOR", "GRID_MIN_DECISION_S", "PairsConfig", "PersonTraces",
           "add_pairs_bench_parser", "measurement_error", "pair_mask", "pair_stats", "person_traces",
           "run_pairs_bench", "sound_grid"]

# The project's targets for the stop statistics on within-person pairs (docs/benchmarks.md).
TARGET_REJECTED_BETTER = 0.10
TARGET_BREATH_FRACTION = 0.75
TARGET_ENDED_30S = 0.05
# The pairs scored by default: true costs 2-20 % apart, the differences an assistance change
# makes (a candidate against its incumbent); larger ones (walk against run) are easy to rank.
DEFAULT_DIFF_PCT = (2.0, 20.0)
_DEFAULTS = OptimizerConfig()
# The sound rule's constants the trade-off grid covers (pairs.png, "grid" in pairs.json).
GRID_MIN_DECISION_S = (30.0, 45.0, 60.0, 90.0)
GRID_A_FLOOR = (0.5, 0.75, 1.0, 1.25, 1.5, 2.0)
_COUNTS = ("n_pairs", "breaths_total", "n_early", "n_ended_30s", "n_better", "n_rejected_better",
           "n_better_above_at_n")


@dataclass(frozen=True)
class PairsConfig:
    """Options of :func:`run_pairs_bench`.

    Attributes:
        n_max: N, breaths of a full evaluation.
        min_decision_s: The sound rule's time floor (s).
        boundary_s: The sound rule's sequential boundary reaches its late levels here (s), or
            None for the fixed clock.
        a_floor: The sound rule's threshold floor (σ).
        accept_z: The sound rule's accept-stop margin (σ), or None for none.
        window: Algorithm 2's window W.
        n_explore: Other bouts of the person behind each candidate's schedule.
        seed: Seeds the choice of those bouts.
        min_diff_pct: Pairs count when their true costs differ by at least this (% of the
            incumbent's)...
        max_diff_pct: ...and at most this (``inf``: no upper bound).
    """

    n_max: int = _DEFAULTS.max_breaths
    min_decision_s: float = float(_DEFAULTS.min_decision_s or 0.0)
    boundary_s: float | None = _DEFAULTS.boundary_s
    a_floor: float = _DEFAULTS.a_floor
    accept_z: float | None = _DEFAULTS.accept_z
    window: int = 2
    n_explore: int = 6
    seed: int = 0
    min_diff_pct: float = DEFAULT_DIFF_PCT[0]
    max_diff_pct: float = DEFAULT_DIFF_PCT[1]

    def __post_init__(self) -> None:
        lo, hi = self.min_diff_pct, self.max_diff_pct
        if any(isinstance(v, bool) or not isinstance(v, int | float) or math.isnan(v) for v in (lo, hi)) \
                or not (math.isfinite(lo) and 0.0 <= lo < hi):
            raise ConfigError(f"true-difference range {lo!r}-{hi!r} %; expected 0 <= low < high (high may "
                              "be inf)")
        if isinstance(self.n_max, bool) or not isinstance(self.n_max, int) or self.n_max < 2:
            raise ConfigError(f"n_max={self.n_max!r}; expected an integer >= 2 breaths")
        for name in ("min_decision_s", "a_floor", "accept_z"):
            v = getattr(self, name)
            if v is None and name == "accept_z":
                continue
            if isinstance(v, bool) or not isinstance(v, int | float) or not (math.isfinite(v) and v >= 0):
                raise ConfigError(f"{name}={v!r}; expected a finite number >= 0")
        b = self.boundary_s
        if b is not None and (isinstance(b, bool) or not isinstance(b, int | float)
                              or not (math.isfinite(b) and b > 0)):
            raise ConfigError(f"boundary_s={b!r}; expected a finite number of seconds > 0 or None")
        for name in ("window", "n_explore"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < (0 if name == "window" else 1):
                raise ConfigError(f"{name}={v!r}; expected an integer >= {0 if name == 'window' else 1}")


@dataclass(frozen=True)
class PersonTraces:
    """One person's full-length evaluations, ready to pair.

    Attributes:
        traces: The chained estimator's running estimate over each bout's first N breaths.
        times: Per trace, the breath times since the setting began (s), shape (N,).
        truth_w: Per trace, the bout's truth (W).
        short: Scored bouts left out for having fewer than N breaths.
        seed_ukf_w: Per trace, the seed UKF's estimate after the bout's first N breaths (W; a
            fresh filter per bout, as Kim et al. 2019 §II.C runs it), for :func:`measurement_error`.
    """

    traces: list[BreathTrace]
    times: list[np.ndarray]
    truth_w: list[float]
    short: int
    seed_ukf_w: list[float] = field(default_factory=list)


def person_traces(person: Sequence[Bout], n_max: int) -> PersonTraces:
    """Run the chained estimator over a person's bouts; keep the scored ones with N breaths.

    Every bout (scored or not, long or short) moves the chained estimator on, as every setting
    a person walked moves the body; a breath the estimator rejects leaves the estimate as in the
    optimizer. Each kept bout is also run through a fresh seed UKF (``seed_ukf_w``).
    """
    traces: list[BreathTrace] = []
    times: list[np.ndarray] = []
    truth: list[float] = []
    ukf: list[float] = []
    short = 0
    for k, (bout, est) in enumerate(chained_estimators(person)):
        means, variances = [], []
        mean = var = math.nan
        for t, w in zip(bout.t_s, bout.watts, strict=True):
            try:
                mean, var = est.update(float(t), float(w))
            except (MeasurementError, EstimatorError):
                pass  # the previous estimate stands
            means.append(mean)
            variances.append(var)
        if not bout.evaluate:
            continue
        if bout.t_s.size < n_max or not np.all(np.isfinite(means[:n_max])):
            short += 1
            continue
        traces.append(BreathTrace(np.array(means[:n_max]), np.array(variances[:n_max]), f"bout {k}"))
        times.append(np.asarray(bout.t_s[:n_max], dtype=float))
        truth.append(float(bout.truth_w))
        ukf.append(_seed_ukf_after(bout, n_max))
    return PersonTraces(traces, times, truth, short, ukf)


def _seed_ukf_after(bout: Bout, n_max: int) -> float:
    """The seed UKF's estimate after the bout's first ``n_max`` breaths (NaN if it has none)."""
    est = MetabolicUKF()
    mean = math.nan
    for t, w in zip(bout.t_s[:n_max], bout.watts[:n_max], strict=True):
        try:
            mean, _ = est.update(float(t), float(w))
        except (MeasurementError, EstimatorError):
            pass  # the previous estimate stands, as in the optimizer
    return float(mean)


def pair_mask(truth_w: Sequence[float], config: PairsConfig) -> np.ndarray:
    """Which ordered pairs count: ``[j, k]`` when candidate j's true cost differs from incumbent
    k's by ``min_diff_pct``-``max_diff_pct`` % of k's, shape (n, n), False on the diagonal."""
    truth = np.asarray(truth_w, dtype=float)
    diff = 100.0 * np.abs(truth[:, None] - truth[None, :]) / truth[None, :]
    mask = (diff >= config.min_diff_pct) & (diff <= config.max_diff_pct)
    np.fill_diagonal(mask, False)
    return mask


def measurement_error(people: Sequence[PersonTraces], config: PairsConfig | None = None) -> dict[str, Any]:
    """How hard the pairs are to rank: the share of truly better candidates (every ordered pair of
    a person's full-length bouts) whose N-breath estimate is above the incumbent's, for the
    chained transition estimator and for the seed UKF.

    Computed on the pairs the rules are scored on (:func:`pair_mask` with ``config``; every pair
    without one), so it says how hard *these* pairs are; a figure from another set of pairs is not
    comparable (it depends on how far apart their costs are). The seed UKF's is None when some
    person's traces carry no seed-UKF estimates (``seed_ukf_w`` empty).
    """
    paired = [p for p in people if len(p.traces) >= 2]
    has_ukf = all(len(p.seed_ukf_w) == len(p.traces) for p in paired)
    n_better = above_tr = above_ukf = 0
    for p in paired:
        truth = np.asarray(p.truth_w, dtype=float)
        final = np.array([tr.means[-1] for tr in p.traces])
        ukf = np.asarray(p.seed_ukf_w, dtype=float)
        better = truth[:, None] < truth[None, :]  # [j, k]: candidate j truly better than k
        if config is not None:
            better &= pair_mask(truth, config)
        n_better += int(better.sum())
        above_tr += int((better & (final[:, None] > final[None, :])).sum())
        if has_ukf:
            above_ukf += int((better & (ukf[:, None] > ukf[None, :])).sum())

    def pct(k: int) -> float | None:
        return 100.0 * k / n_better if n_better else None

    return {"n_better": n_better, "pct_above_transition": pct(above_tr),
            "pct_above_seed_ukf": pct(above_ukf) if has_ukf else None}


def _replays(people: Sequence[PersonTraces], config: PairsConfig) -> list[SoundReplay]:
    """One replay per person with a pair in the true-difference range (Algorithm 2's schedules
    built from all the person's full-length bouts, whatever their differences).

    Raises:
        ConfigError: No person has such a pair.
    """
    out = []
    for p in people:
        if len(p.traces) < 2:
            continue
        mask = pair_mask(p.truth_w, config)
        if not mask.any():
            continue
        groups = exploration_groups(len(p.traces), config.n_explore, config.seed)
        schedules = threshold_schedules(p.traces, min(config.window, config.n_max - 1), groups)
        out.append(SoundReplay(p.traces, p.times, schedules, p.truth_w, pairs=mask))
    if not out:
        raise ConfigError(f"no within-person pairs {config.min_diff_pct:g}-{config.max_diff_pct:g} % apart: "
                          f"every person needs at least 2 scored bouts of >= {config.n_max} breaths, "
                          "and some of them that far apart")
    return out


def _pooled(replays: Sequence[SoundReplay], n_max: int, min_decision_s: float, a_floor: float,
            accept_z: float | None, boundary_s: float | None = None) -> dict[str, Any]:
    """One rule's counts summed over the replays, and the rates of them."""
    c = dict.fromkeys(_COUNTS, 0)
    for replay in replays:
        st = replay.stats(min_decision_s, a_floor, accept_z=accept_z, boundary_s=boundary_s)
        for key in _COUNTS:
            c[key] += int(st[key])
    n, nb = c["n_pairs"], c["n_better"]
    out: dict[str, Any] = {
        **c, "mean_breaths": c["breaths_total"] / n, "breath_fraction": c["breaths_total"] / n / n_max,
        "pct_fewer_breaths": 100.0 * (1.0 - c["breaths_total"] / n / n_max),
        "pct_early": 100.0 * c["n_early"] / n, "pct_ended_30s": 100.0 * c["n_ended_30s"] / n,
        "pct_rejected_better": 100.0 * c["n_rejected_better"] / nb if nb else None,
        "pct_better_above_at_n": 100.0 * c["n_better_above_at_n"] / nb if nb else None}
    return out


def _targets(st: dict[str, Any]) -> dict[str, bool]:
    """The three pair targets, met or not, for pooled statistics."""
    return {"rejected_better_at_most_10pct": st["pct_rejected_better"] is not None
            and st["pct_rejected_better"] <= 100.0 * TARGET_REJECTED_BETTER,
            "breaths_at_least_25pct_fewer": st["breath_fraction"] <= TARGET_BREATH_FRACTION,
            "ended_30s_at_most_5pct": st["pct_ended_30s"] <= 100.0 * TARGET_ENDED_30S}


def pair_stats(people: Sequence[PersonTraces], config: PairsConfig) -> dict[str, dict[str, Any]]:
    """Pooled stop statistics of ``sound``, ``sound-floor``, ``adaptive`` and ``fixed`` over every
    person's pairs.

    ``sound`` has the configuration's constants; ``sound-floor`` is the earlier default (60 s,
    ``a_floor``, accept at 3 σ, no sequential boundary). ``fixed`` runs N breaths against every
    incumbent (no stop); its ``pct_better_above_at_n`` is the measurement's own error. The two
    sound rules carry the ``targets``.

    Raises:
        ConfigError: No person has two full-length scored bouts.
    """
    replays = _replays(people, config)
    out = {"sound": _pooled(replays, config.n_max, config.min_decision_s, config.a_floor, config.accept_z,
                            config.boundary_s),
           "sound-floor": _pooled(replays, config.n_max, FLOOR_MIN_DECISION_S, config.a_floor,
                                  FLOOR_ACCEPT_Z),
           "adaptive": _pooled(replays, config.n_max, 0.0, -math.inf, None),
           "fixed": _pooled(replays, config.n_max, math.inf, math.inf, None)}
    for rule in ("sound", "sound-floor"):
        out[rule]["targets"] = _targets(out[rule])
    return out


def sound_grid(people: Sequence[PersonTraces], config: PairsConfig) -> list[dict[str, Any]]:
    """The sound rule's statistics over :data:`GRID_MIN_DECISION_S` × :data:`GRID_A_FLOOR`.

    The trade-off the constants make on these data (breaths against wrong rejections), with the
    configuration's accept stop and sequential boundary; each entry says whether it meets the
    three targets.
    """
    replays = _replays(people, config)
    out = []
    for m in GRID_MIN_DECISION_S:
        for a in GRID_A_FLOOR:
            st = _pooled(replays, config.n_max, m, a, config.accept_z, config.boundary_s)
            out.append({"min_decision_s": m, "a_floor": a, "mean_breaths": st["mean_breaths"],
                        "pct_rejected_better": st["pct_rejected_better"],
                        "pct_ended_30s": st["pct_ended_30s"], "meets_targets": all(_targets(st).values())})
    return out


def pairs_table(stats: dict[str, dict[str, Any]], n_max: int) -> str:
    """Markdown: one row per rule."""
    def pct(v: float | None) -> str:
        return "–" if v is None else f"{v:.1f} %"

    rows = [[rule, s["n_pairs"], f"{s['mean_breaths']:.1f}", f"{s['pct_fewer_breaths']:.1f} %",
             pct(s["pct_ended_30s"]), pct(s["pct_early"]),
             f"{pct(s['pct_rejected_better'])} (of {s['n_better']})", pct(s["pct_better_above_at_n"])]
            for rule, s in stats.items()]
    return markdown_table(["rule", "pairs", "mean breaths / evaluation", f"fewer than {n_max}",
                           "ended within 30 s", "early stops", "truly better rejected",
                           f"truly better, estimate above the incumbent's at {n_max}"], rows)


def run_pairs_bench(people: Sequence[Sequence[Bout]], config: PairsConfig | None = None,
                    progress: Callable[[int], None] | None = None) -> dict[str, Any]:
    """Trace every person, pair, and pool; the JSON document without command and machine."""
    cfg = PairsConfig() if config is None else config
    t0 = time.perf_counter()
    traced = []
    for i, person in enumerate(people):
        traced.append(person_traces(person, cfg.n_max))
        if progress is not None:
            progress(i + 1)
    stats = pair_stats(traced, cfg)
    grid = sound_grid(traced, cfg)
    return {"benchmark": "pairs", "config": {k: getattr(cfg, k) for k in cfg.__dataclass_fields__},
            "people": len(traced), "people_with_pairs": sum(len(p.traces) >= 2 for p in traced),
            "full_length_bouts": sum(len(p.traces) for p in traced),
            "short_bouts": sum(p.short for p in traced),
            "pairs_all": sum(len(p.traces) * (len(p.traces) - 1) for p in traced),
            "measurement_error": measurement_error(traced, cfg),
            "rules": stats, "grid": grid,
            "wall_s": time.perf_counter() - t0}


# ------------------------------------------------------------------------------ command
def _fmt_accept(z: float | None) -> str:
    return "none" if z is None else f"{z:g}"


def _number_or_none(option: str, text: str, expected: str) -> float | None:
    """A command-line number, or None for ``none``; ConfigError naming ``option`` otherwise."""
    if text.strip().lower() == "none":
        return None
    try:
        return float(text)
    except ValueError as err:
        raise ConfigError(f"{option} {text!r}; expected {expected} or none") from err


def _diff_pct(text: str) -> tuple[float, float]:
    try:
        lo, hi = (float(x) for x in text.split(","))
    except ValueError as err:
        raise ConfigError(f"--diff-pct {text!r}; expected LOW,HIGH in % (e.g. 2,20 or 0,inf)") from err
    return lo, hi


def _cmd_pairs(args: argparse.Namespace) -> int:
    from rich.console import Console

    from bridge.bench.common import options

    console = Console(markup=False, highlight=False, soft_wrap=True)
    replays = args.replay or []
    transitions = args.transitions or []
    with options({"boundary_s": "--boundary-s", "accept_z": "--accept-z", "a_floor": "--a-floor",
                  "min_decision_s": "--min-decision-s", "n_max": "--n-max"}):
        # the command line's values (exit status 2); the files' are 1
        accept = _number_or_none("--accept-z", args.accept_z, "a number of σ >= 0")
        boundary = _number_or_none("--boundary-s", args.boundary_s, "seconds > 0")
        lo, hi = _diff_pct(args.diff_pct)
        cfg = PairsConfig(n_max=args.n_max, min_decision_s=args.min_decision_s, a_floor=args.a_floor,
                          accept_z=accept, boundary_s=boundary, min_diff_pct=lo, max_diff_pct=hi)
        if len(replays) != len(transitions):
            raise ConfigError(f"{len(replays)} --replay and {len(transitions)} --transitions: give one "
                              "--transitions t1,t2,... after each --replay FILE")
        if not replays and args.csv_columns is not None:
            raise ConfigError("--csv-columns goes with --replay")
        if not replays and args.wearer not in WEARERS:
            raise ConfigError(f"--wearer {args.wearer!r}; expected one of {sorted(WEARERS)} "
                              "(or --replay files)")
        if not replays and (args.n < 1 or args.seed < 0 or args.bouts < 3):
            raise ConfigError(f"--n {args.n} --seed {args.seed} --bouts {args.bouts}; expected "
                              "n >= 1, seed >= 0, bouts >= 3")
        if not replays and not (math.isfinite(args.bout_s) and args.bout_s > 0):
            raise ConfigError(f"--bout-s {args.bout_s}; expected a duration > 0 s")
        if args.step_scale is not None and (replays or args.wearer != "synthetic"):
            raise ConfigError(f"--step-scale {args.step_scale:g} goes with --wearer synthetic")
        if args.step_scale is not None and not (math.isfinite(args.step_scale) and args.step_scale >= 0):
            raise ConfigError(f"--step-scale {args.step_scale}; expected a number >= 0")
        trans = [parse_transitions(text) for text in transitions]
    if replays:
        cols = args.csv_columns.split(",") if args.csv_columns else None
        people = [p for f, t in zip(replays, trans, strict=True) for p in replay_people(f, t, cols)]
        source = " ".join(f"--replay {f} --transitions {t}"
                          for f, t in zip(replays, transitions, strict=True))
        source += f" --csv-columns {args.csv_columns}" if args.csv_columns else ""
    else:
        scale = {} if args.step_scale is None else {"step_scale": args.step_scale}
        people = WEARERS[args.wearer](args.n, args.seed, bouts=args.bouts, bout_s=args.bout_s, **scale)
        source = (f"--wearer {args.wearer} --n {args.n} --seed {args.seed} --bouts {args.bouts} "
                  f"--bout-s {args.bout_s:g}")
        source += "" if args.step_scale is None else f" --step-scale {args.step_scale:g}"
    n_people = len(people)
    step = max(1, n_people // 10)

    def progress(i: int) -> None:
        if not args.no_progress and n_people > 1 and (i % step == 0 or i == n_people):
            console.print(f"  {i}/{n_people} people", style="dim")

    who = "1 person" if n_people == 1 else f"{n_people} people"
    console.print(f"hilbo bench pairs: {who}, N = {cfg.n_max}, sound rule "
                  f"{cfg.min_decision_s:g} s / boundary {_fmt_accept(cfg.boundary_s)} s / "
                  f"{cfg.a_floor:g} σ / accept {_fmt_accept(cfg.accept_z)}, "
                  f"pairs with true costs {cfg.min_diff_pct:g}-{cfg.max_diff_pct:g} % apart")
    doc = run_pairs_bench(people, cfg, progress)
    doc["command"] = (f"hilbo bench pairs {source} --n-max {cfg.n_max} "
                      f"--diff-pct {cfg.min_diff_pct:g},{cfg.max_diff_pct:g} "
                      f"--min-decision-s {cfg.min_decision_s:g} --boundary-s {_fmt_accept(cfg.boundary_s)} "
                      f"--a-floor {cfg.a_floor:g} "
                      f"--accept-z {_fmt_accept(cfg.accept_z)} --out {args.out}")
    doc["machine"] = machine_info()
    out = Path(args.out)
    write_json(out / "pairs.json", round_sig(doc))
    table = pairs_table(doc["rules"], cfg.n_max)
    (out / "pairs_table.md").write_text(table)
    console.print(table)
    from bridge.bench.plots import plot_pairs

    chosen = {"mean_breaths": doc["rules"]["sound"]["mean_breaths"],
              "pct_rejected_better": doc["rules"]["sound"]["pct_rejected_better"]}
    plot_pairs(doc["grid"], chosen, out / "pairs.png", n_max=cfg.n_max,
               max_rejected_pct=100.0 * TARGET_REJECTED_BETTER, max_breath_fraction=TARGET_BREATH_FRACTION)
    meeting = [g for g in doc["grid"] if g["meets_targets"]]
    if meeting:
        g = min(meeting, key=lambda g: g["mean_breaths"])
        console.print(f"{len(meeting)} of the grid's {len(doc['grid'])} sound-rule constants meet all three "
                      f"targets on these pairs; fewest breaths: {g['min_decision_s']:g} s / "
                      f"{g['a_floor']:g} σ ({g['mean_breaths']:.1f} breaths, "
                      f"{g['pct_rejected_better']:.1f} % rejected); the trade-off: pairs.png")
    else:
        console.print(f"none of the grid's {len(doc['grid'])} sound-rule constants meets all three targets "
                      "on these pairs; the trade-off: pairs.png")
    if doc["short_bouts"]:
        console.print(f"{doc['short_bouts']} scored bouts had fewer than {cfg.n_max} breaths and were "
                      "left out", style="yellow")
    err = doc["measurement_error"]
    n_scored = doc["rules"]["sound"]["n_pairs"]
    console.print(f"{n_scored} of {doc['pairs_all']} within-person pairs have true costs "
                  f"{cfg.min_diff_pct:g}-{cfg.max_diff_pct:g} % apart; every figure here is on them")
    if err["n_better"] and err["pct_above_seed_ukf"] is not None:
        console.print(f"how hard these pairs are to rank: after {cfg.n_max} breaths the seed UKF puts "
                      f"{err['pct_above_seed_ukf']:.1f} % of truly better candidates above their incumbent, "
                      f"the transition estimator {err['pct_above_transition']:.1f} %")
    for rule in ("sound", "sound-floor"):
        met = doc["rules"][rule]["targets"]
        console.print(f"targets ({rule}): " + ", ".join(
            f"{k} {'met' if v else 'NOT met'}" for k, v in met.items()))
    console.print(str(out / "pairs.json"))
    return 0


def add_pairs_bench_parser(bench_subparsers: Any) -> argparse.ArgumentParser:
    """Add ``pairs`` to the ``hilbo bench`` subcommands; returns its parser."""
    p = bench_subparsers.add_parser(
        "pairs", help="stop statistics on within-person pairs of transitions",
        description="Replay the sound rule, Kim et al. 2019's adaptive rule and fixed N breaths on every "
                    "within-person pair of full-length bouts (candidate against incumbent) of recorded "
                    "breath files (--replay FILE --transitions ..., repeated per person) or of "
                    "simulated people (--wearer); reports breaths per evaluation, evaluations ended "
                    "within 30 s and truly better candidates rejected, against the project's targets.")
    p.add_argument("--replay", action="append", default=None, metavar="FILE",
                   help="a recorded breath file of one person (hilbo-line or a vendor export, detected "
                        "as `hilbo cart inspect` does); repeat per person")
    p.add_argument("--transitions", action="append", default=None, metavar="T1,T2,...",
                   help="after each --replay: its setting-change times in s on the file's clock")
    p.add_argument("--csv-columns", default=None, metavar="TIME,VO2,VCO2",
                   help="with --replay: the files are CSVs with these header names (s, ml/min)")
    p.add_argument("--wearer", default="realistic",
                   help=f"simulated people instead, from {','.join(sorted(WEARERS))} (realistic: hip "
                        "settings, steps of 5-25 %%; synthetic: steps up to ±80 %%)")
    p.add_argument("--step-scale", type=float, default=None, metavar="S",
                   help="with --wearer synthetic: scale its steps by S (1); smaller steps are harder to "
                        "rank (see the 'how hard' line)")
    p.add_argument("--n", type=positive_int, default=20, help="simulated people (20)")
    p.add_argument("--seed", type=nonnegative_int, default=1, help="seed of the simulated people (1)")
    p.add_argument("--bouts", type=int, default=10,
                   help="settings per simulated person, the first a warm-up (10)")
    p.add_argument("--bout-s", type=float, default=180.0, help="seconds per simulated setting (180)")
    p.add_argument("--diff-pct", default=f"{DEFAULT_DIFF_PCT[0]:g},{DEFAULT_DIFF_PCT[1]:g}",
                   metavar="LOW,HIGH",
                   help="score only pairs whose true costs differ by LOW-HIGH %% of the incumbent's "
                        f"({DEFAULT_DIFF_PCT[0]:g},{DEFAULT_DIFF_PCT[1]:g}: an assistance change's "
                        "differences; 0,inf: every pair)")
    p.add_argument("--n-max", type=positive_int, default=_DEFAULTS.max_breaths,
                   help=f"N, breaths of a full evaluation ({_DEFAULTS.max_breaths})")
    p.add_argument("--min-decision-s", type=float, default=_DEFAULTS.min_decision_s,
                   help=f"the sound rule's time floor in s ({_DEFAULTS.min_decision_s:g})")
    p.add_argument("--boundary-s", default=_fmt_accept(_DEFAULTS.boundary_s), metavar="S",
                   help="the sound rule's sequential boundary reaches its late levels at S s in a setting, "
                        f"or none for the fixed clock ({_fmt_accept(_DEFAULTS.boundary_s)})")
    p.add_argument("--a-floor", type=float, default=_DEFAULTS.a_floor,
                   help=f"the sound rule's threshold floor in σ ({_DEFAULTS.a_floor:g})")
    p.add_argument("--accept-z", default=_fmt_accept(_DEFAULTS.accept_z), metavar="Z",
                   help="the sound rule's accept stop in σ, or none "
                        f"({_fmt_accept(_DEFAULTS.accept_z)})")
    p.add_argument("--out", default="runs/bench/pairs",
                   help="output directory (runs/bench/pairs)")
    p.add_argument("--no-progress", action="store_true", help="no progress lines")
    p.set_defaults(func=_cmd_pairs)
    return p
