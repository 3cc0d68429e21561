#!/usr/bin/env python3
"""Run one command inside user-mode Linux with a SocketCAN ``vcan0`` up, and report its result.

Why: the vcan tests need SocketCAN, and the kernel of this machine (and of many CI runners) has
no ``AF_CAN``. Debian's ``user-mode-linux`` kernel has the CAN modules, and it boots in a few
seconds with the host's own filesystem as its root (hostfs), so the project's virtualenv, the
sources and this command's result files are shared with the host unchanged.

What it does: write an init script into a fresh work directory under ``/tmp``; boot
``linux.uml mem=... rootfstype=hostfs rootflags=/ rw init=SCRIPT con=null``; the script mounts
/proc, /sys, /dev (+ /dev/pts, /dev/shm), ``insmod``s can, can-raw, can-bcm, can-dev and vcan
from the module tree the package installs (``/usr/lib/uml/modules/<release>/``), brings up
``vcan0``, runs the command in the caller's working directory with ``HILBO_IN_UML=1`` set (the
recursion guard read by tests/conftest.py), writes its output and exit status to the work
directory, and powers the machine off through sysrq. The whole UML process group is killed if
it outlives ``--timeout``.

Usage::

    scripts/uml_run.py [--timeout S] [--mem SIZE] [--env K=V ...] [--keep] -- CMD [ARG ...]

Exit status: the command's, or 124 on timeout, 125 when UML could not run the command (the
console log is shown), 127 when user-mode Linux is not installed. Standard library only, so it
runs with any Python 3.9+.
"""

from __future__ import annotations

import argparse
import glob
import logging
import os
import shlex
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

__all__ = ["IN_UML_ENV", "UmlResult", "find_uml", "main", "run_in_uml"]

log = logging.getLogger("uml_run")

#: Set to "1" inside the UML guest; tests/conftest.py reads it so it never boots UML recursively.
IN_UML_ENV = "HILBO_IN_UML"

_MODULES = (
    "net/can/can.ko",
    "net/can/can-raw.ko",
    "net/can/can-bcm.ko",
    "drivers/net/can/dev/can-dev.ko",
    "drivers/net/can/vcan.ko",
)

EXIT_TIMEOUT = 124
EXIT_UML_FAILED = 125
EXIT_NO_UML = 127


class UmlResult:
    """Outcome of one boot.

    Attributes:
        status: the command's exit status, or None when it never finished.
        timed_out: True when the boot was killed at the timeout.
        output: the command's combined stdout/stderr (text).
        console: the UML console log (kernel and init messages), for diagnosing a failed boot.
        work_dir: the host directory that held the init script and the result files.
        elapsed_s: wall-clock seconds from boot to power-off.
    """

    def __init__(
        self,
        status: int | None,
        timed_out: bool,
        output: str,
        console: str,
        work_dir: Path,
        elapsed_s: float,
    ) -> None:
        self.status = status
        self.timed_out = timed_out
        self.output = output
        self.console = console
        self.work_dir = work_dir
        self.elapsed_s = elapsed_s

    def __repr__(self) -> str:
        return (
            f"UmlResult(status={self.status}, timed_out={self.timed_out}, "
            f"elapsed_s={self.elapsed_s:.1f}, work_dir={str(self.work_dir)!r})"
        )


def find_uml() -> tuple[str, str] | None:
    """Locate the UML kernel and its CAN module tree.

    Returns:
        (path of ``linux.uml``, why-not message) — the message is empty when everything needed
        (linux.uml, insmod, ip, vcan.ko) is present; None when ``linux.uml`` itself is missing.
    """
    kernel = shutil.which("linux.uml") or ("/usr/bin/linux.uml" if os.path.exists(
        "/usr/bin/linux.uml") else None)
    if kernel is None:
        return None
    missing = []
    for tool in ("insmod", "ip"):
        if shutil.which(tool) is None and not any(
            os.path.exists(f"{d}/{tool}") for d in ("/usr/sbin", "/sbin", "/usr/bin", "/bin")
        ):
            missing.append(tool)
    if not glob.glob("/usr/lib/uml/modules/*/kernel/drivers/net/can/vcan.ko"):
        missing.append("vcan.ko under /usr/lib/uml/modules")
    return kernel, ("missing: " + ", ".join(missing)) if missing else ""


def _init_script(work: Path, cwd: Path, env: dict[str, str], command: list[str]) -> str:
    exports = "\n".join(f"export {k}={shlex.quote(v)}" for k, v in sorted(env.items()))
    modules = " ".join(_MODULES)
    cmd = " ".join(shlex.quote(c) for c in command)
    w = shlex.quote(str(work))
    # Everything the guest writes goes to the work dir, which the host reads after power-off
    # (hostfs writes straight through to the host file). The status file is written last.
    return f"""#!/bin/bash
export PATH=/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin
exec >{w}/setup.log 2>&1
mount -t proc proc /proc
mount -t sysfs sysfs /sys
mountpoint -q /dev || mount -t devtmpfs devtmpfs /dev
mkdir -p /dev/pts /dev/shm
mount -t devpts devpts /dev/pts
mount -t tmpfs tmpfs /dev/shm
mods=/usr/lib/uml/modules/$(uname -r)/kernel
for m in {modules}; do insmod "$mods/$m" || echo "insmod $m failed"; done
ip link set lo up
ip link add dev vcan0 type vcan && ip link set up vcan0
ip -details link show vcan0
export HOME=${{HOME:-/root}} LANG=C.UTF-8 {IN_UML_ENV}=1
{exports}
cd {shlex.quote(str(cwd))}
{cmd} >{w}/output 2>&1 </dev/null
echo $? >{w}/status.tmp
sync
mv {w}/status.tmp {w}/status
sync
echo o >/proc/sysrq-trigger
"""


def _read(path: Path) -> str:
    try:
        return path.read_text(errors="replace")
    except FileNotFoundError:
        return ""


def _kill_group(proc: subprocess.Popen[bytes]) -> None:
    """SIGKILL the guest's whole process group until none of it is left (bounded: 5 s)."""
    deadline = time.monotonic() + 5.0
    while time.monotonic() < deadline:
        try:
            os.killpg(proc.pid, signal.SIGKILL)
        except ProcessLookupError:
            break  # the whole group is gone: the normal case after a clean power-off
        if proc.poll() is None:
            try:
                proc.wait(timeout=0.1)
            except subprocess.TimeoutExpired:
                continue
        time.sleep(0.02)
    else:
        log.warning("UML process group %d still present after SIGKILL", proc.pid)
    proc.wait()


def run_in_uml(
    command: list[str],
    *,
    timeout_s: float = 240.0,
    mem: str = "1G",
    env: dict[str, str] | None = None,
    cwd: Path | None = None,
    keep: bool = False,
) -> UmlResult:
    """Boot UML once, run ``command`` in it with vcan0 up, and return what happened.

    Args:
        command: argv of the command to run inside the guest (absolute paths are safest).
        timeout_s: the whole boot (start to power-off) is killed after this many seconds.
        mem: UML memory size (``mem=`` boot option).
        env: extra environment for the command (``HILBO_IN_UML=1`` is always set).
        cwd: working directory of the command (default: the caller's).
        keep: keep the work directory (init script, console log, output) for inspection.

    Returns:
        An :class:`UmlResult`.

    Raises:
        FileNotFoundError: user-mode Linux is not installed.
    """
    found = find_uml()
    if found is None or found[1]:
        raise FileNotFoundError(
            "user-mode Linux is not usable here ("
            + ("linux.uml not found" if found is None else found[1])
            + "); install it with `apt-get install user-mode-linux kmod iproute2`"
        )
    kernel = found[0]
    work = Path(tempfile.mkdtemp(prefix="hilbo-uml-"))
    (work / "uml").mkdir()
    init = work / "init"
    init.write_text(_init_script(work, (cwd or Path.cwd()).resolve(), env or {}, command))
    init.chmod(0o755)
    argv = [
        kernel,
        f"mem={mem}",
        "rootfstype=hostfs",
        "rootflags=/",
        "rw",
        "quiet",
        f"init={init}",
        "con=null",
        f"uml_dir={work / 'uml'}",
    ]
    log.debug("booting %s", " ".join(argv))
    t0 = time.monotonic()
    timed_out = False
    with open(work / "console.log", "wb") as console:
        # A new session, so that a hung guest is killed with all its host helper processes.
        proc = subprocess.Popen(
            argv, stdin=subprocess.DEVNULL, stdout=console, stderr=subprocess.STDOUT,
            start_new_session=True,
        )
        try:
            proc.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            timed_out = True
        finally:
            _kill_group(proc)
    elapsed_s = time.monotonic() - t0
    status_text = _read(work / "status").strip()
    status = int(status_text) if status_text.lstrip("-").isdigit() else None
    result = UmlResult(
        status=status,
        timed_out=timed_out and status is None,
        output=_read(work / "output"),
        console=_read(work / "console.log") + _read(work / "setup.log"),
        work_dir=work,
        elapsed_s=elapsed_s,
    )
    if not keep:
        shutil.rmtree(work, ignore_errors=True)
    return result


def main(argv: list[str] | None = None) -> int:
    """Command-line entry point; see the module docstring."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--timeout", type=float, default=240.0, help="seconds (default 240)")
    parser.add_argument("--mem", default="1G", help="UML memory (default 1G)")
    parser.add_argument("--env", action="append", default=[], metavar="K=V")
    parser.add_argument("--keep", action="store_true", help="keep the work directory")
    parser.add_argument("command", nargs=argparse.REMAINDER)
    args = parser.parse_args(argv)
    command = args.command[1:] if args.command[:1] == ["--"] else args.command
    if not command:
        parser.error("no command given (put it after --)")
    env = {}
    for item in args.env:
        key, sep, value = item.partition("=")
        if not sep or not key:
            parser.error(f"--env expects K=V, got {item!r}")
        env[key] = value
    logging.basicConfig(level=logging.INFO, format="uml_run: %(message)s")
    try:
        result = run_in_uml(command, timeout_s=args.timeout, mem=args.mem, env=env,
                            keep=args.keep)
    except FileNotFoundError as err:
        log.error("%s", err)
        return EXIT_NO_UML
    sys.stdout.write(result.output)
    sys.stdout.flush()
    if result.status is None:
        log.error(
            "the command did not finish inside UML (%s after %.1f s); console:\n%s",
            "timed out" if result.timed_out else "no status", result.elapsed_s,
            result.console[-4000:],
        )
        return EXIT_TIMEOUT if result.timed_out else EXIT_UML_FAILED
    log.info("UML run finished with status %d in %.1f s", result.status, result.elapsed_s)
    return result.status


if __name__ == "__main__":
    sys.exit(main())
