"""``hilbo virtual-exosuit``: the virtual exosuit as a process on a CAN bus.

Run it next to the bridge (and the virtual cart) on a shared bus, for instance on a Linux PC with
``vcan0`` (``hilbo vcan-setup | sudo sh``)::

    hilbo virtual-exosuit --interface socketcan --channel vcan0 --speed 1 --epoch 1767225600 \\
        --seed 3 --fault drop-status@30+0.5 --fault nack-busy@60x2

or, without the console script, ``python -m virtual_hw.cli_exosuit ...``. Processes that share
``--speed`` and ``--epoch`` share one simulated clock (:class:`~virtual_hw.clock.ScaledClock`);
``--speed max`` is refused here because an as-fast-as-possible clock cannot be shared between
processes (``hilbo sim`` runs the devices in one process for that).

Once the bus is open the process prints ONE machine-readable line on stdout, a JSON object with
``"event": "ready"`` (pid, bus, clock, seed, joints, faults); on SIGINT or SIGTERM (or after
``--lifetime`` seconds) it stops the device within a bounded time and prints a last JSON line
with ``"event": "stopped"``, the device's counters and the applied-profile reports, then exits 0
(1 if the device failed or its bus could not be opened; 2 for an option refused before the
device opens).
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import logging
import math
import os
import sys
from collections.abc import Sequence
from typing import Any

from drivers.errors import DriverConfigError, DriverError
from drivers.exosuit.endpoint import CanBusConfig
from drivers.signals import STOP_SIGNALS, stop_signal_handlers
from virtual_hw.clock import ScaledClock, parse_speed
from virtual_hw.errors import VirtualConfigError, VirtualHwError
from virtual_hw.exosuit import (
    DEFAULT_FEEDBACK_HZ,
    EXOSUIT_FAULTS,
    HEARTBEAT_TIMEOUT_S,
    LIVENESS_TIMEOUT_S,
    SUIT_JOINTS,
    DeviceLimits,
    VirtualExosuit,
)

__all__ = ["STOP_TIMEOUT_S", "add_virtual_exosuit_parser", "main", "run"]

log = logging.getLogger(__name__)

#: Longest time the process waits for the device to close after a stop signal.
STOP_TIMEOUT_S = 5.0


def _add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--interface", default="socketcan",
                        help="python-can interface: socketcan, virtual, pcan, kvaser, slcan, remote, "
                             "... (default socketcan)")
    parser.add_argument("--channel", default="vcan0",
                        help="interface channel, e.g. vcan0, can0, ws://127.0.0.1:54701/ "
                             "(default vcan0)")
    parser.add_argument("--bitrate", type=int, default=1_000_000,
                        help="bitrate in bit/s where the interface takes one (default 1000000)")
    parser.add_argument("--speed", default="1",
                        help="simulated seconds per wall second, e.g. 1 or 10 (default 1); share "
                             "it, with --epoch, with the other virtual devices")
    parser.add_argument("--epoch", type=float, default=None,
                        help="Unix time at which simulated time is 0 (default: now)")
    parser.add_argument("--seed", type=int, default=0, help="seed of strides, noise and faults")
    parser.add_argument("--suit", default="hip_6d", choices=sorted(SUIT_JOINTS),
                        help="actuator layout: hip_6d = two hips (one table), hip_ankle_4d = hip "
                             "and ankle (tables concatenated, hip first) (default hip_6d)")
    parser.add_argument("--feedback-hz", type=float, default=DEFAULT_FEEDBACK_HZ,
                        help=f"ForceFeedback rate per actuator; 0 = none (default "
                             f"{DEFAULT_FEEDBACK_HZ:g})")
    parser.add_argument("--max-force-n", type=float, default=DeviceLimits().max_force_n,
                        help="the device's force limit in N (default %(default)g)")
    parser.add_argument("--max-slope-n-per-pct", type=float,
                        default=DeviceLimits().max_slope_n_per_pct,
                        help="the device's limit on force change per %%GC (default %(default)g)")
    parser.add_argument("--heartbeat-timeout", type=float, default=HEARTBEAT_TIMEOUT_S,
                        help="bridge-heartbeat bus watchdog in s: no frame with an advanced "
                             "counter for this long (default %(default)g, PROTOCOL.md); longer "
                             "only on hosts that stall, such as an emulator")
    parser.add_argument("--liveness-timeout", type=float, default=LIVENESS_TIMEOUT_S,
                        help="bridge liveness watchdog in s: the heartbeat's liveness counter "
                             "unchanged for this long means a hung bridge (default %(default)g, "
                             "PROTOCOL.md)")
    parser.add_argument("--malformed-rate", type=float, default=50.0,
                        help="malformed frames per second while such a fault is on (default 50)")
    parser.add_argument("--fault", action="append", default=[], metavar="SPEC",
                        help="inject a fault (repeatable); see the list below")
    parser.add_argument("--lifetime", type=float, default=None,
                        help="stop by itself after this many wall seconds (default: run until "
                             "SIGINT/SIGTERM)")


def add_virtual_exosuit_parser(subparsers: Any) -> argparse.ArgumentParser:
    """Register ``virtual-exosuit`` on the ``hilbo`` sub-command parsers.

    Args:
        subparsers: what ``ArgumentParser.add_subparsers()`` returned.

    Returns:
        The sub-command's parser; its ``func`` default is :func:`run`.
    """
    parser = subparsers.add_parser(
        "virtual-exosuit",
        help="run a virtual exosuit node on a CAN bus",
        description=__doc__.split("\n\n")[0].replace("``", "") if __doc__ else None,
        epilog=EXOSUIT_FAULTS.describe(),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    _add_arguments(parser)
    parser.set_defaults(func=run)
    return parser


def _emit(record: dict[str, Any]) -> None:
    # The one machine-readable channel of this process: one JSON object per line on stdout.
    sys.stdout.write(json.dumps(record) + "\n")
    sys.stdout.flush()


def _build(args: argparse.Namespace) -> tuple[VirtualExosuit, ScaledClock]:
    speed = parse_speed(args.speed)
    if math.isinf(speed):
        raise VirtualConfigError(
            "--speed max: an as-fast-as-possible clock cannot be shared with other processes; "
            "give a factor such as 1 or 10 (and the same --epoch to every virtual device), or "
            "run the devices in one process with 'hilbo sim --speed max'"
        )
    clock = ScaledClock(speed, args.epoch)
    joints = SUIT_JOINTS[args.suit]
    try:
        bus = CanBusConfig(args.interface, args.channel, args.bitrate)
    except DriverConfigError as err:  # a value of the command line: a usage error (exit status 2)
        raise VirtualConfigError(f"--interface/--channel/--bitrate: {err}") from err
    device = VirtualExosuit(
        bus,
        clock,
        n_actuators=len(joints),
        joints=joints,
        limits=DeviceLimits(max_force_n=args.max_force_n,
                            max_slope_n_per_pct=args.max_slope_n_per_pct),
        seed=args.seed,
        faults=args.fault,
        feedback_hz=args.feedback_hz,
        heartbeat_timeout_s=args.heartbeat_timeout,
        liveness_timeout_s=args.liveness_timeout,
        malformed_rate_hz=args.malformed_rate,
    )
    return device, clock


async def _serve(args: argparse.Namespace) -> int:
    device, clock = _build(args)
    loop = asyncio.get_running_loop()
    stop = asyncio.Event()
    reason = ["lifetime"]

    def on_signal(name: str) -> None:
        reason[0] = name
        stop.set()

    handlers = contextlib.ExitStack()
    for sig in STOP_SIGNALS:  # the callback is told which signal came
        handlers.enter_context(stop_signal_handlers(loop, on_signal, sig.name, signals=(sig,)))
    status = 0
    try:
        await device.open()
        _emit({
            "event": "ready", "device": "virtual-exosuit", "pid": os.getpid(),
            "interface": args.interface, "channel": args.channel, "speed": clock.speed,
            "epoch": clock.epoch_wall, "t_sim": clock.now(), "seed": device.seed,
            "suit": args.suit, "joints": list(device.joints), "feedback_hz": device.feedback_hz,
            "faults": [str(s) for s in device.faults.specs],
        })
        failed = loop.create_task(device.wait(), name="virtual-exosuit-wait")
        stopping = loop.create_task(stop.wait(), name="virtual-exosuit-stop")
        done, _ = await asyncio.wait({failed, stopping}, timeout=args.lifetime,
                                     return_when=asyncio.FIRST_COMPLETED)
        for task in (failed, stopping):
            task.cancel()
        if failed in done and not failed.cancelled() and failed.exception() is not None:
            reason[0] = "failed"
            status = 1
    finally:
        try:
            async with asyncio.timeout(STOP_TIMEOUT_S):
                error = await device.close()
        except TimeoutError:
            error = TimeoutError(f"the device did not close within {STOP_TIMEOUT_S} s")
        handlers.close()
    if error is not None:
        sys.stderr.write(f"hilbo virtual-exosuit: {error!r}\n")
        status = 1
    _emit({
        "event": "stopped", "reason": reason[0], "t_sim": clock.now(), "stats": dict(device.stats),
        "applied": [list(entry) for entry in device.applied_log],
    })
    return status


def run(args: argparse.Namespace) -> int:
    """Run the device until a signal, ``--lifetime`` or a failure.

    Returns:
        The exit status: 0 after a clean stop; 2 for options refused before the device opens
        (a :class:`VirtualConfigError`: bad values or combinations); 1 if the device failed or
        its CAN bus could not be opened.
    """
    try:
        return asyncio.run(_serve(args))
    except VirtualConfigError as err:
        sys.stderr.write(f"hilbo virtual-exosuit: error: {err}\n")
        return 2
    except (VirtualHwError, DriverError, OSError) as err:
        sys.stderr.write(f"hilbo virtual-exosuit: error: {err}\n")
        return 1


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m virtual_hw.cli_exosuit``: the same options as ``hilbo virtual-exosuit``."""
    parser = argparse.ArgumentParser(
        prog="python -m virtual_hw.cli_exosuit",
        description=__doc__.split("\n\n")[0].replace("``", "") if __doc__ else None,
        epilog=EXOSUIT_FAULTS.describe(),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("-v", "--verbose", action="count", default=0, help="more log output")
    _add_arguments(parser)
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.WARNING - 10 * min(args.verbose, 2), stream=sys.stderr,
                        format="%(asctime)s %(levelname)s %(name)s: %(message)s")
    return run(args)


if __name__ == "__main__":
    sys.exit(main())
