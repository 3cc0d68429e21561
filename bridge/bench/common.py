"""Helpers shared by the benchmarks: list parsing, option checks, machine info, JSON and tables."""

from __future__ import annotations

import contextlib
import json
import math
import os
import platform
import sys
from collections.abc import Iterable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from bridge.errors import UsageError
from hilbo_core.errors import ConfigError

__all__ = [
    "blas_threads",
    "choices",
    "machine_info",
    "markdown_table",
    "numbers",
    "options",
    "raise_if_interrupted",
    "round_sig",
    "write_json",
]


def blas_threads(n: int | None = 1) -> dict[str, int]:
    """Set (or with None only read) the thread count of every OpenBLAS loaded in this process.

    numpy and scipy each bundle an OpenBLAS. Their default thread pools turn the small matrices of
    a GP (tens to hundreds of rows) into a loss on a busy machine — measured here, one toy trial
    took 33 s with the default pool under load and 2 s single-threaded — and parallel reductions
    need not add in the same order from run to run. The benchmarks therefore run BLAS
    single-threaded and get their parallelism from the executor's processes. (Setting
    ``OPENBLAS_NUM_THREADS=1`` before numpy is imported does the same for a whole process.)

    Args:
        n: Threads per library (>= 1), or None to change nothing.

    Returns:
        ``{library path: thread count before the call}`` (empty where this cannot be done, e.g.
        not Linux or another BLAS).
    """
    import ctypes

    try:
        maps = Path("/proc/self/maps").read_text()
    except OSError:
        return {}
    paths = sorted({line.split()[-1] for line in maps.splitlines()
                    if "openblas" in line.lower() and ".so" in line.split()[-1]})
    before: dict[str, int] = {}
    for path in paths:
        try:
            lib = ctypes.CDLL(path)
        except OSError:
            continue
        for prefix in ("scipy_openblas", "openblas"):
            for suffix in ("64_", ""):
                getter = getattr(lib, f"{prefix}_get_num_threads{suffix}", None)
                setter = getattr(lib, f"{prefix}_set_num_threads{suffix}", None)
                if getter is None or setter is None:
                    continue
                before[path] = int(getter())
                if n is not None:
                    setter(ctypes.c_int(int(n)))
                break
            if path in before:
                break
    return before


def choices(text: str | Sequence[str] | None, allowed: Iterable[str], what: str,
            default: Sequence[str]) -> list[str]:
    """Parse a comma-separated list of names and check every one against ``allowed``.

    Raises:
        ConfigError: An unknown or repeated name (the message lists the allowed names), or an
            empty list.
    """
    allowed = list(allowed)
    if text is None:
        names = list(default)
    elif isinstance(text, str):
        names = [n.strip() for n in text.split(",") if n.strip()]
    else:
        names = list(text)
    if not names:
        raise ConfigError(f"no {what} given; choose from {allowed}")
    for n in names:
        if n not in allowed:
            raise ConfigError(f"unknown {what} {n!r}; choose from {allowed}")
    dup = sorted({n for n in names if names.count(n) > 1})
    if dup:
        raise ConfigError(f"{what} {dup} given more than once")
    return names


def numbers(text: str | Sequence[float] | None, what: str, default: Sequence[float]) -> list[float]:
    """Parse a comma-separated list of positive numbers.

    Raises:
        ConfigError: Something that is not a positive finite number, or an empty list.
    """
    if text is None:
        return [float(v) for v in default]
    parts = text.split(",") if isinstance(text, str) else list(text)
    out: list[float] = []
    for p in parts:
        if isinstance(p, str) and not p.strip():
            continue
        try:
            v = float(p)
        except (TypeError, ValueError) as err:
            raise ConfigError(f"{what} {p!r} is not a number; expected e.g. {list(default)}") from err
        if not (math.isfinite(v) and v > 0):
            raise ConfigError(f"{what} {p!r}; expected a positive number, e.g. {list(default)}")
        out.append(v)
    if not out:
        raise ConfigError(f"no {what} given; expected e.g. {list(default)}")
    return out


@contextlib.contextmanager
def options(names: Mapping[str, str] | None = None) -> Iterator[None]:
    """Checks of the command line's values before any work: their ConfigError is a usage error
    (exit status 2). A missing optional dependency (a ConfigError from an ImportError) is not:
    the command line is right, the installation is not (exit status 1).

    Args:
        names: Config field -> the option that sets it (``{"boundary_s": "--boundary-s"}``): a
            message that starts ``boundary_s=0.0; ...`` (a config class's check) is said as
            ``--boundary-s 0.0; ...``, the name the user typed.
    """
    try:
        yield
    except ConfigError as err:
        if isinstance(err.__cause__, ImportError):
            raise
        text = str(err)
        for field_name, option in (names or {}).items():
            if text.startswith(f"{field_name}="):
                text = f"{option} {text[len(field_name) + 1:]}".replace(" or None", " or none")
                break
        raise UsageError(text) from err


def machine_info() -> dict[str, Any]:
    """What the numbers were measured on: CPU model, cores, OS, Python and library versions."""
    import scipy

    cpu = platform.processor() or ""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return {
        "cpu": cpu,
        "cores": os.cpu_count(),
        "os": f"{platform.system()} {platform.release()}",
        "python": sys.version.split()[0],
        "numpy": np.__version__,
        "scipy": scipy.__version__,
    }


def round_sig(value: Any, sig: int = 6) -> Any:
    """Round floats (also inside lists and dicts) to ``sig`` significant digits; NaN/inf → None."""
    if isinstance(value, Mapping):
        return {k: round_sig(v, sig) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [round_sig(v, sig) for v in value]
    if isinstance(value, np.ndarray):
        return round_sig(value.tolist(), sig)
    if isinstance(value, float | np.floating):
        v = float(value)
        if not math.isfinite(v):
            return None
        return float(f"{v:.{sig}g}")
    if isinstance(value, np.integer):
        return int(value)
    return value


def write_json(path: Path, data: Any) -> None:
    """Write JSON atomically (a temporary file, then a rename)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(json.dumps(data, indent=1, ensure_ascii=False) + "\n")
    os.replace(tmp, path)


def markdown_table(header: Sequence[str], rows: Iterable[Sequence[Any]]) -> str:
    """A GitHub-flavoured Markdown table."""
    lines = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    lines += ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]
    return "\n".join(lines) + "\n"


def raise_if_interrupted(summary: Mapping[str, Any]) -> None:
    """A session a signal ended (Ctrl-C, SIGTERM) ends the benchmark too: its numbers would
    describe a cut session, so nothing more is run or written (``hilbo bench`` exits 130).

    Raises:
        KeyboardInterrupt: The summary's ``end_reason`` is ``interrupted``.
    """
    if summary.get("end_reason") == "interrupted":
        raise KeyboardInterrupt
