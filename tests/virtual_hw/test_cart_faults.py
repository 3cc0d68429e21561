"""Cart faults as the drivers' BreathStream sees them: counted rejects, reconnects, and no valid
breath around a fault lost."""

from __future__ import annotations

import itertools

import pytest
from vcart_harness import Session, run_session, same_breath

from virtual_hw.cart import CART_FAULTS, BreathFate, CartFault, LinkKind

pytestmark = pytest.mark.timeout(60)


def assert_readable_breaths_all_arrived(session: Session, *, t_tol_s: float = 0.0) -> None:
    readable = session.readable()
    assert len(session.records) == len(readable)
    assert all(
        same_breath(got, e.record, t_tol_s=t_tol_s) for got, e in zip(session.records, readable, strict=True)
    )


def fates(session: Session) -> dict[BreathFate, int]:
    out: dict[BreathFate, int] = {}
    for e in session.cart.history:
        out[e.fate] = out.get(e.fate, 0) + 1
    return out


def test_the_catalog_offers_every_cart_fault() -> None:
    assert set(CART_FAULTS.names) == {f.value for f in CartFault}


@pytest.mark.parametrize(
    ("spec", "fate", "reason", "missing"),
    [
        ("duplicate@60x3", BreathFate.DUPLICATED, "duplicate", 0),
        ("out-of-order@60x2", BreathFate.REORDERED, "out_of_order", 2),
        ("nan@60x3", BreathFate.NAN, "non_finite", 3),
        ("malformed@60x3", BreathFate.MALFORMED, "bad_checksum", 3),
        ("nan@60+10", BreathFate.NAN, "non_finite", None),
    ],
)
async def test_breath_faults_are_counted_by_reason(
    spec: str, fate: BreathFate, reason: str, missing: int | None
) -> None:
    session = await run_session(LinkKind.TCP, faults=[spec], end_s=150.0, seed=21)
    hit = fates(session).get(fate, 0)
    assert hit >= 2
    if "x" in spec:
        assert hit == int(spec.rsplit("x", 1)[1])
    assert session.stream.counters == {reason: hit}
    expected_missing = hit if missing is None else missing
    assert session.stream.validator.missing_seq == expected_missing
    first_hit = min(e.record.t_s for e in session.cart.history if e.fate is fate)
    assert first_hit >= 60.0
    assert_readable_breaths_all_arrived(session)
    assert len(session.records) == len(session.cart.history) - (0 if fate is BreathFate.DUPLICATED else hit)


async def test_garbage_lines_are_rejected_and_no_breath_is_lost() -> None:
    session = await run_session(LinkKind.TCP, faults=["garbage@30x4", "garbage@90x1"], end_s=150.0)
    assert session.cart.stats["garbage_lines"] == 5
    assert session.stream.counters == {"garbage": 5}
    assert len(session.records) == len(session.cart.history)
    assert_readable_breaths_all_arrived(session)


async def test_stall_leaves_a_time_gap_with_correct_later_times_and_no_missing_seq() -> None:
    session = await run_session(LinkKind.TCP, faults=["stall@60+30"], end_s=150.0)
    stalled = [e for e in session.cart.history if e.fate is BreathFate.STALLED]
    assert len(stalled) >= 5 and all(60.0 <= e.record.t_s < 90.0 for e in stalled)
    assert session.stream.counters.total() == 0 and session.stream.validator.missing_seq == 0
    times = [r.t_s for r in session.records]
    gaps = [b - a for a, b in itertools.pairwise(times)]
    assert max(gaps) > 25.0  # the stall shows up as a long interval between breaths
    assert_readable_breaths_all_arrived(session)
    resumed = next(r for r in session.records if r.t_s >= 90.0)
    assert resumed == next(e.record for e in session.cart.history if e.record.t_s >= 90.0)


@pytest.mark.parametrize("kind", [LinkKind.TCP, LinkKind.SERIAL])
async def test_disconnect_makes_the_client_reconnect_and_shows_as_missing_seqs(kind: LinkKind) -> None:
    session = await run_session(kind, faults=["disconnect@60+10"], end_s=150.0, seed=7)
    stream = session.stream
    assert session.cart.stats["disconnects"] == 1
    assert stream.transport.drops == 1 and stream.reconnects == 1
    lost = session.undelivered_seqs()
    assert lost >= 3  # the window plus the client's reconnection backoff
    assert stream.validator.missing_seq == lost
    assert stream.counters.total() == 0  # a graceful close: no line cut in half
    assert_readable_breaths_all_arrived(session)
    assert any(r.t_s < 60.0 for r in session.records) and any(r.t_s > 75.0 for r in session.records)


async def test_udp_disconnect_drops_datagrams_without_a_reconnect() -> None:
    session = await run_session(LinkKind.UDP, faults=["disconnect@60+10"], end_s=150.0, seed=7)
    lost = session.undelivered_seqs()
    assert lost >= 2
    assert all(59.0 <= e.t_sent_s < 70.5 for e in session.cart.history if e.seq is not None and not e.clients)
    assert session.stream.validator.missing_seq == lost and session.stream.reconnects == 0
    assert_readable_breaths_all_arrived(session)


async def test_malformed_csv_rows_are_cut_short_and_garbage_is_not_text() -> None:
    session = await run_session(LinkKind.TCP, fmt="csv", faults=["malformed@40x2", "garbage@80x2"],
                                end_s=120.0)
    assert session.stream.counters == {"field_count": 2, "garbage": 2}
    assert_readable_breaths_all_arrived(session, t_tol_s=1e-6)


async def test_every_fault_at_once_still_delivers_every_readable_breath() -> None:
    specs = ["garbage@20x2", "duplicate@40x2", "out-of-order@60x1", "nan@80x1", "malformed@100x1",
             "stall@120+15", "disconnect@150+8"]
    session = await run_session(LinkKind.TCP, faults=specs, end_s=240.0, seed=13)
    counters = session.stream.counters
    assert counters == {"garbage": 2, "duplicate": 2, "out_of_order": 1, "non_finite": 1, "bad_checksum": 1}
    assert session.stream.reconnects == 1
    assert session.cart.faults.left("duplicate") == 0
    assert_readable_breaths_all_arrived(session)
