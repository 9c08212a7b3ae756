"""``python -m service`` / ``shapeloc-service``: run the localizer service.

``main(settings)`` opens the Zenoh session, runs :class:`service.node.node.ServiceNode` until
SIGINT/SIGTERM, then saves the state and closes everything; it returns the exit status
(0 on a clean shutdown, 1 when the state is unreadable or the network unreachable, 2 for bad
settings). The settings come from defaults < configuration file (``--config FILE`` or
``SHAPELOC_CONFIG``) < environment (``SHAPELOC_<NAME>``) < flags
(:mod:`service.node.settings`); the command line follows :mod:`schemas.cli`.
"""

from __future__ import annotations

import faulthandler
import json
import logging
import signal
import sys
import threading
from collections.abc import Sequence
from types import FrameType

from service.errors import ShapelocError, StateError, Unreachable
from service.node.settings import ServiceSettings, load_settings, security_summary, zenoh_config

log = logging.getLogger("shapeloc.service")


def _setup_logging(level: str) -> None:
    logging.basicConfig(
        level=getattr(logging, level.upper(), logging.INFO),
        format="%(asctime)s %(levelname)s %(name)s[%(process)d]: %(message)s",
        stream=sys.stderr,
        force=True,
    )


def main(settings: ServiceSettings) -> int:
    """Run the service with ``settings`` until SIGINT/SIGTERM; return the exit status."""
    import zenoh

    from service.node.node import ServiceNode

    _setup_logging(settings.log_level)
    zenoh.init_log_from_env_or("warn" if settings.log_level != "debug" else "info")
    log.info("effective settings: %s", json.dumps(settings.summary(), sort_keys=True))
    stop = threading.Event()

    def on_signal(signum: int, _frame: FrameType | None) -> None:
        log.info("received %s, shutting down", signal.Signals(signum).name)
        stop.set()

    old = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    faulthandler.register(signal.SIGUSR1, all_threads=True)  # kill -USR1: dump thread stacks
    try:
        conf = zenoh_config(settings)
        log.info("zenoh: %s", security_summary(conf))
        try:
            session = zenoh.open(conf)
        except Exception as e:
            where = f"connect {settings.connect}"
            if settings.mode != "client":
                where = f"listen {settings.listen}, {where}"
            raise Unreachable(
                f"cannot open Zenoh session (mode {settings.mode}, {where}): {e}"
            ) from e
        with session:
            node = ServiceNode(settings, session)
            front = None
            try:
                node.start()
                if settings.ros2:  # the ROS 2 front on the same session (docs/ros2.md)
                    from service.ros2.front import Ros2Front
                    from service.ros2.options import options_from_settings

                    front = Ros2Front(session, options_from_settings(settings))
                    front.start()
                while not stop.wait(0.5):
                    pass
            finally:
                if front is not None:
                    front.stop()
                node.stop()
        log.info("bye")
        return 0
    except StateError as e:
        log.error("state error: %s", e)
        print(f"shapeloc-service: state error: {e}", file=sys.stderr)
        return 1
    except ShapelocError as e:
        log.error("%s: %s", type(e).__name__, e)
        print(f"shapeloc-service: {type(e).__name__}: {e}", file=sys.stderr)
        return 1
    finally:
        for s, h in old.items():
            signal.signal(s, h)


def cli(argv: Sequence[str] | None = None) -> int:
    """Console entry point: the settings of the command line, the environment and the
    configuration file (:func:`load_settings`), then :func:`main`."""
    try:
        settings = load_settings(sys.argv[1:] if argv is None else argv)
    except ShapelocError as e:
        print(f"shapeloc-service: {e}", file=sys.stderr)
        return 2
    return main(settings)


if __name__ == "__main__":
    sys.exit(cli())
