"""The write side of the service: map and robot-config puts/deletes, pose saving, restore.

:class:`ControlPlane` is a mixin of :class:`service.node.node.ServiceNode`: the control thread
applies map/config messages in arrival order (FIFO), each committed to the
:class:`~service.node.state.StateStore` before any worker or robot uses it, and saves the changed
last poses every ``pose_save_interval_s`` seconds. :func:`load_state` parses the store at
start-up.
"""

from __future__ import annotations

import dataclasses
import logging
import queue
import threading
import time
from collections import Counter
from concurrent.futures import Future
from typing import TYPE_CHECKING, Any

import numpy as np

from schemas import codec, keys
from schemas.messages import Map, PoseMsg, RobotConfig
from service.adapters.convert import map_data_of
from service.core.types import MapData
from service.errors import (
    InvalidMessage,
    LocalizationError,
    ShapelocError,
    StateError,
    UnknownMap,
    UnknownRobot,
)
from service.node.assignment import Assignment
from service.node.intake import Inbound, ScanIntake
from service.node.readiness import Readiness
from service.node.state import SavedPose, StateStore
from service.node.workers import config_request

if TYPE_CHECKING:
    from service.node.mirror import Mirror
    from service.node.scheduler import WorkerLink
    from service.node.settings import ServiceSettings

log = logging.getLogger("shapeloc.service")


@dataclasses.dataclass
class Restored:
    """Everything read back from the state store, parsed, before any worker sees it."""

    maps: dict[str, tuple[Map, MapData]]
    configs: dict[str, RobotConfig]
    poses: dict[str, PoseMsg]
    #: Odometry pose ``(x, y, theta)`` (odometry frame) saved with each restored pose, for the
    #: robots whose last scans carried odometry.
    odoms: dict[str, tuple[float, float, float]] = dataclasses.field(default_factory=dict)


def load_state(store: StateStore) -> Restored:
    """Parse everything in the store (maps, configs, saved poses) without side effects;
    any invalid content raises :class:`StateError` naming the file and the row."""
    out = Restored({}, {}, {})
    for map_id, wire in store.maps().items():
        try:
            msg = Map.parse(wire)
            out.maps[map_id] = (msg, map_data_of(msg))
        except ShapelocError as e:
            raise StateError(f"{store.path}: stored map {map_id!r} is invalid: {e}") from e
    saved = store.poses()
    for robot_id, wire in store.robots().items():
        try:
            cfg = RobotConfig.parse(wire)
        except ShapelocError as e:
            raise StateError(
                f"{store.path}: stored config of robot {robot_id!r} is invalid: {e}"
            ) from e
        out.configs[robot_id] = cfg
        sp = saved.get(robot_id)
        if sp is None or sp.map_id != cfg.map_id:
            continue
        try:
            out.poses[robot_id] = PoseMsg(
                robot_id=robot_id,
                seq=sp.seq,
                stamp=sp.stamp,
                pose=list(sp.pose),
                status=sp.status,
                score=0.0,
                method=cfg.method,
                map_id=cfg.map_id,
                latency_ms=0.0,
            )
        except ShapelocError as e:
            raise StateError(
                f"{store.path}: stored pose of robot {robot_id!r} is invalid: {e}"
            ) from e
        if sp.odom is not None:
            out.odoms[robot_id] = sp.odom
    return out


class ControlPlane:
    """Map/config handling and pose persistence, mixed into the node (which owns the
    attributes declared here)."""

    settings: ServiceSettings
    prefix: str
    lock: threading.RLock
    stopping: threading.Event
    maps: dict[str, tuple[Map, MapData]]
    configs: dict[str, RobotConfig]
    poses: dict[str, PoseMsg]
    odoms: dict[str, tuple[float, float, float]]
    errors: Counter[str]
    state: StateStore | None
    links: list[WorkerLink]
    assignment: Assignment
    search_link: WorkerLink | None
    migrate_lock: threading.Lock
    intake: ScanIntake
    readiness: Readiness
    _dirty: set[str]
    mirror: Mirror
    _control_mutex: threading.RLock
    _control_q: queue.Queue[Inbound | None]
    _control_overflow: int
    _control_bytes: int
    _dropped_reported: int

    def reject(self, key: str, what: str, exc: BaseException | str) -> None:
        raise NotImplementedError

    def _notice(self, key: str, text: str) -> None:
        raise NotImplementedError

    def _link_of(self, robot_id: str) -> WorkerLink:
        raise NotImplementedError

    def serves(self, robot_id: str) -> bool:
        raise NotImplementedError

    def mirror_config(self, robot_id: str, cfg: RobotConfig | None) -> None:
        raise NotImplementedError

    def _control_loop(self) -> None:
        next_save = time.monotonic() + self.settings.pose_save_interval_s
        while not self.stopping.is_set():
            timeout = max(0.0, min(0.5, next_save - time.monotonic()))
            try:
                item = self._control_q.get(timeout=timeout)
            except queue.Empty:
                item = None
            if item is not None:
                with self.lock:
                    self._control_bytes -= 0 if item.payload is None else len(item.payload)
                try:
                    with self._control_mutex:
                        self.handle_control(item)
                except Exception:
                    log.exception("unexpected error on %s", item.key)
                finally:
                    self.clock.mark_applied(item.ctl)
            self._report_overflows()
            if time.monotonic() >= next_save:
                next_save = time.monotonic() + self.settings.pose_save_interval_s
                try:
                    self.save_poses()
                except StateError as e:
                    log.error("periodic pose save failed: %s", e)

    def _report_overflows(self) -> None:
        """One aggregated notice per overflow burst (control queue full, intake dropping)."""
        with self.lock:
            overflow, self._control_overflow = self._control_overflow, 0
        if overflow:
            self.reject(f"{self.prefix}/**", "control", f"control queue full: {overflow} dropped")
        dropped = self.intake.queue.notices_dropped
        if dropped > self._dropped_reported:
            n, self._dropped_reported = dropped - self._dropped_reported, dropped
            log.warning("scan flood: %d rejections counted without a notice or log line", n)
            self._notice(
                keys.robots_wildcard(self.prefix, "scan"),
                f"Overloaded: scan flood, {n} further rejections counted in health only",
            )

    def handle_control(self, item: Inbound) -> None:
        """Apply one map or config put/delete (rejecting it with a notice if invalid)."""
        what = "map" if "/maps/" in item.key else "config"
        try:
            if item.reject is not None:
                raise InvalidMessage(item.reject)
            if what == "map":
                self._handle_map(item)
            else:
                self._handle_config(item)
        except ShapelocError as e:
            self.reject(item.key, what, e)

    def _broadcast(self, req: tuple[Any, ...]) -> list[tuple[str, Any]]:
        futs = [link.submit(req) for link in self.links]
        t = self.settings.reply_wait_s
        return [f.result(timeout=t) for f in futs]

    def _handle_map(self, item: Inbound) -> None:
        assert self.state is not None
        map_id = keys.parse_map_key(self.prefix, item.key)
        if item.delete:
            with self.lock:
                known = map_id in self.maps
            if not known:
                raise UnknownMap(f"cannot delete map {map_id!r}: it is not stored")
            self.state.delete_map(map_id)
            log.info("map %s deleted (robots on it wait for a new one)", map_id)
            self.readiness.deleted(map_id)
            with self.lock:
                self.maps.pop(map_id, None)
            self._broadcast(("map_delete", map_id))
            return
        assert item.payload is not None
        msg = codec.decode(Map, item.payload, item.encoding)
        codec.check_key_id(msg.map_id, map_id, "map_id")
        md = map_data_of(msg)
        self.state.put_map(map_id, msg.to_wire())
        log.info(
            "map %s stored (%s, %d polylines, %d points)",
            map_id,
            msg.kind,
            len(md.polylines),
            sum(len(p) for p in md.polylines),
        )
        version = self.readiness.stored(map_id)
        with self.lock:
            self.maps[map_id] = (msg, md)
        t0 = time.monotonic()
        self._broadcast(("map", md))  # every worker stores it, the tracking ones prepare it
        self.readiness.prepared(map_id, version)
        log.info("map %s prepared on every worker (%.2f s)", map_id, time.monotonic() - t0)
        self.build_index(map_id, version)

    def build_index(self, map_id: str, version: int) -> None:
        """Have the search worker build version ``version`` of the map's view index of global
        localisation into the on-disk cache (asynchronously: the control thread goes on);
        ``maps_indexed`` lists the map once it is built, and ``maps_ready`` once it is also
        prepared (:mod:`service.node.readiness`). Without a search worker the first search
        builds it."""
        link = self.search_link
        if link is None:
            return

        def done(fut: Future[tuple[str, Any]]) -> None:
            try:
                status, out = fut.result()
            except Exception as e:  # the service is stopping
                status, out = "err", str(e)
            if status == "ok":
                self.readiness.indexed(map_id, version)
                log.info("map %s: view index of global localisation ready (%.1f s)", map_id, out)
            else:
                # ready without it: a map that cannot be indexed still tracks robots
                self.readiness.indexed(map_id, version, built=False)
                log.warning(
                    "map %s: view index not built ahead (%s); built by the first search",
                    map_id,
                    out,
                )

        link.submit(("index", map_id)).add_done_callback(done)

    def _handle_config(self, item: Inbound) -> None:
        assert self.state is not None
        robot_id, _leaf = keys.parse_robot_key(self.prefix, item.key)
        if not self.serves(robot_id):  # another instance's robot: mirrored, never a notice
            cfg_other = None
            if not item.delete:
                assert item.payload is not None
                try:
                    cfg_other = codec.decode(RobotConfig, item.payload, item.encoding)
                except ShapelocError:
                    return  # the owner rejects it
            self.mirror_config(robot_id, cfg_other)
            return
        if item.delete:
            with self.lock:
                known = robot_id in self.configs
            if not known:
                raise UnknownRobot(f"cannot delete config of robot {robot_id!r}: unknown robot")
            self.state.delete_robot(robot_id)
            log.info("robot %s removed", robot_id)
            with self.lock:
                self.configs.pop(robot_id, None)
                self.poses.pop(robot_id, None)
                self.odoms.pop(robot_id, None)
                self._dirty.discard(robot_id)
            with self.migrate_lock:
                link = self._link_of(robot_id)
                link.slots.discard(robot_id)
                link.submit(("forget", robot_id)).result()
                self.assignment.release(robot_id)
            return
        assert item.payload is not None
        cfg = codec.decode(RobotConfig, item.payload, item.encoding)
        with self.lock:
            if cfg.map_id not in self.maps:
                raise UnknownMap(
                    f"robot {robot_id!r} names map {cfg.map_id!r}, which is not stored; put "
                    f"{self.prefix}/maps/{cfg.map_id} first"
                )
            if robot_id not in self.configs and len(self.configs) >= self.settings.max_robots:
                raise InvalidMessage(
                    f"robot limit reached ({self.settings.max_robots}); {robot_id!r} refused"
                )
        new = robot_id not in self.configs
        with self.migrate_lock:  # no move between workers while the config is applied
            idx = self.assignment.assign(robot_id)
            search = self.search_link
            if cfg.initial_pose is None and search is not None and idx != search.index:
                # global localisation starts on the search worker (never on a tracking one)
                if not new:
                    self.links[idx].slots.discard(robot_id)
                    self.links[idx].submit(("forget", robot_id)).result(
                        timeout=self.settings.reply_wait_s
                    )
                self.assignment.move(robot_id, search.index)
                idx = search.index
            link = self.links[idx]
            status, why = link.submit(config_request(robot_id, cfg)).result(
                timeout=self.settings.reply_wait_s
            )
            if status != "ok" and new:
                self.assignment.release(robot_id)
        if status != "ok":
            raise LocalizationError(f"robot {robot_id!r}: {why}")
        self.state.put_robot(robot_id, cfg.to_wire())
        log.info(
            "robot %s config stored (map %s, method %s, initial pose %s)",
            robot_id,
            cfg.map_id,
            cfg.method,
            None if cfg.initial_pose is None else as_list(cfg.initial_pose),
        )
        with self.lock:
            self.configs[robot_id] = cfg
            self.poses.pop(robot_id, None)
            self.odoms.pop(robot_id, None)
            self._dirty.discard(robot_id)

    def save_poses(self) -> int:
        """Write the poses that changed since the last save in one transaction; returns how
        many, each with the robot's last odometry pose (also the last poses other instances
        published for the robots this one mirrors). After a failed write the poses stay
        marked for the next save."""
        with self.lock:
            dirty = {
                rid: (self.poses[rid], self.odoms.get(rid))
                for rid in self._dirty
                if rid in self.poses
            }
            self._dirty.clear()
        mirrored = self.mirror.saves()
        if (not dirty and not mirrored) or self.state is None:
            return 0
        rows = dict(mirrored)
        for rid, (p, odom) in dirty.items():
            x, y, th = (float(v) for v in p.pose)
            rows[rid] = SavedPose(p.map_id, x, y, th, p.seq, p.stamp, p.status, odom)
        try:
            self.state.save_poses(rows)
        except StateError:
            with self.lock:
                self._dirty.update(rid for rid in dirty if rid in self.poses)
            self.mirror.mark_dirty(mirrored)
            raise
        return len(rows)


def as_list(a: Any) -> list[float] | None:
    """A pose-like array as a list of floats (``None`` stays ``None``)."""
    return None if a is None else [float(v) for v in np.asarray(a).reshape(-1)]
