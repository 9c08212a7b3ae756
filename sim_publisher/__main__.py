"""``python -m sim_publisher`` / ``shapeloc-sim``: the simulator's command line.

Commands (one entry each in :data:`COMMANDS`):

* ``run``: drive simulated robots and publish over Zenoh. Puts the maps, configures every
  robot, then publishes per robot and tick a scan on ``<prefix>/robots/<id>/scan`` and the
  ground truth on ``<prefix>/robots/<id>/truth`` (msgpack, wire contract v1) at ``--rate`` Hz
  until ``--scans`` / ``--duration`` is reached or SIGINT/SIGTERM arrives. A configuration
  the service refuses ends the run with its reason (exit 1). :func:`main` is the same from
  Python.
* ``replay``: publish a recorded laser log as a robot would (:mod:`sim_publisher.replay`).
* ``experiment``: the paper's section-6 experiment, in process (no Zenoh);
  :mod:`sim_publisher.experiment`.

It follows the convention of every shapeloc program (:mod:`schemas.cli`): the global options
(``--connect``, ``--listen``, ``--mode``, ``--zenoh-config``, ``--prefix``, ``--config``,
``--timeout``, ``-v``) go before or after the command, ``--rate`` is scans per second, a pose
is ``X Y THETA``, help shows the defaults. ``shapeloc-sim`` without a command still means
``run`` for one release, with a deprecation warning.
"""

from __future__ import annotations

import argparse
import logging
import math
import sys
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field

import zenoh

from clients.client import ShapelocClient, Stream, open_session
from schemas import keys
from schemas.cli import (
    DEFAULT_PREFIX,
    HelpFormatter,
    PoseAction,
    add_command,
    add_global_options,
    resolve_client_globals,
    warn_deprecated,
)
from schemas.codec import MSGPACK_ENCODING, encode
from schemas.messages import METHODS, PoseMsg
from service.errors import ServiceTimeout
from sim_publisher import experiment, replay
from sim_publisher.networked import (
    GLOBAL_OPTIONS,
    configure_robots,
    run_until_signal,
    wait_answers,
    wait_service,
    zenoh_config_from_args,
)
from sim_publisher.publisher import SimFleet, fleet_specs

__all__ = [
    "COMMANDS",
    "DEFAULT_COMMAND",
    "Command",
    "SimOptions",
    "add_run_arguments",
    "build_parser",
    "cli",
    "cli_run",
    "main",
    "options_from_args",
    "run_until_signal",
    "zenoh_config_from_args",
]

log = logging.getLogger("shapeloc.sim")

#: Older name of :func:`sim_publisher.networked.wait_service`, kept for callers not yet moved.
_wait_service = wait_service


@dataclass
class SimOptions:
    """Options of one simulator run (see ``--help`` for their meaning; rates in Hz, s).

    ``laser_offset``: the laser's pose ``[x, y, theta]`` on every robot's base (m, rad;
    ``None``: at its origin); ``timeout``: seconds a request to the service may take."""

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
    laser_offset: list[float] | None = None
    timeout: float = 2.0
    #: Publish as ROS 2 robots on rmw_zenoh's keys (sim_publisher/ros2.py, docs/ros2.md).
    ros2: bool = False
    ros2_config: str = "shapeloc"


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
    if options.ros2:
        from sim_publisher import ros2

        ros = ros2.default_options(config_source=options.ros2_config)
        return ros2.run_fleet(conf, options, stop, endpoints, ros)
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
        laser_offset=options.laser_offset,
    )
    with open_session(conf, endpoints) as session:
        client = ShapelocClient(session=session, prefix=options.prefix, timeout=options.timeout)
        try:
            up = options.wait_service > 0 and wait_service(client, options.wait_service, stop)
            if options.wait_service > 0 and not up and not stop.is_set():
                log.warning("publishing anyway")
            if options.put_maps and not stop.is_set():
                for m in fleet.map_messages():
                    try:
                        client.put_map(m, confirm=up)
                    except ServiceTimeout:
                        log.warning("map %s was put but not confirmed by the service", m.map_id)
                    log.info("map %s (%s, %d polylines)", m.map_id, m.kind, len(m.polylines))
            if options.configure and not stop.is_set():
                configs = [(r.robot_id, r.config()) for r in fleet.robots]
                if up:  # a refusal (its reason from the service) ends the run: exit 1
                    try:
                        configure_robots(client, configs, options.wait_service, stop)
                    except ServiceTimeout as exc:
                        log.warning("%s; publishing anyway", exc)
                else:
                    for rid, cfg in configs:
                        client.configure(
                            rid,
                            cfg.map_id,
                            cfg.method,
                            cfg.initial_pose,
                            laser_offset=options.laser_offset,
                        )
                for r in fleet.robots:
                    log.info("robot %s: map %s, method %s", r.robot_id, r.map_id, r.method)
            poses = None
            if options.lockstep and up:
                poses = client.watch_poses([r.robot_id for r in fleet.robots])
            elif options.lockstep:
                log.warning("lockstep needs a service that answers (see --wait-service); off")
            return _publish_loop(session, fleet, options, stop, poses)
        finally:
            client.close()


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
                wait_answers(poses, sent, ids, options.lockstep_timeout, stop)
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
    p.add_argument(
        "--rate", type=float, default=10.0, metavar="HZ", help="scans per second per robot"
    )
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
        help="how many robots (sim-0, sim-1, ...) are kidnapped (default: 1, sim-0)",
    )
    p.add_argument(
        "--look-around",
        type=int,
        default=0,
        metavar="N",
        help="look-around start: every robot first takes N scans turning in place at its start "
        "(--look-turn-deg between scans) and then drives; use with --global so the localiser "
        "sees the whole room (a 180-degree laser: 3 scans 90 degrees apart); 0: off",
    )
    p.add_argument(
        "--look-turn-deg",
        type=float,
        default=90.0,
        metavar="DEG",
        help="turn between look-around scans in degrees, counter-clockwise positive",
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
    p.add_argument(
        "--laser-offset",
        dest="laser_offset",
        action=PoseAction,
        help="pose of the laser on every robot's base, x forward, y left: metres, metres, "
        "radians; scans are taken from there, truth and odometry stay the base's, and the "
        "configuration tells the service (default: 0 0 0, the laser at the base's origin)",
    )
    p.add_argument(
        "--ros2",
        action="store_true",
        help="publish as ROS 2 robots on rmw_zenoh's keys, namespace /<id> with - -> _ "
        "(scan, tf, tf_static; answers on amcl_pose; docs/ros2.md); the laser sits "
        "--laser-offset (default 0.1 0 0) on base_link",
    )
    p.add_argument(
        "--ros2-config",
        choices=("shapeloc", "ros"),
        default="shapeloc",
        help="with --ros2: map and initial pose through shapeloc, or over ROS "
        "(/<ns>/map, /<ns>/initialpose)",
    )


def options_from_args(args: argparse.Namespace) -> SimOptions:
    """Validate parsed arguments into :class:`SimOptions` (raises ``ValueError``); global
    options not given are read from the configuration file or take their defaults
    (:func:`schemas.cli.resolve_client_globals`)."""
    resolve_client_globals(args, GLOBAL_OPTIONS)
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
    if args.timeout <= 0:
        raise ValueError("--timeout must be > 0")
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
        laser_offset=args.laser_offset,
        timeout=args.timeout,
        ros2=args.ros2,
        ros2_config=args.ros2_config,
    )


def cli_run(args: argparse.Namespace) -> int:
    """``shapeloc-sim run``: validate the options, open the session, run until done or a
    signal (SIGINT/SIGTERM stop after the current tick)."""
    return run_until_signal(args, "shapeloc-sim run", options_from_args, main)


@dataclass(frozen=True)
class Command:
    """One ``shapeloc-sim`` command: its help line, the function adding its options to its
    parser, the function running it on the parsed arguments (returns the exit code), and
    whether it talks to a service (its parser then takes the global options too)."""

    help: str
    add_arguments: Callable[[argparse.ArgumentParser], None]
    run: Callable[[argparse.Namespace], int]
    networked: bool = True


#: The commands, in ``--help`` order; add one here and it is wired up.
COMMANDS: dict[str, Command] = {
    "run": Command(
        "drive simulated robots along the office tour and publish their scans and ground "
        "truth over Zenoh",
        add_run_arguments,
        cli_run,
    ),
    "replay": Command(
        "publish a recorded laser log (ROS bag or CARMEN) over Zenoh as a robot would, with "
        "its reference poses on the truth key, and print the accuracy against them",
        replay.add_arguments,
        replay.run,
    ),
    "experiment": Command(
        "the paper's section-6 experiment (Table 1), in process, no Zenoh",
        experiment.add_arguments,
        experiment.run,
        networked=False,
    ),
}
#: What ``shapeloc-sim`` without a command runs (deprecated: name the command).
DEFAULT_COMMAND = "run"
#: The global options that take a value (schemas.cli), skipped when looking for the command.
_VALUE_OPTIONS = frozenset(
    {"--connect", "--listen", "--mode", "--zenoh-config", "--prefix", "--config", "--timeout"}
)


def command_index(argv: Sequence[str]) -> int:
    """Where the command should be in ``argv``: the index of the first token that is not a
    global option (or its value); ``len(argv)`` when there is none."""
    i = 0
    while i < len(argv):
        tok = argv[i]
        if tok in _VALUE_OPTIONS:
            i += 2
        elif tok.split("=", 1)[0] in _VALUE_OPTIONS or tok in ("-v", "--verbose"):
            i += 1
        else:
            return i
    return len(argv)


class _Parser(argparse.ArgumentParser):
    """The top-level parser. Without a command (``shapeloc-sim --robots 2``) it parses the
    arguments as :data:`DEFAULT_COMMAND`'s, as before, and warns that this is deprecated."""

    def parse_known_args(
        self, args: Sequence[str] | None = None, namespace: argparse.Namespace | None = None
    ) -> tuple[argparse.Namespace, list[str]]:
        argv = list(sys.argv[1:] if args is None else args)
        i = command_index(argv)
        if i == len(argv) or (argv[i] not in COMMANDS and argv[i] not in ("-h", "--help")):
            warn_deprecated(
                self.prog, f"{self.prog} without a command", f"{self.prog} {DEFAULT_COMMAND} ..."
            )
            argv.insert(i, DEFAULT_COMMAND)
        return super().parse_known_args(argv, namespace)


def build_parser() -> argparse.ArgumentParser:
    """The simulator's command line: ``shapeloc-sim [GLOBAL OPTIONS] COMMAND ...``."""
    p = _Parser(
        prog="shapeloc-sim",
        description="The shapeloc simulator: simulated robots and recorded logs publishing to "
        "a shapeloc service over Zenoh, and the paper's experiment.\n"
        "Global options go before or after the command.",
        formatter_class=HelpFormatter,
    )
    add_global_options(p, GLOBAL_OPTIONS)
    sub = p.add_subparsers(
        dest="command", metavar="COMMAND", required=True, parser_class=argparse.ArgumentParser
    )
    for name, command in COMMANDS.items():
        if command.networked:
            sp = add_command(sub, name, GLOBAL_OPTIONS, help=command.help)
        else:
            sp = sub.add_parser(
                name, help=command.help, description=command.help, formatter_class=HelpFormatter
            )
        command.add_arguments(sp)
    return p


def cli(argv: Sequence[str] | None = None) -> int:
    """Console entry point ``shapeloc-sim``; returns the exit code."""
    args = build_parser().parse_args(argv)
    return COMMANDS[args.command].run(args)


if __name__ == "__main__":
    sys.exit(cli())
