"""Node logic without a network: a fake Zenoh session records what the node publishes
(tests/service/node/harness.py; the ``harness`` fixture is in conftest.py).

Covers validation -> error notice mapping for maps, configs and scans, map delete / re-put,
queries, health counters, shard filtering and restore from the state directory (also with a
corrupt or invalid state and ``--reset-state``). Uses ``--workers 0`` (in-process) and the ICP
method on a small room so that it runs in a few seconds. The latest-wins slots are in
test_scheduler.py, the assignment in test_workers.py, worker crashes and busy workers in
test_compute.py.
"""

from __future__ import annotations

import time
from pathlib import Path

import msgpack
import numpy as np
import pytest

from schemas.codec import decode, encode
from schemas.limits import MAX_PAYLOAD_BYTES
from schemas.messages import Health, Map, PoseMsg, RobotConfig
from service.core.sensor.raycast import RayCaster
from service.node.node import MAX_SCAN_BYTES
from tests.service.node.harness import (
    ROOM,
    START,
    FakeSample,
    Harness,
    room_segments,
    wait_for,
    wait_notices,
)


def test_declares_token_and_tracks_robot(harness: Harness) -> None:
    h = harness
    assert h.session.tokens == ["shapeloc/service/alive/test-node"]
    h.put_map()
    h.put_config()
    truth = [START + np.array([0.02 * i, 0.01 * i, 0.0]) for i in range(5)]
    for i, p in enumerate(truth):
        h.put_scan("r1", i, p)
        wait_for(lambda i=i: len(h.poses()) == i + 1)
    poses = h.poses()
    assert [p.seq for p in poses] == [0, 1, 2, 3, 4]
    assert poses[-1].stamp == pytest.approx(0.4)
    assert np.linalg.norm(poses[-1].pose[:2] - truth[-1][:2]) < 0.05
    assert poses[-1].method == "icp" and poses[-1].map_id == "room"
    assert all(0.0 <= p.latency_ms < 5000.0 for p in poses)
    hl = h.health()
    assert (hl.robots, hl.maps, hl.scans_processed, hl.scans_rejected) == (1, 1, 5, 0)
    assert h.session.notices() == []


@pytest.mark.parametrize(
    ("key", "payload", "needle"),
    [
        ("shapeloc/maps/room", b"\xc1garbage", "InvalidMessage"),
        ("shapeloc/maps/other", None, "does not match"),
        ("shapeloc/maps/room", msgpack.packb({"map_id": "room", "kind": "metric"}), "polylines"),
        (
            "shapeloc/maps/room",
            msgpack.packb({"map_id": "room", "kind": "metric", "polylines": [[[0, 0]]]}),
            "polylines[0]",
        ),
        ("shapeloc/robots/r1/config", msgpack.packb({"map_id": "nomap"}), "UnknownMap"),
        ("shapeloc/robots/r1/config", msgpack.packb({"map_id": 5}), "map_id"),
        (
            "shapeloc/robots/r1/config",
            msgpack.packb({"map_id": "room", "method": "icp", "initial_pose": None}),
            "LocalizationError",
        ),
        ("shapeloc/robots/r1/config", b"[1, 2", "InvalidMessage"),
    ],
)
def test_bad_control_messages_get_notices(
    harness: Harness, key: str, payload: bytes | None, needle: str
) -> None:
    h = harness
    if "config" in key and b"nomap" not in (payload or b""):
        h.put_map()
    if payload is None:
        payload = encode(Map(map_id="room", kind="metric", polylines=ROOM))
    h.put(key, payload)
    notes = wait_notices(h, 1)
    assert notes[-1].key == key
    assert needle in notes[-1].error
    assert h.health().robots == 0  # nothing half-applied


def test_config_refused_keeps_previous(harness: Harness) -> None:
    h = harness
    h.put_map()
    h.put_config()
    h.put(
        "shapeloc/robots/r1/config",
        msgpack.packb({"map_id": "room", "method": "icp", "initial_pose": None}),
    )
    wait_notices(h, 1)
    assert h.node.configs["r1"].initial_pose is not None
    h.put_scan("r1", 0, START)
    wait_for(lambda: len(h.poses()) == 1)


def test_bad_scans_get_notices_and_good_robot_continues(harness: Harness) -> None:
    h = harness
    h.put_map()
    h.put_config("r1")
    h.put_config("r2")
    bad: list[tuple[str, bytes, str]] = [
        ("shapeloc/robots/r9/scan", msgpack.packb(h.scan_msg(0, START)), "UnknownRobot"),
        ("shapeloc/robots/r2/scan", b"\xc1\xc1", "InvalidMessage"),
        (
            "shapeloc/robots/r2/scan",
            msgpack.packb(h.scan_msg(0, START, stamp=float("nan"))),
            "stamp",
        ),
        ("shapeloc/robots/r2/scan", msgpack.packb({**h.scan_msg(0, START), "seq": "7"}), "seq"),
        (
            "shapeloc/robots/r2/scan",
            msgpack.packb(h.scan_msg(0, START, ranges=[1.0] * 1_000_000)),
            str(MAX_SCAN_BYTES),
        ),
        (
            "shapeloc/robots/r2/scan",
            msgpack.packb(h.scan_msg(0, START, ranges=[1.0] * 10_000)),
            "ranges: 10000 elements exceeds",
        ),
        ("shapeloc/robots/r2/scan", b"\x00" * (MAX_PAYLOAD_BYTES + 1), "exceeds"),
        ("shapeloc/robots/r2/scan", b"\x00" * (MAX_SCAN_BYTES + 1), str(MAX_SCAN_BYTES)),
        (
            "shapeloc/robots/r2/scan",
            msgpack.packb(h.scan_msg(0, START, angle_increment=-0.1)),
            "angle_increment",
        ),
    ]
    for i, (key, payload, needle) in enumerate(bad):
        h.put(key, payload)
        notes = wait_notices(h, i + 1)
        assert notes[-1].key == key
        assert needle in notes[-1].error, notes[-1].error
        h.put_scan("r1", i, START)  # the well-behaved robot keeps getting poses
        wait_for(lambda i=i: len(h.poses("r1")) == i + 1)
    hl = h.health()
    assert hl.scans_rejected == len(bad)
    assert hl.scans_processed == len(bad)
    assert hl.errors is not None
    assert hl.errors["scan.UnknownRobot"] == 1
    assert hl.errors["scan.InvalidMessage"] == len(bad) - 1


def test_json_scan_accepted(harness: Harness) -> None:
    import json

    h = harness
    h.put_map()
    h.put_config()
    wire = h.scan_msg(3, START)
    h.put("shapeloc/robots/r1/scan", json.dumps(wire).encode(), json=True)
    wait_for(lambda: len(h.poses()) == 1)
    assert h.poses()[0].seq == 3


def test_map_delete_then_reput(harness: Harness) -> None:
    h = harness
    h.put_map()
    h.put_config()
    h.put_scan("r1", 0, START)
    wait_for(lambda: len(h.poses()) == 1)
    h.put("shapeloc/maps/room", b"", delete=True)
    assert h.node.maps == {}
    h.put_scan("r1", 1, START)
    notes = wait_notices(h, 1)
    assert "UnknownMap" in notes[-1].error and "waits" in notes[-1].error
    assert h.health().robots == 1  # kept, waiting
    h.put("shapeloc/maps/room", b"", delete=True)
    assert "not stored" in wait_notices(h, 2)[-1].error
    h.put_map()
    h.put_scan("r1", 2, START)
    wait_for(lambda: len(h.poses()) == 2)
    assert np.linalg.norm(h.poses()[-1].pose[:2] - START[:2]) < 0.05


def test_map_replaced_robot_relocalises_on_new_map(harness: Harness) -> None:
    h = harness
    h.put_map()
    h.put_config()
    h.put_scan("r1", 0, START)
    wait_for(lambda: len(h.poses()) == 1)
    shifted = [(np.array(p) + np.array([0.3, 0.0])).tolist() for p in ROOM]
    h.put_map(polylines=shifted)  # the same world, 0.3 m further along x in the map frame
    h.caster = RayCaster(room_segments(shifted))
    for i in range(1, 6):
        h.put_scan("r1", i, START + np.array([0.3, 0.0, 0.0]))
        wait_for(lambda i=i: len(h.poses()) == i + 1)
    worker = h.node.links[0].worker
    loc = worker.core.robots["r1"].localizer  # type: ignore[union-attr]
    assert loc is not None
    np.testing.assert_allclose(loc.map_data.polylines[0], np.array(shifted[0]))
    # ICP restarts from the last pose on the new map and converges to the shifted truth
    assert abs(h.poses()[-1].pose[0] - (START[0] + 0.3)) < 0.05


def test_queries(harness: Harness) -> None:
    h = harness
    h.put_map()
    h.put_config()
    q = h.query("shapeloc/robots/r1/pose")
    assert q.replies == [] and b"no estimate yet" in q.errors[0]
    h.put_scan("r1", 0, START)
    wait_for(lambda: len(h.poses()) == 1)
    q = h.query("shapeloc/robots/r1/pose")
    assert q.replies[0][0] == "shapeloc/robots/r1/pose"
    assert decode(PoseMsg, q.replies[0][1]).seq == 0
    q = h.query("shapeloc/robots/*/pose")
    assert [k for k, _ in q.replies] == ["shapeloc/robots/r1/pose"] and q.errors == []
    q = h.query("shapeloc/robots/ghost/pose")
    assert q.replies == [] and b"unknown robot 'ghost'" in q.errors[0]
    q = h.query("shapeloc/maps/*")
    assert decode(Map, q.replies[0][1]).map_id == "room"
    q = h.query("shapeloc/maps/nope")
    assert q.replies == [] and b"unknown map" in q.errors[0]
    q = h.query("shapeloc/service/health")
    hl = decode(Health, q.replies[0][1])
    assert (hl.status, hl.robots, hl.maps, hl.instance_id) == ("ok", 1, 1, "test-node")


def _odom_of(pose: np.ndarray) -> list[float]:
    """The robot's odometry pose for a map pose: the odometry frame is the map frame moved
    by (5 m, -3 m) and turned by 1 rad."""
    c, s = np.cos(1.0), np.sin(1.0)
    x, y = c * pose[0] - s * pose[1] + 5.0, s * pose[0] + c * pose[1] - 3.0
    return [float(x), float(y), float(pose[2] + 1.0)]


def test_restore_resumes_odometry_increment(tmp_path: Path) -> None:
    """The odometry pose of the last accepted scan is saved with its pose: after a restart the
    next scan's increment (here a 0.7 rad turn, which ICP alone does not follow) is used."""
    h = Harness(tmp_path)
    h.put_map()
    h.put_config()
    path = [START + np.array([0.05 * i, 0.02 * i, 0.01 * i]) for i in range(3)]
    for i, pose in enumerate(path):
        h.put_scan("r1", i, pose, odom=_odom_of(pose))
        wait_for(lambda i=i: len(h.poses()) == i + 1)
    h.put_scan("r1", 3, path[-1])  # no odometry: the remembered one stays that of seq 2
    wait_for(lambda: len(h.poses()) == 4)
    h.node.stop()
    h2 = Harness(tmp_path)
    try:
        np.testing.assert_allclose(h2.node.odoms["r1"], _odom_of(path[-1]), atol=1e-12)
        turned = path[-1] + np.array([0.15, 0.1, 0.7])
        h2.put_scan("r1", 10, turned, odom=_odom_of(turned))
        wait_for(lambda: len(h2.poses()) == 1)
        got = h2.poses()[0].pose
        assert np.linalg.norm(got[:2] - turned[:2]) < 0.05
        assert abs(got[2] - turned[2]) < 0.02
    finally:
        h2.node.stop()
    h3 = Harness(tmp_path)  # a config put forgets the pose and its odometry
    try:
        h3.put_config()
        assert "r1" not in h3.node.odoms and "r1" not in h3.node.poses
    finally:
        h3.node.stop()


def test_restore_from_state(tmp_path: Path) -> None:
    h = Harness(tmp_path)
    h.put_map()
    h.put_config()
    p_end = START + np.array([0.1, 0.05, 0.02])
    for i, f in enumerate(np.linspace(0.0, 1.0, 4)):
        h.put_scan("r1", i, START + f * (p_end - START))
        wait_for(lambda i=i: len(h.poses()) == i + 1)
    last = h.poses()[-1]
    h.node.stop()
    h2 = Harness(tmp_path)
    try:
        assert set(h2.node.maps) == {"room"}
        assert set(h2.node.configs) == {"r1"}
        q = h2.query("shapeloc/robots/r1/pose")
        restored = decode(PoseMsg, q.replies[0][1])
        assert restored.seq == last.seq
        np.testing.assert_allclose(restored.pose, last.pose, atol=1e-9)
        # tracking resumes from the saved pose, not the configured initial pose
        loc = h2.node.links[0].worker.core.robots["r1"].localizer  # type: ignore[union-attr]
        assert loc is not None and loc.pose is not None
        np.testing.assert_allclose(loc.pose, last.pose, atol=1e-9)
        h2.put_scan("r1", 10, p_end)
        wait_for(lambda: len(h2.poses()) == 1)
        assert np.linalg.norm(h2.poses()[0].pose[:2] - p_end[:2]) < 0.1
    finally:
        h2.node.stop()


def test_shard_filter_ignores_other_robots(tmp_path: Path) -> None:
    h = Harness(tmp_path, robots="a$*")
    try:
        h.put_map()
        h.put_config("b1")  # not ours: ignored silently
        h.put_scan("b1", 0, START)
        h.put_config("a1")
        h.put_scan("a1", 0, START)
        wait_for(lambda: len(h.poses("a1")) == 1)
        assert h.session.notices() == []
        assert set(h.node.configs) == {"a1"}
        assert h.query("shapeloc/robots/b1/pose").errors == []  # the other shard answers
    finally:
        h.node.stop()


def test_map_config_scan_in_one_burst_are_causal(harness: Harness) -> None:
    """Map, config and scan delivered back to back through the real callback: the scan waits
    until the map and config received before it are applied (no 'unknown robot/map')."""
    h = harness
    room = encode(Map(map_id="room", kind="metric", polylines=ROOM))
    cfg = encode(RobotConfig(map_id="room", method="icp", initial_pose=list(START)))
    scan = msgpack.packb(h.scan_msg(0, START))
    for robot in ("c1", "c2", "c3"):
        h.node._on_sample(FakeSample("shapeloc/maps/room", room))
        h.node._on_sample(FakeSample(f"shapeloc/robots/{robot}/config", cfg))
        h.node._on_sample(FakeSample(f"shapeloc/robots/{robot}/scan", scan))
    wait_for(lambda: all(len(h.poses(r)) == 1 for r in ("c1", "c2", "c3")))
    assert h.session.notices() == []
    # keys that are not ours to process are ignored without a notice
    h.node._on_sample(FakeSample("shapeloc/robots/c1/pose", b"x"))
    h.node._on_sample(FakeSample("shapeloc/robots/c1/scan/extra", b"x"))
    h.node._on_sample(FakeSample("shapeloc/service/health", b"x"))
    time.sleep(0.1)
    assert h.session.notices() == []
    assert h.node.classify("shapeloc/maps/m") == ("control", "")
    assert h.node.classify("shapeloc/robots/r/scan") == ("scan", "r")
    assert h.node.classify("other/robots/r/scan") == ("other", "")


def test_config_delete_forgets_robot(harness: Harness) -> None:
    h = harness
    h.put_map()
    h.put_config()
    h.put_scan("r1", 0, START)
    wait_for(lambda: len(h.poses()) == 1)
    h.put("shapeloc/robots/r1/config", b"", delete=True)
    assert h.node.configs == {} and h.health().robots == 0
    assert h.node.state is not None and h.node.state.robots() == {}
    assert b"unknown robot" in h.query("shapeloc/robots/r1/pose").errors[0]
    h.put_scan("r1", 1, START)
    assert "UnknownRobot" in wait_notices(h, 1)[-1].error
    h.put("shapeloc/robots/r1/config", b"", delete=True)
    assert "unknown robot" in wait_notices(h, 2)[-1].error


def test_invalid_stored_pose_is_a_state_error(tmp_path: Path) -> None:
    import sqlite3

    from service.errors import StateError

    h = Harness(tmp_path)
    h.put_map()
    h.put_config()
    h.put_scan("r1", 0, START)
    wait_for(lambda: len(h.poses()) == 1)
    h.node.stop()
    db = sqlite3.connect(tmp_path / "state" / "shapeloc.sqlite3")
    db.execute("UPDATE poses SET status='teleported'")
    db.commit()
    db.close()
    with pytest.raises(StateError, match="stored pose of robot 'r1'"):
        Harness(tmp_path)


def test_reset_state_moves_a_corrupt_file_aside_and_says_so(tmp_path: Path) -> None:
    from service.errors import StateError

    state = tmp_path / "state"
    state.mkdir()
    bad = b"garbage, not sqlite" * 300
    (state / "shapeloc.sqlite3").write_bytes(bad)
    with pytest.raises(StateError, match=r"shapeloc\.sqlite3"):
        Harness(tmp_path)
    assert (state / "shapeloc.sqlite3").read_bytes() == bad  # never touched without the flag
    h = Harness(tmp_path, reset_state=True)
    try:
        hl = h.health()
        assert (hl.maps, hl.robots) == (0, 0)
        assert (hl.errors or {}).get("state.Reset") == 1
        moved = list(state.glob("shapeloc.sqlite3.bad-*"))
        assert len(moved) == 1 and moved[0].read_bytes() == bad
        h.put_map()  # the fresh state works
        assert h.node.state is not None and set(h.node.state.maps()) == {"room"}
    finally:
        h.node.stop()
    h2 = Harness(tmp_path, reset_state=True)  # a healthy state is never reset
    try:
        assert set(h2.node.maps) == {"room"}
        assert "state.Reset" not in (h2.health().errors or {})
    finally:
        h2.node.stop()


def test_reset_state_also_covers_invalid_stored_content(tmp_path: Path) -> None:
    import sqlite3

    from service.errors import StateError

    h = Harness(tmp_path)
    h.put_map()
    h.node.stop()
    db = sqlite3.connect(tmp_path / "state" / "shapeloc.sqlite3")
    db.execute("UPDATE maps SET payload=?", (msgpack.packb({"map_id": "room", "kind": "x"}),))
    db.commit()
    db.close()
    with pytest.raises(StateError, match="stored map 'room' is invalid"):
        Harness(tmp_path)
    h2 = Harness(tmp_path, reset_state=True)
    try:
        assert h2.node.maps == {} and (h2.health().errors or {}).get("state.Reset") == 1
        assert len(list((tmp_path / "state").glob("shapeloc.sqlite3.bad-*"))) == 1
    finally:
        h2.node.stop()
