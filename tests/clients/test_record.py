"""The MCAP recorder (clients/record.py, clients/foxglove_msgs.py) fed with wire samples, read
back with the ``mcap`` package's reader: the topics, the schemas Foxglove recognises (by name,
JSON Schema encoding, JSON messages), every message valid against its schema, in order. The
end-to-end recording of a replayed real log is tests/integration/test_record_replay.py."""

from __future__ import annotations

import base64
import io
import json
import math
from typing import Any

import numpy as np
import pytest
from mcap.reader import make_reader

from clients import foxglove_msgs as fx
from clients.record import POSE_SCHEMA, Recorder
from schemas.codec import encode
from schemas.messages import ErrorNotice, Map, PoseMsg, Scan

P = "shapeloc"


def check(value: Any, schema: dict[str, Any], where: str = "$") -> None:
    """Validate ``value`` against the JSON Schema subset Foxglove's schemas use."""
    if "oneOf" in schema:
        assert any(value == alt["const"] for alt in schema["oneOf"]), (where, value)
        return
    kind = schema.get("type")
    if kind == "object":
        assert isinstance(value, dict), where
        for name in schema.get("required", []):
            assert name in value, f"{where}.{name} is required"
        for name, sub in schema.get("properties", {}).items():
            if name in value:
                check(value[name], sub, f"{where}.{name}")
    elif kind == "array":
        assert isinstance(value, list), where
        for i, item in enumerate(value):
            check(item, schema["items"], f"{where}[{i}]")
    elif kind == "number":
        assert isinstance(value, (int, float)) and not isinstance(value, bool), where
        assert math.isfinite(value), where
    elif kind == "integer":
        assert isinstance(value, int) and not isinstance(value, bool), where
    elif kind == "string":
        assert isinstance(value, str), where
        if schema.get("contentEncoding") == "base64":
            base64.b64decode(value, validate=True)
    elif kind == "boolean":
        assert isinstance(value, bool), where
    if "minimum" in schema:
        assert value >= schema["minimum"], where
    if "maximum" in schema:
        assert value <= schema["maximum"], where


def pose_msg(seq: int, status: str = "tracking", **kw: Any) -> PoseMsg:
    fields: dict[str, Any] = dict(
        robot_id="r1",
        seq=seq,
        stamp=50.0 + 0.1 * seq,
        pose=[1.0 + seq, 2.0, 0.5],
        status=status,
        score=0.8,
        method="shape",
        map_id="office",
        latency_ms=4.0,
    )
    fields.update(kw)
    return PoseMsg(**fields)


def scan_msg(seq: int) -> Scan:
    r = np.array([1.0, np.nan, 2.0, 30.0])  # one NaN, one beyond range_max: 2 returns
    return Scan(
        seq=seq,
        stamp=50.0 + 0.1 * seq,
        angle_min=0.0,
        angle_increment=math.pi / 2,
        range_min=0.1,
        range_max=10.0,
        ranges=r,
    )


def record(samples: list[tuple[str, bytes]], robots: set[str] | None = None) -> bytes:
    buf = io.BytesIO()
    rec = Recorder(buf, P, robots)
    for k, (key, payload) in enumerate(samples):
        rec.handle(f"{P}/{key}", payload == b"", payload, None, 1_000_000_000 + k)
    rec.finish()
    return buf.getvalue()


def read(data: bytes) -> list[tuple[str, str, str, str, dict[str, Any], int]]:
    out = []
    for schema, channel, message in make_reader(io.BytesIO(data)).iter_messages():
        out.append(
            (
                channel.topic,
                schema.name,
                schema.encoding,
                channel.message_encoding,
                json.loads(message.data),
                message.log_time,
            )
        )
        check(out[-1][4], json.loads(schema.data), channel.topic)
    return out


def test_a_run_reads_back_whole_in_order_with_foxglove_schemas() -> None:
    ring = [[0, 0], [4, 0], [4, 3], [0, 0]]
    samples = [("maps/office", encode(Map(map_id="office", kind="metric", polylines=[ring])))]
    cand = [[1.0, 2.0, 0.0, 0.2], [3.0, 1.0, 1.0, 0.4]]
    samples.append(("robots/r1/scan", encode(scan_msg(0), ranges_as_bytes=True)))
    samples.append(
        ("robots/r1/pose", encode(pose_msg(0, "initializing", hypotheses=3, candidates=cand)))
    )
    for k in range(1, 4):
        samples.append(("robots/r1/scan", encode(scan_msg(k), ranges_as_bytes=True)))
        samples.append(("robots/r1/pose", encode(pose_msg(k, explained=0.9))))
    samples.append(("errors", encode(ErrorNotice(key=f"{P}/robots/x/scan", error="bad"))))
    got = read(record(samples))

    assert all(enc == "jsonschema" and menc == "json" for _t, _n, enc, menc, _m, _l in got)
    assert [lt for *_r, lt in got] == sorted(lt for *_r, lt in got)
    by_topic: dict[str, list] = {}
    for topic, name, *_rest, msg, _lt in got:
        by_topic.setdefault(topic, []).append((name, msg))
    names = {t: {n for n, _m in v} for t, v in by_topic.items()}
    assert names == {
        "/maps/office": {"foxglove.SceneUpdate"},
        "/robots/r1/scan": {"foxglove.PointCloud"},
        "/robots/r1/pose": {"foxglove.PoseInFrame"},
        "/tf": {"foxglove.FrameTransform"},
        "/robots/r1/candidates": {"foxglove.PosesInFrame"},
        "/robots/r1/estimate": {POSE_SCHEMA},
        "/status": {"foxglove.Log"},
        "/errors": {"foxglove.Log"},
    }
    # every pose and scan, in order, stamped with the robot's stamp
    poses = [m for _n, m in by_topic["/robots/r1/pose"]]
    assert [p["pose"]["position"]["x"] for p in poses] == [1.0, 2.0, 3.0, 4.0]
    assert poses[1]["timestamp"] == {"sec": 50, "nsec": 100_000_000}
    assert all(p["frame_id"] == "office" for p in poses)
    est = [m for _n, m in by_topic["/robots/r1/estimate"]]
    assert [e["seq"] for e in est] == [0, 1, 2, 3] and est[1]["explained"] == 0.9
    clouds = [m for _n, m in by_topic["/robots/r1/scan"]]
    assert len(clouds) == 4 and all(c["frame_id"] == "r1" for c in clouds)
    pts = np.frombuffer(base64.b64decode(clouds[0]["data"]), "<f4").reshape(-1, 2)
    np.testing.assert_allclose(pts, [[1.0, 0.0], [-2.0, 0.0]], atol=1e-6)
    # the robot frame sits at the estimate: the scan is drawn at the published pose
    tf = by_topic["/tf"][2][1]
    assert (tf["parent_frame_id"], tf["child_frame_id"]) == ("office", "r1")
    q = tf["rotation"]
    assert math.isclose(2 * math.atan2(q["z"], q["w"]), 0.5)
    assert tf["translation"] == {"x": 3.0, "y": 2.0, "z": 0.0}
    # candidates during the search, then one empty list that clears them
    cands = [m["poses"] for _n, m in by_topic["/robots/r1/candidates"]]
    assert [len(c) for c in cands] == [2, 0]
    # the status log: the first status and the change
    texts = [m["message"] for _n, m in by_topic["/status"]]
    assert texts == ["r1: searching", "r1: initializing -> tracking (explained 0.90)"]
    (scene,) = [m for _n, m in by_topic["/maps/office"]]
    (line,) = scene["entities"][0]["lines"]
    assert line["type"] == fx.LINE_TYPES.index("LINE_LIST")
    assert line["indices"] == [0, 1, 1, 2, 2, 3] and len(line["points"]) == 4
    (err,) = [m for _n, m in by_topic["/errors"]]
    assert err["level"] == fx.LOG_LEVELS.index("WARNING") and "bad" in err["message"]


def test_a_map_deleted_is_removed_from_the_scene() -> None:
    ring = [[0, 0], [1, 0]]
    got = read(
        record(
            [
                ("maps/m", encode(Map(map_id="m", kind="schematic", polylines=[ring]))),
                ("maps/m", b""),
            ]
        )
    )
    assert got[1][4]["deletions"][0]["id"] == "m" and got[1][4]["entities"] == []


@pytest.mark.parametrize(
    ("key", "payload"),
    [
        ("robots/r1/pose", b"\xc1"),
        ("robots/r1/pose", encode(pose_msg(0, robot_id="other"))),
        ("robots/r1/scan", b"{}"),
        ("maps/m", encode(Map(map_id="n", kind="metric", polylines=[[[0, 0], [1, 1]]]))),
        ("errors", b"\x01"),
        ("robots/not valid/pose", encode(pose_msg(0))),
        ("somewhere/else", b"x"),
    ],
)
def test_untrusted_samples_are_counted_not_written(key: str, payload: bytes) -> None:
    buf = io.BytesIO()
    rec = Recorder(buf, P)
    rec.handle(f"{P}/{key}", False, payload, None, 1)
    stats = rec.finish()
    assert stats.messages == 0 and sum(stats.rejected.values()) == 1
    assert read(buf.getvalue()) == []


def test_only_the_chosen_robots_are_recorded() -> None:
    other = pose_msg(0, robot_id="r2")
    got = read(
        record(
            [("robots/r1/pose", encode(pose_msg(0))), ("robots/r2/pose", encode(other))],
            robots={"r1"},
        )
    )
    assert {t for t, *_ in got} == {"/tf", "/robots/r1/pose", "/robots/r1/estimate", "/status"}


def test_times_become_foxglove_times() -> None:
    assert fx.time_of(1.5) == {"sec": 1, "nsec": 500_000_000}
    assert fx.time_of(-3.0) == {"sec": 0, "nsec": 0}
    assert fx.time_of(1234567890.123456789)["sec"] == 1234567890
