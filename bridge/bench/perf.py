"""``hilbo bench perf``: compute latency of the pieces that run while a person walks.

* **Breath latency** — one :meth:`HILOptimizer.observe_breath` in the optimisation phase: the UKF
  update (Kim et al. 2019 §II.C) and the σ-scaled stopping decision (§II.D), with the optimizer's
  bookkeeping. Breaths come from a simulated wearer; the proposals between evaluations are not
  timed here. Median and p99 over all timed breaths.
* **Proposal latency** — one :meth:`HILOptimizer.ask` in the optimisation phase of ``hip_6d``
  (6-D, two linear constraints): GP hyperparameter fit + EI maximisation. For every size n the
  optimizer holds n − 1 evaluations, proposes once (untimed: in a session the previous proposal
  has warmed the hyperparameters), then gets one more evaluation and the timed proposal follows —
  the situation after every evaluation of a real session. Median and p95 over ``reps`` seeds.
  One proposal at the largest size ≤ 60 is profiled to say where the time goes.
* **Proposal latency, hyperparameters fitted ahead** — the same proposals with ``refit_lag`` 1,
  the bridge's default (``[protocol] refit = "ahead"``): the hyperparameters were fitted on the
  n − 1 earlier evaluations while the n-th was measured, so the timed ``ask()`` conditions the GP
  on all n and maximises EI. This is what stands between a stop decision and the next push.
* **Session wall time** — :func:`bridge.sim.core.run_insim` of a 60-minute ``hip_6d`` session
  (adaptive stopping) at ``speed=max``, for a few subject seeds.
* **The bridge at real time** (opt-in, ``bridge_minutes`` > 0) — a
  :func:`bridge.sim.virtual.run_virtual_sim` session at speed 1 with 2 × 1 kHz force feedback: stop →
  ack latency, dropped and logged feedback frames, CPU (:mod:`bridge.bench.bridge_perf`).

Runs in this process (latency is a single-process property); other load on the machine shows up
in the numbers, so the load average at the start is recorded.
"""

from __future__ import annotations

import cProfile
import math
import os
import pstats
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from bridge.bench.bridge_perf import BridgeRtConfig, bridge_realtime, bridge_table
from bridge.bench.common import blas_threads, markdown_table, round_sig
from bridge.sim.core import SimConfig, run_insim
from bridge.sim.devices import SimulatedWearer
from hilbo_core.errors import ConfigError
from hilbo_core.metabolic import brockway_watts
from hilbo_core.optimizer import HILOptimizer, Phase
from hilbo_core.presets import hip_6d

__all__ = [
    "PerfConfig",
    "breath_latency",
    "perf_table",
    "proposal_ahead_latency",
    "proposal_latency",
    "run_perf",
    "session_wall",
]

TARGETS = {"breath_p99_ms": 2.0, "proposal_p95_ms_at_60": 100.0, "session_60min_wall_s": 20.0}


@dataclass(frozen=True)
class PerfConfig:
    """Sizes of the perf benchmark.

    Attributes:
        breaths: Optimisation-phase breaths to time.
        sizes: Observation counts for the proposal latency.
        reps: Timed proposals per size.
        sessions: 60-minute sessions to time.
        session_minutes: Session length for the wall-time measurement.
        seed: First seed.
        bridge_minutes: Length of the real-time bridge session (minutes; 0 = skip it).
        bridge_speed: Its real-time factor (1 = real time; more only for tests and demos).
        bridge_feedback_hz: Its force-feedback rate per actuator (Hz).
        bridge_baseline_s: How long the virtual exosuit then runs alone, for the bridge's share of
            the CPU (wall s; 0 = skip).
        bridge_gc: That session's garbage-collection policy (``freeze`` or ``automatic``).
        bridge_protocol: That session's protocol (:class:`~bridge.bench.bridge_perf.BridgeProtocol`:
            ``quick``, many stop decisions per minute, or ``lab``, the lab's own).
    """

    breaths: int = 1500
    sizes: tuple[int, ...] = (10, 30, 60, 100)
    reps: int = 20
    sessions: int = 3
    session_minutes: float = 60.0
    seed: int = 1
    bridge_minutes: float = 0.0
    bridge_speed: float = 1.0
    bridge_feedback_hz: float = 1000.0
    bridge_baseline_s: float = 30.0
    bridge_gc: str = "freeze"
    bridge_protocol: str = "quick"

    def __post_init__(self) -> None:
        for name, low in (("breaths", 10), ("reps", 1), ("sessions", 0), ("seed", 0)):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < low:
                raise ConfigError(f"{name}={v!r}; expected an integer >= {low}")
        sizes = tuple(self.sizes)
        if not sizes or any(isinstance(n, bool) or not isinstance(n, int) or n < 3 for n in sizes):
            raise ConfigError(f"sizes={list(sizes)!r}; expected observation counts >= 3")
        object.__setattr__(self, "sizes", sizes)
        if not (math.isfinite(self.session_minutes) and 0 < self.session_minutes <= 600):
            raise ConfigError(f"session_minutes={self.session_minutes!r}; expected a number in (0, 600]")
        if not (math.isfinite(self.bridge_minutes) and 0 <= self.bridge_minutes <= 600):
            raise ConfigError(f"bridge_minutes={self.bridge_minutes!r}; expected 0 (skip) or a number "
                              "in (0, 600]")
        if self.bridge_minutes > 0:
            try:  # the bridge session is validated before any work starts
                self.bridge_config()
            except ConfigError as err:
                raise ConfigError(f"bridge_minutes={self.bridge_minutes:g}: {err}") from err

    def bridge_config(self) -> BridgeRtConfig:
        """The real-time bridge session of this benchmark."""
        return BridgeRtConfig.for_protocol(self.bridge_protocol, minutes=self.bridge_minutes,
                                           speed=self.bridge_speed, feedback_hz=self.bridge_feedback_hz,
                                           seed=self.seed, baseline_s=self.bridge_baseline_s,
                                           gc=self.bridge_gc)


def _quantiles_ms(samples_ns: Sequence[int], q: float, cpu_ns: Sequence[int] = ()) -> dict[str, float]:
    """Median, p``q`` and max in ms of wall-clock samples; the same of CPU-time samples."""
    a = np.asarray(samples_ns, dtype=float) / 1e6
    out = {"median": float(np.median(a)), f"p{q:g}": float(np.percentile(a, q)),
           "max": float(a.max()), "n": int(a.size)}
    if len(cpu_ns):
        c = np.asarray(cpu_ns, dtype=float) / 1e6
        out |= {"cpu_median": float(np.median(c)), f"cpu_p{q:g}": float(np.percentile(c, q))}
    return out


class _Timer:
    """Wall-clock and this thread's CPU time of one call (BLAS runs single-threaded here, so the
    thread's CPU time is the compute; wall minus CPU is time the OS gave to other processes)."""

    def __init__(self) -> None:
        self.wall: list[int] = []
        self.cpu: list[int] = []

    def __enter__(self) -> _Timer:
        self._w = time.perf_counter_ns()
        self._c = time.thread_time_ns()
        return self

    def __exit__(self, *exc: object) -> None:
        self.wall.append(time.perf_counter_ns() - self._w)
        self.cpu.append(time.thread_time_ns() - self._c)

    def drop_last(self) -> None:
        self.wall.pop()
        self.cpu.pop()


def breath_latency(breaths: int, seed: int) -> dict[str, float]:
    """Time ``observe_breath`` for ``breaths`` optimisation-phase breaths (see the module doc)."""
    space = hip_6d()
    wearer = SimulatedWearer(space, seed=seed)
    opt = HILOptimizer(space, budget_breaths=breaths, seed=seed)
    timer = _Timer()
    while not opt.done:
        params = opt.ask()
        t0 = wearer.t_s
        wearer.apply_params(params, t0)
        while True:
            b = wearer.next_breath()
            watts = brockway_watts(b.vo2_ml_min, b.vco2_ml_min)
            with timer:
                step = opt.observe_breath(b.t_s - t0, watts)
            if step.phase is not Phase.OPTIMIZATION:
                timer.drop_last()
            if step.stop:
                break
    return _quantiles_ms(timer.wall, 99, timer.cpu)


def _synthetic_optimizer(n_obs: int, seed: int) -> HILOptimizer:
    """An optimizer on hip_6d holding ``n_obs`` evaluations of a simulated wearer's landscape."""
    space = hip_6d()
    wearer = SimulatedWearer(space, seed=seed)
    rng = np.random.default_rng([seed, n_obs])
    opt = HILOptimizer(space, n_explore=min(6, n_obs), seed=seed)
    units = space.sample_unit(n_obs, rng)
    for u in units:
        params = space.to_dict(space.from_unit(u))
        # A mix of full (≈ 8 W SD) and early-stopped (≈ 25 W SD) estimates, as in a session.
        sd = 8.0 if rng.uniform() < 0.5 else 25.0
        opt.tell(params, wearer.true_cost_w(params) + rng.normal(0.0, sd), sd**2)
    return opt


def _before_timed_proposal(n: int, seed: int, rep: int, *, refit_lag: int = 0) -> HILOptimizer:
    """An optimizer just after its n-th evaluation, its hyperparameters fitted on the first n − 1
    (by the previous proposal of a session, or ahead of this one with ``refit_lag`` 1)."""
    opt = _synthetic_optimizer(n - 1, seed + rep)
    opt.ask()
    opt.cancel_current()
    if refit_lag:
        opt.config = replace(opt.config, refit_lag=refit_lag)
    space = opt.space
    rng = np.random.default_rng([seed, rep, n])
    params = space.to_dict(space.from_unit(space.sample_unit(1, rng)[0]))
    opt.tell(params, 400.0 + rng.normal(0.0, 20.0), 64.0)
    return opt


def proposal_latency(sizes: Sequence[int], reps: int,
                     seed: int) -> tuple[dict[str, dict[str, float]], dict[str, Any]]:
    """Time ``ask()`` at every size (see the module doc); also profile one proposal.

    Returns:
        (``{str(n): {median, p95, max, n, cpu_median, cpu_p95}}`` in ms, a CPU-time profile of
        one proposal at the largest size ≤ 60: total, GP fit and EI maximisation in ms and the
        functions with the most self time).
    """
    out: dict[str, dict[str, float]] = {}
    profile: dict[str, Any] = {}
    prof_n = max([n for n in sizes if n <= 60] or [min(sizes)])
    for n in sizes:
        timer = _Timer()
        for r in range(reps):
            opt = _before_timed_proposal(n, seed, r)
            with timer:
                opt.ask()
            if n == prof_n and r == 0:
                # Profile a second proposal from the same data (hyperparameters warm-started
                # from the first, as in a session): the profiler's overhead stays out of the
                # timed samples.
                opt.cancel_current()
                # Thread CPU time, not wall: on a busy machine preemption would otherwise be
                # charged to whatever function happened to be running.
                prof = cProfile.Profile(time.thread_time)
                prof.enable()
                opt.ask()
                prof.disable()
                profile = _profile_summary(prof, n)
        out[str(n)] = _quantiles_ms(timer.wall, 95, timer.cpu)
    return out, profile


def proposal_ahead_latency(sizes: Sequence[int], reps: int, seed: int) -> dict[str, dict[str, float]]:
    """Time ``ask()`` with the hyperparameters fitted ahead (see the module doc).

    Returns:
        ``{str(n): {median, p95, max, n, cpu_median, cpu_p95}}`` in ms.
    """
    out: dict[str, dict[str, float]] = {}
    for n in sizes:
        timer = _Timer()
        for r in range(reps):
            opt = _before_timed_proposal(n, seed, r, refit_lag=1)
            with timer:
                opt.ask()
        out[str(n)] = _quantiles_ms(timer.wall, 95, timer.cpu)
    return out


def _profile_summary(prof: cProfile.Profile, n: int) -> dict[str, Any]:
    st = pstats.Stats(prof)
    entries = st.stats  # type: ignore[attr-defined]  # {(file, line, func): (cc, nc, tt, ct, callers)}

    def cum_ms(func: str, file_part: str) -> float:
        return 1e3 * sum(v[3] for k, v in entries.items() if k[2] == func and file_part in k[0])

    total = 1e3 * max(v[3] for v in entries.values())
    top = sorted(((v[2], k) for k, v in entries.items()), reverse=True)[:8]
    return {
        "observations": n,
        "total_ms": total,
        "gp_fit_ms": cum_ms("fit", "gp.py"),
        "maximize_ei_ms": cum_ms("maximize_ei", "acquisition.py"),
        "top_self_time_ms": [{"function": f"{os.path.basename(k[0])}:{k[1]}({k[2]})", "ms": 1e3 * tt}
                             for tt, k in top],
    }


def session_wall(sessions: int, minutes: float, seed: int) -> list[dict[str, float]]:
    """Wall time of ``sessions`` simulated sessions of ``minutes`` (hip_6d, adaptive)."""
    out = []
    for k in range(sessions):
        t0, c0 = time.perf_counter(), time.process_time()
        summary = run_insim(SimConfig(minutes=minutes, seed=seed + k))
        out.append({"seed": seed + k, "wall_s": time.perf_counter() - t0, "cpu_s": time.process_time() - c0,
                    "n_evaluations": summary["n_evaluations"], "n_breaths": summary["n_breaths"]})
    return out


def run_perf(cfg: PerfConfig, bridge_out: Path | None = None) -> dict[str, Any]:
    """The whole perf benchmark; the ``perf.json`` content.

    Args:
        cfg: The sizes.
        bridge_out: Where the real-time bridge session writes ``session.mcap`` and
            ``summary.json`` (default a temporary directory); unused with ``bridge_minutes`` 0.
    """
    before = blas_threads(1)  # as the benchmarks and (recommended) the bridge run
    load = os.getloadavg()
    t0 = time.perf_counter()
    breath = breath_latency(cfg.breaths, cfg.seed)
    proposal, profile = proposal_latency(cfg.sizes, cfg.reps, cfg.seed)
    ahead = proposal_ahead_latency(cfg.sizes, cfg.reps, cfg.seed)
    sessions = session_wall(cfg.sessions, cfg.session_minutes, cfg.seed)
    walls = [s["wall_s"] for s in sessions]
    bridge = bridge_realtime(cfg.bridge_config(), bridge_out) if cfg.bridge_minutes > 0 else None
    return round_sig({
        "benchmark": "perf",
        "config": {**asdict(cfg), "sizes": list(cfg.sizes)},
        "load_average_at_start": list(load),
        "blas_threads": 1 if before else "unchanged (no OpenBLAS found)",
        "breath_latency_ms": breath,
        "proposal_latency_ms": proposal,
        "proposal_profile": profile,
        "proposal_ahead_latency_ms": ahead,
        "session_60min_wall_s": float(np.median(walls)) if walls else None,
        "session_60min_cpu_s": float(np.median([s["cpu_s"] for s in sessions])) if walls else None,
        "sessions": sessions,
        "bridge_realtime": bridge,
        "targets": TARGETS,
        "wall_s": time.perf_counter() - t0,
    })


def perf_table(result: dict[str, Any]) -> str:
    """Markdown: every measurement against its target."""

    def met(value: float, target: float) -> str:
        return "yes" if value < target else "no"

    def cpu(q: dict[str, float], key: str, digits: int) -> str:
        if f"cpu_{key}" not in q:
            return "–"
        return f"median {q['cpu_median']:.{digits}f} ms, {key} {q[f'cpu_{key}']:.{digits}f} ms"

    b = result["breath_latency_ms"]
    rows = [["breath (estimator update + stopping decision)",
             f"median {b['median']:.3f} ms, p99 {b['p99']:.3f} ms", cpu(b, "p99", 3),
             f"p99 < {TARGETS['breath_p99_ms']:g} ms", met(b["p99"], TARGETS["breath_p99_ms"])]]
    t60 = TARGETS["proposal_p95_ms_at_60"]
    for n, q in result["proposal_latency_ms"].items():
        rows.append([f"proposal, {n} observations (GP fit + EI)",
                     f"median {q['median']:.1f} ms, p95 {q['p95']:.1f} ms", cpu(q, "p95", 1),
                     f"p95 < {t60:g} ms" if n == "60" else "–", met(q["p95"], t60) if n == "60" else "–"])
    for n, q in (result.get("proposal_ahead_latency_ms") or {}).items():
        rows.append([f"proposal, {n} observations, hyperparameters fitted ahead (EI only)",
                     f"median {q['median']:.1f} ms, p95 {q['p95']:.1f} ms", cpu(q, "p95", 1), "–", "–"])
    s = result["session_60min_wall_s"]
    if s is not None:
        ts = TARGETS["session_60min_wall_s"]
        c = result.get("session_60min_cpu_s")
        rows.append([f"{result['config']['session_minutes']:g}-minute simulated session (median of "
                     f"{len(result['sessions'])})", f"{s:.1f} s", "–" if c is None else f"{c:.1f} s",
                     f"< {ts:g} s", met(s, ts)])
    table = markdown_table(["measurement", "wall clock", "CPU time", "target (wall)", "met"], rows)
    if result.get("bridge_realtime"):
        b = result["bridge_realtime"]
        c = b["config"]
        table += (f"\nThe bridge at real time ({c['minutes']:g} min at speed {c['speed']:g}, "
                  f"{b['actuators']} × {c['feedback_hz']:g} Hz feedback):\n\n" + bridge_table(b))
    return table
