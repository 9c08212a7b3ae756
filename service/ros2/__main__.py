"""``python -m service.ros2``: the ROS 2 front as its own process next to a service.

Connects to the Zenoh network of the service and the robots (``--connect``, client mode by
default) and translates until SIGINT/SIGTERM (see :mod:`service.ros2.front`).
"""

from __future__ import annotations

import argparse
import json
import logging
import signal
import sys
import threading
from collections.abc import Sequence

from service.errors import ShapelocError


def build_parser() -> argparse.ArgumentParser:
    """The command line of ``python -m service.ros2``."""
    from service.ros2.options import add_arguments

    p = argparse.ArgumentParser(
        prog="python -m service.ros2",
        description="Serve ROS 2 robots (rmw_zenoh) from a shapeloc service: no bridge, no ROS.",
    )
    p.add_argument("--connect", action="append", metavar="ENDPOINT", help="Zenoh endpoint")
    p.add_argument("--listen", action="append", metavar="ENDPOINT", help="Zenoh listen endpoint")
    p.add_argument("--mode", choices=["client", "peer"], default="client")
    p.add_argument("--zenoh-config", metavar="FILE", help="Zenoh JSON5 configuration file")
    p.add_argument("--prefix", default="shapeloc", help="shapeloc key prefix")
    p.add_argument("--log-level", default="info", choices=["debug", "info", "warning", "error"])
    add_arguments(p)
    return p


def main(argv: Sequence[str] | None = None) -> int:
    """Run the front until a signal; returns the exit status."""
    import zenoh

    from service.ros2.front import Ros2Front
    from service.ros2.options import options_from_args

    args = build_parser().parse_args(argv)
    logging.basicConfig(
        level=getattr(logging, args.log_level.upper()),
        format="%(asctime)s %(levelname)s %(name)s[%(process)d]: %(message)s",
        stream=sys.stderr,
    )
    try:
        options = options_from_args(args, prefix=args.prefix)
    except ShapelocError as exc:
        print(f"python -m service.ros2: {exc}", file=sys.stderr)
        return 2
    conf = zenoh.Config.from_file(args.zenoh_config) if args.zenoh_config else zenoh.Config()
    conf.insert_json5("mode", json.dumps(args.mode))
    conf.insert_json5("scouting/multicast/enabled", "false")
    if args.connect:
        conf.insert_json5("connect/endpoints", json.dumps(args.connect))
    if args.listen:
        conf.insert_json5("listen/endpoints", json.dumps(args.listen))
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    try:
        session = zenoh.open(conf)
    except zenoh.ZError as exc:
        print(f"python -m service.ros2: cannot open a Zenoh session: {exc}", file=sys.stderr)
        return 1
    with session:
        front = Ros2Front(session, options)
        front.start()
        print("ros2 front ready", flush=True)
        try:
            stop.wait()
        finally:
            front.stop()
    return 0


if __name__ == "__main__":
    sys.exit(main())
