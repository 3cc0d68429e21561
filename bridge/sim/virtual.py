"""``hilbo sim``: the bridge driving the virtual exosuit and virtual cart over real transports.

Everything runs in one process: the virtual exosuit on a python-can ``virtual`` bus, the virtual
cart serving breaths over TCP on loopback, and the very :func:`bridge.run.run_session` a lab
runs, reading that cart and pushing profiles on that bus. The simulated wearer feels the profile
the exosuit *applies* (its ``on_applied`` feeds the cart's wearer), so a refused or lost profile
shows in the metabolic data as it would in a lab.

Clock: the devices share a :class:`~virtual_hw.clock.ScaledClock`. The bridge's watchdogs and
the devices' heartbeats run on wall time, as in the lab, so the speed factor is bounded by how
faithfully they keep up: at ``--speed max`` (:data:`MAX_SPEED` × real time) a 60-minute session
takes about 40 s; a proposal that takes 50 ms of computing then costs 5 s of simulated walking
on the old setting, which the evaluation clock (started when the device reports the new profile
active) excludes.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
import logging
import math
import time
import uuid
from collections.abc import Callable
from pathlib import Path
from typing import Any

import msgspec

from bridge.collector import GcMode
from bridge.config import HilboConfig, LiveConfig, parse_config
from bridge.run import RunResult, run_session, write_json_atomic
from bridge.runtime import BridgeSession
from bridge.sim.core import optimisation_minutes
from drivers.exosuit import CanBusConfig
from hilbo_core.errors import ConfigError
from hilbo_core.presets import preset
from hilbo_core.protocol import ProtocolKind, protocol_preset
from virtual_hw.cart import CartLink, LinkKind, VirtualCart
from virtual_hw.clock import ScaledClock, SkippingClock
from virtual_hw.exosuit import SUIT_JOINTS, VirtualExosuit
from virtual_hw.wearer import Wearer, WearerKind, make_wearer, wearer_kind

__all__ = ["MAX_SPEED", "VirtualSimConfig", "add_simulation_truth", "run_virtual_sim", "sim_config_text"]

logger = logging.getLogger(__name__)

#: The factor ``--speed max`` stands for (see the module docstring).
MAX_SPEED = 100.0
_GC_MODES = frozenset(m.value for m in GcMode)


@dataclasses.dataclass(frozen=True)
class VirtualSimConfig:
    """A simulated session over the virtual devices.

    Attributes:
        minutes: Whole session (both bouts and their warm-ups), in minutes of walking.
        seed: The subject (wearer) and the optimizer's seed.
        speed: Real-time factor (None = :data:`MAX_SPEED`).
        preset: Parameter space.
        stopping: ``sound`` (the default rule), ``sound-floor`` (it on a fixed 60 s clock, the earlier
            default), ``adaptive`` (Kim et al. 2019's Algorithm 1/2) or ``fixed``.
        n_explore, max_breaths, window, warmup_s: The protocol; ``n_explore`` None: the walking
            protocol's (the sound rule walks the fast protocol: 3; the seed's rules Kim et al.
            2019's: 6, with a pause and a second warm-up between the bouts).
        body_mass_kg: The simulated wearer's mass.
        feedback_hz: The virtual exosuit's force-feedback rate per actuator.
        exosuit_faults: Fault specs of the virtual exosuit (``virtual_hw.exosuit.EXOSUIT_FAULTS``).
        cart_faults: Fault specs of the virtual cart (``virtual_hw.cart.CART_FAULTS``).
        gc: The bridge's ``[protocol] gc`` (``freeze`` or ``automatic``, bridge/collector.py).
        proposal_worker: The bridge's ``[protocol] proposal_worker`` (``process`` or ``thread``).
        wearer: The simulated wearer (:class:`virtual_hw.wearer.WearerKind` value): ``realistic``
            (default), ``noisy``, ``slow`` or ``legacy``.
    """

    minutes: float = 60.0
    seed: int = 1
    speed: float | None = None
    preset: str = "hip_6d"
    stopping: str = "sound"
    n_explore: int | None = None
    max_breaths: int = 45
    window: int = 2
    warmup_s: float = 180.0
    body_mass_kg: float = 75.0
    feedback_hz: float = 200.0
    exosuit_faults: tuple[str, ...] = ()
    cart_faults: tuple[str, ...] = ()
    gc: str = "freeze"
    proposal_worker: str = "process"
    wearer: str = WearerKind.REALISTIC.value

    def __post_init__(self) -> None:
        wearer_kind(self.wearer)  # raises ConfigError naming the value and the choices
        if not (math.isfinite(self.minutes) and 0 < self.minutes <= 600):
            raise ConfigError(f"minutes={self.minutes!r}; expected a number in (0, 600]")
        if self.speed is not None and not (math.isfinite(self.speed) and self.speed > 0):
            raise ConfigError(f"speed={self.speed!r}; expected 'max' or a positive factor")
        if self.gc not in _GC_MODES:
            raise ConfigError(f"gc={self.gc!r}; expected one of {sorted(_GC_MODES)}")

    @property
    def budget_min(self) -> float:
        """The optimisation bout's budget: what the minutes leave after the warm-ups and the
        exploration bout (:func:`bridge.sim.core.optimisation_minutes`)."""
        sound = self.stopping in ("sound", "sound-floor")
        kind = ProtocolKind.FAST if sound else ProtocolKind.SEED
        n_explore = self.n_explore if self.n_explore is not None else protocol_preset(kind)[1]["n_explore"]
        return optimisation_minutes(self.minutes, kind, int(n_explore), self.max_breaths, self.warmup_s)


def sim_config_text(cfg: VirtualSimConfig, out_dir: Path, *, device_timeout_ms: float = 250.0) -> str:
    """The session config the simulated lab runs (cart and CAN are filled in at start).

    Args:
        cfg: The simulated session.
        out_dir: Output directory.
        device_timeout_ms: The bridge's device-heartbeat watchdog.
    """
    return f"""
[session]
subject = "sim{cfg.seed}"
body_mass_kg = {cfg.body_mass_kg}
out_dir = "{out_dir.as_posix()}"
notes = "hilbo sim: virtual exosuit and virtual cart, seed {cfg.seed}"

[space]
preset = "{cfg.preset}"

[protocol]
warmup_s = {cfg.warmup_s}
{"" if cfg.n_explore is None else f"n_explore = {cfg.n_explore}"}
max_breaths = {cfg.max_breaths}
window = {cfg.window}
# The session ends at the first breath past `minutes` of walking (session_min, as a lab sets
# it); the bout budget is only an upper bound here (its check: VirtualSimConfig.budget_min).
session_min = {cfg.minutes}
budget_min = {max(cfg.budget_min, cfg.minutes)}
stopping = "{cfg.stopping}"
seed = {cfg.seed}
gc = "{cfg.gc}"
proposal_worker = "{cfg.proposal_worker}"

[cart]
transport = "tcp"
format = "hilbo-line"

[cart.options]
host = "127.0.0.1"
port = 1

[can]
interface = "virtual"
channel = "hilbo-sim"

[watchdog]
device_heartbeat_timeout_ms = {device_timeout_ms}
cart_data_timeout_s = 15.0
# Nobody presses "r" in a simulation: every pause ends by the resume policy, which
# a busy machine may need often (a stalled loop loses the heartbeat).
auto_resume_s = 0.0
max_auto_resumes = 1000
"""


async def run_virtual_sim(cfg: VirtualSimConfig, out: Path, *, operator_view: bool = False,
                          on_session: Callable[[BridgeSession], None] | None = None,
                          on_exosuit: Callable[[VirtualExosuit], None] | None = None,
                          live: LiveConfig | None = None,
                          device_timeout_ms: float = 250.0) -> dict[str, Any]:
    """Run a whole session over the virtual devices; writes OUT/session.mcap and OUT/summary.json.

    Args:
        cfg: The simulated session.
        out: Output directory.
        operator_view: Show the live terminal view.
        on_session: Called with the bridge session before it runs (tests drive the operator).
        on_exosuit: Called with the open virtual exosuit before the bridge starts (its ``stats``
            count what it sent, for ``hilbo bench perf --bridge-minutes``).
        live: The live view (``hilbo sim --live``: :class:`~bridge.config.LiveConfig` enabled);
            None: off.
        device_timeout_ms: The bridge's device-heartbeat watchdog (``hilbo bench watchdog``
            times it at the lab's default, 100 ms).

    Returns:
        The summary, with the simulation's truth (true optimum, true cost of the recommendation).
    """
    wall0 = time.perf_counter()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    log_path = out / "session.mcap"
    if log_path.exists():
        log_path.unlink()  # the simulation's log is regenerated; a lab log never is
    space = preset(cfg.preset)
    speed = cfg.speed or MAX_SPEED
    # --speed max without faults: the clock skips ahead while the bridge waits for a breath
    # (_skip_idle_time). Faults are scheduled in simulated time and watched in wall time, so a
    # session with faults keeps the plain factor.
    skipping = cfg.speed is None and not cfg.exosuit_faults and not cfg.cart_faults
    clock = SkippingClock(speed) if skipping else ScaledClock(speed)
    wearer = make_wearer(cfg.wearer, space, seed=cfg.seed, body_mass_kg=cfg.body_mass_kg)
    channel = f"hilbo-sim-{uuid.uuid4().hex[:8]}"
    hcfg: HilboConfig = parse_config(sim_config_text(cfg, out, device_timeout_ms=device_timeout_ms),
                                     source="<hilbo sim>")
    async with VirtualCart(wearer, clock, link=CartLink(kind=LinkKind.TCP),
                           faults=cfg.cart_faults) as cart:
        hcfg = dataclasses.replace(
            hcfg,
            cart=cart.client_config(),
            can=msgspec.structs.replace(hcfg.can, bus=CanBusConfig("virtual", channel)),
            live=live or hcfg.live,
        )
        async with VirtualExosuit(CanBusConfig("virtual", channel), clock,
                                  joints=SUIT_JOINTS[cfg.preset], seed=cfg.seed,
                                  on_applied=cart.on_profile_applied,
                                  feedback_hz=cfg.feedback_hz, faults=cfg.exosuit_faults) as exo:
            if on_exosuit is not None:
                on_exosuit(exo)
            skipper: list[asyncio.Task[None]] = []

            def started(session: BridgeSession) -> None:
                if isinstance(clock, SkippingClock):
                    skipper.append(asyncio.create_task(_skip_idle_time(session, clock, cart),
                                                       name="sim-clock-skipper"))
                if on_session is not None:
                    on_session(session)

            try:
                result: RunResult = await run_session(
                    hcfg, log_path=log_path, auto_resume_s=0.0, operator_view=operator_view,
                    n_actuators=len(SUIT_JOINTS[cfg.preset]), on_session=started)
            finally:
                for task in skipper:
                    task.cancel()
                    with contextlib.suppress(asyncio.CancelledError):
                        await task
    summary = add_simulation_truth(result.summary, wearer)
    summary["sim"] = {**dataclasses.asdict(cfg), "speed": speed,
                      "clock_skipped_s": clock.skipped_s if isinstance(clock, SkippingClock) else 0.0}
    summary["wall_time_s"] = time.perf_counter() - wall0
    write_json_atomic(out / "summary.json", summary)
    result.summary_path.unlink(missing_ok=True)  # summary.json is the simulation's summary
    return summary


#: Event-loop turns the skipper lets pass before it skips: a breath already written to the
#: loopback socket reaches the bridge's queue in 3 (virtual_hw/clock.py, DEFAULT_SETTLE_TURNS).
_SETTLE_TURNS = 8


async def _skip_idle_time(session: BridgeSession, clock: SkippingClock, cart: VirtualCart) -> None:
    """While the bridge waits for a breath, skip the clock to the cart's next tick.

    The wait for a breath is the one wait of a simulated session that stands for walking (the
    bridge's other waits are its own work: a push, the device applying at its gait-cycle
    boundary, a proposal). Nothing is pending at the exosuit then (the setting is applied before
    its breaths are awaited), so the wearer's breaths and the applied profile stay in order.
    """
    while True:
        await session.breath_wanted.wait()
        for _ in range(_SETTLE_TURNS):
            await asyncio.sleep(0)
        tick = cart.next_tick_s
        if not session.breath_wanted.is_set() or tick is None:
            continue
        if clock.skip_to(tick) == 0.0:
            await asyncio.sleep(0.001)  # the cart has not taken its tick yet (or has ended)


def add_simulation_truth(summary: dict[str, Any], wearer: Wearer,
                         end_s: float | None = None) -> dict[str, Any]:
    """A copy of a session summary with what only a simulation knows: the true optimum, the
    unassisted cost, the true cost of the recommended setting and its regret, the subject.

    Costs and regret are the wearer's unadapted landscape (time 0). The realistic wearer's
    adaptation scales every setting's cost by the same factor, so the regret as % of the
    reduction is the same at any time; ``adaptation_factor_at_end`` and ``regret_w_at_end``
    (the regret in W at the session's end) say what it is at the end.

    Args:
        summary: The bridge's summary (``BridgeSession.summary``).
        wearer: The simulated subject (the cart's wearer, or one built with the same seed).
        end_s: The session's end on the wearer's breath clock; None: the wearer's last breath.
    """
    summary = dict(summary)
    end = wearer.t_s if end_s is None else end_s
    factor = wearer.adaptation_factor(end)
    summary["adaptation_factor_at_end"] = factor
    opt_params, opt_cost = wearer.true_optimum
    summary["true_optimum"] = {"params": opt_params, "cost_w": opt_cost}
    summary["baseline_cost_w"] = wearer.baseline_cost_w
    if summary.get("best_params") is not None:
        true_best = wearer.true_cost_w(summary["best_params"])
        summary["true_cost_of_best"] = true_best
        summary["regret_w"] = true_best - opt_cost
        summary["regret_w_at_end"] = (true_best - opt_cost) * factor
        summary["regret_pct_of_reduction"] = 100.0 * (true_best - opt_cost) / max(
            wearer.baseline_cost_w - opt_cost, 1e-9)
    summary["subject"] = wearer.subject
    return summary
