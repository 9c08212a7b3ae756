"""``shapeloc record FILE.mcap``: record what a shapeloc service publishes, for Foxglove.

Subscribes to the poses, scans, maps and error notices of a prefix and writes them, as they
arrive, into an MCAP file (the ``mcap`` package's writer, zstd chunks) with Foxglove's
well-known schemas, JSON-encoded (:mod:`clients.foxglove_msgs`), so Foxglove opens a run with
no conversion. Topics:

=============================  ======================  =====================================
topic                          schema                  what
=============================  ======================  =====================================
``/maps/<map_id>``             foxglove.SceneUpdate    the map's polylines (frame = map id)
``/robots/<id>/pose``          foxglove.PoseInFrame    each estimate, in its map's frame
``/tf``                        foxglove.FrameTransform map frame -> robot frame at each estimate
``/robots/<id>/scan``          foxglove.PointCloud     each scan's returns, in the robot frame
                                                       (so drawn at the published pose)
``/robots/<id>/candidates``    foxglove.PosesInFrame   a global search's candidate places
``/robots/<id>/estimate``      shapeloc.Pose           the pose message itself (latency,
                                                       explained, ambiguity, ... for plots)
``/status``                    foxglove.Log            each robot's first status and changes
``/errors``                    foxglove.Log            the service's error notices
=============================  ======================  =====================================

A message's log time is its receipt time; its ``timestamp`` is the robot's ``stamp`` (scans,
poses, transforms) so Foxglove pairs a scan with the estimate that answers it. Zenoh callbacks
only queue the raw samples; one thread decodes and writes. A payload that does not decode is
counted (``RecordStats.rejected``) and skipped.

Why the ``mcap`` package and not ``foxglove-sdk``: the SDK writes protobuf-encoded messages
through a compiled extension and would be a second way to make the same file; ``mcap`` is the
format's own small pure-Python reader and writer (the tests read the file back with it), and
Foxglove reads JSON messages with JSON Schemas as natively as protobuf.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import logging
import queue
import sys
import threading
import time
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any, BinaryIO

import zenoh
from mcap.writer import CompressionType, Writer

from clients import foxglove_msgs as fx
from clients.view.palette import MAP_COLOURS, STATUS_COLOURS, rgba
from schemas import keys
from schemas.codec import check_key_id, decode
from schemas.messages import ErrorNotice, Map, PoseMsg, Scan
from service.errors import InvalidMessage

log = logging.getLogger("shapeloc.record")

#: Raw samples waiting for the writer; beyond it new ones are dropped (and counted).
QUEUE_LIMIT = 200_000
#: Seconds at least between two map queries for a map a robot names but the file lacks.
MAPS_EVERY_S = 2.0
POSE_SCHEMA = "shapeloc.Pose"

#: A queued sample: (key, is_delete, payload, encoding, receipt time in ns).
RawSample = tuple[str, bool, bytes, str | None, int]


@dataclass
class RecordStats:
    """What a recording holds (counts of written messages by kind) and what it skipped."""

    path: str = ""
    poses: int = 0
    scans: int = 0
    maps: int = 0
    errors: int = 0
    messages: int = 0
    dropped: int = 0
    rejected: Counter[str] = field(default_factory=Counter)

    def as_dict(self) -> dict[str, Any]:
        """The counts as plain data (``--json``)."""
        d = dataclasses.asdict(self)
        d["rejected"] = dict(self.rejected)
        return d

    def line(self) -> str:
        """One line for the terminal."""
        bad = sum(self.rejected.values())
        return (
            f"{self.path}: {self.messages} messages ({self.poses} poses, {self.scans} scans, "
            f"{self.maps} maps, {self.errors} error notices); {bad} rejected, "
            f"{self.dropped} dropped"
        )


def _pose_schema() -> bytes:
    text = (resources.files("schemas") / "json" / "pose.schema.json").read_text()
    schema = json.loads(text)
    schema["title"] = POSE_SCHEMA
    return json.dumps(schema).encode()


class Recorder:
    """Writes raw wire samples into an MCAP stream as Foxglove messages (one thread only).

    ``out``: a binary file opened for writing; :meth:`finish` completes the file (it does not
    close ``out``). ``robots``: record only these robot ids (``None``: all).
    """

    def __init__(
        self, out: BinaryIO, prefix: str = keys.DEFAULT_PREFIX, robots: set[str] | None = None
    ) -> None:
        self.prefix = keys.validate_prefix(prefix)
        self.robots = robots
        self.writer = Writer(out, compression=CompressionType.ZSTD)
        self.writer.start(profile="", library="shapeloc record")
        self.stats = RecordStats(path=getattr(out, "name", ""))
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, int] = {}
        self._seq: Counter[int] = Counter()
        self._last_ns = 0
        self._status: dict[str, str] = {}
        self._had_candidates: set[str] = set()
        self.map_ids: set[str] = set()
        self.wanted_maps: set[str] = set()
        self._finished = False

    # ------------------------------------------------------------------ channels
    def _schema_id(self, name: str) -> int:
        sid = self._schemas.get(name)
        if sid is None:
            data = _pose_schema() if name == POSE_SCHEMA else json.dumps(fx.SCHEMAS[name]).encode()
            sid = self.writer.register_schema(name=name, encoding="jsonschema", data=data)
            self._schemas[name] = sid
        return sid

    def _write(self, topic: str, schema: str, msg: dict[str, Any], t_ns: int, stamp: float) -> None:
        cid = self._channels.get(topic)
        if cid is None:
            cid = self.writer.register_channel(
                topic=topic, message_encoding="json", schema_id=self._schema_id(schema)
            )
            self._channels[topic] = cid
        # Log times never go backwards, whatever the order the callbacks' clocks were read.
        self._last_ns = max(self._last_ns, t_ns)
        pub = max(0, round(stamp * 1e9)) if stamp == stamp and abs(stamp) < 1e11 else 0
        self.writer.add_message(
            channel_id=cid,
            log_time=self._last_ns,
            publish_time=pub,
            data=json.dumps(msg, allow_nan=False, separators=(",", ":")).encode(),
            sequence=self._seq[cid],
        )
        self._seq[cid] += 1
        self.stats.messages += 1

    # ------------------------------------------------------------------ samples
    def handle(
        self, key: str, delete: bool, payload: bytes, encoding: str | None, t_ns: int
    ) -> None:
        """Decode one raw sample and write what it becomes (nothing if it is rejected)."""
        try:
            if key.startswith(f"{self.prefix}/robots/"):
                robot_id, leaf = keys.parse_robot_key(self.prefix, key)
                if delete or (self.robots is not None and robot_id not in self.robots):
                    return
                if leaf == "pose":
                    self._pose(robot_id, decode(PoseMsg, payload, encoding), t_ns)
                elif leaf == "scan":
                    self._scan(robot_id, decode(Scan, payload, encoding), t_ns)
            elif key.startswith(f"{self.prefix}/maps/"):
                map_id = keys.parse_map_key(self.prefix, key)
                if delete:
                    self._write(
                        f"/maps/{map_id}",
                        "foxglove.SceneUpdate",
                        fx.map_deletion(map_id, t_ns / 1e9),
                        t_ns,
                        t_ns / 1e9,
                    )
                    self.map_ids.discard(map_id)
                else:
                    m = decode(Map, payload, encoding)
                    check_key_id(m.map_id, map_id, "map_id")
                    self.add_map(m, t_ns)
            elif key == keys.errors_key(self.prefix):
                self._error(decode(ErrorNotice, payload, encoding), t_ns)
            else:
                self.stats.rejected["key"] += 1
        except InvalidMessage as exc:
            kind = _kind_of(self.prefix, key)
            if not self.stats.rejected:
                log.warning("record: rejected a sample on %s: %s", key[:200], exc)
            self.stats.rejected[kind] += 1

    def add_map(self, m: Map, t_ns: int) -> None:
        """Write a map's scene (also when it is put again: Foxglove replaces the entity)."""
        colour = rgba(MAP_COLOURS.get(m.kind, "#303030"))
        self._write(
            f"/maps/{m.map_id}",
            "foxglove.SceneUpdate",
            fx.map_scene(m, t_ns / 1e9, colour),
            t_ns,
            t_ns / 1e9,
        )
        self.map_ids.add(m.map_id)
        self.wanted_maps.discard(m.map_id)
        self.stats.maps += 1

    def _pose(self, robot_id: str, msg: PoseMsg, t_ns: int) -> None:
        if msg.robot_id != robot_id:
            raise InvalidMessage(f"robot_id {msg.robot_id!r} differs from the key's")
        base = f"/robots/{robot_id}"
        self._write("/tf", "foxglove.FrameTransform", fx.robot_transform(msg), t_ns, msg.stamp)
        self._write(f"{base}/pose", "foxglove.PoseInFrame", fx.pose_in_frame(msg), t_ns, msg.stamp)
        has_cand = msg.candidates is not None and len(msg.candidates) > 0
        if has_cand or robot_id in self._had_candidates:
            # an empty list once the search ends clears the candidates in Foxglove
            self._write(
                f"{base}/candidates",
                "foxglove.PosesInFrame",
                fx.candidates_in_frame(msg),
                t_ns,
                msg.stamp,
            )
            (self._had_candidates.add if has_cand else self._had_candidates.discard)(robot_id)
        self._write(f"{base}/estimate", POSE_SCHEMA, msg.to_wire(), t_ns, msg.stamp)
        old = self._status.get(robot_id)
        if old != msg.status:
            self._status[robot_id] = msg.status
            label = STATUS_COLOURS.get(msg.status, ("", msg.status))[1]
            text = f"{robot_id}: {label}" if old is None else f"{robot_id}: {old} -> {label}"
            if msg.explained is not None:
                text += f" (explained {msg.explained:.2f})"
            level = "WARNING" if msg.status == "lost" else "INFO"
            self._write(
                "/status",
                "foxglove.Log",
                fx.log_message(msg.stamp, level, robot_id, text),
                t_ns,
                msg.stamp,
            )
        if msg.map_id not in self.map_ids:
            self.wanted_maps.add(msg.map_id)
        self.stats.poses += 1

    def _scan(self, robot_id: str, scan: Scan, t_ns: int) -> None:
        self._write(
            f"/robots/{robot_id}/scan",
            "foxglove.PointCloud",
            fx.scan_cloud(robot_id, scan),
            t_ns,
            scan.stamp,
        )
        self.stats.scans += 1

    def _error(self, notice: ErrorNotice, t_ns: int) -> None:
        t = t_ns / 1e9
        msg = fx.log_message(t, "WARNING", "service", f"{notice.key}: {notice.error}")
        self._write("/errors", "foxglove.Log", msg, t_ns, t)
        self.stats.errors += 1

    def finish(self) -> RecordStats:
        """Write the summary and end the file (idempotent)."""
        if not self._finished:
            self._finished = True
            self.writer.finish()
        return self.stats


def _kind_of(prefix: str, key: str) -> str:
    if key.startswith(f"{prefix}/robots/"):
        return key.rsplit("/", 1)[-1]
    if key.startswith(f"{prefix}/maps/"):
        return "map"
    return "errors"


def _get(session: zenoh.Session, key: str, timeout: float = 2.0) -> list[RawSample]:
    out: list[RawSample] = []
    with contextlib.suppress(zenoh.ZError):
        for reply in session.get(key, timeout=timeout):
            if reply.ok is not None:
                s = reply.ok
                enc = None if s.encoding is None else str(s.encoding)
                out.append((str(s.key_expr), False, s.payload.to_bytes(), enc, time.time_ns()))
    return out


def main(
    conf: zenoh.Config,
    path: str | Path,
    *,
    prefix: str = keys.DEFAULT_PREFIX,
    robots: set[str] | None = None,
    duration: float | None = None,
    stop: threading.Event | None = None,
    ready: Callable[[], None] | None = None,
) -> RecordStats:
    """Record into ``path`` until ``stop`` is set or ``duration`` seconds pass; returns what
    was written. ``ready()`` is called once the subscribers are declared and the stored maps
    written. Raises ``zenoh.ZError`` if the session cannot be opened, ``OSError`` if the file
    cannot be written."""
    stop = stop or threading.Event()
    q: queue.Queue[RawSample] = queue.Queue(QUEUE_LIMIT)
    dropped = [0]

    def on_sample(sample: zenoh.Sample) -> None:
        enc = sample.encoding
        item = (
            str(sample.key_expr),
            sample.kind == zenoh.SampleKind.DELETE,
            sample.payload.to_bytes(),
            None if enc is None else str(enc),
            time.time_ns(),
        )
        try:
            q.put_nowait(item)
        except queue.Full:
            dropped[0] += 1

    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    with zenoh.open(conf) as session, open(out, "wb") as f:
        rec = Recorder(f, prefix, robots)
        rec.stats.path = str(out)
        subs = [
            session.declare_subscriber(k, on_sample)
            for k in (
                keys.robots_wildcard(prefix, "pose"),
                keys.robots_wildcard(prefix, "scan"),
                keys.maps_wildcard(prefix),
                keys.errors_key(prefix),
            )
        ]
        for item in _get(session, keys.maps_wildcard(prefix)):
            rec.handle(*item)
        if ready is not None:
            ready()
        end = None if duration is None else time.monotonic() + duration
        last_maps_query = time.monotonic()
        try:
            while not stop.is_set() and (end is None or time.monotonic() < end):
                with contextlib.suppress(queue.Empty):
                    rec.handle(*q.get(timeout=0.1))
                if rec.wanted_maps and time.monotonic() - last_maps_query > MAPS_EVERY_S:
                    last_maps_query = time.monotonic()
                    for item in _get(session, keys.maps_wildcard(prefix)):
                        rec.handle(*item)
        finally:
            for s in subs:
                with contextlib.suppress(zenoh.ZError):
                    s.undeclare()
            while True:  # what arrived before the subscribers went
                try:
                    rec.handle(*q.get_nowait())
                except queue.Empty:
                    break
            rec.stats.dropped = dropped[0]
            stats = rec.finish()
    return stats


if __name__ == "__main__":  # the same as ``shapeloc record`` (options: its --help)
    from clients.__main__ import cli

    sys.exit(cli(["record", *sys.argv[1:]]))
