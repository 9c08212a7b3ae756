"""``shapeloc-sim replay`` without a network: log scans -> wire messages, the initial pose,
the command line and the pacing (on a recording stand-in for the Zenoh session)."""

from __future__ import annotations

import io
import math
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from schemas.codec import decode, encode, scan_arrays
from schemas.messages import Scan, Truth
from service.adapters.logs import LogScan
from sim_publisher.__main__ import build_parser
from sim_publisher.replay import (
    Progress,
    ReplayOptions,
    _publish,
    initial_pose_for,
    open_replay,
    options_from_args,
    scan_message,
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


def test_command_line() -> None:
    p = build_parser()
    args = p.parse_args(["replay", str(BAG), "--robot", "fr", "--map", "m1", "--rate", "max"])
    o = options_from_args(args)
    assert (o.robot, o.map_id, o.rate, o.odom, o.lockstep, o.method) == (
        "fr",
        "m1",
        None,
        True,
        False,
        "shape",
    )
    args = p.parse_args(
        [
            "replay",
            str(BAG),
            "--robot",
            "fr",
            "--map",
            "m1",
            "--rate",
            "4",
            "--no-odom",
            "--lockstep",
            "--limit",
            "9",
            "--initial-pose",
            "1,2,0.5",
            "--method",
            "icp",
        ]
    )
    o = options_from_args(args)
    assert (o.rate, o.odom, o.lockstep, o.limit, o.initial_pose, o.method) == (
        4.0,
        False,
        True,
        9,
        [1.0, 2.0, 0.5],
        "icp",
    )
    for bad in (["--rate", "0"], ["--rate", "fast"], ["--initial-pose", "1,2"]):
        with pytest.raises(SystemExit):
            p.parse_args(["replay", str(BAG), "--robot", "fr", "--map", "m1", *bad])
    args = p.parse_args(["replay", str(BAG), "--robot", "no/slash", "--map", "m1"])
    with pytest.raises(ValueError, match="--robot"):
        options_from_args(args)


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


@pytest.mark.parametrize("rate", [None, 20.0])
def test_publish_paces_by_log_stamps(rate: float | None) -> None:
    scans = _scans(limit=12)
    opts = ReplayOptions(log=BAG, robot="fr", map_id="m", rate=rate, progress=False)
    session = _Session()
    out = io.StringIO()
    bar = Progress("x", 12, out, enabled=False)
    t0 = time.monotonic()
    sent, _ = _publish(session, opts, iter(scans), threading.Event(), None, bar, set())  # type: ignore[arg-type]
    el = time.monotonic() - t0
    assert sent == 12
    scan_puts = [(t, decode(Scan, p)) for t, k, p in session.log if k.endswith("/fr/scan")]
    truth_puts = [decode(Truth, p) for _, k, p in session.log if k.endswith("/fr/truth")]
    assert [m.seq for _, m in scan_puts] == list(range(12))
    assert all(m.odom == pytest.approx(s.odom) for (_, m), s in zip(scan_puts, scans, strict=True))
    assert [t.seq for t in truth_puts] == [s.index for s in scans if s.reference_ok]
    assert len(truth_puts) == 7  # flag-1 rows only (1-3, 7-9, 11)
    span = scans[-1].stamp - scans[0].stamp
    if rate is None:
        assert el < 0.25 * span  # not paced (12 scans span about 2.3 s of log time)
    else:
        # each scan goes out at (stamp - first stamp) / rate after the first
        lag = [t - scan_puts[0][0] - (m.stamp - scans[0].stamp) / rate for t, m in scan_puts]
        assert min(lag) >= -1e-3 and max(lag) < 0.2  # never early; late only by scheduling


def test_progress_line() -> None:
    out = io.StringIO()
    bar = Progress("fr079.300.bag", 300, out)
    bar.update(150, 149, final=True)
    text = out.getvalue()
    assert text.startswith("replay fr079.300.bag: 150/300 scans (50 %), ")
    assert "149 poses" in text and text.endswith("s\n")
    bar.update(151, 150)  # not due yet (not a terminal: every 5 s)
    assert out.getvalue() == text


def test_publish_without_odometry() -> None:
    scans = _scans(limit=3)
    opts = ReplayOptions(log=BAG, robot="fr", map_id="m", rate=None, odom=False, progress=False)
    session = _Session()
    bar = Progress("x", 3, io.StringIO(), enabled=False)
    _publish(session, opts, iter(scans), threading.Event(), None, bar, set())  # type: ignore[arg-type]
    sent = [decode(Scan, p) for _, k, p in session.log if k.endswith("/fr/scan")]
    assert len(sent) == 3 and all(m.odom is None for m in sent)


def test_replay_takes_the_shared_zenoh_options(tmp_path: Path) -> None:
    from sim_publisher.__main__ import zenoh_config_from_args

    cfg = tmp_path / "z.json5"
    cfg.write_text('{ mode: "client", connect: { endpoints: ["tcp/127.0.0.1:7999"] } }')
    p = build_parser()
    argv = ["replay", str(BAG), "--robot", "r1", "--map", "m", "--zenoh-config", str(cfg)]
    _conf, endpoints = zenoh_config_from_args(p.parse_args(argv))
    assert endpoints == ["tcp/127.0.0.1:7999"]  # from the file
    args = p.parse_args([*argv, "--connect", "tcp/127.0.0.1:7448"])
    assert zenoh_config_from_args(args)[1] == ["tcp/127.0.0.1:7448"]  # the flag replaces it
