"""The session's garbage-collection policy (bridge/collector.py), on the real ``gc`` module."""

from __future__ import annotations

import gc
import weakref

import pytest

from bridge.collector import Collector, GcMode


class _Node:
    """A container with a reference cycle once linked to itself."""

    def __init__(self) -> None:
        self.me: _Node | None = None


def _cycle() -> weakref.ref[_Node]:
    node = _Node()
    node.me = node  # only the cyclic collector can free it
    return weakref.ref(node)


@pytest.fixture(autouse=True)
def _nothing_frozen():
    gc.unfreeze()
    yield
    gc.unfreeze()


def test_freeze_mode_freezes_at_enter_and_unfreezes_at_exit():
    with Collector(GcMode.FREEZE) as c:
        assert gc.get_freeze_count() > 0
        assert c.mode is GcMode.FREEZE
    assert gc.get_freeze_count() == 0


def test_automatic_mode_leaves_the_collector_alone():
    with Collector("automatic") as c:
        assert gc.get_freeze_count() == 0
        assert c.quiet_point() is None and c.full() is None
        ref = _cycle()
        gc.collect()
        assert ref() is None
    assert c.stats.quiet_points == 0 and c.stats.full == 0


def test_quiet_point_collects_new_cycles_and_freezes_the_survivors():
    with Collector() as c:
        frozen = gc.get_freeze_count()
        ref = _cycle()
        kept = [_Node() for _ in range(100)]  # alive: frozen at the quiet point
        assert ref() is not None
        dt = c.quiet_point()
        assert dt is not None and dt >= 0
        assert ref() is None  # the cycle made after the freeze was collected
        assert gc.get_freeze_count() >= frozen + len(kept)
        assert c.stats.quiet_points == 1 and c.stats.quiet_max_ms == pytest.approx(1e3 * dt)
        # Nothing allocated since the quiet point: a full walk would find nothing unfrozen.
        assert len(gc.get_objects(generation=2)) < 50


def test_a_cycle_of_frozen_objects_waits_for_full():
    with Collector() as c:
        node = _Node()
        ref = weakref.ref(node)
        c.quiet_point()  # the node is alive here: frozen
        node.me = node  # now a cycle, and garbage once the name is gone
        del node
        c.quiet_point()  # frozen objects are not walked
        assert ref() is not None
        dt = c.full()
        assert dt is not None and ref() is None
        assert c.stats.full == 1 and gc.get_freeze_count() > 0


def test_refcounting_still_frees_frozen_objects():
    with Collector() as c:
        node = _Node()
        ref = weakref.ref(node)
        c.quiet_point()
        del node
        assert ref() is None


def test_automatic_collections_are_counted_with_their_pauses_and_ours_are_not():
    with Collector() as c:
        c.quiet_point()
        gc.collect(0)  # stands for one CPython starts by itself
        assert c.stats.automatic[0] >= 1
        assert c.stats.automatic_max_ms[0] >= 0
        before = list(c.stats.automatic)
        c.full()
        assert c.stats.automatic == before
    js = c.stats.to_json()
    assert set(js) == {"automatic", "automatic_max_ms", "quiet_points", "quiet_max_ms", "full",
                       "full_max_ms"}
    assert js["quiet_points"] == 1 and js["full"] == 1


def test_overlapping_sessions_unfreeze_only_at_the_outermost_exit():
    outer = Collector()
    with outer:
        with Collector():
            pass
        assert gc.get_freeze_count() > 0  # the outer session is still running
    assert gc.get_freeze_count() == 0
    assert gc.callbacks.count(outer._on_gc) == 0


def test_entering_twice_is_an_error_and_exit_without_enter_is_harmless():
    c = Collector()
    c.__exit__(None, None, None)
    with c, pytest.raises(RuntimeError, match="entered twice"):
        c.__enter__()


def test_bad_mode_names_the_value():
    with pytest.raises(ValueError, match="'never'"):
        Collector("never")
