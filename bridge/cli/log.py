"""``hilbo log``: inspect and repair session logs.

``hilbo log info LOG.mcap [--json]``
    Channels and message counts, time range, session id, the log it resumes, whether the file
    was closed normally or cut off (and how many bytes were lost).
``hilbo log recover IN.mcap [OUT.mcap] [--force]``
    Rewrite the intact part of a log cut off by a crash (or damaged inside) as a normal, indexed
    MCAP file (default ``IN.recovered.mcap``) that Foxglove and any MCAP reader open. A log that
    was closed normally and is intact needs none: that is said, and no copy is written.

Errors (not an MCAP file, an empty file, another program's MCAP, an unwritable output) print
one line naming the file and the problem and exit with status 1; no traceback.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import sys
from pathlib import Path
from typing import Any

from bridge.log import LogError, Topic
from bridge.log.reader import LogContents, read_log, recover

__all__ = ["add_log_parser", "default_recovered_path", "log_info"]

_EXIT_ERROR = 1  # bad input; 2 is argparse's, for a wrong command line


def add_log_parser(subparsers: Any) -> argparse.ArgumentParser:
    """Register ``hilbo log {info,recover}`` on the top-level ``add_subparsers()`` object.

    Each action sets ``func`` (``args.func(args) -> int`` is the exit status).
    """
    log = subparsers.add_parser(
        "log", help="inspect a session log or repair one cut off by a crash",
        description="Inspect a session's MCAP log, or rewrite one cut off by a crash as a normal "
                    "indexed MCAP file.")
    actions = log.add_subparsers(dest="log_command", required=True, metavar="ACTION")
    info = actions.add_parser("info", help="channels, message counts, time range, session and linked log",
                              description="Summarise a session log (works on a crashed, truncated file).")
    info.add_argument("log", metavar="LOG.mcap", help="the session log")
    info.add_argument("--json", action="store_true", help="print the summary as JSON")
    info.set_defaults(func=_cmd_info)
    rec = actions.add_parser("recover", help="rewrite a crashed log as a normal indexed MCAP file",
                             description="Copy every intact message of IN (a log cut off by a crash) "
                                         "into OUT, a normal indexed MCAP file. A log closed normally "
                                         "and intact needs no recovery: said, and no copy written.")
    rec.add_argument("input", metavar="IN.mcap", help="the damaged log")
    rec.add_argument("output", metavar="OUT.mcap", nargs="?", default=None,
                     help="where to write (default: IN.recovered.mcap next to IN)")
    rec.add_argument("--force", action="store_true", help="overwrite OUT if it exists")
    rec.set_defaults(func=_cmd_recover)
    return log


def default_recovered_path(src: str | Path) -> Path:
    """``dir/name.mcap`` → ``dir/name.recovered.mcap``."""
    p = Path(src)
    stem = p.stem if p.suffix == ".mcap" else p.name
    return p.with_name(stem + ".recovered.mcap")


def log_info(contents: LogContents) -> dict[str, Any]:
    """The ``hilbo log info`` summary as a JSON-able dict."""
    rng = contents.time_range_ns
    snaps = contents.records(Topic.OPTIMIZER_STATE)
    breaths = contents.records(Topic.BREATHS)
    return {
        "path": contents.path,
        "size_bytes": contents.size_bytes,
        "complete": contents.complete,
        "unreadable_bytes": contents.unreadable_bytes,
        "stop_reason": contents.stop_reason,
        "damage": [{"start": d.start, "end": d.end, "reason": d.reason} for d in contents.damage],
        "format_version": contents.format_version,
        "session_id": contents.session_id,
        "previous_log": contents.previous_log,
        "library": contents.library,
        "time_range_ns": list(rng) if rng else None,
        "duration_s": (rng[1] - rng[0]) / 1e9 if rng else None,
        # The breaths' clock (the cart's: walked time; at `hilbo sim --speed X` the log's wall
        # time is X times shorter). Its zero is wherever the cart's clock started.
        "breath_time_s": ([min(b.t_s for b in breaths), max(b.t_s for b in breaths)]
                          if breaths else None),
        "channels": {t: {"schema": c.schema_name, "encoding": c.message_encoding,
                         "messages": c.message_count} for t, c in sorted(contents.channels.items())},
        "messages": sum(c.message_count for c in contents.channels.values()),
        "evaluations": len(contents.topic(Topic.OBSERVATIONS)),
        "last_snapshot_evaluations": snaps[-1].n_evaluations if snaps else None,
    }


def _fmt_time(ns: int) -> str:
    return dt.datetime.fromtimestamp(ns / 1e9, tz=dt.UTC).strftime("%Y-%m-%d %H:%M:%S.%f")[:-3] + " UTC"


def _info_text(s: dict[str, Any]) -> str:
    lines = [f"{s['path']}: {s['size_bytes']:,} bytes, "
             + ("closed normally" if s["complete"] else
                f"TRUNCATED ({s['unreadable_bytes']:,} bytes unreadable: {s['stop_reason']})")]
    lines += [f"DAMAGED: bytes {d['start']:,}–{d['end']:,} skipped ({d['reason']}); read on after them"
              for d in s["damage"]]
    chain = f" (resumes {s['previous_log']})" if s["previous_log"] else ""
    lines.append(f"session:    {s['session_id'] or '?'}{chain}")
    lines.append(f"written by: {s['library'] or '?'} (log format {s['format_version'] or '?'})")
    rng = s["time_range_ns"]
    if rng:
        lines.append(f"log time:   {_fmt_time(rng[0])} – {_fmt_time(rng[1])} "
                     f"({s['duration_s'] / 60:.1f} min)")
    walked = s["breath_time_s"]
    if walked:
        lines.append(f"walked:     {(walked[1] - walked[0]) / 60:.1f} min of breaths (breath clock "
                     f"{walked[0] / 60:.1f} – {walked[1] / 60:.1f} min)")
    lines.append(f"evaluations completed: {s['evaluations']}")
    width = max([len(t) for t in s["channels"]] + [7])
    lines.append(f"{'channel':<{width}}  {'schema':<24} {'messages':>9}")
    for topic, c in s["channels"].items():
        lines.append(f"{topic:<{width}}  {c['schema']:<24} {c['messages']:>9,}")
    lines.append(f"{'total':<{width}}  {'':<24} {s['messages']:>9,}")
    return "\n".join(lines)


def _say(text: str) -> None:
    print(text)


def _fail(action: str, err: Exception) -> int:
    print(f"hilbo log {action}: error: {err}", file=sys.stderr)
    return _EXIT_ERROR


def _cmd_info(args: argparse.Namespace) -> int:
    try:
        # Decode only the small channels; counts come from every channel.
        contents = read_log(args.log, topics=[Topic.CONFIG, Topic.OBSERVATIONS, Topic.OPTIMIZER_STATE,
                                              Topic.EVENTS, Topic.BREATHS])
    except LogError as err:
        return _fail("info", err)
    summary = log_info(contents)
    _say(json.dumps(summary, indent=2) if args.json else _info_text(summary))
    return 0


def _cmd_recover(args: argparse.Namespace) -> int:
    out = Path(args.output) if args.output else default_recovered_path(args.input)
    try:
        # Decode nothing: only whether the file was closed normally and is intact.
        source = read_log(args.input, topics=(), require_hilbo=False)
        if source.complete and not source.damaged:
            # A copy would be the same log again, and a second file of one session beside it.
            _say(f"{args.input} was closed normally and is intact: nothing to recover, no copy written "
                 "(it opens as it is in hilbo review, Foxglove and any MCAP reader)")
            return 0
        report = recover(args.input, out, overwrite=args.force)
    except LogError as err:
        return _fail("recover", err)
    state = ("was closed normally but is damaged inside" if report.source_complete else
             f"was cut off: {report.unreadable_bytes:,} bytes unreadable ({report.stop_reason})")
    state += "".join(f"\n  damaged inside: {d.describe()}" for d in report.damage)
    topics = ", ".join(f"{t} {n}" for t, n in sorted(report.per_topic.items()))
    _say(f"{report.src} {state}\nwrote {report.messages:,} messages to {report.dst}"
         + (f"\n  {topics}" if topics else ""))
    return 0
