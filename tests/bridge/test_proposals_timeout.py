"""The proposal worker's reply watchdog: a worker that stops answering is killed; the call runs in a thread.

The worker is stopped with SIGSTOP (alive, holding its pipes, answering nothing), the way a worker
that hangs looks to the session. Every test kills it in a ``finally`` (synchronously, so it also
runs when the coroutine is closed after a pytest timeout): a failure leaves no stopped child.
"""

from __future__ import annotations

import asyncio
import contextlib
import copy
import logging
import math
import os
import signal
import sys
import time

import pytest

from bridge.bench.perf import _synthetic_optimizer
from bridge.errors import BridgeConfigError
from bridge.proposals import ProposalWorker, WorkerKind
from hilbo_core import HILOptimizer, fit_hyperparameters

pytestmark = pytest.mark.skipif(sys.platform == "win32", reason="SIGSTOP is POSIX")

#: The short reply timeout of these tests (s); the defaults are 5 s (ask) and 60 s (fit).
TIMEOUT_S = 0.3
#: Leaving the block after a timeout must not wait for the killed worker: __aexit__ would give a
#: worker still there 5 s to exit. A bound, not a sleep.
EXIT_BOUND_S = 2.0


def optimizer(n_obs: int = 12) -> HILOptimizer:
    return _synthetic_optimizer(n_obs, seed=3)


def _kill(proc: asyncio.subprocess.Process | None) -> None:
    """SIGKILL ``proc`` unless it has been reaped (no await: safe in any ``finally``)."""
    if proc is not None and proc.returncode is None:
        with contextlib.suppress(ProcessLookupError):
            proc.kill()


async def _stopped_worker(worker: ProposalWorker) -> asyncio.subprocess.Process:
    """The entered ``worker``'s process, serving (its start allowance used up), then stopped."""
    await worker.worker_pid()
    proc = worker._proc
    assert proc is not None and worker.in_process
    os.kill(proc.pid, signal.SIGSTOP)
    return proc


def _assert_given_up(worker: ProposalWorker, name: str, caplog: pytest.LogCaptureFixture) -> None:
    assert worker.lost is not None
    assert f"did not answer the '{name}' request within {TIMEOUT_S:g} s ({name}_timeout_s)" in worker.lost
    assert not worker.in_process and worker.pid is None
    errors = [r.getMessage() for r in caplog.records
              if r.name == "bridge.proposals" and r.levelno == logging.ERROR]
    assert errors == [worker.lost]


@pytest.mark.timeout(60)
async def test_a_worker_that_stops_answering_an_ask_is_killed_and_the_ask_runs_in_a_thread(
        caplog: pytest.LogCaptureFixture) -> None:
    opt = optimizer()
    local = copy.deepcopy(opt)
    want = local.ask()
    proc = None
    try:
        async with ProposalWorker(WorkerKind.PROCESS, ask_timeout_s=TIMEOUT_S) as worker:
            proc = await _stopped_worker(worker)
            asked = await worker.ask(opt)
            returncode = proc.returncode  # before the finally's safety net
            assert asked.params == want
            assert asked.opt.to_json() == local.to_json() and asked.opt is not opt
            _assert_given_up(worker, "ask", caplog)
            assert returncode == -signal.SIGKILL  # killed and reaped before the ask returned
            assert await worker.worker_pid() == os.getpid()  # nothing more goes to that worker
            t_exit = time.monotonic()
        exit_s = time.monotonic() - t_exit
    finally:
        _kill(proc)
    assert exit_s < EXIT_BOUND_S


@pytest.mark.timeout(60)
async def test_a_worker_that_stops_answering_a_fit_is_killed_and_the_fit_runs_in_a_thread(
        caplog: pytest.LogCaptureFixture) -> None:
    fit = optimizer().hyperparameter_fit()
    assert fit is not None
    want = fit_hyperparameters(copy.deepcopy(fit))
    proc = None
    try:
        async with ProposalWorker(WorkerKind.PROCESS, fit_timeout_s=TIMEOUT_S) as worker:
            proc = await _stopped_worker(worker)
            hyp = await worker.fit(fit)
            returncode = proc.returncode
            assert hyp == want
            _assert_given_up(worker, "fit", caplog)
            assert returncode == -signal.SIGKILL
            t_exit = time.monotonic()
        exit_s = time.monotonic() - t_exit
    finally:
        _kill(proc)
    assert exit_s < EXIT_BOUND_S


@pytest.mark.timeout(60)
async def test_the_first_reply_may_also_wait_for_the_worker_to_start() -> None:
    """Starting takes about 1.5 s (numpy, scipy): far over this ask timeout, not a lost worker."""
    async with ProposalWorker(WorkerKind.PROCESS, ask_timeout_s=0.05) as worker:
        assert await worker.worker_pid() == worker.pid != os.getpid()
        assert worker.lost is None


@pytest.mark.parametrize("name", ["ask_timeout_s", "fit_timeout_s", "start_timeout_s"])
@pytest.mark.parametrize("value", [0, -1.0, math.nan, math.inf, "5", True, None])
def test_a_bad_timeout_is_rejected_naming_the_value(name: str, value: object) -> None:
    with pytest.raises(BridgeConfigError) as err:
        ProposalWorker(WorkerKind.PROCESS, **{name: value})
    assert isinstance(err.value, ValueError)
    assert str(err.value) == (f"ProposalWorker: {name} must be a positive finite number of seconds, "
                              f"got {value!r}")


def test_timeouts_are_keyword_arguments_in_seconds() -> None:
    worker = ProposalWorker("thread", ask_timeout_s=2, fit_timeout_s=30.5, start_timeout_s=10)
    assert (worker.ask_timeout_s, worker.fit_timeout_s, worker.start_timeout_s) == (2.0, 30.5, 10.0)
    default = ProposalWorker()
    assert (default.ask_timeout_s, default.fit_timeout_s, default.start_timeout_s) == (5.0, 60.0, 60.0)
