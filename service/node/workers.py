"""Where localisation runs: per-robot localisers owned by workers (which worker owns which
robot: :mod:`service.node.assignment`).

:class:`WorkerCore` holds the maps and, for the robots it owns, their configuration, last
pose and localiser; :meth:`WorkerCore.handle` executes one request tuple and returns one reply
tuple. It runs either in the service process (:class:`InlineWorker`, ``--workers 0``) or in a
child process started with the ``spawn`` method (:class:`ProcessWorker`), which is the default
because the shape method is CPU-bound Python and one process saturates one core.

Requests (all picklable):

* ``("map", MapData)``: store/replace a map; robots on it restart from their last pose.
* ``("map_delete", map_id)``: drop a map; its robots are kept and fail on scans until a new
  map of that id is put.
* ``("config", robot_id, method, map_id, initial_pose | None, start_pose | None,
  start_odom | None)``: (re)create the robot's localiser at once (``start_pose`` overrides
  ``initial_pose``: restore from a saved pose; ``start_odom`` is the odometry pose at
  ``start_pose``, so the next scan's odometry increment is measured from it). On failure the
  previous configuration stays.
* ``("scan", robot_id, ranges, angles, odom | None, skipped_odom | None)``: one update; ranges
  in metres with NaN for no return, angles in radians in the robot frame, odom ``(x, y,
  theta)`` or ``None``; ``skipped_odom``: the odometry of the oldest scan this one replaced
  under latest-wins (see :meth:`WorkerCore._scan`), or ``None``.
* ``("forget", robot_id)``.
* ``("index", map_id)``: build (or load) the map's view index of global localisation into the
  on-disk cache (:func:`service.node.prepare.build_index`); replies the seconds taken.
* ``("batch", [request, ...])`` (a process worker's pipe only; :meth:`ProcessWorker.call_batch`):
  the requests in order, one reply for each sent as soon as it is ready.

A tracking worker process warms up (:func:`service.node.prepare.warm_up_worker`) before it
reports itself ready, and prepares every map it is given (:func:`service.node.prepare.
prepare_map`), so no robot pays for the first use of a worker or a map.

Replies are ``("ok", payload)`` or ``("err", reason)``; a scan's payload is a dict with
``pose`` (list of 3 floats, map frame), ``status``, ``score``, ``explained``, ``ambiguity``,
``covariance`` (9 floats row-major, or ``None``), ``hypotheses`` (int or ``None``),
``candidates`` (rows ``[x, y, theta, cost]``, or ``None``), ``state`` (the localiser's state
behind the status, or ``None``), ``unsettled`` (the robot
searches or was fixed by a search a few scans ago: the node keeps it on the search worker) and
``cpu_ms`` (the worker's CPU time for the request).
"""

from __future__ import annotations

import contextlib
import logging
import math
import multiprocessing as mp
import os
import pickle
import select
import signal
import time
import traceback
from collections.abc import Callable
from dataclasses import dataclass
from multiprocessing.connection import Connection
from pathlib import Path
from typing import Any

import numpy as np

from service.adapters.maps.index_files import IndexFiles
from service.core.factory import create_localizer
from service.core.types import Localizer, MapData, wrap_angle
from service.errors import LocalizationError, ServiceTimeout, ShapelocError
from service.node.prepare import build_index, prepare_map, warm_up_worker

log = logging.getLogger("shapeloc.service.worker")

Reply = tuple[str, Any]


@dataclass
class _Robot:
    method: str
    map_id: str
    initial_pose: np.ndarray | None
    last_pose: np.ndarray | None
    localizer: Localizer | None
    #: odometry pose (odometry frame) at ``last_pose``: the last one a scan carried
    last_odom: np.ndarray | None = None
    #: the laser's pose on the robot base (RobotConfig.laser_offset); None: at its origin
    laser_offset: np.ndarray | None = None
    #: the localiser starts at the initial pose without an odometry reading there and has
    #: localised no scan yet (the first scan's odometry is where the initial pose is)
    fresh: bool = False


def config_request(
    robot_id: str,
    config: Any,
    start: list[float] | None = None,
    start_odom: list[float] | None = None,
) -> tuple[Any, ...]:
    """The worker request configuring ``robot_id`` from its wire ``config`` (a
    ``RobotConfig``): method, map, initial pose, laser mounting, and where to start (the last
    pose ``start`` with the odometry pose ``start_odom`` there, or ``None``: the initial
    pose). Poses are lists of floats (they cross a process boundary)."""

    def listed(a: Any) -> list[float] | None:
        return None if a is None else [float(v) for v in np.asarray(a).reshape(-1)]

    return (
        "config",
        robot_id,
        config.method,
        config.map_id,
        listed(config.initial_pose),
        start,
        start_odom,
        listed(getattr(config, "laser_offset", None)),
    )


def _opt_float(v: Any) -> float | None:
    if v is None:
        return None
    f = float(v)
    return f if np.isfinite(f) else None


class WorkerCore:
    """Maps and per-robot localisers of one worker. Not thread-safe: one caller at a time."""

    def __init__(
        self,
        cache_dir: Path | None = None,
        search_budget_ms: float | None = None,
        search: bool = False,
    ) -> None:
        #: the search worker: maps are not prepared for tracking here (its robots search),
        #: their view index is built here instead (``("index", map_id)``)
        self.search = search
        self.maps: dict[str, MapData] = {}
        #: each map's model, shared by its robots' trackers (kept while the map is stored)
        self.models: dict[str, Any] = {}
        self.robots: dict[str, _Robot] = {}
        #: the view indexes of global localisation, one file per map
        self.index_store = None if cache_dir is None else IndexFiles(cache_dir)
        #: per-scan work of a global search while the robot is alone on this worker; half of
        #: it while other robots share the worker (ServiceSettings.search_budget_ms)
        self.search_budget_ms = search_budget_ms

    def handle(self, req: tuple[Any, ...]) -> Reply:
        """Execute one request; never raises (errors come back as ``("err", reason)``)."""
        kind = req[0]
        try:
            if kind == "scan":
                t0 = time.thread_time()
                out = self._scan(*req[1:])
                out["cpu_ms"] = (time.thread_time() - t0) * 1e3
                return ("ok", out)
            if kind == "map":
                self._map(req[1])
                return ("ok", None)
            if kind == "map_delete":
                self._map_delete(req[1])
                return ("ok", None)
            if kind == "config":
                self._config(*req[1:])
                return ("ok", None)
            if kind == "forget":
                self.robots.pop(req[1], None)
                return ("ok", None)
            if kind == "export":
                return ("ok", self._export(req[1]))
            if kind == "import":
                self._import(req[1], req[2])
                return ("ok", None)
            if kind == "ping":
                return ("ok", "pong")
            if kind == "index":
                md = self.maps.get(req[1])
                if md is None:
                    return ("err", f"map {req[1]!r} is not stored in this worker")
                return ("ok", build_index(md, self.index_store))
            return ("err", f"unknown worker request {kind!r}")
        except ShapelocError as e:
            return ("err", str(e))
        except Exception as e:  # a bug in a method must not take the worker down
            log.error("internal error on %s request:\n%s", kind, traceback.format_exc())
            return ("err", f"internal error: {type(e).__name__}: {e}")

    def _map(self, md: MapData) -> None:
        self.maps[md.map_id] = md
        self.models.pop(md.map_id, None)
        # imported here: the service process imports this module, and the model's compiled
        # kernels would cost it ~125 MB of memory with worker processes
        from service.core.sensor.mapmodel import MapModel

        with contextlib.suppress(LocalizationError):  # no segment: its robots get the error
            self.models[md.map_id] = MapModel.shared(md)
        for r in self.robots.values():
            if r.map_id == md.map_id:
                r.localizer = None  # rebuilt on the next scan from its last pose
        if not self.search:
            prepare_map(md)  # the map's first-use work, before the service calls it ready

    def _export(self, robot_id: str) -> bytes:
        """Hand a robot (configuration, last pose and odometry, localiser with its state)
        over to another worker: removed here, returned pickled. As bytes, so the service
        process only passes it on: unpickling a localiser there would import every method
        and the compiled kernels into it (+25 MB of the service's memory on the first move
        in a soak)."""
        r = self.robots.pop(robot_id, None)
        if r is None:
            raise LocalizationError(f"robot {robot_id!r} has no configuration in this worker")
        return pickle.dumps(r, protocol=pickle.HIGHEST_PROTOCOL)

    def _import(self, robot_id: str, robot: _Robot | bytes) -> None:
        """Take over a robot exported by another worker (its pickled state); its localiser is
        re-pointed at this worker's copy of the map (or rebuilt from the last pose when the
        map changed)."""
        if isinstance(robot, bytes):
            robot = pickle.loads(robot)  # only ever our own worker's export
        if not isinstance(robot, _Robot):
            raise LocalizationError(f"import of {robot_id!r}: not a robot state")
        md = self.maps.get(robot.map_id)
        loc = robot.localizer
        if loc is not None and (md is None or loc.map_data.map_id != md.map_id):
            loc = None
        if loc is not None and md is not None:
            loc.map_data = md
        robot.localizer = loc
        self.robots[robot_id] = robot

    def _map_delete(self, map_id: str) -> None:
        self.maps.pop(map_id, None)
        self.models.pop(map_id, None)
        for r in self.robots.values():
            if r.map_id == map_id:
                r.localizer = None

    def _config(
        self,
        robot_id: str,
        method: str,
        map_id: str,
        initial_pose: list[float] | None,
        start_pose: list[float] | None = None,
        start_odom: list[float] | None = None,
        laser_offset: list[float] | None = None,
    ) -> None:
        init = None if initial_pose is None else np.asarray(initial_pose, dtype=np.float64)
        mount = None if laser_offset is None else np.asarray(laser_offset, dtype=np.float64)
        start = None if start_pose is None else np.asarray(start_pose, dtype=np.float64)
        odom = None
        if start is not None and start_odom is not None:
            odom = np.asarray(start_odom, dtype=np.float64)
        md = self.maps.get(map_id)
        loc = None
        if md is not None:
            loc = self._create(method, md, start if start is not None else init, odom, mount)
        fresh = start is None and init is not None
        self.robots[robot_id] = _Robot(method, map_id, init, start, loc, odom, mount, fresh)

    def _create(
        self,
        method: str,
        md: MapData,
        start: np.ndarray | None,
        odom: np.ndarray | None = None,
        laser_offset: np.ndarray | None = None,
    ) -> Localizer:
        """A localiser at ``start`` (the base's pose, map frame); with ``odom`` (the base's
        odometry pose at ``start``), the next scan's odometry increment is measured from it;
        ``laser_offset``: the laser's pose on the base."""
        loc = create_localizer(
            method,
            md,
            start,
            index_store=self.index_store,
            search_budget_ms=self.search_budget_ms,
            laser_offset=laser_offset,
        )
        if start is not None and odom is not None:
            loc.reset(start, odom)
        return loc

    def _scan(
        self,
        robot_id: str,
        ranges: np.ndarray,
        angles: np.ndarray,
        odom: np.ndarray | None,
        skipped_odom: np.ndarray | None = None,
    ) -> dict[str, Any]:
        """Localise one scan of ``robot_id``. ``skipped_odom`` is the odometry of the oldest
        scan this one replaced under latest-wins: when the robot's localiser starts at its
        initial pose without an odometry reading and has localised no scan yet, the initial
        pose is where that replaced scan was taken, so the odometry increment of this scan is
        measured from it (otherwise the localiser measures it from the last scan it
        localised, which is exact whatever was skipped in between)."""
        r = self.robots.get(robot_id)
        if r is None:
            raise LocalizationError(f"robot {robot_id!r} has no configuration in this worker")
        md = self.maps.get(r.map_id)
        if md is None:
            raise LocalizationError(
                f"map {r.map_id!r} of robot {robot_id!r} was deleted; the robot waits for a "
                "map of that id to be put again"
            )
        if r.localizer is None:
            if r.last_pose is not None:
                r.localizer = self._create(r.method, md, r.last_pose, r.last_odom, r.laser_offset)
            else:
                r.localizer = self._create(
                    r.method, md, r.initial_pose, laser_offset=r.laser_offset
                )
                r.fresh = r.initial_pose is not None
        if (
            r.fresh
            and odom is not None
            and skipped_odom is not None
            and not np.array_equal(skipped_odom, odom)
        ):
            r.localizer.reset(r.initial_pose, np.asarray(skipped_odom, dtype=np.float64))
        r.fresh = False
        set_budget = getattr(r.localizer, "set_search_budget", None)
        if self.search_budget_ms is not None and set_budget is not None:
            # the whole budget only while no other robot's scan can queue behind this one
            alone = len(self.robots) == 1
            set_budget(self.search_budget_ms if alone else 0.5 * self.search_budget_ms)
        est = r.localizer.update(ranges, angles, odom)
        if odom is not None:
            r.last_odom = np.asarray(odom, dtype=np.float64).copy()
        pose = np.asarray(est.pose, dtype=np.float64).reshape(-1)
        if pose.shape != (3,) or not np.all(np.isfinite(pose)):
            raise LocalizationError(f"method {r.method!r} produced a non-finite pose {pose}")
        pose[2] = wrap_angle(pose[2])
        r.last_pose = pose.copy()
        cov = None
        if est.covariance is not None:
            c = np.asarray(est.covariance, dtype=np.float64).reshape(-1)
            if c.shape == (9,) and np.all(np.isfinite(c)):
                cov = [float(v) for v in c]
        score = float(est.score)
        return {
            "pose": [float(v) for v in pose],
            "status": str(est.status),
            "score": score if np.isfinite(score) else 0.0,
            "explained": _opt_float(est.explained),
            "ambiguity": _opt_float(est.ambiguity),
            "covariance": cov,
            # searching or just fixed: the node keeps such a robot on the search worker
            "unsettled": bool(getattr(r.localizer, "unsettled", False)),
            "hypotheses": None if est.hypotheses is None else int(est.hypotheses),
            "state": getattr(est, "state", None),
            "candidates": _candidate_rows(est.candidates),
        }


def _candidate_rows(c: np.ndarray | None, k: int = 8) -> list[list[float]] | None:
    """The best ``k`` candidate rows ``[x, y, theta, cost]`` with finite values (or ``None``)."""
    if c is None:
        return None
    a = np.asarray(c, dtype=np.float64).reshape(-1, 4)[:k]
    a = a[np.all(np.isfinite(a), axis=1)]
    return [[float(v) for v in row] for row in a]


class WorkerDiedError(ShapelocError):
    """A worker process exited or stopped answering; it must be restarted."""


class InlineWorker:
    """A :class:`WorkerCore` called directly in the service process (``--workers 0``)."""

    def __init__(
        self, index: int = 0, cache_dir: Path | None = None, search_budget_ms: float | None = None
    ) -> None:
        self.index = index
        warm_up_worker()  # the first robot must not pay for the first use of the methods
        self.core = WorkerCore(cache_dir, search_budget_ms)

    def call(self, req: tuple[Any, ...], timeout_s: float | None = None) -> Reply:
        """Run one request synchronously (``timeout_s`` is ignored in-process)."""
        return self.core.handle(req)

    def call_batch(
        self,
        reqs: list[tuple[Any, ...]],
        timeout_s: float | None,
        on_reply: Callable[[int, Reply], None],
    ) -> None:
        """Run ``reqs`` in order, ``on_reply(i, reply)`` after each."""
        for i, req in enumerate(reqs):
            on_reply(i, self.core.handle(req))

    def alive(self) -> bool:
        """Always true in-process."""
        return True

    def close(self) -> None:
        """Nothing to release."""


def _worker_main(
    conn: Connection,
    log_level: str,
    cache_dir: Path | None = None,
    search_budget_ms: float | None = None,
    nice: int = 0,
    search: bool = False,
) -> None:
    """Entry point of a worker process: serve requests until EOF or ``("stop",)``. A tracking
    worker (``search`` false) warms up before it reports itself ready; the search worker, at
    a low priority, does not (its start-up must fit ``worker_start_timeout_s`` on a busy
    machine, and its robots search anyway)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent owns shutdown
    logging.basicConfig(
        level=getattr(logging, log_level.upper(), logging.INFO),
        format="%(asctime)s %(levelname)s %(name)s[%(process)d]: %(message)s",
    )
    if nice:
        # the search worker: the lowest priority, and the batch scheduling class (it never
        # preempts a tracking worker when it wakes); unlike the idle class it is never
        # starved outright, so a saturated machine still answers searching robots (slowly)
        with contextlib.suppress(OSError):
            os.nice(nice)
        if hasattr(os, "sched_setscheduler") and hasattr(os, "SCHED_BATCH"):
            with contextlib.suppress(OSError):
                os.sched_setscheduler(0, os.SCHED_BATCH, os.sched_param(0))
    if not search:
        warm_up_worker()
    core = WorkerCore(cache_dir, search_budget_ms, search=search)
    # start-up (interpreter, imports, warm-up) is over: the parent's per-request timeout starts
    conn.send(("ready", os.getpid()))
    while True:
        try:
            req = conn.recv()
        except (EOFError, OSError):
            break
        if req[0] == "stop":
            break
        if req[0] == "batch":  # one reply per request, each as soon as it is ready
            for r in req[1]:
                conn.send(core.handle(r))
            continue
        conn.send(core.handle(req))
    conn.close()


class ProcessWorker:
    """A :class:`WorkerCore` in a ``spawn``-ed child process; one request in flight at a time.

    :meth:`call` raises :class:`WorkerDiedError` if the child exits, or :class:`ServiceTimeout` (and
    kills the child) if a reply takes longer than ``timeout_s`` seconds. The child's start-up
    (a new interpreter, the imports and a tracking worker's warm-up) is not charged to its
    first request: the child says
    ``("ready", pid)`` when it can serve, and the first :meth:`call` waits up to
    ``start_timeout_s`` for that before its own ``timeout_s`` starts. A search worker at nice 19
    beside other busy processes can take more than the 30 s request timeout just to start.
    """

    def __init__(
        self,
        index: int,
        log_level: str = "info",
        cache_dir: Path | None = None,
        search_budget_ms: float | None = None,
        nice: int = 0,
        start_timeout_s: float = 120.0,
        search: bool = False,
    ) -> None:
        self.index = index
        self._log_level = log_level
        self._start_timeout_s = start_timeout_s
        self._ready = False
        ctx = mp.get_context("spawn")
        self._conn, child = ctx.Pipe(duplex=True)
        self._proc = ctx.Process(
            target=_worker_main,
            args=(child, log_level, cache_dir, search_budget_ms, nice, search),
            name=f"shapeloc-worker-{index}",
            daemon=True,
        )
        self._proc.start()
        child.close()
        # one poll object for the pipe's lifetime: Connection.poll builds (and closes) a
        # selector per call, which was a sixth of the service process's GIL time with 50
        # robots at 10 Hz
        self._poller = select.poll()
        self._poller.register(self._conn.fileno(), select.POLLIN | select.POLLHUP | select.POLLERR)

    def _readable(self, timeout_s: float | None) -> bool:
        """Whether the child's reply (or its exit) can be read within ``timeout_s``."""
        ms = None if timeout_s is None else max(0, math.ceil(timeout_s * 1000.0))
        return bool(self._poller.poll(ms))

    @property
    def pid(self) -> int | None:
        """Process id of the child."""
        return self._proc.pid

    def alive(self) -> bool:
        """Whether the child process is running."""
        return self._proc.is_alive()

    def _died(self, e: BaseException) -> WorkerDiedError:
        return WorkerDiedError(f"worker {self.index} died (exit code {self._proc.exitcode}): {e}")

    def wait_ready(self) -> None:
        """Wait (at most ``start_timeout_s``) until the child has started; kill it and raise
        :class:`ServiceTimeout` if it has not, :class:`WorkerDiedError` if it exited."""
        if self._ready:
            return
        try:
            started = self._readable(self._start_timeout_s)
            msg = self._conn.recv() if started else None
        except (EOFError, OSError, BrokenPipeError) as e:
            raise self._died(e) from e
        if not started:
            self.kill()
            raise ServiceTimeout(
                f"worker {self.index} did not start within {self._start_timeout_s:g} s; restarted"
            )
        if not (isinstance(msg, tuple) and msg and msg[0] == "ready"):
            self.kill()
            raise WorkerDiedError(f"worker {self.index} sent {msg!r} instead of ready")
        self._ready = True

    def call(self, req: tuple[Any, ...], timeout_s: float | None = None) -> Reply:
        """Send one request and wait for its reply (after the child's start-up, see
        :meth:`wait_ready`, which is not charged to ``timeout_s``)."""
        self.wait_ready()
        try:
            self._conn.send(req)
            if self._readable(timeout_s):
                return self._conn.recv()
        except (EOFError, OSError, BrokenPipeError) as e:
            raise self._died(e) from e
        self.kill()
        raise ServiceTimeout(
            f"worker {self.index} took longer than {timeout_s:.1f} s on a {req[0]} request; "
            "restarted"
        )

    def call_batch(
        self,
        reqs: list[tuple[Any, ...]],
        timeout_s: float | None,
        on_reply: Callable[[int, Reply], None],
    ) -> None:
        """Send ``reqs`` as one batch and call ``on_reply(i, reply)`` for each reply as it
        arrives (each within ``timeout_s`` of the previous one); raises like :meth:`call`."""
        if len(reqs) == 1:
            on_reply(0, self.call(reqs[0], timeout_s))
            return
        self.wait_ready()
        try:
            self._conn.send(("batch", reqs))
            for i in range(len(reqs)):
                if not self._readable(timeout_s):
                    break
                on_reply(i, self._conn.recv())
            else:
                return
        except (EOFError, OSError, BrokenPipeError) as e:
            raise self._died(e) from e
        self.kill()
        raise ServiceTimeout(
            f"worker {self.index} took longer than {timeout_s:.1f} s on a scan of a batch; "
            "restarted"
        )

    def kill(self) -> None:
        """Terminate the child at once."""
        if self._proc.is_alive():
            self._proc.kill()
        self._proc.join(timeout=5)

    def close(self) -> None:
        """Ask the child to stop, then make sure it is gone."""
        with contextlib.suppress(OSError):
            self._conn.send(("stop",))
        self._proc.join(timeout=5)
        if self._proc.is_alive():
            self._proc.kill()
            self._proc.join(timeout=5)
        self._conn.close()
