"""ShapeLocalizer and ShapeConfig (service/core/tracking/localizer.py). Runs in about 2 seconds."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from service.core.factory import create_localizer
from service.core.sensor.raycast import RayCaster
from service.core.tracking.localizer import ShapeConfig, ShapeLocalizer
from service.core.types import MapData
from service.errors import LocalizationError
from sim_publisher.generator import BuildingParams, generate_building
from sim_publisher.scenario import building_setup
from sim_publisher.trajectory import simulate_odometry

# An L-shaped room with a pillar and a cupboard: enough shape for the matcher.
ROOM = MapData.from_lists(
    "lroom",
    "metric",
    [
        [[0, 0], [9, 0], [9, 4], [5, 4], [5, 7], [0, 7], [0, 0]],
        [[6.5, 1.5], [7.2, 1.5], [7.2, 2.2], [6.5, 2.2], [6.5, 1.5]],
        [[0.0, 5.0], [0.6, 5.0], [0.6, 6.2], [0.0, 6.2]],
    ],
)
ANGLES = np.linspace(-math.pi / 2, math.pi / 2, 361)


def _scan(pose: np.ndarray, rng: np.random.Generator, segments: np.ndarray | None = None):
    rc = RayCaster(ROOM.segments() if segments is None else segments)
    r = rc.cast(pose, ANGLES, 15.0)
    return r + rng.normal(0.0, 0.01, r.shape)


def _path(n: int) -> np.ndarray:
    t = np.linspace(0.0, 1.0, n)
    x = 2.0 + 4.0 * t
    y = 2.0 + 0.6 * np.sin(3 * t)
    th = 0.2 * np.sin(5 * t) + 0.1
    return np.column_stack([x, y, th])


def test_tracks_a_short_path_within_2cm() -> None:
    rng = np.random.default_rng(11)
    truth = _path(30)  # ~14 cm steps with a few degrees of rotation
    loc = ShapeLocalizer(ROOM, truth[0])
    errs = []
    for p in truth:
        e = loc.update(_scan(p, rng), ANGLES)
        assert e.status == "tracking"
        errs.append(np.hypot(*(e.pose[:2] - p[:2])))
        assert abs((e.pose[2] - p[2] + math.pi) % (2 * math.pi) - math.pi) < math.radians(0.5)
        assert 0.0 <= e.score <= 1.0
        assert e.matches and all(len(m.scan) >= 1 and len(m.map) >= 1 for m in e.matches)
    assert max(errs) < 0.02
    assert np.allclose(loc.pose, e.pose)


def test_recovers_from_a_20_degree_turn_without_odometry() -> None:
    rng = np.random.default_rng(12)
    start = np.array([3.0, 2.0, 0.2])
    turned = np.array([3.08, 2.05, 0.2 + math.radians(20)])
    loc = ShapeLocalizer(ROOM, start)
    loc.update(_scan(start, rng), ANGLES)
    e = loc.update(_scan(turned, rng), ANGLES)
    assert e.status == "tracking"
    assert np.hypot(*(e.pose[:2] - turned[:2])) < 0.02
    assert abs(e.pose[2] - turned[2]) < math.radians(0.5)


def test_status_lost_when_scans_come_from_elsewhere() -> None:
    """Scans of a different building: quality collapses and after `lost_after` scans the
    status is 'lost' while the pose is not moved by the garbage."""
    rng = np.random.default_rng(13)
    start = np.array([3.0, 2.0, 0.0])
    other = np.array(  # a long narrow corridor with no relation to the room
        [[-20, -0.8, 20, -0.8], [-20, 0.8, 20, 0.8], [3.3, 0.8, 3.3, 3.0]], dtype=float
    )
    loc = ShapeLocalizer(ROOM, start)
    statuses = []
    for _ in range(5):
        e = loc.update(_scan(np.array([0.0, 0.0, 0.0]), rng, other), ANGLES)
        statuses.append(e.status)
    cfg = loc.config
    assert statuses[: cfg.lost_after - 1] == ["tracking"] * (cfg.lost_after - 1)
    assert statuses[cfg.lost_after - 1 :] == ["lost"] * (5 - cfg.lost_after + 1)
    assert np.hypot(*(loc.pose[:2] - start[:2])) < 1.0
    assert e.score < 0.6


def test_unknown_pose_answers_initializing() -> None:
    loc = ShapeLocalizer(ROOM, None)
    e = loc.update(_scan(np.array([3.0, 2.0, 0.0]), np.random.default_rng(1)), ANGLES)
    assert e.status == "initializing"
    assert e.score == 0.0
    assert np.array_equal(e.pose, np.zeros(3))
    assert loc.pose is None
    loc.reset(np.array([3.0, 2.0, 0.0]))
    assert np.allclose(loc.pose, [3.0, 2.0, 0.0])


def test_bad_input_raises_localization_error() -> None:
    loc = ShapeLocalizer(ROOM, np.array([3.0, 2.0, 0.0]))
    with pytest.raises(LocalizationError, match="equal length"):
        loc.update(np.ones(10), np.zeros(9))
    with pytest.raises(LocalizationError, match="empty"):
        loc.update(np.zeros(0), np.zeros(0))
    with pytest.raises(LocalizationError, match="NaN"):
        loc.update(np.full(3, np.inf), np.zeros(3))
    with pytest.raises(LocalizationError, match="finite"):
        loc.update(np.ones(3), np.array([0.0, np.nan, 1.0]))
    with pytest.raises(LocalizationError, match="initial_pose"):
        ShapeLocalizer(ROOM, np.array([1.0, 2.0]))
    with pytest.raises(LocalizationError, match="ShapeConfig"):
        ShapeLocalizer(ROOM, None, config={"penalty_weight": 1.0})  # type: ignore[arg-type]


def test_deterministic() -> None:
    truth = _path(8)
    runs = []
    for _ in range(2):
        rng = np.random.default_rng(21)
        loc = ShapeLocalizer(ROOM, truth[0])
        runs.append(np.array([loc.update(_scan(p, rng), ANGLES).pose for p in truth]))
    assert np.array_equal(runs[0], runs[1])


def test_config_per_kind_and_factory() -> None:
    m, s = ShapeConfig.for_kind("metric"), ShapeConfig.for_kind("schematic")
    assert m.kind == "metric" and s.kind == "schematic"
    assert s.support_tolerance > m.support_tolerance
    assert s.shape_end_weight < m.shape_end_weight
    with pytest.raises(LocalizationError, match="unknown map kind"):
        ShapeConfig.for_kind("sketch")
    # the factory's "shape" localiser (possibly wrapped for global localisation) tracks
    loc = create_localizer("shape", ROOM, np.array([3.0, 2.0, 0.0]))
    assert loc.method == "shape"
    rng = np.random.default_rng(5)
    e = loc.update(_scan(np.array([3.05, 2.0, 0.02]), rng), ANGLES)
    assert e.status == "tracking"
    assert np.hypot(e.pose[0] - 3.05, e.pose[1] - 2.0) < 0.02


@pytest.mark.parametrize("turn_deg", [120.0, -150.0])
def test_turn_beyond_max_turn_is_recovered_without_odometry(turn_deg: float) -> None:
    """A turn far beyond max_turn between two scans: the fit from the velocity prior (heading
    kept) is rejected, and the turn recovery's cut points all round the circle find it."""
    rng = np.random.default_rng(13)
    start = np.array([3.0, 2.0, 0.2])
    turned = np.array([3.08, 2.05, 0.2 + math.radians(turn_deg)])
    cfg = ShapeConfig()
    assert math.radians(abs(turn_deg)) > cfg.max_turn
    loc = ShapeLocalizer(ROOM, start, cfg)
    loc.update(_scan(start, rng), ANGLES)
    e = loc.update(_scan(turned, rng), ANGLES)
    assert e.status == "tracking" and "rejected" not in e.extras
    assert e.extras["turn_recovered"] > cfg.max_turn
    assert np.hypot(*(e.pose[:2] - turned[:2])) < 0.03
    assert abs((e.pose[2] - turned[2] + math.pi) % (2 * math.pi) - math.pi) < math.radians(1)
    # without the recovery the same scan is rejected and the prior's heading kept
    off = ShapeLocalizer(ROOM, start, cfg.model_copy(update={"turn_recovery": False}))
    off.update(_scan(start, np.random.default_rng(13)), ANGLES)
    e2 = off.update(_scan(turned, rng), ANGLES)
    assert "rejected" in e2.extras


def test_beams_through_walls_measure_a_wrong_pose() -> None:
    """The share of beams passing through map walls: none at the true pose, many at a pose
    shifted towards a wall (the returns then lie behind it)."""
    rng = np.random.default_rng(14)
    pose = np.array([3.0, 2.0, 0.1])
    loc = ShapeLocalizer(ROOM, pose)
    r = _scan(pose, rng)
    assert loc.violations(r, ANGLES, [pose])[0] == 0.0
    shifted = pose + np.array([0.0, -0.8, 0.0])
    assert loc.violations(r, ANGLES, [shifted])[0] > 0.2
    off = ShapeLocalizer(ROOM, pose, ShapeConfig(violation_beams=0))
    assert off.violations(r, ANGLES, [shifted])[0] == 0.0


def test_step_bound_follows_the_robots_own_speed_without_odometry() -> None:
    """Without odometry a jump of several times the robot's recent speed is rejected (a
    robot does not triple its speed between two scans); max_step stays the upper bound."""
    rng = np.random.default_rng(15)
    truth = _path(41)  # steps of ~0.1 m
    loc = ShapeLocalizer(ROOM, truth[0])
    for p in truth:
        loc.update(_scan(p, rng), ANGLES)
    speed = float(np.hypot(*loc.motion.velocity.velocity))
    assert 0.08 < speed < 0.13
    pred = loc.motion.predict(loc.pose, None)
    cfg = loc.config
    assert loc._max_step(pred) == pytest.approx(
        min(cfg.max_step, cfg.speed_step_floor + cfg.speed_step_factor * speed)
    )
    # before three accepted scans the speed is unknown: max_step alone bounds the step
    fresh = ShapeLocalizer(ROOM, truth[0])
    assert fresh._max_step(fresh.motion.predict(fresh.pose, None)) == cfg.max_step
    # with the bound, the step gate is tighter than max_step at this speed
    assert loc._max_step(pred) < cfg.max_step


def test_step_bound_with_odometry_is_odom_step_floor_plus_three_sigma() -> None:
    """With odometry a fit may move the pose at most odom_step_floor (+ 3 sigma of the
    odometry step) from the odometry's prediction; each rejection in a row widens it."""
    start = np.array([3.0, 2.0, 0.2])
    loc = ShapeLocalizer(ROOM, start, ShapeConfig(odom_step_floor=0.2))
    cfg = loc.config
    assert 0 < cfg.odom_step_floor < cfg.max_step
    loc.update(_scan(start, np.random.default_rng(16)), ANGLES, np.zeros(3))
    pred = loc.motion.predict(loc.pose, np.array([0.1, 0.0, 0.0]))
    assert pred.source == "odometry"
    three = 3.0 * float(max(pred.sigma[0], pred.sigma[1]))
    assert loc._max_step(pred) == pytest.approx(cfg.odom_step_floor + three)
    loc._rejected = 1
    assert loc._max_step(pred) == pytest.approx(2 * cfg.odom_step_floor + three)
    wide = ShapeLocalizer(ROOM, start)  # the default: max_step
    wide.update(_scan(start, np.random.default_rng(16)), ANGLES, np.zeros(3))
    pred = wide.motion.predict(wide.pose, np.array([0.1, 0.0, 0.0]))
    assert wide._max_step(pred) == pytest.approx(cfg.max_step + three)


def test_plain_prior_fit_is_left_out_only_where_nothing_uses_it(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """Without odometry on a floor plan the shape matching runs on every scan and weights the
    fit's points, so only the weighted fits of the prior and of the shape estimate are made
    (2 per scan, not 3). Forcing the plain prior fit up front as well (the shape matching
    still running on every scan) changes no estimate. With odometry the plain prior fit
    decides whether the shape matching runs, and is made first."""
    from service.core.tracking import localizer as loc_mod
    from sim_publisher.scenario import make_setup

    s = make_setup(2, seed=0, max_scans=12)
    calls: list[int] = []
    real_refine = loc_mod.refine_pose

    def counting(*args, **kwargs):  # type: ignore[no-untyped-def]
        calls.append(0 if kwargs.get("weights") is None else 1)
        return real_refine(*args, **kwargs)

    monkeypatch.setattr(loc_mod, "refine_pose", counting)

    def run(odom: bool) -> list:
        loc = ShapeLocalizer(s.map_data, s.truth[0])
        return [loc.update(*s.scan(i), s.odom[i] if odom else None) for i in range(len(s))]

    lazy = run(False)
    assert ShapeConfig.for_kind(s.map_data.kind).unmatched_weight < 1.0
    assert len(calls) == 2 * len(s) and calls.count(0) == 0
    # the eager order: the plain prior fit first, then "doubtful" as before
    with monkeypatch.context() as m:
        m.setattr(ShapeLocalizer, "_always_doubtful", lambda self, pred: False)
        m.setattr(ShapeLocalizer, "_doubtful", lambda self, f, pred: pred.source != "odometry")
        calls.clear()
        eager = run(False)
        assert calls.count(0) == len(s)
    for a, b in zip(lazy, eager, strict=True):
        assert np.array_equal(a.pose, b.pose) and a.score == b.score and a.status == b.status
    calls.clear()
    run(True)
    assert calls[:1] == [0]  # with odometry the plain prior fit comes first


def _bent_corridor() -> tuple[MapData, np.ndarray, np.ndarray]:
    """A 16 m corridor whose right wall bows 0.3 m inward over 8 m (the world), and its floor
    plan drawn the way a schematisation draws such a wall: two straight lines, the kink 1.5 m
    further along than the bow's apex (the situation of intel's corridor at scans 8377-8431).
    Returns the plan, the world's segments and the tour (7 cm steps along the corridor)."""
    length, bulge = 16.0, 0.3
    ys = np.linspace(0.0, length, 161)
    xr = 1.0 - bulge * np.where((ys > 4) & (ys < 12), np.sin(np.pi * (ys - 4) / 8), 0.0)
    left = np.array([[-1.0, -0.5], [-1.0, length + 0.5]])
    ends = [
        np.array([[-1.0, -0.5], [1.0, -0.5]]),
        np.array([[-1.0, length + 0.5], [1.0, length + 0.5]]),
    ]
    world = [left, np.column_stack([xr, ys]), *ends]
    plan_right = np.array([[1.0, 0.0], [1.0, 4.0], [1.0 - bulge, 9.5], [1.0, 12.0], [1.0, length]])
    plan = MapData.from_lists("bent", "schematic", [left, plan_right, *ends])
    segs = np.array([[*a, *b] for p in world for a, b in itertools.pairwise(p)])
    tour = np.array([[0.0, 0.5 + 0.07 * k, math.pi / 2] for k in range(208)])
    return plan, segs, tour


def _along_error(config: ShapeConfig) -> float:
    """Largest along-corridor error (m) of the shape tracker on :func:`_bent_corridor` with
    exact odometry and 1 cm range noise."""
    from sim_publisher.laser import LaserConfig, LaserSimulator

    plan, segs, tour = _bent_corridor()
    laser = LaserSimulator(segs, LaserConfig(beams=181, max_range=5.0), seed=1)
    loc = ShapeLocalizer(plan, tour[0].copy(), config)
    worst = 0.0
    for k, pose in enumerate(tour):
        r, a = laser.scan(pose, k)
        est = loc.update(r, a, pose)
        worst = max(worst, abs(float(est.pose[1] - pose[1])))
    return worst


def test_odometry_holds_the_pose_where_a_plan_wall_is_drawn_off() -> None:
    """A plan whose wall is slightly off pulls every scan's fit along the corridor; the shape
    tracker's odometry floor (0.02 m per scan) keeps the slide within 0.4 m where the looser
    MotionConfig default (0.03 m) let it reach 0.5 m."""
    from service.core.tracking.motion import MotionConfig

    cfg = ShapeConfig.for_kind("schematic")
    assert cfg.motion.sigma_xy_floor == pytest.approx(0.02)
    tight = _along_error(cfg)
    loose = _along_error(cfg.model_copy(update={"motion": MotionConfig()}))
    assert tight < 0.4
    assert loose > tight + 0.1


def test_a_rejected_scan_keeps_the_prior_and_says_where_it_pointed() -> None:
    """A scan whose fit moves the pose beyond the step bound is rejected: the estimate is the
    prior, while ``last_fit`` is where the scan itself fitted (the global search's
    confirmation uses it: ``GlobalConfig.confirm_unexplained``); after an accepted scan it is
    the published pose."""
    start = np.array([3.0, 2.0, 0.2])
    loc = ShapeLocalizer(ROOM, start, ShapeConfig(odom_step_floor=0.1))
    first = loc.update(_scan(start, np.random.default_rng(3)), ANGLES, np.zeros(3))
    assert first.status == "tracking" and "rejected" not in first.extras
    assert loc.last_fit is not None
    np.testing.assert_allclose(loc.last_fit, first.pose)
    moved = start + np.array([0.35, 0.0, 0.0])  # the odometry says the robot barely moved
    est = loc.update(_scan(moved, np.random.default_rng(4)), ANGLES, np.array([0.01, 0.0, 0.0]))
    assert est.extras.get("rejected") == 3.0
    assert np.hypot(*(est.pose[:2] - first.pose[:2])) < 0.02
    assert loc.last_fit is not None
    assert np.hypot(*(loc.last_fit[:2] - moved[:2])) < 0.05, loc.last_fit


def test_a_turn_between_processed_scans_is_fitted_from_more_than_one_heading() -> None:
    """Two scans replaced under load make one increment a 119-degree turn (generated
    building 1000, the fleet benchmark's robot 13); the odometry's heading is 3.2 degrees
    off there, just outside the fit's basin: fitted from the prior alone the pose lands
    0.15 m off along a corridor and stays there for six scans. With the fits from the
    prior's heading +- half and one sigma weighed too, every pose stays within 0.01 m."""
    su = building_setup(generate_building(1000, BuildingParams()), 1, seed=7, people=False)
    idx = np.arange(0, len(su), 5)
    m = len(idx)
    k = ((13 * m) // 20 + np.arange(200)) % (2 * (m - 1))  # back and forth along the tour
    tour = idx[np.where(k < m, k, 2 * (m - 1) - k)]
    truth = su.reference[tour]
    odom = simulate_odometry(truth, seed=13)
    lz = su.laser
    a = lz.angle_min + np.arange(lz.config.beams) * lz.angle_increment

    def worst(heading_starts_sigma: float) -> float:
        cfg = ShapeConfig.for_kind("metric").model_copy(
            update={"heading_starts_sigma": heading_starts_sigma}
        )
        loc = create_localizer("shape", su.map_data, truth[0], cfg)
        err = []
        for i in [i for i in range(72) if i not in (65, 66)]:
            r = np.asarray(su.scan(int(tour[i]))[0], dtype="<f4").astype(np.float64)
            r[(r <= 0) | (r >= lz.config.max_range)] = np.nan
            est = loc.update(r, a, odom[i])
            assert est.status == "tracking"
            err.append(float(np.hypot(*(est.pose[:2] - truth[i, :2]))))
        return max(err)

    assert worst(0.0) > 0.1  # the case: the prior's fit alone goes to the wrong basin
    assert worst(ShapeConfig().heading_starts_sigma) < 0.01
