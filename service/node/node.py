"""The Zenoh transport layer of the localizer service.

:class:`ServiceNode` owns the session entities (one subscriber on ``<prefix>/**``, the
queryables, the liveliness token), the in-memory view of maps / robot configurations / last
poses and the :class:`~service.node.state.StateStore`. Zenoh callbacks only do O(1) checks and
copy bytes into queues; everything else runs in the node's own threads:

* intake thread (:mod:`service.node.intake`): decodes and validates every scan on arrival; only a
  valid scan reaches its robot's latest-wins slot, so garbage never displaces a good scan;
* one link thread per worker (:mod:`service.node.scheduler`): forwards control changes to its
  worker, then takes the next robot with a pending valid scan (round robin over robots),
  runs it on the worker and publishes the pose (:mod:`service.node.compute`);
* control thread: map and config puts/deletes (FIFO), periodic pose saving;
* query thread: ``get`` on maps, poses and health (FIFO, :mod:`service.node.queries`).

Every rejected message produces an :class:`~schemas.messages.ErrorNotice` on
``<prefix>/errors`` and is counted per kind in the health reply.
"""

from __future__ import annotations

import contextlib
import dataclasses
import logging
import queue
import threading
import time
from collections import Counter, deque
from typing import Any

from schemas import codec, keys
from schemas.limits import MAX_PAYLOAD_BYTES
from schemas.messages import ErrorNotice, Health, Map, PoseMsg, RobotConfig
from service.core.types import MapData
from service.errors import (
    InvalidMessage,
    ShapelocError,
    StateError,
    UnknownRobot,
)
from service.node import queries
from service.node.assignment import Assignment
from service.node.cluster import ClusterPlane
from service.node.compute import ComputePlane
from service.node.control import ControlPlane, Restored, as_list, load_state
from service.node.intake import (
    MAX_SCAN_BYTES,
    ControlClock,
    Inbound,
    RawScan,
    ScanIntake,
    encoding_name,
    error_kind,
)
from service.node.readiness import Readiness
from service.node.scheduler import LatestSlots, WorkerLink
from service.node.settings import ServiceSettings
from service.node.state import StateStore
from service.node.workers import config_request

__all__ = ["MAX_SCAN_BYTES", "LatestSlots", "RejectLog", "ServiceNode"]

log = logging.getLogger("shapeloc.service")

#: Scans of different robots a tracking worker takes in one request (see WorkerLink).
SCAN_BATCH = 8

_MSGPACK = codec.MSGPACK_ENCODING


class RejectLog:
    """Rate limit for rejection log lines: at most ``burst`` lines per kind per ``window_s``
    seconds; the number suppressed is logged with the next line of that kind after the
    window. Counting (health) and notices (``<prefix>/errors``) are never limited."""

    def __init__(self, burst: int = 10, window_s: float = 10.0) -> None:
        self.burst = burst
        self.window_s = window_s
        self._win: dict[str, tuple[float, int, int]] = {}  # kind -> (start, logged, suppressed)
        self._lock = threading.Lock()

    def should_log(self, kind: str, now: float | None = None) -> tuple[bool, int]:
        """``(log this one?, lines suppressed in the window that just ended)``."""
        t = time.monotonic() if now is None else now
        with self._lock:
            start, logged, suppressed = self._win.get(kind, (t, 0, 0))
            if t - start >= self.window_s:
                self._win[kind] = (t, 1, 0)
                return True, suppressed
            if logged < self.burst:
                self._win[kind] = (start, logged + 1, suppressed)
                return True, 0
            self._win[kind] = (start, logged, suppressed + 1)
            return False, 0


class ServiceNode(ClusterPlane, ControlPlane, ComputePlane):
    """The running service on an open Zenoh session.

    Use as ``node = ServiceNode(settings, session); node.start(); ...; node.stop()``; the
    caller owns (and closes) the session. ``start`` restores the state (raising
    :class:`StateError` if it is unreadable, unless ``settings.reset_state``) before
    declaring its queryables and liveliness token; one of several instances
    (:mod:`service.node.cluster`) first catches up with the live ones.
    """

    def __init__(self, settings: ServiceSettings, session: Any) -> None:
        import zenoh

        self.zenoh = zenoh
        self.settings = settings
        self.session = session
        self.prefix = settings.prefix
        self.instance_id = settings.effective_instance_id()
        self.worker_timeout_s = settings.worker_timeout_s
        self.index_timeout_s = settings.index_timeout_s
        self.lock = threading.RLock()
        # held while a map/config message or an ownership change is applied
        self._control_mutex = threading.RLock()
        self._ready = False  # scans are taken only once the state is restored
        self.stopping = threading.Event()
        self._started = time.monotonic()
        self.maps: dict[str, tuple[Map, MapData]] = {}
        self.configs: dict[str, RobotConfig] = {}
        self.poses: dict[str, PoseMsg] = {}
        # last odometry pose (odometry frame) each robot's localiser has seen: that of the last
        # scan carrying one, saved with the pose so a restart measures the next increment from it
        self.odoms: dict[str, tuple[float, float, float]] = {}
        self._dirty: set[str] = set()
        self.scans_processed = 0
        self.scans_rejected = 0
        self.errors: Counter[str] = Counter()
        self.scan_cpu_ms: deque[float] = deque(maxlen=4096)
        #: which maps are prepared (and indexed), whether the workers have warmed up
        self.readiness = Readiness(indexing=False)
        self.clock = ControlClock()
        self.intake = ScanIntake(
            accept=self._offer_scan,
            reject=lambda key, exc: self.reject(key, "scan", exc),
            per_robot=settings.intake_per_robot,
            max_bytes=settings.intake_queue_bytes,
            count_reject=self._count_reject,
        )
        self._reject_log = RejectLog()
        self._control_q: queue.Queue[Inbound | None] = queue.Queue(settings.control_queue_size)
        self._query_q: queue.Queue[Any] = queue.Queue(settings.query_queue_size)
        self._control_overflow = 0
        self._control_bytes = 0
        self._dropped_reported = 0
        self._entities: list[Any] = []
        self._threads: list[threading.Thread] = []
        self._errors_pub: Any = None
        self.state: StateStore | None = None
        self.links: list[WorkerLink] = []
        self.assignment = Assignment(1)
        self.search_link: WorkerLink | None = None
        #: held by the control thread while it applies a configuration, and by a link thread
        #: while it moves a robot between workers (never both)
        self.migrate_lock = threading.Lock()
        self._init_cluster()

    # ------------------------------------------------------------------ lifecycle
    def start(self) -> None:
        """Open and restore the state, start workers and threads, then declare the Zenoh
        entities. Only the subscriber exists before the state is restored (so that a map or
        config put while an instance catches up is queued, not lost); queryables and the
        liveliness token come after."""
        restored = self._open_state()
        n = max(1, self.settings.workers)
        cap = self.settings.max_robots + 64
        # with worker processes, one more (at a lower priority) takes the robots that search:
        # a search then never holds a worker that tracked robots wait for
        extra = 1 if self.settings.workers > 0 and self.settings.search_worker else 0
        # tracking worker processes take the pending scans in batches (one request, a reply
        # each); the search worker one at a time (a search step takes tens of milliseconds),
        # in-process workers too (no pipe to save)
        batch = SCAN_BATCH if self.settings.workers > 0 else 1
        self.links = [
            WorkerLink(self, i, cap, batch=batch if i < n else 1) for i in range(n + extra)
        ]
        self.search_link = self.links[n] if extra else None
        self.assignment = Assignment(n, extra)
        self.readiness = Readiness(indexing=self.search_link is not None)
        # One subscriber for maps, configs, scans and (mirrored) poses: its callback sees them
        # in arrival order, which keeps "put map, put config, put scan" from one client causal.
        self._entities.append(self.session.declare_subscriber(f"{self.prefix}/**", self._on_sample))
        peers = self._catch_up()
        if peers:
            restored = self._reload_state(restored)
        self._init_view(peers)
        self._restore(restored)
        self._warm_workers()
        for link in self.links:
            link.thread.start()
        # done once each tracking worker has warmed up (a process warms up before its first
        # reply); the restored maps were prepared by _restore, their indexes are built now
        self.readiness.warming(link.submit(("ping",)) for link in self.links[:n])
        for map_id in sorted(self.maps):
            version = self.readiness.stored(map_id)
            self.readiness.prepared(map_id, version)
            self.build_index(map_id, version)
        self.intake.start()
        self._threads = [
            threading.Thread(target=self._control_loop, name="shapeloc-control", daemon=True),
            threading.Thread(target=self._query_loop, name="shapeloc-query", daemon=True),
        ]
        for t in self._threads:
            t.start()
        self._ready = True
        self._declare()
        self._declare_membership()
        log.info(
            "service %s serving prefix %r, robots %r, shard %s: %d maps, %d robots restored "
            "(%d of other instances mirrored), %d workers",
            self.instance_id,
            self.prefix,
            self.settings.robots,
            self.settings.shard,
            len(self.maps),
            len(self.configs),
            len(self.mirror),
            self.settings.workers,
        )

    def uptime_s(self) -> float:
        """Seconds since the node was created."""
        return time.monotonic() - self._started

    def _declare(self) -> None:
        s = self.session
        p = self.prefix
        self._errors_pub = s.declare_publisher(keys.errors_key(p))
        self._entities.append(self._errors_pub)
        for ke in (
            keys.maps_wildcard(p),
            keys.robots_wildcard(p, "pose"),
            keys.health_key(p),
            keys.state_selector(p, self.instance_id),
        ):
            self._entities.append(s.declare_queryable(ke, self._on_query))
        self._token = s.liveliness().declare_token(keys.alive_key(p, self.instance_id))
        self._entities.append(self._token)

    def stop(self) -> None:
        """Undeclare entities, stop threads and workers, save poses, close the state."""
        if self.stopping.is_set():
            return
        self.stopping.set()
        for e in reversed(self._entities):
            with contextlib.suppress(Exception):
                e.undeclare()
        self._entities.clear()
        self.intake.stop()
        for link in self.links:
            link.slots.kick()
        for q in (self._control_q, self._query_q):
            with contextlib.suppress(queue.Full):
                q.put_nowait(None)  # wake the thread so it sees the stop flag
        for t in [*self._threads, *(lk.thread for lk in self.links)]:
            if t.is_alive():
                t.join(timeout=self.settings.worker_timeout_s + 5)
        try:
            self.save_poses()
        except StateError as e:
            log.error("could not save poses on shutdown: %s", e)
        for link in self.links:
            link.worker.close()
        if self.state is not None:
            self.state.close()
        log.info("service %s stopped", self.instance_id)

    # ------------------------------------------------------------------ state
    def _open_state(self) -> Restored:
        """Open the store and parse everything in it. With ``reset_state``, an unreadable
        file (or one holding an invalid map, config or pose) is moved aside and the service
        starts empty, loudly; without it the :class:`StateError` propagates (exit 1)."""
        reset = self.settings.reset_state
        self.state = StateStore(self.settings.state_dir, reset=reset)
        try:
            restored = load_state(self.state)
        except StateError as e:
            if not reset:
                self.state.close()
                raise
            self.state.quarantine(str(e))
            restored = Restored({}, {}, {})
        for moved_to, why in self.state.quarantined:
            with self.lock:
                self.errors["state.Reset"] += 1
            log.error(
                "--reset-state: state file %s was unusable (%s); moved it to %s and started "
                "with NO maps and NO robots",
                self.state.path,
                why,
                moved_to,
            )
        return restored

    def _reload_state(self, before: Restored) -> Restored:
        """The store again after catching up (what the live instances told us is in it)."""
        assert self.state is not None
        try:
            return load_state(self.state)
        except StateError as e:
            log.error("state after catching up is unreadable (%s); using the own state", e)
            return before

    def _restore(self, r: Restored) -> None:
        """Hand the restored maps and this instance's robots (in id order) to the workers; a
        restored robot resumes from its saved pose and the odometry pose saved with it. The
        robots of other instances are mirrored (:mod:`service.node.cluster`)."""
        t = self.settings.worker_timeout_s
        for map_id, (msg, md) in r.maps.items():
            self.maps[map_id] = (msg, md)
            for link in self.links:
                link.worker.call(("map", md), t)
        for robot_id, cfg in r.configs.items():
            pm = r.poses.get(robot_id)
            start = None if pm is None else as_list(pm.pose)
            odom = None if pm is None else r.odoms.get(robot_id)
            if not self.serves(robot_id):
                self.mirror.put(robot_id, cfg, pm, odom)
                continue
            if pm is not None:
                self.poses[robot_id] = pm
            if odom is not None:
                self.odoms[robot_id] = odom
            self.configs[robot_id] = cfg
            link = self.links[self.assignment.assign(robot_id)]
            st, why = link.worker.call(config_request(robot_id, cfg, start, as_list(odom)), t)
            if st != "ok":
                log.error("restored robot %s could not be set up: %s", robot_id, why)

    # ------------------------------------------------------------------ workers
    def _link_of(self, robot_id: str) -> WorkerLink:
        return self.links[self.assignment.index_of(robot_id)]

    # ------------------------------------------------------------------ callbacks
    def classify(self, key: str) -> tuple[str, str]:
        """``("scan" | "control" | "other", robot_id)`` of a key below the prefix."""
        head = self.prefix + "/"
        if not key.startswith(head):
            return ("other", "")
        parts = key[len(head) :].split("/")
        if parts[0] == "maps" and len(parts) == 2:
            return ("control", "")
        if parts[0] == "robots" and len(parts) == 3:
            if parts[2] == "scan":
                return ("scan", parts[1])
            if parts[2] == "config":
                return ("control", parts[1])
            if parts[2] == "pose":
                return ("pose", parts[1])
        return ("other", "")

    def _on_sample(self, sample: Any) -> None:
        """Zenoh callback of ``<prefix>/**``: route scans to the intake, maps/configs to the
        control queue, other instances' poses to the mirror, ignore the rest (errors, truth).
        No decoding, no compute."""
        kind, robot_id = self.classify(str(sample.key_expr))
        if kind == "scan":
            self._on_scan(sample, robot_id)
        elif kind == "control":
            self._on_control(sample)
        elif kind == "pose":
            self._on_pose_sample(sample, robot_id)

    def _on_scan(self, sample: Any, robot_id: str) -> None:
        """Copy a scan sample into the intake queue after O(1) checks (no decoding here)."""
        t = time.monotonic()
        if not self._ready or not self.serves(robot_id):
            return
        if robot_id not in self.configs and self.mirror.known(robot_id):
            with self.lock:  # ours now, being taken over from the mirror: not an unknown robot
                self.errors["scan.HandedOver"] += 1
            return
        key = str(sample.key_expr)
        size = len(sample.payload)
        ctl = self.clock.needed(robot_id)
        reject: ShapelocError | None = None
        if sample.kind == self.zenoh.SampleKind.DELETE:
            reject = InvalidMessage("a scan cannot be deleted")
        elif size > MAX_SCAN_BYTES:
            reject = InvalidMessage(f"payload of {size} bytes exceeds {MAX_SCAN_BYTES}")
        elif robot_id not in self.configs and self.clock.applied >= ctl:
            # no configuration and none pending: the payload is not kept (bounds the memory
            # and CPU that unknown robot ids can take)
            reject = UnknownRobot(
                f"robot {robot_id!r} has no configuration; put "
                f"{self.prefix}/robots/{robot_id}/config first"
            )
        if reject is not None:
            item = RawScan(robot_id, key, None, None, t, ctl, reject)
        else:
            payload = sample.payload.to_bytes()
            item = RawScan(robot_id, key, payload, encoding_name(sample.encoding), t, ctl)
        self.intake.put(item)

    def control_item(self, sample: Any) -> Inbound | None:
        """Copy a map/config sample into an :class:`Inbound` (configs of robots another
        instance serves too: they are mirrored, :meth:`mirror_config`; ``None``: an oversize
        config of such a robot, which its owner rejects)."""
        t = time.monotonic()
        key = str(sample.key_expr)
        delete = sample.kind == self.zenoh.SampleKind.DELETE
        size = len(sample.payload)
        if size > MAX_PAYLOAD_BYTES:
            parts = key.rsplit("/", 2)
            if "/robots/" in key and len(parts) == 3 and not self.serves(parts[-2]):
                return None
            return Inbound(
                key, None, None, t, reject=f"payload of {size} bytes exceeds {MAX_PAYLOAD_BYTES}"
            )
        return Inbound(
            key, sample.payload.to_bytes(), encoding_name(sample.encoding), t, delete=delete
        )

    def _on_control(self, sample: Any) -> None:
        """Zenoh callback: queue a map/config put or delete for the control thread."""
        item = self.control_item(sample)
        if item is None:
            return
        size = 0 if item.payload is None else len(item.payload)
        try:
            with self.lock:
                if self._control_bytes + size > self.settings.control_queue_bytes:
                    raise queue.Full
                self._control_bytes += size
            self._control_q.put_nowait(dataclasses.replace(item, ctl=self.clock.received + 1))
            # only this callback thread numbers control messages
            self.clock.next(self.classify(item.key)[1])
        except queue.Full:
            with self.lock:
                self._control_overflow += 1
                self.errors["control.Overloaded"] += 1

    def _on_query(self, query: Any) -> None:
        """Zenoh callback: queue the query for the query thread (answered at once with
        ``reply_err`` if the queue is full)."""
        try:
            self._query_q.put_nowait(query)
        except queue.Full:
            with contextlib.suppress(Exception):
                query.reply_err(b"service overloaded: query queue full")
                query.drop()

    # ------------------------------------------------------------------ errors
    def reject(self, key: str, what: str, exc: BaseException | str) -> None:
        """Count a rejected message, log it (rate-limited) and publish its notice."""
        if isinstance(exc, BaseException):
            kind, text = error_kind(exc), str(exc)
        else:
            kind, text = "InvalidMessage", exc
        name = f"{what}.{kind}"
        with self.lock:
            self.errors[name] += 1
            if what == "scan":
                self.scans_rejected += 1
        log_it, suppressed = self._reject_log.should_log(name)
        if suppressed:
            log.warning("%d more %s rejections were not logged", suppressed, name)
        if log_it:
            log.warning("rejected %s on %s: %s", what, key, text)
        self._notice(key, f"{kind}: {text}")

    def _count_reject(self, key: str, exc: BaseException) -> None:
        """Count a scan rejection whose notice is dropped in a flood (Zenoh callback)."""
        with self.lock:
            self.errors[f"scan.{error_kind(exc)}"] += 1
            self.scans_rejected += 1

    def _notice(self, key: str, text: str) -> None:
        if self._errors_pub is None:
            return
        try:
            self._errors_pub.put(codec.encode(ErrorNotice.make(key, text)), encoding=_MSGPACK)
        except Exception as e:
            log.error("could not publish error notice: %s", e)

    # ------------------------------------------------------------------ queries
    def _query_loop(self) -> None:
        while not self.stopping.is_set():
            try:
                query = self._query_q.get(timeout=0.5)
            except queue.Empty:
                continue
            if query is None:
                continue
            try:
                self.answer(query)
            except Exception:
                log.exception("unexpected error answering %s", query.key_expr)
                with contextlib.suppress(Exception):
                    query.reply_err(b"internal error")
            finally:
                with contextlib.suppress(Exception):
                    query.drop()

    def answer(self, query: Any) -> None:
        """Reply to one ``get`` (see :func:`service.node.queries.answer`)."""
        queries.answer(self, query)

    def health(self) -> Health:
        """Current health message (see :func:`service.node.queries.health`)."""
        return queries.health(self)
