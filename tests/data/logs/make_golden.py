"""Write the golden session log of the current format: ``python tests/data/logs/make_golden.py``.

A short deterministic session through :class:`bridge.log.SessionLog`'s typed methods (every
channel), written to ``tests/data/logs/v<FORMAT_VERSION>/session.mcap``. Run it once per format
version (the file of an older version is never rewritten: it stands for the logs that version
wrote). v1 was written with this script by the writer of main at 41b65f5 (whose SessionLog had no
``started_unix_ns``: its /config holds the wall clock of that run); v2 by the msgspec writer;
v3 when the optimizer state gained ``accept_z``; v4 when it gained the confirmation of the
recommendation; v5 when its config gained the sound rule's ``boundary_s``; v6 when it gained
the opt-in trust region; v7 when evaluations gained ``drift_var`` and the config the opt-in
``drift_corr_s`` and ``acquisition``; v8 when the config gained the GP's ``prior_mean_sd``.

``tests/bridge/test_log_golden.py`` also writes this session in-process and compares a digest of
the writer's output (schemas and records) with ``digests.json``, keyed by format version.
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

from bridge import log as bridge_log
from bridge.log import SessionLog
from drivers.exosuit.codec import DeviceFault, DeviceMode, NackReason
from hilbo_core.metabolic import GaussianProductEstimator
from hilbo_core.optimizer import HILOptimizer
from hilbo_core.presets import hip_6d
from hilbo_core.profiles import build_profile
from hilbo_core.types import BreathRecord

HERE = Path(__file__).resolve().parent
STARTED_UNIX_NS = 1_700_000_000_000_000_000


class _Clock:
    """1 ms per call from a fixed epoch (deterministic log times)."""

    def __init__(self) -> None:
        self.ns = 1_700_000_000_000_000_000

    def __call__(self) -> int:
        self.ns += 1_000_000
        return self.ns


def write_session(path: Path, **log_kwargs: Any) -> None:
    """The golden session: 3 evaluations (2 exploration, 1 optimisation) and every channel."""
    space = hip_6d()
    # Kim et al. 2019's rule (it stops within 3 breaths, so every channel gets its records). Options
    # whose default changed since a format version was written are given as they were then
    # (accept_z: off until 2026-12-05), so a default changes no golden record.
    opt = HILOptimizer(space, n_explore=2, max_breaths=3, window=1, budget_breaths=4, seed=1,
                       stopping="adaptive", n_candidates=32, n_local=0, accept_z=None,
                       estimator_factory=lambda: GaussianProductEstimator(400.0, 1e4, 1600.0))
    with SessionLog(path, session_id="golden", config_json={"protocol": {"n_explore": 2, "max_breaths": 3}},
                    param_names=list(space.names), clock_ns=_Clock(), flush_interval_s=None,
                    **log_kwargs) as log:
        log.log_optimizer_state(opt, reason="start")
        log.log_event("session_start", "session started (exploration)")
        for k in range(3):
            params = opt.ask()
            log.log_proposal(params, index=k, phase=opt.phase.value, t_s=100.0 + 10 * k,
                             incumbent=opt.incumbent, compute_ms=12.5, total_ms=20.0, worker="process")
            log.log_profile_sent(build_profile(space.name, params), version=k + 1, crc32=1000 + k,
                                 index=k, params=params, t_s=100.0 + 10 * k)
            log.log_ack(version=k + 1, accepted=True, attempts=1, elapsed_s=0.04, crc32=1000 + k)
            log.log_force_feedback(actuator=0, desired_n=[10.0, 20.0, 30.0], measured_n=[9.5, 21.0, 29.0],
                                   gait_phase_pct=[10.0, None, 30.0], profile_version=k + 1)
            log.log_device_status(actuator=0, mode=DeviceMode.ASSIST, faults=0, gait_phase_pct=40.0,
                                  profile_version_active=k + 1)
            b = 0
            while True:
                rec = BreathRecord(t_s=100.0 + 10 * k + b, vo2_ml_min=1000.0 + 7 * b + k, vco2_ml_min=900.0,
                                   hr_bpm=110.0 if b % 2 else None, ve_l_min=30.0)
                log.log_breath(rec)
                t = 3.0 * (b + 1)
                step = opt.observe_breath(t, rec.watts)
                log.log_step(step, index=k, t_setting_s=t, watts=rec.watts, t_s=rec.t_s,
                             incumbent=opt.incumbent)
                b += 1
                if step.stop:
                    log.log_observation(step.evaluation, t_start=10.0 * k, t_end=10.0 * k + b, t_s=rec.t_s)
                    log.log_optimizer_state(opt, reason="evaluation", t_s=rec.t_s)
                    break
            if k == 1:
                log.log_event("bout_pause", "exploration bout complete; pausing until the operator resumes")
                log.log_event("pause", "operator pause")
                log.log_device_status(actuator=1, mode=DeviceMode.OFF,
                                      faults=DeviceFault.HEARTBEAT_LOST, profile_version_active=k + 1)
                log.log_event("resume_refused", "cannot resume: device faults")
                log.log_device_status(actuator=1, mode=DeviceMode.ASSIST, faults=0,
                                      profile_version_active=k + 1)
                log.log_event("resume", "resumed by the operator")
        log.log_ack(version=9, accepted=False, reason=NackReason.BAD_CRC, detail=3)
        log.log_rejects("cart", {"bad_crc": 2, "impossible": 1}, t_s=140.0)
        log.log_event("session_end", "session ended after 3 evaluations")


def main() -> int:
    out = HERE / f"v{bridge_log.FORMAT_VERSION}" / "session.mcap"
    if out.exists():
        sys.stderr.write(f"{out} exists; a golden file of a released format is never rewritten\n")
        return 1
    out.parent.mkdir(parents=True, exist_ok=True)
    write_session(out, started_unix_ns=STARTED_UNIX_NS)
    sys.stdout.write(f"{out}\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
