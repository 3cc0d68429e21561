"""The vcan tests' user-mode Linux batch, shared by every pytest process of one run.

The selected ``vcan`` tests run in one UML boot (``scripts/uml_run.py``) whose inner pytest
appends one JSON line per test phase to ``report.jsonl`` in the batch's directory. On the host
each vcan test is a :class:`UmlProxyItem` that waits for its own test's lines there and reports
that outcome.

With pytest-xdist (``make test`` runs ``-n 2``) every worker collects the same proxies but only
one process *owns* the boot: worker ``gw0`` (or the only process without xdist). The controller
names the shared directory (``pytest_configure_node``); the owner starts the boot in it and,
when the boot ends, writes ``status.json``; a proxy on any worker waits for its test's
``teardown`` line, for that status (then its test did not report), or for the boot's deadline
(``batch.json``), polling the files: they are written by another process, so there is nothing
to await.
"""

from __future__ import annotations

import contextlib
import importlib.util
import json
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from types import ModuleType
from typing import Any

import pytest

IN_UML = os.environ.get("HILBO_IN_UML") == "1"
REPORT_ENV = "HILBO_UML_REPORT"
_ROOT = Path(__file__).resolve().parents[1]
#: How long a proxy on a worker that does not own the boot waits for the owner to start it.
_START_WAIT_S = 300.0
#: How often a proxy looks at the batch's files (another process writes them).
_POLL_S = 0.25
#: How long a proxy waits for status.json once the boot's process is gone.
_ORPHAN_GRACE_S = 15.0


def _running(pid: int) -> bool:
    """The process exists (a zombie too: its owner is about to reap it and write the status)."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # exists, another user's (a reused pid): not ours to judge
        return True
    return True


def uml_module() -> ModuleType:
    path = _ROOT / "scripts" / "uml_run.py"
    spec = importlib.util.spec_from_file_location("hilbo_uml_run", path)
    if spec is None or spec.loader is None:
        raise ImportError(f"cannot load {path}")
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


def uml_problem() -> str | None:
    """Why no guest (user-mode Linux, or a KVM guest on hosts where UML fails) can run the vcan
    tests here, or None when one can."""
    if IN_UML:
        return "already inside user-mode Linux"
    return uml_module().guest_problem()


class UmlTestFailure(Exception):
    """The test failed inside user-mode Linux; the message is the inner report."""


@dataclass
class Outcome:
    """One vcan test's outcome as the inner pytest reported it."""

    outcome: str = "passed"  # passed | failed | skipped | xfailed | xpassed
    text: str = ""
    sections: list[tuple[str, str]] = field(default_factory=list)
    #: Its teardown phase has reported: nothing more will come for it.
    done: bool = False


def read_report(path: Path) -> dict[str, Outcome]:
    """The outcomes in a ``report.jsonl`` so far (a line still being written is skipped)."""
    outcomes: dict[str, Outcome] = {}
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        return outcomes
    for line in text.splitlines(keepends=True):
        if not line.endswith("\n"):
            break  # the writer is half-way through it
        rec: dict[str, Any] = json.loads(line)
        out = outcomes.setdefault(rec["nodeid"], Outcome())
        # each phase's report repeats the sections of the phases before it
        out.sections.extend((t, b) for t, b in rec["sections"] if (t, b) not in out.sections)
        if rec["when"] == "teardown":
            out.done = True
        if rec["wasxfail"] is not None:
            out.outcome = "xfailed" if rec["outcome"] == "skipped" else "xpassed"
            out.text = rec["wasxfail"] or rec["longrepr"]
        elif rec["outcome"] == "failed":
            out.outcome = "failed"
            out.text += f"[{rec['when']}] {rec['longrepr']}\n"
        elif rec["outcome"] == "skipped" and out.outcome != "failed":
            out.outcome = "skipped"
            out.text = rec["longrepr"]
    return outcomes


def _read_json(path: Path) -> dict[str, Any] | None:
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (FileNotFoundError, json.JSONDecodeError):  # not written yet, or half-way
        return None


def _write_json(path: Path, value: dict[str, Any]) -> None:
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(value), encoding="utf-8")
    tmp.replace(path)  # readers in other processes see all of it or nothing


class UmlBatch:
    """All the selected vcan tests in one UML boot, started in the background.

    The owner's :meth:`start` launches the boot once the selection is final, so the guest's
    tests run beside the host's (its 2-3 minutes come off the suite's wall time); each proxy
    waits in :meth:`outcome`; the owner's :meth:`finish` waits for a boot whose results other
    workers may still need, and :meth:`close` ends one nobody will wait for (``-x``, Ctrl-C).
    The boot's output goes to files, not pipes, so nothing has to read while it runs.

    Args:
        config: This process's pytest configuration.
        work: The batch's directory, the same in every process of the run.
        owner: This process starts (and ends) the boot.
    """

    def __init__(self, config: pytest.Config, work: Path, *, owner: bool) -> None:
        self.config = config
        self.work = work
        self.owner = owner
        self.nodeids: list[str] = []
        self._proc: subprocess.Popen[bytes] | None = None
        self._watcher: threading.Thread | None = None
        self._created = time.monotonic()
        self._deadline = 0.0  # wall clock (time.time) by which the boot must have reported
        self.timeout_s = float(os.environ.get("HILBO_UML_TIMEOUT_S", "480"))

    @property
    def pid(self) -> int | None:
        """The boot's process id while it runs (its descendants are not a test's leak)."""
        return self._proc.pid if self._proc is not None and self._proc.poll() is None else None

    def start(self, nodeids: list[str]) -> None:
        """Boot UML and start the inner pytest on ``nodeids`` (owner only); returns at once."""
        if not self.owner or self._proc is not None or not nodeids:
            return
        self.nodeids = nodeids
        work = self.work
        work.mkdir(parents=True, exist_ok=True)
        inner = [
            sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-p", "no:xdist",
            "--rootdir", str(self.config.rootpath),
            "--basetemp", str(work / "basetemp"),
            "--junitxml", str(work / "junit.xml"),
            *nodeids,
        ]
        if self.config.inipath is not None:
            inner[4:4] = ["-c", str(self.config.inipath)]
        cmd = [
            sys.executable, str(_ROOT / "scripts" / "uml_run.py"),
            "--timeout", str(self.timeout_s), "--mem", os.environ.get("HILBO_UML_MEM", "1G"),
            "--env", f"{REPORT_ENV}={work / 'report.jsonl'}",
            *(["--keep"] if os.environ.get("HILBO_UML_KEEP") == "1" else []),
            "--", *inner,
        ]
        with open(work / "stdout.txt", "wb") as out, open(work / "stderr.txt", "wb") as err:
            self._proc = subprocess.Popen(cmd, cwd=self.config.rootpath, stdin=subprocess.DEVNULL,
                                          stdout=out, stderr=err, preexec_fn=_die_with_parent)
        # Written once the boot runs: a proxy that finds it waits for that process.
        self._deadline = time.time() + self.timeout_s + 30.0
        _write_json(work / "batch.json", {"deadline": self._deadline, "nodeids": nodeids,
                                          "boot_pid": self._proc.pid})
        # Writes status.json when the boot ends, for the proxies of every worker. Started before
        # any test, so it is not a test's leak; it ends with the boot.
        self._watcher = threading.Thread(target=self._watch, args=(self._proc,),
                                         name="hilbo-uml-batch", daemon=True)
        self._watcher.start()

    def _watch(self, proc: subprocess.Popen[bytes]) -> None:
        status = proc.wait()
        log = (self.work / "stderr.txt").read_text(errors="replace").strip()
        last = log.splitlines()[-1] if log else ""
        _write_json(self.work / "status.json", {
            "status": status,
            "summary": f"{len(self.nodeids)} vcan test(s) ran inside user-mode Linux "
                       f"(inner pytest status {status}); {last}"})

    def outcome(self, nodeid: str) -> Outcome:
        """Wait for ``nodeid``'s outcome from the boot.

        Raises:
            UmlTestFailure: The boot ended, or ran out of time, without reporting it.
        """
        gone: float | None = None  # when the boot's process was first seen gone
        while True:
            result = read_report(self.work / "report.jsonl").get(nodeid)
            if result is not None and result.done:
                return result
            status = _read_json(self.work / "status.json")
            if status is not None:  # the boot has ended: one last look
                result = read_report(self.work / "report.jsonl").get(nodeid)
                if result is not None and result.done:
                    return result
                raise UmlTestFailure(self._failure(f"ended with status {status['status']} "
                                                   f"without reporting {nodeid}"))
            batch = _read_json(self.work / "batch.json")
            if batch is None:
                if time.monotonic() - self._created > _START_WAIT_S:
                    raise UmlTestFailure(f"the user-mode Linux batch was not started within "
                                         f"{_START_WAIT_S:g} s (by worker gw0) in {self.work}")
            elif time.time() > batch["deadline"]:
                self.close()
                raise UmlTestFailure(self._failure(f"did not report {nodeid} within "
                                                   f"{self.timeout_s:g} s (HILBO_UML_TIMEOUT_S)"))
            elif not _running(batch["boot_pid"]):
                # Its owner writes status.json as soon as it has reaped the boot; none within
                # a grace means the owner died with it (an xdist worker that crashed).
                gone = gone if gone is not None else time.monotonic()
                if time.monotonic() - gone > _ORPHAN_GRACE_S:
                    raise UmlTestFailure(self._failure(
                        f"(pid {batch['boot_pid']}) ended without a status before reporting "
                        f"{nodeid}; the worker that started it (gw0) is gone"))
            threading.Event().wait(_POLL_S)

    def _failure(self, what: str) -> str:
        output = _tail(self.work / "stdout.txt")
        log = _tail(self.work / "stderr.txt")
        return (f"the user-mode Linux run {what}.\n--- uml_run log ({self.work}) ---\n{log}\n"
                f"--- inner output ---\n{output}")

    def finish(self, interrupted: bool) -> None:
        """At this process's end (owner): wait (bounded) for a boot other workers' proxies may
        still wait for, unless the run was interrupted; then end it."""
        proc = self._proc
        if proc is not None and not interrupted:
            with contextlib.suppress(subprocess.TimeoutExpired):
                proc.wait(timeout=max(0.0, self._deadline - time.time()))
        self.close()
        if self._watcher is not None:
            self._watcher.join(timeout=5.0)

    def close(self) -> None:
        """End a boot that is still running: SIGINT lets uml_run kill the guest's process group
        (its ``finally``); SIGKILL of what is left after 10 s."""
        proc = self._proc
        if proc is None or proc.poll() is not None:
            return
        try:
            import psutil
            tree = psutil.Process(proc.pid).children(recursive=True)
        except Exception:  # psutil missing or the process just ended: SIGINT + wait still apply
            tree = []
        proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout=10.0)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
        for child in tree:
            with contextlib.suppress(Exception):
                child.kill()

    def descendants(self) -> set[int]:
        """The boot's processes while it runs."""
        pid = self.pid
        if pid is None:
            return set()
        try:
            import psutil
            return {pid, *(c.pid for c in psutil.Process(pid).children(recursive=True))}
        except Exception:  # psutil missing (then only direct children are checked) or it ended
            return {pid}


def summary(work: Path) -> str | None:
    """The line saying how the vcan tests ran, once the boot has ended."""
    status = _read_json(work / "status.json")
    return None if status is None else str(status["summary"])


def keep(work: Path) -> bool:
    """Keep the batch's directory (its console log): asked for, or some test did not report."""
    if os.environ.get("HILBO_UML_KEEP") == "1":
        return True
    batch = _read_json(work / "batch.json")
    if batch is None:
        return False
    reported = read_report(work / "report.jsonl")
    return any(n not in reported for n in batch["nodeids"])


def remove(work: Path) -> None:
    if not keep(work):
        shutil.rmtree(work, ignore_errors=True)


def _tail(path: Path, n: int = 6000) -> str:
    try:
        return path.read_text(errors="replace")[-n:]
    except FileNotFoundError:
        return ""


def _die_with_parent() -> None:
    """In the UML batch's child: SIGTERM when pytest dies however it dies (SIGKILL too), which
    uml_run turns into killing the guest's process group (Linux prctl PR_SET_PDEATHSIG)."""
    with contextlib.suppress(Exception):  # not Linux, or no libc: close() still ends the boot
        import ctypes
        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG = 1


class UmlProxyItem(pytest.Item):
    """Stands in on the host for one vcan test that runs inside user-mode Linux."""

    def __init__(self, *, original: pytest.Item, batch: UmlBatch, **kwargs: Any) -> None:
        super().__init__(**kwargs)
        self.original = original
        self.batch = batch
        self.own_markers.extend(original.own_markers)
        self.keywords.update(original.keywords)

    def runtest(self) -> None:
        result = self.batch.outcome(self.nodeid)
        if result.sections:
            self.add_report_section("call", "inside user-mode Linux", "\n".join(
                f"----- {title} -----\n{body}" for title, body in result.sections
            ))
        if result.outcome == "skipped":
            pytest.skip(f"inside user-mode Linux: {result.text}")
        if result.outcome == "xfailed":
            pytest.xfail(f"inside user-mode Linux: {result.text}")
        if result.outcome == "failed":
            raise UmlTestFailure(result.text)

    def repr_failure(self, excinfo: pytest.ExceptionInfo[BaseException], style: Any = None) -> Any:
        if isinstance(excinfo.value, UmlTestFailure):
            return f"(ran inside user-mode Linux)\n{excinfo.value}"
        return super().repr_failure(excinfo)

    def reportinfo(self) -> tuple[Any, int | None, str]:
        path, lineno, name = self.original.reportinfo()
        return path, lineno, f"{name} [user-mode Linux]"
