"""Shared test machinery: tests marked ``vcan`` run over SocketCAN ``vcan0`` wherever possible.

* Natively, when this kernel has SocketCAN and a ``vcan0`` interface that a raw CAN socket can
  bind (a lab Linux PC after ``scripts/vcan-setup.sh``; inside user-mode Linux).
* Otherwise inside user-mode Linux (Debian's ``user-mode-linux``; ``scripts/ensure-uml.sh``
  installs it): after collection the ``vcan`` items are replaced by proxies and UML is booted once
  in the background (``scripts/uml_run.py``); it runs *all* selected ``vcan`` tests in one
  inner pytest with ``vcan0`` up and writes one JSON line per test phase to a host file; each
  proxy waits for it, then reports its own test's outcome (with the inner failure text and
  captured output). With pytest-xdist (``make test`` runs two workers) worker ``gw0`` boots it
  and every worker's proxies read the same files (tests/uml_batch.py).
  ``HILBO_IN_UML=1`` is set inside the guest, so the inner run never boots UML again.
* Skipped with the reason when neither is possible.

Every test runs under the autouse fixture ``_no_leaks``: a thread or a child process that the
test started and that is still alive after a short bounded grace, or a SIGINT/SIGTERM/SIGHUP
handler it did not restore, (threads joined with a
timeout, processes polled, never a fixed sleep) fails the test in its teardown, naming what
leaked; leaked child processes are then killed so the next test starts clean. An event loop left
running in a thread shows up as that thread. A loop left *set* in the main thread is not
checked: an open one appeared there around a plain sync test (pytest-asyncio 1.5 at work), so
such a check would blame the wrong test. Only the daemon threads of ``_BENIGN_THREADS`` (each
with its reason) may outlive a test.

Also the fixture ``optimize_calls``: the training-set size of every GP hyperparameter optimisation
(a spy on ``GaussianProcess._optimize``), for the tests of when fits happen.

Knobs (environment): ``HILBO_UML_TIMEOUT_S`` (whole boot, default 480 s: it shares the CPU with
the host's tests), ``HILBO_UML_MEM`` (default 1G), ``HILBO_UML_KEEP=1`` (keep the work directory
with the console log),
``HILBO_LEAK_GRACE_S`` (how long a test's threads and processes get to end, default 5 s).
"""

from __future__ import annotations

import os

# Small GP matrices: threaded BLAS only adds contention (see bridge/cli/main.py); before numpy loads.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
os.environ.setdefault("OMP_NUM_THREADS", "1")

import json
import re
import signal
import tempfile
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
import uml_batch
from uml_batch import IN_UML, REPORT_ENV, UmlBatch, UmlProxyItem, uml_problem

VCAN_CHANNEL = "vcan0"


def native_vcan_problem(channel: str = VCAN_CHANNEL) -> str | None:
    """Why SocketCAN ``channel`` is not usable natively, or None when it is."""
    from drivers.exosuit.vcan_setup import vcan_problem

    return vcan_problem(channel)


# --- inside the guest: one JSON line per test phase --------------------------------------------


def pytest_runtest_logreport(report: pytest.TestReport) -> None:
    """Inside UML, append each phase's outcome to the host-visible report file."""
    path = os.environ.get(REPORT_ENV)
    if not (IN_UML and path):
        return
    if report.skipped and isinstance(report.longrepr, tuple):
        text = str(report.longrepr[2])
    else:
        text = "" if report.longrepr is None else str(report.longrepr)
    record = {
        "nodeid": report.nodeid,
        "when": report.when,
        "outcome": report.outcome,
        "longrepr": text,
        "wasxfail": getattr(report, "wasxfail", None),
        "sections": [[title, body] for title, body in report.sections],
        "duration": report.duration,
    }
    with open(path, "a", encoding="utf-8") as fh:
        fh.write(json.dumps(record) + "\n")


# --- on the host: proxies for the vcan tests -----------------------------------------------------



# --- on the host: proxies for the vcan tests, one batch per run (tests/uml_batch.py) ----------

_BATCH_KEY = pytest.StashKey[UmlBatch]()
_WORK_KEY = pytest.StashKey[Path]()
_SUMMARY_KEY = pytest.StashKey["str | None"]()
#: The batch of this process, for the leak check (its boot's processes are no test's leak).
_CURRENT_BATCH: list[UmlBatch] = []


def uml_descendants() -> set[int]:
    """The processes of a running background UML batch (not any test's leak)."""
    return _CURRENT_BATCH[0].descendants() if _CURRENT_BATCH else set()


def _shared_work(config: pytest.Config) -> Path:
    """The batch's directory, made once by the process that is not an xdist worker."""
    work = config.stash.get(_WORK_KEY, None)
    if work is None:
        work = config.stash[_WORK_KEY] = Path(tempfile.mkdtemp(prefix="hilbo-vcan-"))
    return work


@pytest.hookimpl(optionalhook=True)
def pytest_configure_node(node: Any) -> None:
    """pytest-xdist's controller: every worker gets the one batch directory."""
    node.workerinput["hilbo_uml_work"] = str(_shared_work(node.config))


@pytest.hookimpl(trylast=True)
def pytest_collection_modifyitems(
    session: pytest.Session, config: pytest.Config, items: list[pytest.Item]
) -> None:
    """Route the selected vcan tests: native, one UML batch, or skip with the reason."""
    vcan = [i for i in items if i.get_closest_marker("vcan") is not None]
    if not vcan or IN_UML:
        return  # inside UML they run natively (or fail loudly if vcan0 is broken)
    native = native_vcan_problem()
    if native is None:
        return
    uml = uml_problem()
    if uml is not None:
        skip = pytest.mark.skip(reason=f"vcan: {native}, and {uml}")
        for item in vcan:
            item.add_marker(skip)
        return
    worker = getattr(config, "workerinput", None)
    if worker is None:
        batch = UmlBatch(config, _shared_work(config), owner=True)
    else:  # an xdist worker: gw0 boots, the others' proxies read its files
        batch = UmlBatch(config, Path(worker["hilbo_uml_work"]), owner=worker["workerid"] == "gw0")
    config.stash[_BATCH_KEY] = batch
    _CURRENT_BATCH[:] = [batch]
    # The proxies go last, so the host's tests run while the guest does; each may wait for the
    # whole boot, which pytest-timeout's per-test limit must allow.
    wait = pytest.mark.timeout(batch.timeout_s + 60.0)
    proxies = []
    for item in vcan:
        if item.parent is not None:
            proxy = UmlProxyItem.from_parent(item.parent, name=item.name, original=item, batch=batch)
            proxy.add_marker(wait)
            proxies.append(proxy)
    items[:] = [i for i in items if i.get_closest_marker("vcan") is None] + proxies


@pytest.hookimpl(tryfirst=True)
def pytest_runtestloop(session: pytest.Session) -> None:
    """Boot UML in the background once the selection is final (after ``--lf``/``-k``
    deselection), unless no test will run."""
    batch = session.config.stash.get(_BATCH_KEY, None)
    opt = session.config.option
    if batch is None or opt.collectonly or getattr(opt, "setuponly", False) \
            or getattr(opt, "setupplan", False):
        return
    batch.start([i.nodeid for i in session.items if isinstance(i, UmlProxyItem)])


def pytest_sessionfinish(session: pytest.Session, exitstatus: int) -> None:
    """The owner waits for a boot other workers may still need, or ends one nobody will wait
    for (``-x``, an interrupt); the process that made the batch's directory removes it."""
    batch = session.config.stash.get(_BATCH_KEY, None)
    if batch is not None:
        batch.finish(interrupted=exitstatus == pytest.ExitCode.INTERRUPTED
                     or bool(session.shouldstop or session.shouldfail))
    work = session.config.stash.get(_WORK_KEY, None)
    if work is not None and getattr(session.config, "workerinput", None) is None:
        # said in the terminal summary, which comes after this hook
        session.config.stash[_SUMMARY_KEY] = uml_batch.summary(work)
        uml_batch.remove(work)


def pytest_terminal_summary(terminalreporter: Any, exitstatus: int, config: pytest.Config) -> None:
    """Say that (and how) the vcan tests ran inside user-mode Linux."""
    line = config.stash.get(_SUMMARY_KEY, None)
    if line:
        terminalreporter.write_line(f"vcan: {line}")
    work = config.stash.get(_WORK_KEY, None)
    if work is not None and work.exists():  # kept: asked for, or a test did not report
        terminalreporter.write_line(f"vcan: the boot's files are kept in {work}")


@pytest.fixture
def optimize_calls(monkeypatch: pytest.MonkeyPatch) -> list[int]:
    """Training-set size of every hyperparameter optimisation (GaussianProcess._optimize)."""
    from hilbo_core.gp import GaussianProcess

    calls: list[int] = []
    original = GaussianProcess._optimize

    def spy(self, theta0, F, ys, extra, rng):
        calls.append(int(F.shape[0]))
        return original(self, theta0, F, ys, extra, rng)

    monkeypatch.setattr(GaussianProcess, "_optimize", spy)
    return calls


# --- no leaked threads or processes ---------------------------------------------------------------

#: Daemon threads that may outlive a test, by name pattern, each with why it is harmless. Keep
#: this short: a thread belongs here only when it is a process-wide singleton of a library that
#: is started once, idles, and is not the test's to stop.
_BENIGN_THREADS: dict[str, str] = {
    # distributed.utils._offload_executor: one module-global single-thread pool that Dask
    # clients offload (de)serialisation to; created at import, idle between uses, never stopped.
    r"Dask-Offload_\d+": "Dask's process-wide offload thread",
    # Note: asyncio's ThreadedChildWatcher thread per child (``waitpid-N``) is *not* listed: a
    # live one means a child process is still running.
}
#: Child processes that may outlive a test, by command-line pattern, each with why.
_BENIGN_PROCESSES: dict[str, str] = {
    # multiprocessing's resource tracker: one per interpreter, started by the first spawned
    # pool and kept until this process exits (it cleans up semaphores of killed workers).
    r".*from multiprocessing\.resource_tracker import main.*": "multiprocessing's resource tracker",
}
_BENIGN_RE = [re.compile(p) for p in _BENIGN_THREADS]
_BENIGN_PROC_RE = [re.compile(p) for p in _BENIGN_PROCESSES]


#: Threads and child processes started by the setup of fixtures broader than a function (a
#: module's server, say): they outlive the test that first requested them by design.
_broad_threads: set[threading.Thread] = set()
_broad_pids: set[int] = set()


@pytest.hookimpl(hookwrapper=True)
def pytest_fixture_setup(fixturedef: pytest.FixtureDef[Any], request: pytest.FixtureRequest) -> Any:
    """Record what a class/module/package/session fixture starts, so it is not a test's leak."""
    if fixturedef.scope == "function":
        return (yield)
    threads, pids = set(threading.enumerate()), _child_pids()
    try:
        return (yield)
    finally:
        _broad_threads.update(set(threading.enumerate()) - threads)
        _broad_pids.update(_child_pids() - pids - uml_descendants())


def _child_pids() -> set[int]:
    """Running (not zombie) descendants of this process."""
    try:
        import psutil
    except ImportError:  # /proc: direct children only, which is what a test starts
        return _proc_children(os.getpid())
    try:
        kids = psutil.Process().children(recursive=True)
    except psutil.Error:
        return set()
    alive: set[int] = set()
    for kid in kids:
        try:
            if kid.status() != psutil.STATUS_ZOMBIE:
                alive.add(kid.pid)
        except psutil.Error:
            continue  # ended meanwhile
    return alive


def _proc_children(ppid: int) -> set[int]:
    out: set[int] = set()
    try:
        names = os.listdir("/proc")
    except OSError:
        return out
    for name in names:
        if not name.isdigit():
            continue
        try:
            with open(f"/proc/{name}/stat", encoding="ascii", errors="replace") as fh:
                stat = fh.read()
        except OSError:
            continue
        fields = stat.rsplit(")", 1)[-1].split()  # after "pid (comm)": state, ppid, ...
        if len(fields) > 1 and fields[0] != "Z" and int(fields[1]) == ppid:
            out.add(int(name))
    return out


def _cmdline(pid: int) -> str:
    try:
        with open(f"/proc/{pid}/cmdline", "rb") as fh:
            return fh.read().replace(b"\0", b" ").decode(errors="replace").strip()
    except OSError:
        return "?"


def _describe_pid(pid: int) -> str:
    return f"pid {pid}: {_cmdline(pid)[:200]}"


def leaked_after(
    threads_before: set[threading.Thread], pids_before: set[int], grace_s: float
) -> tuple[list[threading.Thread], list[int]]:
    """Threads and child processes started since the snapshot and still alive after ``grace_s``.

    Threads are joined (bounded by what is left of the grace), processes polled every 10 ms;
    allowlisted daemon threads are not reported.
    """
    deadline = time.monotonic() + grace_s
    threads = [
        t for t in threading.enumerate()
        if t not in threads_before and t not in _broad_threads and t is not threading.current_thread()
        and not (t.daemon and any(r.fullmatch(t.name) for r in _BENIGN_RE))
        # A thread started outside Python (the Foxglove SDK's Rust runtime) that called into
        # it, e.g. to log: Python only has a placeholder for it, which cannot be joined; its
        # owner (the server) is checked by the test that stops it.
        and not isinstance(t, threading._DummyThread)
    ]
    for t in threads:
        t.join(timeout=max(0.0, deadline - time.monotonic()))
    pids = {p for p in _child_pids() - pids_before - _broad_pids - uml_descendants()
            if not any(r.fullmatch(_cmdline(p)) for r in _BENIGN_PROC_RE)}
    while pids and time.monotonic() < deadline:
        # Waiting for other code's children to end: they are reaped by their owner, so poll.
        threading.Event().wait(0.01)
        pids &= _child_pids()
    return [t for t in threads if t.is_alive()], sorted(pids)


def _kill_leaked(pids: list[int]) -> None:
    for pid in pids:
        try:
            os.kill(pid, signal.SIGKILL)
        except (ProcessLookupError, PermissionError):
            continue  # ended meanwhile, or the pid is no longer our child's


#: Signals whose handler a test must leave as it found it (a session installs its own for
#: SIGINT/SIGTERM and must remove them; one left behind swallows the next Ctrl-C or timeout).
_GUARDED_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)


@pytest.fixture(autouse=True)
def _no_leaks(request: pytest.FixtureRequest) -> Iterator[None]:
    """Fail a test that leaves a thread, a child process or a signal handler behind (see the
    module docstring)."""
    threads_before = set(threading.enumerate())
    pids_before = _child_pids()
    handlers_before = {sig: signal.getsignal(sig) for sig in _GUARDED_SIGNALS}
    yield
    grace_s = float(os.environ.get("HILBO_LEAK_GRACE_S", "5"))
    threads, pids = leaked_after(threads_before, pids_before, grace_s)
    handlers = [sig for sig, h in handlers_before.items() if signal.getsignal(sig) != h]
    if not threads and not pids and not handlers:
        return
    lines = [f"thread {t.name!r} (daemon={t.daemon}, target={getattr(t, '_target', None)!r})"
             for t in threads]
    lines += [_describe_pid(p) for p in pids]
    lines += [f"signal {signal.Signals(sig).name} handler {signal.getsignal(sig)!r} "
              f"(was {handlers_before[sig]!r})" for sig in handlers]
    _kill_leaked(pids)
    for sig in handlers:
        signal.signal(sig, handlers_before[sig])
    pytest.fail(
        f"{request.node.nodeid} leaked {len(threads)} thread(s), {len(pids)} process(es) and "
        f"{len(handlers)} signal handler(s) still in place {grace_s:g} s after it ended:\n  "
        + "\n  ".join(lines),
        pytrace=False,
    )
