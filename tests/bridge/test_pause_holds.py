"""A pause holds (shared/DESIGN.md): faults injected at every await point of the path from a stop
decision to the next setting's first breath (stop -> propose -> push -> commit -> ack -> applied),
and at hypothesis-chosen times; nothing is committed or assisting while the session is paused."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from supervision_harness import BREATH_S, FAULTS, STATUS_PERIOD_S, run_session

from bridge.supervisor import SupervisorState

pytestmark = pytest.mark.slow


def _path_window(tmp: Path) -> tuple[range, tuple[float, float]]:
    """Suspension numbers and loop times from the breath that ends evaluation 1 to the moment the
    device runs evaluation 2's profile (version 2), measured on a run without faults."""
    base = run_session(tmp, n_evaluations=3)
    assert not base.device.violations
    t_first_segment = base.device.times_of("segment", (2, 0))[0]
    t_start = BREATH_S * math.floor(t_first_segment / BREATH_S)  # the breath of the stop decision
    t_end = base.device.times_of("ack", 2)[0] + 2 * STATUS_PERIOD_S  # active at the next boundary
    times = np.asarray(base.injector.times)
    window = range(int(np.searchsorted(times, t_start)), int(np.searchsorted(times, t_end, side="right")))
    return window, (t_start, t_end)


@pytest.fixture(scope="module")
def window(tmp_path_factory: pytest.TempPathFactory) -> tuple[range, tuple[float, float]]:
    return _path_window(tmp_path_factory.mktemp("window"))


@pytest.mark.parametrize("fault", FAULTS)
def test_fault_at_every_await_point_of_the_push_path(fault: str, window, tmp_path: Path) -> None:
    points, _ = window
    # Every suspension of every task in the path: the ask, the log writes' yields, each paced
    # segment, the commit, the ack wait, the wait for the device to run the new version.
    assert len(points) >= 40
    covered = 0
    for k in points:
        out = run_session(tmp_path, at=k, fault=fault, n_evaluations=3, end_after_s=12.0)
        assert out.device.violations == [], f"fault {fault} at suspension {k}"
        assert out.injector.count > k, "the fault never fired"
        assert not out.device.assisting, "assisting after the session's end"
        events = out.session.status.events
        if fault in ("stop", "bus_error"):
            assert out.session.supervisor.state is SupervisorState.STOPPED
        else:
            # The pause ended (operator "r" once healthy) and the session went on measuring.
            assert any("resumed" in e for e in events), (k, events)
            assert out.session.supervisor.counters["resume_refused"] == 0 or fault == "heartbeat_loss"
        covered += 1
    assert covered == len(points)


@settings(max_examples=1000, deadline=None, derandomize=True,
          suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow])
@given(data=st.data())
def test_faults_at_random_times_never_leave_the_device_assisting_while_paused(
        data: st.DataObject, window, tmp_path: Path) -> None:
    _, (t_start, t_end) = window
    fault = data.draw(st.sampled_from(FAULTS), label="fault")
    at_time_s = data.draw(st.floats(t_start - 0.05, t_end + 0.05), label="at_time_s")
    resume_after_s = data.draw(st.floats(0.0, 4.0), label="resume_after_s")
    out = run_session(tmp_path, at_time_s=at_time_s, fault=fault, n_evaluations=3,
                      resume_after_s=resume_after_s, end_after_s=8.0)
    assert out.device.violations == []
    assert not out.device.assisting
