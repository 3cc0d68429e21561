"""A lab session on a busy PC: ``hilbo run`` at real time on the virtual devices, beside burners.

Each run is the dry run of docs/simulation.md over python-can-remote: a python-can-remote
server on 127.0.0.1, ``hilbo virtual-exosuit`` and ``hilbo virtual-cart`` at ``--speed 1`` as
processes of their own, and ``hilbo run`` with the example config (``hilbo config example``,
its ``[can]`` pointed at the server) and ``--no-view --auto-resume 10``, interrupted after
``--minutes`` (exit 130, as Ctrl-C). ``--burners K`` starts K ``while True: pass`` processes
first (a lab PC that also runs the cart's software, video, a second analysis) and stops them at
the end. One JSON row per run on stdout, and a table at the end:

* evaluations, and pauses by cause (the bridge's watchdog on the device's statuses, the device's
  ``heartbeat_lost`` fault, others);
* recoveries without and with a warm-up (``[protocol] short_pause_s``), and whether every
  setting measured again after a pause had the same parameters;
* whether the resume budget stopped the session (``end_reason``), the worst event-loop stall,
  the virtual exosuit's own watchdog counts and the mean load average.

    .venv/bin/python scripts/busy_pc.py --minutes 15 --burners 0 --out runs/busy/alone
    .venv/bin/python scripts/busy_pc.py --minutes 15 --burners 2 --runs 3 --out runs/busy/burners

The devices are processes on the same busy PC, unlike a suit's firmware: the exosuit's
``stats`` line (its log) says how often its own watchdogs fired.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import signal
import socket
import subprocess
import sys
import time
from collections import Counter
from pathlib import Path

from bridge.log.reader import read_log


def _hilbo(*args: str) -> list[str]:
    return [sys.executable, "-m", "bridge.cli.main", *args]


def _spawn(cmd: list[str], log: Path) -> subprocess.Popen:
    with open(log, "w") as out:
        return subprocess.Popen(cmd, stdout=out, stderr=subprocess.STDOUT)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _wait_port(port: int, timeout_s: float) -> None:
    t_end = time.monotonic() + timeout_s
    while time.monotonic() < t_end:
        try:
            with socket.create_connection(("127.0.0.1", port), timeout=0.5):
                return
        except OSError:
            time.sleep(0.2)
    raise SystemExit(f"busy_pc: nothing listens on 127.0.0.1:{port} after {timeout_s:g} s")


def _config(run_dir: Path, can_port: int, cart_port: int) -> Path:
    text = subprocess.run(_hilbo("config", "example"), check=True, capture_output=True, text=True).stdout
    for pattern, new in ((r'^interface = "socketcan".*$', 'interface = "remote"'),
                         (r'^channel = "vcan0".*$', f'channel = "ws://127.0.0.1:{can_port}/"'),
                         (r"^port = 5050 .*$", f"port = {cart_port}"),
                         (r"^out_dir = .*$", f'out_dir = "{run_dir / "out"}"')):
        text, n = re.subn(pattern, new, text, count=1, flags=re.M)
        if n != 1:
            raise SystemExit(f"busy_pc: the example config has no line matching {pattern!r}")
    path = run_dir / "session.toml"
    path.write_text(text)
    return path


def _stop(procs: list[subprocess.Popen], sig: int = signal.SIGTERM) -> None:
    for p in procs:
        if p.poll() is None:
            p.send_signal(sig)
    for p in procs:
        try:
            p.wait(timeout=10)
        except subprocess.TimeoutExpired:
            p.kill()
            p.wait()


def run_once(run_dir: Path, minutes: float, burners: int, seed: int) -> None:
    """One session of ``minutes`` beside ``burners`` CPU burners; files in ``run_dir``."""
    run_dir.mkdir(parents=True, exist_ok=False)
    can_port, cart_port = _free_port(), _free_port()
    cfg = _config(run_dir, can_port, cart_port)
    url = f"ws://127.0.0.1:{can_port}/"
    devices: list[subprocess.Popen] = []
    burn: list[subprocess.Popen] = []
    loads: list[float] = []
    try:
        devices.append(_spawn([sys.executable, "-m", "can_remote", "--interface", "virtual", "--channel",
                               "busy", "--host", "127.0.0.1", "--port", str(can_port)], run_dir / "can.log"))
        _wait_port(can_port, 30.0)
        epoch = str(int(time.time()))
        devices.append(_spawn(_hilbo("virtual-exosuit", "--interface", "remote", "--channel", url, "--speed",
                                     "1", "--epoch", epoch, "--feedback-hz", "100"), run_dir / "exosuit.log"))
        devices.append(_spawn(_hilbo("virtual-cart", "--port", str(cart_port), "--speed", "1", "--epoch",
                                     epoch, "--seed", str(seed), "--can-interface", "remote", "--can-channel",
                                     url), run_dir / "cart.log"))
        _wait_port(cart_port, 30.0)
        burn = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(burners)]
        with open(run_dir / "run.err", "w") as err:
            run = subprocess.Popen(_hilbo("run", str(cfg), "--no-view", "--auto-resume", "10"),
                                   stdout=subprocess.DEVNULL, stderr=err)
            t_end = time.monotonic() + 60.0 * minutes
            while run.poll() is None and time.monotonic() < t_end:
                loads.append(os.getloadavg()[0])
                time.sleep(min(30.0, max(0.0, t_end - time.monotonic())))
            if run.poll() is None:
                run.send_signal(signal.SIGINT)  # as the operator's Ctrl-C: exit 130, log and summary written
            try:
                rc = run.wait(timeout=120)
            except subprocess.TimeoutExpired:
                run.kill()
                rc = run.wait()
    finally:
        _stop(burn, signal.SIGKILL)
        _stop(devices[1:])  # the devices first, while the server still carries the bus
        _stop(devices[:1])
    (run_dir / "meta.json").write_text(json.dumps({"rc": rc, "burners": burners, "minutes": minutes,
                                                   "load1": loads}))


def summarize(run_dir: Path) -> dict:
    """The row of one run (see the module docstring)."""
    meta = json.loads((run_dir / "meta.json").read_text())
    row: dict = {"run": run_dir.name, "burners": meta["burners"], "rc": meta["rc"],
                 "load1_mean": round(sum(meta["load1"]) / max(1, len(meta["load1"])), 1)}
    logs = sorted((run_dir / "out").glob("*.mcap"))
    sums = sorted((run_dir / "out").glob("*.summary.json"))
    if not logs or not sums:
        row["error"] = "no log or summary"
        return row
    log = read_log(logs[-1])
    events = log.data("/events")
    causes: Counter[str] = Counter()
    for e in events:
        if e["kind"] in ("pause", "watchdog_pause"):
            m = e["message"]
            causes["bridge: no device status" if "device heartbeat lost" in m else
                   "device: heartbeat_lost" if "heartbeat_lost" in m else m[:40]] += 1
    recoveries = [e for e in events if e["kind"] == "recovery"]
    params: dict[int, list] = {}
    for p in log.data("/proposals"):
        params.setdefault(p["index"], []).append(p["params"])
    summary = json.loads(sums[-1].read_text())
    row.update(
        evaluations=summary["n_evaluations"],
        pauses=sum(causes.values()),
        pause_causes=dict(causes),
        recoveries_short=sum(1 for e in recoveries if not e["details"]["warm_up"]),
        recoveries_warm_up=sum(1 for e in recoveries if e["details"]["warm_up"]),
        remeasured_other_setting=sum(1 for v in params.values() if any(x != v[0] for x in v)),
        end_reason=summary["end_reason"],
        resume_budget_stop=summary["end_reason"] == "resume_budget",
        worst_stall_ms=(summary.get("loop") or {}).get("worst_stall_ms"),
        paused_min=round(summary["walking"]["paused_s"] / 60.0, 1),
        warm_up_min=round(summary["walking"]["warm_up_s"] / 60.0, 1),
    )
    stats = re.search(r'"stats": (\{[^}]*\})', (run_dir / "exosuit.log").read_text())
    if stats:
        st = json.loads(stats.group(1))
        row["device_watchdogs"] = {k: st.get(k, 0) for k in ("heartbeat_lost", "liveness_lost")}
    return row


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--minutes", type=float, default=15.0, help="each session's length (default 15)")
    ap.add_argument("--burners", type=int, default=2, help="CPU-burning processes beside it (default 2)")
    ap.add_argument("--runs", type=int, default=1, help="sessions in a row (default 1)")
    ap.add_argument("--seed", type=int, default=1, help="the virtual cart's wearer (default 1)")
    ap.add_argument("--out", type=Path, required=True, help="a new directory for the runs")
    ap.add_argument("--summarize", action="store_true", help="only print the rows of the runs in --out")
    args = ap.parse_args(argv)
    if args.summarize:
        dirs = sorted(d for d in args.out.iterdir() if (d / "meta.json").exists())
    else:
        dirs = [args.out / f"run{i + 1}" for i in range(args.runs)]
        for i, d in enumerate(dirs):
            sys.stderr.write(f"busy_pc: run {i + 1} of {args.runs} ({args.minutes:g} min, "
                             f"{args.burners} burners) in {d}\n")
            run_once(d, args.minutes, args.burners, args.seed)
    rows = [summarize(d) for d in dirs]
    sys.stdout.write("".join(json.dumps(row) + "\n" for row in rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
