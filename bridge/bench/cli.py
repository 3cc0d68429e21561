"""The ``hilbo bench`` subcommands: ``stopping``, ``hil``, ``perf``, ``estimator``, ``pairs``,
``watchdog`` and ``tutor``.

:func:`add_bench_parser` registers them on the main ``hilbo`` parser; :func:`bench_main` is a
standalone entry point (``python -m bridge.bench ...``) with the same exit codes as ``hilbo``:
0 on success; 2 for a wrong command line (argparse's errors, and option values or combinations
refused before any work starts, named in the message); 1 for a failure once the work has
started (an input file that cannot be used, a failed run, a missing optional dependency such
as Optuna); 130 when interrupted.
"""

from __future__ import annotations

import argparse
import json
import logging
import re
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from rich.console import Console

from bridge.argtypes import nonnegative
from bridge.bench.bridge_perf import BridgeProtocol
from bridge.bench.common import choices, machine_info, numbers, options, round_sig, write_json
from bridge.collector import GcMode
from bridge.errors import BridgeError, UsageError
from bridge.sim.devices import WEARER_CHOICES, WearerKind
from drivers.errors import DriverError
from hilbo_core.errors import ConfigError, HilboError
from hilbo_core.studies.benchmarks import FUNCTIONS, METHODS, NOISE_LEVELS, StoppingProtocol

__all__ = ["add_bench_parser", "bench_main", "options"]

logger = logging.getLogger(__name__)


def _int(text: str) -> int:
    try:
        value = int(text)
    except ValueError as err:
        raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from err
    return value


def _scheduler_address(text: str) -> str:
    """``--scheduler``: a Dask scheduler address, ``HOST:PORT`` or ``tcp://HOST:PORT`` (``tls://``
    too; other schemes are passed to Dask as given), refused as a usage error otherwise."""
    address = text.strip()
    scheme, sep, _ = address.partition("://")
    if sep and scheme not in ("tcp", "tls"):
        return address
    m = re.fullmatch(r"(?:(?:tcp|tls)://)?(?:\[[0-9A-Fa-f:.]+\]|[^\s:/\[\]]+):(\d{1,5})", address)
    if m is None or not 1 <= int(m.group(1)) <= 65535:
        raise argparse.ArgumentTypeError(
            f"expected a Dask scheduler address HOST:PORT or tcp://HOST:PORT (port 1-65535), "
            f"got {text!r}")
    return address


def _add_executor_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--workers", type=_int, default=None,
                   help="local worker processes (default: all cores; 1 = in this process)")
    p.add_argument("--scheduler", type=_scheduler_address, default=None, metavar="ADDRESS",
                   help="run on a Dask distributed cluster, e.g. tcp://10.0.0.5:8786 "
                        "(the workers need hilbo installed)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")


def _executor(args: argparse.Namespace) -> Any:
    from bridge.bench.executors import make_executor

    with options():
        if args.workers is not None and args.workers < 1:
            raise ConfigError(f"--workers {args.workers}; expected an integer >= 1")
    # A scheduler that cannot be reached is a runtime failure (exit status 1), not a usage error.
    return make_executor(args.workers, args.scheduler, progress=False if args.no_progress else None)


def _say_missing(found: int, asked: int, what: str) -> None:
    """``--summarize-only`` on an unfinished campaign: say that the tables cover only part of it."""
    if found < asked:
        sys.stderr.write(f"warning: --summarize-only: {found} of the {asked} {what} of this run are "
                         f"on disk; the tables cover only those (run with --resume instead of "
                         f"--summarize-only to finish the campaign)\n")


def _console() -> Console:
    return Console(markup=False, highlight=False, soft_wrap=True)


# ------------------------------------------------------------------------------------ stopping
def _stopping_command(args: argparse.Namespace, campaign: Any) -> str:
    p = campaign.protocol
    return (f"hilbo bench stopping --trials {campaign.trials} --functions {','.join(campaign.functions)} "
            f"--noise {','.join(f'{n:g}' for n in campaign.noises)} --methods {','.join(campaign.methods)} "
            f"--noise-model {p.noise_model.value} --noise-estimate {p.noise_estimate.value} "
            f"--budget {p.budget} --n-explore {p.n_explore} "
            f"--max-breaths {p.max_breaths} --window {p.window} --design {p.design.value} "
            f"--n-candidates {p.n_candidates} "
            f"--n-local {p.n_local} --prior-mean-sd {p.prior_mean_sd:g} --seed {campaign.seed} "
            f"--refit-growth {campaign.refit_growth:g} "
            f"--grid-step {args.grid_step} --out {args.out}"
            + (" --summarize-only" if args.summarize_only else "")
            + "".join(f" --merge {d}" for d in args.merge or []))


def _cmd_stopping(args: argparse.Namespace) -> int:
    from bridge.bench.plots import plot_stopping_function
    from bridge.bench.stopping import (
        PEER_METHODS,
        StoppingCampaign,
        function_descriptions,
        load_trials,
        method_descriptions,
        run_campaign,
        stopping_table,
        summarize_stopping,
    )

    # Every option is checked before any work starts (exit status 2 with the offending value).
    with options():
        functions = choices(args.functions, FUNCTIONS, "function", list(FUNCTIONS))
        methods = choices(args.methods, {**METHODS, **PEER_METHODS}, "method", ["fixed", "adaptive"])
        noises = numbers(args.noise, "noise level", NOISE_LEVELS)
        if args.grid_step < 1:
            raise ConfigError(f"--grid-step {args.grid_step}; expected an integer >= 1")
        protocol = StoppingProtocol(n_explore=args.n_explore, max_breaths=args.max_breaths,
                                    window=args.window, budget=args.budget, noise_model=args.noise_model,
                                    noise_estimate=args.noise_estimate, n_candidates=args.n_candidates,
                                    n_local=args.n_local, design=args.design,
                                    prior_mean_sd=args.prior_mean_sd)
        campaign = StoppingCampaign(functions=tuple(functions), noises=tuple(noises),
                                    methods=tuple(methods), trials=args.trials, seed=args.seed,
                                    protocol=protocol, refit_growth=args.refit_growth)
        if args.merge and not args.summarize_only:
            raise ConfigError("--merge only goes with --summarize-only")
    out = Path(args.out)
    console = _console()
    if args.summarize_only:
        have: dict[Any, dict[str, Any]] = {}
        sources = [out, *(Path(d) for d in args.merge or [])]
        with options():  # a --merge that names nothing is a usage error
            for d in sources[1:]:
                if not (d / "trials.jsonl").is_file():
                    raise ConfigError(f"--merge {d}: no trials.jsonl there (expected the --out "
                                      "directory of another run of this campaign)")
        for d in sources:
            have.update(load_trials(d / "trials.jsonl", protocol, campaign.refit_growth))
        results = [have[t.key()] for t in campaign.tasks() if t.key() in have]
        if not results:
            raise ConfigError(f"--summarize-only: no trial of this campaign in "
                              f"{[str(d / 'trials.jsonl') for d in sources]}")
        _say_missing(len(results), len(campaign.tasks()), "trials")
        wall = None
    else:
        executor = _executor(args)
        console.print(f"hilbo bench stopping: {len(campaign.tasks())} trials on {executor.name}")
        results, wall = run_campaign(campaign, executor, out, resume=args.resume)
    summary = summarize_stopping(results, campaign, grid_step=args.grid_step)
    per_trial = [s["trial_wall_s_mean"] for s in summary["settings"]]
    complete = len(per_trial) == len(functions) * len(noises) * len(methods) and None not in per_trial
    doc = {
        "benchmark": "stopping",
        "command": _stopping_command(args, campaign),
        "campaign": campaign.to_json(),
        "trials_found": len(results),
        "machine": machine_info(),
        "executor": None if args.summarize_only else executor.name,
        "wall_s": wall,
        # Σ over settings of the mean wall time of one trial × the trials asked for: the CPU
        # time the whole campaign needs at the speed these trials ran (divide by the workers).
        "projected_campaign_core_s": sum(per_trial) * campaign.trials if complete else None,
        "methods": method_descriptions(methods),
        "functions": function_descriptions(functions),
        "noise": "σ_z²/σ̃² (Kim et al. 2019 §III.2 levels 0.1, 1, 10); noise_model 'matched': measurements "
                 "have variance σ_z² and the estimator knows it; 'assumed': measurements have "
                 "variance σ̃² and σ_z² is the estimator's assumption; noise_estimate 'seed': "
                 "every measurement is fused with σ_z²; 'pooled': with the variance learnt from "
                 "the trial's measurements, σ_z² as its prior",
        **summary,
    }
    write_json(out / "results.json", doc)
    table = stopping_table(summary)
    (out / "table.md").write_text(table)
    pngs = [plot_stopping_function(summary["settings"], f, out / f"stopping_{f}.png") for f in functions]
    console.print(table)
    if wall is not None:
        console.print(f"{len(results)} trials, this run {wall:.1f} s wall")
    for p in [out / "results.json", out / "table.md", *pngs]:
        console.print(str(p))
    return 0


# ------------------------------------------------------------------------------------ hil
def _cmd_hil(args: argparse.Namespace) -> int:
    from bridge.bench.hil import (
        DEFAULT_HIL_METHODS,
        HIL_METHODS,
        HilProtocol,
        HilTask,
        check_methods_for_wearer,
        hil_comparisons,
        hil_table,
        load_sessions,
        run_hil_task,
        summarize_hil,
    )
    from bridge.bench.plots import plot_hil
    from hilbo_core.presets import PRESETS

    with options():
        spaces = choices(args.spaces, PRESETS, "space", list(PRESETS))
        methods = choices(args.methods, HIL_METHODS, "method", list(DEFAULT_HIL_METHODS))
        if args.subjects < 1:
            raise ConfigError(f"--subjects {args.subjects}; expected an integer >= 1")
        if args.seed < 0:
            raise ConfigError(f"--seed {args.seed}; expected an integer >= 0")
        protocol = HilProtocol(minutes=args.minutes, warmup_s=args.warmup_s, condition_s=args.condition_s,
                               popsize=args.popsize, sigma0=args.sigma0, penalty_w=args.penalty_w,
                               n_explore=args.n_explore, max_breaths=args.max_breaths, window=args.window,
                               grid_min=args.grid_min, wearer=args.wearer)
        check_methods_for_wearer(methods, protocol.wearer)  # before any tuning runs
    seeds = list(range(args.seed, args.seed + args.subjects))
    out = Path(args.out)
    console = _console()
    done = load_sessions(out / "sessions.jsonl", protocol) if (args.resume or args.summarize_only) else {}
    tuning = _hil_tuned_k(args, methods, spaces, seeds, protocol, done, console)
    # Subject-major: an interrupted run has every method on the first subjects.
    tasks = [HilTask(m, s, k, protocol, stopping_k=tuning[s]["k"] if m == "adaptive-tuned-k" else None)
             for k in seeds for s in spaces for m in methods]
    if not args.summarize_only:  # a kept session must have run with this run's K
        want = {t.key(): t.stopping_k for t in tasks}
        done = {key: r for key, r in done.items() if key not in want or r.get("stopping_k") == want[key]}
    if args.summarize_only:
        results = [done[t.key()] for t in tasks if t.key() in done]
        if not results:
            raise ConfigError(f"--summarize-only: {out / 'sessions.jsonl'} holds no session of this run")
        _say_missing(len(results), len(tasks), "sessions")
        wall, executor_name = None, None
    else:
        executor = _executor(args)
        todo = [t for t in tasks if t.key() not in done]
        console.print(f"hilbo bench hil: {len(tasks)} sessions ({len(todo)} to run) on {executor.name}")
        out.mkdir(parents=True, exist_ok=True)
        if not args.resume and (out / "sessions.jsonl").exists():
            (out / "sessions.jsonl").unlink()
        t0 = time.perf_counter()
        # Summarised as sessions.jsonl holds it, so that --summarize-only gives the same numbers.
        written: dict[int, dict[str, Any]] = {}
        with (out / "sessions.jsonl").open("a") as fh:

            def record(i: int, result: dict[str, Any]) -> None:
                written[i] = round_sig(result | {"protocol": protocol.to_json()}, 10)
                fh.write(json.dumps(written[i]) + "\n")
                fh.flush()

            executor.map(run_hil_task, todo, label="HIL sessions", on_result=record)
        wall = time.perf_counter() - t0
        for i, t in enumerate(todo):
            done[t.key()] = written[i]
        results = [done[t.key()] for t in tasks]
        executor_name = executor.name
    entries = summarize_hil(results, spaces, methods, protocol)
    comparisons = hil_comparisons(results, spaces, methods)
    command = (f"hilbo bench hil --subjects {args.subjects} --seed {args.seed} --spaces {','.join(spaces)} "
               f"--methods {','.join(methods)} --minutes {args.minutes:g} --warmup-s {args.warmup_s:g} "
               f"--condition-s {args.condition_s:g} --popsize {args.popsize} --sigma0 {args.sigma0:g} "
               f"--penalty-w {args.penalty_w:g} "
               + ("" if args.n_explore is None else f"--n-explore {args.n_explore} ")
               + f"--max-breaths {args.max_breaths} --window {args.window} --grid-min {args.grid_min:g} "
               f"--wearer {args.wearer} "
               + (f"--tuned-k {args.tuned_k} --tune-subjects {args.tune_subjects} --tune-seed "
                  f"{args.tune_seed} --error-weight {args.error_weight:g} "
                  if "adaptive-tuned-k" in methods else "")
               + f"--out {args.out}"
               + (" --summarize-only" if args.summarize_only else ""))
    write_json(out / "hil.json", {
        "benchmark": "hil", "command": command, "protocol": protocol.to_json(), "subjects": seeds,
        "machine": machine_info(), "executor": executor_name, "wall_s": wall,
        "sessions_found": len(results), "results": entries, "comparisons": comparisons,
        "tuning": tuning or None,
        # Per-session numbers without the recommendation traces (those stay in sessions.jsonl).
        "sessions": [{k: v for k, v in r.items() if k not in ("protocol", "trace")} for r in results],
    })
    table = hil_table(entries, comparisons=comparisons)
    (out / "hil_table.md").write_text(table)
    nested: dict[str, dict[str, Any]] = {}
    for e in entries:
        nested.setdefault(e["space"], {})[e["method"]] = e
    png = plot_hil(nested, out / "hil.png")
    console.print(table)
    if wall is not None:
        console.print(f"{len(results)} sessions, this run {wall:.1f} s wall")
    for p in (out / "hil.json", out / "hil_table.md", png):
        console.print(str(p))
    return 0


def _hil_tuned_k(args: argparse.Namespace, methods: Sequence[str], spaces: Sequence[str],
                 seeds: Sequence[int], protocol: Any, done: dict[Any, dict[str, Any]],
                 console: Console) -> dict[str, dict[str, Any]]:
    """K of ``adaptive-tuned-k`` per space: ``--tuned-k K``, or tuned on training wearers."""
    from bridge.bench.hil import HilTask, run_training_session, tune_constant_k

    if "adaptive-tuned-k" not in methods:
        return {}
    text = str(args.tuned_k).strip()
    with options():
        if text not in ("bo", "grid"):
            try:
                k = float(text)
            except ValueError as err:
                raise ConfigError(f"--tuned-k {text!r}; expected bo, grid or a constant K >= 0 "
                                  "(in σ)") from err
            if not (k >= 0 and k < float("inf")):
                raise ConfigError(f"--tuned-k {text!r}; expected bo, grid or a constant K >= 0 (in σ)")
            return {s: {"k": k, "pick": "given"} for s in spaces}
        if args.tune_subjects < 1:
            raise ConfigError(f"--tune-subjects {args.tune_subjects}; expected an integer >= 1")
        if args.tune_seed < 0:
            raise ConfigError(f"--tune-seed {args.tune_seed}; expected an integer >= 0")
        train = list(range(args.tune_seed, args.tune_seed + args.tune_subjects))
        overlap = sorted(set(train) & set(seeds))
        if overlap:
            raise ConfigError(f"--tune-seed {args.tune_seed} --tune-subjects {args.tune_subjects}: "
                              f"training wearers {overlap} are also test subjects; K must be tuned "
                              "on other wearers")
    if args.summarize_only:  # nothing is run: K as the sessions found used it
        found = {key[1]: r.get("stopping_k") for key, r in done.items() if key[0] == "adaptive-tuned-k"}
        return {s: {"k": float(found.get(s) or 0.0), "pick": f"{text} (as found in sessions.jsonl)"}
                for s in spaces}
    executor = _executor(args)
    out: dict[str, dict[str, Any]] = {}
    for space in spaces:
        t0 = time.perf_counter()
        tasks = [HilTask("adaptive", space, s, protocol) for s in train]
        console.print(f"hilbo bench hil: tuning K for {space} on {len(train)} training wearers "
                      f"(seeds {train[0]}-{train[-1]}) on {executor.name}")
        trajs = [t for r in executor.map(run_training_session, tasks, label="training sessions") for t in r]
        tuned = tune_constant_k(trajs, protocol, pick=text, error_weight=args.error_weight)
        tuned |= {"train_seeds": train, "wall_s": time.perf_counter() - t0}
        console.print(f"  K = {tuned['k']:.3g} ({text}; BO-RESAMPLE {tuned['recommended']['k']:.3g}, "
                      f"grid best {tuned['grid_best']['k']:.3g}) from {tuned['n_trajectories']} "
                      f"trajectories, {tuned['wall_s']:.0f} s")
        out[space] = round_sig(tuned)
    return out


# ------------------------------------------------------------------------------------ perf
def _cmd_perf(args: argparse.Namespace) -> int:
    from bridge.bench.bridge_perf import bridge_table
    from bridge.bench.perf import PerfConfig, perf_table, run_perf

    with options():
        sizes = [int(v) for v in numbers(args.sizes, "observation count", (10, 30, 60, 100))]
        cfg = PerfConfig(breaths=args.breaths, sizes=tuple(sizes), reps=args.reps, sessions=args.sessions,
                         seed=args.seed, bridge_minutes=args.bridge_minutes, bridge_speed=args.bridge_speed,
                         bridge_feedback_hz=args.bridge_feedback_hz,
                         bridge_baseline_s=args.bridge_baseline_s, bridge_gc=args.bridge_gc,
                         bridge_protocol=args.bridge_protocol)
    console = _console()
    console.print("hilbo bench perf: timing breath, proposal and session (in this process)"
                  + (f", then the bridge at real time for {cfg.bridge_minutes:g} min"
                     if cfg.bridge_minutes > 0 else ""))
    out = Path(args.out)
    result = run_perf(cfg, bridge_out=out / "bridge_session")
    result["command"] = (f"hilbo bench perf --breaths {cfg.breaths} --sizes {','.join(map(str, sizes))} "
                         f"--reps {cfg.reps} --sessions {cfg.sessions} --seed {cfg.seed}"
                         + (f" --bridge-minutes {cfg.bridge_minutes:g} --bridge-speed {cfg.bridge_speed:g} "
                            f"--bridge-feedback-hz {cfg.bridge_feedback_hz:g} "
                            f"--bridge-baseline-s {cfg.bridge_baseline_s:g} --bridge-gc {cfg.bridge_gc} "
                            f"--bridge-protocol {cfg.bridge_protocol}"
                            if cfg.bridge_minutes > 0 else "")
                         + f" --out {args.out}")
    result["machine"] = machine_info()
    write_json(out / "perf.json", result)
    bridge = result["bridge_realtime"]
    bridge_files = [out / "perf_bridge.json", out / "perf_bridge_table.md"] if bridge is not None else []
    if bridge is not None:  # the small files docs/results/perf/ keeps
        write_json(out / "perf_bridge.json", {"benchmark": "perf-bridge", "command": result["command"],
                                              "machine": result["machine"], **bridge})
        (out / "perf_bridge_table.md").write_text(bridge_table(bridge))
    table = perf_table(result)
    (out / "perf_table.md").write_text(table)
    console.print(table)
    prof = result.get("proposal_profile") or {}
    if prof:
        console.print(f"one proposal at {prof['observations']} observations: {prof['total_ms']:.1f} ms, "
                      f"GP fit {prof['gp_fit_ms']:.1f} ms, EI maximisation {prof['maximize_ei_ms']:.1f} ms")
    for p in (out / "perf.json", out / "perf_table.md", *bridge_files):
        console.print(str(p))
    return 0


# ------------------------------------------------------------------------------------ parser
def add_bench_parser(subparsers: Any) -> Any:
    """Register ``bench`` with ``estimator``, ``hil``, ``pairs``, ``perf``, ``stopping`` and
    ``watchdog`` on a subparsers object.

    Returns:
        The ``bench`` command's own subparsers, so other benchmarks can join it, e.g.
        ``add_tutor_bench_parser(add_bench_parser(sub))`` for ``hilbo bench tutor``.
    """
    bench = subparsers.add_parser(
        "bench", help="benchmarks: results as JSON, Markdown tables and plots",
        description="Benchmarks of hilbo. Results go to --out as JSON, Markdown tables and plots.")
    bsub = bench.add_subparsers(dest="bench_command", required=True, metavar="BENCH")

    st = bsub.add_parser(
        "stopping", help="Kim et al. 2019 §III.2: stopping vs fixed-interval BO on the Table I functions",
        description="The simulation study of Kim et al. 2019 §III.2 (Table I functions, Gaussian-product "
                    "measurements, three noise levels, 6 exploration points, N = 45, 630 measurements).")
    st.add_argument("--trials", type=_int, default=100, help="trials per function and noise (default 100)")
    st.add_argument("--functions", default=None,
                    help=f"comma-separated, from {','.join(FUNCTIONS)} (default all)")
    st.add_argument("--noise", default=None,
                    help="comma-separated σ_z²/σ̃² factors (default 0.1,1,10)")
    st.add_argument("--methods", default=None,
                    help=f"comma-separated, from {','.join(METHODS)} and the Optuna peers "
                         "tpe-wilcoxon,tpe-halving (pip install hilbo[peers]) (default fixed,adaptive)")
    st.add_argument("--noise-model", default="matched", choices=["matched", "assumed"],
                    help="matched: measurements have variance σ_z²; assumed: they have σ̃² and σ_z² "
                         "is only the estimator's assumption (default matched)")
    st.add_argument("--noise-estimate", default="pooled", choices=["pooled", "seed"],
                    help="pooled: the measurement variance is learnt from the trial's measurements, "
                         "σ_z² being its prior (3 pseudo-measurements); seed: every measurement "
                         "has variance σ_z², as in Kim et al. 2019 (default pooled)")
    st.add_argument("--budget", type=_int, default=630, help="measurements after exploration (630)")
    st.add_argument("--n-explore", type=_int, default=6, help="exploration points (6)")
    st.add_argument("--max-breaths", type=_int, default=45, help="N, measurements per evaluation (45)")
    st.add_argument("--window", type=_int, default=2, help="Algorithm 2's window W (2)")
    st.add_argument("--design", default="sobol_only", choices=["sobol_only", "sobol", "maximin"],
                    help="exploration points: sobol_only (Sobol without a centre point, the seed's "
                         "Fig. 2 study; default), or a lab session's sobol/maximin (centre first)")
    st.add_argument("--n-candidates", type=_int, default=1024,
                    help="EI candidates per proposal (1024)")
    # 1 is 1.6x faster, but it changed the fixed method's y_T beyond noise on the 6-D functions
    # (docs/results.md, "Stopping benchmarks"; the campaign of 2026-12-05 in its git history).
    st.add_argument("--n-local", type=_int, default=3,
                    help="best candidates refined by SLSQP per proposal, as hilbo run does (3)")
    st.add_argument("--prior-mean-sd", type=float, default=0.0, metavar="K",
                    help="the GP's prior mean for every method, K SDs of the observations above "
                         "their average, 0-3 (0: Kim et al. 2019's GP, default; 0.5: a lab "
                         "session's with the sound rules)")
    st.add_argument("--seed", type=_int, default=0, help="seed of the first trial (0)")
    # 1.25, not the optimizer's 1.0: the same y_t within noise, expensive adaptive trials ≈ 8×
    # cheaper (docs/results.md, "Stopping benchmarks"; the measurement is in its git history).
    st.add_argument("--refit-growth", type=float, default=1.25, metavar="G",
                    help="refit the GP hyperparameters once the observations have grown by the "
                         "factor G since the last fit, else re-condition with the last ones; the "
                         "same for every method (1 = at every proposal, as hilbo run does; "
                         "default 1.25)")
    st.add_argument("--grid-step", type=_int, default=1, help="keep y_t every k measurements (1)")
    st.add_argument("--out", default="runs/bench/stopping", help="output directory")
    st.add_argument("--resume", action="store_true",
                    help="keep the trials already in OUT/trials.jsonl and run only the missing ones")
    st.add_argument("--summarize-only", action="store_true",
                    help="run nothing: summarise the trials of this campaign found in OUT/trials.jsonl")
    st.add_argument("--merge", action="append", metavar="DIR",
                    help="with --summarize-only: also read DIR/trials.jsonl (repeatable), e.g. the "
                         "directories of campaigns run in parts or on several machines")
    _add_executor_args(st)
    st.set_defaults(func=_cmd_stopping)

    from bridge.bench.methods import DEFAULT_HIL_METHODS, HIL_METHODS

    defaults = ",".join(DEFAULT_HIL_METHODS)
    others = ",".join(m for m in HIL_METHODS if m not in DEFAULT_HIL_METHODS)
    hil = bsub.add_parser(
        "hil", help="whole simulated sessions: stopping BO, fixed BO, CMA-ES, random search",
        description="Whole HIL sessions on simulated wearers; regret of the recommended setting "
                    f"against minutes walked. Besides the default methods ({defaults}), adaptive-ahead "
                    "(adaptive with the GP hyperparameters fitted ahead, as hilbo run does) and "
                    "the Antonova 2016 ones: "
                    "adaptive-day2 (a second day, no prior), adaptive-prior and adaptive-prior-e3 "
                    "(day 2 with day 1's evaluations as a fast prior; E or 3 exploration points), "
                    "adaptive-features (kernel on raw parameters + force-profile features), "
                    "adaptive-features-only, adaptive-tuned-k (constant-K stopping, see --tuned-k).")
    hil.add_argument("--subjects", type=_int, default=10, help="subject seeds per space (10)")
    hil.add_argument("--seed", type=_int, default=1, help="first subject seed (1)")
    hil.add_argument("--spaces", default=None,
                     help="comma-separated, from hip_6d,hip_ankle_4d (default both)")
    hil.add_argument("--methods", default=None,
                     help=f"comma-separated, from {defaults} (the default) and {others}")
    hil.add_argument("--minutes", type=float, default=60.0, help="session length incl. warm-ups (60)")
    hil.add_argument("--warmup-s", type=float, default=180.0,
                     help="warm-up length (180 s; two warm-ups with the seed protocol and "
                          "CMA-ES/random, one with the fast protocol of sound)")
    hil.add_argument("--condition-s", type=float, default=120.0,
                     help="CMA-ES/random condition length (120 s)")
    hil.add_argument("--popsize", type=_int, default=8, help="CMA-ES generation size (8)")
    hil.add_argument("--sigma0", type=float, default=0.25, help="CMA-ES initial step in the unit cube (0.25)")
    hil.add_argument("--penalty-w", type=float, default=500.0,
                     help="CMA-ES constraint penalty, W per squared unit-cube distance (500)")
    hil.add_argument("--n-explore", type=_int, default=None,
                     help="BO exploration points (default: each method's protocol's: sound 3, the seed's 6)")
    hil.add_argument("--max-breaths", type=_int, default=45, help="BO's N (45)")
    hil.add_argument("--window", type=_int, default=2, help="BO's window W (2)")
    hil.add_argument("--grid-min", type=float, default=1.0, help="minutes grid of the summary (1)")
    hil.add_argument("--wearer", choices=WEARER_CHOICES, default=WearerKind.REALISTIC.value,
                     help="simulated wearer: realistic (default; breath noise and outliers as in "
                          "real data, tau 14-55 s, drift, slow adaptation, two landscape "
                          "families), noisy (breath CV 15-25 %%, 3 %% outliers), slow (tau 30-60 "
                          "s) or legacy (the earlier one; the Antonova 2016 methods need it)")
    hil.add_argument("--tuned-k", default="bo", metavar="bo|grid|K",
                     help="K of adaptive-tuned-k: bo = BO-RESAMPLE's recommendation, grid = the best "
                          "of an exhaustive grid, both tuned offline on the full-length trajectories "
                          "of --tune-subjects training wearers before the sessions; or a number (bo)")
    hil.add_argument("--tune-subjects", type=_int, default=10, help="training wearers for --tuned-k (10)")
    hil.add_argument("--tune-seed", type=_int, default=101,
                     help="first training wearer seed, disjoint from the subjects (101)")
    hil.add_argument("--error-weight", type=nonnegative, default=2.0,
                     help="tuning cost of a wrong early stop, in evaluations (2)")
    hil.add_argument("--out", default="runs/bench/hil", help="output directory")
    hil.add_argument("--resume", action="store_true",
                     help="keep the sessions already in OUT/sessions.jsonl and run only the missing ones")
    hil.add_argument("--summarize-only", action="store_true",
                     help="run nothing: summarise the sessions of this run found in OUT/sessions.jsonl")
    _add_executor_args(hil)
    hil.set_defaults(func=_cmd_hil)

    pf = bsub.add_parser("perf",
                         help="compute latency: breath, proposal, whole session; the bridge at real time",
                         description="Latency of one breath, one proposal and a 60-minute simulated session. "
                                     "With --bridge-minutes M > 0 also the bridge at real time: an "
                                     "M-minute hilbo-sim session at speed 1 (hip_6d, 2 actuators × 1 kHz "
                                     "force feedback; --bridge-protocol quick: 2 exploration points, N = 10, "
                                     "20 s warm-ups, or lab: 3, N = 45, 180 s) reporting "
                                     "stop decision → device ack latency, feedback frames sent / received / "
                                     "lost / logged, the achieved feedback rate and the process's CPU in "
                                     "cores (devices included: an upper bound); also written to "
                                     "OUT/perf_bridge.json and OUT/perf_bridge_table.md, the session's log "
                                     "to OUT/bridge_session/.")
    pf.add_argument("--breaths", type=_int, default=1500, help="optimisation-phase breaths to time (1500)")
    pf.add_argument("--sizes", default="10,30,60,100", help="observation counts for proposals (10,30,60,100)")
    pf.add_argument("--reps", type=_int, default=20, help="timed proposals per size (20)")
    pf.add_argument("--sessions", type=_int, default=3, help="60-minute sessions to time (3)")
    pf.add_argument("--seed", type=_int, default=1, help="first seed (1)")
    pf.add_argument("--bridge-minutes", type=float, default=0.0, metavar="M",
                    help="also run the bridge at real time for M minutes of wall time (at least 2.4; "
                         "5 gives ~10 profile pushes; default 0 = skip)")
    pf.add_argument("--bridge-speed", type=float, default=1.0,
                    help="real-time factor of that session (1 = real time, where the latency targets hold; "
                         "more only for quick checks)")
    pf.add_argument("--bridge-feedback-hz", type=float, default=1000.0,
                    help="its force-feedback rate per actuator (1000 Hz)")
    pf.add_argument("--bridge-baseline-s", type=float, default=30.0, metavar="S",
                    help="then run the virtual exosuit alone for S s: the process's CPU minus the "
                         "device's estimates the bridge's own share (30; 0 = skip)")
    pf.add_argument("--bridge-gc", choices=[m.value for m in GcMode], default=GcMode.FREEZE.value,
                    help="that session's [protocol] gc: full garbage collections at quiet points "
                         "(freeze, the default) or whenever Python decides (automatic)")
    pf.add_argument("--bridge-protocol", choices=[p.value for p in BridgeProtocol],
                    default=BridgeProtocol.QUICK.value,
                    help="that session's protocol: quick (2 exploration points, N = 10, 20 s warm-ups: "
                         "many stop decisions per minute; the default) or lab (the lab's own: 3, "
                         "N = 45, 180 s warm-ups; needs --bridge-minutes of at least 11)")
    pf.add_argument("--out", default="runs/bench/perf", help="output directory")
    pf.set_defaults(func=_cmd_perf)

    from bridge.bench.estimator import add_estimator_bench_parser

    add_estimator_bench_parser(bsub)  # hilbo bench estimator

    from bridge.bench.pairs import add_pairs_bench_parser

    add_pairs_bench_parser(bsub)  # hilbo bench pairs

    from bridge.bench.watchdog import add_watchdog_bench_parser

    add_watchdog_bench_parser(bsub)  # hilbo bench watchdog: device silence -> AssistanceOff

    from bridge.bench.tutor import add_tutor_bench_parser

    add_tutor_bench_parser(bsub)  # hilbo bench tutor: Antonova 2016 §4
    for sub_parser in bsub.choices.values():
        sub_parser.set_defaults(func=_out_checked_first(sub_parser.get_default("func")))
    return bsub


def _out_checked_first(func: Any) -> Any:
    """A bench command that refuses an ``--out`` it could not write into before any work (as
    ``hilbo run`` and ``hilbo sim`` do): a campaign is not lost at its end for a typo."""
    from bridge.config import check_out_dir

    def run(args: argparse.Namespace) -> int:
        if getattr(args, "out", None) is not None:
            check_out_dir(args.out, "--out")
        return int(func(args))

    return run


def bench_main(argv: Sequence[str] | None = None) -> int:
    """Standalone entry point: ``argv`` is what follows ``hilbo bench``; same exit codes."""
    parser = argparse.ArgumentParser(prog="hilbo")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")
    add_bench_parser(sub)
    args = parser.parse_args(["bench", *(sys.argv[1:] if argv is None else argv)])
    logging.basicConfig(level=logging.WARNING)
    try:
        return int(args.func(args))
    except UsageError as err:
        sys.stderr.write(f"hilbo bench {args.bench_command}: error: {err}\n")
        return 2
    except (HilboError, BridgeError, DriverError) as err:
        # Bad input found once the work started, or a failed run: 1 (as ``hilbo bench``).
        sys.stderr.write(f"hilbo bench {args.bench_command}: error: {err}\n")
        return 1
    except OSError as err:
        # A file the benchmark writes (its --out after the check, e.g. a full disk).
        sys.stderr.write(f"hilbo bench {args.bench_command}: error: {err}\n")
        return 1
    except KeyboardInterrupt:
        sys.stderr.write(f"hilbo bench {args.bench_command}: interrupted\n")
        return 130


if __name__ == "__main__":
    sys.exit(bench_main())
