"""bridge.bench.executors: local processes and Dask give the same results in task order."""

from __future__ import annotations

import pytest

from bridge.bench.executors import DaskExecutor, LocalExecutor, make_executor
from bridge.bench.stopping import StoppingTask, run_stopping_task
from hilbo_core.errors import ConfigError
from hilbo_core.studies.benchmarks import StoppingProtocol

TOY = StoppingProtocol(n_explore=3, max_breaths=4, window=1, budget=8, n_candidates=32, n_local=0)
TASKS = [StoppingTask("branin", 1.0, m, s, TOY) for s in (0, 1) for m in ("fixed", "adaptive")]


def square(x: int) -> int:
    return x * x


def fail_on_three(x: int) -> int:
    if x == 3:
        raise ValueError("task 3 failed")
    return x


def _marker_task(path: str) -> bool:
    """Task 0 (no path) returns at once; task 1 returns True once ``path`` exists."""
    return True if not path else wait_for_marker(path)


def wait_for_marker(path: str) -> bool:
    """True once the parent's callback for task 0 made ``path`` (False after 30 s)."""
    import os
    import time

    deadline = time.monotonic() + 30.0  # bounded: a pool that holds results back fails, not hangs
    while time.monotonic() < deadline:
        if os.path.exists(path):
            return True
        time.sleep(0.02)  # in a pool worker process: waits for a file the parent makes, bounded
    return False


def _strip(results: list[dict]) -> list[dict]:
    return [{k: v for k, v in r.items() if k != "wall_s"} for r in results]


def test_in_process_map_keeps_task_order_and_reports_each_result() -> None:
    seen: list[tuple[int, int]] = []
    out = LocalExecutor(1, progress=False).map(square, [3, 1, 2], on_result=lambda i, r: seen.append((i, r)))
    assert out == [9, 1, 4]
    assert seen == [(0, 9), (1, 1), (2, 4)]


@pytest.mark.slow  # spawning the workers (fresh interpreters importing scipy) takes seconds
def test_process_pool_map_keeps_task_order() -> None:
    seen: dict[int, int] = {}
    out = LocalExecutor(2, progress=False).map(square, list(range(7)), on_result=seen.__setitem__)
    assert out == [k * k for k in range(7)]
    assert seen == {k: k * k for k in range(7)}


def test_a_failing_task_raises_its_own_error_in_process() -> None:
    seen: list[int] = []
    with pytest.raises(ValueError, match="task 3 failed"):
        LocalExecutor(1, progress=False).map(fail_on_three, [1, 2, 3, 4],
                                             on_result=lambda i, r: seen.append(r))
    assert seen == [1, 2]


@pytest.mark.slow
def test_process_pool_reports_each_result_as_it_finishes(tmp_path) -> None:
    # A campaign appends every finished trial to trials.jsonl from on_result: results held back
    # until the whole map ends would lose an interrupted campaign. Task 1 only finishes after
    # on_result has run for task 0.
    marker = tmp_path / "task0-reported"
    tasks = ["", str(marker)]

    out = LocalExecutor(2, progress=False).map(
        _marker_task, tasks, on_result=lambda i, r: marker.touch() if i == 0 else None)
    assert out == [True, True]


@pytest.mark.slow
def test_a_failing_task_raises_its_own_error_from_the_pool() -> None:
    with pytest.raises(ValueError, match="task 3 failed"):
        LocalExecutor(2, progress=False).map(fail_on_three, [1, 2, 3, 4])


def test_bad_worker_counts_and_addresses_are_config_errors() -> None:
    with pytest.raises(ConfigError, match="workers=0"):
        LocalExecutor(0)
    with pytest.raises(ConfigError, match="scheduler address"):
        DaskExecutor("  ")
    assert isinstance(make_executor(None, "tcp://127.0.0.1:1"), DaskExecutor)
    assert isinstance(make_executor(3, None), LocalExecutor)


@pytest.mark.slow
def test_local_processes_and_dask_give_identical_stopping_results() -> None:
    distributed = pytest.importorskip("distributed")
    serial = _strip(LocalExecutor(1, progress=False).map(run_stopping_task, TASKS))
    pooled = _strip(LocalExecutor(2, progress=False).map(run_stopping_task, TASKS))
    # A worker thread in this process, but real TCP on loopback: tasks and results are serialised.
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=False, protocol="tcp://",
                                  host="127.0.0.1", dashboard_address=None) as cluster:
        dask = _strip(DaskExecutor(cluster.scheduler_address, progress=False).map(run_stopping_task, TASKS))
    assert serial == pooled == dask
    assert [r["method"] for r in dask] == [t.method for t in TASKS]
    assert [r["seed"] for r in dask] == [t.seed for t in TASKS]


def test_unreachable_scheduler_is_a_config_error() -> None:
    pytest.importorskip("distributed")
    with pytest.raises(ConfigError, match="cannot reach the Dask scheduler"):
        DaskExecutor("tcp://127.0.0.1:9", progress=False, timeout_s=1.0).map(square, [1])
