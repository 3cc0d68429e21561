"""Where a session's GP work runs: proposals and hyperparameter fits, in a worker process or a thread.

Why a process by default: the bridge's event loop handles about 2000 CAN frames/s of force
feedback plus heartbeats and logging, in Python. A proposal computed in a thread of the same
process competes with that loop for the GIL: in ``hilbo bench perf --bridge-minutes 5`` the
proposal thread used ≈ 15 ms of CPU per proposal but took 35–48 ms of wall time
(docs/results.md §3). A worker process computes on the other core.

The optimizer travels by pickle (≈ 15 kB at 60 evaluations, about a millisecond each way),
taken when the ask is started (:meth:`ProposalWorker.start_ask`), so the session can log the
evaluation that just ended while the worker computes; the worker returns the advanced optimizer,
which replaces the session's copy (in a thread too: the thread works on its own copy). A worker that dies
(killed, out of memory) costs nothing collected: the call is repeated in a thread and the session
goes on there (:attr:`ProposalWorker.lost` says why).

A worker process watches the session's process and exits when it is gone, so a session killed
with ``kill -9`` leaves no idle worker behind.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import enum
import logging
import multiprocessing
import os
import pickle
import threading
import time
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass
from typing import Any

from hilbo_core import HILOptimizer, HyperparameterFit, fit_hyperparameters
from hilbo_core.gp import GPHyperparameters

__all__ = ["Asked", "ProposalWorker", "WorkerKind"]

logger = logging.getLogger(__name__)

#: How often a worker process checks that the session's process still exists (s).
_PARENT_POLL_S = 0.5


class WorkerKind(enum.Enum):
    """Where the GP work of a session runs."""

    PROCESS = "process"  # a worker process: no GIL shared with the CAN traffic (the default)
    THREAD = "thread"  # a thread of the session's process


@dataclass(frozen=True)
class Asked:
    """What :meth:`ProposalWorker.ask` returns.

    Attributes:
        opt: The optimizer after the ask: a new object that replaces the caller's.
        params: The setting.
        compute_s: Wall time of ``ask()`` itself in the worker (s).
        total_s: Wall time of the whole call as the caller saw it (s): ``compute_s`` plus moving
            the optimizer to the worker and back (pickling included) and waiting for the event
            loop.
    """

    opt: HILOptimizer
    params: dict[str, float]
    compute_s: float
    total_s: float


def _ask(payload: bytes) -> tuple[HILOptimizer, dict[str, float], float]:
    """``ask()`` of the pickled optimizer ``payload``, returning the advanced optimizer too (it
    comes back from another process) and how long the ask took there."""
    opt = pickle.loads(payload)
    t0 = time.perf_counter()
    params = opt.ask()
    return opt, params, time.perf_counter() - t0


def _watch_parent(pid: int) -> None:
    """Worker initializer: exit when the session's process ``pid`` is gone."""

    def watch() -> None:
        while True:
            threading.Event().wait(_PARENT_POLL_S)
            try:
                os.kill(pid, 0)
            except ProcessLookupError:
                os._exit(0)  # the session died (kill -9): nothing here is worth keeping
            except PermissionError:
                pass  # exists, owned by someone else: cannot happen for our parent

    threading.Thread(target=watch, name="hilbo-parent-watch", daemon=True).start()


def _context() -> multiprocessing.context.BaseContext:
    # forkserver: each session's worker forks from a server that has imported numpy/scipy once
    # (a fresh interpreter per session would spend ≈ 1 s importing), and nothing is forked from
    # the session's own multi-threaded process. Windows has only spawn.
    if "forkserver" in multiprocessing.get_all_start_methods():
        ctx = multiprocessing.get_context("forkserver")
        ctx.set_forkserver_preload(["hilbo_core", "bridge.proposals"])
        return ctx
    return multiprocessing.get_context("spawn")


class ProposalWorker:
    """Runs :meth:`HILOptimizer.ask` and hyperparameter fits off the event loop.

    One call at a time (one worker): a fit made ahead finishes before the next proposal starts.
    Use as a context manager; :meth:`start` launches the process early (during the warm-up walk).

    Args:
        kind: :class:`WorkerKind` (or its value).
    """

    def __init__(self, kind: WorkerKind | str = WorkerKind.PROCESS) -> None:
        self.kind = WorkerKind(kind)
        self._pool: concurrent.futures.Executor | None = None
        self._thread_pool: concurrent.futures.ThreadPoolExecutor | None = None
        #: Why the worker process was given up for a thread, or None.
        self.lost: str | None = None
        self._pid: concurrent.futures.Future[int] | None = None

    def __enter__(self) -> ProposalWorker:
        if self.kind is WorkerKind.PROCESS:
            self._pool = concurrent.futures.ProcessPoolExecutor(
                max_workers=1, mp_context=_context(), initializer=_watch_parent,
                initargs=(os.getpid(),))
        else:
            self._pool = self._threads()
        return self

    def __exit__(self, *exc: object) -> None:
        for pool in (self._pool, self._thread_pool):
            if pool is not None:
                pool.shutdown(wait=True, cancel_futures=True)
        self._pool = self._thread_pool = None

    def start(self) -> None:
        """Start the worker now rather than at the first proposal (the call returns at once)."""
        self._pid = self._executor().submit(os.getpid)

    @property
    def pid(self) -> int | None:
        """The worker process's id once it runs (after :meth:`start`), else None (also for a thread)."""
        f = self._pid
        if not self.in_process or f is None or not f.done() or f.cancelled() or f.exception() is not None:
            return None
        return f.result()

    @property
    def in_process(self) -> bool:
        """The work runs in a worker process (not given up for a thread)."""
        return self.kind is WorkerKind.PROCESS and self.lost is None

    def start_ask(self, opt: HILOptimizer) -> asyncio.Task[Asked]:
        """Start ``opt.ask()`` in the worker on a copy of ``opt`` taken now.

        ``opt`` itself is not touched, so the caller may go on reading (logging) it; it must not
        change it before using the result, which replaces it.

        Returns:
            A task with the :class:`Asked` result (the new optimizer, the setting, the timing).
        """
        t0 = time.perf_counter()
        payload = pickle.dumps(opt, protocol=pickle.HIGHEST_PROTOCOL)
        return asyncio.ensure_future(self._ask(payload, t0))

    async def ask(self, opt: HILOptimizer) -> Asked:
        """``await start_ask(opt)``."""
        return await self.start_ask(opt)

    async def fit(self, fit: HyperparameterFit) -> GPHyperparameters:
        """:func:`hilbo_core.fit_hyperparameters` (``fit``) in the worker."""
        return await self._call(fit_hyperparameters, fit)

    # ------------------------------------------------------------------ internals
    async def _ask(self, payload: bytes, t0: float) -> Asked:
        new_opt, params, compute_s = await self._call(_ask, payload)
        return Asked(new_opt, params, compute_s, time.perf_counter() - t0)

    def _threads(self) -> concurrent.futures.ThreadPoolExecutor:
        if self._thread_pool is None:
            self._thread_pool = concurrent.futures.ThreadPoolExecutor(
                max_workers=1, thread_name_prefix="hilbo-proposal")
        return self._thread_pool

    def _executor(self) -> concurrent.futures.Executor:
        if self._pool is None:
            raise RuntimeError("ProposalWorker used outside its `with` block")
        return self._pool if self.lost is None else self._threads()

    async def _call(self, fn: Any, arg: Any) -> Any:
        loop = asyncio.get_running_loop()
        try:
            return await loop.run_in_executor(self._executor(), fn, arg)
        except BrokenProcessPool as err:
            # The argument is the caller's own object, untouched by the dead worker: the same
            # call in a thread gives exactly the result the worker would have.
            self.lost = f"the proposal worker process died ({err}); proposals continue in a thread"
            logger.error("%s", self.lost)
            return await loop.run_in_executor(self._threads(), fn, arg)
