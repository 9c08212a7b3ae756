"""Compute scheduling: which robot's validated scan runs next, on which worker.

* :class:`LatestSlots`: per-robot latest-wins slots of *validated* scans (the intake,
  :mod:`service.node.intake`, never puts an invalid one here), served round robin over robots.
* :class:`WorkerLink`: one worker plus the thread that feeds it: control requests (maps,
  configs) first, then the next robot with a pending scan, one request in flight.

The node (:class:`service.node.node.ServiceNode`) implements :class:`LinkHost` (in its
:class:`~service.node.compute.ComputePlane` part): it decides what a scan's result means
(publishing the pose) and how a dead worker is restarted.
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections import OrderedDict
from collections.abc import Callable
from concurrent.futures import Future
from typing import Any, Protocol

from service.errors import ServiceTimeout
from service.node.intake import ControlClock, ValidScan
from service.node.workers import InlineWorker, ProcessWorker, WorkerDiedError

log = logging.getLogger("shapeloc.service")

Worker = ProcessWorker | InlineWorker


class LatestSlots:
    """Per-robot latest-wins slots with round-robin order over robots (thread-safe).

    :meth:`offer` keeps only the newest item per robot (the replaced one is counted as
    skipped) and never blocks; a robot keeps its place in the round-robin order while it has a
    pending item, so a robot that publishes fast cannot starve the others. At most ``capacity``
    robots can be pending; further new robots are refused (``offer`` returns ``False``).
    ``merge(old, new)``, if given, makes the item that replaces ``old`` (e.g. carrying what
    the replaced one knew: :meth:`service.node.intake.ValidScan.replacing`).
    """

    def __init__(self, capacity: int, merge: Callable[[Any, Any], Any] | None = None) -> None:
        self._merge = merge
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
                old = self._items[robot_id]
                self._items[robot_id] = item if self._merge is None else self._merge(old, item)
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

    def take_more(self, limit: int) -> list[tuple[str, Any]]:
        """Up to ``limit`` more pending robots (oldest first) with their newest items, without
        waiting."""
        with self._cond:
            out = []
            while self._items and len(out) < limit:
                out.append(self._items.popitem(last=False))
            return out

    def discard(self, robot_id: str) -> None:
        """Drop a pending item (robot forgotten)."""
        with self._cond:
            self._items.pop(robot_id, None)

    def __len__(self) -> int:
        with self._cond:
            return len(self._items)


def _replace_scan(old: ValidScan, new: ValidScan) -> ValidScan:
    return new.replacing(old)


class LinkHost(Protocol):
    """What a :class:`WorkerLink` needs from the node that owns it."""

    stopping: threading.Event
    clock: ControlClock
    worker_timeout_s: float
    #: the limit of an ``("index", map_id)`` request (a view index build takes seconds)
    index_timeout_s: float

    def new_worker(self, index: int) -> Worker:
        """A fresh worker for link ``index``."""
        ...

    def restart_worker(self, link: WorkerLink) -> None:
        """Replace ``link.worker`` by a fresh one and replay maps/configs into it."""
        ...

    def process_batch(self, link: WorkerLink, scans: list[ValidScan]) -> None:
        """Run ``scans`` (of different robots) on ``link`` and publish each result."""
        ...


class WorkerLink:
    """A worker plus the thread that feeds it (control requests first, then scans).

    The thread takes up to ``batch`` pending robots' scans at once and sends them to the
    worker in one request; the worker answers each as soon as it is localised, so the first
    pose of a batch is published as early as if it had been sent alone, and the worker never
    waits for the thread between two scans. A scan in a batch is committed to the worker (a
    newer scan of its robot waits for the next batch), so ``batch`` bounds how stale a
    committed scan can get and how long a control request waits (a batch of tracked scans,
    ~2 ms each, is over in tens of milliseconds).
    """

    def __init__(self, host: LinkHost, index: int, slot_capacity: int, batch: int = 1) -> None:
        self.host = host
        self.index = index
        self.batch = max(1, batch)
        self.worker: Worker = host.new_worker(index)
        self.slots = LatestSlots(capacity=slot_capacity, merge=_replace_scan)
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
        timeout = self.host.index_timeout_s if req[0] == "index" else self.host.worker_timeout_s
        try:
            return self.worker.call(req, timeout)
        except (WorkerDiedError, ServiceTimeout) as e:
            log.error("worker %d: %s; restarting it", self.index, e)
            self.host.restart_worker(self)
            return ("err", str(e))

    def call_batch(
        self, reqs: list[tuple[Any, ...]], on_reply: Callable[[int, tuple[str, Any]], None]
    ) -> None:
        """Run ``reqs`` on the worker as one batch; ``on_reply(i, reply)`` is called for each
        as it arrives, in order. If the worker dies or exceeds ``worker_timeout_s`` on one of
        them it is restarted and every request not answered gets ``("err", reason)``."""
        if len(reqs) == 1:
            on_reply(0, self.call(reqs[0]))
            return
        done = 0

        def got(i: int, reply: tuple[str, Any]) -> None:
            nonlocal done
            done = i + 1
            on_reply(i, reply)

        try:
            self.worker.call_batch(reqs, self.host.worker_timeout_s, got)
        except (WorkerDiedError, ServiceTimeout) as e:
            log.error("worker %d: %s; restarting it", self.index, e)
            self.host.restart_worker(self)
            for i in range(done, len(reqs)):
                on_reply(i, ("err", str(e)))

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
        host = self.host
        deadline = time.monotonic() + timeout_s
        while not host.stopping.is_set() and time.monotonic() < deadline:
            self._drain_control()
            if host.clock.wait_applied(ctl, 0.005):
                return

    def _run(self) -> None:
        host = self.host
        while not host.stopping.is_set():
            self._drain_control()
            got = self.slots.take(timeout_s=0.5)
            if got is None:
                continue
            scans = [got[1]] + [item for _r, item in self.slots.take_more(self.batch - 1)]
            self._await_control(max(scan.ctl for scan in scans))
            try:
                host.process_batch(self, scans)
            except Exception:  # never let the link die
                log.exception(
                    "unexpected error processing scans of %s", [s.robot_id for s in scans]
                )
        # drain control so no caller waits forever
        while True:
            try:
                _req, fut = self.control.get_nowait()
            except queue.Empty:
                break
            fut.set_result(("err", "service is shutting down"))
