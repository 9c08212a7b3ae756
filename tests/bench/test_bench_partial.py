"""The partial-map bench's re-fix measure (bench/bench_partial.py)."""

from __future__ import annotations

import math

import numpy as np

from bench.bench_partial import refix_events


def test_refix_counts_all_travel_and_the_travel_where_the_map_holds() -> None:
    # 1 m per scan; the map does not hold for 3 m, holds one scan, stops holding for 10 m,
    # then holds until the re-fix two scans later
    holds = np.array([True] + [False] * 3 + [True] + [False] * 10 + [True] * 4)
    good = np.zeros(holds.size, dtype=bool)
    good[0] = True
    good[17] = True
    travel = np.arange(holds.size, dtype=float)
    events = refix_events(good, np.ones(holds.size, dtype=bool), holds, travel)
    assert events == [(13.0, 3.0), (2.0, 2.0)]


def test_a_never_refixed_event_is_infinite_with_its_travel_where_the_map_held() -> None:
    holds = np.array([True, False, False, True, True, False])
    good = np.array([True, False, False, False, False, False])
    events = refix_events(good, np.ones(6, dtype=bool), holds, np.arange(6.0))
    assert len(events) == 1 and math.isinf(events[0][0]) and events[0][1] == 1.0


def test_unscored_scans_are_skipped() -> None:
    holds = np.array([True, False, False, True, True])
    scored = np.array([True, True, True, False, True])
    good = np.array([True, False, False, True, True])
    events = refix_events(good, scored, holds, np.arange(5.0))
    assert events == [(0.0, 0.0)]
