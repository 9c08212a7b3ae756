"""Zenoh configuration and sessions for the shapeloc clients.

:func:`zenoh_config` builds a Zenoh config with explicit endpoints and no multicast scouting
(optionally on top of a JSON5 config file), :func:`config_endpoints` reads the endpoints back
for messages, and :func:`open_session` opens a session, turning a connection failure into
:class:`~service.errors.Unreachable`. Used by :class:`clients.client.ShapelocClient`, the
``shapeloc`` CLI and the simulator; re-exported by :mod:`clients.client`.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path

import zenoh

from service.errors import InvalidMessage, Unreachable


def zenoh_config(
    mode: str | None = "client",
    connect: Sequence[str] = (),
    listen: Sequence[str] = (),
    multicast: bool = False,
    config_file: str | Path | None = None,
    default_connect: Sequence[str] = (),
) -> zenoh.Config:
    """Build a Zenoh config with explicit endpoints and (by default) no multicast scouting.

    ``mode`` is ``client`` (needs a reachable router/peer in ``connect``; fails at once
    otherwise), ``peer`` or ``router``. Zenoh's scouting delay is kept: a peer's open waits
    (up to 500 ms) for its connect endpoints, because a query sent before the link is up is
    never routed to the queryables behind it, not even later (eclipse-zenoh 1.10.2).

    ``config_file``: a Zenoh JSON5 configuration (TLS, mutual TLS, user/password, access
    control, ...) used as the base. The arguments are applied on top of it: a given ``mode``
    and non-empty ``connect`` / ``listen`` lists **replace** the file's values, while
    ``mode=None`` and empty lists keep them (``mode=None`` without a file means ``client``).
    ``default_connect`` is used only in client mode when neither ``connect`` nor the file
    names a connect endpoint. Multicast scouting is off unless ``multicast`` is true,
    whatever the file says.
    Raises :class:`InvalidMessage` naming the file if it cannot be read or parsed.
    """
    if mode is not None and mode not in ("client", "peer", "router"):
        raise ValueError(f"zenoh mode must be client, peer or router, not {mode!r}")
    if config_file is not None:
        try:
            conf = zenoh.Config.from_file(str(config_file))
        except Exception as exc:  # zenoh raises ZError (or IOError) with the parser's reason
            raise InvalidMessage(f"zenoh config {config_file}: {exc}") from exc
    else:
        conf = zenoh.Config()
        mode = mode or "client"
    if mode is not None:
        conf.insert_json5("mode", json.dumps(mode))
    conf.insert_json5("scouting/multicast/enabled", "true" if multicast else "false")
    if connect:
        conf.insert_json5("connect/endpoints", json.dumps(list(connect)))
    elif (
        default_connect
        and not config_endpoints(conf, "connect")
        and json.loads(str(conf)).get("mode") == "client"
    ):
        conf.insert_json5("connect/endpoints", json.dumps(list(default_connect)))
    if listen:
        conf.insert_json5("listen/endpoints", json.dumps(list(listen)))
    return conf


def config_endpoints(conf: zenoh.Config, which: str = "connect") -> list[str]:
    """The ``connect`` (or ``listen``) endpoints a Zenoh config holds (for messages)."""
    try:
        eps = (json.loads(str(conf)).get(which) or {}).get("endpoints") or []
    except (ValueError, AttributeError):
        return []
    if isinstance(eps, dict):  # per-mode form {"router": [...], "peer": [...], ...}
        eps = [e for v in eps.values() for e in (v or [])]
    return [str(e) for e in eps]


def open_session(conf: zenoh.Config, endpoints: Sequence[str] = ()) -> zenoh.Session:
    """Open a Zenoh session, turning a connection failure into :class:`Unreachable`."""
    try:
        return zenoh.open(conf)
    except zenoh.ZError as exc:
        where = ", ".join(endpoints) if endpoints else "the configured endpoints"
        reason = str(exc).split(" at /", 1)[0].strip()
        raise Unreachable(
            f"cannot reach a zenoh router or shapeloc service at {where} ({reason})"
        ) from exc
