"""TEST SCAFFOLDING: a minimal device-side responder for the exosuit profile push.

Not the virtual exosuit (that is virtual_hw's job): it only collects ProfileSegments, checks each
ProfileCommit with :class:`~drivers.exosuit.profile.ProfileAssembler` and answers ProfileAck, and
records the heartbeats and assistance-off commands it sees. Behaviours injected for the tests:
corrupt the first N transfers, or the first transfer of given versions (CRC mismatch → nack
bad_crc), drop segment 1 of the first N
transfers (→ nack missing_segment), stay silent on the first N commits (→ bridge timeout),
answer busy to the first N commits; misbehave with answers the bridge must reject: ack a
version on its first segment, before any commit (``early_ack_first`` transfers), answer each
commit ``duplicate_acks`` extra times, or send an ack of the previous version before each
answer (``stale_ack``).

In-process: ``await Responder(behaviour).run(config, ready)``. As a process (the cross-process
vcan test): ``python exosuit_responder.py --interface socketcan --channel vcan0 [...]`` prints
``READY`` once its bus is open, answers a ``STATS`` line on stdin with one JSON line of what it
saw so far, and runs until its stdin closes (or ``--lifetime`` s), then prints that JSON line once
more and exits.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import sys
import threading
from dataclasses import dataclass, field

from drivers.exosuit.codec import (
    AssistanceOff,
    BridgeHeartbeat,
    ProfileAck,
    ProfileCommit,
    ProfileSegment,
)
from drivers.exosuit.endpoint import CanBusConfig, CanEndpoint
from drivers.exosuit.profile import ProfileAssembler

__all__ = ["Behaviour", "Responder", "main"]


@dataclass(frozen=True)
class Behaviour:
    """Faults to inject, counted in commits (transfers) from the start."""

    max_force_n: float = 400.0
    corrupt_first: int = 0
    corrupt_once_versions: frozenset[int] = frozenset()
    drop_first: int = 0
    silent_first: int = 0
    busy_first: int = 0
    early_ack_first: int = 0
    duplicate_acks: int = 0
    stale_ack: bool = False


@dataclass
class Seen:
    """What the responder saw (filled as it runs)."""

    commits: int = 0
    acked: list[tuple[int, tuple[float, ...]]] = field(default_factory=list)
    nacked: list[tuple[int, str]] = field(default_factory=list)
    heartbeats: list[tuple[int, int]] = field(default_factory=list)
    assistance_off: list[int] = field(default_factory=list)

    def to_json(self) -> str:
        return json.dumps({
            "commits": self.commits,
            "acked": [[v, list(t)] for v, t in self.acked],
            "nacked": self.nacked,
            "heartbeats": self.heartbeats,
            "assistance_off": self.assistance_off,
        })


class Responder:
    """The scaffold device: see the module docstring."""

    def __init__(self, behaviour: Behaviour = Behaviour()) -> None:
        self.behaviour = behaviour
        self.assembler = ProfileAssembler(max_force_n=behaviour.max_force_n)
        self.seen = Seen()
        self._versions_seen: set[int] = set()
        self._early: set[int] = set()

    async def handle(self, endpoint: CanEndpoint, message: object) -> None:
        b, seen = self.behaviour, self.seen
        if isinstance(message, ProfileSegment):
            if seen.commits < b.drop_first and message.index == 1:
                return
            if message.index == 0 and len(self._early) < b.early_ack_first and (
                message.version not in self._early
            ):
                self._early.add(message.version)
                await endpoint.send(ProfileAck.ack(message.version))  # before any commit
            self.assembler.on_segment(message)
        elif isinstance(message, ProfileCommit):
            n = seen.commits
            seen.commits += 1
            if n < b.silent_first:
                return
            self.assembler.busy = n < b.busy_first
            first_of_version = message.version not in self._versions_seen
            self._versions_seen.add(message.version)
            corrupt = n < b.corrupt_first or (
                first_of_version and message.version in b.corrupt_once_versions
            )
            if corrupt:  # as if a bit of the table flipped on the way
                message = ProfileCommit(message.version, message.n_points, message.crc32 ^ 1)
            ack, table = self.assembler.on_commit(message)
            if table is not None:
                seen.acked.append((ack.version, table))
            else:
                seen.nacked.append((ack.version, ack.reason.name))
            if b.stale_ack:
                await endpoint.send(ProfileAck.ack((message.version - 2) % 255 + 1))  # the previous version
            for _ in range(1 + b.duplicate_acks):
                await endpoint.send(ack)
        elif isinstance(message, BridgeHeartbeat):
            seen.heartbeats.append((message.counter, int(message.state)))
        elif isinstance(message, AssistanceOff):
            seen.assistance_off.append(int(message.reason))

    async def run(self, config: CanBusConfig, ready: asyncio.Event | None = None) -> None:
        """Serve until cancelled."""
        async with CanEndpoint(config) as endpoint:
            with endpoint.subscribe() as sub:
                if ready is not None:
                    ready.set()
                async for message in sub:
                    await self.handle(endpoint, message)


async def _main_async(args: argparse.Namespace) -> Seen:
    responder = Responder(Behaviour(
        max_force_n=args.max_force_n, corrupt_first=args.corrupt_first,
        corrupt_once_versions=frozenset(args.corrupt_once_version),
        drop_first=args.drop_first, silent_first=args.silent_first, busy_first=args.busy_first,
    ))
    ready = asyncio.Event()
    task = asyncio.create_task(responder.run(CanBusConfig(args.interface, args.channel), ready))
    await asyncio.wait({task, asyncio.create_task(ready.wait())},
                       return_when=asyncio.FIRST_COMPLETED)
    if task.done():
        task.result()  # raises what made the responder stop
    print("READY", flush=True)
    loop = asyncio.get_running_loop()
    stdin_closed = asyncio.Event()

    def report() -> None:
        print(responder.seen.to_json(), flush=True)

    def watch_stdin() -> None:  # a daemon thread, so a lifetime expiry never waits for it
        for line in sys.stdin:
            if line.strip() == "STATS":
                loop.call_soon_threadsafe(report)
        loop.call_soon_threadsafe(stdin_closed.set)

    threading.Thread(target=watch_stdin, daemon=True).start()
    try:
        await asyncio.wait_for(stdin_closed.wait(), args.lifetime)
    except TimeoutError:
        pass
    task.cancel()
    try:
        await task
    except asyncio.CancelledError:
        pass
    return responder.seen


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="test scaffold: exosuit profile responder")
    parser.add_argument("--interface", default="socketcan")
    parser.add_argument("--channel", default="vcan0")
    parser.add_argument("--max-force-n", type=float, default=400.0)
    parser.add_argument("--corrupt-first", type=int, default=0)
    parser.add_argument("--corrupt-once-version", type=int, action="append", default=[])
    parser.add_argument("--drop-first", type=int, default=0)
    parser.add_argument("--silent-first", type=int, default=0)
    parser.add_argument("--busy-first", type=int, default=0)
    parser.add_argument("--lifetime", type=float, default=30.0)
    seen = asyncio.run(_main_async(parser.parse_args(argv)))
    print(seen.to_json(), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
