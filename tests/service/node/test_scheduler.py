"""service/node/scheduler.py without a network: the per-robot latest-wins slots of validated scans
(:class:`~service.node.scheduler.LatestSlots`): latest wins, skips counted, round robin over robots,
the capacity for new robots, and a waiting take woken by an offer or a kick."""

from __future__ import annotations

import threading
import time

from service.node.scheduler import LatestSlots


def test_slots_latest_wins_and_counts_skips() -> None:
    s = LatestSlots(capacity=10)
    for i in range(5):
        assert s.offer("r1", i)
    assert len(s) == 1
    assert s.take(0.0) == ("r1", 4)
    assert s.skipped == 4
    assert s.take(0.0) is None


def test_slots_round_robin_keeps_place() -> None:
    s = LatestSlots(capacity=10)
    s.offer("a", 1)
    s.offer("b", 1)
    s.offer("a", 2)  # a floods but keeps its (first) place, b is not pushed back
    s.offer("c", 1)
    assert [s.take(0.0) for _ in range(3)] == [("a", 2), ("b", 1), ("c", 1)]


def test_slots_capacity_refuses_new_robots_only() -> None:
    s = LatestSlots(capacity=2)
    assert s.offer("a", 1) and s.offer("b", 1)
    assert not s.offer("c", 1)
    assert s.offer("a", 2)  # an already pending robot may still update
    assert s.refused == 1
    s.discard("a")
    assert s.take(0.0) == ("b", 1)


def test_slots_take_wakes_on_offer_and_kick() -> None:
    s = LatestSlots(capacity=2)
    threading.Timer(0.05, s.offer, args=("r", 7)).start()
    assert s.take(5.0) == ("r", 7)
    threading.Timer(0.05, s.kick).start()
    t = time.monotonic()
    assert s.take(5.0) is None
    assert time.monotonic() - t < 2.0
