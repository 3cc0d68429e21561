"""Mutated copies of the real cart exports through the readers: any traceback is a bug.

Every file input must end in a result or in the package's own error (a ``DriverError``, or an
``OSError`` naming the file): never another exception, a hang or an unbounded read. This script
writes ``N`` seeded mutations of each export in ``shared/data/cart-exports`` (bytes flipped,
inserted or cut, the file truncated, numbers replaced by huge ones, and for the xlsx a zip
member damaged, dropped or swapped) and reads each one as ``hilbo cart inspect`` does, with the
format detected and with the export's own format given.

Usage::

    PYTHONPATH=. python scripts/fuzz_files.py --n 10000 [--seed 1] [--exports DIR] [--json OUT]
        [--only cortex_test.xml]

Prints, per export, how many copies were read, refused with a clear error, or raised anything
else (with the exception types and one example each); exit status 1 when any copy raised
something else. The test suite runs a few hundred copies per export through the same functions
(tests/drivers/test_cart_fuzz_exports.py).
"""

from __future__ import annotations

import argparse
import io
import json
import os
import re
import sys
import tempfile
import time
import traceback
import zipfile
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

__all__ = ["EXPORT_FORMATS", "Outcome", "classify", "default_exports", "mutate", "read_as_inspect", "run"]

EXPORT_FORMATS = {"cosmed_test.xlsx": "cosmed", "cortex_test.xml": "cortex", "vyntus_test.txt": "vyntus"}
"""The shared real exports and the preset each is read with."""

_HUGE = (b"4000000000", b"99999999999999999999", b"-1", b"1e309", b"0", b"18446744073709551617")


def default_exports() -> Path:
    """``$HILBO_SHARED_DIR/data/cart-exports``, else ``shared/`` beside the clone."""
    shared = os.environ.get("HILBO_SHARED_DIR")
    root = Path(shared) if shared else Path(__file__).resolve().parents[2] / "shared"
    return root / "data" / "cart-exports"


def _mutate_bytes(data: bytes, rng: np.random.Generator) -> bytes:
    """One byte-level damage: flips, an insertion, a cut, a truncation or a huge number."""
    buf = bytearray(data)
    kind = int(rng.integers(6))
    if not buf:
        return bytes(rng.integers(0, 256, 16, dtype=np.uint8))
    if kind == 0:  # flip a few bytes
        for _ in range(int(rng.integers(1, 9))):
            buf[int(rng.integers(len(buf)))] = int(rng.integers(256))
    elif kind == 1:  # random bytes inserted
        at = int(rng.integers(len(buf) + 1))
        buf[at:at] = bytes(rng.integers(0, 256, int(rng.integers(1, 64)), dtype=np.uint8))
    elif kind == 2:  # a slice cut out
        at = int(rng.integers(len(buf)))
        del buf[at:at + int(rng.integers(1, 256))]
    elif kind == 3:  # truncated
        del buf[int(rng.integers(len(buf))):]
    elif kind == 4:  # a number replaced by a huge, negative or non-finite one
        numbers = [m.span() for m in re.finditer(rb"\d+", bytes(buf))]
        if numbers:
            a, b = numbers[int(rng.integers(len(numbers)))]
            buf[a:b] = _HUGE[int(rng.integers(len(_HUGE)))]
    else:  # a chunk duplicated (a repeated header, a repeated row)
        a = int(rng.integers(len(buf)))
        chunk = bytes(buf[a:a + int(rng.integers(1, 512))])
        at = int(rng.integers(len(buf) + 1))
        buf[at:at] = chunk
    return bytes(buf)


def _mutate_zip(data: bytes, rng: np.random.Generator) -> bytes:
    """Damage one member of a zip (its XML), drop one, or swap two members' contents."""
    try:
        src = zipfile.ZipFile(io.BytesIO(data))
        members = [(i.filename, src.read(i)) for i in src.infolist()]
    except (zipfile.BadZipFile, OSError, ValueError, EOFError):
        return _mutate_bytes(data, rng)
    if not members:
        return _mutate_bytes(data, rng)
    kind = int(rng.integers(3))
    k = int(rng.integers(len(members)))
    if kind == 0:
        name, body = members[k]
        members[k] = (name, _mutate_bytes(body, rng))
    elif kind == 1:
        del members[k]
    else:
        j = int(rng.integers(len(members)))
        (a, x), (b, y) = members[k], members[j]
        members[k], members[j] = (a, y), (b, x)
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w", zipfile.ZIP_DEFLATED) as dst:
        for name, body in members:
            dst.writestr(name, body)
    return out.getvalue()


def mutate(data: bytes, rng: np.random.Generator) -> bytes:
    """A damaged copy of ``data``: zip-member damage for a zip half of the time, else bytes."""
    if data.startswith(b"PK\x03\x04") and rng.random() < 0.5:
        return _mutate_zip(data, rng)
    return _mutate_bytes(data, rng)


@dataclass
class Outcome:
    """What the copies of one export did.

    Attributes:
        read: Copies read to a report.
        refused: Copies refused with the package's error (the message is the user's answer).
        tracebacks: Any other exception, by type.
        examples: One traceback text per exception type.
        slowest_s: The longest single read, in seconds.
    """

    read: int = 0
    refused: int = 0
    tracebacks: Counter[str] = field(default_factory=Counter)
    examples: dict[str, str] = field(default_factory=dict)
    slowest_s: float = 0.0


def read_as_inspect(path: Path, fmt: str | None) -> object:
    """Read ``path`` as ``hilbo cart inspect`` does (``fmt`` None: detect the format)."""
    from drivers.cart.inspect import inspect_file

    return inspect_file(path, fmt)


def classify(outcome: Outcome, read: Callable[..., object], *args: object) -> None:
    """Call ``read(*args)`` and count how it ended in ``outcome``."""
    from bridge.errors import BridgeError
    from drivers.errors import DriverError

    t0 = time.perf_counter()
    try:
        read(*args)
    except (DriverError, BridgeError, OSError):
        outcome.refused += 1
    except Exception as err:  # the point: anything else is what is counted
        name = type(err).__name__
        outcome.tracebacks[name] += 1
        outcome.examples.setdefault(name, traceback.format_exc())
    else:
        outcome.read += 1
    outcome.slowest_s = max(outcome.slowest_s, time.perf_counter() - t0)


def run(exports: Path, n: int, seed: int, work: Path, names: tuple[str, ...] = tuple(EXPORT_FORMATS),
        progress: Callable[[str, int, Outcome], None] | None = None) -> dict[str, Outcome]:
    """``n`` mutated copies of each export read twice (detected, and with the export's format).

    Args:
        exports: The folder of the real exports.
        n: Copies per export.
        seed: Of the mutations (each export's copies come from ``default_rng([seed, k])``, so
            one export's copies do not depend on which others are run).
        work: A folder for the copies.
        names: The exports to mutate (default all of :data:`EXPORT_FORMATS`).
        progress: Called with the export, the copies done and the outcome so far after every
            1000 copies.

    Returns:
        Per export file name, the outcome of its ``2 n`` reads.
    """
    results: dict[str, Outcome] = {}
    for name in names:
        fmt = EXPORT_FORMATS[name]
        rng = np.random.default_rng([seed, list(EXPORT_FORMATS).index(name)])
        data = (exports / name).read_bytes()
        outcome = results[name] = Outcome()
        copy = work / name
        for k in range(1, n + 1):
            copy.write_bytes(mutate(data, rng))
            classify(outcome, read_as_inspect, copy, None)
            classify(outcome, read_as_inspect, copy, fmt)
            if progress is not None and k % 1000 == 0:
                progress(name, k, outcome)
    return results


def main(argv: list[str] | None = None) -> int:
    """Command line: see the module docstring."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--n", type=int, default=10_000, help="mutated copies per export (default 10000)")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--exports", type=Path, default=None,
                    help="the cart-exports folder (default: $HILBO_SHARED_DIR/data/cart-exports, else "
                         "shared/data/cart-exports beside the clone)")
    ap.add_argument("--json", type=Path, default=None, help="write the counts here as JSON")
    ap.add_argument("--only", action="append", choices=sorted(EXPORT_FORMATS), default=None,
                    help="mutate only this export (repeatable; default all)")
    args = ap.parse_args(argv)
    exports = args.exports or default_exports()
    if not all((exports / name).is_file() for name in EXPORT_FORMATS):
        sys.stderr.write(f"fuzz_files: {exports} does not hold {', '.join(EXPORT_FORMATS)}; give "
                         "--exports DIR\n")
        return 2
    import logging

    logging.disable(logging.WARNING)  # damaged files warn by design; the counts are the output
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        results = run(exports, args.n, args.seed, Path(tmp), tuple(args.only or EXPORT_FORMATS),
                      progress=lambda name, k, o: print(  # noqa: T201
                          f"  {name}: {k} copies, {o.tracebacks.total()} tracebacks so far", flush=True))
        wall = time.perf_counter() - t0
    total = 0
    for name, o in results.items():
        total += o.tracebacks.total()
        print(f"{name}: {2 * args.n} reads of {args.n} copies: {o.read} read, {o.refused} refused "  # noqa: T201
              f"with a clear error, {o.tracebacks.total()} tracebacks {dict(o.tracebacks)}; slowest "
              f"read {o.slowest_s * 1000:.0f} ms")
        for kind, text in o.examples.items():
            print(f"--- {kind}\n{text}")  # noqa: T201
    print(f"total tracebacks {total}; {wall:.1f} s")  # noqa: T201
    if args.json is not None:
        args.json.write_text(json.dumps({
            "n": args.n, "seed": args.seed, "wall_s": round(wall, 1),
            "exports": {k: {"reads": 2 * args.n, "read": o.read, "refused": o.refused,
                            "tracebacks": dict(o.tracebacks), "slowest_ms": round(o.slowest_s * 1000)}
                        for k, o in results.items()},
        }, indent=2) + "\n")
    return 1 if total else 0


if __name__ == "__main__":
    sys.exit(main())
