"""``python -m clients.view``: serve the live view of a shapeloc service on localhost."""

from __future__ import annotations

import argparse
import signal
import sys
import threading

import zenoh

from clients.session import config_endpoints, zenoh_config
from clients.view.server import DEFAULT_HOST, DEFAULT_PORT, DEFAULT_RATE_HZ, main
from schemas.keys import DEFAULT_PREFIX

DEFAULT_CONNECT = "tcp/127.0.0.1:7447"


def _cli(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(
        prog="python -m clients.view",
        description="A live view of a shapeloc service in the browser (maps, poses, paths, "
        "statuses, scans, search candidates).",
    )
    p.add_argument(
        "--connect",
        action="append",
        default=None,
        help=f"Zenoh endpoint of the service or router (repeatable; default {DEFAULT_CONNECT})",
    )
    p.add_argument("--zenoh-config", metavar="FILE", help="Zenoh JSON5 config (TLS, ...)")
    p.add_argument("--prefix", default=DEFAULT_PREFIX, help="key prefix (default shapeloc)")
    p.add_argument("--host", default=DEFAULT_HOST, help=f"address to serve on ({DEFAULT_HOST})")
    p.add_argument(
        "--port", type=int, default=DEFAULT_PORT, help=f"port ({DEFAULT_PORT}; 0: any free one)"
    )
    p.add_argument(
        "--rate", type=float, default=DEFAULT_RATE_HZ, help="frames per second pushed to the page"
    )
    args = p.parse_args(argv)
    if args.rate < 1:
        p.error("--rate must be >= 1")
    conf = zenoh_config(
        "client",
        connect=args.connect or (),
        config_file=args.zenoh_config,
        default_connect=[DEFAULT_CONNECT],
    )
    zenoh.init_log_from_env_or("error")
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())

    def ready(url: str) -> None:
        print(f"shapeloc view: {url} (Ctrl-C stops)", flush=True)

    try:
        return main(
            conf,
            host=args.host,
            port=args.port,
            prefix=args.prefix,
            rate_hz=args.rate,
            ready=ready,
            stop=stop,
        )
    except OSError as exc:
        print(f"shapeloc view: cannot serve on {args.host}:{args.port}: {exc}", file=sys.stderr)
        return 1
    except zenoh.ZError as exc:
        where = ", ".join(config_endpoints(conf)) or "the configured endpoints"
        print(f"shapeloc view: cannot reach {where}: {exc}", file=sys.stderr)
        return 1


if __name__ == "__main__":
    sys.exit(_cli())
