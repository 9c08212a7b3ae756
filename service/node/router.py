"""``python -m service.node.router``: a Zenoh router for tests and development.

A Python Zenoh session opened in ``router`` mode routes like ``zenohd`` does for what the
service needs (pub/sub, queries, liveliness) but has no plugins (no REST, no storage
manager). Production uses ``zenohd`` (the ``eclipse/zenoh`` image; configs in ``docker/``,
topology in docs/cluster.md). Multicast scouting is off: everything names its endpoints.

    python -m service.node.router --listen tcp/127.0.0.1:7447 [--connect tcp/OTHER:7447]

It prints ``ready`` on stdout once listening and runs until SIGINT/SIGTERM.
"""

from __future__ import annotations

import json
import signal
import sys
import threading
from collections.abc import Sequence

import zenoh


def router_config(listen: Sequence[str], connect: Sequence[str] = ()) -> zenoh.Config:
    """Router-mode config listening on ``listen`` (and linking to the routers in
    ``connect``), multicast scouting off."""
    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps("router"))
    conf.insert_json5("listen/endpoints", json.dumps(list(listen)))
    if connect:
        conf.insert_json5("connect/endpoints", json.dumps(list(connect)))
    conf.insert_json5("scouting/multicast/enabled", "false")
    return conf


def main(conf: zenoh.Config, stop: threading.Event | None = None) -> int:
    """Run a router with ``conf`` until ``stop`` is set (default: SIGINT/SIGTERM)."""
    if stop is None:
        stop = threading.Event()
        for s in (signal.SIGINT, signal.SIGTERM):
            signal.signal(s, lambda *_a: stop.set())
    zenoh.init_log_from_env_or("warn")
    with zenoh.open(conf):
        print("ready", flush=True)
        stop.wait()
    return 0


if __name__ == "__main__":
    import argparse

    ap = argparse.ArgumentParser(
        prog="python -m service.node.router",
        description="A Zenoh router for tests and development (production: zenohd).",
    )
    ap.add_argument("--listen", action="append", metavar="ENDPOINT", required=True)
    ap.add_argument("--connect", action="append", metavar="ENDPOINT", default=[])
    args = ap.parse_args()
    sys.exit(main(router_config(args.listen, args.connect)))
