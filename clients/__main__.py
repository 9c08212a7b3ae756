"""``shapeloc``: command line of the shapeloc localizer service.

Commands (one entry each in :data:`COMMANDS`): ``health``, ``maps``, ``map put|get|delete``
(and, without a service, ``map import|build|schematize|fidelity``: :mod:`clients.maps_cli`),
``configure``, ``pose``, ``watch``, ``view`` (the live view in the browser,
:mod:`clients.view`) and ``record`` (an MCAP file for Foxglove, :mod:`clients.record`). The
paper's experiment and log replay belong to the simulator (``shapeloc-sim
experiment|replay``).

It follows the convention of every shapeloc program (:mod:`schemas.cli`): the global options
``--connect``, ``--mode``, ``--zenoh-config``, ``--prefix``, ``--config``, ``--timeout`` and
``-v`` go before or after the command; ``--json`` prints a command's data as JSON (``watch``:
one JSON object a line); help shows the defaults. It connects as a Zenoh client to
``--connect`` (default ``tcp/127.0.0.1:7447``) and fails at once if nothing listens;
``--zenoh-config FILE`` (Zenoh JSON5: TLS, mutual TLS, user/password) is the base
configuration and ``--connect`` replaces its endpoints (see docs/security.md). Exit code 0
on success, 1 on an error (one line on stderr), 2 on bad usage.

Deprecated for one release (a warning on stderr): ``configure --pose X Y THETA`` (now
``--initial-pose X Y THETA``) and ``--initial-pose X,Y,THETA``.
"""

from __future__ import annotations

import argparse
import json
import logging
import math
import signal
import sys
import threading
import time
from collections.abc import Callable, Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any, TextIO

import zenoh

from clients import maps_cli
from clients.client import (
    DEFAULT_CONNECT,
    ShapelocClient,
    config_endpoints,
    open_session,
    zenoh_config,
)
from clients.view import DEFAULT_HOST, DEFAULT_NICE, DEFAULT_PORT, DEFAULT_RATE_HZ
from schemas.cli import (
    GlobalOptions,
    HelpFormatter,
    PoseAction,
    add_command,
    add_global_options,
    add_json_option,
    resolve_client_globals,
)
from schemas.messages import METHODS, Map, PoseMsg
from service.errors import ShapelocError, UnknownMap, Unreachable

#: The global options of ``shapeloc`` (schemas.cli): a Zenoh client that queries the service.
#: how long ``map put`` waits for the map to be ready by default: preparing a map takes
#: seconds, and tens of seconds for a large building on a loaded machine
MAP_READY_WAIT_S = 120.0

GLOBAL_OPTIONS = GlobalOptions(listen=False, timeout=True, modes=("client", "peer"))


def _positive(text: str) -> float:
    v = float(text)
    if not v > 0:
        raise argparse.ArgumentTypeError(f"must be > 0, got {text}")
    return v


# ------------------------------------------------------------------ output
def _fmt_pose(m: PoseMsg) -> str:
    x, y, th = m.pose
    return (
        f"{m.robot_id}: x={x:.3f} m y={y:.3f} m theta={math.degrees(th):.1f} deg  "
        f"{m.status}  score={m.score:.2f}  seq={m.seq}  map={m.map_id}  method={m.method}  "
        f"latency={m.latency_ms:.1f} ms"
    )


def map_summary(m: Map) -> dict[str, Any]:
    """A map's id, kind, name, counts and extent (``[xmin, ymin, xmax, ymax]``, m)."""
    pts = [pt for line in m.polylines for pt in line]
    xs = [float(p[0]) for p in pts]
    ys = [float(p[1]) for p in pts]
    return {
        "map_id": m.map_id,
        "kind": m.kind,
        "name": m.name,
        "polylines": len(m.polylines),
        "points": len(pts),
        "bounds": [min(xs), min(ys), max(xs), max(ys)],
    }


def _fmt_map(m: Map) -> str:
    s = map_summary(m)
    x0, y0, x1, y1 = s["bounds"]
    return (
        f"{m.map_id:<24} {m.kind:<10} {s['polylines']:>5} polylines {s['points']:>6} points  "
        f"x [{x0:.2f}, {x1:.2f}] y [{y0:.2f}, {y1:.2f}] m"
    )


def _print_json(obj: Any, out: TextIO) -> None:
    print(json.dumps(obj, sort_keys=True), file=out, flush=True)


# ------------------------------------------------------------------ the commands
@contextmanager
def connect(args: argparse.Namespace) -> Iterator[ShapelocClient]:
    """A client of the service named by the global options (already resolved)."""
    session = None
    endpoints = args.connect or [DEFAULT_CONNECT]
    mode = args.mode or "client"
    if args.zenoh_config or mode != "client":
        conf = zenoh_config(
            args.mode if args.zenoh_config else mode,
            connect=args.connect or (),
            config_file=args.zenoh_config,
            default_connect=[DEFAULT_CONNECT],
        )
        session = open_session(conf, config_endpoints(conf))
    try:
        with ShapelocClient(
            endpoints, session=session, prefix=args.prefix, timeout=args.timeout
        ) as c:
            yield c
    finally:
        if session is not None:
            session.close()


def _add_health(p: argparse.ArgumentParser) -> None:
    add_json_option(p, "the health reply")


def _run_health(args: argparse.Namespace, out: TextIO) -> int:
    with connect(args) as c:
        h = c.health()
    if args.json:
        _print_json(h.to_wire(), out)
    else:
        print(
            f"{h.status}: shapeloc {h.version}, {h.maps} maps, {h.robots} robots, "
            f"{h.scans_processed} scans processed, {h.scans_rejected} rejected",
            file=out,
        )
    return 0


def _add_maps(p: argparse.ArgumentParser) -> None:
    add_json_option(p, "a list of the maps (id, kind, name, polylines, points, bounds)")


def _run_maps(args: argparse.Namespace, out: TextIO) -> int:
    with connect(args) as c:
        maps = c.list_maps()
        if not maps:
            c.health()  # distinguishes "no maps" from "no service"
    if args.json:
        _print_json([map_summary(m) for m in maps], out)
        return 0
    if not maps:
        print("no maps stored", file=out)
    for m in maps:
        print(_fmt_map(m), file=out)
    return 0


def _add_map(p: argparse.ArgumentParser) -> None:
    msub = p.add_subparsers(dest="map_command", metavar="ACTION", required=True)
    put = add_command(
        msub,
        "put",
        GLOBAL_OPTIONS,
        help="store a map file (GeoJSON world, GeoJSON lines, wire JSON, WKT, map_server YAML)",
    )
    put.add_argument("file", help="map file")
    put.add_argument("--id", dest="map_id", help="map id (default: from the file, or its stem)")
    put.add_argument(
        "--kind", choices=("metric", "schematic"), help="map kind (default: from the file)"
    )
    put.add_argument(
        "--wait",
        type=float,
        default=MAP_READY_WAIT_S,
        metavar="S",
        help="wait up to S seconds until the service reports the map ready (every worker holds "
        "it prepared, like map_server's load_map answering once loaded); 0: return once stored",
    )
    add_json_option(put, "a summary of the stored map")
    get = add_command(msub, "get", GLOBAL_OPTIONS, help="show one stored map")
    get.add_argument("map_id")
    add_json_option(get, "the whole map as a wire message (map_id, kind, polylines)")
    dele = add_command(msub, "delete", GLOBAL_OPTIONS, help="delete a stored map")
    dele.add_argument("map_id")
    # import, build, schematize, fidelity: local, no service
    maps_cli.add_parsers(msub, lambda sub, name, **kw: add_command(sub, name, GLOBAL_OPTIONS, **kw))


def _run_map(args: argparse.Namespace, out: TextIO) -> int:
    if args.map_command in maps_cli.LOCAL_ACTIONS:
        return maps_cli.run(args, out)
    with connect(args) as c:
        if args.map_command == "put":
            c.health()
            t0 = time.monotonic()
            m = c.put_map(args.file, map_id=args.map_id, kind=args.kind, confirm=True)
            ready = args.wait > 0
            if ready:
                c.wait_map_ready(m.map_id, args.wait)
            waited = time.monotonic() - t0
            if args.json:
                _print_json({**map_summary(m), "ready": ready, "seconds": round(waited, 3)}, out)
            else:
                how = f"ready in {waited:.1f} s" if ready else "not waiting for ready"
                print(f"stored {_fmt_map(m)}  ({how})", file=out)
        elif args.map_command == "get":
            m = c.get_map(args.map_id)
            if args.json:
                _print_json(m.to_wire(), out)
            else:
                print(_fmt_map(m), file=out)
        else:
            c.get_map(args.map_id)
            c.delete_map(args.map_id)
            print(f"deleted map {args.map_id}", file=out)
    return 0


def _add_configure(p: argparse.ArgumentParser) -> None:
    p.add_argument("robot_id")
    p.add_argument("--map", dest="map_id", required=True, help="id of a stored map")
    p.add_argument("--method", choices=METHODS, default="shape", help="localisation method")
    where = p.add_mutually_exclusive_group(required=True)
    where.add_argument(
        "--initial-pose",
        dest="initial_pose",
        action=PoseAction,
        help="initial pose of the robot base: metres, metres, radians (map frame)",
    )
    where.add_argument(
        "--pose",
        dest="initial_pose",
        action=PoseAction,
        deprecated_for="--initial-pose",
        help=argparse.SUPPRESS,
    )
    where.add_argument(
        "--global",
        dest="global_localization",
        action="store_true",
        help="unknown start pose: global localisation",
    )
    p.add_argument(
        "--laser-offset",
        dest="laser_offset",
        action=PoseAction,
        help="pose of the laser on the robot base, x forward, y left: metres, metres, radians "
        "(default: 0 0 0, the laser at the base's origin facing forward)",
    )
    add_json_option(p, "the configuration sent")


def _run_configure(args: argparse.Namespace, out: TextIO) -> int:
    with connect(args) as c:
        c.health()
        try:
            c.get_map(args.map_id)
        except UnknownMap:
            raise UnknownMap(
                f"the service holds no map {args.map_id!r} (store it with shapeloc map put)"
            ) from None
        pose = None if args.global_localization else args.initial_pose
        msg = c.configure(
            args.robot_id,
            args.map_id,
            args.method,
            pose,
            laser_offset=args.laser_offset,
            confirm=True,
        )
    if args.json:
        _print_json({"robot_id": args.robot_id, **msg.to_wire()}, out)
        return 0
    where = "global localisation" if pose is None else f"initial pose {pose}"
    mount = "" if args.laser_offset is None else f", laser offset {args.laser_offset}"
    print(f"configured {args.robot_id}: map {args.map_id}, {args.method}, {where}{mount}", file=out)
    return 0


def _add_pose(p: argparse.ArgumentParser) -> None:
    p.add_argument("robot_id")
    add_json_option(p, "the pose message")


def _run_pose(args: argparse.Namespace, out: TextIO) -> int:
    with connect(args) as c:
        m = c.get_pose(args.robot_id)
    if args.json:
        _print_json(m.to_wire(), out)
    else:
        print(_fmt_pose(m), file=out)
    return 0


def _add_watch(p: argparse.ArgumentParser) -> None:
    p.add_argument("robot_id", nargs="?", default="*", help="robot id (default: all)")
    p.add_argument("--count", type=int, help="stop after this many poses")
    p.add_argument("--seconds", type=_positive, help="stop after this many seconds")
    add_json_option(p, "each pose message (one JSON object a line)")


def _run_watch(args: argparse.Namespace, out: TextIO) -> int:
    with connect(args) as c:
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
                    if args.json:
                        _print_json(item[1].to_wire(), out)
                    else:
                        print(_fmt_pose(item[1]), file=out, flush=True)
                    n += 1
        finally:
            for sig, handler in old.items():
                signal.signal(sig, handler)
    return 0


def _session_config(args: argparse.Namespace) -> zenoh.Config:
    """The Zenoh configuration the global options name (as :func:`connect` opens it)."""
    return zenoh_config(
        args.mode if args.zenoh_config else (args.mode or "client"),
        connect=args.connect or (),
        config_file=args.zenoh_config,
        default_connect=[DEFAULT_CONNECT],
    )


@contextmanager
def _until_signal() -> Iterator[threading.Event]:
    """An event set by SIGINT / SIGTERM (handlers only in the main thread; restored after)."""
    stop = threading.Event()
    old = {}
    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGINT, signal.SIGTERM):
            old[sig] = signal.signal(sig, lambda *_: stop.set())
    try:
        yield stop
    finally:
        for sig, handler in old.items():
            signal.signal(sig, handler)


def _add_view(p: argparse.ArgumentParser) -> None:
    p.add_argument(
        "--host",
        default=DEFAULT_HOST,
        help="address to serve the page on (another than 127.0.0.1 exposes it to the network, "
        "unauthenticated)",
    )
    p.add_argument("--port", type=int, default=DEFAULT_PORT, help="TCP port (0: any free one)")
    p.add_argument(
        "--frame-rate",
        dest="frame_rate",
        type=float,
        default=DEFAULT_RATE_HZ,
        metavar="HZ",
        help="frames pushed to the page per second",
    )
    p.add_argument(
        "--nice",
        type=int,
        default=DEFAULT_NICE,
        metavar="N",
        help="niceness added to this process, 0-19 (default %(default)s: the view yields the "
        "CPU to the localiser; 0 keeps the priority it was started with)",
    )


def _run_view(args: argparse.Namespace, out: TextIO) -> int:
    from clients.view.server import main as view_main

    if not args.frame_rate >= 1:
        raise ShapelocError(f"--frame-rate must be >= 1, got {args.frame_rate}")
    if not 0 <= args.nice <= 19:
        raise ShapelocError(f"--nice must be in 0..19, got {args.nice}")
    conf = _session_config(args)

    def ready(url: str) -> None:
        print(f"shapeloc view: {url} (Ctrl-C stops)", file=out, flush=True)

    with _until_signal() as stop:
        try:
            return view_main(
                conf,
                host=args.host,
                port=args.port,
                prefix=args.prefix,
                rate_hz=args.frame_rate,
                ready=ready,
                stop=stop,
                nice=args.nice,
            )
        except OSError as exc:
            raise ShapelocError(f"cannot serve the view on {args.host}:{args.port}: {exc}") from exc
        except zenoh.ZError as exc:
            where = ", ".join(config_endpoints(conf)) or "the configured endpoints"
            raise Unreachable(f"cannot reach a zenoh router or service at {where} ({exc})") from exc


def _add_record(p: argparse.ArgumentParser) -> None:
    p.add_argument("file", help="the MCAP file to write (overwritten)")
    p.add_argument(
        "--robot",
        dest="robots",
        action="append",
        default=None,
        metavar="ID",
        help="record only this robot; repeatable (default: every robot)",
    )
    p.add_argument("--seconds", type=_positive, help="stop after this many seconds")
    add_json_option(p, "what was recorded (message counts)")


def _run_record(args: argparse.Namespace, out: TextIO) -> int:
    from clients.record import main as record_main

    conf = _session_config(args)
    with _until_signal() as stop:
        try:
            stats = record_main(
                conf,
                args.file,
                prefix=args.prefix,
                robots=set(args.robots) if args.robots else None,
                duration=args.seconds,
                stop=stop,
                ready=lambda: print(
                    f"recording to {args.file} (Ctrl-C ends it)",
                    file=sys.stderr if args.json else out,
                    flush=True,
                ),
            )
        except OSError as exc:
            raise ShapelocError(f"cannot write {args.file}: {exc}") from exc
        except zenoh.ZError as exc:
            where = ", ".join(config_endpoints(conf)) or "the configured endpoints"
            raise Unreachable(f"cannot reach a zenoh router or service at {where} ({exc})") from exc
    if args.json:
        _print_json(stats.as_dict(), out)
    else:
        print(f"recorded {stats.line()}", file=out)
    return 0


@dataclass(frozen=True)
class Command:
    """One ``shapeloc`` command: its help line, the function adding its options to its
    parser and the function running it (parsed arguments, output stream -> exit code)."""

    help: str
    add_arguments: Callable[[argparse.ArgumentParser], None]
    run: Callable[[argparse.Namespace, TextIO], int]


#: The commands, in ``--help`` order; add one here and it is wired up (its parser takes the
#: global options too).
COMMANDS: dict[str, Command] = {
    "health": Command("service status and counters", _add_health, _run_health),
    "maps": Command("list stored maps", _add_maps, _run_maps),
    "map": Command("store, show, delete, import, build or schematize a map", _add_map, _run_map),
    "configure": Command(
        "configure (and reset) a robot: map, method, initial pose, laser mounting",
        _add_configure,
        _run_configure,
    ),
    "pose": Command("latest pose estimate of a robot", _add_pose, _run_pose),
    "watch": Command("print pose estimates as they arrive (Ctrl-C stops)", _add_watch, _run_watch),
    "view": Command(
        "serve a live view in the browser: maps, poses, paths, statuses, scans, search "
        "candidates (Ctrl-C stops; docs/view.md)",
        _add_view,
        _run_view,
    ),
    "record": Command(
        "record poses, scans, maps and errors into an MCAP file that Foxglove opens "
        "(Ctrl-C ends it; docs/view.md)",
        _add_record,
        _run_record,
    ),
}


def build_parser() -> argparse.ArgumentParser:
    """The ``shapeloc`` argument parser (command in ``args.command``)."""
    p = argparse.ArgumentParser(
        prog="shapeloc",
        description="Talk to a shapeloc localizer service over Zenoh.\n"
        "Global options go before or after the command; every command that prints data takes "
        "--json.",
        formatter_class=HelpFormatter,
    )
    add_global_options(p, GLOBAL_OPTIONS)
    sub = p.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name, command in COMMANDS.items():
        sp = add_command(sub, name, GLOBAL_OPTIONS, help=command.help)
        command.add_arguments(sp)
    return p


def run(args: argparse.Namespace, out: TextIO | None = None) -> int:
    """Execute a parsed command; errors propagate as :class:`ShapelocError`."""
    resolve_client_globals(args, GLOBAL_OPTIONS)
    if getattr(args, "verbose", False):
        logging.basicConfig(level=logging.DEBUG, stream=sys.stderr)
    return COMMANDS[args.command].run(args, out or sys.stdout)


def cli(argv: Sequence[str] | None = None) -> int:
    """Console entry point ``shapeloc``; returns the exit code."""
    args = build_parser().parse_args(argv)
    zenoh.init_log_from_env_or("info" if getattr(args, "verbose", False) else "error")
    try:
        return run(args)
    except ShapelocError as exc:
        print(f"shapeloc: error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        return 130


if __name__ == "__main__":
    sys.exit(cli())
