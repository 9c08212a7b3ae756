"""ShapelocClient against an in-process fake service on a loopback Zenoh router.

The fake answers health / pose / map queries the way wire-v1 says and records puts, so the
client's encoding, decoding and error mapping are checked without the real service.
Runs in about 2 s.
"""

from __future__ import annotations

import json
import socket
import threading
import time
from collections.abc import Iterator

import numpy as np
import pytest
import zenoh

from clients.client import ShapelocClient, zenoh_config
from schemas.codec import decode, encode
from schemas.messages import ErrorNotice, Health, Map, PoseMsg, RobotConfig, Scan, Truth
from service.adapters.maps.files import save_map_file
from service.core.types import MapData
from service.errors import (
    InvalidMessage,
    RemoteError,
    ServiceTimeout,
    UnknownMap,
    UnknownRobot,
    Unreachable,
)

pytestmark = pytest.mark.timeout(60)


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class FakeService:
    """Router session with wire-v1 queryables: health, maps (stored from puts), poses."""

    def __init__(self, session: zenoh.Session, prefix: str = "shapeloc") -> None:
        self.session = session
        self.maps: dict[str, bytes] = {}
        self.puts: list[tuple[str, bytes]] = []
        self.held: list[zenoh.Query] = []
        self.silent = False
        self.lock = threading.Lock()
        p = prefix
        self.entities = [
            session.declare_queryable(f"{p}/service/health", self._health),
            session.declare_queryable(f"{p}/robots/*/pose", self._pose),
            session.declare_queryable(f"{p}/maps/*", self._maps),
            session.declare_subscriber(f"{p}/maps/*", self._map_put),
            session.declare_subscriber(f"{p}/robots/**", self._robot_put),
        ]

    def _health(self, q: zenoh.Query) -> None:
        if self.silent:
            self.held.append(q)  # never answered: the client must time out on its own
            return
        h = Health(
            status="ok",
            version="9.9",
            robots=2,
            maps=len(self.maps),
            scans_processed=5,
            scans_rejected=1,
        )
        q.reply(q.key_expr, encode(h))

    def _pose(self, q: zenoh.Query) -> None:
        rid = str(q.key_expr).split("/")[-2]
        if rid == "ghost":
            q.reply_err(b"unknown robot 'ghost'")
        elif rid == "broken":
            q.reply_err(json.dumps({"error": "localiser crashed: bad map"}).encode())
        else:
            msg = PoseMsg(
                robot_id=rid,
                seq=7,
                stamp=1.5,
                pose=[1.0, 2.0, 0.5],
                status="tracking",
                score=0.9,
                method="shape",
                map_id="office",
                latency_ms=12.5,
            )
            q.reply(q.key_expr, encode(msg))

    def _maps(self, q: zenoh.Query) -> None:
        with self.lock:
            items = list(self.maps.items())
        for mid, payload in items:
            key = f"shapeloc/maps/{mid}"
            if zenoh.KeyExpr(key).intersects(q.key_expr):
                q.reply(key, payload)

    def _map_put(self, s: zenoh.Sample) -> None:
        mid = str(s.key_expr).split("/")[-1]
        with self.lock:
            if s.kind == zenoh.SampleKind.DELETE:
                self.maps.pop(mid, None)
            else:
                self.maps[mid] = s.payload.to_bytes()

    def _robot_put(self, s: zenoh.Sample) -> None:
        with self.lock:
            self.puts.append((str(s.key_expr), s.payload.to_bytes()))

    def close(self) -> None:
        self.held.clear()
        for e in self.entities:
            e.undeclare()


@pytest.fixture
def router() -> Iterator[tuple[zenoh.Session, str]]:
    ep = f"tcp/127.0.0.1:{free_port()}"
    with zenoh.open(zenoh_config("router", listen=[ep])) as session:
        yield session, ep


@pytest.fixture
def fake(router: tuple[zenoh.Session, str]) -> Iterator[tuple[FakeService, str]]:
    svc = FakeService(router[0])
    try:
        yield svc, router[1]
    finally:
        svc.close()


def wait_until(cond, timeout: float = 3.0) -> bool:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if cond():
            return True
        time.sleep(0.02)
    return cond()


def test_client_mode_with_nothing_listening_is_unreachable_fast() -> None:
    ep = f"tcp/127.0.0.1:{free_port()}"
    t0 = time.monotonic()
    with pytest.raises(Unreachable, match=ep.replace(".", r"\.")):
        ShapelocClient(ep)
    assert time.monotonic() - t0 < 2.0


def test_router_without_service_gives_service_timeout(router) -> None:
    with ShapelocClient(router[1], timeout=0.5) as c, pytest.raises(ServiceTimeout) as ei:
        c.health()
    assert str(ei.value) == "no shapeloc service answered on shapeloc/service/health within 0.5 s"


def test_silent_service_times_out_after_the_timeout(fake) -> None:
    svc, ep = fake
    svc.silent = True
    with ShapelocClient(ep, timeout=0.4) as c:
        t0 = time.monotonic()
        with pytest.raises(ServiceTimeout, match=r"within 0\.4 s"):
            c.health()
        elapsed = time.monotonic() - t0
    assert 0.35 <= elapsed < 2.0


def test_health_and_pose_are_decoded(fake) -> None:
    _, ep = fake
    with ShapelocClient(ep) as c:
        h = c.health()
        assert (h.status, h.version, h.robots, h.scans_processed, h.scans_rejected) == (
            "ok",
            "9.9",
            2,
            5,
            1,
        )
        p = c.get_pose("r1")
    assert p.robot_id == "r1" and p.seq == 7 and p.status == "tracking"
    np.testing.assert_allclose(p.pose, [1.0, 2.0, 0.5])


def test_reply_err_maps_to_unknown_robot_and_remote_error(fake) -> None:
    _, ep = fake
    with ShapelocClient(ep) as c:
        with pytest.raises(UnknownRobot, match="unknown robot 'ghost'"):
            c.get_pose("ghost")
        with pytest.raises(RemoteError, match="localiser crashed: bad map"):
            c.get_pose("broken")


def test_invalid_robot_id_is_rejected_before_sending(fake) -> None:
    _, ep = fake
    with ShapelocClient(ep) as c, pytest.raises(InvalidMessage, match="robot_id"):
        c.get_pose("bad id/with slash")


def test_put_list_get_delete_maps(fake) -> None:
    svc, ep = fake
    md = MapData.from_lists("room", "schematic", [[[0, 0], [4, 0], [4, 3], [0, 3], [0, 0]]])
    with ShapelocClient(ep) as c:
        assert c.list_maps() == []
        sent = c.put_map(md, confirm=True)
        assert sent.map_id == "room" and sent.kind == "schematic"
        c.put_map(Map(map_id="hall", kind="metric", polylines=[[[0, 0], [1, 1]]]), confirm=True)
        assert [m.map_id for m in c.list_maps()] == ["hall", "room"]
        got = c.get_map("room")
        np.testing.assert_allclose(got.polylines[0], md.polylines[0])
        c.delete_map("hall")
        assert wait_until(lambda: "hall" not in svc.maps)
        with pytest.raises(UnknownMap, match="'hall'"):
            c.get_map("hall")


def test_put_map_reads_a_map_file(fake, tmp_path) -> None:
    """A path goes through service.adapters.maps.files.load_map_file; --id / --kind override."""
    svc, ep = fake
    md = MapData.from_lists("room", "schematic", [[[0, 0], [4, 0], [4, 3], [0, 3], [0, 0]]])
    path = save_map_file(md, tmp_path / "room.json")
    with ShapelocClient(ep) as c:
        sent = c.put_map(path, map_id="room2", kind="metric", confirm=True)
        assert (sent.map_id, sent.kind) == ("room2", "metric")
        got = c.get_map("room2")
        assert got.kind == "metric"
        np.testing.assert_array_equal(got.polylines[0], md.polylines[0])
        with pytest.raises(InvalidMessage, match="cannot read map file"):
            c.put_map(tmp_path / "missing.json")
    assert set(svc.maps) == {"room2"}


def test_configure_and_send_scan_publish_valid_messages(fake) -> None:
    svc, ep = fake
    scan = Scan(
        seq=3,
        stamp=2.0,
        angle_min=-1.0,
        angle_increment=0.5,
        range_min=0.0,
        range_max=10.0,
        ranges=[1.0, float("nan"), 2.5, 3.0, 4.0],
    )
    with ShapelocClient(ep) as c:
        c.configure("r7", "office", "icp", (1.0, 2.0, 3.0))
        c.configure("r8", "office")
        c.send_scan("r7", scan)
        assert wait_until(lambda: len(svc.puts) == 3)
    by_key = {k: v for k, v in svc.puts}
    cfg = decode(RobotConfig, by_key["shapeloc/robots/r7/config"])
    assert cfg.map_id == "office" and cfg.method == "icp"
    np.testing.assert_allclose(cfg.initial_pose, [1.0, 2.0, 3.0])
    assert decode(RobotConfig, by_key["shapeloc/robots/r8/config"]).initial_pose is None
    assert decode(Scan, by_key["shapeloc/robots/r7/scan"]) == scan


def test_watch_poses_filters_robots_and_skips_garbage(router) -> None:
    session, ep = router
    with ShapelocClient(ep) as c:
        stream = c.watch_poses(["r1", "r3"])
        time.sleep(0.2)
        for rid in ("r1", "r2", "r3"):
            msg = PoseMsg(
                robot_id=rid,
                seq=1,
                stamp=0.0,
                pose=[0, 0, 0],
                status="lost",
                score=0.0,
                method="icp",
                map_id="m",
                latency_ms=1.0,
            )
            session.put(f"shapeloc/robots/{rid}/pose", encode(msg))
        session.put("shapeloc/robots/r1/pose", b"\xc1 not msgpack")
        got = []
        while len(got) < 2:
            item = stream.get(timeout=2.0)
            assert item is not None
            got.append(item[1].robot_id)
        assert sorted(got) == ["r1", "r3"]
        assert wait_until(lambda: (stream.drain(), stream.rejected)[1] == 1)
        assert stream.get(timeout=0.1) is None


def test_callbacks_errors_watcher_and_wrapped_session(router) -> None:
    session, ep = router
    got_poses: list[str] = []
    got_truth: list[int] = []
    with ShapelocClient(session=session) as wrapped:
        wrapped.watch_poses("r2", callback=lambda m: got_poses.append(m.robot_id))
        wrapped.watch_truth(["r2"], callback=lambda t: got_truth.append(t.seq))
        errors = wrapped.errors()
        time.sleep(0.2)
        with ShapelocClient(ep) as c:
            for rid in ("r1", "r2"):
                msg = PoseMsg(
                    robot_id=rid,
                    seq=1,
                    stamp=0.0,
                    pose=[0, 0, 0],
                    status="tracking",
                    score=1.0,
                    method="shape",
                    map_id="m",
                    latency_ms=1.0,
                )
                c.session.put(f"shapeloc/robots/{rid}/pose", encode(msg))
                c.session.put(
                    f"shapeloc/robots/{rid}/truth",
                    encode(Truth(seq=4, stamp=0.0, pose=[1.0, 2.0, 3.0])),
                )
            c.session.put(
                "shapeloc/errors", encode(ErrorNotice(key="shapeloc/robots/x/scan", error="bad"))
            )
            assert wait_until(lambda: got_poses == ["r2"] and got_truth == [4])
            item = errors.get(timeout=2.0)
        assert item is not None and item[1].error == "bad"
    assert not session.is_closed()  # a wrapped session belongs to its owner
