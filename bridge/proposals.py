"""Where a session's GP work runs: proposals and hyperparameter fits, in a worker process or a thread.

Why a process by default: the bridge's event loop handles about 2000 CAN frames/s of force
feedback plus heartbeats and logging, in Python. A proposal computed in a thread of the same
process competes with that loop for the GIL: in ``hilbo bench perf --bridge-minutes 5`` the
proposal thread used ≈ 15 ms of CPU per proposal but took 35–48 ms of wall time
(docs/results.md, "Compute latency"). A worker process computes on the other core.

The worker is a plain child interpreter, ``python -m bridge.proposals``, that reads requests from
its stdin and answers on its stdout (length-prefixed pickles), read by the event loop itself
(asyncio subprocess pipes: no thread hand-offs on the way back). Not ``multiprocessing``: its
spawn and forkserver children import the parent's ``__main__``, so a lab script without the
``if __name__ == "__main__":`` idiom would run its own session a second time inside the worker
(open the bus, truncate the log) before failing. The child also ends by itself when its stdin
closes, i.e. when the session's process is gone, even after ``kill -9``.

The optimizer travels by pickle (≈ 15 kB at 60 evaluations, about a millisecond each way),
taken when the ask is started (:meth:`ProposalWorker.start_ask`), so the session can log the
evaluation that just ended while the worker computes; the worker returns the advanced optimizer,
which replaces the session's copy (in a thread too: the thread works on its own copy). A worker
that dies (killed, out of memory) costs nothing collected: the call is repeated in a thread and
the session goes on there (:attr:`ProposalWorker.lost` says why). So does a worker that stops
answering (stopped, stuck): a watchdog on each reply (``ask_timeout_s``, ``fit_timeout_s``, wall
clock) kills it (SIGKILL) and repeats the call in a thread, so the person does not walk on at the
last profile for the rest of the session.
"""

from __future__ import annotations

import asyncio
import concurrent.futures
import contextlib
import enum
import gc
import logging
import math
import numbers
import os
import pickle
import signal
import struct
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, BinaryIO

from bridge.errors import BridgeConfigError
from hilbo_core import HILOptimizer, HyperparameterFit, fit_hyperparameters
from hilbo_core.gp import GPHyperparameters

__all__ = ["Asked", "ProposalWorker", "WorkerKind"]

logger = logging.getLogger(__name__)

_HEADER = struct.Struct("<Q")  # payload length in bytes
#: How long the session waits for the worker to exit at the end before killing it (s).
_EXIT_TIMEOUT_S = 5.0
#: How long the session waits for a killed worker to be reaped before going on without it (s).
_REAP_TIMEOUT_S = 5.0
#: The worker's BLAS runs single-threaded unless the caller's environment says otherwise: the
#: GP's matrices are small, and a second BLAS thread only takes CPU from the bridge's process
#: (measured: a fitted-ahead ask at 60 observations, 20 reps beside a busy core, used 22 ms of
#: CPU for 15 ms of wall time with 2 threads, 14 for 14 with one). ``hilbo`` sets the same for
#: itself (bridge/cli/main.py); this covers sessions started from Python.
_WORKER_ENV_DEFAULTS = {"OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1"}


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
        to_worker_s: From the start of the call to the worker starting on it (s).
        from_worker_s: From the worker's end of ``ask()`` to the result in the caller's event
            loop (s).
    """

    opt: HILOptimizer
    params: dict[str, float]
    compute_s: float
    total_s: float
    to_worker_s: float = math.nan
    from_worker_s: float = math.nan


def _ask(payload: bytes) -> tuple[HILOptimizer, dict[str, float], float, float, float]:
    """``ask()`` of the pickled optimizer ``payload``, returning the advanced optimizer too (it
    comes back from another process), when the ask started and ended (``time.monotonic``, the
    same clock in every process of the machine) and how long it took."""
    start = time.monotonic()
    opt = pickle.loads(payload)
    t0 = time.perf_counter()
    params = opt.ask()
    return opt, params, time.perf_counter() - t0, start, time.monotonic()


def _pid(_: object = None) -> int:
    return os.getpid()


#: What a worker may be asked to run, by name (the request names the function, not pickles it).
_FUNCTIONS: dict[str, Callable[[Any], Any]] = {"ask": _ask, "fit": fit_hyperparameters, "pid": _pid}


def _seconds(name: str, value: object) -> float:
    """``value`` as a timeout in seconds, or :class:`BridgeConfigError` naming it."""
    if (isinstance(value, bool) or not isinstance(value, numbers.Real)
            or not math.isfinite(value) or value <= 0):
        raise BridgeConfigError(
            f"ProposalWorker: {name} must be a positive finite number of seconds, got {value!r}")
    return float(value)


def _read_message(stream: BinaryIO) -> bytes | None:
    header = stream.read(_HEADER.size)
    if len(header) < _HEADER.size:
        return None  # the session closed our stdin: it ended (or died)
    (n,) = _HEADER.unpack(header)
    data = stream.read(n)
    return data if len(data) == n else None


def _serve(stdin: BinaryIO, stdout: BinaryIO) -> None:
    """The worker's loop: one request at a time until stdin closes."""
    while (request := _read_message(stdin)) is not None:
        name, arg = pickle.loads(request)
        try:
            reply: tuple[str, Any] = ("ok", _FUNCTIONS[name](arg))
        except Exception as err:  # sent back and raised in the session
            reply = ("error", err)
        try:
            data = pickle.dumps(reply, protocol=pickle.HIGHEST_PROTOCOL)
        except Exception as err:  # an unpicklable result or exception
            data = pickle.dumps(("error", RuntimeError(f"{name}: unpicklable reply: {err!r}")))
        stdout.write(_HEADER.pack(len(data)) + data)
        stdout.flush()


class ProposalWorker:
    """Runs :meth:`HILOptimizer.ask` and hyperparameter fits off the event loop.

    One call at a time (one worker): a fit made ahead finishes before the next proposal starts.
    Use as an async context manager; entering starts the worker process (it imports numpy and
    scipy, about a second, while the session's warm-up walk goes on).

    A worker process that does not answer a call in time (wall clock, from the request to the
    reply) is killed (SIGKILL, which also ends a stopped process) and given up, like one that
    died: the call is repeated in a thread, whose result is returned, and so is every later call.

    Args:
        kind: :class:`WorkerKind` (or its value).
        ask_timeout_s: How long a worker process may take to answer an ask (s): an ask takes
            10–40 ms, a cold one under a second. Also the limit of :meth:`worker_pid`.
        fit_timeout_s: How long a worker process may take to answer a hyperparameter fit (s):
            fits take up to a few seconds.
        start_timeout_s: Allowed in addition for the worker's first reply, which also waits for
            the process to start (importing numpy and scipy: about 1.5 s on an idle machine,
            several on a busy one) (s).

    Raises:
        BridgeConfigError: A timeout is not a positive finite number of seconds (also a
            ``ValueError``).
    """

    def __init__(self, kind: WorkerKind | str = WorkerKind.PROCESS, *, ask_timeout_s: float = 5.0,
                 fit_timeout_s: float = 60.0, start_timeout_s: float = 60.0) -> None:
        self.kind = WorkerKind(kind)
        self.ask_timeout_s = _seconds("ask_timeout_s", ask_timeout_s)
        self.fit_timeout_s = _seconds("fit_timeout_s", fit_timeout_s)
        self.start_timeout_s = _seconds("start_timeout_s", start_timeout_s)
        self._answered = False  # the worker process has answered a call (it has started)
        self._proc: asyncio.subprocess.Process | None = None
        self._abandoned: asyncio.subprocess.Process | None = None  # left mid-call by a cancellation
        self._lock: asyncio.Lock | None = None
        self._threads: concurrent.futures.ThreadPoolExecutor | None = None
        #: Why the worker process was given up for a thread, or None.
        self.lost: str | None = None

    async def __aenter__(self) -> ProposalWorker:
        self._lock = asyncio.Lock()  # also marks the worker as entered
        self._answered = False  # a new process: its first reply also waits for it to start
        if self.kind is WorkerKind.PROCESS:
            try:
                self._proc = await asyncio.create_subprocess_exec(
                    sys.executable, "-m", "bridge.proposals",
                    stdin=asyncio.subprocess.PIPE, stdout=asyncio.subprocess.PIPE,
                    env=_WORKER_ENV_DEFAULTS | dict(os.environ))
            except OSError as err:
                self._give_up(f"the proposal worker process could not start ({err})")
        return self

    async def __aexit__(self, *exc: object) -> None:
        abandoned, self._abandoned = self._abandoned, None
        proc, self._proc = self._proc, None
        try:
            if abandoned is not None:
                await self._kill(abandoned)
            if proc is not None:
                if proc.stdin is not None:
                    proc.stdin.close()  # the worker's loop ends at EOF
                try:
                    async with asyncio.timeout(_EXIT_TIMEOUT_S):
                        await proc.wait()
                except TimeoutError:
                    logger.warning("proposal worker %d did not exit; killing it", proc.pid)
                    await self._kill(proc)
        finally:
            # Also when cancelled again while waiting (a second Ctrl-C): the worker must not
            # outlive the session.
            if proc is not None and proc.returncode is None:
                with contextlib.suppress(ProcessLookupError):
                    proc.kill()
            if self._threads is not None:
                self._threads.shutdown(wait=True, cancel_futures=True)
                self._threads = None
            self._lock = None

    @property
    def in_process(self) -> bool:
        """The work runs in a worker process (not given up for a thread)."""
        return self.kind is WorkerKind.PROCESS and self.lost is None

    @property
    def pid(self) -> int | None:
        """The worker process's id, or None (a thread, or given up)."""
        return self._proc.pid if self._proc is not None and self.in_process else None

    def start_ask(self, opt: HILOptimizer) -> asyncio.Task[Asked]:
        """Start ``opt.ask()`` in the worker on a copy of ``opt`` taken now.

        ``opt`` itself is not touched, so the caller may go on reading (logging) it; it must not
        change it before using the result, which replaces it.

        Returns:
            A task with the :class:`Asked` result (the new optimizer, the setting, the timing).
        """
        self._check_entered()
        t0, m0 = time.perf_counter(), time.monotonic()
        payload = pickle.dumps(opt, protocol=pickle.HIGHEST_PROTOCOL)
        return asyncio.ensure_future(self._ask(payload, t0, m0))

    async def ask(self, opt: HILOptimizer) -> Asked:
        """``await start_ask(opt)``."""
        return await self.start_ask(opt)

    async def fit(self, fit: HyperparameterFit) -> GPHyperparameters:
        """:func:`hilbo_core.fit_hyperparameters` (``fit``) in the worker."""
        return await self._call("fit", fit)

    async def worker_pid(self) -> int:
        """The process id the work runs in (this process's in a thread), asked of the worker."""
        return await self._call("pid", None)

    # ------------------------------------------------------------------ internals
    async def _ask(self, payload: bytes, t0: float, m0: float) -> Asked:
        new_opt, params, compute_s, start, end = await self._call("ask", payload)
        return Asked(new_opt, params, compute_s, time.perf_counter() - t0, to_worker_s=start - m0,
                     from_worker_s=time.monotonic() - end)

    def _check_entered(self) -> asyncio.Lock:
        if self._lock is None:
            raise RuntimeError("ProposalWorker used outside its `async with` block")
        return self._lock

    def _give_up(self, why: str) -> None:
        if self.lost is None:
            self.lost = f"{why}; proposals continue in a thread"
            logger.error("%s", self.lost)

    def _timeout(self, name: str) -> tuple[float, str]:
        """The reply timeout of a ``name`` call now (s), and which arguments make it."""
        timeout_s, what = ((self.fit_timeout_s, "fit_timeout_s") if name == "fit"
                           else (self.ask_timeout_s, "ask_timeout_s"))
        if not self._answered:
            return timeout_s + self.start_timeout_s, f"{what} + start_timeout_s: its first reply"
        return timeout_s, what

    async def _call(self, name: str, arg: Any) -> Any:
        async with self._check_entered():  # one request on the pipe at a time
            proc = self._proc
            if proc is not None and self.lost is None:
                timeout_s, what = self._timeout(name)
                watchdog = asyncio.timeout(timeout_s)  # one timer handle: no thread, no polling
                try:
                    async with watchdog:
                        status, value = await self._request(proc, name, arg)
                except (BrokenPipeError, ConnectionResetError, asyncio.IncompleteReadError) as err:
                    code = proc.returncode
                    self._give_up(f"the proposal worker process died (exit status {code}, {err!r})")
                except TimeoutError:
                    if not watchdog.expired():
                        raise
                    # The reply may still come, out of step with the next request: nothing more
                    # goes to this worker. Given up before the awaits below, so a cancellation
                    # there leaves no half-state; __aexit__ no longer waits for it.
                    self._proc = None
                    if proc.stdin is not None:
                        proc.stdin.close()
                    self._give_up(f"the proposal worker process {proc.pid} did not answer the "
                                  f"{name!r} request within {timeout_s:g} s ({what}); killed it")
                    await self._kill(proc)
                except asyncio.CancelledError:
                    # Its reply is still on the way: the pipe is out of step, so nothing more goes
                    # to this worker (only at a session's end in practice). It may be busy for
                    # seconds (a fit, or still importing at a Ctrl-C right after the start), so
                    # __aexit__ kills and reaps it rather than let it outlive the session.
                    self._proc, self._abandoned = None, proc
                    if proc.stdin is not None:
                        proc.stdin.close()
                    raise
                else:
                    self._answered = True
                    if status == "error":
                        raise value
                    return value
            # A thread: the same function on the same argument gives the same result.
            if self._threads is None:
                self._threads = concurrent.futures.ThreadPoolExecutor(
                    max_workers=1, thread_name_prefix="hilbo-proposal")
            return await asyncio.get_running_loop().run_in_executor(self._threads, _FUNCTIONS[name], arg)

    @staticmethod
    async def _kill(proc: asyncio.subprocess.Process) -> None:
        """SIGKILL the worker (a stopped one too) and wait for it to be reaped; bounded, so a
        session never hangs on it."""
        with contextlib.suppress(ProcessLookupError):
            proc.kill()
        try:
            async with asyncio.timeout(_REAP_TIMEOUT_S):
                await proc.wait()
        except TimeoutError:
            logger.warning("killed proposal worker %d not reaped after %g s; going on without",
                           proc.pid, _REAP_TIMEOUT_S)

    @staticmethod
    async def _request(proc: asyncio.subprocess.Process, name: str, arg: Any) -> tuple[str, Any]:
        if proc.stdin is None or proc.stdout is None:
            raise BrokenPipeError("the worker's pipes are closed")
        data = pickle.dumps((name, arg), protocol=pickle.HIGHEST_PROTOCOL)
        proc.stdin.write(_HEADER.pack(len(data)) + data)
        await proc.stdin.drain()
        (n,) = _HEADER.unpack(await proc.stdout.readexactly(_HEADER.size))
        return pickle.loads(await proc.stdout.readexactly(n))


if __name__ == "__main__":  # the worker process: python -m bridge.proposals
    # Ctrl-C (SIGINT to the terminal's process group) is the session's to handle: it stops
    # safely and closes our stdin, which ends this loop. Raised here it would only print a
    # KeyboardInterrupt traceback and cost the session its worker mid-shutdown.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    # The replies get the real stdout to themselves; anything a library prints goes to stderr.
    _replies = os.fdopen(os.dup(sys.stdout.fileno()), "wb")
    os.dup2(sys.stderr.fileno(), sys.stdout.fileno())
    # The imports' objects live as long as the worker: out of the collector's walks, so an
    # automatic full collection inside an ask costs a few ms, not ~40 (bridge/collector.py).
    gc.freeze()
    _serve(sys.stdin.buffer, _replies)
