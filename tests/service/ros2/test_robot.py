"""One ROS 2 robot's translation (service/ros2/robot.py): scans wait for their transforms and
configuration, odometry at the scan's stamp, the laser mounting, answers back to the base."""

from __future__ import annotations

import math

import numpy as np
import pytest

from schemas.messages import Map, PoseMsg, RobotConfig
from schemas.ros2.cdr import Grid, LaserScan, PoseWithCovariance2D, Stamp, Transform2D
from service.core.pose import compose, invert
from service.ros2.options import Ros2Options
from service.ros2.robot import OFFSET_IN_CONFIG, RosRobot, base_covariance

S = 1_000_000_000
MOUNT = (0.1, 0.05, 0.2)


def _scan(t_ns: int, frame: str = "laser") -> LaserScan:
    r = np.full(90, 3.0)
    r.setflags(write=False)
    return LaserScan(Stamp.from_nanoseconds(t_ns), frame, -1.5, 0.03, 0.1, 20.0, r)


def _robot(**kw: object) -> RosRobot:
    return RosRobot("/robot1", "robot1", Ros2Options(scan_wait=1.0, odom_wait=0.2, **kw))  # type: ignore[arg-type]


def _odom(robot: RosRobot, t_ns: int, pose: tuple[float, float, float]) -> None:
    robot.on_tf((Transform2D(Stamp.from_nanoseconds(t_ns), "odom", "base_link", *pose),), False)


def test_a_scan_waits_for_configuration_mount_and_odometry() -> None:
    r = _robot()
    r.config, r.shapeloc_config = "shapeloc", RobotConfig(map_id="m", initial_pose=[0, 0, 0])
    t = 5 * S + 123
    r.on_scan(_scan(t), now=0.0)
    assert r.ready_scans(0.0) == ([], [])  # no mount yet
    r.on_tf((Transform2D(Stamp(0, 0), "base_link", "laser", *MOUNT),), True)
    _odom(r, t - S // 10, (1.0, 0.0, 0.0))
    assert r.ready_scans(0.1) == ([], [])  # odometry only before the stamp: wait
    _odom(r, t + S // 10, (2.0, 0.0, 0.0))
    scans, errors = r.ready_scans(0.2)
    assert errors == [] and len(scans) == 1
    base = (1.5, 0.0, 0.0)  # interpolated at the scan's stamp
    want = base if OFFSET_IN_CONFIG else tuple(compose(np.array(base), np.array(MOUNT)))
    assert np.allclose(scans[0].odom, want)
    assert scans[0].seq == 0 and scans[0].stamp == pytest.approx(5.000000123)


def test_scans_are_dropped_when_transforms_never_come() -> None:
    r = _robot()
    r.config, r.shapeloc_config = "shapeloc", RobotConfig(map_id="m")
    r.on_scan(_scan(S), now=0.0)
    assert r.ready_scans(0.5) == ([], [])
    assert r.ready_scans(1.5) == ([], [])
    assert r.counters.dropped == {"transforms did not arrive": 1} and not r.pending


def test_without_any_odometry_scans_go_without_it_after_odom_wait() -> None:
    r = _robot()
    r.config, r.shapeloc_config = "shapeloc", RobotConfig(map_id="m")
    r.on_scan(_scan(S, frame="base_link"), now=0.0)  # laser frame = base frame: no mount
    assert r.ready_scans(0.1) == ([], [])
    scans, _ = r.ready_scans(0.3)
    assert len(scans) == 1 and scans[0].odom is None


def test_the_answer_is_the_base_pose_with_the_scans_exact_stamp_and_map_to_odom() -> None:
    r = _robot(transform_tolerance=0.5)
    r.config, r.shapeloc_config = "shapeloc", RobotConfig(map_id="m")
    r.on_tf((Transform2D(Stamp(0, 0), "base_link", "laser", *MOUNT),), True)
    t = 1_700_000_000 * S + 987_654_321
    _odom(r, t, (3.0, 1.0, 0.3))
    r.on_scan(_scan(t), now=0.0)
    (scan,), _ = r.ready_scans(0.0)
    true_base = np.array([10.0, -4.0, 2.0])
    est = true_base if OFFSET_IN_CONFIG else compose(true_base, np.array(MOUNT))
    cov = np.diag([0.01, 0.02, 0.003])
    pm = PoseMsg(
        robot_id="robot1", seq=scan.seq, stamp=scan.stamp, pose=list(est), status="tracking",
        score=1.0, method="shape", map_id="m", latency_ms=1.0, covariance=cov,
    )  # fmt: skip
    amcl, tf = r.answer(pm)  # type: ignore[misc]
    assert amcl.stamp == Stamp(1_700_000_000, 987_654_321) and amcl.frame_id == "map"
    assert np.allclose((amcl.x, amcl.y, amcl.yaw), true_base)
    assert tf is not None and (tf.parent, tf.child) == ("map", "odom")
    assert tf.stamp == Stamp(1_700_000_001, 487_654_321)
    # map -> odom composed with odom -> base gives the base in the map
    assert np.allclose(compose(np.array(tf.pose), np.array([3.0, 1.0, 0.3])), true_base)
    assert np.allclose(np.diag(amcl.covariance)[[0, 1]] >= [0.01, 0.02], True)
    # an unknown seq: no answer
    assert r.answer(PoseMsg(**{**pm.to_wire(), "seq": 99})) is None
    # not tracking (dead reckoning, a search): no amcl_pose, the last map -> odom re-stamped
    # at the new scan, whatever pose the estimate carries
    t2 = t + S // 10
    _odom(r, t2, (3.5, 1.0, 0.3))
    r.on_scan(_scan(t2), now=0.0)
    (scan2,), _ = r.ready_scans(0.0)
    lost = PoseMsg(
        **{**pm.to_wire(), "seq": scan2.seq, "stamp": scan2.stamp, "status": "lost",
           "pose": [0.0, 0.0, 0.0]}
    )  # fmt: skip
    amcl2, tf2 = r.answer(lost)  # type: ignore[misc]
    assert amcl2 is None and tf2 is not None and tf2.pose == tf.pose
    assert tf2.stamp == Stamp(1_700_000_001, 587_654_321)
    # a new initial pose forgets it: nothing until the next tracked estimate
    r.on_initial_pose(PoseWithCovariance2D(Stamp(0, 0), "map", 1.0, 2.0, 0.0, np.eye(3)))
    assert r.answer(lost) is None


def test_base_covariance_is_the_laser_covariance_moved_to_the_base() -> None:
    cov = np.diag([0.0, 0.0, 0.01])  # only heading uncertainty at the laser
    laser = (0.0, 0.0, 0.0)
    got = base_covariance(cov, laser, (1.0, 0.0, 0.0))  # base 1 m behind the laser
    # a heading error swings the base sideways by 1 m per radian
    assert got[1, 1] == pytest.approx(0.01) and got[0, 0] == pytest.approx(0.0)
    rng = np.random.default_rng(3)
    samples = rng.multivariate_normal(laser, cov, size=20000)
    bases = np.array([compose(s, invert(np.array([1.0, 0.0, 0.0]))) for s in samples])
    assert np.cov(bases.T)[1, 1] == pytest.approx(0.01, rel=0.05)


def test_a_robot_without_shapeloc_configuration_is_configured_from_ros() -> None:
    r = _robot()
    r.config = "none"
    r.on_tf((Transform2D(Stamp(0, 0), "base_link", "laser", *MOUNT),), True)
    data = np.zeros((40, 40), dtype=np.int8)
    data[5, 5:35] = 100
    data[5:35, 5] = 100
    r.own_grid = Grid(Stamp(0, 0), "map", 0.1, (-2.0, -2.0, 0.0), data)
    r.on_scan(_scan(S), now=0.0)
    puts = r.plan_config(None, False)
    assert [k for k, _ in puts] == ["shapeloc/maps/robot1", "shapeloc/robots/robot1/config"]
    assert isinstance(puts[0][1], Map) and puts[0][1].map_id == "robot1"
    cfg = puts[1][1]
    assert isinstance(cfg, RobotConfig) and cfg.initial_pose is None  # global localisation
    assert r.configured and r.plan_config(None, False) == []
    r.on_initial_pose(PoseWithCovariance2D(Stamp(1, 0), "map", 1.0, 2.0, 0.5, np.zeros((3, 3))))
    ((key, cfg2),) = r.plan_config(None, False)
    want = (
        (1.0, 2.0, 0.5) if OFFSET_IN_CONFIG else compose(np.array([1.0, 2.0, 0.5]), np.array(MOUNT))
    )
    assert key.endswith("/config") and np.allclose(cfg2.initial_pose, want)


def test_an_initial_pose_re_puts_shapelocs_own_configuration() -> None:
    r = _robot()
    r.config = "shapeloc"
    r.shapeloc_config = RobotConfig(map_id="office", method="icp", initial_pose=[0, 0, 0])
    r.on_tf((Transform2D(Stamp(0, 0), "base_link", "laser", 0.0, 0.0, 0.0),), True)
    r.on_scan(_scan(S), now=0.0)
    assert r.plan_config(None, False) == []
    r.on_initial_pose(PoseWithCovariance2D(Stamp(1, 0), "map", 4.0, 5.0, -1.0, np.eye(3)))
    ((_, cfg),) = r.plan_config(None, False)
    assert (cfg.map_id, cfg.method) == ("office", "icp")
    assert np.allclose(cfg.initial_pose, (4.0, 5.0, -1.0))
    with pytest.raises(Exception, match="global frame"):
        r.on_initial_pose(PoseWithCovariance2D(Stamp(1, 0), "odom", 0, 0, 0, np.eye(3)))
    assert math.isfinite(cfg.initial_pose[2])
