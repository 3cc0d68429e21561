"""Worst-case response times of the profile segments on the bus (drivers/PROTOCOL.md, "Bus budget").

Response-time analysis of CAN (Davis, Burns, Bril, Lukkien 2007, eq. 8–13, no error model):
ProfileSegment has the lowest priority on the bus, so a queued segment waits for every
higher-priority frame released meanwhile, and for the segments queued before it. Segments are
queued ``pace_us`` apart on the deadline schedule of ``CanEndpoint.push_profile``; a late one
lets the next follow after half the pace, which is release jitter ``J = pace/2``. The level-i
busy period ``t`` holds ``Q = ceil((t + J) / T)`` segments; instance ``q`` (0-based) is on the
wire ``w_q`` after the busy period starts, with

    w_q = q·C + Σ_hp ceil(w_q / T_j)·C_j,         R_q = J + w_q − q·T + C,

and the worst-case response time of a segment is ``max_q R_q``. An AssistanceOff queued behind
segments in the host's transmit FIFO leaves after the last of them (within that bound of its
queueing) and then wins the next arbitration: ``R + C_max + C_off`` at most (C_max = 135 µs,
the longest frame, which may be on the wire).

``python -m drivers.exosuit.busload`` prints the table PROTOCOL.md quotes (:func:`budget_table`).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

__all__ = [
    "ASSISTANCE_OFF_US",
    "HIGHER_PRIORITY_US",
    "MAX_FRAME_US",
    "SEGMENT_US",
    "SegmentResponse",
    "budget_table",
    "segment_response",
]

#: Worst-case bit times (µs at 1 Mbit/s) and periods (µs) of the traffic above the segments:
#: ForceFeedback 2 × 1 kHz, four drive frames at 1 kHz, DeviceStatus 2 × 50 Hz, the heartbeat.
HIGHER_PRIORITY_US: tuple[tuple[int, int], ...] = (
    (2 * 115, 1000), (4 * 135, 1000), (2 * 115, 20000), (85, 20000))
#: A ProfileSegment (8 data bytes), worst case with stuff bits, µs at 1 Mbit/s.
SEGMENT_US = 135
#: AssistanceOff (1 data byte), worst case, µs.
ASSISTANCE_OFF_US = 65
#: The longest classical CAN frame (8 data bytes), µs: what a frame already on the wire can
#: delay the next arbitration by.
MAX_FRAME_US = 135


@dataclass(frozen=True)
class SegmentResponse:
    """The analysis at one pace.

    Attributes:
        pace_us: Segment period T (µs).
        jitter_us: Release jitter J (µs).
        busy_period_us: Level-i busy period t (µs).
        instances: Segments in the busy period (Q).
        response_us: Worst-case response time of a segment, from its nominal release (µs).
        assistance_off_us: Worst case for an AssistanceOff queued behind segments (µs).
        utilisation: Worst-case bus load with the push running (0–1).
    """

    pace_us: int
    jitter_us: int
    busy_period_us: int
    instances: int
    response_us: int
    assistance_off_us: int
    utilisation: float


def segment_response(pace_us: int, jitter_us: int | None = None, *,
                     higher: Sequence[tuple[int, int]] = HIGHER_PRIORITY_US,
                     c_us: int = SEGMENT_US) -> SegmentResponse:
    """Worst-case response of segments queued every ``pace_us`` (see the module doc).

    Args:
        pace_us: Segment period T in µs (> 0).
        jitter_us: Release jitter J in µs (default T/2, the endpoint's catch-up rule).
        higher: (C, T) of every higher-priority stream, µs.
        c_us: The segment's worst-case frame time, µs.

    Raises:
        ValueError: The load reaches 100 % (the busy period would not end).
    """
    J = pace_us // 2 if jitter_us is None else jitter_us
    util = sum(c / t for c, t in higher) + c_us / pace_us
    if pace_us <= 0 or util >= 1.0:
        raise ValueError(f"pace_us={pace_us!r}: bus load {util:.1%}; expected a pace that keeps it "
                         "under 100 %")
    t = c_us
    while True:
        nt = sum(c * math.ceil(t / tt) for c, tt in higher) + c_us * math.ceil((t + J) / pace_us)
        if nt == t:
            break
        t = nt
    q_max = math.ceil((t + J) / pace_us)
    worst = 0
    for q in range(q_max):
        w = q * c_us + sum(c for c, _ in higher)  # every higher stream released at the start
        while True:
            nw = q * c_us + sum(c * math.ceil(w / tt) for c, tt in higher)
            if nw == w:
                break
            w = nw
        worst = max(worst, J + w - q * pace_us + c_us)
    return SegmentResponse(pace_us, J, t, q_max, worst, worst + MAX_FRAME_US + ASSISTANCE_OFF_US, util)


def budget_table(paces: Sequence[tuple[int, int]] = ((2000, 0), (2000, 1000), (1500, 750),
                                                     (1000, 500))) -> str:
    """The Markdown table of drivers/PROTOCOL.md: (pace, jitter) in µs per row."""
    lines = ["| pace T | jitter J | busy period | segments in it | segment R | AssistanceOff behind "
             "them | bus load |", "|---|---|---|---|---|---|---|"]
    for p, j in paces:
        r = segment_response(p, j)
        lines.append(f"| {r.pace_us / 1000:g} ms | {r.jitter_us / 1000:g} ms "
                     f"| {r.busy_period_us / 1000:.3f} ms | {r.instances} | {r.response_us / 1000:.2f} ms "
                     f"| {r.assistance_off_us / 1000:.2f} ms | {r.utilisation:.1%} |")
    return "\n".join(lines) + "\n"


if __name__ == "__main__":  # python -m drivers.exosuit.busload
    import sys

    sys.stdout.write(budget_table())
