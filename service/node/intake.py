"""Scan intake: raw samples in, validated scans out, before anything competes for compute.

Every payload received on ``<prefix>/robots/<id>/scan`` passes through here *before* it can
enter the robot's latest-wins slot, so an invalid payload never replaces (and never costs the
robot) a valid pending scan:

1. The Zenoh callback does only O(1) checks (scan deletes, oversize payloads, robots without a
   configuration) and copies the bytes into :class:`RawScanQueue`, a per-robot FIFO served
   round robin (so one flooding key cannot delay the other robots' scans). A robot whose
   backlog overflows has it validated in place (see :class:`RawScanQueue`): nothing valid is
   ever dropped to make room.
2. :class:`ScanIntake`'s thread decodes and validates each payload in arrival order
   (:func:`validate_scan`, ~60-120 us for 361 beams) and hands a :class:`ValidScan` (arrays
   ready for the localiser) to its ``accept`` callable, or the reason to its ``reject``
   callable.

Which robot's scan is then computed, and on which worker, is :mod:`service.node.scheduler`'s
business; this module knows nothing about workers. No Zenoh import here: the node passes the
bytes, encodings and keys in.
"""

from __future__ import annotations

import dataclasses
import logging
import threading
import time
from collections import OrderedDict, deque
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from schemas import codec
from schemas.messages import Scan
from service.errors import ShapelocError

log = logging.getLogger("shapeloc.service")

#: Largest scan payload kept for decoding (bytes): 8192 beams as JSON text fit in ~200 KiB, so
#: anything bigger is rejected in the callback without copying it.
MAX_SCAN_BYTES = 512 * 1024
#: Memory an item costs in the raw queue besides its payload (object, key string, deque slot).
ITEM_OVERHEAD_BYTES = 256


@dataclass(frozen=True)
class Inbound:
    """One received map/config sample, as copied out of a Zenoh callback.

    ``payload`` is ``None`` when the callback already rejected it (``reject`` says why);
    ``t_recv`` is ``time.monotonic()`` seconds at reception. ``ctl`` is the sequence number of
    the control message (see :class:`ControlClock`).
    """

    key: str
    payload: bytes | None
    encoding: str | None
    t_recv: float
    delete: bool = False
    reject: str | None = None
    ctl: int = 0


@dataclass(frozen=True)
class RawScan:
    """A scan sample as received: bytes not yet decoded.

    ``reject`` is set (and ``payload`` is ``None``) when the callback already knows the sample
    is refused; ``ctl`` is the number of control messages received before it, so the scan is
    computed only after every map/config received before it has been applied.
    """

    robot_id: str
    key: str
    payload: bytes | None
    encoding: str | None
    t_recv: float
    ctl: int = 0
    reject: ShapelocError | None = None

    @property
    def cost(self) -> int:
        """Bytes charged against the raw queue's budget."""
        return ITEM_OVERHEAD_BYTES + (0 if self.payload is None else len(self.payload))


@dataclass(frozen=True)
class ValidScan:
    """A decoded, validated scan, ready for the localiser.

    ``ranges`` metres with NaN for every no-return beam, ``angles`` radians in the robot frame
    (both float64 ``(n,)``), ``odom`` ``(x, y, theta)`` in the odometry frame or ``None``;
    ``seq``/``stamp`` as sent, ``t_recv``/``ctl`` as in :class:`RawScan`. ``skipped_odom``
    is the odometry of the oldest scan this one replaced under latest-wins (through any chain
    of replacements; ``None``: none replaced, or it carried no odometry): see
    :meth:`replacing`.
    """

    robot_id: str
    key: str
    seq: int
    stamp: float
    ranges: np.ndarray
    angles: np.ndarray
    odom: np.ndarray | None
    t_recv: float
    ctl: int = 0
    skipped_odom: np.ndarray | None = None
    #: CPU ms the intake spent decoding and validating it
    intake_ms: float = 0.0

    def replacing(self, older: ValidScan) -> ValidScan:
        """This scan as the replacement of ``older`` (latest wins), carrying the odometry of
        the oldest scan replaced. A robot whose localiser has localised no scan since its
        configuration needs it: its initial pose is where that first scan was taken, so the
        increment to this scan is measured from there. Not carried across a control message
        (a new configuration or map between the two scans starts a new chain)."""
        if older.ctl != self.ctl:
            return self
        base = older.skipped_odom if older.skipped_odom is not None else older.odom
        if base is None:
            return self
        return dataclasses.replace(self, skipped_odom=base)


def encoding_name(enc: object) -> str | None:
    """The sample's encoding as a string (the codec decides JSON vs msgpack from it)."""
    return None if enc is None else str(enc)


def error_kind(exc: BaseException) -> str:
    """Counter name of a rejection: the exception class name (``InvalidMessage``, ...)."""
    return type(exc).__name__


def validate_scan(raw: RawScan) -> ValidScan:
    """Decode and validate one scan payload (wire contract v1, ``schemas.codec``).

    Raises :class:`~service.errors.InvalidMessage` naming the field and the problem.
    """
    assert raw.payload is not None
    cpu0 = time.thread_time()
    msg = codec.decode(Scan, raw.payload, raw.encoding)
    ranges, angles = codec.scan_arrays(msg)
    odom = None if msg.odom is None else np.array(msg.odom, dtype=np.float64)
    return ValidScan(
        robot_id=raw.robot_id,
        key=raw.key,
        seq=msg.seq,
        stamp=msg.stamp,
        ranges=ranges,
        angles=angles,
        odom=odom,
        t_recv=raw.t_recv,
        ctl=raw.ctl,
        intake_ms=(time.thread_time() - cpu0) * 1e3,
    )


class ControlClock:
    """Counts control messages (maps, configs) received and applied, so that a scan waits
    until every map and every configuration of its robot received before it has been applied
    (causality of "put map, put config, put scan" from one client). ``received`` is written
    by the callback thread only; ``applied`` by the control thread; readers need no lock for
    a snapshot."""

    def __init__(self) -> None:
        self.received = 0
        self.applied = 0
        self._cond = threading.Condition()
        #: number of the last control message about each robot (its config), and of the last
        #: one about anything else (maps): a scan waits only for those (callback thread only)
        self._robot: dict[str, int] = {}
        self._other = 0

    def next(self, robot_id: str = "") -> int:
        """Number the next control message, about ``robot_id`` ("": a map or anything not
        about one robot) (callback thread only)."""
        self.received += 1
        if robot_id:
            if len(self._robot) > 4096:  # forget what is applied (bounds the memory)
                done = self.applied
                self._robot = {r: n for r, n in self._robot.items() if n > done}
            self._robot[robot_id] = self.received
        else:
            self._other = self.received
        return self.received

    def needed(self, robot_id: str) -> int:
        """The control message a scan of ``robot_id`` received now must wait for: the last
        one about that robot or about a map, not another robot's configuration (a slow
        worker applying it must not hold every robot's scans)."""
        return max(self._robot.get(robot_id, 0), self._other)

    def mark_applied(self, ctl: int) -> None:
        """Control message ``ctl`` (and every one before it) has been applied."""
        with self._cond:
            self.applied = max(self.applied, ctl)
            self._cond.notify_all()

    def wait_applied(self, ctl: int, timeout_s: float) -> bool:
        """Block up to ``timeout_s`` seconds until ``ctl`` is applied; whether it is."""
        with self._cond:
            if self.applied < ctl:
                self._cond.wait(timeout_s)
            return self.applied >= ctl


def _cost(entry: RawScan | ValidScan) -> int:
    if isinstance(entry, RawScan):
        return entry.cost
    return ITEM_OVERHEAD_BYTES + entry.ranges.nbytes + entry.angles.nbytes


class RawScanQueue:
    """Per-robot FIFOs of received scans, served round robin over robots (thread-safe).

    Normally an entry is a :class:`RawScan` (bytes not yet decoded) and :meth:`put` costs O(1).
    When a robot already has ``per_robot`` entries waiting, or all robots together hold more
    than ``max_bytes``, the robot's backlog is *compacted* in the calling thread (the Zenoh
    callback of the sample that overflowed it) instead of anything being dropped blindly:
    every waiting raw sample and the new one are validated; invalid ones become rejection
    entries (no payload), of the valid ones only the newest is kept (the older ones are
    ``superseded``: latest wins, as in the slots). Rejection entries beyond ``per_robot // 2``
    per robot are handed to ``overflow_reject`` (counted, without a notice) and removed.

    So no valid scan is ever lost to garbage, memory stays bounded (per robot: ``per_robot``
    raw samples, or one decoded scan plus a few rejection records), and the validation cost of
    a flood lands on the flood itself. A robot that is not flooding never pays for it.
    """

    def __init__(
        self,
        per_robot: int,
        max_bytes: int,
        validate: Callable[[RawScan], ValidScan] | None = None,
        overflow_reject: Callable[[str, BaseException], None] | None = None,
    ) -> None:
        if per_robot < 2 or max_bytes < ITEM_OVERHEAD_BYTES:
            raise ValueError("per_robot must be >= 2 and max_bytes >= the per-item overhead")
        self.per_robot = per_robot
        self.max_bytes = max_bytes
        self._validate = validate_scan if validate is None else validate
        self._overflow_reject = overflow_reject
        self._q: OrderedDict[str, deque[RawScan | ValidScan]] = OrderedDict()
        self._bytes = 0
        self._cond = threading.Condition()
        self._kick = False
        self.compactions = 0
        self.superseded = 0  # valid scans replaced by a newer valid one during compaction
        self.notices_dropped = 0  # rejections counted but not published (see overflow_reject)

    def put(self, item: RawScan) -> None:
        """Queue ``item`` (never blocks; may validate this robot's backlog, see above)."""
        cost = item.cost
        with self._cond:
            q = self._q.get(item.robot_id)
            if q is None:
                q = self._q[item.robot_id] = deque()
            if len(q) >= self.per_robot or self._bytes + cost > self.max_bytes:
                self._compact(q, item)
            else:
                q.append(item)
                self._bytes += cost
            self._cond.notify()

    def _compact(self, q: deque[RawScan | ValidScan], new: RawScan) -> None:
        self.compactions += 1
        self._bytes -= sum(_cost(e) for e in q)
        rejects: list[RawScan] = []
        newest: ValidScan | None = None
        for e in [*q, new]:
            if isinstance(e, RawScan) and e.reject is None:
                try:
                    e = self._validate(e)
                except ShapelocError as exc:
                    rejects.append(RawScan(e.robot_id, e.key, None, None, e.t_recv, e.ctl, exc))
                    continue
            if isinstance(e, ValidScan):
                if newest is not None:
                    self.superseded += 1
                    e = e.replacing(newest)
                newest = e
            else:
                rejects.append(e)
        keep = self.per_robot // 2
        for e in rejects[:-keep] if len(rejects) > keep else []:
            self.notices_dropped += 1
            if self._overflow_reject is not None and e.reject is not None:
                self._overflow_reject(e.key, e.reject)
        q.clear()
        q.extend(rejects[-keep:])
        if newest is not None:
            q.append(newest)
        self._bytes += sum(_cost(e) for e in q)

    def take(self, timeout_s: float | None = None) -> list[RawScan | ValidScan]:
        """Every waiting entry of the robot that has waited longest, oldest first (empty on
        timeout or :meth:`kick`)."""
        with self._cond:
            if not self._q and not self._kick:
                self._cond.wait(timeout_s)
            self._kick = False
            if not self._q:
                return []
            _rid, q = self._q.popitem(last=False)
            self._bytes -= sum(_cost(e) for e in q)
            return list(q)

    def kick(self) -> None:
        """Wake a waiting :meth:`take` (it returns an empty list once)."""
        with self._cond:
            self._kick = True
            self._cond.notify_all()

    @property
    def nbytes(self) -> int:
        """Bytes currently charged."""
        with self._cond:
            return self._bytes

    def __len__(self) -> int:
        with self._cond:
            return sum(len(q) for q in self._q.values())


class ScanIntake:
    """The validation stage between the Zenoh callback and the latest-wins slots.

    ``accept(scan)`` receives every valid scan in arrival order per robot; ``reject(key,
    exc)`` every refused one with its reason (the node counts it, logs it and publishes the
    notice); both run on the intake thread. ``count_reject(key, exc)`` is called instead of
    ``reject`` for rejections whose notice is dropped in a flood (it must only count; it runs
    in the Zenoh callback).
    """

    def __init__(
        self,
        accept: Callable[[ValidScan], None],
        reject: Callable[[str, BaseException], None],
        per_robot: int = 16,
        max_bytes: int = 64 * 1024 * 1024,
        count_reject: Callable[[str, BaseException], None] | None = None,
    ) -> None:
        self.queue = RawScanQueue(per_robot, max_bytes, validate_scan, count_reject)
        self._accept = accept
        self._reject = reject
        self._stopping = threading.Event()
        self._thread = threading.Thread(target=self._run, name="shapeloc-intake", daemon=True)
        self.validated = 0
        self.busy_s = 0.0  # seconds the intake thread spent decoding and validating

    def start(self) -> None:
        """Start the intake thread."""
        self._thread.start()

    def stop(self, timeout_s: float = 5.0) -> None:
        """Stop the thread (samples still queued are discarded)."""
        self._stopping.set()
        self.queue.kick()
        if self._thread.is_alive():
            self._thread.join(timeout_s)

    def put(self, item: RawScan) -> None:
        """Queue a raw sample (callback side; never blocks)."""
        self.queue.put(item)

    def process(self, items: list[RawScan | ValidScan]) -> None:
        """Validate ``items`` in order and pass each to ``accept`` or ``reject``."""
        for item in items:
            if isinstance(item, ValidScan):  # validated already (queue compaction)
                self.validated += 1
                self._accept(item)
                continue
            if item.reject is not None:
                self._reject(item.key, item.reject)
                continue
            t = time.perf_counter()
            try:
                scan = validate_scan(item)
            except ShapelocError as e:
                self.busy_s += time.perf_counter() - t
                self._reject(item.key, e)
                continue
            self.busy_s += time.perf_counter() - t
            self.validated += 1
            self._accept(scan)

    def _run(self) -> None:
        while not self._stopping.is_set():
            items = self.queue.take(timeout_s=0.5)
            if not items:
                continue
            try:
                self.process(items)
            except Exception:  # never let the intake die
                log.exception("unexpected error validating scans of %s", items[0].robot_id)
