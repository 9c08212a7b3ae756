"""CDR encode / decode of the ROS 2 messages (schemas/ros2/cdr.py).

The byte vectors are written here by hand, field by field, with the XCDR1 rules rmw_zenoh's
Fast-CDR uses (4-byte encapsulation header ``00 01 00 00`` for little-endian, every primitive
aligned to its size counted from the end of the header, strings as uint32 length including
the terminating NUL, sequences as uint32 count): an encoder independent of ``rosbags``. Every
decode is also fed hostile bytes.
"""

from __future__ import annotations

import math
import struct

import numpy as np
import pytest

from schemas.ros2 import cdr
from schemas.ros2.cdr import Grid, LaserScan, PoseWithCovariance2D, Stamp, Transform2D
from service.errors import InvalidMessage


class Writer:
    """A minimal little-endian XCDR1 writer (alignment relative to the body)."""

    def __init__(self) -> None:
        self.body = bytearray()

    def _put(self, fmt: str, *v: object) -> None:
        size = struct.calcsize("<" + fmt[0])
        while len(self.body) % size:
            self.body.append(0)
        self.body += struct.pack("<" + fmt, *v)

    def u32(self, v: int) -> None:
        self._put("I", v)

    def i32(self, v: int) -> None:
        self._put("i", v)

    def f32(self, v: float) -> None:
        self._put("f", v)

    def f64(self, v: float) -> None:
        self._put("d", v)

    def string(self, s: str) -> None:
        data = s.encode() + b"\0"
        self.u32(len(data))
        self.body += data

    def header(self, sec: int, nsec: int, frame: str) -> None:
        self.i32(sec)
        self.u32(nsec)
        self.string(frame)

    def bytes(self) -> bytes:
        return b"\x00\x01\x00\x00" + bytes(self.body)


def _pose_cov_bytes(yaw: float, cov: list[float]) -> bytes:
    w = Writer()
    w.header(1_700_000_000, 250_000_000, "map")
    for v in (1.5, -2.25, 0.0):
        w.f64(v)
    for v in (0.0, 0.0, math.sin(yaw / 2), math.cos(yaw / 2)):
        w.f64(v)
    for v in cov:
        w.f64(v)
    return w.bytes()


def test_pose_with_covariance_bytes_equal_the_hand_written_vector() -> None:
    cov3 = np.array([[0.04, 0.001, 0.0], [0.001, 0.09, 0.002], [0.0, 0.002, 0.01]])
    pose = PoseWithCovariance2D(Stamp(1_700_000_000, 250_000_000), "map", 1.5, -2.25, 0.75, cov3)
    cov36 = [0.0] * 36
    for i, a in enumerate((0, 1, 5)):
        for j, b in enumerate((0, 1, 5)):
            cov36[a * 6 + b] = float(cov3[i, j])
    expected = _pose_cov_bytes(0.75, cov36)
    assert cdr.encode_pose_with_covariance(pose) == expected
    back = cdr.decode_pose_with_covariance(expected)
    assert (back.x, back.y) == (1.5, -2.25) and back.yaw == pytest.approx(0.75, abs=1e-15)
    assert np.array_equal(back.covariance, cov3) and back.stamp == pose.stamp


def _scan_bytes(frame: str, inc: float, ranges: list[float]) -> bytes:
    w = Writer()
    w.header(12, 34, frame)
    n = len(ranges)
    for v in (-1.0, -1.0 + (n - 1) * inc, inc, 0.0, 0.1, 0.05, 30.0):
        w.f32(v)
    w.u32(n)
    for r in ranges:
        w.f32(r)
    w.u32(0)  # no intensities
    return w.bytes()


def test_laser_scan_bytes_equal_the_hand_written_vector() -> None:
    ranges = [1.0, float("nan"), float("inf"), 2.5]
    data = _scan_bytes("laser", 0.5, ranges)
    scan = cdr.decode_laser_scan(data)
    assert scan.stamp == Stamp(12, 34) and scan.frame_id == "laser"
    assert (scan.angle_min, scan.angle_increment, scan.range_max) == (-1.0, 0.5, 30.0)
    assert np.array_equal(scan.ranges, ranges, equal_nan=True)
    assert not scan.ranges.flags.writeable
    again = LaserScan(
        scan.stamp, "laser", -1.0, 0.5, scan.range_min, 30.0, scan.ranges, scan.scan_time, 0.0
    )
    assert cdr.encode_laser_scan(again) == data


def test_a_scan_with_negative_increment_is_reversed() -> None:
    data = _scan_bytes("/laser", -0.5, [1.0, 2.0, 3.0])
    scan = cdr.decode_laser_scan(data)
    assert scan.frame_id == "laser"  # leading slash dropped, as tf2 does
    assert scan.angle_increment == 0.5 and scan.angle_min == pytest.approx(-2.0)
    assert list(scan.ranges) == [3.0, 2.0, 1.0]


def test_tf_message_bytes_equal_the_hand_written_vector() -> None:
    tr = Transform2D(Stamp(5, 6), "odom", "base_link", 0.5, -0.25, math.pi / 2)
    w = Writer()
    w.u32(1)
    w.header(5, 6, "odom")
    w.string("base_link")
    for v in (0.5, -0.25, 0.0, 0.0, 0.0, math.sin(math.pi / 4), math.cos(math.pi / 4)):
        w.f64(v)
    assert cdr.encode_tf([tr]) == w.bytes()
    (back,) = cdr.decode_tf(w.bytes())
    assert (back.parent, back.child, back.x, back.y) == ("odom", "base_link", 0.5, -0.25)
    assert back.yaw == pytest.approx(math.pi / 2, abs=1e-15) and back.tilt == 0.0


def test_odometry_round_trip_and_tilted_transforms_report_their_tilt() -> None:
    od = cdr.Odometry2D(Stamp(1, 2), "odom", "base_footprint", 3.0, 4.0, -0.5)
    back = cdr.decode_odometry(cdr.encode_odometry(od))
    assert back.child_frame_id == "base_footprint" and back.yaw == pytest.approx(-0.5)
    # a laser pitched by 0.2 rad (rotation about y)
    w = Writer()
    w.u32(1)
    w.header(0, 0, "base_link")
    w.string("laser")
    for v in (0.1, 0.0, 0.3, 0.0, math.sin(0.1), 0.0, math.cos(0.1)):
        w.f64(v)
    (tr,) = cdr.decode_tf(w.bytes())
    assert tr.tilt == pytest.approx(0.2) and tr.z == 0.3


def test_occupancy_grid_round_trip_keeps_the_row_order() -> None:
    data = np.array([[0, 100, -1], [50, 0, 0]], dtype=np.int8)
    grid = Grid(Stamp(9, 0), "map", 0.05, (-1.0, 2.0, 0.1), data)
    raw = cdr.encode_occupancy_grid(grid)
    back = cdr.decode_occupancy_grid(raw)
    assert back.width == 3 and back.height == 2
    assert np.array_equal(back.data, data)  # row 0 is the message's first row
    assert back.origin[:2] == (-1.0, 2.0) and back.origin[2] == pytest.approx(0.1)
    assert back.resolution == pytest.approx(0.05)


def test_big_endian_cdr_is_read() -> None:
    w = bytearray(b"\x00\x00\x00\x00")
    w += struct.pack(">iI", 1, 2) + struct.pack(">I", 4) + b"map\0"
    for v in (1.0, 2.0, 0.0, 0.0, 0.0, 0.0, 1.0):
        w += struct.pack(">d", v)
    w += struct.pack(">36d", *([0.0] * 36))
    pose = cdr.decode_pose_with_covariance(bytes(w))
    assert (pose.x, pose.y, pose.yaw) == (1.0, 2.0, 0.0) and pose.frame_id == "map"


def _bad_scans() -> list[tuple[str, bytes]]:
    good = _scan_bytes("laser", 0.5, [1.0, 2.0])
    nan_inc = _scan_bytes("laser", float("nan"), [1.0, 2.0])
    zero_inc = _scan_bytes("laser", 0.0, [1.0, 2.0])
    wide = _scan_bytes("laser", 1.0, [1.0] * 10)
    empty = _scan_bytes("laser", 0.5, [])
    many = _scan_bytes("laser", 1e-4, [1.0] * 9000)
    no_frame = _scan_bytes("", 0.5, [1.0])
    huge_count = bytearray(good)
    # the ranges count sits after header (4+4+4+6+2 pad) and 7 floats: claim 2**31 beams
    struct.pack_into("<I", huge_count, 4 + 20 + 28, 2**31)
    return [
        ("empty payload", b""),
        ("header only", b"\x00\x01\x00\x00"),
        ("not CDR", b"\x7b\x22" + good[2:]),
        ("XCDR2 header", b"\x00\x07\x00\x00" + good[4:]),
        ("truncated", good[:-9]),
        ("truncated header", good[:10]),
        ("NaN increment", nan_inc),
        ("zero increment", zero_inc),
        ("more than a turn", wide),
        ("no beams", empty),
        ("too many beams", many),
        ("empty frame", no_frame),
        ("absurd count", bytes(huge_count)),
        ("too large", b"\x00\x01\x00\x00" + b"\x00" * (16 * 1024 * 1024)),
        ("not bytes", "hello"),  # type: ignore[list-item]
    ]


@pytest.mark.parametrize(("why", "data"), _bad_scans(), ids=[w for w, _ in _bad_scans()])
def test_hostile_scans_are_rejected_with_a_clear_error(why: str, data: bytes) -> None:
    with pytest.raises(InvalidMessage, match="LaserScan"):
        cdr.decode_laser_scan(data)


def test_a_scan_is_not_a_tf_message_nor_a_grid() -> None:
    data = _scan_bytes("laser", 0.5, [1.0, 2.0])
    with pytest.raises(InvalidMessage):
        cdr.decode_tf(data)
    with pytest.raises(InvalidMessage):
        cdr.decode_occupancy_grid(data)


def _tf_bytes(q: tuple[float, float, float, float], parent: str = "odom", n: int = 1) -> bytes:
    w = Writer()
    w.u32(n)
    for _ in range(n):
        w.header(0, 0, parent)
        w.string("base_link")
        for v in (0.0, 0.0, 0.0, *q):
            w.f64(v)
    return w.bytes()


@pytest.mark.parametrize(
    "data",
    [
        _tf_bytes((0.0, 0.0, 0.0, 0.0)),  # zero quaternion
        _tf_bytes((0.0, 0.0, float("nan"), 1.0)),
        _tf_bytes((0.0, 0.0, 0.0, 1.0), parent="base_link"),  # its own parent
        _tf_bytes((0.0, 0.0, 0.0, 1.0), n=1025),  # too many transforms
    ],
)
def test_hostile_tf_messages_are_rejected(data: bytes) -> None:
    with pytest.raises(InvalidMessage, match="TFMessage"):
        cdr.decode_tf(data)


def test_hostile_grids_and_poses_are_rejected() -> None:
    grid = Grid(Stamp(0, 0), "map", 0.05, (0.0, 0.0, 0.0), np.zeros((2, 2), dtype=np.int8))
    raw = bytearray(cdr.encode_occupancy_grid(grid))
    # claim 3 x 2 cells for 4 values: width is the uint32 after resolution (float32)
    pos = raw.index(struct.pack("<f", 0.05)) + 4
    struct.pack_into("<I", raw, pos, 3)
    with pytest.raises(InvalidMessage, match="OccupancyGrid"):
        cdr.decode_occupancy_grid(bytes(raw))
    bad_values = Grid(Stamp(0, 0), "map", 0.05, (0.0, 0.0, 0.0), np.full((1, 1), 101, np.int8))
    with pytest.raises(InvalidMessage, match=r"-1\.\.100"):
        cdr.decode_occupancy_grid(cdr.encode_occupancy_grid(bad_values))
    cov = [0.0] * 36
    cov[7] = float("inf")
    with pytest.raises(InvalidMessage, match="covariance"):
        cdr.decode_pose_with_covariance(_pose_cov_bytes(0.0, cov))


def test_stamps_convert_exactly_through_nanoseconds() -> None:
    s = Stamp(1_700_000_000, 123_456_789)
    assert Stamp.from_nanoseconds(s.nanoseconds) == s
    assert Stamp.from_seconds(1.5) == Stamp(1, 500_000_000)
    for bad in ((0, 1_000_000_000), (2**31, 0), (0, -1)):
        with pytest.raises(InvalidMessage):
            Stamp(*bad)
