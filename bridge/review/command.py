"""``hilbo review`` itself: read a session (:mod:`bridge.review.session`), draw its plots
(:mod:`bridge.review.plots`) and write its report and tables (:mod:`bridge.review.report`).

The one module of the review that knows all three, so they never import each other.
"""

from __future__ import annotations

import argparse
import os
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from bridge.errors import ReviewError, UsageError
from bridge.review import plots as review_plots
from bridge.review import report as review_report
from bridge.review.session import CompareResult, ReviewResult, Session, load_session

__all__ = ["add_review_parser", "compare_sessions", "default_compare_dir", "default_review_dir",
           "review_session"]

#: ``hilbo review``'s exit status when a log is damaged inside (its files are still written).
_EXIT_DAMAGED = 1


def default_review_dir(first_log: str | os.PathLike[str]) -> Path:
    """``dir/name.mcap`` → ``dir/name-review/``."""
    p = Path(first_log)
    stem = p.stem if p.suffix == ".mcap" else p.name
    return p.with_name(stem + "-review")


def default_compare_dir(log_a: str | os.PathLike[str], log_b: str | os.PathLike[str]) -> Path:
    """``dirA/a.mcap``, ``dirB/b.mcap`` → ``dirA/compare-a-vs-b/``."""
    a, b = Path(log_a), Path(log_b)
    return a.with_name(f"compare-{a.stem}-vs-{b.stem}")


def _out_dir(out: str | os.PathLike[str]) -> Path:
    p = Path(out)
    try:
        p.mkdir(parents=True, exist_ok=True)
    except FileExistsError as err:
        raise ReviewError(f"--out {str(p)!r} exists and is not a directory; expected a directory") from err
    except OSError as err:
        raise ReviewError(f"--out {str(p)!r}: cannot create the output directory: {err.strerror}") from err
    if not os.access(p, os.W_OK):
        raise ReviewError(f"--out {str(p)!r}: the output directory is not writable")
    return p


def review_session(paths: Sequence[str | os.PathLike[str]],
                   out_dir: str | os.PathLike[str] | None = None) -> ReviewResult:
    """Review one session: plots, ``report.md``/``report.html``, ``evaluations.csv``, ``breaths.csv``.

    Args:
        paths: The session's log file(s) (a resumed session: the old file and the new one).
        out_dir: Output directory (default :func:`default_review_dir` of the first log).

    Returns:
        The files written (in order) and the data shown.

    Raises:
        ReviewError: Bad input or an unwritable output directory (the message names it).
    """
    session = load_session(paths)
    out = _out_dir(out_dir if out_dir is not None else default_review_dir(paths[0]))
    written: list[Path] = []
    plots, skipped = review_plots.session_plots(session, out)
    written.extend(plots.values())
    written.extend(review_report.write_report(session, out, plots, skipped))
    written.append(review_report.write_evaluations_csv(session, out / "evaluations.csv"))
    written.append(review_report.write_breaths_csv(session, out / "breaths.csv"))
    return ReviewResult(out, tuple(written), session, skipped)


def compare_sessions(log_a: str | os.PathLike[str] | Sequence[str | os.PathLike[str]],
                     log_b: str | os.PathLike[str] | Sequence[str | os.PathLike[str]],
                     out_dir: str | os.PathLike[str] | None = None) -> CompareResult:
    """Two sessions side by side: ``compare.png``, ``compare.md`` and ``compare.html``.

    Args:
        log_a: The first session's log, or its logs in order (a resumed session).
        log_b: The second session's log(s).
        out_dir: Output directory (default :func:`default_compare_dir`, next to A's last log).

    Raises:
        ReviewError: Bad input or an unwritable output directory.
    """
    logs_a = [log_a] if isinstance(log_a, str | os.PathLike) else list(log_a)
    logs_b = [log_b] if isinstance(log_b, str | os.PathLike) else list(log_b)
    a, b = load_session(logs_a), load_session(logs_b)
    out = _out_dir(out_dir if out_dir is not None else default_compare_dir(logs_a[-1], logs_b[-1]))
    png = review_plots.compare_plot((a, b), out / "compare.png")
    written = [png, *review_report.write_compare_report((a, b), out, png)]
    return CompareResult(out, tuple(written), (a, b))


# ---------------------------------------------------------------------------------- CLI
def add_review_parser(subparsers: Any) -> argparse.ArgumentParser:
    """Register ``hilbo review`` on the top-level ``add_subparsers()`` object (sets ``func``)."""
    p = subparsers.add_parser(
        "review", help="plots, a report and CSV tables of a session from its log",
        description="Review a session from its MCAP log: PNG plots (breath-by-breath power with the "
                    "session's estimate and its pauses, best so far against minutes walked, "
                    "parameters per evaluation, threshold "
                    "schedule, desired vs measured force of the recommended setting), report.md and "
                    "report.html (self-contained), evaluations.csv and breaths.csv. Give both files of a "
                    "session resumed after a crash to review it as one; a log cut off by a crash is read "
                    "up to its last intact record. With --compare, two sessions side by side. Prints the "
                    "path of every file written.")
    p.add_argument("logs", nargs="+", metavar="LOG.mcap",
                   help="the session log(s); with --compare exactly two sessions, a resumed session's "
                        "logs joined by a comma (A0.mcap,A.mcap)")
    p.add_argument("--compare", action="store_true",
                   help="compare two sessions: compare.png, compare.md, compare.html")
    p.add_argument("--out", metavar="DIR", default=None,
                   help="output directory (default: LOG-review/ next to the first log, e.g. "
                        "runs/sim/session-review/; with --compare: compare-A-vs-B/ next to A)")
    p.set_defaults(func=_cmd_review)
    return p


def _cmd_review(args: argparse.Namespace) -> int:
    if args.compare:
        if len(args.logs) != 2:
            raise UsageError(f"--compare takes exactly two sessions (A.mcap B.mcap; a resumed session's "
                             f"logs joined by a comma, A0.mcap,A.mcap), got {len(args.logs)}")
        sides = [[x for x in arg.split(",") if x] for arg in args.logs]
        compared = compare_sessions(sides[0], sides[1], args.out)
        for tag, s, logs in zip("AB", compared.sessions, sides, strict=True):
            prev = s.files[0].previous_log if s.files else None
            if prev is not None:
                sys.stderr.write(f"hilbo review: warning: {tag} ({logs[0]}) resumed {prev}, which is not "
                                 f"in the comparison: give the session's logs joined by a comma "
                                 f"({prev},{logs[0]}) to compare all of it\n")
        files = compared.files
        sessions: Sequence[Session] = compared.sessions
    else:
        result = review_session(args.logs, args.out)
        files = result.files
        sessions = (result.session,)
    for s in sessions:
        for warning in s.warnings:  # a log left out as a copy of another given with it
            sys.stderr.write(f"hilbo review: warning: {warning}\n")
    for path in files:
        print(path)  # noqa: T201 (CLI output: one line per file written)
    damaged = [f for f in result.session.files if f.damage] if not args.compare else []
    for f in damaged:
        sys.stderr.write(f"hilbo review: warning: {f.path} is damaged inside the file: {f.damage}; what lies "
                         "after the damage was read and reviewed, the report lists the damage\n")
    return _EXIT_DAMAGED if damaged else 0
