"""Soak test of whole simulated sessions: does every ``hilbo sim`` reach its end?

Runs ``hilbo sim --minutes M`` N times in a row, in-process and/or with ``--processes``,
optionally beside one CPU-burning process per core (``--burn``, the busy lab PC), each with a
wall-clock timeout, and prints one row per run: exit status, wall time, evaluations (and how many
in the optimisation bout), pauses, resumes, the worst event-loop stall (ms) and the stalls over
half the device's heartbeat watchdog (summary.json's ``loop``), and whether the log says the
session ended. Exit
status 1 if any run failed, stalled past its timeout or ended without optimisation evaluations.

    .venv/bin/python scripts/soak_sim.py --runs 20 --processes-runs 20 --minutes 30 --burn
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from bridge.log.reader import read_log


def _burn() -> None:
    while True:
        pass


def _run(out: Path, minutes: float, seed: int, processes: bool, timeout_s: float) -> dict:
    cmd = [sys.executable, "-m", "bridge.cli.main", "sim", "--minutes", f"{minutes:g}", "--seed", str(seed),
           "--out", str(out)] + (["--processes"] if processes else [])
    t0 = time.monotonic()
    with open(out.parent / f"{out.name}.stderr", "w") as err:
        proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=err, start_new_session=True)
        try:
            rc: int | str = proc.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
            rc = "stalled"
    row: dict = {"mode": "processes" if processes else "in-process", "seed": seed, "rc": rc,
                 "wall_s": round(time.monotonic() - t0, 1)}
    summary = out / "summary.json"
    if summary.exists():
        s = json.loads(summary.read_text())
        evals = s.get("evaluations", [])
        row["evaluations"] = len(evals)
        row["optimisation"] = sum(1 for e in evals if e.get("phase") == "optimization")
        loop = s.get("loop") or {}
        row.update(worst_stall_ms=loop.get("worst_stall_ms"),
                   stalls_over_half_heartbeat=loop.get("stalls_over_half_heartbeat"))
    log_path = out / "session.mcap"
    if log_path.exists():
        kinds = [e["kind"] for e in read_log(log_path).data("/events")]
        row.update(pauses=kinds.count("pause"), resumes=kinds.count("resume"),
                   ended="session_end" in kinds)
    return row


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--runs", type=int, default=3, help="in-process runs")
    p.add_argument("--processes-runs", type=int, default=0, help="runs with --processes")
    p.add_argument("--minutes", type=float, default=30.0)
    p.add_argument("--timeout-s", type=float, default=600.0, help="wall-clock limit per run")
    p.add_argument("--burn", action="store_true", help="one CPU-burning process per core beside the runs")
    p.add_argument("--out", default=None, help="keep the runs here (default: a temporary folder)")
    args = p.parse_args(argv)
    burners = [multiprocessing.Process(target=_burn, daemon=True) for _ in range(os.cpu_count() or 1)] \
        if args.burn else []
    for b in burners:
        b.start()
    rows = []
    try:
        with tempfile.TemporaryDirectory() as tmp:
            base = Path(args.out) if args.out else Path(tmp)
            base.mkdir(parents=True, exist_ok=True)
            plan = [(False, i) for i in range(args.runs)] + [(True, i) for i in range(args.processes_runs)]
            for k, (processes, i) in enumerate(plan, 1):
                out = base / f"{'p' if processes else 'i'}{i + 1}"
                row = _run(out, args.minutes, i + 1, processes, args.timeout_s)
                rows.append(row)
                sys.stdout.write(f"[{k}/{len(plan)}] {json.dumps(row)}\n")
                sys.stdout.flush()
    finally:
        for b in burners:
            b.terminate()
            b.join()
    bad = [r for r in rows if r["rc"] != 0 or not r.get("ended") or not r.get("optimisation")]
    sys.stdout.write(f"{len(rows) - len(bad)} of {len(rows)} runs reached their end with optimisation "
                     "evaluations\n")
    stalls = [r["worst_stall_ms"] for r in rows if r.get("worst_stall_ms") is not None]
    if stalls:
        sys.stdout.write(f"worst event-loop stall: {max(stalls):.1f} ms (per run: "
                         f"{', '.join(f'{x:.1f}' for x in stalls)})\n")
    return 1 if bad else 0


if __name__ == "__main__":
    sys.exit(main())
