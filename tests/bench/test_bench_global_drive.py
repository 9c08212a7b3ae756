"""The pure helpers of ``bench/bench_global.py --drive``: travel accounting, start choice, the
trial's end and the found / within-limit / confident-wrong classification."""

from __future__ import annotations

import dataclasses
import importlib
import math
from types import SimpleNamespace

import numpy as np
import pytest

from service.core.types import MapData


@pytest.fixture(scope="module")
def bg():
    return importlib.import_module("bench.bench_global")


def test_cumulative_travel_counts_translation_only(bg) -> None:
    xy = np.array([[0.0, 0.0], [3.0, 4.0], [3.0, 4.0], [3.0, 5.0], [np.nan, np.nan]])
    np.testing.assert_allclose(bg.cumulative_travel(xy), [0.0, 5.0, 5.0, 6.0, 6.0])
    assert bg.cumulative_travel(np.zeros((0, 2))).size == 0


def test_trial_end_feeds_the_first_scan_beyond_the_need(bg) -> None:
    travel = np.arange(10.0)  # 1 m per scan
    # from scan 2, travel 3 m is reached at scan 5 and exceeded at scan 6: scans 2..6 are fed
    assert bg.trial_end(travel, 2, 3.0) == 7
    assert bg.trial_end(travel, 2, 2.5) == 7 - 1
    # not enough tour left: up to the last scan
    assert bg.trial_end(travel, 8, 5.0) == 10


def test_fed_scans_take_one_scan_per_block_preferring_a_referenced_one(bg) -> None:
    scored = np.zeros(20, dtype=bool)
    scored[[5, 6, 13]] = True
    # blocks of 4 from scan 2: [2-5] -> 5 (referenced), [6-9] -> 6, [10-13] -> 13,
    # [14-17] -> 14 (none referenced), [18] -> 18, and the last scan 18 is already fed
    assert bg.fed_scans(2, 19, 4, scored) == [5, 6, 13, 14, 18]
    # stride 1 feeds every scan; the end scan is always fed
    assert bg.fed_scans(3, 7, 1, scored) == [3, 4, 5, 6]
    assert bg.fed_scans(0, 10, 4, np.ones(20, dtype=bool)) == [0, 4, 8, 9]


def test_choose_starts_leaves_the_need_and_respects_eligibility(bg) -> None:
    travel = np.arange(30) * 0.5  # 14.5 m tour
    rng = np.random.default_rng(0)
    s = bg.choose_starts(travel, 10.0, 5, rng)
    assert len(s) == 5 and len(set(s.tolist())) == 5 and np.all(np.diff(s) > 0)
    assert np.all(travel[-1] - travel[s] >= 10.0)
    # more asked than qualify: every qualifying scan once
    assert bg.choose_starts(travel, 10.0, 100, rng).tolist() == list(range(10))
    eligible = np.zeros(30, dtype=bool)
    eligible[[3, 7, 20]] = True  # 20 leaves only 5 m
    assert bg.choose_starts(travel, 10.0, 10, rng, eligible).tolist() == [3, 7]
    assert bg.choose_starts(travel, 20.0, 3, rng).size == 0  # tour too short: skipped


def test_choose_starts_is_seeded(bg) -> None:
    travel = np.arange(500) * 0.1
    a = bg.choose_starts(travel, 20.0, 10, np.random.default_rng([1, 0, 0, 1]))
    b = bg.choose_starts(travel, 20.0, 10, np.random.default_rng([1, 0, 0, 1]))
    assert a.tolist() == b.tolist()


def test_spread_sums_to_the_total(bg) -> None:
    assert bg.spread(200, 8) == [25] * 8
    assert bg.spread(10, 3) == [4, 3, 3]
    assert sum(bg.spread(7, 8)) == 7


def test_classify_found_late_after_a_wrong_fix(bg) -> None:
    status = ["initializing", "tracking", "lost", "tracking", "tracking", "tracking", "tracking"]
    close = [False, False, False, True, True, False, None]  # scan 6 not scored
    after = [False, False, False, True, True, False, None]
    travel = [0.0, 1.0, 2.0, 6.0, 7.0, 8.0, 9.0]
    out = bg.classify(status, close, after, travel, limit=5.0)
    assert out.found and not out.within_limit
    assert out.fix == 3 and out.fix_travel == 6.0
    assert out.first_fix_wrong and out.wrong_before_fix == 1
    # after the fix: scans 4 and 5 scored and tracking, 5 fails; 6 is not scored
    assert (out.tracking_after_fix, out.wrong_after_fix) == (2, 1)
    assert bg.classify(status, close, after, travel, limit=6.0).within_limit


def test_classify_unscored_tracking_is_not_a_fix_nor_wrong(bg) -> None:
    status = ["tracking", "tracking", "tracking"]
    close = [None, None, True]
    out = bg.classify(status, close, [None, None, True], [0.0, 0.5, 1.0], limit=15.0)
    assert out.found and out.within_limit and out.fix == 2 and not out.first_fix_wrong
    none = bg.classify(["initializing"] * 3, [False] * 3, [False] * 3, [0, 1, 2], 15.0)
    assert not none.found and not none.first_fix_wrong and math.isnan(none.fix_travel)


def test_fix_ok_needs_position_and_heading(bg) -> None:
    t = np.array([1.0, 2.0, 3.1])
    assert bg.fix_ok(np.array([1.3, 2.3, 3.1 + np.deg2rad(9.0)]), t)
    assert not bg.fix_ok(np.array([1.4, 2.4, 3.1]), t)  # 0.57 m
    assert not bg.fix_ok(np.array([1.0, 2.0, 3.1 + np.deg2rad(11.0)]), t)
    # heading wraps around pi
    assert bg.fix_ok(np.array([1.0, 2.0, -np.pi + 0.01]), np.array([1.0, 2.0, np.pi - 0.01]))


def test_percentile_counts_not_found_as_infinite(bg) -> None:
    assert bg.pct_inf([1.0, 2.0, 3.0], 50) == 2.0
    assert math.isinf(bg.pct_inf([1.0, math.nan], 50))
    assert bg.pct_inf([1.0, 2.0, 3.0, math.nan], 50) == 2.5


def test_hypotheses_read_defensively(bg) -> None:
    assert bg.hypotheses_of(SimpleNamespace(hypotheses=[1, 2, 3], extras={})) == 3.0
    assert bg.hypotheses_of(SimpleNamespace(hypotheses=None, extras={"hypotheses": 4.0})) == 4.0
    assert bg.hypotheses_of(SimpleNamespace(extras={})) is None
    assert bg.hypotheses_of(SimpleNamespace(hypotheses=2)) == 2.0


def _room_scan(half: float, n: int = 360) -> tuple[np.ndarray, np.ndarray]:
    """Ranges from the centre of an empty square room of half-width ``half`` (exact)."""
    a = np.linspace(-np.pi, np.pi, n, endpoint=False)
    return half / np.maximum(np.abs(np.cos(a)), np.abs(np.sin(a))), a


def test_plan_share_counts_the_returns_on_mapped_walls(bg) -> None:
    ps = importlib.import_module("bench.plan_share")
    room = MapData.from_lists("room", "schematic", [[[-2, -2], [2, -2], [2, 2], [-2, 2], [-2, -2]]])
    share = ps.PlanShare(room)
    r, a = _room_scan(2.0)
    assert share.scan_share(np.zeros(3), r, a) == 1.0
    # the same scan placed 1 m off: only the returns that still land near a wall count
    off = share.scan_share(np.array([1.0, 0.0, 0.0]), r, a)
    assert 0.0 < off < 0.6
    # furniture: half the beams stop at 0.8 m, on nothing the plan draws
    r2 = r.copy()
    r2[::2] = 0.8
    assert share.scan_share(np.zeros(3), r2, a) == 0.5
    # no reference, or no returns in range: not scored
    assert np.isnan(share.scan_share(np.array([np.nan, 0.0, 0.0]), r, a))
    assert np.isnan(share.scan_share(np.zeros(3), np.full_like(r, np.nan), a))


def test_share_table_splits_found_trials_by_plan_share(bg) -> None:
    m = bg.DriveMap("real", "fr079", "schematic")
    names = [f.name for f in dataclasses.fields(bg.DriveTrial) if f.name != "search_ms"]
    base = dict.fromkeys(names, 0)
    base.update(group="real", world="fr079", map="schematic", setup="", room="")

    def trial(share: float, within: bool, **kw: object) -> object:
        return bg.DriveTrial(**{**base, "plan_share": share, "within_limit": within, **kw})

    ts = [trial(0.3, False, start=1713, holds_from_m=16.04, found=True, fix_travel_m=19.0)]
    ts += [trial(0.4, True), trial(0.7, True), trial(0.9, True)]
    ts.append(trial(0.2, False, start=1715, holds_from_m=math.inf, found=False))
    ts.append(trial(float("nan"), True))  # no reference: in neither column
    row = bg.share_table(ts, [m]).splitlines()[2]
    assert row == "| real fr079 schematic | 1/3 | 2/2 | 1713: 16.0 / 19.0; 1715: never / never |"


def test_the_map_holds_from_the_first_of_three_holding_scans_in_a_row() -> None:
    gd = importlib.import_module("bench.global_drive")
    travel = [0.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0]
    # a doorway at 0 m and two scans at 2-3 m hold, not three in a row; from 5 m it holds
    shares = [0.6, 0.1, 0.5, 0.7, 0.2, 0.55, 0.8, 0.9]
    assert gd.holds_from(travel, shares) == 5.0
    assert gd.holds_from(travel[:7], shares[:7]) == math.inf  # two in a row only
    assert gd.holds_from([0.0, 0.4, 0.9], [0.5, 0.5, 0.5]) == 0.0
    assert math.isnan(gd.holds_from([], []))


def test_clutter_names_the_same_buildings_and_starts_with_more_furniture(bg) -> None:
    """``--clutter``: the same seeds (and start choice) with a denser furnishing; the floor
    plan is unchanged, the scans see more furniture (a lower plan share)."""
    plain = bg.drive_maps(["worlds"], [3], [], ["schematic"])
    dense = bg.drive_maps(["worlds"], [3], [], ["schematic"], clutter=0.25)
    assert [m.world for m in plain] == ["3"] and [m.world for m in dense] == ["3@0.25"]
    m, d = plain[0], dense[0]
    assert (d.seed, d.clutter, m.clutter) == (3, 0.25, None)
    assert d.code() == m.code()
    assert d.label() == "building 3 (clutter 0.25) setup 2 (schematic)"
    bw = importlib.import_module("bench.bench_worlds")
    b0, b1 = bw.generated_building(1, 0), bw.generated_building(1, 0, 0.25)
    assert b1.clutter > b0.clutter + 0.05
    p0, p1 = b0.schematic().map_data.polylines, b1.schematic().map_data.polylines
    assert len(p0) == len(p1) and all(np.array_equal(a, b) for a, b in zip(p0, p1, strict=True))
