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

On a host CPU with AMX (Intel Sapphire Rapids and later) Debian's UML kernels (6.1 and 6.12)
panic at the first guest process ("userspace - ptrace set fp regs failed, errno = 14": the
host's XSAVE buffer is larger than UML's). There UML runs with ``scripts/uml_xstate_shim.c``
preloaded (compiled with the system's cc on first use, cached next to the work directories),
which pads UML's ptrace writes of the FPU state to the host's size.

A second guest, opt-in with ``HILBO_GUEST=qemu``, runs the same init script in a QEMU virtual
machine instead: QEMU boots the host's own Debian kernel (``linux-image-amd64``) with a tiny
initramfs (static busybox + the 9p/virtio modules) that mounts the host's ``/`` over virtio-9p and
switches to it, so the guest again shares the host's filesystem and virtualenv. It emulates the
CPU (TCG) unless ``HILBO_QEMU_ACCEL=kvm``: under nested virtualisation, as on this project's CI
VMs, ``/dev/kvm`` opens but a Linux guest hangs before printing anything.
It is much slower than UML (minutes, not seconds, for the vcan tests) and is kept for hosts
where UML cannot run at all. ``HILBO_GUEST=uml|qemu`` chooses (default uml).

Usage::

    scripts/uml_run.py [--timeout S] [--mem SIZE] [--env K=V ...] [--keep] -- CMD [ARG ...]

Exit status: the command's, or 124 on timeout, 125 when UML could not run the command (the
console log is shown), 127 when user-mode Linux is not installed. Standard library only, so it
runs with any Python 3.9+.
"""

from __future__ import annotations

import argparse
import contextlib
import glob
import hashlib
import logging
import lzma
import os
import shlex
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

__all__ = ["IN_UML_ENV", "UmlResult", "choose_backend", "find_qemu", "find_uml", "guest_problem", "main",
           "run_in_uml", "xstate_shim"]

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


def _init_script(work: Path, cwd: Path, env: dict[str, str], command: list[str],
                 *, backend: str = "uml") -> str:
    exports = "\n".join(f"export {k}={shlex.quote(v)}" for k, v in sorted(env.items()))
    modules = " ".join(_MODULES)
    # UML's modules live in the package's own tree; the QEMU guest runs the host's Debian kernel,
    # whose modules (possibly compressed) modprobe finds under /lib/modules.
    load = (f'mods=/usr/lib/uml/modules/$(uname -r)/kernel\n'
            f'for m in {modules}; do insmod "$mods/$m" || echo "insmod $m failed"; done'
            if backend == "uml" else
            'for m in can can-raw can-bcm can-dev vcan; do modprobe "$m" || echo "modprobe $m failed"; done')
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
{load}
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


# --- the QEMU guest ------------------------------------------------------------------------------

_QEMU_TAG = "hostroot"
#: Modules the initramfs loads (with their dependencies) to mount the host's / over virtio-9p.
_QEMU_BOOT_MODULES = ("virtio_pci", "9pnet_virtio", "9p")


def _host_has_amx() -> bool:
    try:
        flags = Path("/proc/cpuinfo").read_text(errors="replace")
    except OSError:
        return False
    return " amx_tile" in flags


def _kvm_openable() -> str:
    try:
        fd = os.open("/dev/kvm", os.O_RDWR)
    except OSError as err:
        return f"/dev/kvm: {err.strerror}"
    os.close(fd)
    return ""


def find_qemu() -> tuple[str, Path, str] | str:
    """Locate what the QEMU guest needs.

    Returns:
        (qemu binary, kernel image, kernel release), or a message saying what is missing.
    """
    qemu = shutil.which("qemu-system-x86_64")
    missing = [] if qemu else ["qemu-system-x86_64 (apt-get install qemu-system-x86)"]
    if not (shutil.which("busybox") or os.path.exists("/bin/busybox")):
        missing.append("busybox (apt-get install busybox-static)")
    if os.environ.get("HILBO_QEMU_ACCEL", "tcg") == "kvm":
        problem = _kvm_openable()
        if problem:
            missing.append(problem)
    kernel: Path | None = None
    release = ""
    for image in sorted(glob.glob("/boot/vmlinuz-*"), reverse=True):
        rel = image.removeprefix("/boot/vmlinuz-")
        if glob.glob(f"/lib/modules/{rel}/kernel/drivers/net/can/vcan.ko*"):
            kernel, release = Path(image), rel
            break
    if kernel is None:
        missing.append("a kernel with vcan under /boot and /lib/modules (apt-get install linux-image-amd64)")
    if missing or qemu is None or kernel is None:
        return "missing: " + ", ".join(missing)
    return qemu, kernel, release


def choose_backend() -> str:
    """``uml`` (default) or ``qemu``, as ``HILBO_GUEST`` says."""
    return "qemu" if os.environ.get("HILBO_GUEST") == "qemu" else "uml"


_SHIM_SOURCE = Path(__file__).resolve().parent / "uml_xstate_shim.c"


def xstate_shim() -> Path | None:
    """The compiled :file:`uml_xstate_shim.c` on an AMX host (None elsewhere: not needed).

    Raises:
        FileNotFoundError: the host needs it and there is no C compiler to build it.
    """
    if not _host_has_amx():
        return None
    source = _SHIM_SOURCE.read_bytes()
    digest = hashlib.sha256(source).hexdigest()[:16]
    out = Path(tempfile.gettempdir()) / f"hilbo-uml-xstate-shim-{digest}.so"
    if out.exists():
        return out
    cc = shutil.which("cc") or shutil.which("gcc")
    if cc is None:
        raise FileNotFoundError("this CPU has AMX, so user-mode Linux needs scripts/uml_xstate_shim.c "
                                "compiled, and there is no C compiler (apt-get install gcc)")
    tmp = out.with_suffix(f".{os.getpid()}.tmp")
    subprocess.run([cc, "-shared", "-fPIC", "-O2", "-o", str(tmp), str(_SHIM_SOURCE), "-ldl"],
                   check=True, capture_output=True)
    tmp.replace(out)  # atomic: parallel runs never load a half-written library
    return out


def guest_problem() -> str | None:
    """Why no guest can run the vcan tests here, or None when the chosen one can."""
    backend = choose_backend()
    if backend == "qemu":
        found = find_qemu()
        return f"the QEMU guest is not usable ({found})" if isinstance(found, str) else None
    uml = find_uml()
    if uml is None:
        return "linux.uml not installed (scripts/ensure-uml.sh installs it as root)"
    if not uml[1] and _host_has_amx() and not (shutil.which("cc") or shutil.which("gcc")):
        return "this CPU has AMX and user-mode Linux then needs a C compiler for its shim (gcc)"
    return uml[1] or None


def _module_deps(release: str) -> tuple[dict[str, list[str]], set[str]]:
    """modules.dep as {name: [relative paths of it and its dependencies]} and the built-in names."""
    base = Path(f"/lib/modules/{release}")
    deps: dict[str, list[str]] = {}
    for line in (base / "modules.dep").read_text().splitlines():
        path, _, rest = line.partition(":")
        name = Path(path).name.split(".ko")[0].replace("-", "_")
        deps[name] = [path, *rest.split()]
    builtin = set()
    with contextlib.suppress(OSError):
        for line in (base / "modules.builtin").read_text().splitlines():
            builtin.add(Path(line).name.split(".ko")[0].replace("-", "_"))
    return deps, builtin


def _load_order(release: str, wanted: tuple[str, ...]) -> list[str]:
    """Module files (relative to /lib/modules/RELEASE) in an order insmod accepts."""
    deps, builtin = _module_deps(release)
    order: list[str] = []

    def visit(path: str) -> None:
        name = Path(path).name.split(".ko")[0].replace("-", "_")
        entry = deps.get(name, [path])
        # modules.dep lists a module's dependencies deepest last: load them in reverse.
        for dep in reversed(entry[1:]):
            visit(dep)
        if path not in order:
            order.append(path)

    for mod in wanted:
        key = mod.replace("-", "_")
        if key in builtin:
            continue
        if key not in deps:
            raise FileNotFoundError(f"kernel {release} has no module {mod} (nor is it built in)")
        visit(deps[key][0])
    return order


def _module_bytes(path: Path) -> bytes:
    data = path.read_bytes()
    if path.suffix == ".xz":
        return lzma.decompress(data)
    if path.suffix == ".zst":
        zstd = shutil.which("zstd")
        if zstd is None:
            raise FileNotFoundError(f"{path} is zstd-compressed and there is no zstd to unpack it")
        return subprocess.run([zstd, "-dc", str(path)], check=True, capture_output=True).stdout
    return data


def _cpio(entries: list[tuple[str, int, bytes]]) -> bytes:
    """A newc cpio archive of (name, mode, data) entries: what the kernel unpacks as initramfs."""
    out = bytearray()
    for ino, (name, mode, data) in enumerate([*entries, ("TRAILER!!!", 0, b"")], start=1):
        raw = name.encode() + b"\0"
        fields = [ino, mode, 0, 0, 1, 0, len(data), 0, 0, 0, 0, len(raw), 0]
        out += b"070701" + b"".join(f"{v:08x}".encode() for v in fields) + raw
        out += b"\0" * (-len(out) % 4) + data
        out += b"\0" * (-len(out) % 4)
    return bytes(out)


def _initramfs(release: str, work: Path, init: Path) -> Path:
    busybox = Path(shutil.which("busybox") or "/bin/busybox")
    files = _load_order(release, _QEMU_BOOT_MODULES)
    names = [f"m{k}.ko" for k in range(len(files))]
    script = f"""#!/bin/busybox sh
/bin/busybox mkdir -p /proc /dev /newroot
/bin/busybox mount -t proc proc /proc
/bin/busybox mount -t devtmpfs devtmpfs /dev
for m in {' '.join(names)}; do /bin/busybox insmod /lib/$m || echo "insmod $m failed"; done
if ! /bin/busybox mount -t 9p -o trans=virtio,version=9p2000.L,msize=512000,cache=loose \\
     {_QEMU_TAG} /newroot; then
  echo "mounting the host's / over 9p failed"; /bin/busybox poweroff -f
fi
/bin/busybox umount /dev
/bin/busybox umount /proc
exec /bin/busybox switch_root /newroot {shlex.quote(str(init))}
"""
    entries: list[tuple[str, int, bytes]] = [
        ("bin", 0o040755, b""), ("lib", 0o040755, b""), ("dev", 0o040755, b""),
        ("proc", 0o040755, b""), ("newroot", 0o040755, b""),
        ("bin/busybox", 0o100755, busybox.read_bytes()),
        ("init", 0o100755, script.encode()),
    ]
    for name, rel in zip(names, files, strict=True):
        entries.append((f"lib/{name}", 0o100644, _module_bytes(Path(f"/lib/modules/{release}") / rel)))
    path = work / "initramfs.cpio"
    path.write_bytes(_cpio(entries))
    return path


def _uncompressed_kernel(image: Path, work: Path) -> Path:
    """The ELF ``vmlinux`` inside a bzImage, which QEMU boots through its PVH entry point.

    Why: it boots a little faster under TCG (no decompression in an emulated CPU), and with KVM
    under nested virtualisation the bzImage's decompressor stops QEMU with "KVM internal error
    ... emulation failure" (shadow paging cannot emulate its BMI2 instructions).
    """
    data = image.read_bytes()
    for magic, tool in ((b"\x28\xb5\x2f\xfd", ["zstd", "-dcq"]), (b"\xfd7zXZ\x00", ["xz", "-dcq"]),
                        (b"\x1f\x8b\x08", ["gzip", "-dcq"])):
        off = data.find(magic)
        if off < 0 or shutil.which(tool[0]) is None:
            continue
        # The compressed payload is followed by the bzImage's trailer: the tool then complains
        # about trailing data after writing the whole kernel, so its exit status is not used.
        out = subprocess.run(tool, input=data[off:], capture_output=True, check=False).stdout
        if out[:4] == b"\x7fELF":
            path = work / "vmlinux"
            path.write_bytes(out)
            return path
    raise FileNotFoundError(f"could not unpack the kernel in {image} (needs zstd, xz or gzip)")


def _accel_args() -> list[str]:
    # KVM where it really works (a lab PC); TCG by default, because under nested virtualisation
    # (this project's CI VMs) /dev/kvm opens but a Linux guest hangs before its first message.
    if os.environ.get("HILBO_QEMU_ACCEL", "tcg") == "kvm":
        return ["-accel", "kvm", "-cpu", "host"]
    return ["-accel", "tcg,thread=multi", "-cpu", "max"]


def _qemu_argv(work: Path, init: Path, mem: str) -> list[str]:
    found = find_qemu()
    if isinstance(found, str):
        raise FileNotFoundError(f"the QEMU guest is not usable here ({found})")
    qemu, kernel, release = found
    initrd = _initramfs(release, work, init)
    return [
        qemu, "-machine", "pc", *_accel_args(), "-smp", "2", "-m", mem,
        "-nodefaults", "-no-user-config", "-display", "none", "-no-reboot", "-nic", "none",
        "-serial", f"file:{work / 'serial.log'}",
        "-kernel", str(_uncompressed_kernel(kernel, work)), "-initrd", str(initrd),
        "-append", "console=ttyS0 quiet panic=-1 rdinit=/init",
        "-fsdev", "local,id=hostroot,path=/,security_model=passthrough,multidevs=remap",
        "-device", f"virtio-9p-pci,fsdev=hostroot,mount_tag={_QEMU_TAG}",
    ]


def run_in_uml(
    command: list[str],
    *,
    timeout_s: float = 240.0,
    mem: str = "1G",
    env: dict[str, str] | None = None,
    cwd: Path | None = None,
    keep: bool = False,
    backend: str | None = None,
) -> UmlResult:
    """Boot the guest once, run ``command`` in it with vcan0 up, and return what happened.

    Args:
        command: argv of the command to run inside the guest (absolute paths are safest).
        timeout_s: the whole boot (start to power-off) is killed after this many seconds.
        mem: guest memory size (UML's ``mem=``, QEMU's ``-m``), e.g. ``1G``.
        env: extra environment for the command (``HILBO_IN_UML=1`` is always set).
        cwd: working directory of the command (default: the caller's).
        keep: keep the work directory (init script, console log, output) for inspection.
        backend: ``uml`` or ``qemu``; None chooses (:func:`choose_backend`).

    Returns:
        An :class:`UmlResult`.

    Raises:
        FileNotFoundError: the chosen guest is not installed or not usable.
    """
    backend = backend or choose_backend()
    if backend == "uml":
        found = find_uml()
        if found is None or found[1]:
            raise FileNotFoundError(
                "user-mode Linux is not usable here ("
                + ("linux.uml not found" if found is None else found[1])
                + "); install it with `apt-get install user-mode-linux kmod iproute2`"
            )
    work = Path(tempfile.mkdtemp(prefix="hilbo-uml-"))
    (work / "uml").mkdir()
    init = work / "init"
    init.write_text(_init_script(work, (cwd or Path.cwd()).resolve(), env or {}, command,
                                 backend=backend))
    init.chmod(0o755)
    if backend == "uml":
        argv = [
            found[0],
            f"mem={mem}",
            "rootfstype=hostfs",
            "rootflags=/",
            "rw",
            "quiet",
            f"init={init}",
            "con=null",
            f"uml_dir={work / 'uml'}",
        ]
    else:
        try:
            argv = _qemu_argv(work, init, mem)
        except BaseException:
            shutil.rmtree(work, ignore_errors=True)
            raise
    boot_env = dict(os.environ)
    shim = xstate_shim() if backend == "uml" else None
    if shim is not None:
        boot_env["LD_PRELOAD"] = str(shim)
    log.debug("booting %s", " ".join(argv))
    t0 = time.monotonic()
    timed_out = False
    with open(work / "console.log", "wb") as console:
        # A new session, so that a hung guest is killed with all its host helper processes.
        proc = subprocess.Popen(
            argv, stdin=subprocess.DEVNULL, stdout=console, stderr=subprocess.STDOUT,
            start_new_session=True, env=boot_env,
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
        console=_read(work / "console.log") + _read(work / "serial.log") + _read(work / "setup.log"),
        work_dir=work,
        elapsed_s=elapsed_s,
    )
    if not keep:
        shutil.rmtree(work, ignore_errors=True)
    return result


def _exit_on_sigterm(signum: int, frame: object) -> None:
    raise SystemExit(128 + signum)


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
    # SIGTERM (a cancelled CI job, `timeout`, the death of a parent that asked for it) ends the
    # boot like Ctrl-C: the exception unwinds run_in_uml, whose `finally` kills the guest's own
    # process group (it runs in a session of its own, so the signal does not reach it).
    signal.signal(signal.SIGTERM, _exit_on_sigterm)
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
    log.info("%s run finished with status %d in %.1f s", choose_backend().upper(), result.status,
             result.elapsed_s)
    return result.status


if __name__ == "__main__":
    sys.exit(main())
