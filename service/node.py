"""The Zenoh transport layer of the localizer service.

:class:`ServiceNode` owns the session entities (subscribers, queryables, liveliness token),
the in-memory view of maps / robot configurations / last poses, the :class:`StateStore` and
one *link thread* per worker. Zenoh callbacks only copy bytes into queues or latest-wins
slots; decoding, persistence and localisation run in the node's own threads:

* control thread: map and config puts/deletes (FIFO), periodic pose saving;
* query thread: ``get`` on maps, poses and health (FIFO);
* one link thread per worker: forwards control changes to its worker, then takes the next
  robot with a pending scan (round robin over robots; per robot only the newest unprocessed
  scan is kept), validates it, runs it on the worker and publishes the pose.

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
from collections import Counter, OrderedDict
from concurrent.futures import Future
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from schemas import codec, keys
from schemas.limits import MAX_PAYLOAD_BYTES
from schemas.messages import ErrorNotice, Health, Map, PoseMsg, RobotConfig, Scan
from service import __version__
from service.convert import map_data_of
from service.core.types import MapData
from service.errors import (
    InvalidMessage,
    LocalizationError,
    ServiceTimeout,
    ShapelocError,
    StateError,
    UnknownMap,
    UnknownRobot,
)
from service.settings import ServiceSettings
from service.state import SavedPose, StateStore
from service.workers import Assignment, InlineWorker, ProcessWorker, WorkerDiedError

log = logging.getLogger("shapeloc.service")

_MSGPACK = codec.MSGPACK_ENCODING

#: Largest scan payload kept for decoding (bytes): 8192 beams as JSON text fit in ~200 KiB, so
#: anything bigger is rejected in the callback without copying it.
MAX_SCAN_BYTES = 512 * 1024
VIEW_CACHE_DIR = "viewcache"  # under the state dir: per-map view index of global localisation

# --------------------------------------------------------------------------- pure helpers


@dataclass(frozen=True)
class Inbound:
    """One received sample, as copied out of a Zenoh callback.

    ``payload`` is ``None`` when the callback already rejected it (``reject`` says why);
    ``t_recv`` is ``time.monotonic()`` seconds at reception. ``ctl`` is the number of control
    messages (maps, configs) received before it (for a control message: its own number), so a
    scan is only processed once every map/config received before it has been applied.
    """

    key: str
    payload: bytes | None
    encoding: str | None
    t_recv: float
    delete: bool = False
    reject: str | None = None
    ctl: int = 0


def encoding_name(enc: object) -> str | None:
    """The sample's encoding as a string (the codec decides JSON vs msgpack from it)."""
    return None if enc is None else str(enc)


def error_kind(exc: BaseException) -> str:
    """Counter name of a rejection: the exception class name (``InvalidMessage``, ...)."""
    return type(exc).__name__


def scan_arrays_of(msg: Scan) -> tuple[np.ndarray, np.ndarray]:
    """``(ranges, angles)`` of a scan: ranges in metres with NaN for no return, angles in
    radians in the robot frame."""
    return codec.scan_arrays(msg)


class LatestSlots:
    """Per-robot latest-wins slots with round-robin order over robots (thread-safe).

    :meth:`offer` keeps only the newest item per robot (the replaced one is counted as
    skipped) and never blocks; a robot keeps its place in the round-robin order while it has a
    pending item, so a robot that publishes fast cannot starve the others. At most ``capacity``
    robots can be pending; further new robots are refused (``offer`` returns ``False``).
    """

    def __init__(self, capacity: int) -> None:
        self._items: OrderedDict[str, Any] = OrderedDict()
        self._cond = threading.Condition()
        self.capacity = capacity
        self.skipped = 0
        self.refused = 0
        self._kick = False

    def offer(self, robot_id: str, item: Any) -> bool:
        """Store ``item`` as the newest pending item of ``robot_id``."""
        with self._cond:
            if robot_id in self._items:
                self.skipped += 1
                self._items[robot_id] = item
            elif len(self._items) >= self.capacity:
                self.refused += 1
                return False
            else:
                self._items[robot_id] = item
            self._cond.notify()
            return True

    def kick(self) -> None:
        """Wake a waiting :meth:`take` (it returns ``None`` once)."""
        with self._cond:
            self._kick = True
            self._cond.notify_all()

    def take(self, timeout_s: float | None = None) -> tuple[str, Any] | None:
        """Oldest pending robot and its newest item, or ``None`` on timeout / kick."""
        with self._cond:
            if not self._items and not self._kick:
                self._cond.wait(timeout_s)
            self._kick = False
            if not self._items:
                return None
            return self._items.popitem(last=False)

    def discard(self, robot_id: str) -> None:
        """Drop a pending item (robot forgotten)."""
        with self._cond:
            self._items.pop(robot_id, None)

    def __len__(self) -> int:
        with self._cond:
            return len(self._items)


# --------------------------------------------------------------------------- the node


class _Link:
    """A worker plus the thread that feeds it (control requests first, then scans)."""

    def __init__(self, node: ServiceNode, index: int) -> None:
        self.node = node
        self.index = index
        self.worker: ProcessWorker | InlineWorker = node._new_worker(index)
        self.slots = LatestSlots(capacity=node.settings.max_robots + 64)
        self.control: queue.SimpleQueue[tuple[tuple[Any, ...], Future[Any]]] = queue.SimpleQueue()
        self.thread = threading.Thread(target=self._run, name=f"shapeloc-link-{index}", daemon=True)

    def submit(self, req: tuple[Any, ...]) -> Future[Any]:
        """Queue a control request for this worker; the future gets its reply tuple."""
        fut: Future[Any] = Future()
        self.control.put((req, fut))
        self.slots.kick()
        return fut

    def call(self, req: tuple[Any, ...]) -> tuple[str, Any]:
        """Run a request on the worker, restarting it (and failing this request) if it dies."""
        try:
            return self.worker.call(req, self.node.settings.worker_timeout_s)
        except (WorkerDiedError, ServiceTimeout) as e:
            log.error("worker %d: %s; restarting it", self.index, e)
            self.node._restart_worker(self)
            return ("err", str(e))

    def _drain_control(self) -> None:
        while True:
            try:
                req, fut = self.control.get_nowait()
            except queue.Empty:
                return
            fut.set_result(self.call(req))

    def _await_control(self, ctl: int, timeout_s: float = 5.0) -> None:
        """Wait until control message ``ctl`` (and all before it) is applied, serving this
        worker's control requests meanwhile (the control thread may be waiting on them)."""
        node = self.node
        deadline = time.monotonic() + timeout_s
        while not node._stopping.is_set() and time.monotonic() < deadline:
            self._drain_control()
            with node._ctl_cond:
                if node._ctl_applied >= ctl:
                    return
                node._ctl_cond.wait(0.005)

    def _run(self) -> None:
        node = self.node
        while not node._stopping.is_set():
            self._drain_control()
            got = self.slots.take(timeout_s=0.5)
            if got is None:
                continue
            robot_id, inbound = got
            self._await_control(inbound.ctl)
            try:
                node._process_scan(self, robot_id, inbound)
            except Exception:  # never let the link die
                log.exception("unexpected error processing a scan of %s", robot_id)
        # drain control so no caller waits forever
        while True:
            try:
                _req, fut = self.control.get_nowait()
            except queue.Empty:
                break
            fut.set_result(("err", "service is shutting down"))


class ServiceNode:
    """The running service on an open Zenoh session.

    Use as ``node = ServiceNode(settings, session); node.start(); ...; node.stop()``; the
    caller owns (and closes) the session. ``start`` restores the state (raising
    :class:`StateError` if it is unreadable) before declaring anything on the network.
    """

    def __init__(self, settings: ServiceSettings, session: Any) -> None:
        import zenoh

        self._zenoh = zenoh
        self.settings = settings
        self.session = session
        self.prefix = settings.prefix
        self.instance_id = settings.effective_instance_id()
        self._robots_ke = zenoh.KeyExpr(settings.robots)
        self._shard_cache: dict[str, bool] = {}
        self._lock = threading.RLock()
        self._stopping = threading.Event()
        self._started = time.monotonic()
        self.maps: dict[str, tuple[Map, MapData]] = {}
        self.configs: dict[str, RobotConfig] = {}
        self.poses: dict[str, PoseMsg] = {}
        self._dirty: set[str] = set()
        self.scans_processed = 0
        self.scans_rejected = 0
        self.errors: Counter[str] = Counter()
        self._control_q: queue.Queue[Inbound | None] = queue.Queue(settings.control_queue_size)
        self._query_q: queue.Queue[Any] = queue.Queue(settings.query_queue_size)
        self._control_overflow = 0
        self._control_bytes = 0
        self._ctl_received = 0
        self._ctl_applied = 0
        self._ctl_cond = threading.Condition()
        self._entities: list[Any] = []
        self._threads: list[threading.Thread] = []
        self.state: StateStore | None = None
        self.links: list[_Link] = []
        self.assignment = Assignment(1)

    # ------------------------------------------------------------------ lifecycle
    def _new_worker(self, index: int) -> ProcessWorker | InlineWorker:
        # Global localisation caches each map's view index here (rebuilt when the map changes).
        cache_dir = Path(self.settings.state_dir) / VIEW_CACHE_DIR
        if self.settings.workers == 0:
            return InlineWorker(index, cache_dir)
        return ProcessWorker(index, self.settings.log_level, cache_dir)

    def start(self) -> None:
        """Open the state, start workers, restore, then declare the Zenoh entities."""
        self.state = StateStore(self.settings.state_dir)
        n = max(1, self.settings.workers)
        self.links = [_Link(self, i) for i in range(n)]
        self.assignment = Assignment(n)
        self._restore()
        for link in self.links:
            link.thread.start()
        self._threads = [
            threading.Thread(target=self._control_loop, name="shapeloc-control", daemon=True),
            threading.Thread(target=self._query_loop, name="shapeloc-query", daemon=True),
        ]
        for t in self._threads:
            t.start()
        self._declare()
        log.info(
            "service %s serving prefix %r, robots %r: %d maps, %d robots restored, %d workers",
            self.instance_id,
            self.prefix,
            self.settings.robots,
            len(self.maps),
            len(self.configs),
            self.settings.workers,
        )

    def _declare(self) -> None:
        z = self._zenoh
        s = self.session
        p = self.prefix
        self._errors_pub = s.declare_publisher(keys.errors_key(p))
        self._entities.append(self._errors_pub)
        # One subscriber for maps, configs and scans: its callback sees them in arrival order,
        # which keeps "put map, put config, put scan" from one client causal.
        self._entities.append(s.declare_subscriber(f"{p}/**", self._on_sample))
        for ke in (
            keys.maps_wildcard(p),
            keys.robots_wildcard(p, "pose"),
            keys.health_key(p),
        ):
            self._entities.append(s.declare_queryable(ke, self._on_query))
        self._token = s.liveliness().declare_token(keys.alive_key(p, self.instance_id))
        self._entities.append(self._token)
        _ = z

    def stop(self) -> None:
        """Undeclare entities, stop threads and workers, save poses, close the state."""
        if self._stopping.is_set():
            return
        self._stopping.set()
        for e in reversed(self._entities):
            with contextlib.suppress(Exception):
                e.undeclare()
        self._entities.clear()
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

    # ------------------------------------------------------------------ restore
    def _restore(self) -> None:
        assert self.state is not None
        for map_id, wire in self.state.maps().items():
            try:
                msg = Map.parse(wire)
                md = map_data_of(msg)
            except ShapelocError as e:
                raise StateError(f"stored map {map_id!r} is invalid: {e}") from e
            self.maps[map_id] = (msg, md)
            for link in self.links:
                link.worker.call(("map", md), self.settings.worker_timeout_s)
        saved = self.state.poses()
        for robot_id, wire in self.state.robots().items():
            try:
                cfg = RobotConfig.parse(wire)
            except ShapelocError as e:
                raise StateError(f"stored config of robot {robot_id!r} is invalid: {e}") from e
            if not self.serves(robot_id):
                continue
            sp = saved.get(robot_id)
            start = None
            if sp is not None and sp.map_id == cfg.map_id:
                start = list(sp.pose)
                try:
                    self.poses[robot_id] = PoseMsg(
                        robot_id=robot_id,
                        seq=sp.seq,
                        stamp=sp.stamp,
                        pose=start,
                        status=sp.status,
                        score=0.0,
                        method=cfg.method,
                        map_id=cfg.map_id,
                        latency_ms=0.0,
                    )
                except ShapelocError as e:
                    raise StateError(f"stored pose of robot {robot_id!r} is invalid: {e}") from e
            self.configs[robot_id] = cfg
            link = self.links[self.assignment.assign(robot_id)]
            st, why = link.worker.call(
                ("config", robot_id, cfg.method, cfg.map_id, _lst(cfg.initial_pose), start),
                self.settings.worker_timeout_s,
            )
            if st != "ok":
                log.error("restored robot %s could not be set up: %s", robot_id, why)

    # ------------------------------------------------------------------ sharding
    def serves(self, robot_id: str) -> bool:
        """Whether this instance's ``--robots`` key expression covers ``robot_id``."""
        hit = self._shard_cache.get(robot_id)
        if hit is None:
            try:
                hit = bool(self._robots_ke.intersects(self._zenoh.KeyExpr(robot_id)))
            except Exception:
                hit = True  # invalid ids are rejected (with a notice) further on
            if len(self._shard_cache) < 100_000:
                self._shard_cache[robot_id] = hit
        return hit

    def _link_of(self, robot_id: str) -> _Link:
        return self.links[self.assignment.index_of(robot_id)]

    def _restart_worker(self, link: _Link) -> None:
        with contextlib.suppress(Exception):
            link.worker.close()
        link.worker = self._new_worker(link.index)
        t = self.settings.worker_timeout_s
        with self._lock:
            maps = [md for _m, md in self.maps.values()]
            robots = [
                (rid, cfg, self.poses.get(rid))
                for rid, cfg in self.configs.items()
                if self._link_of(rid) is link
            ]
        for md in maps:
            link.worker.call(("map", md), t)
        for rid, cfg, pm in robots:
            start = None if pm is None else _lst(pm.pose)
            link.worker.call(
                ("config", rid, cfg.method, cfg.map_id, _lst(cfg.initial_pose), start), t
            )

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
        return ("other", "")

    def _on_sample(self, sample: Any) -> None:
        """Zenoh callback of ``<prefix>/**``: route scans to slots, maps/configs to the control
        queue, ignore the rest (poses, errors, truth). No decoding, no compute."""
        kind, robot_id = self.classify(str(sample.key_expr))
        if kind == "scan":
            self._on_scan(sample, robot_id)
        elif kind == "control":
            self._on_control(sample)

    def _on_scan(self, sample: Any, robot_id: str) -> None:
        """Copy the scan into its robot's latest-wins slot (no compute)."""
        t = time.monotonic()
        key = str(sample.key_expr)
        if not self.serves(robot_id):
            return
        delete = sample.kind == self._zenoh.SampleKind.DELETE
        size = len(sample.payload)
        ctl = self._ctl_received
        if delete:
            item = Inbound(key, None, None, t, delete=True, reject="a scan cannot be deleted")
        elif size > MAX_SCAN_BYTES:
            item = Inbound(
                key, None, None, t, reject=f"payload of {size} bytes exceeds {MAX_SCAN_BYTES}"
            )
        elif robot_id not in self.configs and self._ctl_applied >= ctl:
            # no configuration and none pending: rejected later as UnknownRobot, so the
            # payload is not kept (bounds the memory unknown robot ids can take)
            item = Inbound(key, None, None, t)
        else:
            item = Inbound(key, sample.payload.to_bytes(), encoding_name(sample.encoding), t)
        item = dataclasses.replace(item, ctl=ctl)
        if not self._link_of(robot_id).slots.offer(robot_id, item):
            reason = f"service overloaded: more than {self.settings.max_robots} robots pending"
            self._queue_notice(Inbound(key, None, None, t, reject=reason))

    def _queue_notice(self, item: Inbound) -> None:
        """Have the control thread publish a rejection decided in a callback."""
        try:
            self._control_q.put_nowait(item)
        except queue.Full:
            with self._lock:
                self._control_overflow += 1
                self.errors["control.Overloaded"] += 1

    def control_item(self, sample: Any) -> Inbound | None:
        """Copy a map/config sample into an :class:`Inbound` (``None``: another shard's robot)."""
        t = time.monotonic()
        key = str(sample.key_expr)
        if "/robots/" in key:
            parts = key.rsplit("/", 2)
            if len(parts) == 3 and not self.serves(parts[-2]):
                return None
        delete = sample.kind == self._zenoh.SampleKind.DELETE
        size = len(sample.payload)
        if size > MAX_PAYLOAD_BYTES:
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
            with self._lock:
                if self._control_bytes + size > self.settings.control_queue_bytes:
                    raise queue.Full
                self._control_bytes += size
            self._control_q.put_nowait(dataclasses.replace(item, ctl=self._ctl_received + 1))
            self._ctl_received += 1  # only this callback thread writes it
        except queue.Full:
            with self._lock:
                self._control_overflow += 1
                self.errors["control.Overloaded"] += 1

    def _on_query(self, query: Any) -> None:
        """Zenoh callback: queue the query for the query thread (dropped if the queue is full,
        which finalises it with no reply)."""
        with contextlib.suppress(queue.Full):
            self._query_q.put_nowait(query)

    # ------------------------------------------------------------------ errors
    def reject(self, key: str, what: str, exc: BaseException | str) -> None:
        """Count a rejected message and publish its :class:`ErrorNotice`."""
        if isinstance(exc, BaseException):
            kind, text = error_kind(exc), str(exc)
        else:
            kind, text = "InvalidMessage", exc
        with self._lock:
            self.errors[f"{what}.{kind}"] += 1
            if what == "scan":
                self.scans_rejected += 1
        log.warning("rejected %s on %s: %s", what, key, text)
        notice = ErrorNotice.make(key, f"{kind}: {text}")
        try:
            self._errors_pub.put(codec.encode(notice), encoding=_MSGPACK)
        except Exception as e:
            log.error("could not publish error notice: %s", e)

    # ------------------------------------------------------------------ scans
    def _process_scan(self, link: _Link, robot_id: str, inbound: Inbound) -> None:
        key = inbound.key
        owner = self._link_of(robot_id)
        if owner is not link:  # assigned to another worker after the scan was queued here
            owner.slots.offer(robot_id, inbound)
            return
        if inbound.reject is not None:
            self.reject(key, "scan", InvalidMessage(inbound.reject))
            return
        try:
            keys.validate_id(robot_id, "robot_id")
            with self._lock:
                cfg = self.configs.get(robot_id)
                have_map = cfg is not None and cfg.map_id in self.maps
            if cfg is None:
                raise UnknownRobot(
                    f"robot {robot_id!r} has no configuration; put "
                    f"{self.prefix}/robots/{robot_id}/config first"
                )
            if inbound.payload is None:
                raise UnknownRobot(
                    f"scan of robot {robot_id!r} arrived before its configuration; put "
                    f"{self.prefix}/robots/{robot_id}/config first"
                )
            if not have_map:
                raise UnknownMap(
                    f"map {cfg.map_id!r} of robot {robot_id!r} is not stored (deleted?); the "
                    "robot waits for it"
                )
            assert inbound.payload is not None
            msg = codec.decode(Scan, inbound.payload, inbound.encoding)
            ranges, angles = scan_arrays_of(msg)
            odom = None if msg.odom is None else np.array(msg.odom, dtype=np.float64)
        except ShapelocError as e:
            self.reject(key, "scan", e)
            return
        status, out = link.call(("scan", robot_id, ranges, angles, odom))
        if status != "ok":
            self.reject(key, "scan", LocalizationError(str(out)))
            return
        try:
            pose_msg = PoseMsg(
                robot_id=robot_id,
                seq=msg.seq,
                stamp=msg.stamp,
                pose=out["pose"],
                status=out["status"],
                score=out["score"],
                method=cfg.method,
                map_id=cfg.map_id,
                latency_ms=(time.monotonic() - inbound.t_recv) * 1e3,
                covariance=out["covariance"],
                explained=_clip01(out["explained"]),
                ambiguity=_clip01(out["ambiguity"]),
            )
            payload = codec.encode(pose_msg)
        except ShapelocError as e:
            self.reject(key, "scan", LocalizationError(f"estimate not publishable: {e}"))
            return
        with self._lock:
            if self.configs.get(robot_id) is not cfg:
                return  # reconfigured meanwhile: this estimate belongs to the old config
            self.poses[robot_id] = pose_msg
            self._dirty.add(robot_id)
            self.scans_processed += 1
        self.session.put(keys.robot_key(self.prefix, robot_id, "pose"), payload, encoding=_MSGPACK)

    # ------------------------------------------------------------------ control
    def _control_loop(self) -> None:
        next_save = time.monotonic() + self.settings.pose_save_interval_s
        while not self._stopping.is_set():
            timeout = max(0.0, min(0.5, next_save - time.monotonic()))
            try:
                item = self._control_q.get(timeout=timeout)
            except queue.Empty:
                item = None
            if item is not None:
                with self._lock:
                    self._control_bytes -= 0 if item.payload is None else len(item.payload)
                try:
                    self.handle_control(item)
                except Exception:
                    log.exception("unexpected error on %s", item.key)
                finally:
                    with self._ctl_cond:
                        self._ctl_applied = max(self._ctl_applied, item.ctl)
                        self._ctl_cond.notify_all()
            with self._lock:
                overflow, self._control_overflow = self._control_overflow, 0
            if overflow:
                self.reject(
                    f"{self.prefix}/**", "control", f"control queue full: {overflow} dropped"
                )
            if time.monotonic() >= next_save:
                next_save = time.monotonic() + self.settings.pose_save_interval_s
                try:
                    self.save_poses()
                except StateError as e:
                    log.error("periodic pose save failed: %s", e)

    def handle_control(self, item: Inbound) -> None:
        """Apply one map or config put/delete (rejecting it with a notice if invalid)."""
        kind, _rid = self.classify(item.key)
        what = "scan" if kind == "scan" else "map" if "/maps/" in item.key else "config"
        try:
            if item.reject is not None:
                raise InvalidMessage(item.reject)
            if what == "scan":
                raise InvalidMessage("scan without a reason to reject")  # not reached
            if what == "map":
                self._handle_map(item)
            else:
                self._handle_config(item)
        except ShapelocError as e:
            self.reject(item.key, what, e)

    def _broadcast(self, req: tuple[Any, ...]) -> list[tuple[str, Any]]:
        futs = [link.submit(req) for link in self.links]
        t = self.settings.worker_timeout_s * 2 + 5
        return [f.result(timeout=t) for f in futs]

    def _handle_map(self, item: Inbound) -> None:
        assert self.state is not None
        map_id = keys.parse_map_key(self.prefix, item.key)
        if item.delete:
            with self._lock:
                known = map_id in self.maps
            if not known:
                raise UnknownMap(f"cannot delete map {map_id!r}: it is not stored")
            self.state.delete_map(map_id)
            log.info("map %s deleted (robots on it wait for a new one)", map_id)
            with self._lock:
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
        with self._lock:
            self.maps[map_id] = (msg, md)
        self._broadcast(("map", md))

    def _handle_config(self, item: Inbound) -> None:
        assert self.state is not None
        robot_id, _leaf = keys.parse_robot_key(self.prefix, item.key)
        if item.delete:
            with self._lock:
                known = robot_id in self.configs
            if not known:
                raise UnknownRobot(f"cannot delete config of robot {robot_id!r}: unknown robot")
            self.state.delete_robot(robot_id)
            log.info("robot %s removed", robot_id)
            with self._lock:
                self.configs.pop(robot_id, None)
                self.poses.pop(robot_id, None)
                self._dirty.discard(robot_id)
            link = self._link_of(robot_id)
            link.slots.discard(robot_id)
            link.submit(("forget", robot_id)).result()
            self.assignment.release(robot_id)
            return
        assert item.payload is not None
        cfg = codec.decode(RobotConfig, item.payload, item.encoding)
        with self._lock:
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
        link = self.links[self.assignment.assign(robot_id)]
        status, why = link.submit(
            ("config", robot_id, cfg.method, cfg.map_id, _lst(cfg.initial_pose), None)
        ).result(timeout=self.settings.worker_timeout_s * 2 + 5)
        if status != "ok":
            if new:
                self.assignment.release(robot_id)
            raise LocalizationError(f"robot {robot_id!r}: {why}")
        self.state.put_robot(robot_id, cfg.to_wire())
        log.info(
            "robot %s config stored (map %s, method %s, initial pose %s)",
            robot_id,
            cfg.map_id,
            cfg.method,
            None if cfg.initial_pose is None else _lst(cfg.initial_pose),
        )
        with self._lock:
            self.configs[robot_id] = cfg
            self.poses.pop(robot_id, None)
            self._dirty.discard(robot_id)

    def save_poses(self) -> int:
        """Write the poses that changed since the last save; returns how many."""
        with self._lock:
            dirty = {rid: self.poses[rid] for rid in self._dirty if rid in self.poses}
            self._dirty.clear()
        if not dirty or self.state is None:
            return 0
        self.state.save_poses(
            {
                rid: SavedPose(
                    p.map_id,
                    float(p.pose[0]),
                    float(p.pose[1]),
                    float(p.pose[2]),
                    p.seq,
                    p.stamp,
                    p.status,
                )
                for rid, p in dirty.items()
            }
        )
        return len(dirty)

    # ------------------------------------------------------------------ queries
    def _query_loop(self) -> None:
        while not self._stopping.is_set():
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
        """Reply to one ``get`` on maps, a robot pose or the health key."""
        z = self._zenoh
        ke = query.key_expr
        p = self.prefix
        health = keys.health_key(p)
        if ke.intersects(z.KeyExpr(health)):
            query.reply(health, codec.encode(self.health()), encoding=_MSGPACK)
        if ke.intersects(z.KeyExpr(keys.maps_wildcard(p))):
            with self._lock:
                items = [(mid, m) for mid, (m, _md) in self.maps.items()]
            hits = 0
            for mid, m in items:
                k = keys.map_key(p, mid)
                if ke.intersects(z.KeyExpr(k)):
                    query.reply(k, codec.encode(m), encoding=_MSGPACK)
                    hits += 1
            if hits == 0 and "*" not in str(ke):
                query.reply_err(f"unknown map: no map stored under {ke}".encode())
        if ke.intersects(z.KeyExpr(keys.robots_wildcard(p, "pose"))):
            with self._lock:
                robots = list(self.configs)
                poses = dict(self.poses)
            hits = 0
            for rid in robots:
                k = keys.robot_key(p, rid, "pose")
                if ke.intersects(z.KeyExpr(k)) and rid in poses:
                    query.reply(k, codec.encode(poses[rid]), encoding=_MSGPACK)
                    hits += 1
            if hits == 0 and "*" not in str(ke):
                parts = str(ke).split("/")
                rid = parts[-2] if len(parts) >= 2 else ""
                if not self.serves(rid):
                    return  # another shard answers for this robot
                if rid in robots:
                    query.reply_err(f"robot {rid!r} has no estimate yet".encode())
                else:
                    query.reply_err(f"unknown robot {rid!r}".encode())

    def health(self) -> Health:
        """Current health message (counts over this instance's robots)."""
        with self._lock:
            by_status = Counter(p.status for p in self.poses.values())
            skipped = sum(lk.slots.skipped for lk in self.links)
            errors = dict(self.errors)
            if skipped:
                errors["scan.Skipped"] = skipped
            return Health(
                status="ok",
                version=__version__,
                robots=len(self.configs),
                maps=len(self.maps),
                scans_processed=self.scans_processed,
                scans_rejected=self.scans_rejected,
                instance_id=self.instance_id,
                uptime_s=time.monotonic() - self._started,
                errors=errors,
                robots_by_status=dict(by_status),
            )


def _lst(a: Any) -> list[float] | None:
    return None if a is None else [float(v) for v in np.asarray(a).reshape(-1)]


def _clip01(v: float | None) -> float | None:
    return None if v is None else min(1.0, max(0.0, float(v)))
