"""Laser odometry: the motion between scans from the scans alone, as the odometry of a robot
that sends none (service/core/laser_odometry.py)."""

from __future__ import annotations

import math
import pickle
from functools import lru_cache
from typing import Any

import numpy as np
import pytest

from service.core import numeric
from service.core.baselines import scan_points
from service.core.factory import create_localizer
from service.core.mounting import MountedLocalizer
from service.core.pose import compose, invert
from service.core.reloc.global_localization import GlobalShapeLocalizer
from service.core.sensor.raycast import RayCaster
from service.core.tracking.laser_odometry import (
    LaserOdometry,
    LaserOdometryConfig,
    LaserOdometryLocalizer,
    config_for_kind,
    observability,
    turn_candidates,
    with_laser_odometry,
)
from service.core.tracking.motion import MotionConfig, OdometryMotion, odometry_sigmas
from service.core.tracking.scan_odometry import surface_normals
from service.core.types import Estimate, MapData, wrap_angle
from service.errors import LocalizationError
from sim_publisher.generator import BuildingParams, generate_building
from sim_publisher.scenario import Setup, building_setup


@lru_cache(maxsize=2)
def _floor_plan(seed: int) -> Setup:
    """Tuning building ``seed``'s floor-plan tour (setup 2: a scan every 104 mm, turning 32
    degrees between scans at the median), no moving people."""
    return building_setup(generate_building(seed, BuildingParams(people=0)), 2, seed=0)


def _error(delta: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    return (
        math.hypot(float(delta[0] - truth[0]), float(delta[1] - truth[1])),
        abs(float(wrap_angle(float(delta[2] - truth[2])))),
    )


class _Recorder:
    """A localiser that records the odometry it is given and answers ``tracking`` at the
    origin."""

    method = "fake"

    def __init__(self) -> None:
        self.map_data = MapData.from_lists("m", "metric", [[[0.0, 0.0], [1.0, 0.0]]])
        self.odoms: list[np.ndarray | None] = []
        self.resets: list[tuple[Any, Any]] = []
        self.extra = 7

    @property
    def pose(self) -> np.ndarray | None:
        return np.zeros(3)

    def update(self, ranges: np.ndarray, angles: np.ndarray, odom: Any = None) -> Estimate:
        self.odoms.append(odom)
        return Estimate(pose=np.zeros(3), status="initializing", score=0.0)

    def reset(self, initial_pose: Any, odom: Any = None) -> None:
        self.resets.append((initial_pose, odom))


def test_the_turn_between_two_histograms_is_their_correlation_peak() -> None:
    rng = np.random.default_rng(3)
    h = np.zeros(180)
    h[[10, 55, 100, 145]] = [5.0, 3.0, 4.0, 2.0]
    h += 0.05 * rng.random(180)
    turned = np.roll(h, -20)  # a turn of +40 degrees moves every wall 20 bins back
    got = turn_candidates(h, turned, 3, math.pi)
    assert got[0] == pytest.approx(math.radians(40.0), abs=math.radians(1.0))
    assert turn_candidates(h, np.zeros(180), 3, math.pi) == []
    # a turn beyond the widest allowed is not offered
    assert all(abs(t) <= 0.5 for t in turn_candidates(h, turned, 3, 0.5))


def test_increments_on_a_simulated_floor_plan_drive_match_the_truth_and_the_noise_model() -> None:
    """Building 0's tour, 130 scans: the robot turns up to 52 degrees between scans and, at
    scan 105, 140 degrees (beyond what two views of a 180-degree laser share: the local map of
    the last keyframes matches it). Every increment is known and right; the errors stay within
    2 sigma of the noise model the tracker gives a scan-matched increment
    (``odometry_sigmas(..., matched=True)``). Measured: translation max 13 mm, heading max
    0.6 deg."""
    su = _floor_plan(0)
    lo = LaserOdometry()
    motion = MotionConfig()
    worst_t = worst_r = 0.0
    for i in range(131):
        step = lo.step(*su.scan(i))
        if i == 0:
            assert step is None
            continue
        assert step is not None and step.matched, f"scan {i}: increment unknown"
        truth = compose(invert(su.truth[i - 1]), su.truth[i])
        et, er = _error(step.delta, truth)
        s_trans, s_rot = odometry_sigmas(step.delta, motion, matched=True)
        assert et < 2.0 * s_trans and er < 2.0 * s_rot, f"scan {i}: {et:.3f} m, {er:.4f} rad"
        worst_t, worst_r = max(worst_t, et), max(worst_r, er)
        if i == 105:
            assert abs(truth[2]) > math.radians(135.0)  # the big turn is in the window
    assert worst_t < 0.03 and worst_r < math.radians(1.5)


def test_an_unknown_increment_is_not_made_up() -> None:
    """Two scans of unrelated places: the fit explains too little, the increment stays the
    constant-velocity guess and is not trusted."""
    su = _floor_plan(0)
    lo = LaserOdometry()
    lo.step(*su.scan(0))
    lo.remember(np.array([0.1, 0.0, 0.0]))
    r, a = su.scan(200)
    step = lo.step(np.where(np.isfinite(r), 0.3 + 0.0 * r, np.nan), a)  # a round room of 0.3 m
    assert step is not None and not step.matched
    assert step.delta == pytest.approx([0.1, 0.0, 0.0])


def test_a_floor_plan_drive_without_odometry_is_tracked() -> None:
    """Building 0's floor plan, the first 130 scans (13.5 m) with no odometry: with the laser
    odometry every scan passes the paper's setup-2 test (500 mm, 45 deg) and is tracked; the
    paper's own mode (no odometry of any kind) loses the track at scan 96, after a turn of 44
    degrees between scans followed by one of 140."""
    su = _floor_plan(0)
    loc = create_localizer("shape", su.map_data, su.reference[0])
    paper = create_localizer("shape", su.map_data, su.reference[0], laser_odometry=False)
    assert isinstance(loc, LaserOdometryLocalizer) and isinstance(paper, GlobalShapeLocalizer)
    failed_paper = 0
    for i in range(131):
        r, a = su.scan(i)
        est = loc.update(r, a, None)
        assert su.passed(i, est.pose), f"scan {i}: {est.pose} vs {su.reference[i]}"
        assert est.status == "tracking", f"scan {i}: {est.status}"
        failed_paper += not su.passed(i, paper.update(r, a, None).pose)
    assert failed_paper > 10  # measured 35


def test_a_global_fix_without_odometry_on_a_floor_plan() -> None:
    """Building 65's floor plan, no initial pose, no odometry, from scan 17 (the window of the
    drive-search tests, which send odometry): the laser odometry carries the hypotheses
    between scans, and the fix comes after 3.2 m as with the simulated odometry, correct, with
    no wrong ``tracking`` pose before or after it."""
    su = _floor_plan(65)
    loc = create_localizer("shape", su.map_data, None, search_budget_ms=50.0)
    fix = None
    for i in range(17, 161):
        est = loc.update(*su.scan(i), None)
        if est.status != "tracking":
            continue
        t = su.reference[i]
        assert float(np.hypot(*(est.pose[:2] - t[:2]))) < 0.5, f"scan {i}: wrong place"
        assert abs(float(wrap_angle(float(est.pose[2] - t[2])))) < math.radians(10.0)
        fix = i if fix is None else fix
    assert fix is not None, "no fix"
    assert (fix - 17) * su.step_m < 15.0  # measured 3.2 m


def test_wheel_odometry_passes_bit_for_bit_and_a_switch_keeps_one_frame() -> None:
    """Scans 0-9 with the robot's odometry, 10-19 without, 20-29 with again: the first ten
    readings are the robot's own objects' values; then the laser odometry continues from the
    last one with the true increments; back on wheel odometry the readings continue from the
    laser one with the wheel increments (one frame, no jump)."""
    su = _floor_plan(0)
    inner = _Recorder()
    loc = LaserOdometryLocalizer(inner)
    for i in range(30):
        loc.update(*su.scan(i), None if 10 <= i < 20 else su.odom[i])
    got = inner.odoms
    for i in range(10):
        assert got[i] is not None and np.array_equal(got[i], su.odom[i])
    for i in range(10, 21):
        truth = compose(invert(su.truth[i - 1]), su.truth[i])
        inc = compose(invert(np.asarray(got[i - 1])), np.asarray(got[i]))
        et, er = _error(inc, truth)
        assert et < 0.02 and er < 0.01, f"scan {i}"
    for i in range(21, 30):
        wheel = compose(invert(su.odom[i - 1]), su.odom[i])
        inc = compose(invert(np.asarray(got[i - 1])), np.asarray(got[i]))
        assert inc == pytest.approx(wheel, abs=1e-9)


def test_an_unknown_increment_goes_without_odometry_and_the_next_one_counts_the_motion() -> None:
    """An unmatched scan goes to the inner localiser without odometry (the paper's mode: a
    rejected scan counts towards lost at once, as a kidnap needs); the next fresh reading
    spans both scans' motion (the guess while the inner localiser does not track)."""
    su = _floor_plan(0)
    inner = _Recorder()
    loc = LaserOdometryLocalizer(inner)
    for i in range(5):
        loc.update(*su.scan(i))
    r, a = su.scan(5)
    loc.update(np.full_like(r, 0.3), a)  # a scan of nothing it saw: unmatched
    assert loc.last_step is not None and not loc.last_step.matched
    assert inner.odoms[5] is None
    loc.update(*su.scan(6))
    assert loc.last_step is not None
    assert inner.odoms[6] is not None and not np.array_equal(inner.odoms[6], inner.odoms[4])


def test_the_wrapper_delegates_resets_and_pickles() -> None:
    inner = _Recorder()
    loc = LaserOdometryLocalizer(inner)
    assert loc.method == "fake" and loc.extra == 7 and loc.map_data is inner.map_data
    su = _floor_plan(0)
    loc.update(*su.scan(0))
    loc.update(*su.scan(1))
    loc.reset(np.array([1.0, 2.0, 0.0]), np.array([5.0, 5.0, 0.5]))
    assert inner.resets[-1][1] == pytest.approx([5.0, 5.0, 0.5])
    assert not loc.odometry.has_previous  # the robot may have been carried elsewhere
    loc.update(*su.scan(2))
    assert inner.odoms[-1] == pytest.approx([5.0, 5.0, 0.5])  # the reading given to reset
    back = pickle.loads(pickle.dumps(loc))
    assert isinstance(back, LaserOdometryLocalizer) and back.extra == 7
    with pytest.raises(LocalizationError):
        loc.update(np.array([1.0]), np.array([0.0, 1.0]))
    with pytest.raises(LocalizationError):
        loc.update(*su.scan(3), np.array([np.nan, 0.0, 0.0]))


def test_the_factory_wraps_shape_only_unless_asked_and_mounts_outside() -> None:
    su = _floor_plan(0)
    md = su.map_data
    assert isinstance(create_localizer("shape", md, su.reference[0]), LaserOdometryLocalizer)
    assert not isinstance(create_localizer("icp", md, su.reference[0]), LaserOdometryLocalizer)
    icp = create_localizer("icp", md, su.reference[0], laser_odometry=True)
    assert isinstance(icp, LaserOdometryLocalizer)
    mounted = create_localizer("shape", md, su.reference[0], laser_offset=[0.2, 0.0, 0.0])
    assert isinstance(mounted, MountedLocalizer)
    assert isinstance(mounted.inner, LaserOdometryLocalizer)  # the laser's motion, laser frame
    plain = _Recorder()
    assert with_laser_odometry(plain, False) is plain  # type: ignore[arg-type]


def _walls(*corners: tuple[float, float]) -> np.ndarray:
    """Closed polyline through ``corners`` as segments ``[x0, y0, x1, y1]``."""
    c = np.array([*corners, corners[0]], dtype=np.float64)
    return np.hstack([c[:-1], c[1:]])


def _scans(
    walls: np.ndarray, poses: list[np.ndarray], fov: float = math.pi
) -> list[tuple[np.ndarray, np.ndarray]]:
    """Noise-free scans (361 beams over ``fov``, 30 m) of ``walls`` taken at ``poses``."""
    caster = RayCaster(walls)
    angles = np.linspace(-fov / 2.0, fov / 2.0, 361)
    return [(caster.cast(np.asarray(p, dtype=np.float64), angles, 30.0), angles) for p in poses]


# An L-shaped room with a pillar: walls in two directions and corners, so both directions of
# the position and the heading are seen.
_ROOM = np.vstack(
    [
        _walls((-3.0, -2.0), (6.0, -2.0), (6.0, 1.0), (2.0, 1.0), (2.0, 4.0), (-3.0, 4.0)),
        _walls((0.5, 0.0), (1.0, 0.0), (1.0, 0.5), (0.5, 0.5)),
    ]
)
# A straight corridor 2 m wide and 200 m long: along it no wall ends within the laser's range.
_CORRIDOR = np.vstack(
    [np.array([[-100.0, -1.0, 100.0, -1.0]]), np.array([[-100.0, 1.0, 100.0, 1.0]])]
)


def test_a_scan_pair_with_a_known_motion_gives_that_increment_fully_observed() -> None:
    start = np.array([-1.0, -0.5, 0.2])
    truth = np.array([0.12, -0.04, 0.3])
    (s0, a0), (s1, a1) = _scans(_ROOM, [start, compose(start, truth)])
    lo = LaserOdometry()
    assert lo.step(s0, a0) is None
    step = lo.step(s1, a1)
    assert step is not None and step.matched
    et, er = _error(step.delta, truth)
    assert et < 0.01 and er < math.radians(0.5), (et, er)
    assert not np.any(step.spread)  # every direction of the position is measured


def test_a_corridor_pair_reports_the_axis_as_unobserved_and_measures_the_rest() -> None:
    """Two scans 0.15 m apart along a featureless corridor (and 0.05 m across it, turned 3
    degrees): the walls tell the motion across the corridor and the turn, not the motion along
    it. The step says so: its extra variance lies along the corridor's axis only. On a floor
    plan's defaults the increment is still given as odometry (the guess along the axis), on a
    metric map's it is not (the map decides along the axis)."""
    start = np.array([0.0, -0.1, 0.0])
    truth = np.array([0.15, 0.05, math.radians(3.0)])
    scans = _scans(_CORRIDOR, [start, compose(start, truth)])
    for kind, given in (("schematic", True), ("metric", False)):
        lo = LaserOdometry(config_for_kind(kind))
        lo.step(*scans[0])
        step = lo.step(*scans[1])
        assert step is not None and step.matched is given, kind
        assert abs(step.delta[1] - truth[1]) < 0.01, kind  # across the corridor: measured
        assert abs(float(wrap_angle(float(step.delta[2] - truth[2])))) < math.radians(0.5)
        assert step.spread[0, 0] > 0.0, kind  # along the axis: the guess's miss
        assert step.spread[1, 1] == pytest.approx(0.0, abs=1e-12), kind
        assert step.spread[0, 1] == pytest.approx(0.0, abs=1e-12), kind


def test_observability_of_a_corridor_has_no_weight_along_its_axis() -> None:
    """The normal matrix of a corridor's pairs: all its weight across the corridor; a room's:
    weight in both directions."""
    cfg = LaserOdometryConfig().fit
    for walls, both in ((_CORRIDOR, False), (_ROOM, True)):
        ((r, a),) = _scans(walls, [np.array([0.0, -0.5 if both else 0.0, 0.1])])
        pts = scan_points(r, a, cfg.max_range)
        nrm = surface_normals(pts, cfg.normal_window, cfg.normal_radius, cfg.max_flatness)
        ok = np.all(np.isfinite(nrm), axis=1)
        pts, nrm = pts[ok], nrm[ok]
        normal, total = observability(pts, nrm, pts, nrm, np.zeros(3), cfg)
        assert total > 0.5 * len(pts)  # a scan against itself: nearly every point is paired
        vals, _ = numeric.eigh_sym2(normal)
        if both:
            assert min(vals) > 0.05 * total
        else:
            assert min(vals) < 1e-6 * total


def test_an_unobserved_direction_weakens_the_prior_along_it_only() -> None:
    """The tracker's odometry prior with an increment's extra variance along the robot's x
    axis (heading 90 degrees: the map's y axis): less information along it, the same across
    it, the heading's untouched; a non-finite spread is refused."""
    motion = OdometryMotion(MotionConfig())
    pose = np.array([1.0, 2.0, math.pi / 2.0])
    motion.predict(pose, np.zeros(3))
    plain = motion.predict(pose, np.array([0.1, 0.0, 0.0])).information
    motion = OdometryMotion(MotionConfig())
    motion.predict(pose, np.zeros(3))
    spread = np.diag([0.05**2, 0.0])
    wide = motion.predict(pose, np.array([0.1, 0.0, 0.0]), spread=spread).information
    assert wide[1, 1] < 0.5 * plain[1, 1]  # robot x is map y at this heading
    assert wide[0, 0] == pytest.approx(plain[0, 0])
    assert wide[2, 2] == pytest.approx(plain[2, 2])
    with pytest.raises(LocalizationError):
        motion.predict(pose, np.array([0.2, 0.0, 0.0]), spread=np.full((2, 2), np.nan))


def test_the_map_kind_picks_the_defaults_and_a_new_map_switches_them() -> None:
    assert config_for_kind("metric").unobserved_unknown
    assert not config_for_kind("schematic").unobserved_unknown
    inner = _Recorder()
    loc = LaserOdometryLocalizer(inner)
    assert loc.odometry.config.unobserved_unknown  # the recorder's map is metric
    inner.map_data = MapData.from_lists("p", "schematic", [[[0.0, 0.0], [1.0, 0.0]]])
    su = _floor_plan(0)
    loc.update(*su.scan(0))
    assert not loc.odometry.config.unobserved_unknown
    fixed = LaserOdometryLocalizer(inner, LaserOdometryConfig(unobserved_unknown=True))
    fixed.update(*su.scan(0))
    assert fixed.odometry.config.unobserved_unknown  # an explicit config is kept


def test_the_wrappers_reads_and_writes_reach_the_inner_localiser() -> None:
    """A caller that tunes the localiser it got from the factory (``loc.gconfig = ...``) tunes
    the one that localises, and ``loc.config`` is the inner localiser's configuration."""
    su = _floor_plan(0)
    loc = create_localizer("shape", su.map_data, None)
    assert isinstance(loc, LaserOdometryLocalizer)
    inner = loc.inner
    assert isinstance(inner, GlobalShapeLocalizer)
    assert loc.config is inner.config
    loc.gconfig = inner.gconfig.model_copy(update={"settle_scans": 7})
    assert inner.gconfig.settle_scans == 7 and "gconfig" not in loc.__dict__
    loc.last_step = None  # the wrapper's own attributes stay its own
    assert "last_step" in loc.__dict__


def test_a_pose_the_scan_contradicts_is_not_tracked_on_an_odometry_from_the_scans() -> None:
    """A floor plan's dead-end corridor; the robot stands 5 m from the end wall, facing it,
    the localiser believes it 1.5 m closer (slid along the axis, where neither the scans nor
    the plan's side walls pin it). The side walls explain most of the scan and the fit is
    accepted; its beams to the end wall return from beyond the mapped wall. With the wheel
    odometry's reading the track stays (only a rejected scan is checked); with a reading
    measured from the scans the pose no longer anchors the dead-reckoned reference, so it is
    not published as tracking, and a search starts after ``lost_after`` such scans."""
    plan = MapData.from_lists(
        "dead-end",
        "schematic",
        [[[-20.0, -1.0], [5.0, -1.0], [5.0, 1.0], [-20.0, 1.0]]],
    )
    walls = np.array([[-20.0, -1.0, 5.0, -1.0], [5.0, -1.0, 5.0, 1.0], [5.0, 1.0, -20.0, 1.0]])
    ((r, a),) = _scans(walls, [np.zeros(3)])
    for from_scans in (False, True):
        loc = create_localizer("shape", plan, np.array([1.5, 0.0, 0.0]), laser_odometry=False)
        assert isinstance(loc, GlobalShapeLocalizer)
        statuses = []
        for _ in range(4):
            est = loc.update(r, a, np.zeros(3), from_scans=from_scans)
            statuses.append(est.status)
            assert est.extras.get("rejected") is None or from_scans
        if from_scans:
            # the first scan starts the dead-reckoned reference; from the next on the slid
            # pose is no longer published as tracking, and a search starts once lost_after
            # scans in a row contradicted it
            assert statuses[0] == "tracking", statuses
            assert "tracking" not in statuses[1:], statuses
            assert est.state == "searching", est.state
        else:
            assert statuses == ["tracking"] * 4, statuses
            assert float(loc.pose[0]) > 0.5  # tracking, and still more than 0.5 m off


def test_only_a_reading_measured_from_the_scans_is_marked_so() -> None:
    """The wrapper tells the localiser which readings it measured from the scans: a scan
    without odometry's, not a wheel odometry's."""
    seen: list[bool] = []

    class Marked(_Recorder):
        def update(
            self, ranges: np.ndarray, angles: np.ndarray, odom: Any = None, from_scans: bool = False
        ) -> Estimate:
            seen.append(from_scans)
            return super().update(ranges, angles, odom)

    (s0, a0), (s1, a1), (s2, a2) = _scans(
        _ROOM, [np.array([-1.0, -0.5, 0.0]), np.array([-0.9, -0.5, 0.0]), np.zeros(3)]
    )
    loc = LaserOdometryLocalizer(Marked())  # type: ignore[arg-type]
    loc.update(s0, a0, None)
    loc.update(s1, a1, None)
    loc.update(s2, a2, np.array([0.2, 0.0, 0.0]))
    assert seen == [True, True, False]


def test_a_wall_far_ahead_measures_the_motion_along_a_corridor() -> None:
    """A corridor 2 m wide closed by a wall 12 m ahead, a 1-degree laser (returns on that
    wall 0.21 m apart): the wall's points get surface normals and measure the 0.1 m the robot
    moved along the axis. With a 0.2 m neighbourhood (a wheel odometry check's) they got
    none, and the increment along the axis was the constant-velocity guess, here none."""
    walls = np.array([[-30.0, -1.0, 12.0, -1.0], [12.0, -1.0, 12.0, 1.0], [12.0, 1.0, -30.0, 1.0]])
    truth = np.array([0.1, 0.0, 0.0])
    angles = np.linspace(-math.pi / 2.0, math.pi / 2.0, 181)
    caster = RayCaster(walls)
    scans = [(caster.cast(p, angles, 30.0), angles) for p in (np.zeros(3), truth)]
    default = config_for_kind("schematic")
    narrow = default.model_copy(
        update={"fit": default.fit.model_copy(update={"normal_radius": 0.2})}
    )
    errors = []
    for cfg in (default, narrow):
        lo = LaserOdometry(cfg)
        lo.step(*scans[0])
        step = lo.step(*scans[1])
        assert step is not None and step.matched
        errors.append(abs(float(step.delta[0] - truth[0])))
    assert errors[0] < 0.02, errors
    assert errors[1] > 0.08, errors
