"""Simulated robots and replayed logs as ROS 2 robots on rmw_zenoh's keys.

``shapeloc-sim run --ros2`` and ``shapeloc-sim replay --ros2`` publish what a ROS 2 robot
with rmw_zenoh would, in a namespace per robot and with no shapeloc code on the robot's
side: ``/<ns>/scan`` (``sensor_msgs/LaserScan``, frame ``laser``), ``/<ns>/tf``
(``odom -> base_link`` at each scan's stamp) and ``/<ns>/tf_static`` (``base_link ->
laser``, transient local), each with rmw_zenoh's attachment and the node's liveliness tokens;
the robot listens to ``/<ns>/amcl_pose`` and ``/<ns>/tf`` as nav2 would. How it gets its map
and initial pose: ``shapeloc`` puts them as today (map, robot configuration); ``ros``
publishes ``/<ns>/map`` (the map rasterised to an occupancy grid) and ``/<ns>/initialpose``
instead, as a ROS 2 user with map_server and RViz would.

Frames. The simulator's laser sits at its robot's origin; as a ROS 2 robot it is mounted at
``mount`` (the laser's pose in ``base_link``, default 0.1 m ahead), so ``base_link`` is
``laser ∘ mount⁻¹``: odometry, initial pose and the ground truth put on
``<prefix>/robots/<id>/truth`` (evaluation only) are the base's. A replayed log's mounting is
its own (``LogInfo.laser_offset``).
"""

from __future__ import annotations

import contextlib
import itertools
import logging
import math
import queue
import re
import sys
import threading
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import zenoh

from schemas import keys
from schemas.codec import MSGPACK_ENCODING, encode
from schemas.messages import RobotConfig, Truth
from schemas.ros2 import cdr, graph
from schemas.ros2.cdr import Grid, LaserScan, PoseWithCovariance2D, Stamp, Transform2D
from schemas.ros2.types import LASER_SCAN, OCCUPANCY_GRID, POSE_WITH_COVARIANCE_STAMPED, TF_MESSAGE
from service.core.pose import compose, invert
from service.core.types import MapData
from service.errors import InvalidMessage
from service.ros2.options import domain_from_env
from service.ros2.robot import OFFSET_IN_CONFIG
from service.ros2.rosnode import EntityCounter, RosNode

log = logging.getLogger("shapeloc.sim.ros2")

CONFIG_SOURCES = ("shapeloc", "ros")


@dataclass(frozen=True)
class Ros2SimOptions:
    """How a simulated robot appears as a ROS 2 robot (frames, mounting, domain)."""

    domain_id: int = 0
    node_name: str = "sim_robot"
    base_frame: str = "base_link"
    odom_frame: str = "odom"
    laser_frame: str = "laser"
    global_frame: str = "map"
    #: Laser pose in the base frame (m, m, rad) of a simulated robot.
    mount: tuple[float, float, float] = (0.1, 0.0, 0.0)
    #: Where the map and initial pose come from: ``shapeloc`` or ``ros``.
    config_source: str = "shapeloc"
    #: Cell size (m) of the occupancy grid a ``ros`` robot publishes.
    map_resolution: float = 0.05

    def __post_init__(self) -> None:
        if self.config_source not in CONFIG_SOURCES:
            raise ValueError(f"--ros2-config must be one of {', '.join(CONFIG_SOURCES)}")
        if not 0.005 <= self.map_resolution <= 1.0:
            raise ValueError("the map resolution must lie in [0.005, 1] m")
        graph.check_domain(self.domain_id)


def namespace_for(robot_id: str) -> str:
    """The ROS namespace of a simulated robot id (``sim-0`` -> ``/sim_0``)."""
    token = re.sub(r"[^A-Za-z0-9_]", "_", robot_id)
    if not token or token[0].isdigit():
        token = "r" + token
    return "/" + token


def rasterise(map_data: MapData, resolution: float, margin: float = 1.0) -> Grid:
    """An occupancy grid (100 on the map's lines, 0 elsewhere; row 0 at the origin) of the
    polylines of ``map_data``, cells of ``resolution`` metres, ``margin`` around them."""
    pts = np.vstack(map_data.polylines)
    x0, y0 = pts.min(axis=0) - margin
    x1, y1 = pts.max(axis=0) + margin
    w = math.ceil((x1 - x0) / resolution)
    h = math.ceil((y1 - y0) / resolution)
    data = np.zeros((h, w), dtype=np.int8)
    for poly in map_data.polylines:
        for a, b in itertools.pairwise(poly):
            n = max(2, math.ceil(np.hypot(*(b - a)) / (0.25 * resolution)) + 1)
            t = np.linspace(0.0, 1.0, n)[:, None]
            p = a + t * (b - a)
            cols = np.clip(((p[:, 0] - x0) / resolution).astype(int), 0, w - 1)
            rows = np.clip(((p[:, 1] - y0) / resolution).astype(int), 0, h - 1)
            data[rows, cols] = 100
    return Grid(Stamp(0, 0), "map", resolution, (float(x0), float(y0), 0.0), data)


def config_for(
    map_id: str, method: str, laser_pose: Sequence[float] | None, mount: Sequence[float]
) -> RobotConfig:
    """The shapeloc configuration of a ROS 2 robot whose laser starts at ``laser_pose``: with
    the wire's ``laser_offset`` the base's pose and the mounting, else the laser's pose (the
    front then composes the mounting, docs/ros2.md)."""
    if not OFFSET_IN_CONFIG:
        pose = None if laser_pose is None else [float(v) for v in laser_pose]
        return RobotConfig(map_id=map_id, method=method, initial_pose=pose)
    base = None
    if laser_pose is not None:
        base = [float(v) for v in compose(np.asarray(laser_pose), invert(np.asarray(mount)))]
    return RobotConfig(
        map_id=map_id, method=method, initial_pose=base, laser_offset=[float(v) for v in mount]
    )


class Ros2Robot:
    """A ROS 2 robot's traffic on ``session``: node ``node_name`` in ``namespace``."""

    def __init__(
        self,
        session: zenoh.Session,
        namespace: str,
        options: Ros2SimOptions,
        counter: EntityCounter | None = None,
    ) -> None:
        self.o = options
        self.namespace = namespace
        self.node = RosNode(
            session, options.domain_id, namespace, options.node_name, counter or EntityCounter()
        )
        self.scan_pub = self.node.publisher("scan", LASER_SCAN, graph.SENSOR_DATA_QOS)
        self.tf_pub = self.node.publisher("tf", TF_MESSAGE, graph.TF_QOS)
        self.static_pub = self.node.publisher("tf_static", TF_MESSAGE, graph.LATCHED_QOS)
        self._map_pub: Any = None
        self._init_pub: Any = None
        #: amcl_pose answers by the scan stamp (integer ns) they carry.
        self.answers: dict[int, PoseWithCovariance2D] = {}
        #: map -> odom transforms received on tf.
        self.map_to_odom: list[Transform2D] = []
        self._arrived: queue.Queue[int] = queue.Queue()
        self.node.subscriber(
            "amcl_pose", POSE_WITH_COVARIANCE_STAMPED, graph.LATCHED_QOS, self._on_amcl
        )
        self.node.subscriber("tf", TF_MESSAGE, graph.TF_QOS, self._on_tf)

    def _on_amcl(self, sample: Any) -> None:
        try:
            msg = cdr.decode_pose_with_covariance(sample.payload.to_bytes())
        except InvalidMessage as exc:
            log.warning("%s: bad amcl_pose: %s", self.namespace, exc)
            return
        self.answers[msg.stamp.nanoseconds] = msg
        self._arrived.put(msg.stamp.nanoseconds)

    def _on_tf(self, sample: Any) -> None:
        try:
            trs = cdr.decode_tf(sample.payload.to_bytes())
        except InvalidMessage:
            return
        self.map_to_odom.extend(
            t for t in trs if t.parent == self.o.global_frame and t.child == self.o.odom_frame
        )

    def publish_static(self, mount: Sequence[float]) -> None:
        """``base_link -> laser`` on tf_static (transient local: late joiners get it)."""
        x, y, yaw = (float(v) for v in mount)
        tr = Transform2D(Stamp(0, 0), self.o.base_frame, self.o.laser_frame, x, y, yaw)
        self.static_pub.put(cdr.encode_tf([tr]))

    def publish_map(self, map_data: MapData) -> Grid:
        """The map, rasterised, on ``/<ns>/map`` (transient local, as map_server)."""
        if self._map_pub is None:
            self._map_pub = self.node.publisher("map", OCCUPANCY_GRID, graph.LATCHED_QOS)
        grid = rasterise(map_data, self.o.map_resolution)
        self._map_pub.put(cdr.encode_occupancy_grid(grid))
        return grid

    def publish_initial_pose(self, base: Sequence[float], stamp: Stamp) -> None:
        """The base's initial pose on ``/<ns>/initialpose`` (as RViz's 2D Pose Estimate)."""
        if self._init_pub is None:
            self._init_pub = self.node.publisher(
                "initialpose", POSE_WITH_COVARIANCE_STAMPED, graph.SYSTEM_DEFAULT_QOS
            )
        cov = np.diag([0.25, 0.25, 0.07])
        x, y, yaw = (float(v) for v in base)
        msg = PoseWithCovariance2D(stamp, self.o.global_frame, x, y, yaw, cov)
        self._init_pub.put(cdr.encode_pose_with_covariance(msg))

    def publish_scan(
        self,
        stamp: Stamp,
        angle_min: float,
        angle_increment: float,
        range_min: float,
        range_max: float,
        ranges: np.ndarray,
        odom_base: Sequence[float] | None,
    ) -> None:
        """``odom -> base_link`` at ``stamp`` on tf (unless None), then the scan."""
        if odom_base is not None:
            x, y, yaw = (float(v) for v in odom_base)
            tr = Transform2D(stamp, self.o.odom_frame, self.o.base_frame, x, y, yaw)
            self.tf_pub.put(cdr.encode_tf([tr]))
        r = np.asarray(ranges, dtype=np.float64)
        scan = LaserScan(
            stamp, self.o.laser_frame, angle_min, angle_increment, range_min, range_max, r
        )
        self.scan_pub.put(cdr.encode_laser_scan(scan))

    def wait_answer(self, stamp: Stamp, within: float, stop: threading.Event) -> bool:
        """Lockstep: wait until the amcl_pose of ``stamp`` arrived (or ``within`` s)."""
        end = time.monotonic() + within
        while stamp.nanoseconds not in self.answers and not stop.is_set():
            left = end - time.monotonic()
            if left <= 0:
                return False
            with contextlib.suppress(queue.Empty):
                self._arrived.get(timeout=min(left, 0.2))
        return stamp.nanoseconds in self.answers

    def close(self) -> None:
        self.node.close()


def _truth_put(
    session: zenoh.Session, prefix: str, rid: str, seq: int, stamp: float, base: Sequence[float]
) -> None:
    truth = Truth(seq=seq, stamp=stamp, pose=[float(v) for v in base])
    session.put(
        keys.robot_key(prefix, rid, "truth"),
        encode(truth),
        encoding=zenoh.Encoding(MSGPACK_ENCODING),
        congestion_control=zenoh.CongestionControl.BLOCK,
    )


def _put_config(session: zenoh.Session, prefix: str, rid: str, cfg: RobotConfig) -> None:
    session.put(
        keys.robot_key(prefix, rid, "config"),
        encode(cfg),
        encoding=zenoh.Encoding(MSGPACK_ENCODING),
        congestion_control=zenoh.CongestionControl.BLOCK,
    )


def robot_id(namespace: str) -> str:
    """The robot id the front gives this namespace."""
    return graph.robot_id_of_namespace(namespace, "robot")


def default_options(
    domain_id: int | None = None, config_source: str = "shapeloc", node_name: str = "sim_robot"
) -> Ros2SimOptions:
    """Options with the domain of ``ROS_DOMAIN_ID`` unless given."""
    dom = domain_from_env() if domain_id is None else domain_id
    return Ros2SimOptions(domain_id=dom, config_source=config_source, node_name=node_name)


def steps(n: int | None) -> Iterator[int]:
    """0, 1, ... (up to ``n`` exclusive, forever without)."""
    k = 0
    while n is None or k < n:
        yield k
        k += 1


def run_fleet(
    conf: zenoh.Config,
    options: Any,
    stop: threading.Event | None = None,
    endpoints: Sequence[str] = (),
    ros: Ros2SimOptions | None = None,
) -> int:
    """``shapeloc-sim run --ros2``: the fleet of ``options`` (a ``SimOptions``) as ROS 2
    robots, one namespace each (:func:`namespace_for`); returns the exit code."""
    from clients.client import ShapelocClient, open_session
    from sim_publisher.networked import wait_service
    from sim_publisher.publisher import SimFleet, fleet_specs

    ros = ros or default_options()
    stop = stop or threading.Event()
    fleet = SimFleet.from_specs(
        fleet_specs(
            options.robots, options.maps, options.methods, setup=options.setup,
            step_mm=options.step_mm, seed=options.seed, starts=options.starts,
            id_prefix=options.id_prefix,
        ),
        global_localization=options.global_localization,
        send_odom=options.odom,
    )  # fmt: skip
    offset = getattr(options, "laser_offset", None)
    mount = np.asarray(ros.mount if offset is None else offset, dtype=np.float64)
    with open_session(conf, endpoints) as session:
        client = ShapelocClient(session=session, prefix=options.prefix, timeout=2.0)
        counter = EntityCounter()
        robots: list[tuple[Any, str, Ros2Robot]] = []
        try:
            up = options.wait_service > 0 and wait_service(client, options.wait_service, stop)
            if ros.config_source == "shapeloc" and options.configure and options.put_maps:
                for m in fleet.map_messages():
                    client.put_map(m, confirm=up)
            for r in fleet.robots:
                ns = namespace_for(r.robot_id)
                rid = robot_id(ns)
                if ros.config_source == "shapeloc" and options.configure:
                    laser0 = r.config().initial_pose
                    cfg = config_for(r.map_id, r.method, laser0, mount)
                    _put_config(session, options.prefix, rid, cfg)
                    if up:
                        client.wait_configured(rid, options.wait_service)
                robot = Ros2Robot(session, ns, ros, counter)
                robot.publish_static(mount)
                if ros.config_source == "ros":
                    robot.publish_map(fleet.maps[r.map_id])
                    if not options.global_localization:
                        laser0 = np.asarray(r.start_pose)
                        base0 = compose(laser0, invert(mount))
                        robot.publish_initial_pose(base0, Stamp.from_seconds(time.time()))
                robots.append((r, rid, robot))
                log.info("ROS 2 robot %s in %s (%s configuration)", rid, ns, ros.config_source)
            if ros.config_source == "ros":
                stop.wait(0.5)  # the front imports the map before the first scans
            return _ros_loop(session, robots, options, mount, stop)
        finally:
            for _, _, robot in robots:
                robot.close()
            client.close()


def _ros_loop(
    session: zenoh.Session,
    robots: list[tuple[Any, str, Ros2Robot]],
    options: Any,
    mount: np.ndarray,
    stop: threading.Event,
) -> int:
    inv = invert(mount)
    period = 0.0 if options.max_rate else 1.0 / options.rate
    t0 = next_tick = time.monotonic()
    sent = missed = 0
    for k in steps(options.scans):
        if stop.is_set() or (
            options.duration is not None and time.monotonic() - t0 >= options.duration
        ):
            break
        stamp = Stamp.from_seconds(time.time())
        for r, rid, robot in robots:
            scan, truth = r.step(stamp.seconds())
            odom = None if scan.odom is None else compose(np.asarray(scan.odom), inv)
            _truth_put(
                session, options.prefix, rid, k, scan.stamp, compose(np.asarray(truth.pose), inv)
            )
            robot.publish_scan(
                stamp, scan.angle_min, scan.angle_increment, scan.range_min, scan.range_max,
                scan.ranges, odom,
            )  # fmt: skip
        if options.lockstep:
            for _r, rid, robot in robots:
                if not robot.wait_answer(stamp, options.lockstep_timeout, stop):
                    missed += 1
                    log.warning("lockstep: no amcl_pose for scan %d of %s", k, rid)
        sent += 1
        if period > 0:
            next_tick += period
            delay = next_tick - time.monotonic()
            if delay > 0:
                stop.wait(delay)
            else:
                next_tick = time.monotonic()
    stop.wait(0.3)  # the last answers
    for _r, rid, robot in robots:
        log.info(
            "%s: %d scans, %d amcl_pose answers, %d map->odom transforms",
            rid, sent, len(robot.answers), len(robot.map_to_odom),
        )  # fmt: skip
    return 0


def replay_log(
    conf: zenoh.Config,
    options: Any,
    stop: threading.Event | None = None,
    endpoints: Sequence[str] = (),
    ros: Ros2SimOptions | None = None,
) -> int:
    """``shapeloc-sim replay --ros2``: the log of ``options`` (a ``ReplayOptions``) as a ROS 2
    robot in namespace ``/<--robot>`` (odometry on tf at each scan's stamp, the log's laser
    mounting on tf_static); the reference poses go on the truth key as the base's."""
    from clients.client import ShapelocClient, open_session
    from sim_publisher.networked import wait_service
    from sim_publisher.replay import initial_pose_for, open_replay

    ros = ros or default_options()
    stop = stop or threading.Event()
    info, scans = open_replay(options)
    first = next(scans, None)
    ns = graph.namespace_of_robot_id(options.robot)
    rid = robot_id(ns)
    given = getattr(options, "laser_offset", None)
    mount = np.asarray(info.laser_offset if given is None else given, dtype=np.float64)
    inv = invert(mount)
    with open_session(conf, endpoints) as session:
        client = ShapelocClient(session=session, prefix=options.prefix, timeout=2.0)
        robot: Ros2Robot | None = None
        try:
            up = options.wait_service > 0 and wait_service(client, options.wait_service, stop)
            if options.configure:
                laser0 = initial_pose_for(options, first)
                cfg = config_for(options.map_id, options.method, laser0, mount)
                _put_config(session, options.prefix, rid, cfg)
                if up:
                    client.wait_configured(rid, options.wait_service)
            robot = Ros2Robot(session, ns, ros)
            robot.publish_static(mount)
            stop.wait(0.2)  # tf_static before the first scan
            t_wall0 = stamp0 = None
            sent = 0
            all_scans = [] if first is None else [first]
            for scan in _chain(all_scans, scans):
                if stop.is_set():
                    break
                if options.speed is not None:
                    if t_wall0 is None or stamp0 is None:
                        t_wall0, stamp0 = time.monotonic(), scan.stamp
                    delay = t_wall0 + (scan.stamp - stamp0) / options.speed - time.monotonic()
                    if delay > 0 and stop.wait(delay):
                        break
                stamp = Stamp.from_seconds(scan.stamp)
                odom = None
                if options.odom and scan.odom is not None:
                    odom = compose(np.asarray(scan.odom), inv)
                if scan.reference is not None and scan.reference_ok:
                    base = compose(np.asarray(scan.reference), inv)
                    _truth_put(session, options.prefix, rid, scan.index, stamp.seconds(), base)
                robot.publish_scan(
                    stamp, scan.angle_min, scan.angle_increment, scan.range_min,
                    scan.range_max, scan.ranges, odom,
                )  # fmt: skip
                sent += 1
                if options.lockstep and not robot.wait_answer(
                    stamp, options.lockstep_timeout, stop
                ):
                    log.warning("lockstep: no amcl_pose for scan %d", scan.index)
            stop.wait(0.5)
            log.info(
                "replay %s as ROS 2 robot %s: %d scans, %d amcl_pose answers",
                options.log.name, ns, sent, len(robot.answers),
            )  # fmt: skip
            print(
                f"replay {options.log.name} as {ns}: {sent} scans, {len(robot.answers)} "
                "amcl_pose answers",
                file=sys.stderr,
            )
        finally:
            if robot is not None:
                robot.close()
            client.close()
    return 0


def _chain(head: list[Any], tail: Iterator[Any]) -> Iterator[Any]:
    yield from head
    yield from tail
