"""The ROS 2 front's Zenoh side (service/ros2/front.py) on a loopback Zenoh pair, without a
service: hostile samples are rejected with an ErrorNotice and the front goes on; the graph
shows its node and endpoints with rmw_zenoh's tokens."""

from __future__ import annotations

import json
import socket
import time
from collections.abc import Iterator

import pytest
import zenoh

from schemas import codec
from schemas.messages import ErrorNotice
from schemas.ros2 import cdr, graph, types
from schemas.ros2.attachment import Attachment, encode_attachment
from service.ros2.front import Ros2Front
from service.ros2.options import Ros2Options


def _conf(mode: str, endpoint: str) -> zenoh.Config:
    c = zenoh.Config()
    c.insert_json5("mode", json.dumps(mode))
    c.insert_json5("scouting/multicast/enabled", "false")
    c.insert_json5(
        "listen/endpoints" if mode == "peer" else "connect/endpoints", json.dumps([endpoint])
    )
    return c


@pytest.fixture
def pair() -> Iterator[tuple[zenoh.Session, zenoh.Session]]:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        ep = f"tcp/127.0.0.1:{s.getsockname()[1]}"
    with zenoh.open(_conf("peer", ep)) as a, zenoh.open(_conf("client", ep)) as b:
        yield a, b


def _wait(cond, within: float = 5.0) -> bool:
    end = time.monotonic() + within
    while time.monotonic() < end:
        if cond():
            return True
        time.sleep(0.02)
    return False


def test_hostile_samples_are_rejected_and_the_front_goes_on(pair) -> None:
    front_s, robot_s = pair
    notices: list[ErrorNotice] = []
    robot_s.declare_subscriber(
        "shapeloc/errors", lambda s: notices.append(codec.decode(ErrorNotice, s.payload.to_bytes()))
    )
    with Ros2Front(front_s, Ros2Options(scan_wait=0.2)) as front:
        scan_key = graph.topic_key(0, "/robot7/scan", types.LASER_SCAN)
        tf_key = graph.topic_key(0, "/robot7/tf", types.TF_MESSAGE)
        att = encode_attachment(Attachment(1, 2, bytes(16)))
        robot_s.put(scan_key, b"\x00\x01\x00\x00garbage", attachment=att)
        robot_s.put(tf_key, b"\x7b}")  # JSON, no attachment
        robot_s.put(scan_key, b"\x00\x01\x00\x00" + b"\xff" * 64, attachment=b"\x01\x02")
        long_ns = "/" + "n" * 70
        good = cdr.encode_tf([cdr.Transform2D(cdr.Stamp(1, 0), "odom", "base_link", 0, 0, 0)])
        robot_s.put(graph.topic_key(0, f"{long_ns}/tf", types.TF_MESSAGE), good)
        robot_s.put(tf_key, good)  # a good one after the bad ones
        assert _wait(lambda: len(notices) >= 4)
        assert _wait(
            lambda: "/robot7" in front.robots and "odom" in front.robots["/robot7"].tf.frames()
        )
        text = " | ".join(n.error for n in notices)
        assert "LaserScan" in text and "TFMessage" in text and "robot id of namespace" in text
        assert front.rejected >= 4
        assert {n.key for n in notices} >= {scan_key, tf_key}


def test_the_graph_shows_the_front_node_per_namespace(pair) -> None:
    front_s, robot_s = pair
    opts = Ros2Options(namespaces=("/site_a/robot1",), domain_id=3)
    with Ros2Front(front_s, opts):

        def tokens() -> list[graph.Token]:
            out = []
            for reply in robot_s.liveliness().get("@ros2_lv/3/**", timeout=1.0):
                if reply.ok is not None:
                    out.append(graph.parse_token(str(reply.ok.key_expr)))
            return out

        assert _wait(lambda: len(tokens()) >= 11)
        toks = tokens()
        nodes = {(t.namespace, t.node_name) for t in toks if t.kind == "NN"}
        assert nodes == {("/", "shapeloc"), ("/site_a/robot1", "shapeloc")}
        eps = {(t.kind, t.topic, t.qos.encode()) for t in toks if t.kind != "NN"}  # type: ignore[union-attr]
        assert ("MS", "/site_a/robot1/scan", "2::,5:,:,:,,") in eps
        assert ("MS", "/site_a/robot1/tf_static", ":1:,1:,:,:,,") in eps
        assert ("MP", "/site_a/robot1/amcl_pose", ":1:,1:,:,:,,") in eps
        assert ("MP", "/site_a/robot1/tf", "::,100:,:,:,,") in eps
        assert ("MS", "/map", ":1:,1:,:,:,,") in eps
        zid = str(front_s.zid())
        assert all(t.zid == zid and t.domain_id == 3 for t in toks)
        ids = sorted(t.entity_id for t in toks)
        assert len(ids) == len(set(ids))  # one counter per session
