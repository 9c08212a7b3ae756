"""The live view's server (clients/view/server.py) in process: a loopback Zenoh router plays
the service (it answers the maps and health queries and carries the poses and scans), and an
aiohttp client plays the page. No browser: tests/clients/view/test_view_browser.py has one."""

from __future__ import annotations

import asyncio
import json
import math
import socket
import threading
import time
from collections.abc import Iterator

import aiohttp
import numpy as np
import pytest
import zenoh

from clients.session import zenoh_config
from clients.view.server import main
from schemas.codec import encode
from schemas.messages import Health, Map, PoseMsg, Scan

pytestmark = pytest.mark.timeout(60)

P = "shapeloc"
RATE = 10.0


def free_endpoint() -> str:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return f"tcp/127.0.0.1:{s.getsockname()[1]}"


@pytest.fixture
def fake_service() -> Iterator[tuple[zenoh.Session, str]]:
    """A router session that answers like a service holding one map."""
    ep = free_endpoint()
    with zenoh.open(zenoh_config("router", listen=[ep])) as session:
        ring = [[0, 0], [6, 0], [6, 4], [0, 4], [0, 0]]
        m = Map(map_id="office", kind="metric", polylines=[ring])
        h = Health(
            status="ok", version="9.9", robots=1, maps=1, scans_processed=5, scans_rejected=0
        )
        qs = [
            session.declare_queryable(
                f"{P}/maps/*", lambda q: q.reply(f"{P}/maps/office", encode(m))
            ),
            session.declare_queryable(
                f"{P}/service/health", lambda q: q.reply(f"{P}/service/health", encode(h))
            ),
        ]
        yield session, ep
        for q in qs:
            q.undeclare()


@pytest.fixture
def view(fake_service) -> Iterator[str]:
    """The view server on a free port, connected to the fake service; yields its URL."""
    urls: list[str] = []
    ready = threading.Event()
    stop = threading.Event()

    def on_ready(url: str) -> None:
        urls.append(url)
        ready.set()

    conf = zenoh_config("client", connect=[fake_service[1]])
    t = threading.Thread(
        target=main,
        args=(conf,),
        kwargs=dict(port=0, rate_hz=RATE, ready=on_ready, stop=stop),
        daemon=True,
    )
    t.start()
    assert ready.wait(20), "the view did not start"
    yield urls[0]
    stop.set()
    t.join(10)
    assert not t.is_alive()


def robot_traffic(session: zenoh.Session, stop: threading.Event, rid: str = "r1") -> None:
    """A robot at 20 Hz: scan k, then the pose answering it."""
    k = 0
    while not stop.is_set():
        r = np.full(91, 2.0)
        scan = Scan(
            seq=k,
            stamp=float(k),
            angle_min=-math.pi / 2,
            angle_increment=math.pi / 90,
            range_min=0.1,
            range_max=8.0,
            ranges=r,
        )
        session.put(f"{P}/robots/{rid}/scan", encode(scan, ranges_as_bytes=True))
        pose = PoseMsg(
            robot_id=rid,
            seq=k,
            stamp=float(k),
            pose=[1.0 + 0.01 * k, 2.0, 0.3],
            status="tracking",
            score=0.9,
            method="shape",
            map_id="office",
            latency_ms=2.0,
            explained=0.9,
        )
        session.put(f"{P}/robots/{rid}/pose", encode(pose))
        k += 1
        time.sleep(0.05)


async def _frames(ws: aiohttp.ClientWebSocketResponse, seconds: float) -> list[dict]:
    out = []
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        try:
            msg = await asyncio.wait_for(ws.receive(), max(0.01, end - time.monotonic()))
        except TimeoutError:
            break
        data = json.loads(msg.data)
        if data["type"] == "frame":
            out.append(data)
    return out


def test_a_page_gets_hello_maps_and_live_frames(fake_service, view) -> None:
    stop = threading.Event()
    pub = threading.Thread(target=robot_traffic, args=(fake_service[0], stop), daemon=True)
    pub.start()

    async def run() -> None:
        async with aiohttp.ClientSession() as http:
            async with http.get(view) as resp:
                assert resp.status == 200 and "shapeloc live view" in await resp.text()
            async with http.get(view + "static/view.js") as resp:
                assert resp.status == 200 and "shapelocView" in await resp.text()
            ws = await http.ws_connect(view + "ws")
            hello = json.loads((await ws.receive()).data)
            assert hello["type"] == "hello" and hello["palette"]["status"]["tracking"]["colour"]
            maps = json.loads((await ws.receive()).data)
            assert maps["type"] == "maps"
            snapshot = json.loads((await ws.receive()).data)
            assert snapshot["type"] == "frame"
            frames = await _frames(ws, 3.0)
            # the map arrives once the server's first maps query is answered
            assert any(f["service"] and f["service"]["version"] == "9.9" for f in frames)
            rate = (len(frames) - 1) / (frames[-1]["time"] - frames[0]["time"])
            assert rate >= 0.8 * RATE, rate
            last = frames[-1]["robots"][0]
            assert last["id"] == "r1" and last["status"] == "tracking"
            assert last["scan"]["seq"] == last["seq"]  # the scan the pose answers
            assert sum(len(f["robots"][0]["trail"]) for f in frames[-10:]) >= 10

            # the page draws no robot: no scans are sent (nor decoded)
            await ws.send_str(json.dumps({"type": "select", "robots": []}))
            await asyncio.sleep(0.3)
            frames = await _frames(ws, 0.5)
            assert frames and all("scan" not in f["robots"][0] for f in frames)
            # what a page sends is untrusted: nonsense is ignored, the stream goes on
            for junk in (
                "not json",
                '{"type": "select", "robots": "r1"}',
                "[1, 2]",
                json.dumps({"type": "select", "robots": ["bad id!"] * 3}),
            ):
                await ws.send_str(junk)
            frames = await _frames(ws, 0.5)
            assert frames and all("scan" not in f["robots"][0] for f in frames)
            await ws.send_str(json.dumps({"type": "select", "robots": None}))
            await asyncio.sleep(0.3)
            frames = await _frames(ws, 0.5)
            assert any("scan" in f["robots"][0] for f in frames)
            await ws.close()
            async with http.get(view + "api/frame") as resp:
                full = await resp.json()
                assert full["robots"][0]["path"] and full["view"]["pages"] == 0

    try:
        asyncio.run(run())
    finally:
        stop.set()
        pub.join(5)


def test_the_maps_message_carries_the_services_map(fake_service, view) -> None:
    async def run() -> dict:
        async with aiohttp.ClientSession() as http:
            ws = await http.ws_connect(view + "ws")
            end = time.monotonic() + 10
            while time.monotonic() < end:
                m = json.loads((await ws.receive(timeout=5)).data)
                if m["type"] == "maps" and m["maps"]:
                    return m
            raise AssertionError("no maps message with the map")

    m = asyncio.run(run())
    (office,) = m["maps"]
    assert office["id"] == "office" and office["bounds"] == [0.0, 0.0, 6.0, 4.0]


def test_another_sites_page_cannot_open_the_websocket(view) -> None:
    async def run() -> tuple[int, int]:
        async with aiohttp.ClientSession() as http:
            bad = await http.get(view + "ws", headers={"Origin": "http://evil.example"})
            host = view.split("//", 1)[1].rstrip("/")
            ws = await http.ws_connect(view + "ws", headers={"Origin": f"http://{host}"})
            hello = json.loads((await ws.receive(timeout=5)).data)
            await ws.close()
            return bad.status, hello["type"] == "hello"

    status, ok = asyncio.run(run())
    assert status == 403 and ok


class _Socket:
    """What :meth:`ViewServer.tick` touches of a page's WebSocket: nothing (never sent)."""


def test_frames_are_deltas_with_a_key_frame_a_second_and_a_lagging_page_resyncs() -> None:
    from clients.view.server import KEYFRAME_S, MAX_BEHIND, Page, ViewServer

    server = ViewServer(session=None, rate_hz=RATE)  # tick() needs no session
    st = server.state
    for rid in ("r1", "r2"):
        st.ingest(f"{P}/robots/{rid}/pose", False, _pose(rid, 0), None, 1000.0)
    page = Page(_Socket())
    server.pages.add(page)
    first = json.loads(server.tick(1000.0))
    assert first["key"] and len(first["robots"]) == 2
    st.ingest(f"{P}/robots/r1/pose", False, _pose("r1", 1), None, 1000.1)
    delta = json.loads(server.tick(1000.1))
    assert not delta["key"] and [r["id"] for r in delta["robots"]] == ["r1"]
    assert json.loads(server.tick(1000.0 + KEYFRAME_S))["key"]
    assert len(page.frames) == 3  # nothing was sent: every delta waits, in order
    t = 1000.0 + KEYFRAME_S
    while len(page.frames) < MAX_BEHIND:
        t += 0.1
        server.tick(t)
    server.tick(t + 0.1)  # one too many: the backlog is replaced by one snapshot
    (snap,) = (json.loads(f) for f in page.frames)
    assert page.resyncs == 1 and snap["key"]
    assert [len(r["path"]) for r in snap["robots"]] == [2, 1]


def _pose(rid: str, k: int) -> bytes:
    return encode(
        PoseMsg(robot_id=rid, seq=k, stamp=float(k), pose=[1.0 + k, 2.0, 0.3],
                status="tracking", score=0.9, method="shape", map_id="office", latency_ms=2.0)
    )  # fmt: skip
