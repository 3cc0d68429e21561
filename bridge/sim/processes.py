"""``hilbo sim --processes``: the simulated session with the virtual devices as processes.

``hilbo sim`` runs the bridge and both virtual devices in one process. With ``--processes`` the
virtual exosuit (``python -m virtual_hw.cli_exosuit``) and the virtual cart (``python -m
virtual_hw.cli_cart``) run as children of hilbo, as a lab's devices are machines of their own:
the exosuit on a CAN bus shared between processes, the cart serving breaths over TCP on
loopback and learning the applied profile from that bus
(:class:`virtual_hw.exosuit.AppliedProfileListener`). The bridge is the very
:func:`bridge.run.run_session` of ``hilbo run``, in this process; it writes ``DIR/session.mcap``
and ``DIR/summary.json`` as the in-process simulation does.

The bus (``--bus``):

* ``vcan``: SocketCAN ``vcan0`` (a Linux PC after ``hilbo vcan-setup | sudo sh``);
* ``remote``: a python-can-remote server (``python -m can_remote --interface virtual --host
  127.0.0.1``; never its default 0.0.0.0, an open bus on the network) started here as a third
  child on 127.0.0.1 and a free port; every process is a websocket client of it (the path for a
  PC without SocketCAN);
* ``auto`` (default): ``vcan`` where a raw CAN socket can bind ``vcan0``, else ``remote``.

Clock: the devices share one :class:`~virtual_hw.clock.ScaledClock` through ``--speed`` and
``--epoch``; ``--speed max`` stands for :data:`~bridge.sim.virtual.MAX_SPEED` here too (an
as-fast-as-possible clock cannot be shared between processes). Heartbeats now cross process
boundaries on a possibly loaded PC, so both watchdogs are looser than in one process
(:data:`DEVICE_HEARTBEAT_TIMEOUT_S`, :data:`BRIDGE_DEVICE_TIMEOUT_MS`), and a simulated operator
resumes a session paused by one (or by a silent cart) once the device and the cart are healthy
again (:data:`RESUME_AFTER_S`), as the pause between the bouts is resumed at once; the log has
the pause and the resume like any other.

Truth: the cart's wearer is ``make_wearer(wearer, preset, seed, body_mass_kg)``
(:func:`virtual_hw.wearer.make_wearer`; the cart process gets ``--wearer``), a deterministic
function of those four; this process builds the same subject to add the true optimum, the true
cost of the recommendation and the regret to the summary.

Lifecycle: :func:`device_processes` starts the children and always stops them (SIGTERM, then
SIGKILL after :data:`STOP_TIMEOUT_S`), on errors and Ctrl-C too. They run in sessions of their
own, so a Ctrl-C at the terminal reaches hilbo alone, which ends the session first (assistance
off while the device still listens) and then stops them. A child that exits early ends the
session with a :class:`~bridge.errors.DeviceProcessError` quoting its stderr; each child's stderr
is kept in ``DIR/processes/NAME.log``.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import importlib.util
import json
import logging
import signal
import socket
import sys
import time
from collections.abc import AsyncIterator, Callable, Sequence
from pathlib import Path
from typing import IO, Any

import msgspec

from bridge.config import parse_config
from bridge.errors import BridgeConfigError, DeviceProcessError
from bridge.run import RunResult, run_session, write_json_atomic
from bridge.runtime import BridgeSession, Command
from bridge.sim.virtual import MAX_SPEED, VirtualSimConfig, add_simulation_truth, sim_config_text
from drivers.cart import CartConfig, TcpOptions
from drivers.errors import DriverError
from drivers.exosuit import CanBusConfig
from drivers.exosuit.vcan_setup import vcan_problem
from hilbo_core.presets import preset
from virtual_hw.exosuit import SUIT_JOINTS
from virtual_hw.wearer import make_wearer

__all__ = [
    "BRIDGE_DEVICE_TIMEOUT_MS",
    "BUS_CHOICES",
    "DEVICE_HEARTBEAT_TIMEOUT_S",
    "RESUME_AFTER_S",
    "START_TIMEOUT_S",
    "STOP_TIMEOUT_S",
    "ChildProcess",
    "DeviceProcesses",
    "device_processes",
    "remote_problem",
    "resolve_bus",
    "run_process_sim",
    "vcan_problem",
]

logger = logging.getLogger(__name__)

#: What ``--bus`` accepts.
BUS_CHOICES = ("auto", "vcan", "remote")
#: The SocketCAN interface of ``--bus vcan``.
VCAN_CHANNEL = "vcan0"
#: Longest wait for a child to be ready (interpreter start and numpy/scipy imports, loaded PC).
START_TIMEOUT_S = 60.0
#: Longest wait for a child to exit after SIGTERM before it is killed.
STOP_TIMEOUT_S = 10.0
#: The virtual exosuit's bridge-heartbeat watchdog across processes (100 ms in PROTOCOL.md).
DEVICE_HEARTBEAT_TIMEOUT_S = 0.5
#: The bridge's device-heartbeat watchdog across processes (250 ms in one process).
BRIDGE_DEVICE_TIMEOUT_MS = 1000.0
#: The simulated operator resumes a pause after the device and cart have been healthy this long.
RESUME_AFTER_S = 0.5
_STDERR_TAIL_CHARS = 2000
_LOOPBACK = "127.0.0.1"


# ------------------------------------------------------------------------------ the bus


def remote_problem() -> str | None:
    """Why a python-can-remote server cannot be started here, or None when it can."""
    if importlib.util.find_spec("can_remote") is None:
        return "python-can-remote is not installed (pip install python-can-remote)"
    return None


def resolve_bus(choice: str) -> str:
    """The bus (``"vcan"`` or ``"remote"``) for a ``--bus`` choice.

    Raises:
        BridgeConfigError: An unknown choice, or the chosen bus cannot be used here (the
            message says why).
    """
    if choice not in BUS_CHOICES:
        raise BridgeConfigError(f"--bus {choice!r}; expected one of {', '.join(BUS_CHOICES)}")
    vcan = vcan_problem() if choice in ("auto", "vcan") else None
    if choice == "vcan" and vcan is not None:
        raise BridgeConfigError(f"--bus vcan: {vcan}; or use --bus remote (python-can-remote)")
    if choice == "vcan" or (choice == "auto" and vcan is None):
        return "vcan"
    remote = remote_problem()
    if remote is not None:
        reason = f"--bus {choice}: " + (f"{vcan}, and " if vcan is not None else "")
        raise BridgeConfigError(reason + remote)
    return "remote"


def _free_port() -> int:
    # The port may be taken between here and the server's bind; the server then exits at once
    # and its stderr says so.
    with socket.socket() as probe:
        probe.bind((_LOOPBACK, 0))
        return int(probe.getsockname()[1])


# ------------------------------------------------------------------------------ processes


class ChildProcess:
    """One virtual device (or the CAN server) as a child process.

    Its stdout is a pipe (the device's machine-readable lines, :attr:`lines`), its stderr the
    file ``log_path``. Call :meth:`start`, then :meth:`first_line` or :meth:`wait_listening`,
    and always :meth:`stop`.

    Args:
        name: Shown in messages (``virtual-exosuit``, ``virtual-cart``, ``can-remote``).
        argv: The command.
        log_path: Where its stderr goes.
    """

    def __init__(self, name: str, argv: Sequence[str], log_path: Path) -> None:
        self.name = name
        self.argv = [str(a) for a in argv]
        self.log_path = Path(log_path)
        self.lines: list[str] = []
        self.proc: asyncio.subprocess.Process | None = None
        self._stderr: IO[bytes] | None = None

    @property
    def pid(self) -> int | None:
        """The process id, once started."""
        return None if self.proc is None else self.proc.pid

    @property
    def returncode(self) -> int | None:
        """The exit status once it has exited (negative: killed by that signal), else None."""
        return None if self.proc is None else self.proc.returncode

    async def start(self) -> None:
        """Start it, in a session of its own (a terminal's Ctrl-C does not reach it).

        Raises:
            DeviceProcessError: The command cannot be started.
        """
        self.log_path.parent.mkdir(parents=True, exist_ok=True)
        self._stderr = open(self.log_path, "wb")  # the child's stderr; closed by stop()
        try:
            self.proc = await asyncio.create_subprocess_exec(
                *self.argv, stdin=asyncio.subprocess.DEVNULL, stdout=asyncio.subprocess.PIPE,
                stderr=self._stderr, start_new_session=True,
            )
        except OSError as err:
            self._close_log()
            raise DeviceProcessError(f"{self.name}: cannot start {self.argv[0]}: {err}") from err
        logger.info("started %s (pid %d): %s", self.name, self.proc.pid, " ".join(self.argv))

    def stderr_tail(self, limit: int = _STDERR_TAIL_CHARS) -> str:
        """The end of what it wrote on stderr."""
        try:
            data = self.log_path.read_bytes()
        except OSError:
            return ""
        return data[-limit:].decode(errors="replace").strip()

    def failure(self, what: str) -> DeviceProcessError:
        """An error naming this process and what went wrong, with its exit status and stderr."""
        text = f"{self.name} {what}"
        if self.returncode is not None:
            text += f" (exit status {self.returncode})"
        tail = self.stderr_tail()
        text += (f"; the end of its stderr ({self.log_path}):\n{tail}" if tail
                 else f"; it wrote nothing on stderr ({self.log_path})")
        return DeviceProcessError(text)

    def _running(self) -> asyncio.subprocess.Process:
        if self.proc is None or self.proc.stdout is None:
            raise DeviceProcessError(f"{self.name} was not started")
        return self.proc

    async def first_line(self, timeout_s: float = START_TIMEOUT_S) -> str:
        """The first line it prints on stdout (its address or ready record).

        Raises:
            DeviceProcessError: It exited first, or printed nothing within ``timeout_s``.
        """
        proc = self._running()
        assert proc.stdout is not None
        try:
            async with asyncio.timeout(timeout_s):
                raw = await proc.stdout.readline()
        except TimeoutError:
            raise self.failure(f"printed nothing within {timeout_s:g} s of its start") from None
        if not raw:
            with contextlib.suppress(TimeoutError):
                async with asyncio.timeout(STOP_TIMEOUT_S):
                    await proc.wait()
            raise self.failure("exited before it was ready")
        line = raw.decode(errors="replace").strip()
        self.lines.append(line)
        return line

    async def wait_listening(self, host: str, port: int, timeout_s: float = START_TIMEOUT_S) -> None:
        """Wait until it accepts TCP connections on ``host:port``.

        Raises:
            DeviceProcessError: It exited first, or did not listen within ``timeout_s``.
        """
        self._running()
        loop = asyncio.get_running_loop()
        deadline = loop.time() + timeout_s
        while True:
            if self.returncode is not None:
                raise self.failure("exited before it was ready")
            try:
                _, writer = await asyncio.open_connection(host, port)
            except OSError:
                if loop.time() > deadline:
                    raise self.failure(f"did not listen on {host}:{port} within {timeout_s:g} s") from None
                await asyncio.sleep(0.05)
                continue
            writer.close()
            with contextlib.suppress(OSError):
                await writer.wait_closed()
            return

    async def stop(self, timeout_s: float = STOP_TIMEOUT_S) -> int | None:
        """SIGTERM, then SIGKILL after ``timeout_s``; keep what it printed last. Idempotent.

        Returns:
            The exit status (None if it was never started).
        """
        proc = self.proc
        if proc is None:
            self._close_log()
            return None
        try:
            if proc.returncode is None:
                with contextlib.suppress(ProcessLookupError):
                    proc.send_signal(signal.SIGTERM)
                try:
                    async with asyncio.timeout(timeout_s):
                        await proc.wait()
                except TimeoutError:
                    logger.warning("%s (pid %d) did not stop within %g s of SIGTERM; killing it",
                                   self.name, proc.pid, timeout_s)
                    self.kill()
                    await proc.wait()
            if proc.stdout is not None and not proc.stdout.at_eof():
                with contextlib.suppress(TimeoutError):
                    async with asyncio.timeout(1.0):
                        rest = await proc.stdout.read()
                    self.lines.extend(line.strip() for line in rest.decode(errors="replace").splitlines())
        finally:
            self._close_log()
        return proc.returncode

    def _close_log(self) -> None:
        if self._stderr is not None:
            self._stderr.close()
            self._stderr = None

    def kill(self) -> None:
        """SIGKILL it now if it still runs (the last resort; no waiting)."""
        if self.proc is not None and self.proc.returncode is None:
            with contextlib.suppress(ProcessLookupError):
                self.proc.kill()

    def json_record(self, event: str) -> dict[str, Any] | None:
        """The last JSON line on its stdout with ``"event": event`` (the virtual exosuit's)."""
        for line in reversed(self.lines):
            with contextlib.suppress(ValueError):
                record = json.loads(line)
                if isinstance(record, dict) and record.get("event") == event:
                    return record
        return None


@dataclasses.dataclass
class DeviceProcesses:
    """The virtual devices running as processes: where the bridge reaches them.

    Attributes:
        bus: ``"vcan"`` or ``"remote"``.
        can: The exosuit's bus, for the bridge's ``[can]``.
        cart: The cart's address, for the bridge's ``[cart]``.
        speed: The devices' real-time factor.
        epoch: Unix time of their simulated time 0.
        children: Every child, in start order.
    """

    bus: str
    can: CanBusConfig
    cart: CartConfig
    speed: float
    epoch: float
    children: list[ChildProcess]

    def exited(self) -> ChildProcess | None:
        """The first child that has exited, if any."""
        return next((c for c in self.children if c.returncode is not None), None)

    async def wait_any_exit(self) -> ChildProcess:
        """Wait until some child exits; return it."""
        waits = {asyncio.ensure_future(c.proc.wait()): c for c in self.children if c.proc is not None}
        try:
            done, _ = await asyncio.wait(waits, return_when=asyncio.FIRST_COMPLETED)
        finally:
            for task in waits:
                task.cancel()
        return waits[next(iter(done))]

    def report(self) -> dict[str, Any]:
        """What the summary says about the processes."""
        out: dict[str, Any] = {
            "bus": self.bus,
            "can": {"interface": self.can.interface, "channel": self.can.channel},
            "speed": self.speed,
            "epoch": self.epoch,
            "children": {c.name: {"pid": c.pid, "exit_status": c.returncode, "argv": c.argv,
                                  "stderr": str(c.log_path)} for c in self.children},
        }
        exo = next((c for c in self.children if c.name == "virtual-exosuit"), None)
        stopped = exo.json_record("stopped") if exo is not None else None
        if stopped is not None:
            out["exosuit"] = {"stats": stopped.get("stats", {}),
                              "profiles_applied": len(stopped.get("applied", []))}
        return out


def _cancel_on_sigterm(arm: bool) -> None:
    """Make SIGTERM cancel the current task (so ``finally`` blocks stop the children), or not.

    run_session installs its own SIGTERM handler for the session and removes it at the end, so
    this is armed again before the children are stopped.
    """
    loop = asyncio.get_running_loop()
    task = asyncio.current_task()
    with contextlib.suppress(NotImplementedError, RuntimeError, ValueError):
        if arm and task is not None:
            loop.add_signal_handler(signal.SIGTERM, task.cancel)
        elif not arm:
            loop.remove_signal_handler(signal.SIGTERM)


def _cart_address(child: ChildProcess, line: str) -> CartConfig:
    parts = line.split()
    if len(parts) != 3 or parts[0] != "tcp" or not parts[2].isdigit():
        raise child.failure(f"printed {line!r} instead of its address ('tcp HOST PORT')")
    return CartConfig(transport="tcp", options=TcpOptions(host=parts[1], port=int(parts[2])))


@contextlib.asynccontextmanager
async def device_processes(
    cfg: VirtualSimConfig,
    *,
    bus: str,
    log_dir: Path,
    speed: float | None = None,
    heartbeat_timeout_s: float = DEVICE_HEARTBEAT_TIMEOUT_S,
) -> AsyncIterator[DeviceProcesses]:
    """Start the virtual exosuit and the virtual cart as processes; stop them on leaving.

    With ``bus="remote"`` a python-can-remote server is started first. The children are
    stopped in reverse order (SIGTERM, then SIGKILL after :data:`STOP_TIMEOUT_S`) however the
    block is left, Ctrl-C and SIGTERM of this process included.

    Args:
        cfg: The simulated session (preset, seed, body mass, faults, feedback rate).
        bus: ``"vcan"`` or ``"remote"`` (see :func:`resolve_bus`).
        log_dir: Where each child's stderr goes (``NAME.log``).
        speed: Real-time factor (default: ``cfg.speed``, else :data:`~bridge.sim.virtual.MAX_SPEED`).
        heartbeat_timeout_s: The virtual exosuit's bridge-heartbeat watchdog.

    Raises:
        DeviceProcessError: A child could not be started or exited before it was ready.
    """
    if bus not in ("vcan", "remote"):
        raise BridgeConfigError(f"bus={bus!r}; expected 'vcan' or 'remote' (see resolve_bus)")
    speed = speed or cfg.speed or MAX_SPEED
    log_dir = Path(log_dir)
    py = sys.executable
    children: list[ChildProcess] = []
    _cancel_on_sigterm(True)
    try:
        if bus == "remote":
            port = _free_port()
            server = ChildProcess(
                "can-remote",
                [py, "-m", "can_remote", "--interface", "virtual", "--channel", "hilbo-sim",
                 "--host", _LOOPBACK, "--port", str(port)],
                log_dir / "can-remote.log")
            children.append(server)
            await server.start()
            await server.wait_listening(_LOOPBACK, port)
            can = CanBusConfig("remote", f"ws://{_LOOPBACK}:{port}/")
        else:
            can = CanBusConfig("socketcan", VCAN_CHANNEL)
        epoch = time.time()
        clock = ["--speed", repr(speed), "--epoch", repr(epoch), "--seed", str(cfg.seed)]
        exosuit = ChildProcess(
            "virtual-exosuit",
            [py, "-m", "virtual_hw.cli_exosuit", "--interface", can.interface,
             "--channel", str(can.channel), *clock, "--suit", cfg.preset,
             "--feedback-hz", repr(cfg.feedback_hz), "--heartbeat-timeout", repr(heartbeat_timeout_s),
             *(a for spec in cfg.exosuit_faults for a in ("--fault", str(spec)))],
            log_dir / "virtual-exosuit.log")
        cart = ChildProcess(
            "virtual-cart",
            [py, "-m", "virtual_hw.cli_cart", "--transport", "tcp", "--host", _LOOPBACK,
             "--port", "0", "--preset", cfg.preset, "--body-mass-kg", repr(cfg.body_mass_kg),
             "--wearer", cfg.wearer,
             *clock, "--can-interface", can.interface, "--can-channel", str(can.channel),
             *(a for spec in cfg.cart_faults for a in ("--fault", str(spec)))],
            log_dir / "virtual-cart.log")
        children += [exosuit, cart]
        await exosuit.start()
        await cart.start()  # both start now; their ready lines are awaited one after the other
        ready = await exosuit.first_line()
        with contextlib.suppress(ValueError):
            if json.loads(ready).get("event") == "ready":
                ready = ""
        if ready:
            raise exosuit.failure(f"printed {ready!r} instead of its ready record")
        cart_config = _cart_address(cart, await cart.first_line())
        yield DeviceProcesses(bus, can, cart_config, speed, epoch, children)
    finally:
        _cancel_on_sigterm(True)
        try:
            for child in reversed(children):
                await child.stop()
        finally:
            for child in children:  # interrupted while stopping: never leave one running
                child.kill()
            _cancel_on_sigterm(False)


# ------------------------------------------------------------------------------ the session


async def _simulated_operator(session: BridgeSession, *, period_s: float = 0.1) -> None:
    """Resume any pause once the device and the cart have been healthy for RESUME_AFTER_S."""
    loop = asyncio.get_running_loop()
    healthy_since: float | None = None
    while True:
        await asyncio.sleep(period_s)
        st = session.status
        if not (st.state.startswith("paused") and st.device == "ok" and st.cart == "ok"):
            healthy_since = None
            continue
        now = loop.time()
        if healthy_since is None:
            healthy_since = now
        elif now - healthy_since >= RESUME_AFTER_S:
            logger.info("simulated operator: resuming (%s)", st.state)
            session.command(Command.RESUME)
            healthy_since = None


async def _run_supervised(hcfg: Any, devices: DeviceProcesses, *, log_path: Path, operator_view: bool,
                          n_actuators: int, on_session: Callable[[BridgeSession], None] | None) -> RunResult:
    """run_session with a simulated operator, ended (and turned into a DeviceProcessError) when a
    child exits."""
    sessions: list[BridgeSession] = []
    died: list[ChildProcess] = []
    operators: list[asyncio.Task[None]] = []

    def hook(session: BridgeSession) -> None:
        sessions.append(session)
        operators.append(asyncio.get_running_loop().create_task(_simulated_operator(session),
                                                                name="simulated-operator"))
        if died:
            session.command(Command.STOP)
        if on_session is not None:
            on_session(session)

    async def supervise() -> None:
        child = await devices.wait_any_exit()
        died.append(child)
        logger.error("%s exited during the session (status %s)", child.name, child.returncode)
        for session in sessions:
            session.command(Command.STOP)

    watcher = asyncio.create_task(supervise(), name="device-processes")
    try:
        result = await run_session(hcfg, log_path=log_path, auto_resume_s=0.0,
                                   operator_view=operator_view, n_actuators=n_actuators,
                                   on_session=hook)
    except DriverError as err:
        gone = died[0] if died else devices.exited()
        if gone is not None:
            raise gone.failure("exited during the session") from err
        raise
    finally:
        for task in (watcher, *operators):
            task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await task
    if died:
        raise died[0].failure("exited during the session")
    return result


async def run_process_sim(cfg: VirtualSimConfig, out: Path, *, bus: str = "auto", operator_view: bool = False,
                          on_session: Callable[[BridgeSession], None] | None = None) -> dict[str, Any]:
    """Run a whole simulated session with the virtual devices as processes.

    Writes OUT/session.mcap, OUT/summary.json (the fields of the in-process simulation, with
    ``sim.processes`` describing the children) and OUT/processes/NAME.log.

    Args:
        cfg: The simulated session.
        out: Output directory.
        bus: ``auto``, ``vcan`` or ``remote`` (:func:`resolve_bus`).
        operator_view: Show the live terminal view.
        on_session: Called with the bridge session before it runs.

    Returns:
        The summary, with the simulation's truth.

    Raises:
        BridgeConfigError: The bus cannot be used here.
        DeviceProcessError: A device process could not start, or died.
    """
    wall0 = time.perf_counter()
    kind = resolve_bus(bus)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    log_path = out / "session.mcap"
    if log_path.exists():
        log_path.unlink()  # the simulation's log is regenerated; a lab log never is
    speed = cfg.speed or MAX_SPEED
    # The cart process's subject, rebuilt here (it is a function of these four) for the truth.
    wearer = make_wearer(cfg.wearer, preset(cfg.preset), seed=cfg.seed, body_mass_kg=cfg.body_mass_kg)
    hcfg = parse_config(sim_config_text(cfg, out, device_timeout_ms=BRIDGE_DEVICE_TIMEOUT_MS),
                        source="<hilbo sim --processes>")
    async with device_processes(cfg, bus=kind, log_dir=out / "processes", speed=speed) as devices:
        hcfg = dataclasses.replace(hcfg, cart=devices.cart,
                                   can=msgspec.structs.replace(hcfg.can, bus=devices.can))
        result = await _run_supervised(hcfg, devices, log_path=log_path, operator_view=operator_view,
                                       n_actuators=len(SUIT_JOINTS[cfg.preset]), on_session=on_session)
    # The rebuilt wearer has not walked: the session's end is the last evaluation's end (session
    # time, within a breath of the cart's breath clock), for the adaptation at the end.
    end_s = max((float(e["t_end"]) for e in result.summary.get("evaluations") or ()), default=0.0)
    summary = add_simulation_truth(result.summary, wearer, end_s=end_s)
    summary["sim"] = {**dataclasses.asdict(cfg), "speed": speed, "processes": devices.report()}
    summary["wall_time_s"] = time.perf_counter() - wall0
    write_json_atomic(out / "summary.json", summary)
    result.summary_path.unlink(missing_ok=True)  # summary.json is the simulation's summary
    return summary
