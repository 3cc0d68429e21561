"""``hilbo validate``: the validation walk (bridge/validate.py) on the command line."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

import msgspec

__all__ = ["add_validate_parser"]


def _cmd_validate(args: argparse.Namespace) -> int:
    import asyncio
    import dataclasses

    from rich.console import Console

    from bridge.cli.session_end import ended_text, run_exit_status
    from bridge.config import check_out_dir, load_config
    from bridge.errors import UsageError
    from bridge.run import continued_by, keyboard_present, newest_log, run_session
    from bridge.validate import ValidationError, ValidationPlan, result_lines

    if (args.source is None) == (args.resume is None):
        given = "both were given" if args.source is not None else "neither was given"
        raise UsageError("give --from LOG (the optimisation session to validate) or --resume LOG "
                         f"(a validation walk to continue): one of them; {given}")
    console = Console(stderr=True, markup=False, highlight=False, soft_wrap=True)
    cfg = load_config(args.config)
    check_out_dir(args.out or cfg.session.out_dir, "--out" if args.out else "[session] out_dir",
                  create=True)
    if args.live:
        cfg = dataclasses.replace(cfg, live=msgspec.structs.replace(cfg.live, enabled=True))
    resume = Path(args.resume) if args.resume else None
    if resume is None:
        source = Path(args.source)
        # As hilbo run --resume refuses it: a log a later one continues holds only part of the
        # session, and so would the recommendation built from it.
        directories = {source.parent, Path(args.out or cfg.session.out_dir)}
        later = continued_by(source, directories)
        if later is not None:
            newest = newest_log(later, directories) or later
            raise ValidationError(f"{source} was continued by {later} (hilbo run --resume): its "
                                  "recommendation leaves out the rest of the session. Validate the "
                                  f"newest log of the session: hilbo validate CONFIG --from {newest}")
        plan = ValidationPlan.new(cfg, source)
    else:
        plan = ValidationPlan.resumed(cfg, resume)
    v = cfg.validation
    console.print(f"hilbo validate: {cfg.source} (subject {cfg.session.subject}), the recommendation of "
                  f"{plan.source_log}; {len(plan.conditions)} conditions of {v.condition_min:g} min "
                  f"({v.condition_breaths} breaths) in the order "
                  + ", ".join(c.name for c in plan.conditions) + f" (seed {v.seed})", highlight=False)
    if v.generic is None:
        console.print("hilbo validate: note: no [validation] generic setting: OPT against unassisted"
                      + (" and zero-force walking" if v.zero_force else " only"))
    if (args.auto_resume is None and cfg.watchdog.auto_resume_s is None
            and not keyboard_present(not args.no_view)):
        console.print("hilbo validate: note: no keyboard: a pause lasts until SIGTERM/Ctrl-C; give "
                      "--auto-resume S or set [watchdog] auto_resume_s")
    result = asyncio.run(run_session(cfg, resume=resume, out_dir=Path(args.out) if args.out else None,
                                     operator_view=not args.no_view, auto_resume_s=args.auto_resume,
                                     validation=plan))
    summary: dict[str, Any] = result.summary
    console.print(ended_text(summary).splitlines()[0])  # a walk recommends nothing (label_summary)
    for line in result_lines(summary.get("validation") or []):
        console.print(line)
    print(result.log_path)
    print(result.summary_path)
    return run_exit_status(summary)


def add_validate_parser(subparsers: Any) -> argparse.ArgumentParser:
    """Register ``hilbo validate`` on the top-level ``add_subparsers()`` object."""
    from bridge.argtypes import seconds
    from bridge.cli.session_end import VALIDATE_EXIT_STATUS

    p = subparsers.add_parser(
        "validate", help="the validation walk: the recommended setting vs a generic one vs unassisted",
        description="Measure the recommended setting of an optimisation session (its log, --from), "
                    "the generic setting of [validation] generic, unassisted walking (assistance "
                    "off) and, with [validation] zero_force = true, zero-force walking (the suit "
                    "actuated, 0 N at every point), each for "
                    "[validation] condition_min minutes in a randomised order ([validation] seed), "
                    "with the session's estimator and cart, as hilbo run measures (the same "
                    "safety limits, pauses, keys and resume policy). Prints each condition's "
                    "estimate with its 95 % interval and its reduction against unassisted walking; "
                    "the log and the summary hold them, and hilbo review reports them.",
        epilog=VALIDATE_EXIT_STATUS)
    p.add_argument("config", help="the session config (with a [validation] table)")
    p.add_argument("--from", dest="source", metavar="LOG.mcap", default=None,
                   help="the optimisation session whose recommendation is validated")
    p.add_argument("--resume", metavar="LOG.mcap", default=None,
                   help="continue a validation walk cut off by a crash or a stop (its measured "
                        "conditions are kept)")
    p.add_argument("--out", default=None, help="output directory (default: [session] out_dir)")
    p.add_argument("--no-view", action="store_true", help="no live terminal view (as hilbo run)")
    p.add_argument("--auto-resume", type=seconds, default=None, metavar="S",
                   help="the resume policy, as hilbo run --auto-resume")
    p.add_argument("--live", action="store_true", help="stream the walk to Foxglove (as hilbo run --live)")
    p.set_defaults(func=_cmd_validate)
    return p
