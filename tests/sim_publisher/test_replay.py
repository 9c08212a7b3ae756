"""``shapeloc-sim replay`` without a network: log scans -> wire messages, the initial pose,
the command line and the pacing (on a recording stand-in for the Zenoh session)."""

from __future__ import annotations

import math
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from schemas.cli import resolve_client_globals
from schemas.codec import decode, encode, scan_arrays
from schemas.messages import PoseMsg, Scan, Truth
from service.adapters.logs import LogScan
from service.core.pose import relative
from sim_publisher.__main__ import build_parser
from sim_publisher.networked import GLOBAL_OPTIONS, zenoh_config_from_args
from sim_publisher.replay import (
    Collected,
    ReplayOptions,
    accuracy,
    initial_pose_for,
    open_replay,
    options_from_args,
    publish_log,
    scan_message,
    summary_text,
    truth_message,
)

DATA = Path(__file__).resolve().parents[1] / "data" / "real"
BAG = DATA / "fr079.300.bag"
REFERENCE = DATA / "fr079.300.gfs_reference_per_scan.txt"
CSAIL = DATA / "mit-csail.300.clf.gz"


def _scans(path: Path = BAG, reference: Path | None = REFERENCE, limit: int = 20) -> list:
    opts = ReplayOptions(log=path, robot="r", map_id="m", reference=reference, limit=limit)
    return list(open_replay(opts)[1])


def test_scan_message_carries_the_log_scan_as_sent_on_the_wire() -> None:
    scans = _scans()
    s = scans[7]
    msg = scan_message(s)
    assert msg.seq == 7 and msg.stamp == s.stamp
    assert msg.angle_min == s.angle_min and msg.angle_increment == s.angle_increment
    assert msg.range_min == s.range_min and msg.range_max == s.range_max
    assert np.array_equal(msg.ranges, s.ranges, equal_nan=True)
    assert msg.odom == pytest.approx(s.odom)
    assert scan_message(s, odom=False).odom is None
    # as the simulator sends it: msgpack with float32 range bytes; decodes to the same scan
    back = decode(Scan, encode(msg, ranges_as_bytes=True))
    ranges, angles = scan_arrays(back)
    assert back.seq == 7 and back.stamp == s.stamp
    assert angles == pytest.approx(s.angles, abs=1e-9)
    assert np.allclose(ranges, s.ranges, atol=1e-6, equal_nan=True)
    assert back.odom == pytest.approx(s.odom)


def test_scan_message_with_no_returns_and_no_odometry() -> None:
    ranges = np.array([1.0, np.nan, 2.5])
    ranges.flags.writeable = False
    s = LogScan(0, 5.0, -0.1, 0.1, 0.0, 80.0, ranges)
    msg = scan_message(s)
    assert msg.odom is None and math.isnan(msg.ranges[1])
    back = decode(Scan, encode(msg, ranges_as_bytes=True))
    assert np.isnan(scan_arrays(back)[0][1])


def test_truth_only_for_trustworthy_references() -> None:
    scans = _scans()
    flags = [s.reference_ok for s in scans]
    # fr079's rows 0, 4, 5, 6 are flag 0 (carried by odometry), 1-3 and 7-9 flag 1
    assert flags[:10] == [False, True, True, True, False, False, False, True, True, True]
    assert truth_message(scans[0]) is None
    t = truth_message(scans[3])
    assert isinstance(t, Truth) and t.seq == 3 and t.stamp == scans[3].stamp
    assert t.pose == pytest.approx(scans[3].reference)
    assert truth_message(_scans(reference=None)[3]) is None
    # a CARMEN log without reference: odometry only
    csail = _scans(CSAIL, reference=None, limit=2)
    assert csail[0].odom is not None and truth_message(csail[0]) is None


def test_initial_pose_explicit_global_or_first_reference() -> None:
    scans = _scans(limit=2)
    opts = ReplayOptions(log=BAG, robot="r", map_id="m")
    assert initial_pose_for(opts, scans[0]) == pytest.approx(scans[0].reference)
    opts.initial_pose = [1.0, 2.0, 0.5]
    assert initial_pose_for(opts, scans[0]) == [1.0, 2.0, 0.5]
    opts.initial_pose, opts.global_localization = None, True
    assert initial_pose_for(opts, scans[0]) is None
    opts.global_localization = False
    with pytest.raises(ValueError, match="no initial pose"):
        initial_pose_for(opts, _scans(reference=None, limit=1)[0])


def _parse(*extra: str):
    p = build_parser()
    args = p.parse_args(["replay", str(BAG), "--robot", "fr", "--map", "m1", *extra])
    resolve_client_globals(args, GLOBAL_OPTIONS, environ={})
    return options_from_args(args)


def test_command_line(capsys) -> None:
    o = _parse("--speed", "max")
    assert (o.robot, o.map_id, o.speed, o.odom, o.lockstep, o.method) == (
        "fr",
        "m1",
        None,
        True,
        False,
        "shape",
    )
    assert (o.prefix, o.timeout, o.json, o.relations, o.laser_offset) == (
        "shapeloc",
        2.0,
        False,
        None,
        None,
    )
    o = _parse(
        "--speed",
        "4",
        "--no-odom",
        "--lockstep",
        "--limit",
        "9",
        "--initial-pose",
        "1",
        "2",
        "0.5",
        "--method",
        "icp",
        "--relations",
        "r.txt",
        "--json",
        "--laser-offset",
        "0.3",
        "0.1",
        "0.2",
    )
    assert (o.speed, o.odom, o.lockstep, o.limit, o.initial_pose, o.method) == (
        4.0,
        False,
        True,
        9,
        [1.0, 2.0, 0.5],
        "icp",
    )
    assert o.relations == Path("r.txt") and o.json and o.laser_offset == [0.3, 0.1, 0.2]
    assert capsys.readouterr().err == ""  # nothing deprecated was used
    p = build_parser()
    for bad in (["--speed", "0"], ["--speed", "fast"], ["--initial-pose", "1", "2"]):
        with pytest.raises(SystemExit):
            p.parse_args(["replay", str(BAG), "--robot", "fr", "--map", "m1", *bad])
    with pytest.raises(ValueError, match="--robot"):
        _parse().robot  # noqa: B018 - the valid baseline parses
        options_from_args(p.parse_args(["replay", str(BAG), "--robot", "no/slash", "--map", "m1"]))


def test_old_spellings_still_work_with_a_warning(capsys) -> None:
    """``--rate N`` was the speed factor and ``--initial-pose`` took X,Y,THETA: both still
    work for one release, each with one warning line on stderr."""
    o = _parse("--rate", "4")
    assert o.speed == 4.0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "warning: --rate as the replay's speed factor is deprecated" in err[0]
    assert "use --speed" in err[0]
    assert _parse("--rate", "max").speed is None
    capsys.readouterr()
    o = _parse("--initial-pose", "1,2,0.5")
    assert o.initial_pose == [1.0, 2.0, 0.5]
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--initial-pose X,Y,THETA (comma form) is deprecated" in err[0]


def test_laser_offset_turns_the_log_into_a_base_with_a_laser() -> None:
    """With --laser-offset the odometry and reference go out as the base's: composing them
    with the offset gives the log's (laser) poses back."""
    from service.core.pose import compose

    off = [0.3, 0.1, 0.2]
    s = _scans(limit=4)[3]
    msg = scan_message(s, laser_offset=off)
    assert np.allclose(
        relative(compose(np.asarray(msg.odom), np.asarray(off)), s.odom), 0, atol=1e-9
    )
    t = truth_message(s, laser_offset=off)
    assert t is not None
    assert np.allclose(
        relative(compose(np.asarray(t.pose), np.asarray(off)), s.reference), 0, atol=1e-9
    )
    opts = ReplayOptions(log=BAG, robot="r", map_id="m", laser_offset=off)
    first = _scans(limit=1)[0]
    start = initial_pose_for(opts, first)
    assert np.allclose(
        relative(compose(np.asarray(start), np.asarray(off)), first.reference), 0, atol=1e-9
    )


def _pose_msg(seq: int, pose, status: str = "tracking", stamp: float = 0.0) -> PoseMsg:
    return PoseMsg(
        robot_id="r",
        seq=seq,
        stamp=stamp,
        pose=pose,
        status=status,
        score=0.5,
        method="shape",
        map_id="m",
        latency_ms=1.0,
    )


def test_accuracy_summary_counts_within_each_distance() -> None:
    truth = {k: np.array([float(k), 0.0, 0.0]) for k in range(10)}
    offsets = [0.0, 0.05, 0.09, 0.2, 0.29, 0.31, 0.45, 0.6, 1.0]  # seq 9 gets no pose
    poses = {k: _pose_msg(k, [k + d, 0.0, 0.0]) for k, d in enumerate(offsets)}
    poses[8] = _pose_msg(8, [9.0, 0.0, 0.0], status="lost")
    a = accuracy(truth, poses)
    ref = a["reference"]
    assert ref["scans"] == 10 and ref["answered"] == 9
    assert ref["within_0.1_m"] == pytest.approx(3 / 9)
    assert ref["within_0.3_m"] == pytest.approx(5 / 9)
    assert ref["within_0.5_m"] == pytest.approx(7 / 9)
    assert ref["error_max_m"] == pytest.approx(1.0)
    assert a["status"] == {"tracking": 8, "lost": 1} and a["poses"] == 9 and a["relations"] is None
    text = summary_text({"log": "x.bag", "robot": "r", "scans": 10, "seconds": 1.0, **a})
    assert "within 0.1 m 33.3 %, 0.3 m 55.6 %, 0.5 m 77.8 %" in text
    assert "(9 answered)" in text and "lost 1, tracking 8" in text
    none = accuracy({}, poses)
    assert none["reference"] is None
    assert "no reference poses" in summary_text(
        {"log": "x", "robot": "r", "scans": 1, "seconds": 1.0, **none}
    )


def test_accuracy_with_relations_reuses_the_relations_metric() -> None:
    """Perfect poses (the reference itself) score a relations error of the reference's own."""
    from service.adapters.logs import load_relations, relations_error

    scans = _scans(limit=300)
    rel = load_relations(DATA / "fr079.300.relations")
    poses = {
        s.index: _pose_msg(s.index, [float(v) for v in s.reference], stamp=s.stamp)
        for s in scans
        if s.reference is not None
    }
    a = accuracy({}, poses, rel)
    want = relations_error([s.stamp for s in scans], [s.reference for s in scans], rel)
    assert a["relations"]["used"] == want.used == 64
    assert a["relations"]["translation_mean_m"] == pytest.approx(want.translation_mean)
    assert "relations error" in summary_text(
        {"log": "x", "robot": "r", "scans": 300, "seconds": 1.0, **a}
    )


class _Pub:
    def __init__(self, key: str, log: list) -> None:
        self.key, self.log = key, log

    def put(self, payload: bytes) -> None:
        self.log.append((time.monotonic(), self.key, payload))

    def undeclare(self) -> None:
        pass


class _Session:
    """Records what would be put, with the time it was put."""

    def __init__(self) -> None:
        self.log: list = []

    def declare_publisher(self, key: str, **_kw: object) -> _Pub:
        return _Pub(key, self.log)


class _Bar:
    def __init__(self) -> None:
        self.n = 0

    def update(self, k: int) -> None:
        self.n += k

    def set_postfix(self, **_kw: object) -> None:
        pass


def _seen() -> Collected:
    return Collected(truth={}, poses={}, notices=[])


@pytest.mark.parametrize("speed", [None, 20.0])
def test_publish_paces_by_log_stamps(speed: float | None) -> None:
    scans = _scans(limit=12)
    opts = ReplayOptions(log=BAG, robot="fr", map_id="m", speed=speed, progress=False)
    session = _Session()
    bar = _Bar()
    seen = _seen()
    t0 = time.monotonic()
    sent = publish_log(session, opts, iter(scans), threading.Event(), None, bar, seen)  # type: ignore[arg-type]
    assert bar.n == 12 and sorted(seen.truth) == [s.index for s in scans if s.reference_ok]
    el = time.monotonic() - t0
    assert sent == 12
    scan_puts = [(t, decode(Scan, p)) for t, k, p in session.log if k.endswith("/fr/scan")]
    truth_puts = [decode(Truth, p) for _, k, p in session.log if k.endswith("/fr/truth")]
    assert [m.seq for _, m in scan_puts] == list(range(12))
    assert all(m.odom == pytest.approx(s.odom) for (_, m), s in zip(scan_puts, scans, strict=True))
    assert [t.seq for t in truth_puts] == [s.index for s in scans if s.reference_ok]
    assert len(truth_puts) == 7  # flag-1 rows only (1-3, 7-9, 11)
    span = scans[-1].stamp - scans[0].stamp
    if speed is None:
        assert el < 0.25 * span  # not paced (12 scans span about 2.3 s of log time)
    else:
        # each scan goes out at (stamp - first stamp) / speed after the first
        lag = [t - scan_puts[0][0] - (m.stamp - scans[0].stamp) / speed for t, m in scan_puts]
        assert min(lag) >= -1e-3 and max(lag) < 0.2  # never early; late only by scheduling


def test_publish_without_odometry() -> None:
    scans = _scans(limit=3)
    opts = ReplayOptions(log=BAG, robot="fr", map_id="m", speed=None, odom=False, progress=False)
    session = _Session()
    publish_log(session, opts, iter(scans), threading.Event(), None, _Bar(), _seen())  # type: ignore[arg-type]
    sent = [decode(Scan, p) for _, k, p in session.log if k.endswith("/fr/scan")]
    assert len(sent) == 3 and all(m.odom is None for m in sent)


def test_replay_takes_the_shared_zenoh_options(tmp_path: Path) -> None:
    cfg = tmp_path / "z.json5"
    cfg.write_text('{ mode: "client", connect: { endpoints: ["tcp/127.0.0.1:7999"] } }')
    p = build_parser()
    argv = ["replay", str(BAG), "--robot", "r1", "--map", "m", "--zenoh-config", str(cfg)]
    _conf, endpoints = zenoh_config_from_args(p.parse_args(argv))
    assert endpoints == ["tcp/127.0.0.1:7999"]  # from the file
    args = p.parse_args([*argv, "--connect", "tcp/127.0.0.1:7448"])
    assert zenoh_config_from_args(args)[1] == ["tcp/127.0.0.1:7448"]  # the flag replaces it
    # before the command too
    args = p.parse_args(["--connect", "tcp/127.0.0.1:7449", *argv])
    assert zenoh_config_from_args(args)[1] == ["tcp/127.0.0.1:7449"]
