"""Pluggable executors for benchmark campaigns: local processes, or a Dask distributed cluster.

A campaign is a list of *tasks* (small frozen, picklable values) and a module-level function
``fn(task) -> result``. Every task carries its own seeds, so a result depends on the task alone
and a campaign gives identical results whichever executor runs it and in whatever order the
workers finish; :meth:`Executor.map` returns the results in task order.

* :class:`LocalExecutor` — ``concurrent.futures.ProcessPoolExecutor`` over all cores by default;
  ``workers=1`` runs in this process (no pool: easy to profile and debug).
* :class:`DaskExecutor` — a ``distributed.Client`` connected to an existing scheduler
  (``--scheduler tcp://host:8786``). The workers need hilbo installed (same version), because
  tasks refer to its functions by name.

Both show a rich progress bar on stderr when it is a terminal.
"""

from __future__ import annotations

import asyncio
import logging
import multiprocessing
import os
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from contextlib import contextmanager
from typing import Any, Protocol, TypeVar

from rich.console import Console
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

from hilbo_core.errors import ConfigError

__all__ = ["DaskExecutor", "Executor", "LocalExecutor", "keep_freed_memory", "make_executor"]

logger = logging.getLogger(__name__)

_BLAS_THREAD_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS")

# glibc mallopt parameters (malloc.h): M_TRIM_THRESHOLD = -1, M_MMAP_THRESHOLD = -3.
_M_TRIM_THRESHOLD = -1
_M_MMAP_THRESHOLD = -3
_KEEP_BYTES = 1 << 30

T = TypeVar("T")
R = TypeVar("R")


class Executor(Protocol):
    """Runs ``fn`` over tasks and returns the results in task order."""

    name: str

    def map(self, fn: Callable[[T], R], tasks: Sequence[T], *, label: str = "tasks",
            on_result: Callable[[int, R], None] | None = None) -> list[R]:
        """``[fn(t) for t in tasks]``, computed wherever the executor computes.

        Args:
            fn: A module-level (picklable) function.
            tasks: Picklable task values.
            label: Text of the progress bar.
            on_result: Called in this process with ``(index, result)`` as each task finishes
                (in completion order), e.g. to append it to a file.

        Raises:
            Whatever ``fn`` raised for the first task that failed (the rest are cancelled).
        """
        ...


def keep_freed_memory(limit_bytes: int = _KEEP_BYTES) -> bool:
    """Let glibc's malloc keep freed blocks up to ``limit_bytes`` instead of returning them.

    A benchmark worker allocates and frees the same multi-MB arrays thousands of times (the
    (1024 candidates × n) kernel block of every EI maximisation, the n × n matrices of every GP
    fit). By default glibc serves such blocks with mmap, or trims them off the heap when freed, so
    every allocation page-faults afresh: measured on one Ackley trial (σ_z² = σ̃², adaptive, seed
    1), 8.5 s CPU of which 1.0 s system time by default, 6.4 s and 0.2 s with this. Arithmetic is
    untouched (same results); the worker's resident memory stays at its peak.

    Returns:
        True if set; False where there is no glibc (nothing changes then).
    """
    import ctypes
    import ctypes.util

    name = ctypes.util.find_library("c")
    if name is None:
        return False
    try:
        libc = ctypes.CDLL(name)
        mallopt = libc.mallopt
    except (OSError, AttributeError):
        return False
    ok = mallopt(_M_MMAP_THRESHOLD, int(limit_bytes)) == 1
    return bool(mallopt(_M_TRIM_THRESHOLD, int(limit_bytes)) == 1 and ok)


@contextmanager
def _progress(total: int, label: str, enabled: bool | None) -> Iterator[Callable[[], None]]:
    console = Console(stderr=True)
    show = console.is_terminal if enabled is None else enabled
    if not show or total == 0:
        yield lambda: None
        return
    with Progress(TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(),
                  TimeElapsedColumn(), console=console, transient=False) as bar:
        tid = bar.add_task(label, total=total)
        yield lambda: bar.advance(tid)


class LocalExecutor:
    """Local processes (``ProcessPoolExecutor``); ``workers=1`` runs in this process.

    Args:
        workers: Number of worker processes; None means ``os.cpu_count()``.
        progress: Show a progress bar (None: only when stderr is a terminal).
    """

    def __init__(self, workers: int | None = None, progress: bool | None = None) -> None:
        if workers is not None and (isinstance(workers, bool) or not isinstance(workers, int) or workers < 1):
            raise ConfigError(f"workers={workers!r}; expected an integer >= 1 (or none for all cores)")
        self.workers = workers or os.cpu_count() or 1
        self.progress = progress
        self.name = f"local processes ({self.workers})" if self.workers > 1 else "in-process"

    def map(self, fn: Callable[[T], R], tasks: Sequence[T], *, label: str = "tasks",
            on_result: Callable[[int, R], None] | None = None) -> list[R]:
        """See :meth:`Executor.map`."""
        tasks = list(tasks)
        results: list[Any] = [None] * len(tasks)
        with _progress(len(tasks), label, self.progress) as advance:
            if self.workers == 1 or len(tasks) <= 1:
                for i, task in enumerate(tasks):
                    results[i] = fn(task)
                    if on_result is not None:
                        on_result(i, results[i])
                    advance()
                return results
            # Spawned workers with single-threaded BLAS: no oversubscription of the cores, and
            # the same floating-point reduction order as any other single-threaded worker.
            for var in _BLAS_THREAD_VARS:
                os.environ.setdefault(var, "1")
            with ProcessPoolExecutor(max_workers=min(self.workers, len(tasks)),
                                     mp_context=multiprocessing.get_context("spawn")) as pool:
                futures: dict[Future[R], int] = {pool.submit(fn, t): i for i, t in enumerate(tasks)}
                pending = set(futures)
                while pending:
                    # FIRST_COMPLETED, not FIRST_EXCEPTION: the latter waits for *all* futures
                    # when none fails, so on_result (which appends to trials.jsonl) only ran at
                    # the very end and an interrupted campaign kept nothing.
                    done, pending = wait(pending, return_when=FIRST_COMPLETED)
                    for fut in done:
                        err = fut.exception()
                        if err is not None:
                            for other in pending:
                                other.cancel()
                            raise err
                        i = futures[fut]
                        results[i] = fut.result()
                        if on_result is not None:
                            on_result(i, results[i])
                        advance()
        return results


class DaskExecutor:
    """A Dask distributed cluster reached through its scheduler address.

    Args:
        address: Scheduler address, e.g. ``tcp://10.0.0.5:8786`` or ``127.0.0.1:8786``.
        progress: Show a progress bar (None: only when stderr is a terminal).
        timeout_s: How long to wait for the scheduler when connecting.
    """

    def __init__(self, address: str, progress: bool | None = None, timeout_s: float = 30.0) -> None:
        if not isinstance(address, str) or not address.strip():
            raise ConfigError(f"scheduler address {address!r}; expected e.g. tcp://host:8786")
        self.address = address.strip()
        self.progress = progress
        self.timeout_s = timeout_s
        self.name = f"dask ({self.address})"

    def map(self, fn: Callable[[T], R], tasks: Sequence[T], *, label: str = "tasks",
            on_result: Callable[[int, R], None] | None = None) -> list[R]:
        """See :meth:`Executor.map`."""
        tasks = list(tasks)
        results: list[Any] = [None] * len(tasks)
        # An asynchronous client on an event loop of this call: a synchronous Client runs its own
        # "IO loop" thread, which it leaves running when it cannot connect (distributed 2026.8).
        asyncio.run(self._map(fn, tasks, label, on_result, results))
        return results

    async def _map(self, fn: Callable[[T], R], tasks: list[T], label: str,
                   on_result: Callable[[int, R], None] | None, results: list[Any]) -> None:
        from distributed import Client, as_completed

        try:
            client = await Client(self.address, timeout=self.timeout_s, set_as_default=False,
                                  asynchronous=True)
        except OSError as err:
            raise ConfigError(f"cannot reach the Dask scheduler at {self.address!r}: {err}") from err
        async with client:
            with _progress(len(tasks), label, self.progress) as advance:
                # pure=False: identical tasks are still separate runs; the result depends only
                # on the task's own seeds, never on which worker runs it.
                futures = client.map(fn, tasks, pure=False)
                index = {f.key: i for i, f in enumerate(futures)}
                try:
                    with client.as_current():  # as_completed finds the client by context
                        async for fut in as_completed(futures):
                            i = index[fut.key]
                            results[i] = await fut  # re-raises the task's exception here
                            if on_result is not None:
                                on_result(i, results[i])
                            advance()
                except BaseException:
                    await client.cancel(futures)
                    raise


def make_executor(workers: int | None = None, scheduler: str | None = None,
                  progress: bool | None = None) -> LocalExecutor | DaskExecutor:
    """The executor the command line asked for: Dask when a scheduler is given, else local."""
    if scheduler:
        if workers is not None:
            logger.info("--workers is ignored with --scheduler: the cluster decides")
        return DaskExecutor(scheduler, progress=progress)
    return LocalExecutor(workers, progress=progress)
