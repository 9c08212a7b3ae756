"""ROS 1 and ROS 2 bags (``rosbags``, pure Python, no ROS install).

Topics are found by message type when not given: the scan topic is the ``sensor_msgs/LaserScan``
topic (``/scan`` when there are several); odometry is the ``nav_msgs/Odometry`` topic (``/odom``
when there are several), else the ``odom -> <base>`` transforms on ``/tf``. The laser offset is
the chain of ``/tf_static`` transforms from the odometry's child frame (the base) to the scan's
``header.frame_id``; only level mounts (yaw only) are accepted. ``LogScan.odom`` is the
odometry pose of the base (``nav_msgs/Odometry`` ``pose.pose`` or the ``odom -> base``
transform), linearly interpolated at the scan's ``header.stamp`` and composed with that offset:
the laser's odometry pose (m, rad, in the odometry frame).

Streaming: the bag is read once in bag-time order. Odometry poses are buffered (small); a scan is
held back only until an odometry message at or after its stamp has been read (or
:data:`MAX_WAIT_S` of bag time have passed), so it can be interpolated, then yielded.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from service.adapters.logs.scan import (
    LogInfo,
    LogScan,
    OdometryTrack,
    clean_ranges,
    tilt_of_quaternion,
    yaw_of_quaternion,
)
from service.core.pose import compose
from service.errors import LogFormatError

LASERSCAN = "sensor_msgs/msg/LaserScan"
ODOMETRY = "nav_msgs/msg/Odometry"
TF_TYPES = ("tf2_msgs/msg/TFMessage", "tf/msg/tfMessage")
#: A scan waits at most this long (bag time, s) for odometry at or after its stamp.
MAX_WAIT_S = 2.0
#: Largest roll/pitch (rad) of a laser mount still treated as level.
MAX_TILT_RAD = 1e-3


def is_ros2_bag(path: Path) -> bool:
    """Whether ``path`` is a ROS 2 bag: a directory with ``metadata.yaml``, or a ``.db3`` /
    ``.mcap`` file."""
    if path.is_dir():
        return (path / "metadata.yaml").is_file()
    return path.suffix in (".db3", ".mcap")


def _bag_path(path: Path) -> Path:
    """The path ``AnyReader`` wants: a ROS 2 storage file inside a bag directory -> the
    directory."""
    if (
        path.is_file()
        and path.suffix in (".db3", ".mcap")
        and (path.parent / "metadata.yaml").is_file()
    ):
        return path.parent
    return path


def _open(path: Path) -> Any:
    from rosbags.highlevel import AnyReader, AnyReaderError
    from rosbags.typesys import Stores, get_typestore

    try:
        reader = AnyReader([_bag_path(path)], default_typestore=get_typestore(Stores.LATEST))
        reader.open()
    except (AnyReaderError, OSError, ValueError, KeyError) as exc:
        raise LogFormatError(f"{path}: cannot open as a ROS bag: {exc}") from exc
    return reader


def _frame(name: str) -> str:
    return name.lstrip("/")


def _stamp(header: Any) -> float:
    return header.stamp.sec + header.stamp.nanosec * 1e-9


def _pick(path: Path, kind: str, topics: Sequence[str], preferred: str) -> str | None:
    names = sorted(set(topics))
    if not names:
        return None
    if len(names) == 1:
        return names[0]
    if preferred in names:
        return preferred
    raise LogFormatError(f"{path}: several {kind} topics {names}; choose one explicitly")


def _first(reader: Any, conns: list[Any]) -> Any | None:
    for conn, _t, raw in reader.messages(connections=conns):
        return reader.deserialize(raw, conn.msgtype)
    return None


def _static_transforms(reader: Any) -> dict[str, tuple[str, np.ndarray, float]]:
    """``child -> (parent, [x, y, yaw], tilt)`` of every transform on ``/tf_static``."""
    conns = [c for c in reader.connections if c.topic == "/tf_static" and c.msgtype in TF_TYPES]
    out: dict[str, tuple[str, np.ndarray, float]] = {}
    for conn, _t, raw in reader.messages(connections=conns):
        for tr in reader.deserialize(raw, conn.msgtype).transforms:
            q = tr.transform.rotation
            v = tr.transform.translation
            out[_frame(tr.child_frame_id)] = (
                _frame(tr.header.frame_id),
                np.array([v.x, v.y, yaw_of_quaternion(q.x, q.y, q.z, q.w)]),
                tilt_of_quaternion(q.x, q.y, q.z, q.w),
            )
    return out


def _chain(
    path: Path, static: dict[str, tuple[str, np.ndarray, float]], base: str, laser: str
) -> np.ndarray | None:
    """Pose of ``laser`` in ``base`` from the static transforms, ``None`` without a chain."""
    pose = np.zeros(3)
    frame = laser
    seen = set()
    while frame != base:
        if frame not in static or frame in seen:
            return None
        seen.add(frame)
        parent, tf, tilt = static[frame]
        if tilt > MAX_TILT_RAD:
            raise LogFormatError(
                f"{path}: /tf_static {parent}->{frame} tilts the laser by {math.degrees(tilt):.2f}"
                " deg; only level (yaw-only) mounts are supported (pass laser_offset to override)"
            )
        pose = compose(tf, pose)
        frame = parent
    return pose


def read_bag(
    path: Path,
    *,
    scan_topic: str | None = None,
    odom_topic: str | None = None,
    max_range: float | None = None,
    limit: int | None = None,
    laser_offset: Sequence[float] | None = None,
) -> tuple[LogInfo, Iterator[LogScan]]:
    """Open a ROS 1 (``.bag``) or ROS 2 bag; see :func:`service.adapters.logs.read_log`."""
    ros2 = is_ros2_bag(path)
    reader = _open(path)
    try:
        conns = reader.connections
        scan_conns_all = [c for c in conns if c.msgtype == LASERSCAN]
        if scan_topic is None:
            scan_topic = _pick(path, "LaserScan", [c.topic for c in scan_conns_all], "/scan")
            if scan_topic is None:
                raise LogFormatError(f"{path}: no sensor_msgs/LaserScan topic")
        scan_conns = [c for c in conns if c.topic == scan_topic]
        if not scan_conns or any(c.msgtype != LASERSCAN for c in scan_conns):
            raise LogFormatError(f"{path}: {scan_topic!r} is not a sensor_msgs/LaserScan topic")

        odom_kind = None
        if odom_topic is None:
            odom_names = [c.topic for c in conns if c.msgtype == ODOMETRY]
            odom_topic = _pick(path, "Odometry", odom_names, "/odom")
            has_tf = any(c.topic == "/tf" and c.msgtype in TF_TYPES for c in conns)
            if odom_topic is None and has_tf:
                odom_topic = "/tf"
        odom_conns = [c for c in conns if c.topic == odom_topic] if odom_topic else []
        if odom_topic is not None:
            if not odom_conns:
                raise LogFormatError(f"{path}: no topic {odom_topic!r}")
            types = {c.msgtype for c in odom_conns}
            if types == {ODOMETRY}:
                odom_kind = "odometry"
            elif types <= set(TF_TYPES):
                odom_kind = "tf"
            else:
                raise LogFormatError(f"{path}: {odom_topic!r} is neither nav_msgs/Odometry nor tf")

        first_scan = _first(reader, scan_conns)
        laser_frame = _frame(first_scan.header.frame_id) if first_scan is not None else None
        odom_frames = None
        if odom_kind == "odometry":
            m = _first(reader, odom_conns)
            if m is not None:
                odom_frames = (_frame(m.header.frame_id), _frame(m.child_frame_id))
        elif odom_kind == "tf":
            odom_frames = _tf_odom_frames(reader, odom_conns)
            if odom_frames is None:
                odom_kind, odom_topic, odom_conns = None, None, []

        if laser_offset is not None:
            offset = np.asarray(laser_offset, dtype=np.float64).reshape(3)
            source = "given"
        else:
            offset, source = np.zeros(3), "none"
            if odom_frames is not None and laser_frame is not None:
                chain = _chain(path, _static_transforms(reader), odom_frames[1], laser_frame)
                if chain is not None and laser_frame != odom_frames[1]:
                    offset, source = chain, "tf_static"
        info = LogInfo(
            format="ros2" if ros2 else "ros1",
            path=path,
            scan_count=sum(c.msgcount for c in scan_conns),
            beams=len(first_scan.ranges) if first_scan is not None else None,
            angle_min=float(first_scan.angle_min) if first_scan is not None else None,
            angle_increment=float(first_scan.angle_increment) if first_scan is not None else None,
            laser_offset=offset,
            laser_offset_source=source,
            scan_topic=scan_topic,
            odom_topic=odom_topic,
            odom_frames=odom_frames,
            laser_frame=laser_frame,
            duration=reader.duration * 1e-9,
        )
    finally:
        reader.close()
    return info, _stream(info, odom_kind, max_range, limit)


def _tf_odom_frames(reader: Any, conns: list[Any]) -> tuple[str, str] | None:
    """``("odom", child)`` of the first ``odom -> child`` transform on the tf topic."""
    for k, (conn, _t, raw) in enumerate(reader.messages(connections=conns)):
        for tr in reader.deserialize(raw, conn.msgtype).transforms:
            if _frame(tr.header.frame_id) == "odom":
                return ("odom", _frame(tr.child_frame_id))
        if k > 1000:
            break
    return None


def _stream(
    info: LogInfo,
    odom_kind: str | None,
    max_range: float | None,
    limit: int | None,
) -> Iterator[LogScan]:
    if limit is not None and limit <= 0:
        return
    reader = _open(info.path)  # already open: AnyReader's context manager would reopen it
    try:
        track = OdometryTrack()
        offset = info.laser_offset
        topic = info.odom_topic
        # connections belong to one reader: look the topics up again in this one
        scan_conns = [c for c in reader.connections if c.topic == info.scan_topic]
        conns = scan_conns + [c for c in reader.connections if topic and c.topic == topic]
        scan_ids = {c.id for c in scan_conns}
        pending: deque[tuple[int, float, Any]] = deque()  # (bag time ns, stamp, message)
        index = 0
        emitted = 0

        def build(stamp: float, msg: Any) -> LogScan:
            nonlocal index
            rmax = float(msg.range_max)
            if max_range is not None:
                rmax = min(rmax, float(max_range))
            odom = None
            if odom_kind is not None:
                base = track.at(stamp)
                odom = compose(base, offset) if base is not None else None
            scan = LogScan(
                index=index,
                stamp=stamp,
                angle_min=float(msg.angle_min),
                angle_increment=float(msg.angle_increment),
                range_min=float(msg.range_min),
                range_max=rmax,
                ranges=clean_ranges(np.asarray(msg.ranges), float(msg.range_min), rmax),
                odom=odom,
            )
            index += 1
            return scan

        for conn, t_ns, raw in reader.messages(connections=conns):
            msg = reader.deserialize(raw, conn.msgtype)
            if conn.id in scan_ids:
                pending.append((t_ns, _stamp(msg.header), msg))
            elif odom_kind == "odometry":
                p = msg.pose.pose
                q = p.orientation
                track.add(
                    _stamp(msg.header),
                    p.position.x,
                    p.position.y,
                    yaw_of_quaternion(q.x, q.y, q.z, q.w),
                )
            else:
                child = info.odom_frames[1] if info.odom_frames else ""
                for tr in msg.transforms:
                    if _frame(tr.header.frame_id) == "odom" and _frame(tr.child_frame_id) == child:
                        v, q = tr.transform.translation, tr.transform.rotation
                        yaw = yaw_of_quaternion(q.x, q.y, q.z, q.w)
                        track.add(_stamp(tr.header), v.x, v.y, yaw)
            while pending and (
                odom_kind is None
                or pending[0][1] <= track.last_stamp
                or t_ns - pending[0][0] > MAX_WAIT_S * 1e9
            ):
                _t, stamp, m = pending.popleft()
                yield build(stamp, m)
                emitted += 1
                if limit is not None and emitted >= limit:
                    return
        while pending:
            _t, stamp, m = pending.popleft()
            yield build(stamp, m)
            emitted += 1
            if limit is not None and emitted >= limit:
                return
    finally:
        reader.close()
