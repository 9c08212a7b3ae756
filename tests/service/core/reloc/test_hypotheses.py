"""Pose hypotheses of the budgeted multi-hypothesis search (service/core/reloc/hypotheses.py): a
finished search's hypotheses moved by the odometry since its scan and merged, the kept ones
re-scored on every scan (the odometry-moved pose kept where the beams explain it better), and
the re-scoring's polish held to the odometry pose along a corridor. The search as bounded
steps is in test_global_search.py, the budgeted search over a drive in test_drive_search.py,
the winner's probation in test_probation.py."""

from __future__ import annotations

import numpy as np

from service.core.reloc import global_search as gs
from service.core.reloc import hypotheses as hy
from service.core.reloc.global_config import GlobalConfig
from service.core.reloc.global_localization import load_or_build_index
from service.core.reloc.view_index import build_index
from service.core.shapes.configuration import scan_configuration
from service.core.tracking.localizer import ShapeConfig
from service.core.types import MapData
from sim_publisher.scenario import make_setup


def test_merge_moves_a_finished_search_by_the_odometry_since_its_scan() -> None:
    h = gs.Hypothesis(pose=np.array([1.0, 1.0, 0.0]), cost=0.1)
    move = np.array([1.0, 0.0, np.pi / 2])  # 1 m forward, then a quarter turn left
    tracks = hy.merge([], [h], move, keep=4)
    assert len(tracks) == 1 and tracks[0].age == 0
    np.testing.assert_allclose(tracks[0].pose, [2.0, 1.0, np.pi / 2], atol=1e-12)
    # a hypothesis already held is not added twice, and counts as found again
    assert tracks[0].found == 1
    near = [gs.Hypothesis(pose=np.array([2.05, 1.0, 1.6]), cost=0.2)] * 2
    again = hy.merge(tracks, near, None, 4)
    assert len(again) == 1 and again[0].found == 2  # once per search, however often it is hit


def test_rescore_fits_each_track_to_the_scan_and_ranks_the_true_pose_first() -> None:
    su = make_setup(1, max_scans=2000)
    md = su.map_data
    cfg = ShapeConfig.for_kind("metric")
    g = GlobalConfig.for_kind("metric")
    idx = load_or_build_index(md, cfg, g)
    truth = su.truth[1200]
    r, a = su.scan(1200)
    P = scan_configuration(r, a, cfg.extraction())
    near = truth + np.array([0.06, -0.04, 0.02])  # a dead-reckoned pose, a few cm off
    wrong = truth + np.array([2.0, 1.0, 0.5])
    tracks = [
        hy.Track(near.copy(), [], gs.Hypothesis(pose=near.copy(), cost=0.5)),
        hy.Track(wrong.copy(), [], gs.Hypothesis(pose=wrong.copy(), cost=0.4)),
    ]
    spent = hy.rescore(idx, tracks, r, a, P, cfg, g, limit=100.0, odometry=True)
    assert spent > 0
    assert all(t.age == 1 and len(t.costs) == 1 for t in tracks)
    assert tracks[0].costs[0] < tracks[1].costs[0] - 0.3
    assert np.hypot(*(tracks[0].pose[:2] - truth[:2])) < 0.03
    # a limit that affords one track re-scores the best one and records a miss for the other
    t2 = [
        hy.Track(near.copy(), [], gs.Hypothesis(pose=near.copy(), cost=0.2)),
        hy.Track(wrong.copy(), [], gs.Hypothesis(pose=wrong.copy(), cost=0.4)),
    ]
    hy.rescore(idx, t2, r, a, P, cfg, g, limit=1.0, odometry=True)
    assert t2[0].age == 1 and t2[1].age == 0 and t2[1].costs == [1.0]


def test_rescore_keeps_the_odometry_moved_pose_where_the_beams_explain_it_better() -> None:
    """``GlobalConfig.rescore_keep_moved`` (opt-in): with odometry a kept hypothesis is
    polished on the distance field, which furniture returns pull off a floor plan's walls;
    the pose the odometry moved it to is verified too and kept when its cost is lower.
    Generated tuning building 46 (floor plan), a track at the exact pose on scans 8-19 of its
    tour: the polish alone moves it 0.07-0.17 m and up to doubles its cost (its keyframes
    then score 0.2-0.3 worse than a congruent room 8 m away, which won: 3 wrong first fixes
    at 50 ms); kept, it stays put wherever that verifies better. Off by default."""
    from sim_publisher.generator import BuildingParams, generate_building
    from sim_publisher.scenario import building_setup

    su = building_setup(generate_building(46, BuildingParams(people=0)), 2, seed=0)
    cfg = ShapeConfig.for_kind("schematic")
    g = GlobalConfig.for_kind("schematic")
    assert not g.rescore_keep_moved
    idx = load_or_build_index(su.map_data, cfg, g)
    off, stayed = [], 0
    for i in range(8, 20):
        truth = su.truth[i]
        r, a = su.scan(i)
        P = scan_configuration(r, a, cfg.extraction())
        got = {}
        for keep in (False, True):
            gk = g.model_copy(update={"rescore_keep_moved": keep})
            t = hy.Track(truth.copy(), [], gs.Hypothesis(pose=truth.copy(), cost=0.5))
            hy.rescore(idx, [t], r, a, P, cfg, gk, limit=100.0, odometry=True)
            got[keep] = (float(np.hypot(*(t.pose[:2] - truth[:2]))), t.costs[0])
        off.append(got[False][0])
        assert got[True][1] <= got[False][1] + 1e-12
        stayed += got[True][0] < 0.01
    assert min(off) > 0.05 and stayed >= 9, (off, stayed)


def test_the_rescoring_polish_holds_a_hypothesis_to_its_odometry_pose_in_a_corridor() -> None:
    # a straight 20 m corridor, 2 m wide, closed at both ends: along its axis the field
    # score is flat, so the unconstrained polish may slide a hypothesis anywhere along it
    md = MapData.from_lists(
        "corridor",
        "schematic",
        [[[0.0, 0.0], [20.0, 0.0], [20.0, 2.0], [0.0, 2.0], [0.0, 0.0]]],
    )
    index = build_index(md)
    wall = np.linspace(-3.0, 3.0, 61)
    pts = np.vstack(
        [
            np.column_stack([wall, np.full_like(wall, -1.0)]),
            np.column_stack([wall, np.full_like(wall, 1.0)]),
        ]
    )
    start = np.array([[10.0, 1.0, 0.0]])
    free, _ = gs._polish(index, start, pts, 0.05)
    held, _ = gs._polish(index, start, pts, 0.05, prior=GlobalConfig().rescore_prior)
    assert abs(free[0, 0] - 10.0) > 0.1, "the corridor was expected to leave the axis free"
    np.testing.assert_allclose(held[0], start[0], atol=1e-9)
    # across the corridor the walls still correct an odometry error of 12 cm, to within
    # the distance field's cell (its score is flat inside one)
    for y in (1.12, 0.88):
        fixed, _ = gs._polish(index, np.array([[10.0, y, 0.0]]), pts, 0.05, prior=0.02)
        assert abs(fixed[0, 1] - 1.0) <= index.resolution + 1e-9, fixed
