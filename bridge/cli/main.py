"""The ``hilbo`` command line."""

from __future__ import annotations

import argparse
import contextlib
import io
import logging
import os
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

import msgspec

from bridge.argtypes import minutes, nonnegative_int, seconds
from bridge.cli.session_end import EXIT_INTERRUPTED, RUN_EXIT_STATUS, ended_text, run_exit_status

# The GP's matrices are small (tens to a few hundred rows): multi-threaded BLAS only adds
# contention there (measured: proposal p95 61 ms threaded vs 28 ms single-threaded on 2 cores).
# Set before numpy is first imported; a user's explicit setting wins.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

__all__ = ["main"]

if TYPE_CHECKING:
    from bridge.operator_view import ConsoleGuard
    from bridge.runtime import BridgeSession


def _speed(text: str) -> float | None:
    if text == "max":
        return None
    try:
        value = float(text)
    except ValueError as err:
        raise argparse.ArgumentTypeError(f"speed must be 'max' or a positive number, got {text!r}") from err
    if not value > 0:
        raise argparse.ArgumentTypeError(f"speed must be 'max' or a positive number, got {text!r}")
    return value


def _check_sim_minutes(args: argparse.Namespace, cfg: Any) -> None:
    """A session too short for the protocol is a wrong command line: said before anything
    starts or any directory is made."""
    from bridge.errors import UsageError
    from hilbo_core.errors import ConfigError

    try:
        cfg.budget_min  # noqa: B018 - the property checks that the minutes leave an optimisation
    except ConfigError as err:
        raise UsageError(f"--minutes {args.minutes:g}: {err}") from err


def _version() -> str:
    from importlib import metadata

    try:
        return metadata.version("hilbo")
    except metadata.PackageNotFoundError:  # a checkout on PYTHONPATH, not installed
        return "unknown (not installed)"


def _cmd_sim(args: argparse.Namespace) -> int:
    from bridge.errors import UsageError

    if args.processes and args.engine == "core":
        raise UsageError("--processes runs the virtual devices as processes; --engine core has none")
    if args.bus is not None and not args.processes:
        raise UsageError("--bus goes with --processes (in one process the devices share "
                                "python-can's virtual bus)")
    if args.live and (args.engine == "core" or args.processes):
        raise UsageError("--live streams the in-process bridge session (without --processes "
                         "and --engine core)")
    if args.engine == "core":
        return _cmd_sim_core(args)
    import asyncio

    from rich.console import Console

    from bridge.config import LiveConfig, check_out_dir
    from bridge.sim.virtual import MAX_SPEED, VirtualSimConfig, run_virtual_sim

    console = Console(stderr=True, markup=False, highlight=False, soft_wrap=True)
    cfg = VirtualSimConfig(minutes=args.minutes, seed=args.seed, speed=args.speed,
                           preset=args.preset, stopping=args.stopping, wearer=args.wearer)
    _check_sim_minutes(args, cfg)
    out = check_out_dir(args.out, "--out")
    speed = cfg.speed or MAX_SPEED
    where = "the virtual exosuit and cart"
    if args.processes:
        from bridge.sim.processes import resolve_bus, run_process_sim

        bus = resolve_bus(args.bus or "auto")
        where += f" as processes ({'SocketCAN vcan0' if bus == 'vcan' else 'python-can-remote'})"
    # The clock skips the waits for breaths, so the session takes less than minutes/speed, plus
    # the proposal worker's start (seconds; more on a busy PC).
    console.print(f"hilbo sim: {cfg.minutes:g}-minute {cfg.preset} session on {where}, {cfg.wearer} "
                  f"wearer seed {cfg.seed}, "
                  f"{speed:g}x real time (under {cfg.minutes * 60 / speed:.0f} s of session time)")
    if args.processes:
        summary = asyncio.run(run_process_sim(cfg, out, bus=bus, operator_view=console.is_terminal))
    else:
        live = LiveConfig(enabled=True) if args.live else None
        if live is not None:
            console.print(f"hilbo sim: live view on ws://{live.host}:{live.port} (Foxglove: Open connection)")
        summary = asyncio.run(run_virtual_sim(cfg, out, operator_view=console.is_terminal, live=live))
    _print_done(console, summary)
    print(out / "summary.json")
    print(out / "session.mcap")
    return EXIT_INTERRUPTED if summary.get("end_reason") == "interrupted" else 0


def _print_done(console: Any, summary: dict[str, Any]) -> None:
    best = summary.get("best_mean")
    if "recommendation" in summary:  # the bridge's session: the same last lines as hilbo run's
        console.print(ended_text(summary))
    line = (f"done: {summary['n_evaluations']} evaluations ({summary['n_early_stops']} early stops) "
            f"in {summary['wall_time_s']:.1f} s wall")
    if best is not None and "true_cost_of_best" in summary:
        line += (f"; recommended {best:.1f} W estimated, {summary['true_cost_of_best']:.1f} W true vs "
                 f"optimum {summary['true_optimum']['cost_w']:.1f} W (regret {summary['regret_w']:.1f} W)")
    console.print(line)


def _cmd_run(args: argparse.Namespace) -> int:
    from bridge.operator_view import console_guard

    # A console that closes (`hilbo run ... | tee run.log`, tee killed) must not end a session
    # with a person walking in the suit: what is printed after it is dropped, the log records it.
    with console_guard() as guard:
        return _run(args, guard)


def _run(args: argparse.Namespace, guard: ConsoleGuard) -> int:
    import asyncio
    import dataclasses

    from rich.console import Console

    from bridge.config import check_cart_file, check_out_dir, config_warnings, load_config
    from bridge.run import keyboard_present, run_session

    console = Console(stderr=True, markup=False, highlight=False, soft_wrap=True)
    cfg = load_config(args.config)
    for warning in config_warnings(cfg):
        print(f"hilbo run: warning: {warning}", file=sys.stderr)
    check_out_dir(args.out or cfg.session.out_dir, "--out" if args.out else "session.out_dir",
                  create=True)
    # A replayed cart file is read as `hilbo config check` reads it before the session starts:
    # a file that does not fit [cart] is refused without a log of nothing.
    if check_cart_file(cfg, io.StringIO(), sys.stderr, prog="hilbo run") != 0:
        return 1
    if args.live:
        cfg = dataclasses.replace(cfg, live=msgspec.structs.replace(cfg.live, enabled=True))
    if cfg.live.enabled:
        console.print(f"hilbo run: live view on ws://{cfg.live.host}:{cfg.live.port} "
                      "(Foxglove: Open connection)")
    resume = Path(args.resume) if args.resume else None
    console.print(f"hilbo run: {cfg.source} (subject {cfg.session.subject})"
                  + (f", resuming {resume}" if resume else ""))
    if (args.auto_resume is None and cfg.watchdog.auto_resume_s is None
            and not keyboard_present(not args.no_view)):
        console.print("hilbo run: note: no keyboard (--no-view, or stdin or stderr not a terminal): "
                      "any pause (the one between the bouts too) lasts until SIGTERM/Ctrl-C; give "
                      "--auto-resume S or set [watchdog] auto_resume_s")

    def on_session(session: BridgeSession) -> None:
        guard.record_to(session.log)  # a console lost from now on is named in the log
        # Said at the start: after a crash (kill -9) the log to resume is named on the screen.
        console.print(f"hilbo run: log {session.log.path}")

    result = asyncio.run(run_session(cfg, resume=resume, out_dir=Path(args.out) if args.out else None,
                                     operator_view=not args.no_view, auto_resume_s=args.auto_resume,
                                     on_session=on_session))
    console.print(ended_text(result.summary))
    print(result.log_path)
    print(result.summary_path)
    return run_exit_status(result.summary)


def _cmd_sim_core(args: argparse.Namespace) -> int:
    from rich.console import Console

    from bridge.run import write_json_atomic
    from bridge.sim.core import SimConfig, SimEvaluation, run_insim
    from hilbo_core import HILOptimizer

    console = Console(stderr=True, markup=False, highlight=False, soft_wrap=True)
    cfg = SimConfig(minutes=args.minutes, seed=args.seed, speed=args.speed, preset=args.preset,
                    stopping=args.stopping, wearer=args.wearer)
    _check_sim_minutes(args, cfg)
    from bridge.config import check_out_dir

    out = check_out_dir(args.out, "--out")
    out.mkdir(parents=True, exist_ok=True)

    def progress(rec: SimEvaluation, opt: HILOptimizer) -> None:
        e = rec.evaluation
        mark = "stopped early" if e.stopped_early else e.reason
        console.print(
            f"[{rec.t_end / 60:5.1f} min] eval {e.index + 1:3d} {e.phase:12s} "
            f"{e.mean:7.1f} ± {e.var ** 0.5:5.1f} W  {e.breaths:2d} breaths  {mark}"
        )

    console.print(f"hilbo sim: {cfg.minutes:g}-minute {cfg.preset} session, seed {cfg.seed}, "
                  f"speed {'max' if cfg.speed is None else cfg.speed}")
    summary = run_insim(cfg, on_evaluation=progress)
    path = out / "summary.json"
    write_json_atomic(path, summary)
    _print_done(console, summary)
    print(path)
    return 0


def _cmd_vcan_setup(args: argparse.Namespace) -> int:
    from drivers.exosuit.vcan_setup import persistent_vcan_files, setup_script

    if args.persistent:
        for name, text in persistent_vcan_files(args.iface).items():
            print(f"# ---- {name}")
            print(text)
    else:
        print(setup_script(args.iface, bitrate=args.bitrate))
    return 0


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of every subcommand."""
    parser = argparse.ArgumentParser(
        prog="hilbo",
        description="Human-in-the-loop Bayesian optimisation of soft-exosuit assistance.",
    )
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more log output")
    parser.add_argument("--version", action="version", version=f"hilbo {_version()}")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    sim = sub.add_parser("sim", help="run a whole session on the virtual exosuit and cart",
                         description="Run a whole HIL session: the bridge drives the virtual exosuit "
                                     "(python-can virtual bus) and the virtual cart (TCP on loopback) "
                                     "with a simulated wearer; writes DIR/session.mcap and "
                                     "DIR/summary.json. --processes runs the two devices as processes "
                                     "of their own (SocketCAN vcan0 or python-can-remote, see --bus). "
                                     "--engine core runs the optimizer against the "
                                     "wearer directly, without devices or log (fastest).")
    sim.add_argument("--minutes", type=minutes, default=60.0,
                     help="session length in minutes of walking, up to 600 (default 60); it must leave "
                          "at least a minute of optimisation after the warm-up and the exploration "
                          "bout, which take about 10 minutes with the default rule (20 with "
                          "--stopping adaptive or fixed, the seed's protocol)")
    sim.add_argument("--speed", type=_speed, default=None,
                     help="'max' (default; 100x with the devices, unlimited with --engine core) "
                          "or a real-time factor such as 1 or 10")
    sim.add_argument("--seed", type=nonnegative_int, default=1,
                     help="subject and optimizer seed, >= 0 (default 1)")
    sim.add_argument("--out", default="runs/sim", help="output directory (default runs/sim)")
    sim.add_argument("--preset", default="hip_6d", choices=["hip_6d", "hip_ankle_4d"],
                     help="parameter space (default hip_6d)")
    sim.add_argument("--wearer", default="realistic", choices=["realistic", "noisy", "slow", "legacy"],
                     help="simulated wearer: realistic (default; breath noise and outliers as in "
                          "real data, tau 14-55 s, drift, slow adaptation, two landscape families), "
                          "noisy (breath CV 15-25 %%, 3 %% outliers), slow (tau 30-60 s) or legacy "
                          "(the earlier one)")
    sim.add_argument("--stopping", default="sound", choices=["sound", "sound-floor", "adaptive", "fixed"],
                     help="stopping rule in the optimisation phase: sound (default), sound-floor (it "
                          "on a fixed 60 s clock, the earlier default), adaptive "
                          "(Kim et al. 2019's Algorithm 1/2 with the σ-scaled rule) or fixed (N breaths)")
    sim.add_argument("--engine", default="bridge", choices=["bridge", "core"],
                     help="bridge (default): the whole system over real transports; core: the "
                          "optimizer and the wearer only")
    sim.add_argument("--processes", action="store_true",
                     help="run the virtual exosuit and cart as processes of their own (children of "
                          "hilbo, always stopped at the end), on a CAN bus shared between processes")
    sim.add_argument("--bus", choices=["auto", "vcan", "remote"], default=None,
                     help="with --processes: vcan = SocketCAN vcan0; remote = a python-can-remote "
                          "server started on 127.0.0.1; auto (default) = vcan0 where it exists, "
                          "else remote")
    sim.add_argument("--live", action="store_true",
                     help="stream the session to Foxglove on ws://127.0.0.1:8765 (docs/review.md: Live view)")
    sim.set_defaults(func=_cmd_sim)

    run = sub.add_parser("run", help="run a lab session from a config file",
                         description="Run a HIL session: read the cart, estimate, stop, propose and "
                                     "push profiles to the exosuit as CONFIG.toml says. Keys in the "
                                     "live view: p pause (assistance off), r resume, q stop; Ctrl-C "
                                     "stops safely too.",
                         epilog=RUN_EXIT_STATUS)
    run.add_argument("config", help="the session config (see: hilbo config example)")
    run.add_argument("--resume", metavar="LOG.mcap", default=None,
                     help="continue the session of this log (also one cut off by a crash) in a new log")
    run.add_argument("--out", default=None, help="output directory (default: [session] out_dir)")
    run.add_argument("--no-view", action="store_true",
                     help="no live terminal view: one line per evaluation and per pause, resume "
                          "or refusal on stderr")
    run.add_argument("--auto-resume", type=seconds, default=None, metavar="S",
                     help="the resume policy: end any pause the operator did not ask for (between "
                          "the bouts, lost heartbeat, silent cart) once the device and the cart "
                          "have been healthy for S seconds, at most [watchdog] max_auto_resumes "
                          "times, then stop (default: [watchdog] auto_resume_s, else wait for r)")
    run.add_argument("--live", action="store_true",
                     help="stream the session to Foxglove (as [live] enabled = true; docs/review.md)")
    run.set_defaults(func=_cmd_run)

    from bridge.config import add_config_parser

    add_config_parser(sub)

    from bridge.cli.validate import add_validate_parser

    add_validate_parser(sub)

    from bridge.bench.cli import add_bench_parser
    from bridge.bench.tune_stopping import add_tune_stopping_parser
    from bridge.cli.log import add_log_parser

    add_bench_parser(sub)
    add_tune_stopping_parser(sub)

    add_log_parser(sub)

    from bridge.cli.cart import add_cart_parser

    add_cart_parser(sub)

    from bridge.review.command import add_review_parser

    add_review_parser(sub)

    from bridge.sim.devices import add_virtual_cart_parser, add_virtual_exosuit_parser

    add_virtual_cart_parser(sub)
    add_virtual_exosuit_parser(sub)

    vcan = sub.add_parser(
        "vcan-setup", help="print the shell commands that bring up a (v)can interface",
        description="Print a shell script that creates and brings up a virtual CAN interface (vcanN) "
                    "or configures a real one (canN) with a bitrate. Run it as root: "
                    "hilbo vcan-setup | sudo sh")
    vcan.add_argument("iface", nargs="?", default="vcan0", help="interface name (default vcan0)")
    vcan.add_argument("--bitrate", type=int, default=1_000_000,
                      help="bitrate for a real canN interface (default 1000000)")
    vcan.add_argument("--persistent", action="store_true",
                      help="print systemd-networkd files that create it at every boot instead")
    vcan.set_defaults(func=_cmd_vcan_setup)
    return parser


def _innermost_parser(parser: argparse.ArgumentParser, argv: Sequence[str]) -> argparse.ArgumentParser:
    """The (sub)parser the command line names: ``hilbo bench stopping ...`` -> its parser."""
    for token in argv:
        sub = next((a for a in parser._actions if isinstance(a, argparse._SubParsersAction)), None)
        if sub is None:
            break
        if token in sub.choices:
            parser = sub.choices[token]
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``hilbo`` console script."""
    from bridge.errors import BridgeError, UsageError, first_leaf
    from drivers.errors import DriverError
    from hilbo_core.errors import HilboError

    parser = build_parser()
    args, extra = parser.parse_known_args(argv)
    if extra:
        # Said by the subcommand's own parser, with its usage (argparse's top parser would
        # print the top-level usage for `hilbo sim --bogus`).
        _innermost_parser(parser, sys.argv[1:] if argv is None else argv).error(
            f"unrecognized arguments: {' '.join(extra)}")
    logging.basicConfig(level=logging.WARNING - 10 * min(args.verbose, 2),
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    try:
        return int(args.func(args))
    except UsageError as err:
        print(f"hilbo {args.command}: error: {err}", file=sys.stderr)
        return 2
    except (HilboError, BridgeError, DriverError) as err:
        # Bad input or a failure at run time: 1. Only argparse's usage errors are 2.
        print(f"hilbo {args.command}: error: {err}", file=sys.stderr)
        return 1
    except BaseExceptionGroup as group:
        # A session's task group wraps the error of the task that failed (the cart stream's
        # CartError or a column map's DriverConfigError): report that error, not a traceback.
        known = group.subgroup(lambda e: isinstance(e, HilboError | BridgeError | DriverError))
        if known is None:
            raise
        print(f"hilbo {args.command}: error: {first_leaf(known)}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(f"hilbo {args.command}: interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:
        # `hilbo review LOG | head`: the reader left; what was asked for is written. Point stdout
        # at /dev/null so the interpreter's own flush at exit does not raise again.
        with contextlib.suppress(OSError):
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 141
    except OSError as err:  # a file that cannot be written or read: its name, no traceback
        print(f"hilbo {args.command}: error: {err}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(main())
