"""``shapeloc-sim replay LOG``: publish a recorded laser log over Zenoh as a robot would.

Reads the log with :func:`service.adapters.logs.read_log` (ROS 1 / ROS 2 bag, CARMEN log, also a
GMapping-corrected one) and puts, for scan ``k`` of the log (``seq = k``, ``stamp`` = the log's
own stamp, seconds):

- a :class:`~schemas.messages.Scan` on ``<prefix>/robots/<id>/scan`` with the log's beam
  geometry and ranges (metres; no-returns NaN, sent as float32 bytes like the simulator's) and,
  unless ``--no-odom``, ``odom`` = the log's odometry of the LASER frame at the scan's stamp
  (the wire puts the laser at the robot origin, so the robot frame here is the laser's);
- a :class:`~schemas.messages.Truth` on ``<prefix>/robots/<id>/truth`` with the scan's
  reference pose (laser, map frame) when it has a trustworthy one: flag 1 of ``--reference
  FILE`` (a ``*.gfs_reference_per_scan.txt``, matched by stamp), or a corrected log's own pose.
  Flag-0 rows (carried by odometry) are not published.

Pacing: ``--rate 1`` replays in real time (the gaps between log stamps), ``--rate N`` N times
faster, ``--rate max`` as fast as possible. ``--lockstep`` also waits for the robot's pose for
each scan before the next (the same client code as ``shapeloc-sim run --lockstep``).

The map is not put (``shapeloc map put FILE`` does that; ``--map`` names the stored map's id).
Unless ``--no-configure``, the robot's configuration is put as ``shapeloc-sim run`` does: map,
method and initial pose: ``--initial-pose X,Y,THETA``; else ``--global`` (none: global
localisation); else the first replayed scan's reference pose (with ``--reference`` or a corrected
log). A progress line goes to standard error.
"""

from __future__ import annotations

import argparse
import logging
import math
import sys
import threading
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TextIO

import numpy as np
import zenoh

from clients.client import DEFAULT_PREFIX, ShapelocClient, Stream, open_session
from schemas import keys
from schemas.codec import MSGPACK_ENCODING, encode
from schemas.messages import METHODS, PoseMsg, Scan, Truth
from service.adapters.logs import LogInfo, LogScan, attach_reference, load_reference, read_log
from service.errors import ServiceTimeout

log = logging.getLogger("shapeloc.sim.replay")

#: Seconds between progress lines when standard error is not a terminal.
PROGRESS_EVERY_S = 5.0
#: Seconds between progress updates on a terminal (one line rewritten with ``\\r``).
PROGRESS_TTY_S = 0.25


@dataclass
class ReplayOptions:
    """Options of one replay (see ``shapeloc-sim replay --help``; seconds, metres, radians).

    ``rate``: real-time factor (``None``: as fast as possible). ``initial_pose``: explicit
    ``[x, y, theta]`` (map frame), else ``None`` and ``global_localization`` decides.
    """

    log: Path
    robot: str
    map_id: str
    method: str = "shape"
    rate: float | None = 1.0
    lockstep: bool = False
    lockstep_timeout: float = 30.0
    odom: bool = True
    reference: Path | None = None
    limit: int | None = None
    initial_pose: list[float] | None = None
    global_localization: bool = False
    configure: bool = True
    wait_service: float = 30.0
    prefix: str = DEFAULT_PREFIX
    scan_topic: str | None = None
    odom_topic: str | None = None
    max_range: float | None = None
    progress: bool = True


def scan_message(scan: LogScan, odom: bool = True) -> Scan:
    """The wire scan of a log scan: ``seq`` = its index in the log, the log's stamp, beam
    geometry and ranges (NaN = no return), ``odom`` (laser frame) when asked for and known."""
    return Scan(
        seq=scan.index,
        stamp=scan.stamp,
        angle_min=scan.angle_min,
        angle_increment=scan.angle_increment,
        range_min=scan.range_min,
        range_max=scan.range_max,
        ranges=scan.ranges,
        odom=[float(v) for v in scan.odom] if odom and scan.odom is not None else None,
    )


def truth_message(scan: LogScan) -> Truth | None:
    """The wire truth of a log scan: its trustworthy reference pose (laser, map frame), or
    ``None`` when it has none (no reference, or a flag-0 one)."""
    if scan.reference is None or not scan.reference_ok:
        return None
    return Truth(seq=scan.index, stamp=scan.stamp, pose=[float(v) for v in scan.reference])


def open_replay(options: ReplayOptions) -> tuple[LogInfo, Iterator[LogScan]]:
    """Open the log (and its reference file) as :func:`main` replays it."""
    info, scans = read_log(
        options.log,
        scan_topic=options.scan_topic,
        odom_topic=options.odom_topic,
        max_range=options.max_range,
        limit=options.limit,
    )
    if options.reference is not None:
        track = load_reference(options.reference)
        scans = attach_reference(scans, track, scan_count=info.scan_count)
    return info, scans


def _peek(scans: Iterator[LogScan]) -> tuple[LogScan | None, Iterator[LogScan]]:
    first = next(scans, None)
    if first is None:
        return None, iter(())

    def chained() -> Iterator[LogScan]:
        yield first
        yield from scans

    return first, chained()


def initial_pose_for(options: ReplayOptions, first: LogScan | None) -> list[float] | None:
    """The configuration's initial pose: explicit, else ``None`` for ``global_localization``,
    else the first scan's reference pose (any flag); raises ``ValueError`` if none applies."""
    if options.initial_pose is not None:
        return list(options.initial_pose)
    if options.global_localization:
        return None
    if first is not None and first.reference is not None:
        return [float(v) for v in first.reference]
    raise ValueError(
        "no initial pose: give --initial-pose X,Y,THETA, --global, or --reference FILE (or a "
        "corrected log) whose first pose starts the robot"
    )


class Progress:
    """One progress line on ``out``: scans sent of the total, rate, poses received."""

    def __init__(self, name: str, total: int | None, out: TextIO, enabled: bool = True) -> None:
        self.name, self.total, self.out, self.enabled = name, total, out, enabled
        self.tty = enabled and out.isatty()
        self.t0 = time.monotonic()
        self.last = -math.inf

    def line(self, sent: int, answered: int | None) -> str:
        """The text of the progress line."""
        el = max(time.monotonic() - self.t0, 1e-9)
        of = f"/{self.total}" if self.total is not None else ""
        pct = f" ({100.0 * sent / self.total:.0f} %)" if self.total else ""
        ans = f", {answered} poses" if answered is not None else ""
        return (
            f"replay {self.name}: {sent}{of} scans{pct}, {sent / el:.1f} scans/s{ans}, {el:.1f} s"
        )

    def update(self, sent: int, answered: int | None, final: bool = False) -> None:
        """Print the line when due (always when ``final``)."""
        if not self.enabled:
            return
        now = time.monotonic()
        if not final and now - self.last < (PROGRESS_TTY_S if self.tty else PROGRESS_EVERY_S):
            return
        self.last = now
        text = self.line(sent, answered)
        if self.tty:
            self.out.write("\r" + text + ("\n" if final else ""))
        else:
            self.out.write(text + "\n")
        self.out.flush()


def main(
    conf: zenoh.Config,
    options: ReplayOptions,
    stop: threading.Event | None = None,
    endpoints: Sequence[str] = (),
    progress_out: TextIO | None = None,
) -> int:
    """Replay ``options.log`` on a Zenoh session opened from ``conf``; returns the exit code.

    ``stop`` (set from a signal handler or another thread) ends the replay after the current
    scan. Raises :class:`LogFormatError` for a bad log, ``ValueError`` for bad options.
    """
    from sim_publisher.__main__ import _wait_service  # shared with `run`

    stop = stop or threading.Event()
    info, scans = open_replay(options)
    first, scans = _peek(scans)
    pose0 = initial_pose_for(options, first) if options.configure else None
    total = info.scan_count
    if total is not None and options.limit is not None:
        total = min(total, options.limit)
    with open_session(conf, endpoints) as session:
        client = ShapelocClient(session=session, prefix=options.prefix, timeout=2.0)
        try:
            up = options.wait_service > 0 and _wait_service(client, options.wait_service, stop)
            if options.configure and not stop.is_set():
                client.configure(options.robot, options.map_id, options.method, pose0)
                log.info(
                    "robot %s: map %s, method %s, initial pose %s",
                    options.robot,
                    options.map_id,
                    options.method,
                    "global" if pose0 is None else np.round(pose0, 4).tolist(),
                )
                if up:
                    try:
                        client.wait_configured(options.robot, options.wait_service)
                    except ServiceTimeout as exc:
                        log.warning("%s; replaying anyway", exc)
            poses = None
            if options.lockstep and up:
                poses = client.watch_poses([options.robot])
            elif options.lockstep:
                log.warning("lockstep needs a service that answers (see --wait-service); off")
            answered: set[int] = set()  # seqs answered (written on Zenoh's thread)
            client.watch_poses([options.robot], callback=lambda m: answered.add(m.seq))
            bar = Progress(
                options.log.name, total, progress_out or sys.stderr, enabled=options.progress
            )
            sent, got = _publish(session, options, scans, stop, poses, bar, answered)
        finally:
            client.close()
    el = max(time.monotonic() - bar.t0, 1e-9)
    log.info("done: %d scans in %.1f s (%.1f scans/s), %d poses seen", sent, el, sent / el, got)
    return 0


def _publish(
    session: zenoh.Session,
    options: ReplayOptions,
    scans: Iterator[LogScan],
    stop: threading.Event,
    poses: Stream[PoseMsg] | None,
    bar: Progress,
    answered: set[int],
) -> tuple[int, int]:
    from sim_publisher.__main__ import _wait_answers  # the lockstep of `run`

    enc = zenoh.Encoding(MSGPACK_ENCODING)
    block = zenoh.CongestionControl.BLOCK
    # as `run`: scans may be dropped under congestion except in lockstep; truth never is
    scan_pub = session.declare_publisher(
        keys.robot_key(options.prefix, options.robot, "scan"),
        encoding=enc,
        congestion_control=block if poses is not None else zenoh.CongestionControl.DROP,
    )
    truth_pub = session.declare_publisher(
        keys.robot_key(options.prefix, options.robot, "truth"),
        encoding=enc,
        congestion_control=block,
    )
    sent = 0
    t_wall0 = stamp0 = None
    try:
        for scan in scans:
            if stop.is_set():
                break
            if options.rate is not None:
                if t_wall0 is None or stamp0 is None:
                    t_wall0, stamp0 = time.monotonic(), scan.stamp
                delay = t_wall0 + (scan.stamp - stamp0) / options.rate - time.monotonic()
                if delay > 0 and stop.wait(delay):
                    break
            truth = truth_message(scan)
            if truth is not None:
                truth_pub.put(encode(truth))
            scan_pub.put(encode(scan_message(scan, options.odom), ranges_as_bytes=True))
            sent += 1
            if poses is not None:
                _wait_answers(poses, scan.index, {options.robot}, options.lockstep_timeout, stop)
            bar.update(sent, len(answered))
    finally:
        scan_pub.undeclare()
        truth_pub.undeclare()
    if poses is None and not stop.is_set():
        stop.wait(0.5)  # let the last answers arrive before counting them
    got = len(answered)
    bar.update(sent, got, final=True)
    return sent, got


def _rate(text: str) -> float | None:
    if text == "max":
        return None
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"--rate takes a number > 0 or 'max', not {text!r}"
        ) from None
    if not (v > 0 and math.isfinite(v)):
        raise argparse.ArgumentTypeError(f"--rate must be > 0 (or 'max'), not {text!r}")
    return v


def _pose(text: str) -> list[float]:
    try:
        v = [float(t) for t in text.split(",")]
    except ValueError:
        v = []
    if len(v) != 3 or not all(math.isfinite(x) for x in v):
        raise argparse.ArgumentTypeError(f"--initial-pose takes X,Y,THETA, not {text!r}")
    return v


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The options of ``shapeloc-sim replay``."""
    p.add_argument("log", type=Path, metavar="LOG", help="ROS 1/2 bag or CARMEN log (.gz too)")
    p.add_argument("--robot", required=True, help="robot id to publish as")
    p.add_argument("--map", dest="map_id", required=True, help="id of the stored map to use")
    p.add_argument("--method", default="shape", choices=METHODS, help="localisation method")
    p.add_argument(
        "--rate",
        type=_rate,
        default=1.0,
        metavar="1|N|max",
        help="1: real time (default); N: N times faster; max: as fast as possible",
    )
    p.add_argument(
        "--lockstep",
        action="store_true",
        help="send the next scan only once the robot's pose for the last one arrived",
    )
    p.add_argument(
        "--lockstep-timeout",
        type=float,
        default=30.0,
        help="seconds to wait for a pose in lockstep before going on (default 30)",
    )
    p.add_argument("--no-odom", dest="odom", action="store_false", help="omit odometry")
    p.add_argument(
        "--reference",
        type=Path,
        metavar="FILE",
        help="per-scan reference poses (raw_stamp x y theta flag): flag-1 rows go on the truth "
        "key, the first row is the default initial pose",
    )
    p.add_argument("--limit", type=int, metavar="N", help="replay only the first N scans")
    g = p.add_mutually_exclusive_group()
    g.add_argument(
        "--initial-pose", type=_pose, metavar="X,Y,THETA", help="initial pose (map frame)"
    )
    g.add_argument(
        "--global",
        dest="global_localization",
        action="store_true",
        help="configure the robot with initial_pose null (global localisation)",
    )
    p.add_argument(
        "--no-configure",
        dest="configure",
        action="store_false",
        help="do not put the robot's configuration",
    )
    p.add_argument("--scan-topic", help="bag topic of the scans (default: by message type)")
    p.add_argument("--odom-topic", help="bag topic of the odometry (default: by message type)")
    p.add_argument("--max-range", type=float, help="treat longer readings as no-returns (m)")
    p.add_argument("--no-progress", dest="progress", action="store_false", help="no progress line")
    p.add_argument(
        "--wait-service",
        type=float,
        default=30.0,
        help="seconds to wait for the service's health before replaying (0: don't)",
    )
    p.add_argument("--prefix", default=DEFAULT_PREFIX, help="key prefix")
    from sim_publisher.__main__ import add_zenoh_arguments  # the options `run` takes

    add_zenoh_arguments(p)
    p.add_argument("-v", "--verbose", action="store_true", help="debug logging")


def options_from_args(args: argparse.Namespace) -> ReplayOptions:
    """Validate parsed arguments into :class:`ReplayOptions` (raises ``ValueError``)."""
    if args.limit is not None and args.limit < 0:
        raise ValueError("--limit must be >= 0")
    if args.lockstep_timeout <= 0:
        raise ValueError("--lockstep-timeout must be > 0")
    for what, value in (("--robot", args.robot), ("--map", args.map_id)):
        problem = keys.id_error(value)
        if problem is not None:
            raise ValueError(f"{what} {value!r}: {problem}")
    return ReplayOptions(
        log=args.log,
        robot=args.robot,
        map_id=args.map_id,
        method=args.method,
        rate=args.rate,
        lockstep=args.lockstep,
        lockstep_timeout=args.lockstep_timeout,
        odom=args.odom,
        reference=args.reference,
        limit=args.limit,
        initial_pose=args.initial_pose,
        global_localization=args.global_localization,
        configure=args.configure,
        wait_service=args.wait_service,
        prefix=args.prefix,
        scan_topic=args.scan_topic,
        odom_topic=args.odom_topic,
        max_range=args.max_range,
        progress=args.progress,
    )


def run(args: argparse.Namespace) -> int:
    """``shapeloc-sim replay``: validate, open the session, replay until done or a signal
    (SIGINT/SIGTERM stop after the current scan)."""
    from sim_publisher.__main__ import run_until_signal  # what `run` does around its loop

    return run_until_signal(args, "shapeloc-sim replay", options_from_args, main)
