"""The virtual cart: breaths over pty, TCP and UDP parse back identically; assistance changes them."""

from __future__ import annotations

import asyncio
import itertools
import math
import os
import time

import numpy as np
import pytest
from vcart_harness import QUIET, SPACE, run_session, same_breath

from drivers.cart import (
    BreathStream,
    CartFormat,
    HbrLineParser,
    SerialOptions,
    TcpOptions,
    UdpOptions,
    UdpTransport,
)
from hilbo_core.errors import MeasurementError
from virtual_hw.cart import (
    VIRTUAL_CSV_MAPPING,
    BreathFate,
    CartLink,
    LinkKind,
    VirtualCart,
)
from virtual_hw.clock import ScaledClock, VirtualClock
from virtual_hw.errors import ClockError, FaultSpecError, VirtualConfigError
from virtual_hw.wearer import SimulatedWearer, relaxed_rate_w

pytestmark = pytest.mark.timeout(60)

EMIT_S = 0.5


@pytest.mark.parametrize("kind", list(LinkKind))
async def test_breaths_parse_back_identically_at_increasing_times(kind: LinkKind) -> None:
    session = await run_session(kind, end_s=300.0, seed=11)
    expected = SimulatedWearer(SPACE, 11).breaths_until(300.0)  # the same subject, untouched
    assert len(expected) > 80
    assert session.records == expected
    assert session.stream.counters.total() == 0 and session.stream.validator.missing_seq == 0
    times = [r.t_s for r in session.records]
    assert all(b > a for a, b in itertools.pairwise(times))
    # Each line leaves at the first tick after its breath ended...
    for e in session.cart.history:
        assert e.fate is BreathFate.SENT and e.clients == 1
        assert 0.0 <= e.t_sent_s - e.record.t_s <= EMIT_S
    if kind is not LinkKind.SERIAL:
        # ... and an in-process socket reader has it before simulated time moves on. (The pty is
        # read by pyserial's thread, which the settle turns do not cover.)
        assert session.received_s == [e.t_sent_s for e in session.cart.history]


@pytest.mark.parametrize("kind", list(LinkKind))
async def test_csv_rows_parse_back_with_the_vendor_mapping(kind: LinkKind) -> None:
    session = await run_session(kind, fmt="csv", end_s=120.0, seed=4)
    expected = SimulatedWearer(SPACE, 4).breaths_until(120.0)
    assert len(session.records) == len(expected) > 30
    # h:mm:ss.ffffff clock times: to the microsecond; the gases exactly.
    assert all(same_breath(a, b, t_tol_s=1e-6) for a, b in zip(session.records, expected, strict=True))
    assert session.stream.parser.mapping == VIRTUAL_CSV_MAPPING  # type: ignore[attr-defined]


async def test_an_applied_profile_changes_the_metabolic_level_after_the_first_order_response() -> None:
    wearer = SimulatedWearer(SPACE, 2, config=QUIET)
    params, best_w = wearer.true_optimum
    profiles = wearer.profiles_for(params)
    baseline, tau = wearer.baseline_cost_w, wearer.tau_s
    t_apply = 300.0
    targets: list[float] = []

    async def exosuit(cart: VirtualCart, clock: VirtualClock) -> None:
        with clock.participant("exosuit") as me:
            await me.sleep_until(t_apply)
            targets.append(cart.on_profile_applied(profiles))

    session = await run_session(LinkKind.TCP, wearer=wearer, end_s=720.0, during=exosuit)
    assert targets == [pytest.approx(best_w)]

    def window(lo: float, hi: float) -> list:
        return [r for r in session.records if lo <= r.t_s < hi]

    before = window(t_apply - 120.0, t_apply)
    after = window(t_apply + 240.0, t_apply + 360.0)
    assert len(before) > 30 and len(after) > 30
    assert np.mean([r.watts for r in before]) == pytest.approx(baseline, rel=1e-9)
    expected_after = np.mean([relaxed_rate_w(r.t_s, t_apply, baseline, best_w, tau) for r in after])
    assert np.mean([r.watts for r in after]) == pytest.approx(expected_after, rel=1e-9)
    assert baseline - expected_after > 0.9 * (baseline - best_w) > 0.05 * baseline
    # First-order, not a step: the first breath after the switch is still near the old level.
    first = window(t_apply, t_apply + 10.0)[0]
    assert first.watts > baseline - 0.3 * (baseline - best_w)


async def test_noisy_wearer_shows_the_saving_in_two_minute_means() -> None:
    wearer = SimulatedWearer(SPACE, 9)
    params, best_w = wearer.true_optimum
    profiles = wearer.profiles_for(params)

    async def exosuit(cart: VirtualCart, clock: VirtualClock) -> None:
        with clock.participant("exosuit") as me:
            await me.sleep_until(300.0)
            cart.on_profile_applied(profiles)

    session = await run_session(LinkKind.UDP, wearer=wearer, end_s=720.0, during=exosuit)
    before = [r.watts for r in session.records if 180.0 <= r.t_s < 300.0]
    after = [r.watts for r in session.records if 540.0 <= r.t_s < 660.0]
    se = math.sqrt(np.var(before) / len(before) + np.var(after) / len(after))
    assert np.mean(before) - np.mean(after) > 3 * se
    assert np.mean(before) - np.mean(after) > 0.5 * (wearer.baseline_cost_w - best_w)


async def test_a_late_or_early_switch_time_never_rewrites_or_leaks_breaths() -> None:
    wearer = SimulatedWearer(SPACE, 3, config=QUIET)
    clock = VirtualClock()
    cart = VirtualCart(wearer, clock, link=CartLink(LinkKind.UDP, port=9))
    profiles = wearer.profiles_for(wearer.true_optimum[0])
    wearer.breaths_until(100.0)  # breaths already reported up to ~100 s
    last = wearer.t_s
    cart.on_profile_applied(profiles, t_sim=50.0)  # late status: moved up, no MeasurementError
    assert wearer.metabolic_rate_w(last) == pytest.approx(wearer.baseline_cost_w)
    cart.on_profile_applied((), t_sim=200.0)  # a future switch: breaths up to it are pending...
    assert wearer.t_s > 190.0
    with pytest.raises(MeasurementError):
        wearer.apply_profiles((), 150.0)  # (the wearer itself refuses going back)
    with pytest.raises(ClockError, match="finite"):
        cart.on_profile_applied((), t_sim=math.nan)


async def test_pending_breaths_are_not_written_before_their_time() -> None:
    wearer = SimulatedWearer(SPACE, 6)

    async def early_status(cart: VirtualCart, clock: VirtualClock) -> None:
        with clock.participant("exosuit") as me:
            await me.sleep_until(10.0)
            cart.on_profile_applied((), t_sim=100.0)  # generates breaths up to 100 s now

    session = await run_session(LinkKind.TCP, wearer=wearer, end_s=120.0, during=early_status)
    assert all(e.t_sent_s >= e.record.t_s for e in session.cart.history)
    assert len(session.records) == len(session.cart.history) > 30


async def test_client_config_matches_the_link() -> None:
    clock = VirtualClock()
    wearer = SimulatedWearer(SPACE, 1)
    async with VirtualCart(wearer, clock, link=CartLink(LinkKind.TCP)) as cart:
        cfg = cart.client_config(connect_timeout_s=2.0)
        assert isinstance(cfg.options, TcpOptions)
        assert cfg.options.port == cart.port > 0 and cart.address == f"tcp 127.0.0.1 {cart.port}"
        assert cfg.format is CartFormat.HILBO_LINE and cfg.csv is None
        with pytest.raises(VirtualConfigError, match="serial path"):
            _ = cart.serial_path
    async with VirtualCart(SimulatedWearer(SPACE, 1), VirtualClock(), link=CartLink(LinkKind.SERIAL),
                           fmt="csv") as cart:
        cfg = cart.client_config()
        assert isinstance(cfg.options, SerialOptions) and cfg.options.port == cart.serial_path
        assert cart.address == f"serial {cart.serial_path}"
        assert cfg.csv == VIRTUAL_CSV_MAPPING
        path = cart.serial_path
    assert not os.path.lexists(path)  # the symlink and its directory are gone


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"fmt": "xml"}, "fmt"),
        ({"csv_mapping": VIRTUAL_CSV_MAPPING}, "csv_mapping"),
        ({"emit_period_s": 0.0}, "emit_period_s"),
        ({"end_s": math.inf}, "end_s"),
        ({"history_size": 0}, "history_size"),
        ({"link": "tcp"}, "link"),
    ],
)
def test_bad_options_are_refused_by_name(kwargs: dict, match: str) -> None:
    with pytest.raises(VirtualConfigError, match=match):
        VirtualCart(SimulatedWearer(SPACE, 1), VirtualClock(), **kwargs)


def test_bad_links_and_faults_are_refused_by_name() -> None:
    with pytest.raises(VirtualConfigError, match="UDP needs"):
        CartLink(LinkKind.UDP)
    with pytest.raises(VirtualConfigError, match="link kind"):
        CartLink("can")  # type: ignore[arg-type]
    with pytest.raises(VirtualConfigError, match="max_clients"):
        CartLink(max_clients=0)
    with pytest.raises(FaultSpecError, match="lasts a while"):
        VirtualCart(SimulatedWearer(SPACE, 1), VirtualClock(), faults=["disconnect@10"])


async def test_tcp_serves_several_clients_and_refuses_beyond_the_limit() -> None:
    clock = VirtualClock()
    cart = VirtualCart(SimulatedWearer(SPACE, 8), clock, link=CartLink(LinkKind.TCP, max_clients=2),
                       end_s=30.0, wait_for_client=True)
    async with cart:
        conns = [await asyncio.open_connection("127.0.0.1", cart.port) for _ in range(3)]
        readers = [c[0] for c in conns]
        third = await asyncio.wait_for(readers[2].read(), timeout=5.0)  # closed at once
        await asyncio.wait_for(cart.wait(), timeout=10.0)
        data = [await asyncio.wait_for(r.readuntil(b"\r\n"), timeout=5.0) for r in readers[:2]]
        for _, w in conns:
            w.close()
    assert third == b""
    assert data[0] == data[1] and data[0].startswith(b"$HBR,0,")
    assert cart.stats["clients_accepted"] == 2 and cart.stats["clients_refused"] == 1
    assert all(e.clients == 2 for e in cart.history)


async def test_a_cart_joining_a_shared_clock_late_reports_only_breaths_from_then_on() -> None:
    udp = UdpTransport(UdpOptions(port=0))
    async with BreathStream(udp, HbrLineParser()) as stream:
        # The session is ~100 s old. 10x, not faster: the cart serves 30 s of it (3 s of wall),
        # so a busy machine that descheduled this test for a second still sees breaths.
        clock = ScaledClock(10.0, epoch_wall=time.time() - 10.0)
        start = clock.now()
        cart = VirtualCart(SimulatedWearer(SPACE, 2), clock, end_s=start + 30.0,
                           link=CartLink(LinkKind.UDP, port=udp.local_address[1]))
        async with cart:
            await asyncio.wait_for(cart.wait(), timeout=60.0)
        sent = [e.record for e in cart.history]
        got = [await asyncio.wait_for(anext(stream), timeout=20.0) for _ in sent]
    assert cart.stats["breaths_before_start"] > 25  # ~100 s of breaths nobody measured
    assert len(sent) >= 3 and got == sent
    assert sent[0].t_s >= start and [e.seq for e in cart.history] == list(range(len(sent)))
