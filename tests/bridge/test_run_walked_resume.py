"""What a resumed session counts as walked before it (bridge.run._walked_before_resume): the
run's own account at its end; after a crash, what it was given plus the span of its breaths."""

from __future__ import annotations

from pathlib import Path

import msgspec
from test_session_end import SIM, run_replay

from bridge.log.reader import read_log
from bridge.log.resume import rebuild_optimizer
from bridge.run import _walked_before_resume, _walked_lower_bound


def test_a_stopped_run_counts_what_it_logged_and_a_crashed_one_its_breaths(tmp_path: Path) -> None:
    result, _ = run_replay(tmp_path, 60)
    log = result.log_path
    events = read_log(log, topics=["/events"]).records("/events")
    breaths = read_log(log, topics=["/breaths"]).records("/breaths")
    opt, _ = rebuild_optimizer(log)
    warmup_s = SIM.warmup_s
    walked_s = result.summary["walking"]["session_s"]
    assert walked_s > 0
    # It ended (the cart's end): its own account, exactly.
    assert _walked_before_resume(log, events, opt.evaluations, warmup_s) == walked_s

    # The same log cut off by a crash (no session_end): what it was given (0, a first run) plus
    # the span of its breaths, which is at least what its evaluations show.
    crashed = [e for e in events if e.kind != "session_end"]
    span = max(b.t_s for b in breaths) - min(b.t_s for b in breaths)
    floor = _walked_lower_bound(opt.evaluations, warmup_s)
    assert _walked_before_resume(log, crashed, opt.evaluations, warmup_s) == max(span, floor)
    assert abs(span - walked_s) <= 3 * 3.0 + 1e-9  # the breaths before the session's start, at most

    # A resumed run carries what it was given.
    resumed = [msgspec.structs.replace(e, details={**(e.details or {}), "walked_before_s": 100.0})
               if e.kind == "session_start" else e for e in crashed]
    assert _walked_before_resume(log, resumed, opt.evaluations, warmup_s) == max(100.0 + span, floor)

    # A log written before session_start carried it: the evaluations' lower bound.
    old = [msgspec.structs.replace(e, details={}) if e.kind == "session_start" else e for e in crashed]
    assert _walked_before_resume(log, old, opt.evaluations, warmup_s) == \
        _walked_lower_bound(opt.evaluations, warmup_s)
