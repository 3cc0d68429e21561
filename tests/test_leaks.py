"""The autouse leak check of tests/conftest.py fails a test that leaves a thread, a child
process or a signal handler behind, and lets one that cleans up (or whose thread ends within
the grace) pass."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.timeout(120)

_CONFTEST = Path(__file__).with_name("conftest.py")

_TESTS = '''
import signal, subprocess, sys, threading

import pytest

_stop = threading.Event()


def test_leaks_a_thread():
    threading.Thread(target=_stop.wait, name="leaky-thread", daemon=True).start()


def test_leaks_a_process():
    subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])


def test_thread_that_ends_within_the_grace_is_fine():
    threading.Thread(target=threading.Event().wait, args=(0.2,), name="short").start()


def test_process_reaped_is_fine():
    subprocess.run([sys.executable, "-c", "pass"], check=True)


@pytest.fixture(scope="module")
def server():
    proc = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    yield proc
    proc.kill()
    proc.wait()


def test_a_module_fixture_process_is_not_the_test_s_leak(server):
    assert server.poll() is None


def test_the_module_fixture_process_is_still_alive(server):
    assert server.poll() is None  # not killed as a leak of the test before


def test_leaks_a_signal_handler():
    signal.signal(signal.SIGTERM, lambda *_: None)


def test_the_handler_was_restored():
    assert signal.getsignal(signal.SIGTERM) is signal.SIG_DFL


def test_zzz_cleanup():
    _stop.set()
'''


def test_leak_check_fails_leakers_only(tmp_path: Path) -> None:
    shutil.copy(_CONFTEST, tmp_path / "conftest.py")
    shutil.copy(_CONFTEST.with_name("uml_batch.py"), tmp_path / "uml_batch.py")  # it imports it
    (tmp_path / "test_leaky.py").write_text(_TESTS, encoding="utf-8")
    env = dict(os.environ, HILBO_LEAK_GRACE_S="1")
    proc = subprocess.run(
        [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-p", "no:randomly",
         "--rootdir", str(tmp_path), "-c", os.devnull, str(tmp_path / "test_leaky.py")],
        cwd=tmp_path, env=env, capture_output=True, text=True, timeout=100, check=False,
    )
    out = proc.stdout
    assert proc.returncode == 1, out
    assert "9 passed, 3 errors" in out, out
    assert "ERROR test_leaky.py::test_leaks_a_thread" in out
    assert "ERROR test_leaky.py::test_leaks_a_process" in out
    assert "ERROR test_leaky.py::test_leaks_a_signal_handler" in out
    assert "leaked 1 thread(s), 0 process(es) and 0 signal" in out and "'leaky-thread' (daemon=True" in out
    assert "leaked 0 thread(s), 1 process(es) and 0 signal" in out and "time.sleep(60)" in out
    assert "leaked 0 thread(s), 0 process(es) and 1 signal" in out and "signal SIGTERM handler" in out
