"""One ROS 2 robot (one namespace) as the front sees it: tf, waiting scans, configuration,
and the translation between its ROS 2 messages and shapeloc's wire. No I/O here: methods
take decoded messages and return the wire messages to put; :mod:`service.ros2.front` moves
the bytes.

Frames. ROS robots publish the odometry of their base (``odom -> base_link`` on tf, or
``nav_msgs/Odometry``) and the laser's mounting (``base_link -> <scan frame>`` on
``tf_static``); nav2 expects the base's pose back. When the wire's ``RobotConfig`` carries
``laser_offset`` (the laser's pose in the base frame), the front puts the base's odometry and
the mounting and the service answers with base poses. Until then (:data:`OFFSET_IN_CONFIG`
false) the front does that composition itself, so the service sees the laser as the robot
origin, as the wire defines it: the scan's ``odom`` is the laser's odometry pose
(``odom_base ∘ mount``), an initial pose becomes the laser's (``base ∘ mount``), and each
answer is turned back into the base's pose (``laser ∘ mount⁻¹``, its covariance carried
through the same change of reference point).
"""

from __future__ import annotations

import math
import time
from collections import OrderedDict, deque
from dataclasses import dataclass, field

import numpy as np

from schemas import keys
from schemas.messages import Map, PoseMsg, RobotConfig, Scan, WireModel
from schemas.ros2.cdr import (
    Grid,
    LaserScan,
    Odometry2D,
    PoseWithCovariance2D,
    Stamp,
    Transform2D,
)
from service.adapters.convert import map_message_of
from service.adapters.maps.grid import OccupancyGrid, grid_to_map
from service.core.pose import compose, invert
from service.errors import InvalidMessage
from service.ros2.options import Ros2Options
from service.ros2.tf import Pose2, TfBuffer, TfError, TfWait

#: Whether the wire's RobotConfig carries the laser's mounting (see the module docstring).
OFFSET_IN_CONFIG: bool = "laser_offset" in RobotConfig.model_fields
#: Scans whose answers can still be matched to their stamp and odometry.
MAX_SENT = 512


@dataclass(frozen=True)
class Sent:
    """What the front put for one scan: its exact ROS stamp, the base's odometry pose at it
    (``None`` without odometry) and the laser's mounting in the base frame."""

    stamp: Stamp
    stamp_s: float
    odom_base: Pose2 | None
    mount: Pose2


@dataclass
class Counters:
    """Per-robot traffic counts (logged by the front)."""

    scans_in: int = 0
    scans_out: int = 0
    dropped: dict[str, int] = field(default_factory=dict)
    poses_out: int = 0

    def drop(self, why: str) -> None:
        self.dropped[why] = self.dropped.get(why, 0) + 1


def grid_map(grid: Grid, map_id: str) -> Map:
    """The wire map of a ROS occupancy grid (faces of its occupied cells, metric)."""
    # nav_msgs/OccupancyGrid row 0 lies at the origin; map_server images (and
    # service.adapters.maps.grid) put row 0 at the top
    og = OccupancyGrid(np.flipud(grid.data), grid.resolution, grid.origin)
    return map_message_of(grid_to_map(og, map_id))


def base_covariance(cov: np.ndarray, laser: Pose2, mount: Pose2) -> np.ndarray:
    """Covariance of ``base = laser ∘ mount⁻¹`` given that of ``laser`` (first order)."""
    inv = invert(np.asarray(mount, dtype=np.float64))
    th = laser[2]
    c, s = math.cos(th), math.sin(th)
    # d(base_xy)/d(theta) = R'(theta) @ inv_xy
    dx = -s * inv[0] - c * inv[1]
    dy = c * inv[0] - s * inv[1]
    jac = np.array([[1.0, 0.0, dx], [0.0, 1.0, dy], [0.0, 0.0, 1.0]])
    return jac @ np.asarray(cov, dtype=np.float64).reshape(3, 3) @ jac.T


class RosRobot:
    """State of one namespace. ``config`` is ``unknown`` until the service was asked,
    ``shapeloc`` when shapeloc holds a configuration of its own, ``none`` when it holds none,
    ``ros`` once the front put one from ROS data."""

    def __init__(self, namespace: str, robot_id: str, options: Ros2Options) -> None:
        self.namespace = namespace
        self.robot_id = robot_id
        self.o = options
        self.tf = TfBuffer()
        self.pending: deque[tuple[LaserScan, float]] = deque()
        self.sent: OrderedDict[int, Sent] = OrderedDict()
        self.seq = 0
        self.config = "unknown"
        self.shapeloc_config: RobotConfig | None = None
        self.own_grid: Grid | None = None
        self.initial_pose: PoseWithCovariance2D | None = None
        self._initial_pending = False
        self._put_map: object | None = None  # the grid last put as a map
        self._configured_with: tuple[object, ...] | None = None
        self.first_scan_at: float | None = None
        #: A configuration was put and the service has not shown it holds it yet.
        self.awaiting_ack = False
        self.probe_at = 0.0
        self.counters = Counters()
        #: The last tracked ``map -> odom`` (base frames), re-stamped while the robot is not
        #: tracking; forgotten with a new initial pose.
        self.map_odom: np.ndarray | None = None

    # ----------------------------------------------------------------- inputs
    def on_tf(self, transforms: tuple[Transform2D, ...], static: bool) -> None:
        """Transforms from ``tf`` (timed) or ``tf_static``."""
        for tr in transforms:
            if static:
                self.tf.set_static(tr.parent, tr.child, tr.pose)
            else:
                self.tf.add(tr.parent, tr.child, tr.stamp.nanoseconds, tr.pose, "tf")

    def on_odometry(self, od: Odometry2D) -> None:
        """``nav_msgs/Odometry``: used only while no tf carries the same edge."""
        if self.tf.has_edge(od.child_frame_id, "tf") or self.tf.has_edge(
            od.child_frame_id, "static"
        ):
            return
        self.tf.add(
            od.frame_id, od.child_frame_id, od.stamp.nanoseconds, (od.x, od.y, od.yaw), "odom"
        )

    def on_initial_pose(self, pose: PoseWithCovariance2D) -> None:
        """``initialpose`` (RViz's "2D Pose Estimate"), the base's pose in the map frame."""
        if pose.frame_id != self.o.global_frame_id:
            raise InvalidMessage(
                f"initialpose: frame {pose.frame_id!r} is not the global frame "
                f"{self.o.global_frame_id!r}"
            )
        self.initial_pose = pose
        self._initial_pending = True
        self.map_odom = None

    def on_scan(self, scan: LaserScan, now: float) -> None:
        """Queue a scan until its transforms and the robot's configuration are there."""
        self.counters.scans_in += 1
        if self.first_scan_at is None:
            self.first_scan_at = now
        self.pending.append((scan, now))
        while len(self.pending) > self.o.max_pending:
            self.pending.popleft()
            self.counters.drop("queue full")

    # ----------------------------------------------------------------- configuration
    @property
    def configured(self) -> bool:
        """Whether scans may go to the service."""
        if self.awaiting_ack:
            return False
        return self.config == "shapeloc" or (
            self.config == "ros" and self._configured_with is not None
        )

    def mount(self, frame: str, t_ns: int) -> Pose2:
        """The laser frame's pose in the base frame (raises TfWait / TfError)."""
        m = self.tf.lookup(self.o.base_frame_id, frame, t_ns)
        return m

    def _last_mount(self) -> Pose2 | None:
        for s in reversed(self.sent.values()):
            return s.mount
        if self.pending:
            scan = self.pending[-1][0]
            try:
                return self.mount(scan.frame_id, scan.stamp.nanoseconds)
            except TfError:
                return None
        return None

    def _config_message(self, map_id: str, method: str) -> RobotConfig | None:
        """The configuration to put, or None while no scan has named the laser frame (its
        mounting is needed to put the initial pose, or the ``laser_offset``)."""
        pose = None
        extra: dict[str, object] = {}
        mount = self._last_mount()
        if mount is None:  # configure once a scan names the laser frame: its mounting is known
            return None
        if self.initial_pose is not None:
            base = (self.initial_pose.x, self.initial_pose.y, self.initial_pose.yaw)
            if OFFSET_IN_CONFIG:
                pose = list(base)
            else:
                pose = [float(v) for v in compose(np.asarray(base), np.asarray(mount))]
        if OFFSET_IN_CONFIG:
            extra["laser_offset"] = [float(v) for v in mount]
        return RobotConfig(map_id=map_id, method=method, initial_pose=pose, **extra)

    def plan_config(
        self, global_grid: Grid | None, global_map_put: bool
    ) -> list[tuple[str, WireModel]]:
        """Configuration (and map) messages to put now, given what has been received."""
        prefix = self.o.prefix
        out: list[tuple[str, WireModel]] = []
        if self.config == "shapeloc":
            cfg0 = self.shapeloc_config
            if cfg0 is None:
                return out
            if self._initial_pending:
                cfg = self._config_message(cfg0.map_id, cfg0.method)
                if cfg is not None:
                    out.append((keys.robot_key(prefix, self.robot_id, "config"), cfg))
                    self.shapeloc_config = cfg
                    self._initial_pending = False
            elif OFFSET_IN_CONFIG:
                # shapeloc's own configuration, with the mounting tf_static gives
                mount = self._last_mount()
                offset = getattr(cfg0, "laser_offset", None)
                if mount is not None and (
                    offset is None or not np.allclose(offset, mount, atol=1e-9)
                ):
                    cfg = RobotConfig(
                        map_id=cfg0.map_id, method=cfg0.method,
                        initial_pose=None if cfg0.initial_pose is None else list(cfg0.initial_pose),
                        laser_offset=[float(v) for v in mount],
                    )  # fmt: skip
                    out.append((keys.robot_key(prefix, self.robot_id, "config"), cfg))
                    self.shapeloc_config = cfg
            return out
        if self.config not in ("none", "ros") or not self.o.import_maps:
            return out
        if self.own_grid is not None:
            grid, map_id = self.own_grid, self.robot_id
            if self._put_map is not grid:
                out.append((keys.map_key(prefix, map_id), grid_map(grid, map_id)))
                self._put_map = grid
        elif global_grid is not None and global_map_put:
            grid, map_id = global_grid, self.o.global_map_id
        else:
            return out
        state = (map_id, id(grid), id(self.initial_pose))
        if self._configured_with != state or self._initial_pending:
            cfg = self._config_message(map_id, self.o.method)
            if cfg is not None:
                out.append((keys.robot_key(prefix, self.robot_id, "config"), cfg))
                self._configured_with = state
                self._initial_pending = False
                self.config = "ros"
        return out

    # ----------------------------------------------------------------- scans out
    def ready_scans(self, now: float | None = None) -> tuple[list[Scan], list[str]]:
        """The waiting scans that can go now, as wire scans (oldest first), and the reasons
        of those that are not valid wire scans; drops those that waited longer than
        ``scan_wait`` or whose transforms cannot exist."""
        now = time.monotonic() if now is None else now
        out: list[Scan] = []
        errors: list[str] = []
        o = self.o
        while self.pending:
            scan, arrived = self.pending[0]
            late = now - arrived > o.scan_wait
            if not self.configured:
                if late:
                    self._drop("no configuration")
                    continue
                break
            t = scan.stamp.nanoseconds
            try:
                mount = self.mount(scan.frame_id, t)
                odom = self._odometry(t, now)
            except TfWait:
                if late:
                    self._drop("transforms did not arrive")
                    continue
                break
            except TfError:
                self._drop("no transform at the scan's stamp")
                continue
            if odom is _WAIT:
                break
            self.pending.popleft()
            try:
                out.append(self._wire_scan(scan, mount, odom))  # type: ignore[arg-type]
            except InvalidMessage as exc:
                self.counters.drop("not a valid wire scan")
                errors.append(str(exc))
        return out, errors

    def _drop(self, why: str) -> None:
        self.pending.popleft()
        self.counters.drop(why)

    def _odometry(self, t_ns: int, now: float) -> Pose2 | object | None:
        o = self.o
        if o.odom_frame_id in self.tf.frames():
            return self.tf.lookup(o.odom_frame_id, o.base_frame_id, t_ns)
        if self.first_scan_at is not None and now - self.first_scan_at < o.odom_wait:
            return _WAIT
        return None

    def _wire_scan(self, scan: LaserScan, mount: Pose2, odom_base: Pose2 | None) -> Scan:
        seq = self.seq
        self.seq += 1
        odom = odom_base
        if odom_base is not None and not OFFSET_IN_CONFIG:
            odom = tuple(compose(np.asarray(odom_base), np.asarray(mount)))  # type: ignore[assignment]
        msg = Scan(
            seq=seq,
            stamp=scan.stamp.seconds(),
            angle_min=scan.angle_min,
            angle_increment=scan.angle_increment,
            range_min=scan.range_min,
            range_max=scan.range_max,
            ranges=scan.ranges,
            odom=None if odom is None else [float(v) for v in odom],
        )
        self.sent[seq] = Sent(scan.stamp, msg.stamp, odom_base, mount)
        while len(self.sent) > MAX_SENT:
            self.sent.popitem(last=False)
        self.counters.scans_out += 1
        return msg

    # ----------------------------------------------------------------- answers
    def answer(
        self, pose: PoseMsg
    ) -> tuple[PoseWithCovariance2D | None, Transform2D | None] | None:
        """``amcl_pose`` and the ``map -> odom`` transform for an estimate of the service;
        None when it answers no scan this front put. An estimate that is not ``tracking``
        gets no ``amcl_pose``, only the last ``map -> odom`` stamped anew (as AMCL republishes
        its last transform on every scan): the robot's pose in ``map`` then follows its
        odometry, the localiser's dead reckoning, and tf listeners do not time out. Before
        the first tracked estimate, nothing."""
        sent = self.sent.get(pose.seq)
        if sent is None or abs(pose.stamp - sent.stamp_s) > 1e-6:
            return None
        if pose.status != "tracking":
            if self.map_odom is None or sent.odom_base is None:
                return None
            return None, self._map_odom_tf(sent, self.map_odom)
        p = np.asarray(pose.pose, dtype=np.float64)
        cov = (
            np.asarray(pose.covariance, dtype=np.float64)
            if pose.covariance is not None
            else np.zeros((3, 3))
        )
        if OFFSET_IN_CONFIG:
            base = p
        else:
            base = compose(p, invert(np.asarray(sent.mount)))
            cov = base_covariance(cov, (p[0], p[1], p[2]), sent.mount)
        o = self.o
        amcl = PoseWithCovariance2D(
            sent.stamp, o.global_frame_id, float(base[0]), float(base[1]), float(base[2]), cov
        )
        tf = None
        if sent.odom_base is not None:
            self.map_odom = compose(base, invert(np.asarray(sent.odom_base)))
            tf = self._map_odom_tf(sent, self.map_odom)
        self.counters.poses_out += 1
        return amcl, tf

    def _map_odom_tf(self, sent: Sent, m: np.ndarray) -> Transform2D:
        """``map -> odom`` = ``m``, stamped ``transform_tolerance`` after the scan, as AMCL."""
        o = self.o
        stamp = Stamp.from_nanoseconds(sent.stamp.nanoseconds + round(o.transform_tolerance * 1e9))
        return Transform2D(
            stamp, o.global_frame_id, o.odom_frame_id, float(m[0]), float(m[1]), float(m[2])
        )


_WAIT = object()
