"""What the live view knows: the latest state of every robot and map, built from raw samples.

:class:`ViewState` takes the raw samples the server drained from its Zenoh subscribers
(``ingest``: key, put or delete, payload bytes, encoding, receipt time) and turns them into
the messages the page draws (``frame``, ``maps_message``). It imports neither zenoh nor the web
server, so it is tested without either.

Costs are bounded so that the view never competes with the service it watches:

* every pose is read (the path and the status need them all), with a lean reader: msgpack
  unpacked and only the fields the page shows checked, a tenth of a full model decode
  (:func:`read_pose`; JSON payloads take the full decode);
* scans are **not** decoded on arrival: each robot keeps its last few raw scan payloads, and
  a frame decodes only the one that answers the robot's latest pose (same ``seq``), only for
  robots some page shows, and only once (the decoded beams are kept with the payload);
* beams are thinned to at most ``max_beams`` per scan (180: one every 2 degrees of a full
  turn, what a screen can show of a 10 m scan), ranges packed as millimetres in base64;
* a frame carries only the robots that changed since the previous one (``delta``), with
  positions rounded to 0.1 mm and headings to 0.1 mrad; every robot goes out in a key frame
  (the server sends one a second) so that rates and staleness stay current;
* the number of robots and maps kept is capped (ids come from the network).

Every network input is untrusted: a payload that does not decode, a key that is not a valid
robot or map key, or a pose whose ``robot_id`` differs from its key is counted in
:attr:`ViewState.rejected` (by reason) and logged once per reason, and nothing else changes.
"""

from __future__ import annotations

import base64
import logging
import math
from collections import Counter, deque
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any

import msgpack
import numpy as np

from schemas import keys
from schemas.codec import decode, is_json_encoding, scan_arrays
from schemas.fields import wrap_pi
from schemas.limits import MAX_BEAMS as WIRE_MAX_BEAMS
from schemas.limits import MAX_CANDIDATES, MAX_PAYLOAD_BYTES, MAX_UINT
from schemas.messages import Map, PoseMsg, Scan
from service.errors import InvalidMessage

log = logging.getLogger("shapeloc.view")

#: A queued sample: (key, is_delete, payload, encoding, receipt time in s since the epoch).
RawSample = tuple[str, bool, bytes, str | None, float]

#: Defaults (see :class:`ViewState`).
PATH_LEN = 300
SCAN_RING = 16
MAX_BEAMS = 180
MAX_ROBOTS = 1000
MAX_MAPS = 64
#: Distinct rejection reasons kept (the rest are counted as "<kind>: other").
MAX_REASONS = 64
#: A robot with no pose for this long is shown as stale; after FORGET_S it is dropped.
STALE_S = 3.0
FORGET_S = 600.0
#: Statuses longer than this are refused (a status the view does not know is drawn grey).
MAX_STATUS_LEN = 64
#: Poses of these statuses are not added to the path: during a global search the published
#: pose is the best hypothesis so far, which jumps between places.
NO_PATH_STATUSES = frozenset({"initializing"})


@dataclass
class _ScanSlot:
    """One raw scan payload; ``seq`` and ``beams`` are filled when it is first decoded."""

    payload: bytes
    encoding: str | None
    decoded: bool = False
    seq: int = -1
    beams: dict[str, Any] | None = None


@dataclass
class RobotView:
    """The latest of one robot: its pose, recent path, raw scans and arrival times."""

    robot_id: str
    path_len: int
    scan_ring: int
    pose: PoseView | None = None
    received_at: float = 0.0
    #: A pose arrived since the last frame (the robot goes out in the next delta frame).
    changed: bool = False
    #: Whether the last frame it went out in showed it stale.
    sent_stale: bool = False
    poses: int = 0
    scans: int = 0
    path: deque[tuple[float, float]] = field(init=False)
    new_points: list[tuple[float, float]] = field(default_factory=list)
    ring: deque[_ScanSlot] = field(init=False)
    arrivals: deque[float] = field(default_factory=lambda: deque(maxlen=128))

    def __post_init__(self) -> None:
        self.path = deque(maxlen=self.path_len)
        self.ring = deque(maxlen=self.scan_ring)

    def rate_hz(self, now: float, window_s: float = 2.0) -> float:
        """Poses per second over the last ``window_s`` seconds (0 if fewer than two)."""
        recent = [t for t in self.arrivals if now - t <= window_s]
        if len(recent) < 2 or recent[-1] <= recent[0]:
            return 0.0
        return (len(recent) - 1) / (recent[-1] - recent[0])


def _r(v: float, nd: int) -> float:
    return round(float(v), nd)


def map_payload(m: Map) -> dict[str, Any]:
    """A stored map as the page draws it: polylines in mm-rounded metres and their bounds."""
    lines = [np.round(p, 3).tolist() for p in m.polylines]
    pts = np.concatenate(m.polylines, axis=0)
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    return {
        "id": m.map_id,
        "kind": m.kind,
        "name": m.name or "",
        "polylines": lines,
        "bounds": [_r(lo[0], 3), _r(lo[1], 3), _r(hi[0], 3), _r(hi[1], 3)],
    }


#: A range sent to the page is a little-endian uint16 count of ``u`` metres; this value is
#: "no return". ``u`` is 1 mm, or 1 cm for a laser reaching past 65 m.
NO_RETURN = 0xFFFF


def scan_beams(scan: Scan, max_beams: int = MAX_BEAMS) -> dict[str, Any]:
    """A scan's beams for the page, thinned to at most ``max_beams``: ``a0`` (rad), ``da``
    (rad between the beams sent), ``u`` (metres per unit) and ``d``, the ranges as base64 of
    little-endian uint16 units (:data:`NO_RETURN` where nothing was hit). Packed, a scan is a
    third of its JSON number list and costs the server no float formatting."""
    ranges, _angles = scan_arrays(scan)
    step = max(1, math.ceil(ranges.size / max(1, max_beams)))
    return _beams(
        scan.seq, scan.angle_min, scan.angle_increment, scan.range_max, ranges[::step], step
    )


def _beams(
    seq: int, angle_min: float, increment: float, range_max: float, r: np.ndarray, step: int
) -> dict[str, Any]:
    unit = 0.001 if range_max < (NO_RETURN - 1) * 0.001 else 0.01
    units = np.full(r.shape, NO_RETURN, dtype="<u2")
    ok = np.isfinite(r)
    units[ok] = np.clip(np.rint(r[ok] / unit), 0, NO_RETURN - 1)
    return {
        "seq": seq,
        "a0": float(angle_min),
        "da": float(increment * step),
        "u": unit,
        "d": base64.b64encode(units.tobytes()).decode("ascii"),
    }


def unpack_ranges(beams: dict[str, Any]) -> np.ndarray:
    """The ranges (m, NaN = no return) of :func:`scan_beams`' output (what the page does)."""
    units = np.frombuffer(base64.b64decode(beams["d"]), dtype="<u2")
    out = units.astype(np.float64) * beams["u"]
    out[units == NO_RETURN] = np.nan
    return out


@dataclass(frozen=True, slots=True)
class PoseView:
    """The fields of a pose message the page shows (see :func:`read_pose`)."""

    robot_id: str
    seq: int
    pose: tuple[float, float, float]
    status: str
    score: float
    method: str
    map_id: str
    latency_ms: float
    #: ``(xx, xy, yy)`` of the covariance, or ``None``.
    cov_xy: tuple[float, float, float] | None = None
    explained: float | None = None
    ambiguity: float | None = None
    hypotheses: int | None = None
    #: ``[[x, y, theta, cost], ...]`` rounded to 0.1 mm / 0.1 mrad, or ``None``.
    candidates: list[list[float]] | None = None


def _unpack(payload: bytes, what: str) -> dict[str, Any]:
    if not payload:
        raise InvalidMessage("payload: empty")
    if len(payload) > MAX_PAYLOAD_BYTES:
        raise InvalidMessage(f"payload: {len(payload)} bytes exceeds limit {MAX_PAYLOAD_BYTES}")
    try:
        obj = msgpack.unpackb(payload, raw=False, strict_map_key=True, use_list=False)
    except (msgpack.ExtraData, msgpack.StackError, msgpack.FormatError) as exc:
        raise InvalidMessage(f"msgpack: malformed ({type(exc).__name__})") from None
    except (ValueError, TypeError, msgpack.UnpackException) as exc:
        text = str(exc)
        if "incomplete" in text or "exceeds max_" in text:
            raise InvalidMessage("msgpack: truncated payload") from None
        raise InvalidMessage(f"msgpack: malformed ({text[:80]})") from None
    if not isinstance(obj, dict):
        raise InvalidMessage(f"message: {what} must be a map, got {type(obj).__name__}")
    return obj


def _finite(obj: dict[str, Any], name: str) -> float:
    v = obj.get(name)
    t = type(v)
    if t is float or t is int:
        f = float(v)
        if math.isfinite(f):
            return f
    raise InvalidMessage(f"{name}: must be a finite number, got {v!r:.40}")


def _opt_unit(obj: dict[str, Any], name: str) -> float | None:
    if obj.get(name) is None:
        return None
    f = _finite(obj, name)
    if not 0.0 <= f <= 1.0:
        raise InvalidMessage(f"{name}: must be in [0, 1], got {f!r}")
    return f


def _count(obj: dict[str, Any], name: str) -> int:
    v = obj.get(name)
    if type(v) is not int or not 0 <= v <= MAX_UINT:
        raise InvalidMessage(f"{name}: must be an integer in [0, 2^64), got {v!r:.40}")
    return v


def _numbers(v: object, n: int, name: str) -> list[float]:
    if not isinstance(v, (list, tuple)) or len(v) != n:
        raise InvalidMessage(f"{name}: must be {n} numbers")
    out = []
    for x in v:
        if type(x) is not float and type(x) is not int:
            raise InvalidMessage(f"{name}: must be {n} numbers")
        f = float(x)
        if not math.isfinite(f):
            raise InvalidMessage(f"{name}: must be finite")
        out.append(f)
    return out


def _ident(obj: dict[str, Any], name: str) -> str:
    v = obj.get(name)
    reason = keys.id_error(v)
    if reason is not None:
        raise InvalidMessage(f"{name}: {reason}")
    return v  # type: ignore[return-value]


def read_pose(payload: bytes, encoding: str | None) -> PoseView:
    """A pose message's shown fields. msgpack is read by a lean reader that checks exactly
    the fields it keeps (types, finiteness, ranges, identifiers, the wire's limits), about a
    tenth of the full model decode; a JSON payload goes through the full decode. Unknown
    fields are ignored; a status the view does not know is kept (drawn grey).
    Raises ``InvalidMessage``."""
    if is_json_encoding(encoding):
        m = decode(PoseMsg, payload, encoding)
        return PoseView(
            m.robot_id, m.seq, (float(m.pose[0]), float(m.pose[1]), float(m.pose[2])),
            m.status, float(m.score), m.method, m.map_id, float(m.latency_ms),
            None if m.covariance is None else (
                float(m.covariance[0, 0]), float(m.covariance[0, 1]), float(m.covariance[1, 1])
            ),
            m.explained, m.ambiguity, m.hypotheses,
            None if m.candidates is None or not len(m.candidates)
            else np.round(m.candidates, 4).tolist(),
        )  # fmt: skip
    obj = _unpack(payload, "pose")
    x, y, th = _numbers(obj.get("pose"), 3, "pose")
    status = obj.get("status")
    if not isinstance(status, str) or not 0 < len(status) <= MAX_STATUS_LEN:
        raise InvalidMessage(f"status: must be a string of 1-{MAX_STATUS_LEN} characters")
    cov = obj.get("covariance")
    cov_xy = None
    if cov is not None:
        c = _numbers(cov, 9, "covariance")  # row-major 3x3, as on the wire
        cov_xy = (c[0], c[1], c[4])
    hyp = None if obj.get("hypotheses") is None else _count(obj, "hypotheses")
    cand_in = obj.get("candidates")
    cand = None
    if cand_in is not None:
        if not isinstance(cand_in, (list, tuple)) or len(cand_in) > MAX_CANDIDATES:
            raise InvalidMessage(f"candidates: must be at most {MAX_CANDIDATES} rows")
        cand = []
        for row in cand_in:
            cx, cy, ct, cc = _numbers(row, 4, "candidates")
            cand.append([round(cx, 4), round(cy, 4), round(wrap_pi(ct), 4), round(cc, 4)])
    return PoseView(
        robot_id=_ident(obj, "robot_id"),
        seq=_count(obj, "seq"),
        pose=(x, y, wrap_pi(th)),
        status=status,
        score=_finite(obj, "score"),
        method=_ident(obj, "method"),
        map_id=_ident(obj, "map_id"),
        latency_ms=_finite(obj, "latency_ms"),
        cov_xy=cov_xy,
        explained=_opt_unit(obj, "explained"),
        ambiguity=_opt_unit(obj, "ambiguity"),
        hypotheses=hyp,
        candidates=cand or None,
    )


def read_scan_beams(
    payload: bytes, encoding: str | None, max_beams: int = MAX_BEAMS
) -> dict[str, Any]:
    """:func:`scan_beams` of a raw scan payload. The usual msgpack scan with float32 bytes is
    read lean (the fields the page needs checked, only the beams sent converted); anything
    else (JSON, ranges as a number list) goes through the full decode. Raises
    ``InvalidMessage``."""
    if is_json_encoding(encoding):
        return scan_beams(decode(Scan, payload, encoding), max_beams)
    obj = _unpack(payload, "scan")
    raw = obj.get("ranges")
    if not isinstance(raw, bytes):
        return scan_beams(decode(Scan, payload, encoding), max_beams)
    n = len(raw) // 4
    if len(raw) % 4 or not 0 < n <= WIRE_MAX_BEAMS:
        raise InvalidMessage(f"ranges: {len(raw)} bytes is not 1-{WIRE_MAX_BEAMS} float32")
    lo, hi = _finite(obj, "range_min"), _finite(obj, "range_max")
    step = max(1, math.ceil(n / max(1, max_beams)))
    r = np.frombuffer(raw, dtype="<f4")[::step].astype(np.float64)
    with np.errstate(invalid="ignore"):
        r[~((r >= lo) & (r <= hi))] = np.nan  # NaN, inf and out of range: no return
    return _beams(
        _count(obj, "seq"), _finite(obj, "angle_min"), _finite(obj, "angle_increment"), hi,
        r, step,
    )  # fmt: skip


class ViewState:
    """The view's model of the fleet, fed with raw samples, read as page messages.

    ``prefix``: the wire's key prefix. ``path_len``: positions kept per robot for its path.
    ``scan_ring``: raw scans kept per robot to find the one its latest pose answers.
    ``max_beams``: beams per scan sent to the page. ``max_robots`` / ``max_maps``: caps on
    what the network can make this process keep.
    """

    def __init__(
        self,
        prefix: str = keys.DEFAULT_PREFIX,
        *,
        path_len: int = PATH_LEN,
        scan_ring: int = SCAN_RING,
        max_beams: int = MAX_BEAMS,
        max_robots: int = MAX_ROBOTS,
        max_maps: int = MAX_MAPS,
    ) -> None:
        self.prefix = keys.validate_prefix(prefix)
        self.path_len = path_len
        self.scan_ring = scan_ring
        self.max_beams = max_beams
        self.max_robots = max_robots
        self.max_maps = max_maps
        self.robots: dict[str, RobotView] = {}
        self.maps: dict[str, Map] = {}
        self._map_payloads: dict[str, dict[str, Any]] = {}
        #: Bumped whenever a map is stored or deleted (the server then resends the maps).
        self.maps_version = 0
        #: Rejected samples by reason ("pose: ...", "scan: ...", "map: ...", "key: ...").
        self.rejected: Counter[str] = Counter()
        self.decoded_scans = 0
        self.health: dict[str, Any] | None = None
        self._prefix_robots = f"{self.prefix}/robots/"
        self._prefix_maps = f"{self.prefix}/maps/"

    # ------------------------------------------------------------------ intake
    def _reject(self, reason: str) -> None:
        if reason not in self.rejected:
            if len(self.rejected) >= MAX_REASONS:
                reason = reason.split(":", 1)[0] + ": other"
            else:
                log.warning("view: rejected a sample (%s); the next ones are counted", reason)
        self.rejected[reason] += 1

    def ingest_all(self, samples: Iterable[RawSample]) -> None:
        """:meth:`ingest` each sample in order."""
        for s in samples:
            self.ingest(*s)

    def ingest(
        self, key: str, delete: bool, payload: bytes, encoding: str | None, t: float
    ) -> None:
        """Take one raw sample of a pose, scan or map key (anything else is rejected)."""
        try:
            if key.startswith(self._prefix_robots):
                robot_id, leaf = keys.parse_robot_key(self.prefix, key)
                if leaf == "pose" and not delete:
                    self._on_pose(robot_id, payload, encoding, t)
                elif leaf == "scan" and not delete:
                    self._on_scan(robot_id, payload, encoding)
                return
            if key.startswith(self._prefix_maps):
                map_id = keys.parse_map_key(self.prefix, key)
                if delete:
                    self.delete_map(map_id)
                else:
                    self._on_map(map_id, payload, encoding)
                return
            self._reject("key: not a robot or map key")
        except InvalidMessage as exc:
            self._reject(f"{_kind_of(key)}: {_first_words(str(exc))}")

    def _robot(self, robot_id: str) -> RobotView | None:
        r = self.robots.get(robot_id)
        if r is None:
            if len(self.robots) >= self.max_robots:
                self._reject(f"robots: more than {self.max_robots}")
                return None
            r = RobotView(robot_id, self.path_len, self.scan_ring)
            self.robots[robot_id] = r
        return r

    def _on_pose(self, robot_id: str, payload: bytes, encoding: str | None, t: float) -> None:
        msg = read_pose(payload, encoding)
        if msg.robot_id != robot_id:
            raise InvalidMessage(f"robot_id {msg.robot_id!r} differs from the key's")
        r = self._robot(robot_id)
        if r is None:
            return
        if r.pose is not None and r.pose.map_id != msg.map_id:
            r.path.clear()  # another map, other coordinates
            r.new_points.clear()
        r.pose = msg
        r.received_at = t
        r.poses += 1
        r.changed = True
        r.arrivals.append(t)
        if msg.status not in NO_PATH_STATUSES:
            pt = (_r(msg.pose[0], 3), _r(msg.pose[1], 3))
            r.path.append(pt)
            r.new_points.append(pt)

    def _on_scan(self, robot_id: str, payload: bytes, encoding: str | None) -> None:
        r = self._robot(robot_id)
        if r is None:
            return
        r.scans += 1
        r.ring.append(_ScanSlot(payload, encoding))

    def _on_map(self, map_id: str, payload: bytes, encoding: str | None) -> None:
        msg = decode(Map, payload, encoding)
        if msg.map_id != map_id:
            raise InvalidMessage(f"map_id {msg.map_id!r} differs from the key's")
        if map_id not in self.maps and len(self.maps) >= self.max_maps:
            self._reject(f"maps: more than {self.max_maps}")
            return
        old = self.maps.get(map_id)
        if old is not None and old == msg:
            return
        self.maps[map_id] = msg
        self._map_payloads[map_id] = map_payload(msg)
        self.maps_version += 1

    def delete_map(self, map_id: str) -> None:
        """Forget a map (deleted on the wire)."""
        if self.maps.pop(map_id, None) is not None:
            self._map_payloads.pop(map_id, None)
            self.maps_version += 1

    def missing_maps(self) -> set[str]:
        """Map ids some robot uses that this view does not hold (to ask the service for)."""
        used = {r.pose.map_id for r in self.robots.values() if r.pose is not None}
        return used - set(self.maps)

    # ------------------------------------------------------------------ output
    def maps_message(self) -> dict[str, Any]:
        """``{"type": "maps", "maps": [...]}``: every map held, sorted by id."""
        return {
            "type": "maps",
            "version": self.maps_version,
            "maps": [self._map_payloads[k] for k in sorted(self._map_payloads)],
        }

    def _scan_for(self, r: RobotView) -> dict[str, Any] | None:
        """The beams of the scan the robot's latest pose answers, if it is still held."""
        if r.pose is None:
            return None
        want = r.pose.seq
        for slot in reversed(r.ring):
            if not slot.decoded:
                slot.decoded = True
                try:
                    beams = read_scan_beams(slot.payload, slot.encoding, self.max_beams)
                except InvalidMessage as exc:
                    self._reject(f"scan: {_first_words(str(exc))}")
                    continue
                self.decoded_scans += 1
                slot.seq = beams["seq"]
                slot.beams = beams
                slot.payload = b""  # decoded once: the bytes are no longer needed
            if slot.seq == want:
                return slot.beams
            if 0 <= slot.seq < want:
                return None  # older than the pose: the answered scan is gone
        return None

    def frame(
        self,
        now: float,
        *,
        full: bool = False,
        delta: bool = False,
        with_scan: Callable[[str], bool] | None = None,
    ) -> dict[str, Any]:
        """``{"type": "frame", ...}``: the robots' latest state.

        ``full``: each robot's whole path (``path``) rather than the positions added since
        the last :meth:`end_tick` (``trail``). ``delta``: only the robots that got a pose or
        turned stale since the last :meth:`end_tick` (``"key": false``); otherwise every robot
        (``"key": true``: a robot missing from a key frame is gone). ``with_scan(robot_id)``:
        whether to include the robot's scan (default: every robot); only those scans are ever
        decoded, and in a delta frame only for a robot with a new pose.
        """
        out = []
        for rid in sorted(self.robots):
            r = self.robots[rid]
            if now - r.received_at > FORGET_S and r.received_at > 0:
                continue
            stale = now - r.received_at > STALE_S
            if delta and not r.changed and stale == r.sent_stale:
                continue
            scan = (full or delta or r.changed) and (with_scan is None or with_scan(rid))
            out.append(self._robot_entry(r, now, full, scan))
        return {
            "type": "frame",
            "key": not delta,
            "time": round(now, 3),
            "robots": out,
            "rejected": sum(self.rejected.values()),
            "service": self.health,
        }

    def _robot_entry(self, r: RobotView, now: float, full: bool, scan: bool) -> dict[str, Any]:
        e: dict[str, Any] = {"id": r.robot_id, "hz": _r(r.rate_hz(now), 1)}
        if full:
            e["path"] = [list(p) for p in r.path]
        elif r.new_points:
            e["trail"] = [list(p) for p in r.new_points]
        p = r.pose
        if p is None:
            e["status"] = None
            return e
        age = max(0.0, now - r.received_at)
        e.update(
            map=p.map_id,
            status=p.status,
            seq=p.seq,
            x=round(p.pose[0], 4),
            y=round(p.pose[1], 4),
            th=round(p.pose[2], 4),
            lat=_r(p.latency_ms, 2),
            score=_r(p.score, 3),
            method=p.method,
            age=_r(age, 2),
            stale=age > STALE_S,
        )
        if p.explained is not None:
            e["explained"] = _r(p.explained, 3)
        if p.ambiguity is not None:
            e["ambiguity"] = _r(p.ambiguity, 3)
        if p.hypotheses is not None:
            e["hyp"] = p.hypotheses
        if p.candidates is not None:
            e["cand"] = p.candidates
        if p.cov_xy is not None:
            e["cov"] = [float(f"{c:.4g}") for c in p.cov_xy]
        if scan:
            beams = self._scan_for(r)
            if beams is not None:
                e["scan"] = beams
        return e

    def end_tick(self, now: float) -> list[str]:
        """After a frame went out: clear the per-tick path additions and change marks, drop
        forgotten robots. Returns the ids dropped."""
        gone = []
        for rid in list(self.robots):
            r = self.robots[rid]
            r.new_points.clear()
            r.changed = False
            r.sent_stale = now - r.received_at > STALE_S
            if r.received_at > 0 and now - r.received_at > FORGET_S:
                del self.robots[rid]
                gone.append(rid)
        return gone


def _kind_of(key: str) -> str:
    parts = key.split("/")
    if "maps" in parts:
        return "map"
    return parts[-1] if parts and parts[-1] in ("pose", "scan") else "key"


def _first_words(text: str, limit: int = 80) -> str:
    return text if len(text) <= limit else text[: limit - 3] + "..."
