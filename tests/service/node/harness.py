"""The fake-Zenoh harness of the node tests (no network): a fake session records what the
node publishes, :class:`Harness` runs a :class:`~service.node.node.ServiceNode` on it (``--workers
0``, in-process, unless told otherwise) with ICP on a small room, and feeds it maps, configs,
scans and queries. The ``harness`` fixture is in conftest.py; test modules import the rest
(``from tests.service.node.harness import ...``)."""

from __future__ import annotations

import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import msgpack
import numpy as np
import zenoh

from schemas.codec import decode, encode
from schemas.messages import ErrorNotice, Health, Map, PoseMsg, RobotConfig
from service.core.sensor.raycast import RayCaster
from service.node.node import ServiceNode
from service.node.settings import ServiceSettings

ROOM = [[[0.0, 0.0], [6.0, 0.0], [6.0, 4.0], [0.0, 4.0], [0.0, 0.0]], [[2.0, 1.0], [3.0, 1.0]]]
ANGLES = np.linspace(-np.pi / 2, np.pi / 2, 181)
START = np.array([1.0, 1.5, 0.2])


# --------------------------------------------------------------------------- fake zenoh


class FakePublisher:
    def __init__(self, sink: list[tuple[str, bytes]], key: str) -> None:
        self.sink, self.key = sink, key

    def put(self, payload: bytes, encoding: Any = None) -> None:
        self.sink.append((self.key, bytes(payload)))

    def undeclare(self) -> None:
        pass


class FakeEntity:
    def undeclare(self) -> None:
        pass


class FakeSession:
    """Records puts; keeps the callbacks the node declares."""

    def __init__(self) -> None:
        self.puts: list[tuple[str, bytes]] = []
        self.subs: dict[str, Callable[[Any], None]] = {}
        self.tokens: list[str] = []

    def declare_publisher(self, key: str) -> FakePublisher:
        return FakePublisher(self.puts, key)

    def declare_subscriber(self, key: str, cb: Callable[[Any], None]) -> FakeEntity:
        self.subs[key] = cb
        return FakeEntity()

    def declare_queryable(self, key: str, cb: Callable[[Any], None]) -> FakeEntity:
        return FakeEntity()

    def liveliness(self) -> FakeSession:
        return self

    def declare_token(self, key: str) -> FakeEntity:
        self.tokens.append(key)
        return FakeEntity()

    def put(self, key: str, payload: bytes, encoding: Any = None) -> None:
        self.puts.append((key, bytes(payload)))

    def on(self, key: str) -> list[bytes]:
        return [p for k, p in self.puts if k == key]

    def notices(self) -> list[ErrorNotice]:
        return [decode(ErrorNotice, p) for p in self.on("shapeloc/errors")]


class FakeSample:
    def __init__(self, key: str, payload: bytes, delete: bool = False, json: bool = False):
        self.key_expr = zenoh.KeyExpr(key)
        self.payload = zenoh.ZBytes(payload)
        self.encoding = zenoh.Encoding("application/json" if json else "application/msgpack")
        self.kind = zenoh.SampleKind.DELETE if delete else zenoh.SampleKind.PUT


class FakeQuery:
    def __init__(self, key: str) -> None:
        self.key_expr = zenoh.KeyExpr(key)
        self.replies: list[tuple[str, bytes]] = []
        self.errors: list[bytes] = []

    def reply(self, key: str, payload: bytes, encoding: Any = None) -> None:
        self.replies.append((str(key), bytes(payload)))

    def reply_err(self, payload: bytes) -> None:
        self.errors.append(bytes(payload))

    def drop(self) -> None:
        pass


def wait_for(pred: Callable[[], bool], timeout_s: float = 10.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not pred():
        if time.monotonic() > deadline:
            raise AssertionError("condition not met in time")
        time.sleep(0.005)


# --------------------------------------------------------------------------- node fixture


class Harness:
    def __init__(self, tmp: Path, **kw: Any) -> None:
        self.tmp = tmp
        self.kw = kw
        self.session = FakeSession()
        settings = ServiceSettings(
            **{"state_dir": tmp / "state", "workers": 0, "instance_id": "test-node", **kw}
        )
        self.node = ServiceNode(settings, self.session)
        self.node.start()
        self.caster = RayCaster(room_segments(ROOM))

    def put(self, key: str, payload: bytes, delete: bool = False, json: bool = False) -> None:
        """Deliver a sample as Zenoh would (scans via callback, control synchronously)."""
        sample = FakeSample(key, payload, delete, json)
        if key.endswith("/scan"):
            self.node._on_sample(sample)
        else:
            item = self.node.control_item(sample)
            if item is not None:  # None: another shard's robot, ignored
                self.node.handle_control(item)

    def put_map(self, map_id: str = "room", polylines: list = ROOM) -> None:
        self.put(
            f"shapeloc/maps/{map_id}",
            encode(Map(map_id=map_id, kind="metric", polylines=polylines)),
        )

    def put_config(self, robot: str = "r1", map_id: str = "room", pose: Any = START) -> None:
        cfg = RobotConfig(map_id=map_id, method="icp", initial_pose=list(pose))
        self.put(f"shapeloc/robots/{robot}/config", encode(cfg))

    def scan_msg(self, seq: int, pose: np.ndarray, **over: Any) -> dict[str, Any]:
        r = self.caster.cast(pose, ANGLES, 15.0)
        wire = {
            "seq": seq,
            "stamp": float(seq) * 0.1,
            "angle_min": float(ANGLES[0]),
            "angle_increment": float(ANGLES[1] - ANGLES[0]),
            "range_min": 0.0,
            "range_max": 15.0,
            "ranges": [float(v) for v in r],
        }
        wire.update(over)
        return wire

    def put_scan(self, robot: str, seq: int, pose: np.ndarray, **over: Any) -> None:
        self.put(f"shapeloc/robots/{robot}/scan", msgpack.packb(self.scan_msg(seq, pose, **over)))

    def poses(self, robot: str = "r1") -> list[PoseMsg]:
        return [decode(PoseMsg, p) for p in self.session.on(f"shapeloc/robots/{robot}/pose")]

    def health(self) -> Health:
        return self.node.health()

    def query(self, key: str) -> FakeQuery:
        q = FakeQuery(key)
        self.node.answer(q)
        return q


def room_segments(polylines: list) -> np.ndarray:
    return np.vstack([np.hstack([np.array(p)[:-1], np.array(p)[1:]]) for p in polylines])


def wait_notices(h: Harness, n: int) -> list[ErrorNotice]:
    wait_for(lambda: len(h.session.notices()) >= n)
    return h.session.notices()
