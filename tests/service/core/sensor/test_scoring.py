"""Scoring a pose against the map (service/core/sensor/scoring.py): beams and the field."""

from __future__ import annotations

import numpy as np
import pytest

from service.core.reloc import global_search as gs
from service.core.reloc.config import GlobalConfig
from service.core.reloc.drive import RESCORE_PRIOR
from service.core.reloc.global_localization import load_or_build_index
from service.core.reloc.states import DISTINCT_PEAK
from service.core.sensor.raycast import RayCaster
from service.core.sensor.scoring import BeamModel, beam_fractions
from service.core.shapes.configuration import scan_configuration
from service.core.tracking.localizer import ShapeConfig
from service.core.types import MapData

ROOM = np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 6.0], [0.0, 6.0], [0.0, 0.0]])
# a cabinet drawn in the map, 1.5 m in front of the robot's left wall, gone when the scan runs
CABINET = np.array([[2.0, 1.5], [2.0, 4.5]])


def _scan(pose: np.ndarray, beams: int = 360) -> tuple[np.ndarray, np.ndarray]:
    angles = np.linspace(-np.pi, np.pi, beams, endpoint=False)
    ranges = RayCaster(MapData.from_lists("now", "metric", [ROOM]).segments()).cast(
        pose, angles, 15.0
    )
    return ranges, angles


def test_a_beam_past_a_gone_object_onto_a_mapped_wall_is_no_violation() -> None:
    """The map holds a cabinet the laser now sees past: without ``see_through`` the true pose
    pays for ~1/6 of its beams as violations (cost above a bad fit's); with it those beams
    are neither hits nor violations. A pose 1.5 m off, whose beams leave the room through
    its walls into unmapped space, keeps its violations either way."""
    md = MapData.from_lists("room", "metric", [ROOM, CABINET])
    cfg = ShapeConfig.for_kind("metric")
    truth = np.array([5.0, 3.0, np.pi])
    ranges, angles = _scan(truth)
    P = scan_configuration(ranges, angles, cfg.extraction())
    off = np.array([6.5, 3.0, np.pi])
    out = {}
    for see in (False, True):
        g = GlobalConfig.for_kind("metric").model_copy(update={"see_through": see})
        idx = load_or_build_index(md, cfg, g)
        out[see] = (
            gs.verify(idx, truth, ranges, angles, P, cfg, g),
            gs.verify(idx, off, ranges, angles, P, cfg, g),
        )
    true_plain, off_plain = out[False]
    true_see, off_see = out[True]
    assert true_plain.violation > 0.1
    assert true_see.violation == 0.0
    assert true_see.hit == true_plain.hit
    assert true_see.cost < true_plain.cost - 0.2
    # the wrong pose: beams through the right-hand wall end in unmapped space
    assert off_see.violation > 0.05
    assert off_see.violation <= off_plain.violation
    assert off_see.cost > true_see.cost + 0.2


def test_field_violations_agree_with_the_ray_casters() -> None:
    """The search's cheap violation share (beams marched on the distance field) is the exact
    ray cast's within a beam or two, at the true pose (none: the beams end at the walls they
    came from) and at poses across the partition of two rooms (beams through it)."""
    partition = np.array([[5.0, 0.0], [5.0, 6.0]])
    md = MapData.from_lists("two", "schematic", [ROOM, partition])
    cfg = ShapeConfig.for_kind("schematic")
    g = GlobalConfig.for_kind("schematic")
    idx = load_or_build_index(md, cfg, g)
    truth = np.array([2.0, 3.0, 0.3])
    angles = np.linspace(-np.pi, np.pi, 40, endpoint=False)
    sensor = idx.sensor
    ranges = sensor.caster.cast(truth, angles, 15.0)
    margin = max(cfg.support_tolerance, g.violation_margin)
    rng = np.random.default_rng(3)
    poses = np.vstack(
        [
            truth,
            np.column_stack(
                [rng.uniform(0.5, 9.5, 30), rng.uniform(0.5, 5.5, 30), rng.uniform(-3, 3, 30)]
            ),
        ]
    )
    field = sensor.crossings(poses, ranges, angles, margin)
    tol = cfg.support_tolerance
    m = BeamModel(tolerance=tol, margin=g.violation_margin)
    exact = np.array(
        [beam_fractions(ranges, sensor.caster.cast(p, angles, 15.0), m).through for p in poses]
    )
    assert field[0] == 0.0 and exact[0] == 0.0
    assert exact.max() > 0.3  # poses whose beams cross the partition or the outer walls
    assert np.max(np.abs(field - exact)) <= 2 / 40


def test_a_short_return_counts_by_how_far_in_front_of_the_predicted_wall_it_lies() -> None:
    """``BeamModel.short_scale`` (floor plans' keyframes: 1 m): with the flat credit a return
    0.5 m in front of the predicted wall (furniture along the wall of its room) and one 4 m in
    front of it (a pose that puts the walls far behind the returns) count the same; graded,
    the first counts exp(-0.5) of a short return, the second exp(-4)."""
    r = np.full(10, 2.0)
    near, far = np.full(10, 2.5), np.full(10, 6.0)
    flat = BeamModel(tolerance=0.2, margin=0.5)
    a, b = (beam_fractions(r, pred, flat) for pred in (near, far))
    assert (a.hit, a.through, a.short) == (0.0, 0.0, 1.0) and a == b
    graded = BeamModel(tolerance=0.2, margin=0.5, short_scale=1.0)
    assert beam_fractions(r, near, graded).short == pytest.approx(np.exp(-0.5))
    assert beam_fractions(r, far, graded).short == pytest.approx(np.exp(-4.0))
    # hits, violations and beams with nothing predicted are counted as before
    mixed = beam_fractions(
        np.array([5.0, 9.0, 3.0, 1.0]), np.array([5.1, 5.0, np.nan, 2.0]), graded
    )
    assert (mixed.hit, mixed.through, mixed.short) == pytest.approx((0.25, 0.25, np.exp(-1.0) / 4))


def test_the_polish_with_a_prior_holds_a_pose_to_it_along_a_corridor() -> None:
    """Along a straight corridor the field score is flat: the polish without a prior may
    slide a pose anywhere along it; with the re-scoring's prior it stays where the odometry
    put it, and across the corridor the walls still correct it to within the field's cell."""
    from service.core.reloc.view_index import build_index

    md = MapData.from_lists(
        "corridor", "schematic", [[[0.0, 0.0], [20.0, 0.0], [20.0, 2.0], [0.0, 2.0], [0.0, 0.0]]]
    )
    sensor = build_index(md).sensor
    wall = np.linspace(-3.0, 3.0, 61)
    pts = np.vstack(
        [
            np.column_stack([wall, np.full_like(wall, -1.0)]),
            np.column_stack([wall, np.full_like(wall, 1.0)]),
        ]
    )
    start = np.array([[10.0, 1.0, 0.0]])
    free, _ = sensor.polish(start, pts, 0.05)
    held, _ = sensor.polish(start, pts, 0.05, prior=RESCORE_PRIOR)
    assert abs(free[0, 0] - 10.0) > 0.1, "the corridor was expected to leave the axis free"
    np.testing.assert_allclose(held[0], start[0], atol=1e-9)
    for y in (1.12, 0.88):
        fixed, _ = sensor.polish(np.array([[10.0, y, 0.0]]), pts, 0.05, prior=0.02)
        assert abs(fixed[0, 1] - 1.0) <= sensor.resolution + 1e-9, fixed


def test_the_window_search_finds_a_place_past_a_fits_reach_and_says_how_distinct() -> None:
    """In a room the window search over +-2 m finds a pose 1.3 m and 0.1 rad from its centre
    to the field's cell, and no other place in the window scores near it; in a long corridor
    (only its parallel walls in view) every place along the axis scores alike: not distinct."""
    from service.core.sensor.scoring import sensor_model

    room = MapData.from_lists("room", "metric", [ROOM, CABINET])
    truth = np.array([6.0, 3.0, 0.4])
    angles = np.linspace(-np.pi, np.pi, 360, endpoint=False)
    r = RayCaster(room.segments()).cast(truth, angles, 15.0)
    pts = np.column_stack([r * np.cos(angles), r * np.sin(angles)])
    sensor = sensor_model(room)
    centre = truth + np.array([1.0, -0.83, 0.1])
    peak = sensor.window(centre, 2.0, 0.2, pts)
    assert peak is not None
    assert np.hypot(*(peak.pose[:2] - truth[:2])) <= sensor.resolution
    assert abs(peak.pose[2] - truth[2]) < 0.01
    assert peak.distinct > DISTINCT_PEAK, peak

    corridor = MapData.from_lists(
        "corridor", "metric", [[[0.0, 0.0], [40.0, 0.0], [40.0, 2.0], [0.0, 2.0], [0.0, 0.0]]]
    )
    wall = np.linspace(-5.0, 5.0, 101)
    side = np.vstack(
        [
            np.column_stack([wall, np.full_like(wall, -1.0)]),
            np.column_stack([wall, np.full_like(wall, 1.0)]),
        ]
    )
    along = sensor_model(corridor).window(np.array([20.0, 1.2, 0.0]), 2.0, 0.1, side)
    assert along is not None
    assert abs(along.pose[1] - 1.0) <= 0.05  # across the corridor the walls still tell
    assert along.distinct < 0.05, along
    assert sensor.window(centre, 2.0, 0.2, np.zeros((0, 2))) is None
