"""``hilbo cart inspect FILE``: which cart format a file is and what a session would read from it."""

from __future__ import annotations

import argparse
import sys
from typing import Any, TextIO

from bridge.argtypes import positive_int

__all__ = ["add_cart_parser"]


def _cmd_inspect(args: argparse.Namespace, out: TextIO | None = None, err: TextIO | None = None) -> int:
    from drivers.cart.inspect import inspect_file
    from drivers.cart.stream import CartFormat
    from drivers.errors import DriverError

    out = out or sys.stdout
    err = err or sys.stderr
    try:
        report = inspect_file(args.file, CartFormat(args.format) if args.format else None)
    except DriverError as exc:
        err.write(f"hilbo cart inspect: error: {exc}\n")
        return 1
    except OSError as exc:
        err.write(f"hilbo cart inspect: error: cannot read {args.file}: {exc.strerror or exc}\n")
        return 1
    out.write(report.render(n=args.show) + "\n")
    if report.n_rejected and not report.records:
        err.write(f"hilbo cart inspect: error: every record of {args.file} is rejected as {report.format}\n")
        return 1
    return 0


def add_cart_parser(subparsers: Any) -> argparse.ArgumentParser:
    """Register ``hilbo cart inspect FILE [--format F] [--show N]``.

    Args:
        subparsers: The ``add_subparsers()`` object of the ``hilbo`` parser.

    Returns:
        The ``cart`` parser; the action sets ``func(args) -> exit code`` (0 ok, 1 unreadable or
        unknown format, or every record rejected).
    """
    from drivers.cart.stream import CartFormat

    parser = subparsers.add_parser(
        "cart", help="inspect a metabolic-cart export or recording",
        description="Tools for metabolic-cart files (drivers/cart/FORMAT.md).",
    )
    actions = parser.add_subparsers(dest="cart_action", required=True, metavar="ACTION")
    inspect = actions.add_parser(
        "inspect", help="which format a cart file is, what it maps and reads, and its [cart] table",
        description="Detect the format of a cart export (COSMED xlsx/CSV, CORTEX XML, Vyntus txt, "
                    "Parvo CSV) or hilbo-line recording; print the columns it maps to which fields "
                    "and units, the breaths it reads and rejects (by reason), the first and last "
                    "breaths, and the [cart] TOML table that replays it. Exit status 1 for an "
                    "unknown format or a file whose every record is rejected.",
    )
    inspect.add_argument("file", help="the export or recording")
    inspect.add_argument("--format", choices=[f.value for f in CartFormat if f is not CartFormat.CSV],
                         default=None, help="read as this format instead of detecting it")
    inspect.add_argument("--show", type=positive_int, default=3, metavar="N",
                         help="breaths to show at the start and at the end (default 3)")
    inspect.set_defaults(func=_cmd_inspect)
    return parser
