"""The stop -> ack latencies the session reports pair one to one with the log's pushes that
answer a stop decision, also when a pause comes and goes between the decision and the push
(its length is then no part of a stop -> ack latency)."""

from __future__ import annotations

import asyncio
from pathlib import Path

from supervision_harness import InlineWorker, run_session

from bridge.bench.bridge_perf import _breakdown, _log_counts
from bridge.proposals import Asked
from bridge.runtime import BridgeSession, Command
from hilbo_core import HILOptimizer


class _PausingWorker(InlineWorker):
    """Asks in the loop; the ``pause_at``-th ask (0-based) sees the operator pause and resume
    while it runs, so the push after it comes after a pause that began after the decision."""

    def __init__(self, session: BridgeSession, pause_at: int) -> None:
        super().__init__()
        self.session, self.pause_at, self.n = session, pause_at, 0

    def start_ask(self, opt: HILOptimizer) -> asyncio.Task[Asked]:
        k, self.n = self.n, self.n + 1
        if k != self.pause_at:
            return super().start_ask(opt)
        session = self.session

        async def ask() -> Asked:
            session.command(Command.PAUSE)
            await asyncio.sleep(0.5)
            session.command(Command.RESUME)
            await asyncio.sleep(0.5)  # the resume's own awaits run before the answer
            return Asked(opt, opt.ask(), 0.0, 0.0)
        return asyncio.get_running_loop().create_task(ask())


def _install(pause_at: int):
    def on_session(session: BridgeSession) -> None:
        # run_session puts its InlineWorker in after on_session; swap it in at the first breath.
        original = session._propose

        async def propose(act):  # type: ignore[no-untyped-def]
            if not isinstance(session._worker, _PausingWorker):
                session._worker = _PausingWorker(session, pause_at)  # type: ignore[assignment]
            return await original(act)
        session._propose = propose  # type: ignore[method-assign]
    return on_session


def test_a_pause_between_a_stop_decision_and_its_push_is_left_out_on_both_sides(tmp_path: Path) -> None:
    out = run_session(tmp_path, n_evaluations=5, on_session=_install(pause_at=3))
    assert out.summary["n_evaluations"] >= 4
    counts = _log_counts(out.log)
    assert counts["events"].get("pause") == 1 == counts["events"].get("resume")
    assert out.session.supervisor.pauses == 1
    stop_ms = [1e3 * s for s in out.session.stop_latencies_s]
    pushes = counts["pushes"]
    # Every push but the pause's answers a stop decision; the two sides agree which.
    assert 1 <= len(stop_ms) == sum(p.after_stop for p in pushes)
    assert _breakdown(stop_ms, pushes) is not None
    # The latency of the push after the pause would hold the pause's second: none does.
    assert max(stop_ms) < 500.0
