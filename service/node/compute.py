"""The compute side of the service: workers, scans and pose publishing.

:class:`ComputePlane` is a mixin of :class:`service.node.node.ServiceNode` and implements its
:class:`~service.node.scheduler.LinkHost` part: it creates and restarts the workers (replaying the
maps and robots into a fresh one), admits each valid scan from the intake into its robot's
latest-wins slot, runs it on the robot's worker, publishes the pose on
``<prefix>/robots/<id>/pose`` and moves a robot between a tracking worker and the search
worker when it starts or stops searching.
"""

from __future__ import annotations

import contextlib
import logging
import threading
import time
from collections import Counter, deque
from pathlib import Path
from typing import TYPE_CHECKING, Any

from schemas import codec, keys
from schemas.messages import Map, PoseMsg, RobotConfig
from service.core.types import MapData
from service.errors import (
    InvalidMessage,
    LocalizationError,
    ShapelocError,
    UnknownMap,
    UnknownRobot,
)
from service.node.assignment import Assignment
from service.node.control import as_list
from service.node.intake import ValidScan
from service.node.workers import InlineWorker, ProcessWorker, config_request

if TYPE_CHECKING:
    from service.node.scheduler import Worker, WorkerLink
    from service.node.settings import ServiceSettings

log = logging.getLogger("shapeloc.service")

VIEW_CACHE_DIR = "viewcache"  # under the state dir: per-map view index of global localisation


class ComputePlane:
    """Workers, scan processing and pose publishing, mixed into the node (which owns the
    attributes declared here)."""

    settings: ServiceSettings
    session: Any
    prefix: str
    lock: threading.RLock
    maps: dict[str, tuple[Map, MapData]]
    configs: dict[str, RobotConfig]
    poses: dict[str, PoseMsg]
    odoms: dict[str, tuple[float, float, float]]
    errors: Counter[str]
    scans_processed: int
    links: list[WorkerLink]
    assignment: Assignment
    search_link: WorkerLink | None
    migrate_lock: threading.Lock
    suspended: frozenset[str]
    #: CPU ms of each of the last processed scans (node threads and worker): health's figure
    scan_cpu_ms: deque[float]
    _dirty: set[str]

    def _link_of(self, robot_id: str) -> WorkerLink:
        raise NotImplementedError

    def serves(self, robot_id: str) -> bool:
        raise NotImplementedError

    def reject(self, key: str, what: str, exc: BaseException | str) -> None:
        raise NotImplementedError

    # ------------------------------------------------------------------ workers
    def new_worker(self, index: int) -> Worker:
        """A fresh worker for link ``index`` (in-process with ``--workers 0``)."""
        # Global localisation caches each map's view index here (rebuilt when the map changes).
        cache_dir = Path(self.settings.state_dir) / VIEW_CACHE_DIR
        budget = self.settings.search_budget_ms or None  # 0: a whole search per scan
        if self.settings.workers == 0:
            return InlineWorker(index, cache_dir, budget)
        nice = self.settings.search_worker_nice if index >= self.settings.workers else 0
        return ProcessWorker(
            index,
            self.settings.log_level,
            cache_dir,
            budget,
            nice,
            start_timeout_s=self.settings.worker_start_timeout_s,
            search=index >= self.settings.workers,
        )

    def restart_worker(self, link: WorkerLink) -> None:
        """Replace a dead or hung worker and replay the maps and its robots (from their last
        poses and odometry) into the new one."""
        with self.lock:
            self.errors["worker.Restarted"] += 1
        with contextlib.suppress(Exception):
            link.worker.close()
        link.worker = self.new_worker(link.index)
        t = self.settings.worker_timeout_s
        with self.lock:
            maps = [md for _m, md in self.maps.values()]
            robots = [
                (rid, cfg, self.poses.get(rid), self.odoms.get(rid))
                for rid, cfg in self.configs.items()
                if self._link_of(rid) is link
            ]
        for md in maps:
            link.worker.call(("map", md), t)
        for rid, cfg, pm, odom in robots:
            start = None if pm is None else as_list(pm.pose)
            odom_start = None if pm is None else as_list(odom)
            link.worker.call(config_request(rid, cfg, start, odom_start), t)

    # ------------------------------------------------------------------ scans
    def _offer_scan(self, scan: ValidScan) -> None:
        """Intake sink: a valid scan enters its robot's latest-wins slot."""
        if not self.serves(scan.robot_id):
            return  # handed over to another instance since it arrived
        if scan.robot_id in self.suspended:  # back from being cut off: see ClusterPlane
            with self.lock:
                self.errors["scan.Suspended"] += 1
            return
        if not self._link_of(scan.robot_id).slots.offer(scan.robot_id, scan):
            self.reject(
                scan.key,
                "scan",
                InvalidMessage(
                    f"service overloaded: more than {self.settings.max_robots} robots pending"
                ),
            )

    def process_scan(self, link: WorkerLink, scan: ValidScan) -> None:
        """Localise one valid scan on ``link``'s worker and publish the pose."""
        self.process_batch(link, [scan])

    def process_batch(self, link: WorkerLink, scans: list[ValidScan]) -> None:
        """Localise valid scans of different robots on ``link``'s worker in one request and
        publish each pose as soon as the worker answers it; then move the robots that started
        or stopped searching. Each scan's CPU time (this thread's share of the batch, the
        worker's and the intake's validation) goes to :attr:`scan_cpu_ms`."""
        cpu0 = time.thread_time()
        todo = [(scan, cfg) for scan in scans if (cfg := self._admit(link, scan)) is not None]
        if not todo:
            return
        worker_ms = [0.0] * len(todo)
        published = [False] * len(todo)
        moves: list[tuple[str, bool]] = []

        def on_reply(i: int, reply: tuple[str, Any]) -> None:
            scan, cfg = todo[i]
            status, out = reply
            if status != "ok":
                self.reject(scan.key, "scan", LocalizationError(str(out)))
                return
            worker_ms[i] = float(out.get("cpu_ms", 0.0))
            published[i] = self._publish(scan, cfg, out)
            unsettled = bool(out.get("unsettled"))
            search = self.search_link
            if published[i] and search is not None and unsettled != (link is search):
                moves.append((scan.robot_id, unsettled))

        link.call_batch(
            [("scan", s.robot_id, s.ranges, s.angles, s.odom, s.skipped_odom) for s, _ in todo],
            on_reply,
        )
        own_ms = (time.thread_time() - cpu0) * 1e3 / len(todo)
        for i, (scan, _cfg) in enumerate(todo):
            if published[i]:
                self.scan_cpu_ms.append(own_ms + worker_ms[i] + scan.intake_ms)
        for robot_id, to_search in moves:
            self._migrate(link, robot_id, to_search)

    def _admit(self, link: WorkerLink, scan: ValidScan) -> RobotConfig | None:
        """The robot's configuration if ``scan`` is to be localised on ``link`` now; ``None``
        if it is not (handed over to another instance, re-queued on the robot's new worker, or
        rejected with a notice: unknown robot, map not stored)."""
        robot_id, key = scan.robot_id, scan.key
        if not self.serves(robot_id):
            return None  # handed over to another instance since it arrived
        owner = self._link_of(robot_id)
        if owner is not link:  # assigned to another worker after the scan was queued here
            owner.slots.offer(robot_id, scan)
            return None
        try:
            keys.validate_id(robot_id, "robot_id")
            with self.lock:
                cfg = self.configs.get(robot_id)
                have_map = cfg is not None and cfg.map_id in self.maps
            if cfg is None:
                raise UnknownRobot(
                    f"robot {robot_id!r} has no configuration; put "
                    f"{self.prefix}/robots/{robot_id}/config first"
                )
            if not have_map:
                raise UnknownMap(
                    f"map {cfg.map_id!r} of robot {robot_id!r} is not stored (deleted?); the "
                    "robot waits for it"
                )
        except ShapelocError as e:
            self.reject(key, "scan", e)
            return None
        return cfg

    def _publish(self, scan: ValidScan, cfg: RobotConfig, out: dict[str, Any]) -> bool:
        """Publish the worker's estimate ``out`` of ``scan`` as the robot's pose and keep it
        as its last pose (with the scan's odometry); whether it was published (not if the
        robot was reconfigured meanwhile, or the estimate is not a valid pose message)."""
        robot_id = scan.robot_id
        try:
            pose_msg = PoseMsg(
                robot_id=robot_id,
                seq=scan.seq,
                stamp=scan.stamp,
                pose=out["pose"],
                status=out["status"],
                score=out["score"],
                method=cfg.method,
                map_id=cfg.map_id,
                latency_ms=(time.monotonic() - scan.t_recv) * 1e3,
                covariance=out["covariance"],
                explained=_clip01(out["explained"]),
                ambiguity=_clip01(out["ambiguity"]),
                hypotheses=out.get("hypotheses"),
                candidates=out.get("candidates") or None,
                odom=None if scan.odom is None else [float(v) for v in scan.odom],
                state=out.get("state"),
            )
            payload = codec.encode(pose_msg)
        except ShapelocError as e:
            self.reject(scan.key, "scan", LocalizationError(f"estimate not publishable: {e}"))
            return False
        with self.lock:
            if self.configs.get(robot_id) is not cfg:
                return False  # reconfigured meanwhile: this estimate belongs to the old config
            self.poses[robot_id] = pose_msg
            if scan.odom is not None:
                self.odoms[robot_id] = (
                    float(scan.odom[0]),
                    float(scan.odom[1]),
                    float(scan.odom[2]),
                )
            self._dirty.add(robot_id)
            self.scans_processed += 1
        self.session.put(
            keys.robot_key(self.prefix, robot_id, "pose"), payload, encoding=codec.MSGPACK_ENCODING
        )
        return True

    def _migrate(self, link: WorkerLink, robot_id: str, to_search: bool) -> None:
        """Move a robot that started searching to the search worker, or one that has tracked
        ``settle_scans`` scans since its fix back to the least-loaded tracking worker (a wrong
        or early fix that is lost again then stays on the search worker), with its
        localiser's state (runs on
        ``link``'s thread, the robot's current owner). Skipped while a configuration is being
        applied (the control thread holds ``migrate_lock``); the next scan tries again."""
        if not self.migrate_lock.acquire(blocking=False):
            return
        try:
            if self._link_of(robot_id) is not link:
                return
            assert self.search_link is not None
            idx = self.search_link.index if to_search else self.assignment.least_loaded()
            status, robot = link.call(("export", robot_id))
            if status != "ok":
                log.warning("robot %s not moved: %s", robot_id, robot)
                return
            self.links[idx].submit(("import", robot_id, robot))
            self.assignment.move(robot_id, idx)
            with self.lock:
                self.errors["worker.MovedToSearch" if to_search else "worker.MovedBack"] += 1
        finally:
            self.migrate_lock.release()


def _clip01(v: float | None) -> float | None:
    return None if v is None else min(1.0, max(0.0, float(v)))
