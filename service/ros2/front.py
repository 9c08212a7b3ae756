"""The ROS 2 front: shapeloc on rmw_zenoh's keys, as nav2's AMCL looks to a ROS 2 robot.

It runs on a Zenoh session (the service's own with ``python -m service --ros2``, or its own
process with ``python -m service.ros2``) and only translates, so it stays apart from the
node's internals:

* ROS 2 in: ``/<ns>/scan``, ``/<ns>/tf``, ``/<ns>/tf_static``, ``/<ns>/odom``,
  ``/<ns>/initialpose``, ``/<ns>/map`` and ``/map`` of every namespace (wildcard
  subscriptions on rmw_zenoh data keys; ``tf_static`` and the maps through Zenoh's advanced
  subscriber with history, as rmw_zenoh's transient-local subscriptions, so late joiners get
  them). The namespace names the robot (:func:`schemas.ros2.graph.robot_id_of_namespace`).
* shapeloc out: ``<prefix>/robots/<id>/scan`` with the odometry at the scan's stamp from the
  tf buffer, and, for a robot shapeloc has no configuration of, ``<prefix>/maps/<id>`` from
  its ROS map and ``<prefix>/robots/<id>/config`` (method, map, initial pose from
  ``initialpose``); with a shapeloc configuration, ``initialpose`` re-puts that one with the
  new pose.
* shapeloc in: ``<prefix>/robots/*/pose`` (a session's own puts reach its own subscribers,
  so this works inside the service process too).
* ROS 2 out: ``/<ns>/amcl_pose`` (the base's pose in the global frame, the scan's stamp, the
  service's covariance; transient local, as AMCL) and ``map -> odom`` on ``/<ns>/tf``; every
  sample with rmw_zenoh's attachment.
* The graph: a node (``--ros-node-name``, default ``shapeloc``) in each namespace with the
  liveliness tokens of its subscriptions and publishers, so ``ros2 node list`` and
  ``ros2 topic list`` on the robot show it.

Zenoh callbacks only queue; one worker thread decodes, keeps the state and publishes. Every
ROS 2 sample is untrusted: a bad one is logged (at most once a second per kind), counted and
published as an ``ErrorNotice`` on ``<prefix>/errors``; the front goes on with the others.
"""

from __future__ import annotations

import contextlib
import logging
import queue
import threading
import time
from typing import Any

import zenoh

from schemas import codec, keys
from schemas.messages import ErrorNotice, PoseMsg, RobotConfig, WireModel
from schemas.ros2 import cdr, graph
from schemas.ros2.attachment import decode_attachment
from schemas.ros2.types import (
    LASER_SCAN,
    OCCUPANCY_GRID,
    ODOMETRY,
    POSE_WITH_COVARIANCE_STAMPED,
    TF_MESSAGE,
    RosType,
)
from service.errors import InvalidMessage
from service.ros2.options import Ros2Options
from service.ros2.robot import RosRobot, grid_map
from service.ros2.rosnode import EntityCounter, RosNode, RosPublisher, subscribe

log = logging.getLogger("shapeloc.ros2")

#: Inputs: topic leaf -> (type, QoS of the subscription token, transient local).
INPUTS: dict[str, tuple[RosType, graph.QoS, bool]] = {
    "scan": (LASER_SCAN, graph.SENSOR_DATA_QOS, False),
    "tf": (TF_MESSAGE, graph.TF_QOS, False),
    "tf_static": (TF_MESSAGE, graph.LATCHED_QOS, True),
    "odom": (ODOMETRY, graph.DEFAULT_10_QOS, False),
    "initialpose": (POSE_WITH_COVARIANCE_STAMPED, graph.SYSTEM_DEFAULT_QOS, False),
    "map": (OCCUPANCY_GRID, graph.LATCHED_QOS, True),
}
#: Outputs: topic leaf -> (type, QoS of the publisher).
OUTPUTS: dict[str, tuple[RosType, graph.QoS]] = {
    "amcl_pose": (POSE_WITH_COVARIANCE_STAMPED, graph.LATCHED_QOS),
    "tf": (TF_MESSAGE, graph.TF_QOS),
}
_MSGPACK = zenoh.Encoding(codec.MSGPACK_ENCODING)
#: Seconds between two looks at the service for a robot's configuration while it does not
#: answer.
PROBE_RETRY_S = 2.0


class Ros2Front:
    """The front on ``session`` (not closed by it). :meth:`start`, then :meth:`stop`."""

    def __init__(self, session: zenoh.Session, options: Ros2Options) -> None:
        self.session = session
        self.o = options
        self.zid = str(session.zid())
        self.robots: dict[str, RosRobot] = {}
        self.by_id: dict[str, str] = {}  # robot id -> namespace
        self._events: queue.Queue[tuple[Any, ...]] = queue.Queue(maxsize=20000)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._subs: list[Any] = []
        self._nodes: list[RosNode] = []
        self._pubs: dict[tuple[str, str], RosPublisher] = {}
        self._counter = EntityCounter()
        self._global_grid: cdr.Grid | None = None
        self._global_put: cdr.Grid | None = None
        self._last_log: dict[str, float] = {}
        self.rejected = 0
        self.queue_drops = 0

    # ----------------------------------------------------------------- lifecycle
    def start(self) -> None:
        """Declare the subscriptions and start the worker thread."""
        d = self.o.domain_id
        for leaf, (rtype, qos, _latched) in INPUTS.items():
            sel = graph.topic_selector(d, leaf, rtype)
            self._subs.append(subscribe(self.session, sel, qos, self._enqueuer(leaf), True))
        self._subs.append(
            self.session.declare_subscriber(
                keys.robots_wildcard(self.o.prefix, "pose"), self._enqueuer("pose")
            )
        )
        if self.o.import_maps:
            root = RosNode(self.session, d, "/", self.o.node_name, self._counter)
            rtype, qos, _ = INPUTS["map"]
            root.subscription_token("/map", rtype, qos)
            self._nodes.append(root)
        self._thread = threading.Thread(target=self._run, name="ros2-front", daemon=True)
        self._thread.start()
        for ns in self.o.namespaces:
            self._events.put(("announce", ns))
        log.info(
            "ROS 2 front on domain %d (zid %s), frames %s/%s/%s, prefix %s",
            d, self.zid, self.o.global_frame_id, self.o.odom_frame_id, self.o.base_frame_id,
            self.o.prefix,
        )  # fmt: skip

    def stop(self, timeout: float = 5.0) -> None:
        """Stop the worker and undeclare every subscription, publisher and token."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(timeout)
        for sub in self._subs:
            with contextlib.suppress(Exception):
                sub.undeclare()
        for node in self._nodes:
            node.close()
        self._subs.clear()
        self._pubs.clear()
        self._nodes.clear()
        for r in self.robots.values():
            c = r.counters
            log.info(
                "robot %s (%s): %d scans in, %d to the service, %d poses out, dropped %s",
                r.robot_id, r.namespace, c.scans_in, c.scans_out, c.poses_out, c.dropped,
            )  # fmt: skip

    def __enter__(self) -> Ros2Front:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    # ----------------------------------------------------------------- zenoh side
    def _enqueuer(self, kind: str) -> Any:
        events = self._events

        def on_sample(sample: Any) -> None:
            att = sample.attachment
            enc = str(sample.encoding)
            item = (
                kind,
                str(sample.key_expr),
                sample.payload.to_bytes(),
                None if att is None else att.to_bytes(),
                enc,
            )
            try:
                events.put_nowait(item)
            except queue.Full:
                self.queue_drops += 1

        return on_sample

    def _declare_robot(self, robot: RosRobot) -> None:
        """The robot's node, its subscription tokens and its publishers."""
        node = RosNode(
            self.session, self.o.domain_id, robot.namespace, self.o.node_name, self._counter
        )
        for leaf, (rtype, qos, _latched) in INPUTS.items():
            node.subscription_token(leaf, rtype, qos)
        for leaf, (rtype, qos) in OUTPUTS.items():
            self._pubs[(robot.robot_id, leaf)] = node.publisher(leaf, rtype, qos)
        self._nodes.append(node)

    def _probe(self, robot_id: str) -> None:
        """Ask the service (in a helper thread) whether it configures ``robot_id`` itself."""
        up, cfg = False, None
        try:
            for reply in self.session.get(keys.health_key(self.o.prefix), timeout=1.0):
                up = up or reply.ok is not None
            sel = f"{self.o.prefix}/service/state/*/config/{robot_id}"
            for reply in self.session.get(sel, timeout=1.0):
                if reply.ok is not None and cfg is None:
                    with contextlib.suppress(InvalidMessage):
                        cfg = codec.decode(
                            RobotConfig, reply.ok.payload.to_bytes(), str(reply.ok.encoding)
                        )
        except zenoh.ZError as exc:
            log.warning("configuration look-up of %s failed: %s", robot_id, exc)
        self._events.put(("probe", robot_id, up, cfg))

    def _confirm(self, robot_id: str, within: float = 5.0) -> None:
        """Wait (in a helper thread) until the service answers for a robot the front just
        configured, so its scans do not overtake the configuration."""
        key = keys.robot_key(self.o.prefix, robot_id, "pose")
        end = time.monotonic() + within
        while time.monotonic() < end and not self._stop.is_set():
            try:
                for reply in self.session.get(key, timeout=0.5):
                    if reply.ok is not None:
                        self._events.put(("ack", robot_id))
                        return
                    text = reply.err.payload.to_bytes().decode("utf-8", "replace").lower()
                    if "unknown robot" not in text and text != "timeout":
                        self._events.put(("ack", robot_id))
                        return
            except zenoh.ZError:
                pass
            time.sleep(0.05)
        self._events.put(("ack", robot_id))  # go on anyway; rejected scans are reported

    # ----------------------------------------------------------------- worker
    def _run(self) -> None:
        next_tick = 0.0
        while not self._stop.is_set():
            try:
                ev = self._events.get(timeout=0.05)
            except queue.Empty:
                ev = None
            try:
                if ev is not None:
                    self._handle(ev)
                now = time.monotonic()
                if now >= next_tick:
                    next_tick = now + 0.05
                    for robot in list(self.robots.values()):
                        self._serve(robot, now)
            except Exception:  # the front must keep serving every other robot
                log.exception("ROS 2 front: unexpected error (going on)")

    def _handle(self, ev: tuple[Any, ...]) -> None:
        kind = ev[0]
        if kind == "announce":
            self._robot(ev[1])
            return
        if kind == "probe":
            self._on_probe(ev[1], ev[2], ev[3])
            return
        if kind == "ack":
            robot = self.robots.get(self.by_id.get(ev[1], ""))
            if robot is not None:
                robot.awaiting_ack = False
                self._serve(robot, time.monotonic())
            return
        _, key, payload, att, enc = ev
        if kind == "pose":
            self._on_pose(key, payload, enc)
            return
        try:
            self._on_ros(kind, key, payload, att)
        except InvalidMessage as exc:
            self._reject(key, str(exc))

    def _on_ros(self, leaf: str, key: str, payload: bytes, att: bytes | None) -> None:
        rtype = INPUTS[leaf][0]
        topic = graph.topic_of_key(self.o.domain_id, key, rtype)
        namespace, name = graph.split_name(topic)
        if name != leaf:
            return
        if att is not None:
            try:
                decode_attachment(att)
            except InvalidMessage as exc:  # the payload is still usable
                self._note("attachment", f"{key[:120]}: {exc}")
        if leaf == "map" and namespace == "/":
            self._global_grid = cdr.decode_occupancy_grid(payload)
            log.info(
                "global map %s: %d x %d cells",
                topic,
                self._global_grid.width,
                self._global_grid.height,
            )
            return
        robot = self._robot(namespace)
        if robot is None:
            return
        if leaf == "scan":
            robot.on_scan(cdr.decode_laser_scan(payload), time.monotonic())
        elif leaf in ("tf", "tf_static"):
            robot.on_tf(cdr.decode_tf(payload), static=leaf == "tf_static")
        elif leaf == "odom":
            robot.on_odometry(cdr.decode_odometry(payload))
        elif leaf == "initialpose":
            robot.on_initial_pose(cdr.decode_pose_with_covariance(payload))
        elif leaf == "map":
            robot.own_grid = cdr.decode_occupancy_grid(payload)
        self._serve(robot, time.monotonic())

    def _robot(self, namespace: str) -> RosRobot | None:
        robot = self.robots.get(namespace)
        if robot is not None:
            return robot
        try:
            rid = graph.robot_id_of_namespace(namespace, self.o.default_robot_id)
        except InvalidMessage as exc:
            self._reject(f"{self.o.domain_id}{namespace}", str(exc))
            return None
        if rid in self.by_id:
            self._reject(f"{self.o.domain_id}{namespace}", f"robot id {rid!r} already taken")
            return None
        robot = RosRobot(namespace, rid, self.o)
        self.robots[namespace] = robot
        self.by_id[rid] = namespace
        self._declare_robot(robot)
        self._start_probe(robot)
        log.info("ROS 2 robot %s in namespace %s", rid, namespace)
        return robot

    def _start_probe(self, robot: RosRobot) -> None:
        robot.probe_at = float("inf")  # one look-up at a time
        threading.Thread(
            target=self._probe, args=(robot.robot_id,), name="ros2-probe", daemon=True
        ).start()

    def _on_probe(self, robot_id: str, up: bool, cfg: RobotConfig | None) -> None:
        robot = self.robots.get(self.by_id.get(robot_id, ""))
        if robot is None or robot.config not in ("unknown",):
            return
        if cfg is not None:
            robot.config, robot.shapeloc_config = "shapeloc", cfg
            log.info(
                "robot %s: shapeloc configuration (map %s, %s)", robot_id, cfg.map_id, cfg.method
            )
        elif up:
            robot.config = "none"
            robot.probe_at = time.monotonic() + PROBE_RETRY_S
            log.info("robot %s: no shapeloc configuration; from ROS (map, initialpose)", robot_id)
        else:
            robot.probe_at = time.monotonic() + PROBE_RETRY_S
        self._serve(robot, time.monotonic())

    def _serve(self, robot: RosRobot, now: float) -> None:
        """Put what the robot's state allows: map, configuration, ready scans."""
        no_map = robot.own_grid is None and self._global_grid is None
        if robot.config == "none" and no_map and now >= robot.probe_at:
            robot.config = "unknown"  # configured by shapeloc meanwhile?
        if robot.config == "unknown" and now >= robot.probe_at:
            self._start_probe(robot)
        global_ready = False
        if robot.own_grid is None and robot.config in ("none", "ros") and self.o.import_maps:
            global_ready = self._put_global_map()
        try:
            for key, msg in robot.plan_config(self._global_grid, global_ready):
                self._put(key, msg)
                log.info("put %s", key)
                if isinstance(msg, RobotConfig) and not robot.awaiting_ack:
                    robot.awaiting_ack = True
                    threading.Thread(
                        target=self._confirm, args=(robot.robot_id,), name="ros2-ack", daemon=True
                    ).start()
        except InvalidMessage as exc:
            self._reject(f"{self.o.prefix}/robots/{robot.robot_id}/config", str(exc))
        scans, errors = robot.ready_scans(now)
        for error in errors:
            self._reject(f"{self.o.domain_id}{robot.namespace}/scan", error)
        for scan in scans:
            self.session.put(
                keys.robot_key(self.o.prefix, robot.robot_id, "scan"),
                codec.encode(scan, ranges_as_bytes=True),
                encoding=_MSGPACK,
            )

    def _put_global_map(self) -> bool:
        grid = self._global_grid
        if grid is None:
            return False
        if self._global_put is not grid:
            try:
                msg = grid_map(grid, self.o.global_map_id)
            except InvalidMessage as exc:
                self._reject(f"{self.o.domain_id}/map", str(exc))
                self._global_grid = None
                return False
            self._put(keys.map_key(self.o.prefix, self.o.global_map_id), msg)
            self._global_put = grid
        return True

    def _put(self, key: str, msg: WireModel) -> None:
        self.session.put(
            key,
            codec.encode(msg),
            encoding=_MSGPACK,
            congestion_control=zenoh.CongestionControl.BLOCK,
        )

    def _on_pose(self, key: str, payload: bytes, enc: str) -> None:
        try:
            rid, _ = keys.parse_robot_key(self.o.prefix, key)
        except InvalidMessage:
            return
        ns = self.by_id.get(rid)
        if ns is None:
            return
        robot = self.robots[ns]
        try:
            pose = codec.decode(PoseMsg, payload, enc)
        except InvalidMessage as exc:
            self._note("pose", f"{key}: {exc}")
            return
        out = robot.answer(pose)
        if out is None:
            return
        amcl, tf = out
        if amcl is not None:
            self._pubs[(rid, "amcl_pose")].put(cdr.encode_pose_with_covariance(amcl))
        if tf is not None:
            self._pubs[(rid, "tf")].put(cdr.encode_tf([tf]))

    # ----------------------------------------------------------------- errors
    def _note(self, kind: str, text: str) -> None:
        now = time.monotonic()
        if now - self._last_log.get(kind, 0.0) >= 1.0:
            self._last_log[kind] = now
            log.warning("ROS 2 front: %s", text)

    def _reject(self, key: str, error: str) -> None:
        self.rejected += 1
        self._note("reject", f"rejected {key[:200]}: {error}")
        with contextlib.suppress(zenoh.ZError):
            self.session.put(
                keys.errors_key(self.o.prefix),
                codec.encode(ErrorNotice.make(key, error)),
                encoding=_MSGPACK,
            )
