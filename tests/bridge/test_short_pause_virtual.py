"""A pause proportionate to the fault, end to end on the virtual devices: the operator's p then
r a few seconds later measures the very setting it abandoned again, at once, without a warm-up
(the log shows the same parameters for the same evaluation index); a long pause warms up first
and then measures that same setting again too."""

from __future__ import annotations

import asyncio
import dataclasses

import pytest

from bridge.log.reader import read_log
from bridge.runtime import BridgeSession, Command
from bridge.sim.virtual import VirtualSimConfig, run_virtual_sim
from hilbo_core.types import BreathRecord

pytestmark = pytest.mark.slow


def small() -> VirtualSimConfig:
    return VirtualSimConfig(minutes=9.0, seed=2, n_explore=3, max_breaths=10, warmup_s=20.0,
                            proposal_worker="thread")


EVALUATION = 5  # the second of the optimisation bout (3 exploration settings before it)


def pause_in_evaluation(pause_s: float):
    """An operator who presses p after 2 breaths of evaluation 5 and r ``pause_s`` of walking
    later; records the breath times of both."""
    times: dict[str, float] = {}

    def operator(session: BridgeSession) -> None:
        session.settings = dataclasses.replace(session.settings, operator_present=True)
        st = session.status

        # At the breaths themselves (the session's listeners), not by polling in wall time: at
        # 100x on a busy machine a poll could miss the evaluation's second breath.
        def on_breath(rec: BreathRecord) -> None:
            if "p" not in times and st.evaluation == EVALUATION and st.breaths_in_setting >= 2:
                times["p"] = st.breath_time_s
                session.command(Command.PAUSE)
            elif "p" in times and "r" not in times and st.breath_time_s >= times["p"] + pause_s:
                times["r"] = st.breath_time_s
                session.command(Command.RESUME)
        session.breath_listeners.append(on_breath)

    return operator, times


def proposals_of(log, index: int) -> list[dict]:
    return [p for p in log.data("/proposals") if p["index"] == index]


# Both far from short_pause_s (30 s): at 100x on a busy machine a key may take effect a few
# breaths after it was pressed, which must not move a pause across the threshold.
@pytest.mark.parametrize(("pause_s", "warm_up"), [(5.0, False), (90.0, True)],
                         ids=["short-no-warm-up", "long-warm-up"])
def test_the_abandoned_setting_is_measured_again(tmp_path, pause_s: float, warm_up: bool) -> None:
    operator, times = pause_in_evaluation(pause_s)
    asyncio.run(run_virtual_sim(small(), tmp_path, on_session=operator))
    log = read_log(tmp_path / "session.mcap")
    assert "r" in times
    # Evaluation 5 (index 4), a GP proposal: proposed, abandoned by the pause, proposed again.
    proposed = proposals_of(log, EVALUATION - 1)
    assert [p["phase"] for p in proposed] == ["optimization", "optimization"]
    again = [p["params"] for p in proposed]
    assert again[0] == again[1]
    events = log.data("/events")
    (recovery,) = [e for e in events if e["kind"] == "recovery"]
    assert recovery["details"]["warm_up"] is warm_up
    i_resume = next(i for i, e in enumerate(events) if e["kind"] == "resume")
    # Measured to its end after the resume: an evaluation with index 1 and those parameters.
    done = [o for o in log.data("/observations") if o["index"] == EVALUATION - 1]
    assert done and done[0]["params"] == again[0]
    assert i_resume < events.index(recovery)
