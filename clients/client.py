"""Python client of the shapeloc localizer service (wire contract v1) over Eclipse Zenoh.

:class:`ShapelocClient` opens its own Zenoh session (client mode by default, so it fails fast
when nothing listens at the given endpoints) or wraps a session the caller owns. Requests
(``get``) time out after ``timeout`` seconds with :class:`~service.errors.ServiceTimeout`;
``reply_err`` answers become :class:`~service.errors.RemoteError`, or
:class:`~service.errors.UnknownRobot` / :class:`~service.errors.UnknownMap` when the service
says so. Poses and maps are in the map frame (metres, radians, REP 103).

The Zenoh configuration helpers (:func:`zenoh_config`, :func:`config_endpoints`,
:func:`open_session`) live in :mod:`clients.session` and :class:`Stream` in
:mod:`clients.stream`; both are re-exported here.
"""

from __future__ import annotations

import contextlib
import json
import time
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path
from typing import Any

import msgpack
import numpy as np
import zenoh
from pydantic import BaseModel

from clients.session import config_endpoints, open_session, zenoh_config
from clients.stream import M, Stream, encoding_of
from schemas import keys
from schemas.codec import MSGPACK_ENCODING, decode, encode
from schemas.messages import ErrorNotice, Health, Map, PoseMsg, RobotConfig, Scan, Truth
from service.adapters.convert import map_message_of
from service.adapters.maps.files import load_map_file
from service.core.types import MapData
from service.errors import (
    InvalidMessage,
    RemoteError,
    ServiceTimeout,
    ShapelocError,
    UnknownMap,
    UnknownRobot,
    Unreachable,
)

__all__ = [
    "DEFAULT_CONNECT",
    "DEFAULT_PREFIX",
    "DEFAULT_TIMEOUT",
    "ShapelocClient",
    "Stream",
    "config_endpoints",
    "open_session",
    "zenoh_config",
]

DEFAULT_CONNECT = "tcp/127.0.0.1:7447"
DEFAULT_PREFIX = "shapeloc"
DEFAULT_TIMEOUT = 2.0
#: the least time :meth:`ShapelocClient.configure` waits for a confirmation (seconds)
CONFIGURE_WAIT_S = 10.0


def _remote_error(key: str, payload: bytes) -> ShapelocError:
    """Map a ``reply_err`` payload (text, or a JSON/msgpack ``{"error": ...}`` map) to an error."""
    text = ""
    data: Any = None
    try:
        data = msgpack.unpackb(payload, raw=False)
    except Exception:
        try:
            data = json.loads(payload)
        except Exception:
            data = None
    if isinstance(data, dict) and isinstance(data.get("error"), str):
        text = data["error"]
        kind = str(data.get("type", ""))
    else:
        text = payload.decode("utf-8", errors="replace").strip()
        kind = ""
    low = text.lower()
    msg = f"{key}: {text}" if text else f"{key}: the service answered with an empty error"
    if kind == "UnknownRobot" or "unknown robot" in low:
        return UnknownRobot(text)
    if kind == "UnknownMap" or "unknown map" in low:
        return UnknownMap(text)
    return RemoteError(msg)


def _robot_of_key(key: str) -> str:
    parts = key.rsplit("/", 2)
    return parts[-2] if len(parts) == 3 else ""


class _KeyFilter:
    """Accept ``<prefix>/robots/<id>/<leaf>`` keys of the given robot ids."""

    def __init__(self, ids: frozenset[str]) -> None:
        self.ids = ids

    def __call__(self, key: str) -> bool:
        return _robot_of_key(key) in self.ids


class ShapelocClient:
    """Talk to a shapeloc service: maps, robot configuration, scans, poses, health, errors.

    Either ``connect`` endpoints (a Zenoh session is opened in ``mode``, default ``client``)
    or an existing ``session`` (not closed by this object). ``timeout`` (s) bounds every
    request. Use as a context manager so the session and subscriptions are always closed.
    """

    def __init__(
        self,
        connect: str | Sequence[str] | None = DEFAULT_CONNECT,
        *,
        session: zenoh.Session | None = None,
        prefix: str = DEFAULT_PREFIX,
        timeout: float = DEFAULT_TIMEOUT,
        mode: str = "client",
    ) -> None:
        if timeout <= 0:
            raise ValueError(f"timeout must be > 0 s, got {timeout}")
        self.prefix = keys.validate_prefix(prefix)
        self.timeout = float(timeout)
        self._streams: list[Stream[Any]] = []
        self._subs: list[Any] = []
        if session is not None:
            self.session = session
            self._owns = False
            self.endpoints: tuple[str, ...] = ()
        else:
            eps = (connect,) if isinstance(connect, str) else tuple(connect or ())
            self.endpoints = eps
            self.session = open_session(zenoh_config(mode, connect=eps), eps)
            self._owns = True

    # ----------------------------------------------------------------- lifecycle
    def close(self) -> None:
        """Undeclare subscriptions and close the session if this client opened it."""
        for s in self._streams:
            s.close()
        self._streams.clear()
        for sub in self._subs:
            with contextlib.suppress(zenoh.ZError):
                sub.undeclare()
        self._subs.clear()
        if self._owns and not self.session.is_closed():
            self.session.close()

    def __enter__(self) -> ShapelocClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # ----------------------------------------------------------------- requests
    def _get(self, key: str, many: bool = False) -> list[tuple[str, bytes, str | None]]:
        """Run a get; return the ok replies; raise on error replies or on no reply at all."""
        oks: list[tuple[str, bytes, str | None]] = []
        err: ShapelocError | None = None
        try:
            replies = self.session.get(key, timeout=self.timeout)
            for reply in replies:
                if reply.ok is not None:
                    s = reply.ok
                    oks.append((str(s.key_expr), s.payload.to_bytes(), encoding_of(s)))
                elif reply.err is not None and err is None:
                    payload = reply.err.payload.to_bytes()
                    if payload == b"Timeout":
                        # zenoh's own notice that the query timed out, from this session or
                        # from a router on the way (then it carries the router's id)
                        continue
                    err = _remote_error(key, payload)
        except zenoh.ZError as exc:
            raise Unreachable(f"zenoh request on {key} failed: {exc}") from exc
        if err is not None and not oks:
            raise err
        if not oks and not many:
            raise ServiceTimeout(f"no shapeloc service answered on {key} within {self.timeout} s")
        return oks

    def _get_one(self, key: str, model: type[M]) -> M:
        _, payload, enc = self._get(key)[0]
        return decode(model, payload, enc)

    def _put(self, key: str, msg: BaseModel) -> None:
        self.session.put(
            key,
            encode(msg),
            encoding=zenoh.Encoding(MSGPACK_ENCODING),
            congestion_control=zenoh.CongestionControl.BLOCK,
        )

    def health(self) -> Health:
        """The service's health (``get <prefix>/service/health``)."""
        return self._get_one(keys.health_key(self.prefix), Health)

    def wait_for_service(self, within: float) -> Health:
        """Poll :meth:`health` until the service answers or ``within`` seconds pass."""
        end = time.monotonic() + within
        while True:
            try:
                return self.health()
            except ServiceTimeout:
                if time.monotonic() >= end:
                    raise ServiceTimeout(
                        f"no shapeloc service answered on {keys.health_key(self.prefix)} "
                        f"within {within} s"
                    ) from None
                time.sleep(0.1)

    def put_map(
        self,
        map_: MapData | Map | str | Path,
        *,
        map_id: str | None = None,
        kind: str | None = None,
        confirm: bool = False,
        ready: bool = False,
        within: float = 60.0,
    ) -> Map:
        """Store a map (``put <prefix>/maps/<map_id>``); returns the message sent.

        ``map_`` is a core :class:`MapData`, a wire :class:`Map` or the path of a map file in
        any format :func:`service.adapters.maps.files.load_map_file` reads (wire JSON/msgpack,
        GeoJSON world or outlines, WKT world). ``map_id`` / ``kind`` override the map's own. With
        ``confirm`` the map is read back until the service holds it (raises
        :class:`ServiceTimeout` otherwise). With ``ready`` (implies ``confirm``) it also waits,
        up to ``within`` seconds, until the service reports the map ready
        (:meth:`wait_map_ready`): start robots after that and their first scans are localised
        at full speed (a freshly started service also warms its workers up first, a few
        seconds).
        """
        if isinstance(map_, MapData):
            msg = map_message_of(map_)
        elif isinstance(map_, Map):
            msg = map_
        else:
            msg = map_message_of(load_map_file(map_, map_id=map_id, kind=kind))
        if (map_id is not None and msg.map_id != map_id) or (kind is not None and msg.kind != kind):
            msg = Map(
                map_id=map_id or msg.map_id,
                kind=kind or msg.kind,
                polylines=msg.polylines,
                name=msg.name,
            )
        key = keys.map_key(self.prefix, msg.map_id)
        self._put(key, msg)
        if confirm or ready:
            self._confirm(lambda: self._map_matches(msg))
        if ready:
            self.wait_map_ready(msg.map_id, within)
        return msg

    def wait_map_ready(self, map_id: str, within: float, indexed: bool = False) -> Health:
        """Poll :meth:`health` until the service lists ``map_id`` in ``Health.maps_ready``
        (the map's first-use work is done: robots are localised at full speed from their
        first scan) or, with ``indexed``, in ``Health.maps_indexed`` too (its view index of
        global localisation was built, not only attempted). A service that does not report
        readiness (no ``maps_ready``) counts as ready once it holds the map. Raises
        :class:`ServiceTimeout` after ``within`` seconds. Returns the last health."""
        end = time.monotonic() + within
        while True:
            try:
                h = self.health()
            except ServiceTimeout:
                h = None
            if h is not None:
                if h.maps_ready is None:
                    if self._holds(map_id):
                        return h
                elif map_id in h.maps_ready and (
                    not indexed or h.maps_indexed is None or map_id in h.maps_indexed
                ):
                    return h
            if time.monotonic() >= end:
                what = "indexed" if indexed else "ready"
                raise ServiceTimeout(
                    f"the service did not report map {map_id!r} {what} in {within} s"
                )
            time.sleep(0.05)

    def _holds(self, map_id: str) -> bool:
        try:
            self.get_map(map_id)
        except (ServiceTimeout, UnknownMap, RemoteError):
            return False
        return True

    def _map_matches(self, msg: Map) -> bool:
        try:
            got = self.get_map(msg.map_id)
        except (ServiceTimeout, UnknownMap, RemoteError):
            return False
        return (
            got.kind == msg.kind
            and len(got.polylines) == len(msg.polylines)
            and all(np.array_equal(a, b) for a, b in zip(got.polylines, msg.polylines, strict=True))
        )

    def _confirm(self, check: Callable[[], bool]) -> None:
        end = time.monotonic() + self.timeout
        while not check():
            if time.monotonic() >= end:
                raise ServiceTimeout(
                    f"the service did not confirm the change within {self.timeout} s"
                )
            time.sleep(0.05)

    def delete_map(self, map_id: str) -> None:
        """Remove a stored map (``delete <prefix>/maps/<map_id>``)."""
        self.session.delete(keys.map_key(self.prefix, map_id))

    def get_map(self, map_id: str) -> Map:
        """The stored map ``map_id``; :class:`UnknownMap` if the service does not hold it."""
        key = keys.map_key(self.prefix, map_id)
        oks = self._get(key, many=True)
        if not oks:
            raise UnknownMap(f"the service holds no map {map_id!r} (or did not answer on {key})")
        _, payload, enc = oks[0]
        return decode(Map, payload, enc)

    def list_maps(self) -> list[Map]:
        """All stored maps, sorted by id (a running service with no maps gives ``[]``)."""
        oks = self._get(keys.maps_wildcard(self.prefix), many=True)
        maps = [decode(Map, payload, enc) for _, payload, enc in oks]
        return sorted(maps, key=lambda m: m.map_id)

    def configure(
        self,
        robot_id: str,
        map_id: str,
        method: str = "shape",
        initial_pose: Sequence[float] | np.ndarray | None = None,
        *,
        laser_offset: Sequence[float] | np.ndarray | None = None,
        confirm: bool = False,
        grace: float = 0.5,
        within: float | None = None,
    ) -> RobotConfig:
        """Configure (and reset) a robot: its map, method and initial pose of its base
        (``None``: global; map frame, metres and radians), and ``laser_offset``, the laser's
        pose ``[x, y, theta]`` on the base (``None``: ``[0, 0, 0]``).

        With ``confirm``, wait (up to ``within`` seconds; default the client's ``timeout``,
        at least 10 s, as the service applies a configuration on the robot's worker, which may
        be preparing a map) until the service knows the robot, and raise
        :class:`RemoteError` if the service publishes an error notice for this configuration
        meanwhile or within ``grace`` seconds after (best effort for re-configurations: a
        rejection reported later than that is not seen).
        """
        pose = None if initial_pose is None else [float(v) for v in np.asarray(initial_pose)]
        extra: dict[str, Any] = {}
        if laser_offset is not None:
            extra["laser_offset"] = [float(v) for v in np.asarray(laser_offset)]
        msg = RobotConfig(map_id=map_id, method=method, initial_pose=pose, **extra)
        key = keys.robot_key(self.prefix, robot_id, "config")
        if not confirm:
            self._put(key, msg)
            return msg
        with Stream(
            self.session, keys.errors_key(self.prefix), ErrorNotice, lambda e: e.key == key
        ) as notices:
            self._put(key, msg)
            wait = max(self.timeout, CONFIGURE_WAIT_S) if within is None else within
            end = time.monotonic() + wait
            known_at = None
            while True:
                item = notices.get(timeout=0.05)
                if item is not None:
                    raise RemoteError(
                        f"the service rejected the configuration of {robot_id!r}: {item[1].error}"
                    )
                now = time.monotonic()
                if known_at is None:
                    try:
                        self.get_pose(robot_id)
                        known_at = now
                    except RemoteError:
                        known_at = now  # known, e.g. "has no estimate yet"
                    except UnknownRobot:
                        pass
                if known_at is not None and now - known_at >= grace:
                    return msg
                if known_at is None and now >= end:
                    raise ServiceTimeout(
                        f"the service did not take the configuration of {robot_id!r} within "
                        f"{wait} s"
                    )

    def send_scan(self, robot_id: str, scan: Scan) -> None:
        """Publish one scan of ``robot_id`` (``put <prefix>/robots/<id>/scan``)."""
        self.session.put(
            keys.robot_key(self.prefix, robot_id, "scan"),
            encode(scan),
            encoding=zenoh.Encoding(MSGPACK_ENCODING),
        )

    def get_pose(self, robot_id: str) -> PoseMsg:
        """Latest estimate of ``robot_id``; :class:`UnknownRobot` if it is not configured."""
        return self._get_one(keys.robot_key(self.prefix, robot_id, "pose"), PoseMsg)

    def wait_configured(self, robot_id: str, within: float) -> None:
        """Poll until the service knows ``robot_id`` (its pose query no longer says "unknown
        robot"), or raise :class:`ServiceTimeout` after ``within`` seconds."""
        end = time.monotonic() + within
        while True:
            try:
                self.get_pose(robot_id)
                return
            except RemoteError:
                return  # known, e.g. "has no estimate yet"
            except (UnknownRobot, ServiceTimeout):
                if time.monotonic() >= end:
                    raise ServiceTimeout(
                        f"the service did not take the configuration of robot {robot_id!r} "
                        f"within {within} s"
                    ) from None
                time.sleep(0.05)

    # ----------------------------------------------------------------- subscriptions
    def _subscribe(
        self, key_expr: str, model: type[M], callback: Callable[[M], None] | None
    ) -> Stream[M] | Any:
        if callback is None:
            stream = Stream(self.session, key_expr, model)
            self._streams.append(stream)
            return stream

        def on_sample(sample: Any) -> None:
            try:
                msg = decode(model, sample.payload.to_bytes(), encoding_of(sample))
            except InvalidMessage:
                return
            callback(msg)

        sub = self.session.declare_subscriber(key_expr, on_sample)
        self._subs.append(sub)
        return sub

    def _watch_robots(
        self,
        leaf: str,
        model: type[M],
        robot_ids: str | Iterable[str],
        callback: Callable[[M], None] | None,
        id_of: Callable[[str], str],
    ) -> Stream[M] | Any:
        accept = None
        if robot_ids == "*":
            key_expr = keys.robots_wildcard(self.prefix, leaf)
        elif isinstance(robot_ids, str):
            key_expr = keys.robot_key(self.prefix, robot_ids, leaf)
        else:
            wanted = frozenset(robot_ids)
            if not wanted:
                raise ValueError("robot_ids is empty")
            key_expr = keys.robots_wildcard(self.prefix, leaf)
            accept = wanted
        if callback is None:
            stream = Stream(
                self.session, key_expr, model, None, None if accept is None else _KeyFilter(accept)
            )
            self._streams.append(stream)
            return stream

        def on_sample(sample: Any) -> None:
            key = str(sample.key_expr)
            if accept is not None and id_of(key) not in accept:
                return
            try:
                msg = decode(model, sample.payload.to_bytes(), encoding_of(sample))
            except InvalidMessage:
                return
            callback(msg)

        sub = self.session.declare_subscriber(key_expr, on_sample)
        self._subs.append(sub)
        return sub

    def watch_poses(
        self,
        robot_ids: str | Iterable[str] = "*",
        callback: Callable[[PoseMsg], None] | None = None,
    ) -> Stream[PoseMsg] | Any:
        """Subscribe to pose estimates of one robot, of all (``"*"``) or of several ids.

        Without ``callback``: a :class:`Stream` of ``(key, PoseMsg)``. With ``callback``: the
        Zenoh subscriber (the callback runs on Zenoh's thread; keep it short). Either is
        undeclared by :meth:`close`.
        """
        return self._watch_robots("pose", PoseMsg, robot_ids, callback, _robot_of_key)

    def watch_truth(
        self,
        robot_ids: str | Iterable[str] = "*",
        callback: Callable[[Truth], None] | None = None,
    ) -> Stream[Truth] | Any:
        """Subscribe to simulator ground truth (``<prefix>/robots/<id>/truth``), as
        :meth:`watch_poses`; the robot id is the key's second-to-last chunk."""
        return self._watch_robots("truth", Truth, robot_ids, callback, _robot_of_key)

    def watch_errors(
        self, callback: Callable[[ErrorNotice], None] | None = None
    ) -> Stream[ErrorNotice] | Any:
        """Subscribe to the service's error notices (``<prefix>/errors``)."""
        return self._subscribe(keys.errors_key(self.prefix), ErrorNotice, callback)

    errors = watch_errors
