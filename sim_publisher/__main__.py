"""``python -m sim_publisher`` / ``shapeloc-sim``: the simulator's command line.

Subcommands (one entry each in :data:`COMMANDS`):

* ``run`` (also what ``shapeloc-sim`` without a subcommand means, so ``shapeloc-sim --connect
  ... --robots 2`` keeps working): drive simulated robots and publish over Zenoh. Puts the
  maps, configures every robot, then publishes per robot and tick a scan on
  ``<prefix>/robots/<id>/scan`` and the ground truth on ``<prefix>/robots/<id>/truth``
  (msgpack, wire contract v1) until ``--scans`` / ``--duration`` is reached or SIGINT/SIGTERM
  arrives. :func:`main` is the same from Python.
* ``experiment``: the paper's section-6 experiment, in process (no Zenoh);
  :mod:`sim_publisher.experiment`.
"""

from __future__ import annotations

import argparse
import logging
import math
import signal
import sys
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import zenoh

from clients.client import (
    DEFAULT_PREFIX,
    ShapelocClient,
    Stream,
    config_endpoints,
    open_session,
    zenoh_config,
)
from schemas import keys
from schemas.codec import MSGPACK_ENCODING, encode
from schemas.messages import METHODS, PoseMsg
from service.errors import ServiceTimeout, ShapelocError
from sim_publisher import experiment, replay
from sim_publisher.publisher import SimFleet, fleet_specs

log = logging.getLogger("shapeloc.sim")


@dataclass
class SimOptions:
    """Options of one simulator run (see ``--help`` for their meaning; rates in Hz, s)."""

    robots: int = 1
    maps: list[str] = field(default_factory=lambda: ["metric"])
    methods: list[str] = field(default_factory=lambda: ["shape"])
    setup: int | None = None
    step_mm: float | None = None
    starts: list[float] | None = None
    seed: int = 0
    id_prefix: str = "sim-"
    global_localization: bool = False
    odom: bool = True
    rate: float = 10.0
    max_rate: bool = False
    scans: int | None = None
    duration: float | None = None
    prefix: str = DEFAULT_PREFIX
    wait_service: float = 30.0
    configure: bool = True
    put_maps: bool = True
    lockstep: bool = False
    lockstep_timeout: float = 30.0
    kidnap_at: int | None = None
    kidnap_to: float | None = None
    kidnap_robots: int = 1
    look_around: int = 0
    look_turn_deg: float = 90.0


def main(
    conf: zenoh.Config,
    options: SimOptions,
    stop: threading.Event | None = None,
    endpoints: Sequence[str] = (),
) -> int:
    """Run the simulator on a Zenoh session opened from ``conf``; returns the exit code.

    ``stop`` (set from a signal handler or another thread) ends the run after the current tick.
    """
    stop = stop or threading.Event()
    fleet = SimFleet.from_specs(
        fleet_specs(
            options.robots,
            options.maps,
            options.methods,
            setup=options.setup,
            step_mm=options.step_mm,
            seed=options.seed,
            starts=options.starts,
            id_prefix=options.id_prefix,
            kidnap_at=options.kidnap_at,
            kidnap_to=options.kidnap_to,
            kidnap_robots=options.kidnap_robots,
        ),
        global_localization=options.global_localization,
        send_odom=options.odom,
        look_around=options.look_around,
        look_turn=math.radians(options.look_turn_deg),
    )
    with open_session(conf, endpoints) as session:
        client = ShapelocClient(session=session, prefix=options.prefix, timeout=2.0)
        try:
            up = options.wait_service > 0 and _wait_service(client, options.wait_service, stop)
            if options.put_maps and not stop.is_set():
                for m in fleet.map_messages():
                    try:
                        client.put_map(m, confirm=up)
                    except ServiceTimeout:
                        log.warning("map %s was put but not confirmed by the service", m.map_id)
                    log.info("map %s (%s, %d polylines)", m.map_id, m.kind, len(m.polylines))
            if options.configure and not stop.is_set():
                for r in fleet.robots:
                    client.configure(r.robot_id, r.map_id, r.method, r.config().initial_pose)
                    log.info("robot %s: map %s, method %s", r.robot_id, r.map_id, r.method)
                for r in fleet.robots if up else []:
                    if stop.is_set():
                        break
                    try:
                        client.wait_configured(r.robot_id, options.wait_service)
                    except ServiceTimeout as exc:
                        log.warning("%s; publishing anyway", exc)
            poses = None
            if options.lockstep and up:
                poses = client.watch_poses([r.robot_id for r in fleet.robots])
            elif options.lockstep:
                log.warning("lockstep needs a service that answers (see --wait-service); off")
            return _publish_loop(session, fleet, options, stop, poses)
        finally:
            client.close()


def _wait_service(client: ShapelocClient, within: float, stop: threading.Event) -> bool:
    """Poll the service's health for up to ``within`` s (or until ``stop``); True if it is up."""
    end = time.monotonic() + within
    while not stop.is_set():
        try:
            h = client.health()
            log.info("service %s up: %d maps, %d robots", h.version, h.maps, h.robots)
            return True
        except ServiceTimeout:
            if time.monotonic() >= end:
                log.warning("no shapeloc service answered within %.1f s; publishing anyway", within)
                return False
            stop.wait(0.1)
    return False


def _wait_answers(
    poses: Stream[PoseMsg], seq: int, ids: set[str], within: float, stop: threading.Event
) -> None:
    """Lockstep: block until every robot in ``ids`` has a pose for scan ``seq`` (or later),
    ``within`` seconds pass, or ``stop`` is set."""
    end = time.monotonic() + within
    missing = set(ids)
    while missing and not stop.is_set():
        left = end - time.monotonic()
        if left <= 0:
            log.warning(
                "lockstep: no pose for scan %d of %s within %.1f s; going on",
                seq,
                ", ".join(sorted(missing)),
                within,
            )
            return
        item = poses.get(timeout=min(left, 0.2))
        if item is not None and item[1].seq >= seq:
            missing.discard(item[1].robot_id)


def _publish_loop(
    session: zenoh.Session,
    fleet: SimFleet,
    options: SimOptions,
    stop: threading.Event,
    poses: Stream[PoseMsg] | None = None,
) -> int:
    enc = zenoh.Encoding(MSGPACK_ENCODING)
    block = zenoh.CongestionControl.BLOCK
    # Scans may be dropped under congestion like a real sensor's, except in lockstep (a lost
    # scan would stall it); ground truth is never dropped (it is what results are scored on).
    scan_cc = block if poses is not None else zenoh.CongestionControl.DROP
    pubs = []
    for r in fleet.robots:
        scan_pub = session.declare_publisher(
            keys.robot_key(options.prefix, r.robot_id, "scan"),
            encoding=enc,
            congestion_control=scan_cc,
        )
        truth_pub = session.declare_publisher(
            keys.robot_key(options.prefix, r.robot_id, "truth"),
            encoding=enc,
            congestion_control=block,
        )
        pubs.append((r, scan_pub, truth_pub))
    period = 0.0 if options.max_rate else 1.0 / options.rate
    t0 = time.monotonic()
    next_tick = t0
    last_report = t0
    sent = 0
    try:
        while not stop.is_set():
            now = time.monotonic()
            if options.duration is not None and now - t0 >= options.duration:
                break
            if options.scans is not None and sent >= options.scans:
                break
            stamp = time.time()
            for r, scan_pub, truth_pub in pubs:
                scan, truth = r.step(stamp)
                truth_pub.put(encode(truth))
                scan_pub.put(encode(scan, ranges_as_bytes=True))
            if poses is not None:
                ids = {r.robot_id for r in fleet.robots}
                _wait_answers(poses, sent, ids, options.lockstep_timeout, stop)
            sent += 1
            if now - last_report >= 5.0:
                log.info("%d scans per robot published (%.1f Hz)", sent, sent / (now - t0))
                last_report = now
            if period > 0:
                next_tick += period
                delay = next_tick - time.monotonic()
                if delay > 0:
                    stop.wait(delay)
                else:
                    next_tick = time.monotonic()  # fell behind: do not burst to catch up
    finally:
        for _, a, b in pubs:
            a.undeclare()
            b.undeclare()
    el = max(time.monotonic() - t0, 1e-9)
    log.info("done: %d scans per robot in %.1f s (%.1f Hz)", sent, el, sent / el)
    return 0


def _csv(text: str) -> list[str]:
    return [t.strip() for t in text.split(",") if t.strip()]


def add_run_arguments(p: argparse.ArgumentParser) -> None:
    """The options of ``shapeloc-sim run`` (see :func:`options_from_args`)."""
    p.add_argument("--robots", type=int, default=1, help="number of robots (ids sim-0..N-1)")
    p.add_argument(
        "--map",
        type=_csv,
        default=["metric"],
        help="metric | schematic | a map/world file; a comma list cycles over the robots",
    )
    p.add_argument(
        "--method",
        type=_csv,
        default=["shape"],
        help=f"{' | '.join(METHODS)}; a comma list cycles over the robots",
    )
    g = p.add_mutually_exclusive_group()
    g.add_argument("--setup", type=int, choices=(1, 2), help="tour sampling (default per map)")
    g.add_argument("--step-mm", type=float, help="tour sampling step in mm instead of a setup")
    p.add_argument(
        "--starts",
        type=lambda s: [float(v) for v in _csv(s)],
        help="start of each robot as a fraction of the tour (default k/N)",
    )
    p.add_argument("--seed", type=int, default=0, help="base seed; robot k uses seed+k")
    p.add_argument("--id-prefix", default="sim-", help="robot id prefix")
    p.add_argument(
        "--global",
        dest="global_localization",
        action="store_true",
        help="configure robots with initial_pose null (global localisation)",
    )
    p.add_argument("--no-odom", dest="odom", action="store_false", help="omit odometry")
    p.add_argument("--rate", type=float, default=10.0, help="scans per second per robot")
    p.add_argument("--max-rate", action="store_true", help="publish as fast as possible")
    p.add_argument(
        "--lockstep",
        action="store_true",
        help="send the next scan only once every robot's pose for the last one arrived "
        "(no scan is skipped; results match an in-process run)",
    )
    p.add_argument(
        "--kidnap-at",
        type=int,
        help="kidnapped robot: at this scan seq the truth jumps to --kidnap-to (the localiser "
        "is not told)",
    )
    p.add_argument(
        "--kidnap-to",
        type=float,
        help="where the kidnapped robot is put: a fraction of the tour in [0, 1]",
    )
    p.add_argument(
        "--kidnap-robots",
        type=int,
        default=1,
        help="how many robots (sim-0, sim-1, ...) are kidnapped (default 1: sim-0)",
    )
    p.add_argument(
        "--look-around",
        type=int,
        default=0,
        metavar="N",
        help="look-around start: every robot first takes N scans turning in place at its start "
        "(--look-turn-deg between scans) and then drives; use with --global so the localiser "
        "sees the whole room (a 180-degree laser: 3 scans 90 degrees apart). Default 0: off",
    )
    p.add_argument(
        "--look-turn-deg",
        type=float,
        default=90.0,
        metavar="DEG",
        help="turn between look-around scans in degrees, counter-clockwise positive (default 90)",
    )
    p.add_argument("--scans", type=int, help="stop after this many scans per robot")
    p.add_argument("--duration", type=float, help="stop after this many seconds")
    p.add_argument(
        "--wait-service",
        type=float,
        default=30.0,
        help="seconds to wait for the service's health before publishing (0: don't)",
    )
    p.add_argument(
        "--no-configure",
        dest="configure",
        action="store_false",
        help="do not put the robots' configurations",
    )
    p.add_argument("--no-maps", dest="put_maps", action="store_false", help="do not put the maps")
    p.add_argument("--prefix", default=DEFAULT_PREFIX, help="key prefix")
    add_zenoh_arguments(p)
    p.add_argument("-v", "--verbose", action="store_true", help="debug logging")


DEFAULT_CONNECT = "tcp/127.0.0.1:7447"


def add_zenoh_arguments(p: argparse.ArgumentParser) -> None:
    """The Zenoh options every networked subcommand shares: ``--mode``, ``--connect``,
    ``--listen`` and ``--zenoh-config`` (read back with :func:`zenoh_config_from_args`)."""
    p.add_argument(
        "--mode",
        choices=("client", "peer", "router"),
        default=None,
        help="Zenoh mode (default client, or the --zenoh-config file's)",
    )
    p.add_argument(
        "--connect",
        action="append",
        default=None,
        help=f"endpoint to connect to (repeatable; default {DEFAULT_CONNECT} in client mode)",
    )
    p.add_argument("--listen", action="append", default=None, help="endpoint to listen on")
    p.add_argument(
        "--zenoh-config",
        dest="zenoh_config",
        metavar="FILE",
        default=None,
        help="Zenoh JSON5 config (TLS, mTLS, user/password) as the base; --mode, --connect "
        "and --listen replace its values",
    )


def zenoh_config_from_args(args: argparse.Namespace) -> tuple[zenoh.Config, list[str]]:
    """The session config of :func:`add_zenoh_arguments`' options and the connect endpoints
    (for messages). Raises :class:`~service.errors.InvalidMessage` for an unreadable file."""
    conf = zenoh_config(
        args.mode,
        connect=args.connect or (),
        listen=args.listen or (),
        config_file=getattr(args, "zenoh_config", None),
        default_connect=[DEFAULT_CONNECT],
    )
    return conf, config_endpoints(conf, "connect")


def options_from_args(args: argparse.Namespace) -> SimOptions:
    """Validate parsed arguments into :class:`SimOptions` (raises ``ValueError``)."""
    if args.robots < 1:
        raise ValueError("--robots must be >= 1")
    if args.rate <= 0:
        raise ValueError("--rate must be > 0")
    if args.scans is not None and args.scans < 0:
        raise ValueError("--scans must be >= 0")
    if args.duration is not None and args.duration < 0:
        raise ValueError("--duration must be >= 0")
    if (args.kidnap_at is None) != (args.kidnap_to is None):
        raise ValueError("--kidnap-at and --kidnap-to go together")
    if args.kidnap_at is not None and args.kidnap_at < 0:
        raise ValueError("--kidnap-at must be >= 0")
    if args.kidnap_to is not None and not 0.0 <= args.kidnap_to <= 1.0:
        raise ValueError("--kidnap-to must be in [0, 1]")
    if args.kidnap_robots < 0:
        raise ValueError("--kidnap-robots must be >= 0")
    if args.look_around < 0:
        raise ValueError("--look-around must be >= 0")
    if not math.isfinite(args.look_turn_deg):
        raise ValueError("--look-turn-deg must be a finite number")
    bad = [m for m in args.method if m not in METHODS]
    if bad:
        raise ValueError(f"unknown method {bad[0]!r}; expected one of {', '.join(METHODS)}")
    return SimOptions(
        robots=args.robots,
        maps=args.map,
        methods=args.method,
        setup=args.setup,
        step_mm=args.step_mm,
        starts=args.starts,
        seed=args.seed,
        id_prefix=args.id_prefix,
        global_localization=args.global_localization,
        odom=args.odom,
        rate=args.rate,
        max_rate=args.max_rate,
        scans=args.scans,
        duration=args.duration,
        prefix=args.prefix,
        wait_service=args.wait_service,
        configure=args.configure,
        put_maps=args.put_maps,
        lockstep=args.lockstep,
        kidnap_at=args.kidnap_at,
        kidnap_to=args.kidnap_to,
        kidnap_robots=args.kidnap_robots,
        look_around=args.look_around,
        look_turn_deg=args.look_turn_deg,
    )


def run_until_signal(
    args: argparse.Namespace,
    prog: str,
    parse: Callable[[argparse.Namespace], Any],
    body: Callable[[zenoh.Config, Any, threading.Event, list[str]], int],
) -> int:
    """What every networked subcommand does around its ``body``: logging, ``parse`` the
    options (``ValueError`` -> exit 2), the Zenoh config (:func:`zenoh_config_from_args`),
    SIGINT/SIGTERM set the ``stop`` event, errors print ``prog: error: ...`` (exit 1)."""
    logging.basicConfig(
        level=logging.DEBUG if args.verbose else logging.INFO,
        format="%(asctime)s %(name)s %(levelname)s %(message)s",
        stream=sys.stderr,
    )
    zenoh.init_log_from_env_or("error")
    try:
        options = parse(args)
    except ValueError as exc:
        print(f"{prog}: error: {exc}", file=sys.stderr)
        return 2
    try:
        conf, endpoints = zenoh_config_from_args(args)
    except ShapelocError as exc:
        print(f"{prog}: error: {exc}", file=sys.stderr)
        return 2
    stop = threading.Event()

    def on_signal(signum: int, _frame: object) -> None:
        log.info("signal %d: stopping", signum)
        stop.set()

    old = {sig: signal.signal(sig, on_signal) for sig in (signal.SIGINT, signal.SIGTERM)}
    try:
        return body(conf, options, stop, endpoints)
    except (ShapelocError, ValueError) as exc:
        print(f"{prog}: error: {exc}", file=sys.stderr)
        return 1
    finally:
        for sig, handler in old.items():
            signal.signal(sig, handler)


def cli_run(args: argparse.Namespace) -> int:
    """``shapeloc-sim run``: validate the options, open the session, run until done or a
    signal (SIGINT/SIGTERM stop after the current tick)."""
    return run_until_signal(args, "shapeloc-sim", options_from_args, main)


@dataclass(frozen=True)
class Command:
    """One ``shapeloc-sim`` subcommand: its help line, the function adding its options to its
    subparser and the function running it on the parsed arguments (returns the exit code)."""

    help: str
    add_arguments: Callable[[argparse.ArgumentParser], None]
    run: Callable[[argparse.Namespace], int]


#: The subcommands, in ``--help`` order; add one here (e.g. ``replay``) and it is wired up.
COMMANDS: dict[str, Command] = {
    "run": Command(
        "drive simulated robots along the office tour and publish their scans and ground "
        "truth over Zenoh (the default when no subcommand is given)",
        add_run_arguments,
        cli_run,
    ),
    "experiment": Command(
        "the paper's section-6 experiment (Table 1), in process, no Zenoh",
        experiment.add_arguments,
        experiment.run,
    ),
    "replay": Command(
        "publish a recorded laser log (ROS bag or CARMEN) over Zenoh as a robot would, with "
        "its reference poses on the truth key",
        replay.add_arguments,
        replay.run,
    ),
}
#: What ``shapeloc-sim`` runs when its first argument is not a subcommand.
DEFAULT_COMMAND = "run"


class _Parser(argparse.ArgumentParser):
    """The top-level parser: arguments not starting with a subcommand (or ``-h``) are parsed
    as :data:`DEFAULT_COMMAND`'s, so ``shapeloc-sim --robots 2`` means
    ``shapeloc-sim run --robots 2``; its help ends with the default command's options."""

    default_parser: argparse.ArgumentParser | None = None

    def format_help(self) -> str:
        text = super().format_help()
        if self.default_parser is not None:
            text += (
                f"\nWithout a COMMAND the options are those of {DEFAULT_COMMAND!r}:\n\n"
                + self.default_parser.format_help()
            )
        return text

    def parse_known_args(
        self, args: Sequence[str] | None = None, namespace: argparse.Namespace | None = None
    ) -> tuple[argparse.Namespace, list[str]]:
        argv = list(sys.argv[1:] if args is None else args)
        if not argv or (argv[0] not in COMMANDS and argv[0] not in ("-h", "--help")):
            argv.insert(0, DEFAULT_COMMAND)
        return super().parse_known_args(argv, namespace)


def build_parser() -> argparse.ArgumentParser:
    """The simulator's command line: ``shapeloc-sim [COMMAND] ...`` (``run`` by default)."""
    p = _Parser(
        prog="shapeloc-sim",
        description="The shapeloc simulator: simulated robots publishing to a shapeloc service "
        f"over Zenoh, and the paper's experiment. Without a COMMAND, {DEFAULT_COMMAND!r} is "
        "meant.",
    )
    sub = p.add_subparsers(
        dest="command", metavar="COMMAND", required=True, parser_class=argparse.ArgumentParser
    )
    for name, command in COMMANDS.items():
        sp = sub.add_parser(name, help=command.help, description=command.help)
        command.add_arguments(sp)
        if name == DEFAULT_COMMAND:
            p.default_parser = sp
    return p


def cli(argv: Sequence[str] | None = None) -> int:
    """Console entry point ``shapeloc-sim``; returns the exit code."""
    args = build_parser().parse_args(argv)
    return COMMANDS[args.command].run(args)


if __name__ == "__main__":
    sys.exit(cli())
