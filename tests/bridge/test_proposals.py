"""The proposal worker: the same proposals and fits in a process or a thread; a dead worker costs nothing."""

from __future__ import annotations

import asyncio
import copy
import dataclasses
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest

from bridge.bench.perf import _synthetic_optimizer
from bridge.proposals import ProposalWorker, WorkerKind
from hilbo_core import HILOptimizer, OptimizerStateError, fit_hyperparameters


def optimizer(n_obs: int = 12) -> HILOptimizer:
    return _synthetic_optimizer(n_obs, seed=3)


@pytest.mark.parametrize("kind", list(WorkerKind))
async def test_ask_and_fit_give_what_the_optimizer_gives_in_place(kind: WorkerKind) -> None:
    opt = optimizer()
    local = copy.deepcopy(opt)
    want = local.ask()
    fit = copy.deepcopy(opt).hyperparameter_fit()
    assert fit is not None
    async with ProposalWorker(kind) as worker:
        asked = await worker.ask(opt)
        hyp = await worker.fit(fit)
    got_opt, got = asked.opt, asked.params
    assert 0 < asked.compute_s <= asked.total_s
    assert asked.to_worker_s >= 0 and asked.from_worker_s >= 0
    assert got == want
    assert got_opt.to_json() == local.to_json()  # the whole advanced state, generator included
    assert got_opt is not opt and opt.current_params is None  # the caller's copy is untouched
    assert hyp == fit_hyperparameters(fit)
    assert worker.lost is None


@pytest.mark.parametrize("kind", list(WorkerKind))
async def test_one_turn_of_the_loop_hands_the_request_to_the_worker(kind: WorkerKind) -> None:
    """The session relies on it: after a stop decision it yields once, then logs for
    milliseconds without yielding; the worker must already be computing meanwhile."""
    block_s = 0.5
    async with ProposalWorker(kind) as worker:
        await worker.worker_pid()  # started and serving
        task = worker.start_ask(optimizer())
        await asyncio.sleep(0)
        time.sleep(block_s)  # blocking the loop in wall time is the point: the session's sync logging
        asked = await task
    # Handed over before the block: received within it, not after it.
    assert asked.to_worker_s < block_s / 2


async def test_the_process_worker_runs_in_another_process() -> None:
    async with ProposalWorker(WorkerKind.PROCESS) as worker:
        assert worker.in_process
        pid = await worker.worker_pid()
        assert pid == worker.pid != os.getpid()
    assert not _alive(pid)  # the block's end stops it
    async with ProposalWorker("thread") as worker:
        assert not worker.in_process and worker.pid is None
        assert await worker.worker_pid() == os.getpid()


def _environ(pid: int) -> dict[str, str]:
    raw = Path(f"/proc/{pid}/environ").read_bytes().split(b"\0")
    return dict(item.decode().split("=", 1) for item in raw if b"=" in item)


@pytest.mark.skipif(not Path("/proc/self/environ").exists(), reason="reads /proc/PID/environ")
async def test_the_worker_process_runs_blas_single_threaded_unless_told_otherwise(monkeypatch) -> None:
    monkeypatch.delenv("OPENBLAS_NUM_THREADS", raising=False)
    monkeypatch.setenv("OMP_NUM_THREADS", "2")  # the caller's explicit setting wins
    async with ProposalWorker(WorkerKind.PROCESS) as worker:
        env = _environ(await worker.worker_pid())
    assert env["OPENBLAS_NUM_THREADS"] == "1" and env["OMP_NUM_THREADS"] == "2"


async def test_errors_in_the_worker_are_raised_in_the_session() -> None:
    opt = optimizer()
    opt._opt_breaths = 10**9  # the budget is spent: ask() refuses
    opt.config = dataclasses.replace(opt.config, budget_breaths=10)
    async with ProposalWorker(WorkerKind.PROCESS) as worker:
        with pytest.raises(OptimizerStateError, match="budget is spent"):
            await worker.ask(opt)
        assert worker.in_process  # an error of the optimizer is not a dead worker


async def test_a_dead_worker_process_is_replaced_by_a_thread_with_the_same_result() -> None:
    opt = optimizer()
    want = copy.deepcopy(opt).ask()
    async with ProposalWorker(WorkerKind.PROCESS) as worker:
        os.kill(await worker.worker_pid(), signal.SIGKILL)
        asked = await worker.ask(opt)
        assert asked.params == want and asked.opt is not opt
        assert worker.lost is not None and "died" in worker.lost
        assert not worker.in_process and worker.pid is None
        assert await worker.worker_pid() == os.getpid()  # and it stays in the thread
        again = await worker.ask(copy.deepcopy(opt))
        assert again.params == want


def test_unknown_kind_is_rejected_with_the_choices() -> None:
    with pytest.raises(ValueError, match="'gpu' is not a valid WorkerKind"):
        ProposalWorker("gpu")


def test_using_the_worker_outside_its_block_is_an_error() -> None:
    with pytest.raises(RuntimeError, match="outside its `async with` block"):
        ProposalWorker().start_ask(optimizer(3))


@pytest.mark.skipif(sys.platform == "win32", reason="kill -9 and /proc are POSIX")
def test_a_worker_exits_when_its_session_is_killed() -> None:
    # No `if __name__ == "__main__":` here on purpose: the worker does not import this script.
    script = textwrap.dedent("""
        import asyncio, sys
        from bridge.proposals import ProposalWorker

        async def main():
            async with ProposalWorker("process") as w:
                print(await w.worker_pid(), flush=True)
                await asyncio.get_running_loop().run_in_executor(None, sys.stdin.read)

        asyncio.run(main())
    """)
    proc = subprocess.Popen([sys.executable, "-c", script], stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, text=True)
    try:
        worker_pid = int(proc.stdout.readline())
        assert _alive(worker_pid)
    finally:
        proc.kill()  # kill -9: no cleanup runs in the session process
        proc.wait(timeout=30)
    # The worker reads EOF on its stdin and exits; bounded wait for a real process to end.
    deadline = time.monotonic() + 20.0
    while _alive(worker_pid) and time.monotonic() < deadline:
        time.sleep(0.05)  # a real process exiting: bounded poll
    assert not _alive(worker_pid)


async def test_a_call_cancelled_mid_way_leaves_no_worker_process() -> None:
    # Ctrl-C while the session waits for the worker's first reply (it is still importing numpy
    # and scipy): the worker is out of step and is killed and reaped on leaving the block, not
    # left to find its EOF after the session has exited.
    async with ProposalWorker(WorkerKind.PROCESS) as worker:
        pid = worker.pid
        assert pid is not None
        first = asyncio.ensure_future(worker.worker_pid())
        await asyncio.sleep(0)  # the request is on the pipe; the reply is awaited
        assert not first.done()
        first.cancel()
        with pytest.raises(asyncio.CancelledError):
            await first
        assert worker.pid is None  # nothing more goes to it
    assert not os.path.exists(f"/proc/{pid}")  # ended and reaped


def _alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] != "Z"  # a zombie has exited
    except FileNotFoundError:
        return False


def test_hyperparameter_fits_in_a_worker_are_deterministic() -> None:
    fit = optimizer(20).hyperparameter_fit()
    assert fit is not None
    a, b = fit_hyperparameters(fit), fit_hyperparameters(fit)
    assert a == b and np.all(np.isfinite(a.lengthscales))
