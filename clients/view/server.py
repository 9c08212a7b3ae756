"""The live view's server: Zenoh subscribers in, an HTTP page and a WebSocket push out.

One process, best-effort: :func:`main` first lowers the priority of the whole process
(``nice``; ``shapeloc view`` adds :data:`clients.view.DEFAULT_NICE`) so that on a shared
machine the localiser always wins the CPU. Then:

* Zenoh delivers samples into bounded ring channels of its own (Rust, no Python and no GIL on
  Zenoh's threads; when full, the oldest sample is dropped);
* an asyncio loop (aiohttp) serves the page and its assets (``static/``), and every
  ``1 / rate_hz`` seconds drains the rings into a :class:`~clients.view.state.ViewState`,
  builds one frame and hands it to every connected page. Frames are deltas (only the robots
  that changed), with a key frame of every robot once a second; a page keeps up to
  :data:`MAX_BEHIND` unsent frames, and one further behind gets a fresh snapshot instead (a
  slow browser never queues frames up).

It subscribes to ``<prefix>/robots/*/pose``, ``<prefix>/robots/*/scan`` and
``<prefix>/maps/*``, asks the service for its maps (``get <prefix>/maps/*``) at start and
whenever a robot names a map it does not hold, and for its health every few seconds. It
publishes nothing. Each page tells the server which robots it draws; only their scans are
ever decoded.

Endpoints: ``/`` (the page), ``/static/*`` (its script and style), ``/ws`` (the WebSocket:
``hello``, ``maps``, then ``frame`` messages; the page sends ``select``), ``/api/frame``
(one full frame as JSON, for scripts and tests).
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import os
import socket
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path
from typing import Any

import zenoh
from aiohttp import WSMsgType, web

from clients.view import DEFAULT_HOST, DEFAULT_PORT, DEFAULT_RATE_HZ
from clients.view.palette import palette_message
from clients.view.state import STALE_S, ViewState
from schemas import keys
from schemas.codec import decode
from schemas.messages import Health
from service.errors import InvalidMessage

log = logging.getLogger("shapeloc.view")

#: Samples each ring channel holds between two ticks (poses: every one feeds a path; scans:
#: only the newest few per robot are ever drawn; maps: rare). Beyond it the oldest go.
POSE_RING = 8192
SCAN_RING = 2048
MAP_RING = 256
#: Seconds between two key frames (every robot, not only those that changed).
KEYFRAME_S = 1.0
#: Frames a page may have unsent; one more and it gets a snapshot instead of the backlog.
MAX_BEHIND = 10
#: Seconds between health queries, and at least between two map queries.
HEALTH_EVERY_S = 2.0
MAPS_EVERY_S = 2.0
#: Largest message a page may send (its robot selection).
MAX_CLIENT_MSG = 256 * 1024
MAX_SELECTED = 10_000


def static_dir() -> Path:
    """The folder of the page's assets (shipped as package data)."""
    return Path(str(resources.files("clients.view") / "static"))


@dataclass(eq=False)
class Page:
    """One connected page: messages it must get in order, then the newest frame."""

    ws: web.WebSocketResponse
    control: list[str] = field(default_factory=list)
    #: Frames to send, oldest first (deltas: each one matters).
    frames: list[str] = field(default_factory=list)
    wake: asyncio.Event = field(default_factory=asyncio.Event)
    #: Robot ids the page draws (their scans are sent); ``None``: all.
    robots: frozenset[str] | None = None
    sent: int = 0
    #: Times the page fell more than MAX_BEHIND frames behind and got a snapshot.
    resyncs: int = 0


class ViewServer:
    """Subscribes on ``session`` and serves the live view (see the module docstring).

    ``rate_hz``: frames pushed per second (>= 1). The session stays the caller's.
    """

    def __init__(
        self,
        session: zenoh.Session,
        prefix: str = keys.DEFAULT_PREFIX,
        rate_hz: float = DEFAULT_RATE_HZ,
        state: ViewState | None = None,
    ) -> None:
        if not rate_hz >= 1.0:
            raise ValueError(f"rate_hz must be >= 1, got {rate_hz}")
        self.session = session
        self.prefix = keys.validate_prefix(prefix)
        self.rate_hz = float(rate_hz)
        self.state = state or ViewState(self.prefix)
        self.pages: set[Page] = set()
        self.frames = 0
        self._last_key = -1e9
        self._maps_version_sent = -1
        self._last_maps_query = -1e9
        self._maps_query: asyncio.Future[Any] | None = None
        self._health_query: asyncio.Future[Any] | None = None
        self._last_health = -1e9
        self._cpu = (time.process_time(), time.monotonic())
        self.cpu_percent = 0.0
        self._subs: list[Any] = []

    # ------------------------------------------------------------------ zenoh side
    def subscribe(self) -> None:
        """Declare the three subscribers, each into a ring channel (idempotent)."""
        if self._subs:
            return
        ring = zenoh.handlers.RingChannel
        # scans first: a tick drains them before the poses that answer them
        for key, size in (
            (keys.maps_wildcard(self.prefix), MAP_RING),
            (keys.robots_wildcard(self.prefix, "scan"), SCAN_RING),
            (keys.robots_wildcard(self.prefix, "pose"), POSE_RING),
        ):
            self._subs.append(self.session.declare_subscriber(key, ring(size)))

    def _get(self, key: str, timeout: float = 2.0) -> list[tuple[str, bytes, str | None]]:
        """Blocking ``get`` (run in an executor): the ok replies as (key, payload, encoding)."""
        out = []
        with contextlib.suppress(zenoh.ZError):
            for reply in self.session.get(key, timeout=timeout):
                if reply.ok is not None:
                    s = reply.ok
                    enc = None if s.encoding is None else str(s.encoding)
                    out.append((str(s.key_expr), s.payload.to_bytes(), enc))
        return out

    # ------------------------------------------------------------------ ticks
    def _drain(self) -> int:
        """Move what the ring channels hold into the state; the number of samples."""
        n = 0
        now = time.time()
        ingest = self.state.ingest
        delete = zenoh.SampleKind.DELETE
        for sub in self._subs:
            for _ in range(POSE_RING):
                sample = sub.try_recv()
                if sample is None:
                    break
                enc = sample.encoding
                ingest(
                    str(sample.key_expr),
                    sample.kind == delete,
                    sample.payload.to_bytes(),
                    None if enc is None else str(enc),
                    now,
                )
                n += 1
        return n

    def _with_scan(self) -> Callable[[str], bool] | None:
        union: set[str] = set()
        for p in self.pages:
            if p.robots is None:
                return None
            union |= p.robots
        return union.__contains__

    def _view_info(self) -> dict[str, Any]:
        return {
            "cpu": round(self.cpu_percent, 1),
            "pages": len(self.pages),
            "rate_hz": self.rate_hz,
            "decoded_scans": self.state.decoded_scans,
            "resyncs": sum(p.resyncs for p in self.pages),
        }

    def tick(self, now: float | None = None) -> str | None:
        """Drain the rings into the state and, if a page is connected, build one frame (a
        delta, or a key frame once every :data:`KEYFRAME_S`) and queue it for every page.
        Returns the frame's JSON (``None`` without pages)."""
        now = time.time() if now is None else now
        self._drain()
        self._update_cpu()
        text = None
        if self.pages:
            if self.state.maps_version != self._maps_version_sent:
                maps = json.dumps(self.state.maps_message(), allow_nan=False)
                for p in self.pages:
                    p.control.append(maps)
                    p.wake.set()
            self._maps_version_sent = self.state.maps_version
            key = now - self._last_key >= KEYFRAME_S
            if key:
                self._last_key = now
            with_scan = self._with_scan()
            frame = self.state.frame(now, delta=not key, with_scan=with_scan)
            frame["n"] = self.frames
            frame["view"] = self._view_info()
            text = _dumps(frame)
            self.frames += 1
            snapshot = None
            for p in self.pages:
                if len(p.frames) >= MAX_BEHIND:
                    # too far behind for deltas: the whole state (paths too) in one frame
                    if snapshot is None:
                        full = self.state.frame(now, full=True, with_scan=with_scan)
                        full["n"] = frame["n"]
                        full["view"] = frame["view"]
                        snapshot = _dumps(full)
                    p.frames = [snapshot]
                    p.resyncs += 1
                else:
                    p.frames.append(text)
                p.wake.set()
        self.state.end_tick(now)
        return text

    def _update_cpu(self) -> None:
        cpu, wall = time.process_time(), time.monotonic()
        if wall - self._cpu[1] >= 2.0:
            self.cpu_percent = 100.0 * (cpu - self._cpu[0]) / (wall - self._cpu[1])
            self._cpu = (cpu, wall)

    async def _queries(self, loop: asyncio.AbstractEventLoop) -> None:
        """Start a maps or health query in the executor when due; apply finished ones."""
        now = time.monotonic()
        if self._maps_query is not None and self._maps_query.done():
            for key, payload, enc in self._maps_query.result():
                self.state.ingest(key, False, payload, enc, time.time())
            self._maps_query = None
        if self._health_query is not None and self._health_query.done():
            self.state.health = _health_summary(self._health_query.result())
            self._health_query = None
        want_maps = self._last_maps_query < -1e8 or bool(self.state.missing_maps())
        if self._maps_query is None and want_maps and now - self._last_maps_query >= MAPS_EVERY_S:
            self._last_maps_query = now
            self._maps_query = loop.run_in_executor(
                None, self._get, keys.maps_wildcard(self.prefix)
            )
        if self._health_query is None and now - self._last_health >= HEALTH_EVERY_S:
            self._last_health = now
            self._health_query = loop.run_in_executor(
                None, self._get, keys.health_key(self.prefix), 1.0
            )

    async def _ticker(self, stop: threading.Event) -> None:
        loop = asyncio.get_running_loop()
        period = 1.0 / self.rate_hz
        due = loop.time()
        while not stop.is_set():
            due += period
            delay = due - loop.time()
            if delay > 0:
                await asyncio.sleep(delay)
            elif delay < -period:
                due = loop.time()  # fell behind (machine busy): do not burst to catch up
            await self._queries(loop)
            self.tick()

    # ------------------------------------------------------------------ web side
    def build_app(self) -> web.Application:
        """The aiohttp application (routes only; :meth:`serve` runs it)."""
        app = web.Application()
        root = static_dir()
        app.router.add_get("/", self._index)
        app.router.add_get("/ws", self._ws)
        app.router.add_get("/api/frame", self._api_frame)
        app.router.add_static("/static/", root, show_index=False, follow_symlinks=False)
        return app

    async def _index(self, _request: web.Request) -> web.StreamResponse:
        return web.FileResponse(static_dir() / "index.html", headers={"Cache-Control": "no-store"})

    async def _api_frame(self, _request: web.Request) -> web.Response:
        frame = self.state.frame(time.time(), full=True)
        frame["view"] = self._view_info()
        return web.json_response(frame, dumps=lambda o: json.dumps(o, allow_nan=False))

    def _hello(self) -> dict[str, Any]:
        return {
            "type": "hello",
            "palette": palette_message(),
            "prefix": self.prefix,
            "rate_hz": self.rate_hz,
            "path_len": self.state.path_len,
            "stale_s": STALE_S,
        }

    async def _ws(self, request: web.Request) -> web.StreamResponse:
        if not _same_origin(request):
            # another site's page in the user's browser may not read the fleet
            raise web.HTTPForbidden(text="cross-origin WebSocket refused")
        # no per-message deflate: on a local link it only costs CPU at both ends
        ws = web.WebSocketResponse(heartbeat=20.0, max_msg_size=MAX_CLIENT_MSG, compress=False)
        await ws.prepare(request)
        page = Page(ws)
        # Built and registered without an await in between: the snapshot holds every path
        # point up to the last tick, the next frame's trails continue from there.
        snapshot = self.state.frame(time.time(), full=True, with_scan=lambda _r: False)
        snapshot["n"] = self.frames
        page.control += [
            json.dumps(self._hello()),
            json.dumps(self.state.maps_message(), allow_nan=False),
            _dumps(snapshot),
        ]
        page.wake.set()
        self.pages.add(page)
        sender = asyncio.create_task(self._send_loop(page))
        try:
            async for msg in ws:
                if msg.type == WSMsgType.TEXT:
                    page.robots = _selection(msg.data, page.robots)
                elif msg.type == WSMsgType.ERROR:
                    break
        finally:
            self.pages.discard(page)
            sender.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await sender
        return ws

    async def _send_loop(self, page: Page) -> None:
        with contextlib.suppress(ConnectionError, RuntimeError):
            while not page.ws.closed:
                await page.wake.wait()
                page.wake.clear()
                while page.control:
                    await page.ws.send_str(page.control.pop(0))
                while page.frames and not page.control:
                    await page.ws.send_str(page.frames.pop(0))
                    page.sent += 1

    async def serve(
        self,
        sock: socket.socket,
        stop: threading.Event,
        ready: Callable[[str], None] | None = None,
    ) -> None:
        """Serve on the bound ``sock`` until ``stop`` is set; ``ready(url)`` once listening."""
        self.subscribe()
        runner = web.AppRunner(self.build_app(), access_log=None)
        await runner.setup()
        site = web.SockSite(runner, sock)
        await site.start()
        host, port = sock.getsockname()[:2]
        if ready is not None:
            ready(f"http://{_url_host(host)}:{port}/")
        ticker = asyncio.create_task(self._ticker(stop))
        try:
            while not stop.is_set() and not ticker.done():
                await asyncio.sleep(0.1)
        finally:
            ticker.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await ticker
            for p in list(self.pages):
                with contextlib.suppress(Exception):
                    await p.ws.close()
            await runner.cleanup()


def _dumps(msg: dict[str, Any]) -> str:
    """Compact strict JSON (no spaces after separators: a tenth fewer bytes)."""
    return json.dumps(msg, allow_nan=False, separators=(",", ":"))


def lower_priority(nice: int) -> int:
    """Add ``nice`` (0-19) to the niceness of every thread of this process (on Linux a
    thread's niceness is its own, so threads already started are lowered one by one); new
    threads inherit it. Returns the main thread's niceness after. Raises ``ValueError``
    outside 0-19 (a negative value would need privileges and is not what a view wants)."""
    if not 0 <= nice <= 19:
        raise ValueError(f"nice must be in 0..19, got {nice}")
    if nice == 0:
        return os.getpriority(os.PRIO_PROCESS, 0)
    tids: list[int] = []
    with contextlib.suppress(OSError):
        tids = [int(t) for t in os.listdir("/proc/self/task")]
    if not tids:
        os.nice(nice)
        return os.getpriority(os.PRIO_PROCESS, 0)
    for tid in tids:
        with contextlib.suppress(OSError):  # a thread may have ended meanwhile
            now = os.getpriority(os.PRIO_PROCESS, tid)
            os.setpriority(os.PRIO_PROCESS, tid, min(19, now + nice))
    return os.getpriority(os.PRIO_PROCESS, 0)


def _same_origin(request: web.Request) -> bool:
    """A browser names the page that opens a WebSocket in ``Origin``: it must be this server
    (scripts and tests send none)."""
    origin = request.headers.get("Origin")
    if origin is None:
        return True
    host = request.headers.get("Host", "")
    return origin in (f"http://{host}", f"https://{host}")


def _url_host(host: str) -> str:
    if host in ("0.0.0.0", "::"):
        return "127.0.0.1"
    return f"[{host}]" if ":" in host else host


def _selection(text: str, current: frozenset[str] | None) -> frozenset[str] | None:
    """A page's ``{"type": "select", "robots": [ids] | null}``; anything else keeps
    ``current`` (the page is a network peer too: its messages are checked)."""
    try:
        msg = json.loads(text)
    except ValueError:
        return current
    if not isinstance(msg, dict) or msg.get("type") != "select":
        return current
    robots = msg.get("robots")
    if robots is None:
        return None
    if not isinstance(robots, list) or len(robots) > MAX_SELECTED:
        return current
    return frozenset(r for r in robots if isinstance(r, str) and keys.id_error(r) is None)


def _health_summary(replies: list[tuple[str, bytes, str | None]]) -> dict[str, Any] | None:
    for _key, payload, enc in replies:
        try:
            h = decode(Health, payload, enc)
        except InvalidMessage:
            continue
        return {
            "status": h.status,
            "version": h.version,
            "instance": h.instance_id,
            "robots": h.robots,
            "maps": h.maps,
            "processed": h.scans_processed,
            "rejected": h.scans_rejected,
        }
    return None


def bind(host: str = DEFAULT_HOST, port: int = DEFAULT_PORT) -> socket.socket:
    """A listening TCP socket on ``host:port`` (port 0: any free port)."""
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    sock = socket.socket(family, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    try:
        sock.bind((host, port))
        sock.listen(64)
    except OSError:
        sock.close()
        raise
    sock.setblocking(False)
    return sock


def main(
    conf: zenoh.Config,
    *,
    host: str = DEFAULT_HOST,
    port: int = DEFAULT_PORT,
    prefix: str = keys.DEFAULT_PREFIX,
    rate_hz: float = DEFAULT_RATE_HZ,
    ready: Callable[[str], None] | None = None,
    stop: threading.Event | None = None,
    nice: int = 0,
) -> int:
    """Run the live view until ``stop`` is set: lower this process's priority by ``nice``
    (0-19; ``shapeloc view`` passes :data:`clients.view.DEFAULT_NICE`), open a Zenoh session
    with ``conf``, serve the page on ``host:port`` (0: a free port), call ``ready(url)`` once
    it listens. Returns 0.

    Raises ``OSError`` if the port cannot be bound, ``zenoh.ZError`` if the session cannot
    be opened, ``ValueError`` for a ``nice`` outside 0-19.
    """
    lower_priority(nice)
    stop = stop or threading.Event()
    sock = bind(host, port)
    try:
        with zenoh.open(conf) as session:
            server = ViewServer(session, prefix, rate_hz)
            asyncio.run(server.serve(sock, stop, ready))
    finally:
        sock.close()
    return 0
