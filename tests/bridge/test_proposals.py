"""The proposal worker: the same proposals and fits in a process or a thread; a dead worker costs nothing."""

from __future__ import annotations

import copy
import os
import signal
import subprocess
import sys
import textwrap
import time

import numpy as np
import pytest

from bridge.bench.perf import _synthetic_optimizer
from bridge.proposals import ProposalWorker, WorkerKind
from hilbo_core import HILOptimizer, fit_hyperparameters


def optimizer(n_obs: int = 12) -> HILOptimizer:
    return _synthetic_optimizer(n_obs, seed=3)


def _worker_pid(worker: ProposalWorker) -> int:
    return worker._executor().submit(os.getpid).result(timeout=60)


@pytest.mark.parametrize("kind", list(WorkerKind))
async def test_ask_and_fit_give_what_the_optimizer_gives_in_place(kind: WorkerKind) -> None:
    opt = optimizer()
    local = copy.deepcopy(opt)
    want = local.ask()
    fit = copy.deepcopy(opt).hyperparameter_fit()
    assert fit is not None
    with ProposalWorker(kind) as worker:
        worker.start()
        asked = await worker.ask(opt)
        hyp = await worker.fit(fit)
    got_opt, got = asked.opt, asked.params
    assert 0 < asked.compute_s <= asked.total_s
    assert got == want
    assert got_opt.to_json() == local.to_json()  # the whole advanced state, generator included
    assert got_opt is not opt and opt.current_params is None  # the caller's copy is untouched
    assert hyp == fit_hyperparameters(fit)
    assert worker.lost is None


async def test_the_process_worker_runs_in_another_process() -> None:
    with ProposalWorker(WorkerKind.PROCESS) as worker:
        assert worker.in_process
        assert _worker_pid(worker) != os.getpid()
    with ProposalWorker("thread") as worker:
        assert not worker.in_process
        assert _worker_pid(worker) == os.getpid()


async def test_a_dead_worker_process_is_replaced_by_a_thread_with_the_same_result() -> None:
    opt = optimizer()
    want = copy.deepcopy(opt).ask()
    with ProposalWorker(WorkerKind.PROCESS) as worker:
        pid = _worker_pid(worker)
        os.kill(pid, signal.SIGKILL)
        asked = await worker.ask(opt)
        got_opt, got = asked.opt, asked.params
        assert got == want and got_opt is not opt
        assert worker.lost is not None and "died" in worker.lost
        assert not worker.in_process
        assert _worker_pid(worker) == os.getpid()  # and it stays in the thread
        again = await worker.ask(copy.deepcopy(opt))
        assert again.params == want


def test_unknown_kind_is_rejected_with_the_choices() -> None:
    with pytest.raises(ValueError, match="'gpu' is not a valid WorkerKind"):
        ProposalWorker("gpu")


def test_using_the_worker_outside_its_block_is_an_error() -> None:
    with pytest.raises(RuntimeError, match="outside its `with` block"):
        ProposalWorker().start()


@pytest.mark.skipif(sys.platform == "win32", reason="kill -9 and /proc are POSIX")
def test_a_worker_exits_when_its_session_is_killed(tmp_path) -> None:
    script = textwrap.dedent("""
        import os, sys
        from bridge.proposals import ProposalWorker
        w = ProposalWorker("process").__enter__()
        print(w._executor().submit(os.getpid).result(timeout=60), flush=True)
        sys.stdin.read()  # until killed
    """)
    proc = subprocess.Popen([sys.executable, "-c", script], stdin=subprocess.PIPE,
                            stdout=subprocess.PIPE, text=True)
    try:
        worker_pid = int(proc.stdout.readline())
        assert _alive(worker_pid)
    finally:
        proc.kill()  # kill -9: no cleanup runs in the session process
        proc.wait(timeout=30)
    # The worker polls its session every 0.5 s; bounded wait for a real process to exit.
    deadline = time.monotonic() + 20.0
    while _alive(worker_pid) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not _alive(worker_pid)


def _alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().split()[2] != "Z"  # a zombie has exited
    except FileNotFoundError:
        return False


def test_hyperparameter_fits_in_a_worker_are_deterministic() -> None:
    fit = optimizer(20).hyperparameter_fit()
    assert fit is not None
    a, b = fit_hyperparameters(fit), fit_hyperparameters(fit)
    assert a == b and np.all(np.isfinite(a.lengthscales))
