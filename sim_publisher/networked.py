"""What every networked ``shapeloc-sim`` command (``run``, ``replay``) does around its loop.

Both :mod:`sim_publisher.__main__` (``run``) and :mod:`sim_publisher.replay` import this
module, and it imports neither, so the two do not import each other:

* :data:`GLOBAL_OPTIONS`: the simulator's global options (:mod:`schemas.cli`: it may listen
  and queries the service);
* :func:`zenoh_config_from_args`: the Zenoh session configuration of those options;
* :func:`wait_service`: poll the service's health until it answers;
* :func:`configure_robots`: put robot configurations and wait until the service took each,
  raising the service's own reason when it refused one;
* :func:`wait_answers`: the lockstep wait for every robot's pose of one scan;
* :func:`run_until_signal`: logging, option validation, signals and exit codes around a
  command's body.
"""

from __future__ import annotations

import argparse
import logging
import signal
import sys
import threading
import time
from collections.abc import Callable, Sequence
from typing import Any

import zenoh

from clients.client import ShapelocClient, Stream, config_endpoints, zenoh_config
from schemas import keys
from schemas.cli import DEFAULT_CONNECT, GlobalOptions, resolve_client_globals
from schemas.messages import PoseMsg, RobotConfig
from service.errors import RemoteError, ServiceTimeout, ShapelocError, UnknownRobot

log = logging.getLogger("shapeloc.sim")

#: The simulator's global options (schemas.cli): it may listen, and it queries the service.
GLOBAL_OPTIONS = GlobalOptions(listen=True, timeout=True)
#: Seconds to wait, once every robot is known, for a late rejection of a re-configuration.
CONFIG_GRACE_S = 0.3


def zenoh_config_from_args(args: argparse.Namespace) -> tuple[zenoh.Config, list[str]]:
    """The session config of the global options (``--mode``, ``--connect``, ``--listen``,
    ``--zenoh-config``) and the connect endpoints (for messages). Raises
    :class:`~service.errors.InvalidMessage` for an unreadable file."""
    conf = zenoh_config(
        args.mode,
        connect=args.connect or (),
        listen=args.listen or (),
        config_file=getattr(args, "zenoh_config", None),
        default_connect=[DEFAULT_CONNECT],
    )
    return conf, config_endpoints(conf, "connect")


def wait_service(client: ShapelocClient, within: float, stop: threading.Event) -> bool:
    """Poll the service's health for up to ``within`` s (or until ``stop``); True if it is up."""
    end = time.monotonic() + within
    while not stop.is_set():
        try:
            h = client.health()
            log.info("service %s up: %d maps, %d robots", h.version, h.maps, h.robots)
            return True
        except ServiceTimeout:
            if time.monotonic() >= end:
                log.warning("no shapeloc service answered within %.1f s", within)
                return False
            stop.wait(0.1)
    return False


def configure_robots(
    client: ShapelocClient,
    configs: Sequence[tuple[str, RobotConfig]],
    within: float,
    stop: threading.Event | None = None,
) -> None:
    """Put each ``(robot_id, config)`` and wait until the service knows every robot.

    Raises :class:`RemoteError` with the service's reason (its notice on ``<prefix>/errors``,
    e.g. ``UnknownMap: ...``) as soon as it refuses one, and :class:`ServiceTimeout` when a
    robot is still unknown after ``within`` seconds. A refusal of a re-configuration (the
    robot was already known) is seen if it arrives within :data:`CONFIG_GRACE_S` after the
    last robot became known.
    """
    stop = stop or threading.Event()
    by_key = {keys.robot_key(client.prefix, rid, "config"): rid for rid, _ in configs}
    with client.watch_errors() as notices:
        for rid, cfg in configs:
            client.configure(
                rid,
                cfg.map_id,
                cfg.method,
                cfg.initial_pose,
                laser_offset=cfg.laser_offset if cfg.laser_offset.any() else None,
            )
        pending = [rid for rid, _ in configs]
        end = time.monotonic() + within
        known_at: float | None = None
        while not stop.is_set():
            for key, notice in notices.drain():
                if notice.key in by_key:
                    raise RemoteError(
                        f"the service refused the configuration of robot {by_key[notice.key]!r}: "
                        f"{notice.error}"
                    )
                log.debug("notice on %s: %s", key, notice.error)
            for rid in list(pending):
                try:
                    client.get_pose(rid)
                    pending.remove(rid)
                except RemoteError:
                    pending.remove(rid)  # known, e.g. "has no estimate yet"
                except (UnknownRobot, ServiceTimeout):
                    pass
            now = time.monotonic()
            if not pending:
                known_at = known_at or now
                if now - known_at >= CONFIG_GRACE_S:
                    return
            elif now >= end:
                raise ServiceTimeout(
                    f"the service did not take the configuration of {', '.join(pending)} "
                    f"within {within:g} s"
                )
            stop.wait(0.05)


def wait_answers(
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


def run_until_signal(
    args: argparse.Namespace,
    prog: str,
    parse: Callable[[argparse.Namespace], Any],
    body: Callable[[zenoh.Config, Any, threading.Event, list[str]], int],
) -> int:
    """What every networked command does around its ``body``: the global options (from the
    configuration file where the command line is silent, :func:`resolve_client_globals`),
    logging, ``parse`` the options (``ValueError`` -> exit 2), the Zenoh config
    (:func:`zenoh_config_from_args`), SIGINT/SIGTERM set the ``stop`` event, errors print
    ``prog: error: ...`` (exit 1)."""
    logging.basicConfig(
        level=logging.DEBUG if getattr(args, "verbose", False) else logging.INFO,
        format="%(asctime)s %(name)s %(levelname)s %(message)s",
        stream=sys.stderr,
    )
    zenoh.init_log_from_env_or("error")
    try:
        resolve_client_globals(args, GLOBAL_OPTIONS)
        options = parse(args)
        conf, endpoints = zenoh_config_from_args(args)
    except (ShapelocError, ValueError) as exc:
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
