"""``hilbo virtual-cart``: the virtual metabolic cart as a process of its own.

::

    hilbo virtual-cart --transport tcp --port 0 --speed 10 --seed 3 --fault disconnect@120+10
    python -m virtual_hw.cli_cart ...        # the same, without the hilbo entry point

The first line on stdout says where to connect, machine-readably, and is flushed at once::

    serial /tmp/hilbo-vcart-k2j/cart.tty     # open with pyserial (a stable symlink to the pty)
    tcp 127.0.0.1 40123                      # connect (the cart is the server)
    udp 127.0.0.1 5005                       # the cart sends datagrams to this address

Logs go to stderr. SIGINT/SIGTERM stop the cart cleanly (exit status 0); so does the end of
``--minutes``. Bad options exit with status 2 and a message naming the option; a failure once
the cart runs (an address in use, a bus that cannot be opened) exits with status 1 and one line.

Clock: ``--speed 1`` is real time; ``--speed X`` runs X times faster; processes given the same
``--epoch`` (a Unix time) and ``--speed`` share one simulated clock (the virtual exosuit, the
bridge). ``--speed max`` runs as fast as the cart's reader takes the lines, and starts the
session when the first client attaches (UDP: at once).

Assistance: the wearer feels the profile the exosuit *applies*. In-process, the virtual exosuit
calls :meth:`VirtualCart.on_profile_applied`. A separate cart process learns it from the
exosuit's bus (``--can-interface``/``--can-channel``): it reassembles the pushed tables and
follows the device's active version (:class:`virtual_hw.exosuit.AppliedProfileListener`);
without those options its wearer walks unassisted. The feed is the :data:`ProfileFeed`
returned by :func:`profile_feed_from_args`.
"""

from __future__ import annotations

import argparse
import asyncio
import logging
import math
import sys
from collections.abc import Callable, Coroutine, Sequence
from typing import Any, TextIO

from drivers.cart import CartFormat
from drivers.errors import DriverError
from drivers.signals import stop_signal_handlers
from hilbo_core.errors import ConfigError, HilboError
from hilbo_core.presets import PRESETS, preset
from virtual_hw.cart import CART_FAULTS, CartLink, LinkKind, VirtualCart
from virtual_hw.clock import make_clock, parse_speed
from virtual_hw.errors import VirtualConfigError, VirtualHwError
from virtual_hw.faults import FaultSpec
from virtual_hw.wearer import WEARER_CHOICES, WearerKind, make_wearer

__all__ = [
    "ProfileFeed",
    "add_virtual_cart_parser",
    "configure_parser",
    "main",
    "profile_feed_from_args",
    "run_from_args",
    "serve",
]

_log = logging.getLogger(__name__)

ProfileFeed = Callable[[VirtualCart], Coroutine[Any, Any, None]]
"""Runs beside the cart and calls ``cart.on_profile_applied(profiles, t)`` whenever the exosuit
reports a newly applied profile (e.g. a CAN listener); it may run until cancelled."""

_DESCRIPTION = (
    "Serve a simulated wearer's breath-by-breath gas exchange like a metabolic cart, over a "
    "pseudo-terminal, a TCP server or UDP datagrams. Prints the address to connect to on the "
    "first line of stdout."
)


def _speed_arg(text: str) -> float:
    try:
        return parse_speed(text)
    except VirtualConfigError as err:
        raise argparse.ArgumentTypeError(str(err)) from err


def _fault_arg(text: str) -> FaultSpec:
    try:
        return CART_FAULTS.parse(text)
    except VirtualConfigError as err:
        raise argparse.ArgumentTypeError(str(err)) from err


def _minutes_arg(text: str) -> float:
    try:
        value = float(text)
    except ValueError as err:
        raise argparse.ArgumentTypeError(f"minutes must be a positive number, got {text!r}") from err
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"minutes must be a positive number, got {text!r}")
    return value


def _seed_arg(text: str) -> int:
    # Checked here, not by make_wearer, so the error names --seed (the wearer's own ConfigError
    # is reported as a --body-mass-kg error, the only other value it checks).
    if not text.strip().isdecimal():
        raise argparse.ArgumentTypeError(f"seed must be a non-negative integer, got {text!r}")
    return int(text)


def configure_parser(parser: argparse.ArgumentParser) -> argparse.ArgumentParser:
    """Add the virtual cart's options to ``parser`` (shared by the subcommand and ``main``)."""
    parser.add_argument("--transport", choices=[k.value for k in LinkKind], default=LinkKind.TCP.value,
                        help="serial (a pty it creates), tcp (a server) or udp (default tcp)")
    parser.add_argument("--host", default="127.0.0.1",
                        help="tcp: address to listen on; udp: address to send to (default 127.0.0.1)")
    parser.add_argument("--port", type=int, default=0,
                        help="tcp: port to listen on, 0 = any free one (default); udp: destination port")
    parser.add_argument("--format", choices=[f.value for f in CartFormat],
                        default=CartFormat.HILBO_LINE.value,
                        help="hilbo-line (default) or a vendor-like csv "
                             "(virtual_hw.cart.VIRTUAL_CSV_MAPPING)")
    parser.add_argument("--preset", choices=sorted(PRESETS), default="hip_6d",
                        help="parameter space of the wearer's assistance (default hip_6d)")
    parser.add_argument("--seed", type=_seed_arg, default=1, help="wearer (subject) seed (default 1)")
    parser.add_argument("--wearer", choices=WEARER_CHOICES, default=WearerKind.REALISTIC.value,
                        help="realistic (default: breath noise and outliers as in real data, "
                             "tau 14-55 s, drift, slow adaptation, two landscape families), noisy "
                             "(breath CV 15-25 %%, 3 %% outliers), slow (tau 30-60 s) or legacy "
                             "(the earlier simulated wearer)")
    parser.add_argument("--body-mass-kg", type=float, default=75.0,
                        help="the wearer's body mass, 20-250 kg (default 75; match [session] "
                             "body_mass_kg)")
    parser.add_argument("--speed", type=_speed_arg, default=1.0,
                        help="'max' or a real-time factor such as 1 (default) or 10")
    parser.add_argument("--epoch", type=float, default=None,
                        help="Unix time of simulated time 0, shared with the other virtual devices "
                             "(default: now; not with --speed max)")
    parser.add_argument("--fault", type=_fault_arg, action="append", default=[], metavar="SPEC",
                        help="inject a fault, e.g. disconnect@120+10 or duplicate@300x2 (repeatable; "
                             "kinds below)")
    parser.add_argument("--minutes", type=_minutes_arg, default=None,
                        help="stop after this many simulated minutes (default: run until stopped)")
    can = parser.add_argument_group(
        "applied assistance",
        "follow the profile the virtual exosuit applies, from its CAN bus (without these options "
        "the wearer walks unassisted)",
    )
    can.add_argument("--can-interface", default=None, help="python-can interface (e.g. socketcan, virtual)")
    can.add_argument("--can-channel", default=None, help="python-can channel (e.g. vcan0)")
    return parser


def add_virtual_cart_parser(subparsers: Any) -> argparse.ArgumentParser:
    """Register ``virtual-cart`` on the ``hilbo`` subparsers; its ``func`` is :func:`run_from_args`.

    Args:
        subparsers: What ``ArgumentParser.add_subparsers()`` returned.

    Returns:
        The subcommand's parser.
    """
    parser = subparsers.add_parser(
        "virtual-cart",
        help="run the virtual metabolic cart (simulated wearer) as a process",
        description=_DESCRIPTION,
        epilog=CART_FAULTS.describe(),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    configure_parser(parser)
    parser.set_defaults(func=run_from_args)
    return parser


def profile_feed_from_args(args: argparse.Namespace) -> ProfileFeed | None:
    """Where the cart process learns the applied profile: from the exosuit's bus when
    ``--can-interface`` and ``--can-channel`` are given (the pushed tables and the device's
    status, :class:`virtual_hw.exosuit.AppliedProfileListener`), else nowhere (the wearer walks
    unassisted).

    Raises:
        VirtualConfigError: Only one of the two options given.
    """
    if args.can_interface is None and args.can_channel is None:
        return None
    if args.can_interface is None or args.can_channel is None:
        raise VirtualConfigError(
            "--can-interface and --can-channel go together (the exosuit's bus, e.g. "
            "--can-interface socketcan --can-channel vcan0)"
        )
    from drivers.exosuit import CanBusConfig
    from virtual_hw.exosuit import SUIT_JOINTS, applied_profile_feed

    return applied_profile_feed(CanBusConfig(args.can_interface, args.can_channel),
                                joints=SUIT_JOINTS[args.preset])


async def serve(
    cart: VirtualCart, stop: asyncio.Event, *, out: TextIO, profile_feed: ProfileFeed | None = None
) -> None:
    """Run ``cart`` until its session ends or ``stop`` is set; print its address first.

    Raises:
        BaseException: Whatever the cart or the profile feed failed with.
    """
    async with cart:
        out.write(cart.address + "\n")
        out.flush()
        tasks = {
            asyncio.create_task(cart.wait(), name="virtual-cart session"),
            asyncio.create_task(stop.wait(), name="virtual-cart stop"),
        }
        if profile_feed is not None:
            tasks.add(asyncio.create_task(profile_feed(cart), name="virtual-cart profile feed"))
        try:
            done, _ = await asyncio.wait(tasks, return_when=asyncio.FIRST_COMPLETED)
        finally:
            for task in tasks:
                task.cancel()
            results = await asyncio.gather(*tasks, return_exceptions=True)
        for result in results:
            if isinstance(result, BaseException) and not isinstance(result, asyncio.CancelledError):
                raise result
        _log.info("virtual cart stopping (%s)", ", ".join(sorted(t.get_name() for t in done)))
    _log.info("virtual cart served %d breaths: %s", len(cart.history), dict(cart.stats))


async def _run(args: argparse.Namespace, out: TextIO) -> None:
    feed = profile_feed_from_args(args)
    try:
        wearer = make_wearer(args.wearer, preset(args.preset), seed=args.seed,
                             body_mass_kg=args.body_mass_kg)
    except ConfigError as err:  # a value of the command line: a usage error (exit status 2)
        raise VirtualConfigError(f"--body-mass-kg {args.body_mass_kg:g}: {err}") from err
    clock = make_clock(args.speed, args.epoch)
    link = CartLink(kind=LinkKind(args.transport), host=args.host, port=args.port)
    cart = VirtualCart(
        wearer, clock, link=link, fmt=args.format, faults=args.fault,
        end_s=None if args.minutes is None else 60.0 * args.minutes,
        wait_for_client=math.isinf(clock.speed),
    )
    stop = asyncio.Event()
    loop = asyncio.get_running_loop()
    # Windows has no asyncio signal handlers: Ctrl-C arrives as KeyboardInterrupt instead.
    with stop_signal_handlers(loop, stop.set):
        await serve(cart, stop, out=out, profile_feed=feed)


def run_from_args(args: argparse.Namespace) -> int:
    """Run the cart for parsed arguments.

    Returns:
        The exit status: 0 after a clean stop; 2 for options refused before serving (a
        :class:`VirtualConfigError`: bad values or combinations); 1 for a failure once it runs
        (an address in use, a CAN bus that cannot be opened, a failed cart).
    """
    try:
        asyncio.run(_run(args, sys.stdout))
    except VirtualConfigError as err:
        sys.stderr.write(f"hilbo virtual-cart: error: {err}\n")
        return 2
    except (VirtualHwError, HilboError, DriverError, OSError) as err:
        sys.stderr.write(f"hilbo virtual-cart: error: {err}\n")
        return 1
    except KeyboardInterrupt:
        return 0  # Ctrl-C where asyncio has no signal handlers: a normal way to stop
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m virtual_hw.cli_cart [options]``: the same as ``hilbo virtual-cart``."""
    parser = argparse.ArgumentParser(
        prog="hilbo virtual-cart", description=_DESCRIPTION, epilog=CART_FAULTS.describe(),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more log output")
    configure_parser(parser)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING - 10 * min(args.verbose, 2), stream=sys.stderr,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    return run_from_args(args)


if __name__ == "__main__":
    sys.exit(main())
