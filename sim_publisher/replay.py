"""``shapeloc-sim replay LOG``: publish a recorded laser log over Zenoh as a robot would.

Reads the log with :func:`service.adapters.logs.read_log` (ROS 1 / ROS 2 bag, CARMEN log, also a
GMapping-corrected one) and puts, for scan ``k`` of the log (``seq = k``, ``stamp`` = the log's
own stamp, seconds):

- a :class:`~schemas.messages.Scan` on ``<prefix>/robots/<id>/scan`` with the log's beam
  geometry and ranges (metres; no-returns NaN, sent as float32 bytes like the simulator's) and,
  unless ``--no-odom``, ``odom`` = the log's odometry at the scan's stamp;
- a :class:`~schemas.messages.Truth` on ``<prefix>/robots/<id>/truth`` with the scan's
  reference pose when it has a trustworthy one: flag 1 of ``--reference FILE`` (a
  ``*.gfs_reference_per_scan.txt``, matched by stamp), or a corrected log's own pose. Flag-0
  rows (carried by odometry) are not published.

Frames. The log reader gives the LASER's odometry and reference poses (it composes the log's
own mounting, e.g. fr079's 0.04 m). By default they go out as they are: the robot is its
laser, ``laser_offset`` zero. With ``--laser-offset X Y THETA`` the replayed robot is a base
carrying the laser at that pose: odometry, truth and the initial pose go out as the base's
(the laser's pose composed with the offset's inverse) and the configuration carries the
offset, as a nav2 robot's front sends them; the service's poses are then the base's.

Pacing: ``--speed 1`` replays in real time (the gaps between log stamps), ``--speed N`` N times
faster, ``--speed max`` as fast as possible. ``--lockstep`` also waits for the robot's pose
for each scan before the next (the same wait as ``shapeloc-sim run --lockstep``).

The map is not put (``shapeloc map put FILE`` does that; ``--map`` names the stored map's id).
Unless ``--no-configure``, the map must be stored and the robot's configuration is put and
confirmed: map, method, initial pose (``--initial-pose X Y THETA``; else ``--global``; else the
first replayed scan's reference pose) and mounting. A missing map or a configuration the
service refuses ends the replay at once with the service's reason (exit 1), as does a service
that does not answer within ``--wait-service`` s (``--wait-service 0``: replay without one).

At the end a summary goes to standard output (``--json``: as one JSON object): scans sent,
poses received by status, and with a reference the share of reference scans whose pose is
within 0.1 / 0.3 / 0.5 m, the error quantiles and, with ``--relations FILE``, Kümmerle et al.'s
relations error (:func:`service.adapters.logs.relations_error`). Exit 1 also when no pose at
all came back. A progress bar (tqdm) goes to standard error.

Deprecated for one release (a warning on stderr): ``--rate N`` as the speed factor (now
``--speed N``; ``--rate`` is scans per second everywhere) and ``--initial-pose X,Y,THETA``.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import sys
import threading
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TextIO

import numpy as np
import zenoh
from tqdm import tqdm

from clients.client import ShapelocClient, Stream, open_session
from schemas import keys
from schemas.cli import (
    DEFAULT_PREFIX,
    PoseAction,
    add_json_option,
    resolve_client_globals,
    warn_deprecated,
)
from schemas.codec import MSGPACK_ENCODING, encode
from schemas.messages import METHODS, ErrorNotice, PoseMsg, RobotConfig, Scan, Truth
from service.adapters.logs import (
    LogInfo,
    LogScan,
    Relations,
    attach_reference,
    load_reference,
    load_relations,
    read_log,
    relations_error,
)
from service.core.mounting import to_base
from service.errors import ServiceTimeout, UnknownMap
from sim_publisher.networked import (
    GLOBAL_OPTIONS,
    configure_robots,
    run_until_signal,
    wait_answers,
    wait_service,
)

log = logging.getLogger("shapeloc.sim.replay")

#: Distances (m) of the accuracy summary: the share of reference scans within each.
WITHIN_M = (0.1, 0.3, 0.5)
#: Seconds to wait after the last scan for the last answers (without lockstep).
DRAIN_S = 0.5


@dataclass
class ReplayOptions:
    """Options of one replay (see ``shapeloc-sim replay --help``; seconds, metres, radians).

    ``speed``: real-time factor (``None``: as fast as possible). ``initial_pose``: explicit
    ``[x, y, theta]`` (map frame), else ``None`` and ``global_localization`` decides.
    ``laser_offset``: the replayed robot's laser pose on its base (``None``: the robot is its
    laser). ``relations``: a relations file to score the poses with.
    """

    log: Path
    robot: str
    map_id: str
    method: str = "shape"
    speed: float | None = 1.0
    lockstep: bool = False
    lockstep_timeout: float = 30.0
    odom: bool = True
    reference: Path | None = None
    relations: Path | None = None
    limit: int | None = None
    initial_pose: list[float] | None = None
    global_localization: bool = False
    laser_offset: list[float] | None = None
    configure: bool = True
    wait_service: float = 30.0
    prefix: str = DEFAULT_PREFIX
    timeout: float = 2.0
    scan_topic: str | None = None
    odom_topic: str | None = None
    max_range: float | None = None
    progress: bool = True
    json: bool = False
    #: Publish as a ROS 2 robot in namespace /<robot> (sim_publisher/ros2.py).
    ros2: bool = False


def _base(pose: Sequence[float] | np.ndarray, offset: Sequence[float] | None) -> list[float]:
    p = np.asarray(pose, dtype=np.float64)
    if offset is not None:
        p = to_base(p, np.asarray(offset, dtype=np.float64))
    return [float(v) for v in p]


def scan_message(
    scan: LogScan, odom: bool = True, laser_offset: Sequence[float] | None = None
) -> Scan:
    """The wire scan of a log scan: ``seq`` = its index in the log, the log's stamp, beam
    geometry and ranges (NaN = no return), ``odom`` when asked for and known (the laser's,
    or the base's with ``laser_offset``)."""
    return Scan(
        seq=scan.index,
        stamp=scan.stamp,
        angle_min=scan.angle_min,
        angle_increment=scan.angle_increment,
        range_min=scan.range_min,
        range_max=scan.range_max,
        ranges=scan.ranges,
        odom=_base(scan.odom, laser_offset) if odom and scan.odom is not None else None,
    )


def truth_message(scan: LogScan, laser_offset: Sequence[float] | None = None) -> Truth | None:
    """The wire truth of a log scan: its trustworthy reference pose (map frame; the laser's,
    or the base's with ``laser_offset``), or ``None`` when it has none (no reference, or a
    flag-0 one)."""
    if scan.reference is None or not scan.reference_ok:
        return None
    return Truth(seq=scan.index, stamp=scan.stamp, pose=_base(scan.reference, laser_offset))


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
    else the first scan's reference pose (any flag; the base's with a ``laser_offset``);
    raises ``ValueError`` if none applies."""
    if options.initial_pose is not None:
        return list(options.initial_pose)
    if options.global_localization:
        return None
    if first is not None and first.reference is not None:
        return _base(first.reference, options.laser_offset)
    raise ValueError(
        "no initial pose: give --initial-pose X Y THETA, --global, or --reference FILE (or a "
        "corrected log) whose first pose starts the robot"
    )


# ------------------------------------------------------------------ the accuracy summary
@dataclass
class Collected:
    """What one replay saw: the reference (truth) poses it sent and the poses and error
    notices that came back, by scan ``seq``. Filled from Zenoh's callback thread (plain dict
    and list stores only)."""

    truth: dict[int, np.ndarray]
    poses: dict[int, PoseMsg]
    notices: list[ErrorNotice]


def accuracy(
    truth: dict[int, np.ndarray],
    poses: dict[int, PoseMsg],
    relations: Relations | None = None,
) -> dict[str, Any]:
    """The replay's accuracy: status counts of the poses; with ``truth`` (reference poses by
    seq) the share of answered reference scans within each of :data:`WITHIN_M` and the
    position error quantiles (m) and heading error median (deg); with ``relations`` the
    relations error of the poses (scored at their stamps)."""
    out: dict[str, Any] = {"poses": len(poses), "status": {}}
    for m in poses.values():
        out["status"][m.status] = out["status"].get(m.status, 0) + 1
    out["reference"] = None
    if truth:
        seqs = [s for s in sorted(truth) if s in poses]
        ref: dict[str, Any] = {"scans": len(truth), "answered": len(seqs)}
        if seqs:
            est = np.array([poses[s].pose for s in seqs])
            tru = np.array([truth[s] for s in seqs])
            err = np.hypot(est[:, 0] - tru[:, 0], est[:, 1] - tru[:, 1])
            dth = np.abs(np.angle(np.exp(1j * (est[:, 2] - tru[:, 2]))))
            for d in WITHIN_M:
                ref[f"within_{d:g}_m"] = float(np.mean(err <= d))
            ref["error_median_m"] = float(np.median(err))
            ref["error_p90_m"] = float(np.percentile(err, 90))
            ref["error_max_m"] = float(err.max())
            ref["heading_error_median_deg"] = float(np.degrees(np.median(dth)))
        out["reference"] = ref
    out["relations"] = None
    if relations is not None:
        ordered = sorted(poses.values(), key=lambda m: m.seq)
        r = relations_error([m.stamp for m in ordered], [m.pose for m in ordered], relations)
        out["relations"] = {
            "file": str(relations.path) if relations.path is not None else None,
            "translation_mean_m": r.translation_mean,
            "translation_std_m": r.translation_std,
            "translation_max_m": r.translation_max,
            "rotation_mean_deg": r.rotation_mean,
            "rotation_std_deg": r.rotation_std,
            "rotation_max_deg": r.rotation_max,
            "used": r.used,
            "skipped": r.skipped,
        }
    return out


def summary_text(s: dict[str, Any]) -> str:
    """The summary as lines of text (``s`` as :func:`main` builds it)."""
    status = ", ".join(f"{k} {v}" for k, v in sorted(s["status"].items())) or "none"
    lines = [
        f"replay {s['log']} as {s['robot']}: {s['scans']} scans sent in {s['seconds']:.1f} s, "
        f"{s['poses']} poses received ({status})"
    ]
    if s.get("rejected"):
        lines.append(
            f"  {s['rejected']} messages rejected by the service; first: {s['first_error']}"
        )
    ref = s.get("reference")
    if ref is None:
        lines.append("  no reference poses: no accuracy (give --reference FILE)")
    elif not ref["answered"]:
        lines.append(f"  none of the {ref['scans']} reference scans got a pose")
    else:
        within = ", ".join(f"{d:g} m {100 * ref[f'within_{d:g}_m']:.1f} %" for d in WITHIN_M)
        lines.append(
            f"  against {ref['scans']} reference poses ({ref['answered']} answered): within "
            f"{within}"
        )
        lines.append(
            f"  position error median {ref['error_median_m']:.3f} m, p90 "
            f"{ref['error_p90_m']:.3f} m, max {ref['error_max_m']:.3f} m; heading error median "
            f"{ref['heading_error_median_deg']:.2f} deg"
        )
    rel = s.get("relations")
    if rel is not None:
        lines.append(
            f"  relations error {rel['translation_mean_m']:.4f} ± {rel['translation_std_m']:.4f}"
            f" m (max {rel['translation_max_m']:.3f}), {rel['rotation_mean_deg']:.3f} ± "
            f"{rel['rotation_std_deg']:.3f} deg; {rel['used']} relations, {rel['skipped']} "
            "skipped"
        )
    return "\n".join(lines)


# ------------------------------------------------------------------ the replay
def main(
    conf: zenoh.Config,
    options: ReplayOptions,
    stop: threading.Event | None = None,
    endpoints: Sequence[str] = (),
    progress_out: TextIO | None = None,
    out: TextIO | None = None,
) -> int:
    """Replay ``options.log`` on a Zenoh session opened from ``conf``; print the summary on
    ``out`` (default standard output); return the exit code.

    ``stop`` (set from a signal handler or another thread) ends the replay after the current
    scan. Raises :class:`LogFormatError` for a bad log, ``ValueError`` for bad options,
    :class:`UnknownMap` / :class:`RemoteError` / :class:`ServiceTimeout` when the service
    lacks the map, refuses the configuration or does not answer.
    """
    stop = stop or threading.Event()
    if options.ros2:
        from sim_publisher import ros2

        return ros2.replay_log(conf, options, stop, endpoints)
    relations = load_relations(options.relations) if options.relations is not None else None
    info, scans = open_replay(options)
    first, scans = _peek(scans)
    pose0 = initial_pose_for(options, first) if options.configure else None
    total = info.scan_count
    if total is not None and options.limit is not None:
        total = min(total, options.limit)
    seen = Collected(truth={}, poses={}, notices=[])
    t0 = time.monotonic()
    with open_session(conf, endpoints) as session:
        client = ShapelocClient(session=session, prefix=options.prefix, timeout=options.timeout)
        try:
            up = options.wait_service > 0 and wait_service(client, options.wait_service, stop)
            if options.wait_service > 0 and not up and not stop.is_set():
                raise ServiceTimeout(
                    f"no shapeloc service answered on {keys.health_key(options.prefix)} within "
                    f"{options.wait_service:g} s (check --connect and --prefix; --wait-service "
                    "0 replays without one)"
                )
            if options.configure and not stop.is_set():
                _configure(client, options, pose0, up, stop)
            poses = None
            if options.lockstep and up:
                poses = client.watch_poses([options.robot])
            elif options.lockstep:
                log.warning("lockstep needs a service that answers (see --wait-service); off")
            client.watch_poses([options.robot], callback=lambda m: seen.poses.__setitem__(m.seq, m))
            mine = f"{options.prefix}/robots/{options.robot}/"
            client.watch_errors(
                callback=lambda n: seen.notices.append(n) if n.key.startswith(mine) else None
            )
            bar = tqdm(
                total=total,
                desc=f"replay {options.log.name}",
                unit="scan",
                file=progress_out or sys.stderr,
                disable=not options.progress,
                mininterval=0.25,
                dynamic_ncols=True,
            )
            with bar:
                sent = publish_log(session, options, scans, stop, poses, bar, seen)
        finally:
            client.close()
    el = max(time.monotonic() - t0, 1e-9)
    summary = {
        "log": options.log.name,
        "robot": options.robot,
        "scans": sent,
        "seconds": el,
        "rejected": len(seen.notices),
        "first_error": seen.notices[0].error if seen.notices else None,
        **accuracy(seen.truth, dict(seen.poses), relations),
    }
    log.info("done: %d scans in %.1f s (%.1f scans/s)", sent, el, sent / el)
    target = out or sys.stdout
    if options.json:
        print(json.dumps(summary, sort_keys=True), file=target, flush=True)
    else:
        print(summary_text(summary), file=target, flush=True)
    if up and sent and not summary["poses"] and not stop.is_set():
        reason = f": {summary['first_error']}" if summary["first_error"] else ""
        print(
            f"shapeloc-sim replay: error: no pose came back for robot {options.robot!r} from "
            f"{sent} scans{reason}",
            file=sys.stderr,
        )
        return 1
    return 0


def _configure(
    client: ShapelocClient,
    options: ReplayOptions,
    pose0: list[float] | None,
    up: bool,
    stop: threading.Event,
) -> None:
    """Put the robot's configuration; with a service up, check the map first and wait for
    the service to take the configuration (its refusal raises with its reason)."""
    extra: dict[str, Any] = {}
    if options.laser_offset is not None:
        extra["laser_offset"] = options.laser_offset
    cfg = RobotConfig(map_id=options.map_id, method=options.method, initial_pose=pose0, **extra)
    if up:
        try:
            client.get_map(options.map_id)
        except UnknownMap:
            raise UnknownMap(
                f"the service holds no map {options.map_id!r}; store it first with "
                f"shapeloc map put FILE --id {options.map_id}"
            ) from None
        configure_robots(client, [(options.robot, cfg)], options.wait_service, stop)
    else:
        client.configure(
            options.robot, cfg.map_id, cfg.method, pose0, laser_offset=options.laser_offset
        )
    log.info(
        "robot %s: map %s, method %s, initial pose %s%s",
        options.robot,
        options.map_id,
        options.method,
        "global" if pose0 is None else np.round(pose0, 4).tolist(),
        "" if options.laser_offset is None else f", laser offset {options.laser_offset}",
    )


def publish_log(
    session: zenoh.Session,
    options: ReplayOptions,
    scans: Iterator[LogScan],
    stop: threading.Event,
    poses: Stream[PoseMsg] | None,
    bar: Any,
    seen: Collected,
) -> int:
    """Put every scan (and its truth) paced by ``options.speed``; returns the scans sent."""
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
            if options.speed is not None:
                if t_wall0 is None or stamp0 is None:
                    t_wall0, stamp0 = time.monotonic(), scan.stamp
                delay = t_wall0 + (scan.stamp - stamp0) / options.speed - time.monotonic()
                if delay > 0 and stop.wait(delay):
                    break
            truth = truth_message(scan, options.laser_offset)
            if truth is not None:
                seen.truth[truth.seq] = np.asarray(truth.pose)
                truth_pub.put(encode(truth))
            msg = scan_message(scan, options.odom, options.laser_offset)
            scan_pub.put(encode(msg, ranges_as_bytes=True))
            sent += 1
            if poses is not None:
                wait_answers(poses, scan.index, {options.robot}, options.lockstep_timeout, stop)
            bar.update(1)
            bar.set_postfix(poses=len(seen.poses), refresh=False)
    finally:
        scan_pub.undeclare()
        truth_pub.undeclare()
    if poses is None and not stop.is_set():
        stop.wait(DRAIN_S)  # let the last answers arrive before counting them
    bar.set_postfix(poses=len(seen.poses))
    return sent


# ------------------------------------------------------------------ the command line
def _speed(text: str) -> float | None:
    if text == "max":
        return None
    try:
        v = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"takes a number > 0 or 'max', not {text!r}") from None
    if not (v > 0 and math.isfinite(v)):
        raise argparse.ArgumentTypeError(f"must be > 0 (or 'max'), not {text!r}")
    return v


class _RateAsSpeed(argparse.Action):
    """``--rate N``, the old name of ``--speed N`` in ``replay``: still works, warns."""

    def __call__(
        self,
        parser: argparse.ArgumentParser,
        namespace: argparse.Namespace,
        values: Any,
        option_string: str | None = None,
    ) -> None:
        warn_deprecated(
            parser.prog,
            "--rate as the replay's speed factor",
            "--speed 1|N|max (--rate is scans per second in every command)",
        )
        namespace.speed = values


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The options of ``shapeloc-sim replay`` (the global options come with its parser)."""
    p.add_argument("log", type=Path, metavar="LOG", help="ROS 1/2 bag or CARMEN log (.gz too)")
    p.add_argument("--robot", required=True, help="robot id to publish as")
    p.add_argument("--map", dest="map_id", required=True, help="id of the stored map to use")
    p.add_argument("--method", default="shape", choices=METHODS, help="localisation method")
    p.add_argument(
        "--speed",
        type=_speed,
        default=1.0,
        metavar="1|N|max",
        help="1: real time (the log's own timing); N: N times faster; max: as fast as "
        "possible (default: 1)",
    )
    p.add_argument("--rate", type=_speed, action=_RateAsSpeed, help=argparse.SUPPRESS)
    p.add_argument(
        "--lockstep",
        action="store_true",
        help="send the next scan only once the robot's pose for the last one arrived (nothing "
        "is skipped)",
    )
    p.add_argument(
        "--lockstep-timeout",
        type=float,
        default=30.0,
        metavar="S",
        help="seconds to wait for a pose in lockstep before going on",
    )
    p.add_argument("--no-odom", dest="odom", action="store_false", help="omit odometry")
    p.add_argument(
        "--reference",
        type=Path,
        metavar="FILE",
        help="per-scan reference poses (raw_stamp x y theta flag): flag-1 rows go on the truth "
        "key and are what the accuracy summary scores; the first row is the default initial "
        "pose",
    )
    p.add_argument(
        "--relations",
        type=Path,
        metavar="FILE",
        help="Kümmerle relations (t1 t2 x y z roll pitch yaw) to score the poses with in the "
        "summary",
    )
    p.add_argument("--limit", type=int, metavar="N", help="replay only the first N scans")
    g = p.add_mutually_exclusive_group()
    g.add_argument(
        "--initial-pose",
        dest="initial_pose",
        action=PoseAction,
        help="initial pose: metres, metres, radians (map frame; default: the first reference pose)",
    )
    g.add_argument(
        "--global",
        dest="global_localization",
        action="store_true",
        help="configure the robot with initial_pose null (global localisation)",
    )
    p.add_argument(
        "--laser-offset",
        dest="laser_offset",
        action=PoseAction,
        help="replay as a robot base carrying the log's laser at this pose (x forward, y left: "
        "metres, metres, radians): odometry, truth and initial pose go out as the base's and "
        "the configuration carries the offset (default: none, the robot is its laser)",
    )
    p.add_argument(
        "--no-configure",
        dest="configure",
        action="store_false",
        help="do not put the robot's configuration",
    )
    p.add_argument("--scan-topic", help="bag topic of the scans (default: by message type)")
    p.add_argument("--odom-topic", help="bag topic of the odometry (default: by message type)")
    p.add_argument(
        "--max-range", type=float, metavar="M", help="treat longer readings as no-returns (m)"
    )
    p.add_argument("--no-progress", dest="progress", action="store_false", help="no progress bar")
    p.add_argument(
        "--wait-service",
        type=float,
        default=30.0,
        metavar="S",
        help="seconds to wait for the service's health before replaying (0: do not wait, and "
        "replay even without a service)",
    )
    p.add_argument(
        "--ros2",
        action="store_true",
        help="publish as a ROS 2 robot on rmw_zenoh's keys in namespace /<robot>: scan, tf "
        "(odometry), tf_static (the log's laser mounting); answers on amcl_pose (docs/ros2.md)",
    )
    add_json_option(p, "the summary")


def options_from_args(args: argparse.Namespace) -> ReplayOptions:
    """Validate parsed arguments into :class:`ReplayOptions` (raises ``ValueError``); global
    options not given are read from the configuration file or take their defaults
    (:func:`schemas.cli.resolve_client_globals`)."""
    resolve_client_globals(args, GLOBAL_OPTIONS)
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
        speed=args.speed,
        lockstep=args.lockstep,
        lockstep_timeout=args.lockstep_timeout,
        odom=args.odom,
        reference=args.reference,
        relations=args.relations,
        limit=args.limit,
        initial_pose=args.initial_pose,
        global_localization=args.global_localization,
        laser_offset=args.laser_offset,
        configure=args.configure,
        wait_service=args.wait_service,
        prefix=args.prefix,
        timeout=args.timeout,
        scan_topic=args.scan_topic,
        odom_topic=args.odom_topic,
        max_range=args.max_range,
        progress=args.progress,
        json=args.json,
        ros2=args.ros2,
    )


def run(args: argparse.Namespace) -> int:
    """``shapeloc-sim replay``: validate, open the session, replay until done or a signal
    (SIGINT/SIGTERM stop after the current scan), print the summary."""
    return run_until_signal(args, "shapeloc-sim replay", options_from_args, main)


__all__ = [
    "WITHIN_M",
    "Collected",
    "ReplayOptions",
    "accuracy",
    "add_arguments",
    "initial_pose_for",
    "main",
    "open_replay",
    "options_from_args",
    "run",
    "scan_message",
    "summary_text",
    "truth_message",
]
