"""``shapeloc``: command line of the shapeloc localizer service.

Commands: ``health``, ``maps``, ``map put|get|delete`` (and, without a service, ``map
import|build|schematize|fidelity``: :mod:`clients.maps_cli`), ``configure``, ``pose`` and ``watch``
(the paper's experiment is ``shapeloc-sim experiment``: it belongs to the simulator). It
connects as a Zenoh client to ``--connect`` (default ``tcp/127.0.0.1:7447``) and fails at once
if nothing listens. ``--zenoh-config FILE`` (Zenoh JSON5: TLS, mutual TLS, user/password) is the
base configuration; ``--connect`` replaces its endpoints and the mode is always ``client``
(see docs/reliability.md). Exit code 0 on success, 1 on an error (one line on stderr), 2 on
bad usage.
"""

from __future__ import annotations

import argparse
import math
import signal
import sys
import threading
import time
from collections.abc import Sequence

import zenoh

from clients import maps_cli
from clients.client import (
    DEFAULT_CONNECT,
    DEFAULT_PREFIX,
    DEFAULT_TIMEOUT,
    ShapelocClient,
    config_endpoints,
    open_session,
    zenoh_config,
)
from schemas.messages import METHODS, Map, PoseMsg
from service.errors import ShapelocError, UnknownMap


def _positive(text: str) -> float:
    v = float(text)
    if not v > 0:
        raise argparse.ArgumentTypeError(f"must be > 0, got {text}")
    return v


def build_parser() -> argparse.ArgumentParser:
    """The ``shapeloc`` argument parser (subcommand in ``args.command``)."""
    p = argparse.ArgumentParser(
        prog="shapeloc",
        description="Talk to a shapeloc localizer service over Zenoh.",
    )
    p.add_argument(
        "--connect",
        action="append",
        default=None,
        help=f"Zenoh endpoint of the service or router (repeatable; default {DEFAULT_CONNECT})",
    )
    p.add_argument(
        "--zenoh-config",
        dest="zenoh_config",
        metavar="FILE",
        help="Zenoh JSON5 config (TLS, mTLS, user/password); --connect replaces its endpoints",
    )
    p.add_argument("--prefix", default=DEFAULT_PREFIX, help="key prefix (default shapeloc)")
    p.add_argument(
        "--timeout", type=_positive, default=DEFAULT_TIMEOUT, help="request timeout in s"
    )
    sub = p.add_subparsers(dest="command", metavar="COMMAND", required=True)

    sub.add_parser("health", help="service status and counters")
    sub.add_parser("maps", help="list stored maps")

    mp = sub.add_parser("map", help="store, show or delete a map")
    msub = mp.add_subparsers(dest="map_command", metavar="ACTION", required=True)
    put = msub.add_parser("put", help="store a map file (GeoJSON world, GeoJSON lines, wire JSON)")
    put.add_argument("file", help="map file")
    put.add_argument("--id", dest="map_id", help="map id (default: from the file, or its stem)")
    put.add_argument("--kind", choices=("metric", "schematic"), help="map kind")
    get = msub.add_parser("get", help="show one stored map")
    get.add_argument("map_id")
    dele = msub.add_parser("delete", help="delete a stored map")
    dele.add_argument("map_id")
    maps_cli.add_parsers(msub)  # import, build, schematize, fidelity (local, no service)

    cfg = sub.add_parser("configure", help="configure (and reset) a robot")
    cfg.add_argument("robot_id")
    cfg.add_argument("--map", dest="map_id", required=True, help="id of a stored map")
    cfg.add_argument("--method", choices=METHODS, default="shape")
    where = cfg.add_mutually_exclusive_group(required=True)
    where.add_argument(
        "--pose",
        nargs=3,
        type=float,
        metavar=("X", "Y", "THETA"),
        help="initial pose: metres, metres, radians (map frame)",
    )
    where.add_argument(
        "--global", dest="global_localization", action="store_true", help="unknown start pose"
    )

    pose = sub.add_parser("pose", help="latest pose estimate of a robot")
    pose.add_argument("robot_id")

    watch = sub.add_parser("watch", help="print pose estimates as they arrive (Ctrl-C stops)")
    watch.add_argument("robot_id", nargs="?", default="*", help="robot id (default: all)")
    watch.add_argument("--count", type=int, help="stop after this many poses")
    watch.add_argument("--seconds", type=_positive, help="stop after this many seconds")
    return p


def _fmt_pose(m: PoseMsg) -> str:
    x, y, th = m.pose
    return (
        f"{m.robot_id}: x={x:.3f} m y={y:.3f} m theta={math.degrees(th):.1f} deg  "
        f"{m.status}  score={m.score:.2f}  seq={m.seq}  map={m.map_id}  method={m.method}  "
        f"latency={m.latency_ms:.1f} ms"
    )


def _fmt_map(m: Map) -> str:
    pts = [pt for line in m.polylines for pt in line]
    xs = [float(p[0]) for p in pts]
    ys = [float(p[1]) for p in pts]
    return (
        f"{m.map_id:<24} {m.kind:<10} {len(m.polylines):>5} polylines {len(pts):>6} points  "
        f"x [{min(xs):.2f}, {max(xs):.2f}] y [{min(ys):.2f}, {max(ys):.2f}] m"
    )


def run(args: argparse.Namespace, out: object = None) -> int:
    """Execute a parsed command; errors propagate as :class:`ShapelocError`."""
    out = out or sys.stdout
    if args.command == "map" and args.map_command in maps_cli.LOCAL_ACTIONS:
        return maps_cli.run(args, out)  # type: ignore[arg-type]
    endpoints = args.connect or [DEFAULT_CONNECT]
    session = None
    if getattr(args, "zenoh_config", None):
        conf = zenoh_config(
            "client",
            connect=args.connect or (),
            config_file=args.zenoh_config,
            default_connect=[DEFAULT_CONNECT],
        )
        session = open_session(conf, config_endpoints(conf))
    try:
        return _run(args, out, endpoints, session)
    finally:
        if session is not None:
            session.close()


def _run(
    args: argparse.Namespace, out: object, endpoints: list[str], session: zenoh.Session | None
) -> int:
    with ShapelocClient(endpoints, session=session, prefix=args.prefix, timeout=args.timeout) as c:
        cmd = args.command
        if cmd == "health":
            h = c.health()
            print(
                f"{h.status}: shapeloc {h.version}, {h.maps} maps, {h.robots} robots, "
                f"{h.scans_processed} scans processed, {h.scans_rejected} rejected",
                file=out,
            )
        elif cmd == "maps":
            maps = c.list_maps()
            if not maps:
                c.health()  # distinguishes "no maps" from "no service"
                print("no maps stored", file=out)
            for m in maps:
                print(_fmt_map(m), file=out)
        elif cmd == "map":
            if args.map_command == "put":
                c.health()
                m = c.put_map(args.file, map_id=args.map_id, kind=args.kind, confirm=True)
                print(f"stored {_fmt_map(m)}", file=out)
            elif args.map_command == "get":
                print(_fmt_map(c.get_map(args.map_id)), file=out)
            else:
                c.get_map(args.map_id)
                c.delete_map(args.map_id)
                print(f"deleted map {args.map_id}", file=out)
        elif cmd == "configure":
            c.health()
            try:
                c.get_map(args.map_id)
            except UnknownMap:
                raise UnknownMap(
                    f"the service holds no map {args.map_id!r} (store it with shapeloc map put)"
                ) from None
            pose = None if args.global_localization else args.pose
            c.configure(args.robot_id, args.map_id, args.method, pose, confirm=True)
            where = "global localisation" if pose is None else f"initial pose {pose}"
            print(
                f"configured {args.robot_id}: map {args.map_id}, {args.method}, {where}", file=out
            )
        elif cmd == "pose":
            print(_fmt_pose(c.get_pose(args.robot_id)), file=out)
        elif cmd == "watch":
            return _watch(c, args, out)
    return 0


def _watch(c: ShapelocClient, args: argparse.Namespace, out: object) -> int:
    c.health()
    stop = threading.Event()
    old = {}
    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGINT, signal.SIGTERM):
            old[sig] = signal.signal(sig, lambda *_: stop.set())
    end = None if args.seconds is None else time.monotonic() + args.seconds
    n = 0
    try:
        with c.watch_poses(args.robot_id) as stream:
            while not stop.is_set():
                if args.count is not None and n >= args.count:
                    break
                if end is not None and time.monotonic() >= end:
                    break
                item = stream.get(timeout=0.2)
                if item is None:
                    continue
                print(_fmt_pose(item[1]), file=out, flush=True)
                n += 1
    finally:
        for sig, handler in old.items():
            signal.signal(sig, handler)
    return 0


def cli(argv: Sequence[str] | None = None) -> int:
    """Console entry point ``shapeloc``; returns the exit code."""
    args = build_parser().parse_args(argv)
    zenoh.init_log_from_env_or("error")
    try:
        return run(args)
    except ShapelocError as exc:
        print(f"shapeloc: error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(cli())
