"""CDR encode / decode of the five ROS 2 messages the front uses, as planar values.

Decoding takes the bytes of a sample as rmw_zenoh puts them (the 4-byte CDR encapsulation
header, then the XCDR1 body; little- or big-endian) and returns small frozen dataclasses in
SI units with the planar part of every pose (``x``, ``y``, ``yaw``): the wire of a 2-D
localiser. Every decode treats its input as untrusted: a payload that is not CDR, is
truncated, holds the wrong type, carries NaN/inf where a number is needed, or is larger than
the limits below raises :class:`service.errors.InvalidMessage` naming the message and field.

Encoding goes through ``rosbags``' serializer of the target distribution's type store
(:mod:`schemas.ros2.types`), so what is published is exactly that distribution's layout.

Conventions (REP 103 / REP 105): angles in radians counter-clockwise, frames ``x`` forward and
``y`` left; a quaternion ``(x, y, z, w)`` is turned into its yaw and the tilt of its z axis.
Frame ids are returned without a leading ``/`` (tf2 rejects one).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Final

import numpy as np

from schemas.limits import MAX_BEAMS, MAX_FOV, MAX_PAYLOAD_BYTES
from schemas.ros2.types import (
    LASER_SCAN,
    OCCUPANCY_GRID,
    ODOMETRY,
    POSE_WITH_COVARIANCE_STAMPED,
    TF_MESSAGE,
    RosType,
    typestore,
)
from service.errors import InvalidMessage

#: Most transforms in one TFMessage.
MAX_TRANSFORMS: Final[int] = 1024
#: Longest frame id (characters).
MAX_FRAME_LEN: Final[int] = 256
#: Most cells of an OccupancyGrid (as ``service.maps.grid`` accepts from files: 64 M cells).
MAX_GRID_CELLS: Final[int] = 64_000_000
#: Largest OccupancyGrid payload (its cells plus the header and metadata).
MAX_GRID_BYTES: Final[int] = MAX_GRID_CELLS + 4096
#: Indices of x, y and yaw in a row-major 6x6 ROS covariance (x, y, z, roll, pitch, yaw).
COV_INDEX: Final[tuple[int, int, int]] = (0, 1, 5)

_INT32 = (-(2**31), 2**31 - 1)


# --------------------------------------------------------------------------- values
@dataclass(frozen=True)
class Stamp:
    """A ``builtin_interfaces/Time``: ``sec`` (int32) and ``nanosec`` (0 .. 999 999 999)."""

    sec: int
    nanosec: int

    def __post_init__(self) -> None:
        if isinstance(self.sec, bool) or not isinstance(self.sec, (int, np.integer)):
            raise InvalidMessage(f"stamp.sec: must be an integer, got {self.sec!r}")
        if not _INT32[0] <= int(self.sec) <= _INT32[1]:
            raise InvalidMessage(f"stamp.sec: {self.sec} is outside int32")
        if isinstance(self.nanosec, bool) or not isinstance(self.nanosec, (int, np.integer)):
            raise InvalidMessage(f"stamp.nanosec: must be an integer, got {self.nanosec!r}")
        if not 0 <= int(self.nanosec) < 1_000_000_000:
            raise InvalidMessage(f"stamp.nanosec: {self.nanosec} is outside 0..999999999")
        object.__setattr__(self, "sec", int(self.sec))
        object.__setattr__(self, "nanosec", int(self.nanosec))

    @property
    def nanoseconds(self) -> int:
        """The stamp in integer nanoseconds."""
        return self.sec * 1_000_000_000 + self.nanosec

    def seconds(self) -> float:
        """The stamp in seconds (float; about 0.2 us resolution at today's epoch times)."""
        return self.sec + self.nanosec * 1e-9

    @staticmethod
    def from_nanoseconds(ns: int) -> Stamp:
        """The stamp of ``ns`` integer nanoseconds."""
        sec, nsec = divmod(int(ns), 1_000_000_000)
        return Stamp(sec, nsec)

    @staticmethod
    def from_seconds(t: float) -> Stamp:
        """The stamp nearest to ``t`` seconds (finite)."""
        if not math.isfinite(t):
            raise InvalidMessage(f"stamp: {t!r} is not a finite time")
        return Stamp.from_nanoseconds(round(t * 1e9))


@dataclass(frozen=True)
class Transform2D:
    """One ``geometry_msgs/TransformStamped``: ``child`` in ``parent`` at ``stamp``.

    ``x``, ``y`` metres, ``yaw`` radians (-pi, pi]; ``z`` the height and ``tilt`` the angle
    (radians) between the child's z axis and the parent's (0 for a level mount).
    """

    stamp: Stamp
    parent: str
    child: str
    x: float
    y: float
    yaw: float
    z: float = 0.0
    tilt: float = 0.0

    @property
    def pose(self) -> tuple[float, float, float]:
        """``(x, y, yaw)``."""
        return (self.x, self.y, self.yaw)


@dataclass(frozen=True, eq=False)
class LaserScan:
    """A ``sensor_msgs/LaserScan`` with increasing beam angles.

    Beam ``i`` points at ``angle_min + i * angle_increment`` in ``frame_id``;
    ``angle_increment > 0`` (a scan sent with a negative increment is reversed on decode).
    ``ranges`` is a read-only float64 ``(n,)`` array of the values as sent (NaN, inf or values
    outside ``[range_min, range_max]`` mean no return).
    """

    stamp: Stamp
    frame_id: str
    angle_min: float
    angle_increment: float
    range_min: float
    range_max: float
    ranges: np.ndarray
    scan_time: float = 0.0
    time_increment: float = 0.0


@dataclass(frozen=True)
class Odometry2D:
    """The pose part of a ``nav_msgs/Odometry``: ``child_frame_id`` in ``frame_id``."""

    stamp: Stamp
    frame_id: str
    child_frame_id: str
    x: float
    y: float
    yaw: float


@dataclass(frozen=True, eq=False)
class PoseWithCovariance2D:
    """A ``geometry_msgs/PoseWithCovarianceStamped`` in the plane.

    ``covariance`` is the read-only ``(3, 3)`` covariance of ``[x, y, yaw]`` (rows and columns
    0, 1 and 5 of the message's 6x6).
    """

    stamp: Stamp
    frame_id: str
    x: float
    y: float
    yaw: float
    covariance: np.ndarray


@dataclass(frozen=True, eq=False)
class Grid:
    """A ``nav_msgs/OccupancyGrid``.

    ``data`` read-only int8 ``(height, width)``: row 0 is the message's first row, the one at
    the origin (so it is the bottom row when drawn with y up); values -1 unknown, 0..100
    occupancy percent. ``origin`` ``(x, y, yaw)`` is the pose of the corner of cell (0, 0).
    """

    stamp: Stamp
    frame_id: str
    resolution: float
    origin: tuple[float, float, float]
    data: np.ndarray

    @property
    def height(self) -> int:
        """Rows."""
        return int(self.data.shape[0])

    @property
    def width(self) -> int:
        """Columns."""
        return int(self.data.shape[1])


# --------------------------------------------------------------------------- helpers
def _fail(what: str, reason: str) -> InvalidMessage:
    return InvalidMessage(f"{what}: {reason}")


def _finite(what: str, value: Any) -> float:
    v = float(value)
    if not math.isfinite(v):
        raise _fail(what, f"must be finite, got {v!r}")
    return v


def frame_name(what: str, value: Any) -> str:
    """A frame id as tf2 keeps it: a string without leading ``/``, 1 to
    :data:`MAX_FRAME_LEN` characters, no whitespace or control characters."""
    if not isinstance(value, str):
        raise _fail(what, f"must be a string, got {type(value).__name__}")
    name = value.lstrip("/")
    if not name:
        raise _fail(what, "is empty")
    if len(name) > MAX_FRAME_LEN:
        raise _fail(what, f"{len(name)} characters exceeds limit {MAX_FRAME_LEN}")
    if any(c.isspace() or ord(c) < 32 or ord(c) == 127 for c in name):
        raise _fail(what, f"{name[:80]!r} holds whitespace or control characters")
    return name


def yaw_of(x: float, y: float, z: float, w: float) -> float:
    """Yaw (radians, (-pi, pi]) of the quaternion ``(x, y, z, w)`` (any norm > 0)."""
    yaw = math.atan2(2.0 * (w * z + x * y), w * w + x * x - y * y - z * z)
    return math.pi if yaw == -math.pi else yaw


def tilt_of(x: float, y: float, z: float, w: float) -> float:
    """Angle (radians) between the rotated z axis of a unit quaternion and the z axis."""
    c = 1.0 - 2.0 * (x * x + y * y)
    return math.acos(max(-1.0, min(1.0, c)))


def quaternion_of_yaw(yaw: float) -> tuple[float, float, float, float]:
    """``(x, y, z, w)`` of a rotation by ``yaw`` about z."""
    return (0.0, 0.0, math.sin(0.5 * yaw), math.cos(0.5 * yaw))


def _rotation(what: str, q: Any) -> tuple[float, float]:
    """``(yaw, tilt)`` of a message quaternion, checked and normalised."""
    x, y, z, w = (_finite(f"{what}.{k}", getattr(q, k)) for k in ("x", "y", "z", "w"))
    n = math.sqrt(x * x + y * y + z * z + w * w)
    if not 0.5 < n < 2.0:
        raise _fail(what, f"quaternion norm {n:.6g} is not about 1")
    x, y, z, w = x / n, y / n, z / n, w / n
    return yaw_of(x, y, z, w), tilt_of(x, y, z, w)


def _stamp(what: str, t: Any) -> Stamp:
    return Stamp(int(t.sec), int(t.nanosec)) if t is not None else _none(what)


def _none(what: str) -> Stamp:
    raise _fail(what, "missing")


def _deserialize(data: object, rtype: RosType, limit: int = MAX_PAYLOAD_BYTES) -> Any:
    """``rosbags``' object of ``data``; every failure of the untrusted bytes (any exception
    of the third-party parser, which has no error type of its own) becomes InvalidMessage."""
    what = rtype.ros.rsplit("/", 1)[-1]
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise _fail(what, f"payload must be bytes, got {type(data).__name__}")
    raw = bytes(data)
    if len(raw) > limit:
        raise _fail(what, f"payload of {len(raw)} bytes exceeds limit {limit}")
    if len(raw) < 4:
        raise _fail(what, f"payload of {len(raw)} bytes is shorter than the CDR header")
    if raw[0] != 0 or raw[1] not in (0, 1):
        raise _fail(what, f"not a plain CDR encapsulation (header {raw[:4].hex()})")
    try:
        return typestore().deserialize_cdr(raw, rtype.ros)
    except Exception as exc:  # untrusted bytes through a third-party parser: any failure
        raise _fail(what, f"malformed or truncated CDR ({type(exc).__name__}: {exc})") from None


def _serialize(msg: Any, rtype: RosType) -> bytes:
    return bytes(typestore().serialize_cdr(msg, rtype.ros))


def _ros_types() -> dict[str, Any]:
    return typestore().types


def _header(stamp: Stamp, frame_id: str) -> Any:
    t = _ros_types()
    time = t["builtin_interfaces/msg/Time"](sec=stamp.sec, nanosec=stamp.nanosec)
    return t["std_msgs/msg/Header"](stamp=time, frame_id=frame_id)


def _pose_msg(x: float, y: float, yaw: float, z: float = 0.0) -> Any:
    t = _ros_types()
    qx, qy, qz, qw = quaternion_of_yaw(yaw)
    return t["geometry_msgs/msg/Pose"](
        position=t["geometry_msgs/msg/Point"](x=float(x), y=float(y), z=float(z)),
        orientation=t["geometry_msgs/msg/Quaternion"](x=qx, y=qy, z=qz, w=qw),
    )


def _pose_2d(what: str, pose: Any) -> tuple[float, float, float]:
    x = _finite(f"{what}.position.x", pose.position.x)
    y = _finite(f"{what}.position.y", pose.position.y)
    _finite(f"{what}.position.z", pose.position.z)
    yaw, _tilt = _rotation(f"{what}.orientation", pose.orientation)
    return x, y, yaw


# --------------------------------------------------------------------------- LaserScan
def decode_laser_scan(data: object) -> LaserScan:
    """Decode and check a ``sensor_msgs/LaserScan`` (see :class:`LaserScan`)."""
    m = _deserialize(data, LASER_SCAN)
    w = "LaserScan"
    stamp = _stamp(f"{w}.header.stamp", m.header.stamp)
    frame = frame_name(f"{w}.header.frame_id", m.header.frame_id)
    angle_min = _finite(f"{w}.angle_min", m.angle_min)
    _finite(f"{w}.angle_max", m.angle_max)
    inc = _finite(f"{w}.angle_increment", m.angle_increment)
    rmin = _finite(f"{w}.range_min", m.range_min)
    rmax = _finite(f"{w}.range_max", m.range_max)
    scan_time = _finite(f"{w}.scan_time", m.scan_time)
    time_inc = _finite(f"{w}.time_increment", m.time_increment)
    ranges = np.asarray(m.ranges, dtype=np.float64)
    n = len(ranges)
    if n < 1:
        raise _fail(f"{w}.ranges", "is empty")
    if n > MAX_BEAMS:
        raise _fail(f"{w}.ranges", f"{n} elements exceeds limit {MAX_BEAMS}")
    if inc == 0.0:
        raise _fail(f"{w}.angle_increment", "must not be 0")
    if (n - 1) * abs(inc) > MAX_FOV:
        raise _fail(f"{w}.angle_increment", f"{n} beams x {inc!r} rad spans more than 2*pi")
    if rmin < 0.0:
        raise _fail(f"{w}.range_min", f"must be >= 0, got {rmin!r}")
    if not rmax > rmin:
        raise _fail(f"{w}.range_max", f"must be > range_min ({rmin!r}), got {rmax!r}")
    if inc < 0.0:  # a scanner turning clockwise: the same beams in increasing angle order
        angle_min, inc, ranges = angle_min + (n - 1) * inc, -inc, ranges[::-1].copy()
    ranges.setflags(write=False)
    return LaserScan(stamp, frame, angle_min, inc, rmin, rmax, ranges, scan_time, time_inc)


def encode_laser_scan(scan: LaserScan) -> bytes:
    """CDR bytes of ``scan`` (``angle_max`` = the last beam's angle; ranges as float32, no
    intensities)."""
    t = _ros_types()
    ranges = np.asarray(scan.ranges, dtype=np.float32)
    msg = t[LASER_SCAN.ros](
        header=_header(scan.stamp, scan.frame_id),
        angle_min=float(scan.angle_min),
        angle_max=float(scan.angle_min + (len(ranges) - 1) * scan.angle_increment),
        angle_increment=float(scan.angle_increment),
        time_increment=float(scan.time_increment),
        scan_time=float(scan.scan_time),
        range_min=float(scan.range_min),
        range_max=float(scan.range_max),
        ranges=ranges,
        intensities=np.zeros(0, dtype=np.float32),
    )
    return _serialize(msg, LASER_SCAN)


# --------------------------------------------------------------------------- TFMessage
def decode_tf(data: object) -> tuple[Transform2D, ...]:
    """Decode and check a ``tf2_msgs/TFMessage`` (at most :data:`MAX_TRANSFORMS`)."""
    m = _deserialize(data, TF_MESSAGE)
    if len(m.transforms) > MAX_TRANSFORMS:
        raise _fail("TFMessage.transforms", f"{len(m.transforms)} exceeds limit {MAX_TRANSFORMS}")
    out = []
    for k, tr in enumerate(m.transforms):
        w = f"TFMessage.transforms[{k}]"
        parent = frame_name(f"{w}.header.frame_id", tr.header.frame_id)
        child = frame_name(f"{w}.child_frame_id", tr.child_frame_id)
        if parent == child:
            raise _fail(w, f"frame {parent!r} is its own parent")
        v = tr.transform.translation
        x = _finite(f"{w}.transform.translation.x", v.x)
        y = _finite(f"{w}.transform.translation.y", v.y)
        z = _finite(f"{w}.transform.translation.z", v.z)
        yaw, tilt = _rotation(f"{w}.transform.rotation", tr.transform.rotation)
        stamp = _stamp(f"{w}.header.stamp", tr.header.stamp)
        out.append(Transform2D(stamp, parent, child, x, y, yaw, z, tilt))
    return tuple(out)


def encode_tf(transforms: Sequence[Transform2D]) -> bytes:
    """CDR bytes of a ``tf2_msgs/TFMessage`` of planar transforms (rotation about z only)."""
    t = _ros_types()
    items = []
    for tr in transforms:
        qx, qy, qz, qw = quaternion_of_yaw(tr.yaw)
        items.append(
            t["geometry_msgs/msg/TransformStamped"](
                header=_header(tr.stamp, tr.parent),
                child_frame_id=tr.child,
                transform=t["geometry_msgs/msg/Transform"](
                    translation=t["geometry_msgs/msg/Vector3"](
                        x=float(tr.x), y=float(tr.y), z=float(tr.z)
                    ),
                    rotation=t["geometry_msgs/msg/Quaternion"](x=qx, y=qy, z=qz, w=qw),
                ),
            )
        )
    return _serialize(t[TF_MESSAGE.ros](transforms=items), TF_MESSAGE)


# --------------------------------------------------------------------------- Odometry
def decode_odometry(data: object) -> Odometry2D:
    """Decode and check the pose of a ``nav_msgs/Odometry``."""
    m = _deserialize(data, ODOMETRY)
    w = "Odometry"
    stamp = _stamp(f"{w}.header.stamp", m.header.stamp)
    frame = frame_name(f"{w}.header.frame_id", m.header.frame_id)
    child = frame_name(f"{w}.child_frame_id", m.child_frame_id)
    x, y, yaw = _pose_2d(f"{w}.pose.pose", m.pose.pose)
    return Odometry2D(stamp, frame, child, x, y, yaw)


def encode_odometry(odom: Odometry2D) -> bytes:
    """CDR bytes of a ``nav_msgs/Odometry`` with this pose (zero twist and covariances)."""
    t = _ros_types()
    zeros = np.zeros(36, dtype=np.float64)
    vec = t["geometry_msgs/msg/Vector3"]
    msg = t[ODOMETRY.ros](
        header=_header(odom.stamp, odom.frame_id),
        child_frame_id=odom.child_frame_id,
        pose=t["geometry_msgs/msg/PoseWithCovariance"](
            pose=_pose_msg(odom.x, odom.y, odom.yaw), covariance=zeros
        ),
        twist=t["geometry_msgs/msg/TwistWithCovariance"](
            twist=t["geometry_msgs/msg/Twist"](
                linear=vec(x=0.0, y=0.0, z=0.0), angular=vec(x=0.0, y=0.0, z=0.0)
            ),
            covariance=zeros,
        ),
    )
    return _serialize(msg, ODOMETRY)


# --------------------------------------------------------------------------- pose
def covariance_6x6(cov3: np.ndarray) -> np.ndarray:
    """The row-major 36-element ROS covariance holding the ``(3, 3)`` covariance of
    ``[x, y, yaw]`` at rows/columns 0, 1, 5 (zeros elsewhere)."""
    c = np.asarray(cov3, dtype=np.float64).reshape(3, 3)
    out = np.zeros((6, 6), dtype=np.float64)
    idx = np.array(COV_INDEX)
    out[np.ix_(idx, idx)] = c
    return out.reshape(36)


def decode_pose_with_covariance(data: object) -> PoseWithCovariance2D:
    """Decode and check a ``geometry_msgs/PoseWithCovarianceStamped``."""
    m = _deserialize(data, POSE_WITH_COVARIANCE_STAMPED)
    w = "PoseWithCovarianceStamped"
    stamp = _stamp(f"{w}.header.stamp", m.header.stamp)
    frame = frame_name(f"{w}.header.frame_id", m.header.frame_id)
    x, y, yaw = _pose_2d(f"{w}.pose.pose", m.pose.pose)
    cov = np.asarray(m.pose.covariance, dtype=np.float64)
    if cov.shape != (36,):
        raise _fail(f"{w}.pose.covariance", f"has {cov.size} elements, expected 36")
    if not np.all(np.isfinite(cov)):
        raise _fail(f"{w}.pose.covariance", "must be finite")
    idx = np.array(COV_INDEX)
    cov3 = cov.reshape(6, 6)[np.ix_(idx, idx)].copy()
    cov3.setflags(write=False)
    return PoseWithCovariance2D(stamp, frame, x, y, yaw, cov3)


def encode_pose_with_covariance(pose: PoseWithCovariance2D) -> bytes:
    """CDR bytes of a ``geometry_msgs/PoseWithCovarianceStamped`` (z 0, rotation about z)."""
    t = _ros_types()
    msg = t[POSE_WITH_COVARIANCE_STAMPED.ros](
        header=_header(pose.stamp, pose.frame_id),
        pose=t["geometry_msgs/msg/PoseWithCovariance"](
            pose=_pose_msg(pose.x, pose.y, pose.yaw), covariance=covariance_6x6(pose.covariance)
        ),
    )
    return _serialize(msg, POSE_WITH_COVARIANCE_STAMPED)


# --------------------------------------------------------------------------- OccupancyGrid
def decode_occupancy_grid(data: object) -> Grid:
    """Decode and check a ``nav_msgs/OccupancyGrid`` (see :class:`Grid`)."""
    m = _deserialize(data, OCCUPANCY_GRID, MAX_GRID_BYTES)
    w = "OccupancyGrid"
    stamp = _stamp(f"{w}.header.stamp", m.header.stamp)
    frame = frame_name(f"{w}.header.frame_id", m.header.frame_id)
    res = _finite(f"{w}.info.resolution", m.info.resolution)
    if res <= 0.0:
        raise _fail(f"{w}.info.resolution", f"must be > 0, got {res!r}")
    width, height = int(m.info.width), int(m.info.height)
    if width < 1 or height < 1:
        raise _fail(f"{w}.info", f"{width} x {height} cells is empty")
    if width * height > MAX_GRID_CELLS:
        raise _fail(f"{w}.info", f"{width} x {height} cells exceeds limit {MAX_GRID_CELLS}")
    cells = np.asarray(m.data, dtype=np.int8)
    if cells.size != width * height:
        raise _fail(f"{w}.data", f"{cells.size} cells, info says {width} x {height}")
    if cells.size and (cells.min() < -1 or cells.max() > 100):
        raise _fail(f"{w}.data", "values must lie in -1..100")
    x, y, yaw = _pose_2d(f"{w}.info.origin", m.info.origin)
    grid = cells.reshape(height, width).copy()
    grid.setflags(write=False)
    return Grid(stamp, frame, res, (x, y, yaw), grid)


def encode_occupancy_grid(grid: Grid) -> bytes:
    """CDR bytes of a ``nav_msgs/OccupancyGrid`` (``map_load_time`` = the stamp)."""
    t = _ros_types()
    time = t["builtin_interfaces/msg/Time"](sec=grid.stamp.sec, nanosec=grid.stamp.nanosec)
    x, y, yaw = grid.origin
    msg = t[OCCUPANCY_GRID.ros](
        header=_header(grid.stamp, grid.frame_id),
        info=t["nav_msgs/msg/MapMetaData"](
            map_load_time=time,
            resolution=float(grid.resolution),
            width=grid.width,
            height=grid.height,
            origin=_pose_msg(x, y, yaw),
        ),
        data=np.ascontiguousarray(grid.data, dtype=np.int8).reshape(-1),
    )
    return _serialize(msg, OCCUPANCY_GRID)
