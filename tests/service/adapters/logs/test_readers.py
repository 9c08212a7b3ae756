"""Log readers on the committed excerpts (tests/data/real, first 300 scans of each log) and on
small hand-written CARMEN files."""

from __future__ import annotations

import gzip
import math
from pathlib import Path

import numpy as np
import pytest

from service.adapters.logs import log_format, read_log
from service.adapters.logs.scan import yaw_of_quaternion
from service.core.pose import compose
from service.errors import LogFormatError

DATA = Path(__file__).resolve().parents[3] / "data" / "real"
INTEL = DATA / "intel.300.bag"
FR079 = DATA / "fr079.300.bag"
CSAIL = DATA / "mit-csail.300.clf.gz"


def _odom_messages(bag: Path) -> tuple[np.ndarray, np.ndarray]:
    """Stamps (s) and base poses of every /odom message, read with rosbags directly."""
    from rosbags.highlevel import AnyReader

    stamps, poses = [], []
    with AnyReader([bag]) as reader:
        conns = [c for c in reader.connections if c.topic == "/odom"]
        for conn, _t, raw in reader.messages(connections=conns):
            m = reader.deserialize(raw, conn.msgtype)
            q = m.pose.pose.orientation
            stamps.append(m.header.stamp.sec + m.header.stamp.nanosec * 1e-9)
            poses.append(
                (
                    m.pose.pose.position.x,
                    m.pose.pose.position.y,
                    yaw_of_quaternion(q.x, q.y, q.z, q.w),
                )
            )
    return np.array(stamps), np.array(poses)


@pytest.mark.parametrize(
    ("path", "fmt", "beams", "increment", "first_stamp", "last_stamp"),
    [
        (INTEL, "ros1", 180, math.pi / 179, 976052857.33753, 976052915.764712),
        (FR079, "ros1", 360, math.pi / 359, 1211.520329, 1275.960036),
        (CSAIL, "carmen", 361, math.pi / 360, 1134864629.895182, 1134864693.695181),
    ],
)
def test_excerpt_counts_beams_angles_stamps(
    path: Path, fmt: str, beams: int, increment: float, first_stamp: float, last_stamp: float
) -> None:
    info, it = read_log(path)
    scans = list(it)
    assert log_format(path) == fmt and info.format == fmt
    assert info.scan_count == 300 and len(scans) == 300
    assert info.beams == beams and {s.beams for s in scans} == {beams}
    assert info.angle_min == pytest.approx(-math.pi / 2, abs=1e-7)
    assert info.angle_increment == pytest.approx(increment, rel=1e-6)
    assert info.fov == pytest.approx(math.pi, abs=1e-5)
    assert scans[0].angles[-1] == pytest.approx(math.pi / 2, abs=1e-5)
    assert [s.index for s in scans] == list(range(300))
    assert scans[0].stamp == pytest.approx(first_stamp, abs=1e-6)
    assert scans[-1].stamp == pytest.approx(last_stamp, abs=1e-6)
    assert np.all(np.diff([s.stamp for s in scans]) > 0)
    assert all(s.odom is not None and s.reference is None for s in scans)
    assert info.has_odom and not info.corrected


def test_known_ranges_and_no_returns() -> None:
    intel = next(read_log(INTEL)[1])
    assert intel.ranges[0] == pytest.approx(1.07, abs=1e-6)
    assert intel.ranges[90] == pytest.approx(17.12, abs=1e-5)
    assert not intel.ranges.flags.writeable
    fr = next(read_log(FR079)[1])
    assert fr.ranges[90] == pytest.approx(2.59, abs=1e-6)
    csail = next(read_log(CSAIL)[1])
    # the first FLASER line reads 1.40 (first beam), 4.36 (middle), 2.70 (last); 75 of its
    # beams are no-returns
    assert csail.ranges[[0, 180, 360]] == pytest.approx([1.40, 4.36, 2.70])
    assert int(np.isnan(csail.ranges).sum()) == 75
    assert csail.points().shape == (361 - 75, 2)
    # max_range caps the readings
    capped = next(read_log(CSAIL, max_range=2.0)[1])
    assert capped.range_max == 2.0 and np.nanmax(capped.ranges) <= 2.0


def test_limit_stops_early() -> None:
    for path in (FR079, CSAIL):
        info, it = read_log(path, limit=7)
        assert info.scan_count == 300
        assert len(list(it)) == 7
        assert list(read_log(path, limit=0)[1]) == []


def test_fr079_odometry_is_the_laser_frame_at_the_scan_stamp() -> None:
    info, it = read_log(FR079)
    assert info.laser_offset_source == "tf_static"
    assert info.laser_offset == pytest.approx([0.04, 0.0, 0.0])
    assert info.odom_frames == ("odom", "base_link") and info.laser_frame == "laser"
    scans = list(it)
    base_scans = list(read_log(FR079, laser_offset=(0.0, 0.0, 0.0))[1])
    t, p = _odom_messages(FR079)
    checked = 0
    for s, b in zip(scans, base_scans, strict=True):
        assert s.odom == pytest.approx(compose(b.odom, [0.04, 0.0, 0.0]), abs=1e-12)
        k = int(np.searchsorted(t, s.stamp))
        if 0 < k < len(t) and abs(p[k, 2] - p[k - 1, 2]) < 1.0:
            w = (s.stamp - t[k - 1]) / (t[k] - t[k - 1])
            expect = p[k - 1] + w * (p[k] - p[k - 1])
            assert b.odom == pytest.approx(expect, abs=1e-9)
            checked += 1
    assert checked > 250
    # the laser point moves 0.04 m ahead of the base: differs wherever the heading is known
    d = scans[100].odom[:2] - base_scans[100].odom[:2]
    assert np.hypot(*d) == pytest.approx(0.04, abs=1e-12)


def test_carmen_odometry_is_the_flaser_odometry() -> None:
    with gzip.open(CSAIL, "rt") as fh:
        first_line = fh.read().splitlines()[3].split()
    scan = next(read_log(CSAIL)[1])
    assert first_line[:2] == ["FLASER", "361"]
    # tokens: FLASER n r1..r361 x y theta odom_x odom_y odom_theta timestamp host logger_time
    assert scan.odom == pytest.approx([float(v) for v in first_line[366:369]])
    assert scan.stamp == float(first_line[369])


def _flaser(ranges: list[float], pose: tuple[float, ...], odom: tuple[float, ...], t: float) -> str:
    vals = " ".join(f"{r:.2f}" for r in ranges)
    p = " ".join(f"{v:.6f}" for v in (*pose, *odom))
    return f"FLASER {len(ranges)} {vals} {p} {t:.6f} host {t:.6f}\n"


def test_carmen_param_offset_and_corrected_logs(tmp_path: Path) -> None:
    raw = tmp_path / "raw.log"
    raw.write_text(
        "# comment\nPARAM robot_frontlaser_offset 0.25 host 0\n"
        + _flaser([1.0, 2.0, 81.83], (9, 9, 9), (1.0, 2.0, math.pi / 2), 10.0)
        + "ODOM 1 2 0 0 0 0 10.1 host 10.1\n"
        + _flaser([3.0, 0.0, 80.0], (9, 9, 9), (1.5, 2.0, 0.0), 10.5)
    )
    info, it = read_log(raw)
    a, b = list(it)
    assert info.laser_offset_source == "PARAM robot_frontlaser_offset"
    assert a.odom == pytest.approx([1.0, 2.25, math.pi / 2], abs=1e-6)
    assert b.odom == pytest.approx([1.75, 2.0, 0.0], abs=1e-9)
    assert a.angle_increment == pytest.approx(math.pi / 2)
    # 81.83 (SICK no-return) and 0.0 are NaN; 80.0 is a valid reading
    assert np.isnan(a.ranges[2]) and np.isnan(b.ranges[1]) and b.ranges[2] == 80.0
    corrected = tmp_path / "run-corrected.log.gz"
    with gzip.open(corrected, "wt") as fh:
        fh.write(_flaser([1.0, 2.0, 3.0], (0.5, -0.5, 0.1), (7, 7, 7), 1.0) + "NEFF 30\n")
    info, it = read_log(corrected)
    (c,) = list(it)
    assert info.corrected and not info.has_odom
    assert c.odom is None and c.reference_ok
    assert c.reference == pytest.approx([0.5, -0.5, 0.1])


def test_carmen_robotlaser1(tmp_path: Path) -> None:
    # laser 0.3 m ahead of the robot pose: the offset comes from the line itself
    line = (
        "ROBOTLASER1 0 -1.5707963 3.1415927 1.5707963 30.0 0.01 0 3 1.0 30.0 2.0 0 "
        "1.3 2.0 0.0 1.0 2.0 0.0 0 0 0 0 0 5.0 host 5.0\n"
    )
    path = tmp_path / "rl.clf"
    path.write_text(line)
    info, it = read_log(path)
    (s,) = list(it)
    assert info.laser_offset_source == "ROBOTLASER1"
    assert info.laser_offset == pytest.approx([0.3, 0.0, 0.0])
    assert s.odom == pytest.approx([1.3, 2.0, 0.0])
    assert s.ranges[0] == 1.0 and np.isnan(s.ranges[1]) and s.ranges[2] == 2.0


@pytest.mark.parametrize(
    ("line", "problem"),
    [
        ("FLASER 3 1.0 2.0 0 0 0 0 0 0 1.0 host 1.0\n", "needs 14 fields"),
        ("FLASER 3 1.0 x 3.0 0 0 0 0 0 0 1.0 host 1.0\n", "not a number"),
        ("FLASER 3 1.0 2.0 3.0 0 0 nan 0 0 0 1.0 host 1.0\n", "not finite"),
        ("FLASER -2 host\n", "must be positive"),
        ("ODOM 1 2 3\n", "ODOM needs"),
    ],
)
def test_malformed_carmen_names_file_and_line(tmp_path: Path, line: str, problem: str) -> None:
    path = tmp_path / "bad.clf"
    good = _flaser([1.0, 2.0, 3.0], (0, 0, 0), (0, 0, 0), 0.5)
    path.write_text("# header\n" + good + line + good)
    with pytest.raises(LogFormatError, match=rf"bad\.clf:3: .*{problem}"):
        list(read_log(path)[1])
    info, it = read_log(path, skip_bad_lines=True)
    assert len(list(it)) == 2
    assert len(info.bad_lines) == 1 and f"{path}:3:" in info.bad_lines[0]


def test_unreadable_inputs_raise_log_format_error(tmp_path: Path) -> None:
    with pytest.raises(LogFormatError, match="no such file"):
        read_log(tmp_path / "missing.bag")
    odd = tmp_path / "scan.xyz"
    odd.write_text("1 2 3\n")
    with pytest.raises(LogFormatError, match=r"scan\.xyz: unknown log format"):
        read_log(odd)
    fake = tmp_path / "broken.bag"
    fake.write_bytes(b"#ROSBAG V2.0\nnot really a bag")
    with pytest.raises(LogFormatError, match=r"broken\.bag: cannot open as a ROS bag"):
        read_log(fake)
    with pytest.raises(LogFormatError, match="not a sensor_msgs/LaserScan"):
        read_log(FR079, scan_topic="/odom")


@pytest.mark.parametrize("storage", ["sqlite3", "mcap"])
def test_ros2_bag_reads_like_the_ros1_bag_it_was_converted_from(
    tmp_path: Path, storage: str
) -> None:
    from rosbags.convert import convert

    dst = tmp_path / f"fr079-{storage}"
    convert(
        srcs=[FR079],
        dst=dst,
        dst_storage=storage,
        dst_version=8,
        compress=None,
        compress_mode="file",
        default_typestore=None,
        typestore=None,
        exclude_topics=[],
        include_topics=[],
        exclude_msgtypes=[],
        include_msgtypes=[],
    )
    ros1 = list(read_log(FR079)[1])
    storage_file = next(p for p in dst.iterdir() if p.suffix in (".db3", ".mcap"))
    for target in (dst, storage_file):  # the bag directory or its storage file
        info, it = read_log(target)
        assert info.format == "ros2" and info.scan_count == 300
        assert info.laser_offset == pytest.approx([0.04, 0.0, 0.0])
        scans = list(it)
        assert [s.stamp for s in scans] == [s.stamp for s in ros1]
        assert all(
            np.array_equal(a.ranges, b.ranges, equal_nan=True) and np.array_equal(a.odom, b.odom)
            for a, b in zip(scans, ros1, strict=True)
        )


def test_odometry_from_tf_equals_odometry_from_odom_topic() -> None:
    by_odom = list(read_log(FR079)[1])
    info, it = read_log(FR079, odom_topic="/tf")
    assert info.odom_topic == "/tf" and info.odom_frames == ("odom", "base_link")
    by_tf = list(it)
    assert all(np.array_equal(a.odom, b.odom) for a, b in zip(by_odom, by_tf, strict=True))
