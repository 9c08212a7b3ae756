"""The partial-map bench's re-fix measure (bench/bench_partial.py)."""

from __future__ import annotations

import math

import numpy as np

from bench.bench_partial import (
    Refix,
    late_list,
    refix_events,
    summarise,
    wrong_episodes,
    wrong_list,
)


def test_refix_counts_all_travel_and_the_travel_where_the_map_holds() -> None:
    # 1 m per scan; the map does not hold for 3 m, holds one scan, stops holding for 10 m,
    # then holds until the re-fix two scans later
    holds = np.array([True] + [False] * 3 + [True] + [False] * 10 + [True] * 4)
    good = np.zeros(holds.size, dtype=bool)
    good[0] = True
    good[17] = True
    travel = np.arange(holds.size, dtype=float)
    events = refix_events(good, np.ones(holds.size, dtype=bool), holds, travel)
    assert events == [Refix(4, 13.0, 3.0), Refix(15, 2.0, 2.0)]


def test_a_never_refixed_event_is_infinite_with_its_travel_where_the_map_held() -> None:
    holds = np.array([True, False, False, True, True, False])
    good = np.array([True, False, False, False, False, False])
    events = refix_events(good, np.ones(6, dtype=bool), holds, np.arange(6.0))
    assert len(events) == 1 and events[0].scan == 3
    assert math.isinf(events[0].travel) and events[0].holding == 1.0


def test_unscored_scans_are_skipped() -> None:
    holds = np.array([True, False, False, True, True])
    scored = np.array([True, True, True, False, True])
    good = np.array([True, False, False, True, True])
    events = refix_events(good, scored, holds, np.arange(5.0))
    assert events == [Refix(4, 0.0, 0.0)]


def test_the_page_lists_each_refix_beyond_5_m_where_the_map_holds() -> None:
    # the map holds at scan 1, not for 3 m, then from scan 5 on; the first correct tracking
    # pose 6 scans later: 6 m, all of it where the map holds
    n = 14
    holds = np.array([True] * 2 + [False] * 3 + [True] * (n - 5))
    scored = np.ones(n, dtype=bool)
    truth = np.zeros((n, 3))
    poses = np.zeros((n, 3))
    poses[2:11, 0] = 2.0  # off while lost
    status = ["tracking"] * 2 + ["lost"] * 9 + ["tracking"] * 3
    row = summarise(poses, truth, scored, holds, np.arange(float(n)), status, status)
    assert row["late"] == [(5, 6.0, 6.0)] and row["refix_late_holding"] == 1
    text = late_list([{**row, "case": "intel partial"}, {"case": "building 0", "late": []}])
    assert text == "- intel partial: scan 5: 6.0 / 6.0 m\n"
    assert late_list([{"case": "building 0", "late": []}]) == "- none\n"


def test_confident_wrong_scans_are_listed_by_episode() -> None:
    # scored scans 0-9; scan 4 unscored: scans 3 and 5 are one episode; a lost scan ends one
    err = np.array([0.1, 0.7, 0.9, 20.0, 0.0, 19.5, 0.2, 0.6, 0.6, 3.0])
    tracking = np.array([True] * 8 + [False, True])
    scored = np.ones(10, dtype=bool)
    scored[4] = False
    assert wrong_episodes(err, tracking, scored) == [
        (1, 4, 0.7, 20.0),
        (7, 1, 0.6, 0.6),
        (9, 1, 3.0, 3.0),
    ]
    rows = [{"case": "intel partial, seed 5", "wrong_runs": [(1, 4, 0.7, 20.0), (9, 1, 3.0, 3.0)]}]
    assert wrong_list(rows) == (
        "- intel partial, seed 5: scan 1: 4 scans, 0.7-20.0 m; scan 9: 1 scan, 3.0-3.0 m\n"
    )
    assert wrong_list([{"case": "building 0", "wrong_runs": []}]) == "- none\n"
