"""The real service process on loopback, driven with raw Zenoh and schemas.codec.

Each test spawns ``python -m service`` on a free port (see conftest.py) and kills it at
teardown. Together about 40-60 s on the 2-core CI machine (the shape method dominates).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

import msgpack
import numpy as np
import pytest
import zenoh

from schemas.codec import decode, encode
from schemas.messages import ErrorNotice, Health, Map, PoseMsg, RobotConfig, Scan
from service.adapters.convert import map_message_of
from service.core.factory import create_localizer
from sim_publisher.office import office_metric_map, office_schematic_map
from sim_publisher.scenario import make_setup

pytestmark = [pytest.mark.integration, pytest.mark.timeout(180)]

P = "shapeloc"


class Recorder:
    """Collects decoded poses (per robot) and error notices from a client session."""

    def __init__(self, session: zenoh.Session) -> None:
        self.lock = threading.Lock()
        self.poses: dict[str, list[PoseMsg]] = {}
        self.notices: list[ErrorNotice] = []
        self.t_recv: dict[tuple[str, int], float] = {}
        session.declare_subscriber(f"{P}/robots/*/pose", self._on_pose)
        session.declare_subscriber(f"{P}/errors", self._on_error)

    def _on_pose(self, s: zenoh.Sample) -> None:
        m = decode(PoseMsg, s.payload.to_bytes(), str(s.encoding))
        with self.lock:
            self.poses.setdefault(m.robot_id, []).append(m)
            self.t_recv[(m.robot_id, m.seq)] = time.monotonic()

    def _on_error(self, s: zenoh.Sample) -> None:
        m = decode(ErrorNotice, s.payload.to_bytes(), str(s.encoding))
        with self.lock:
            self.notices.append(m)

    def count(self, robot: str) -> int:
        with self.lock:
            return len(self.poses.get(robot, []))

    def last(self, robot: str) -> PoseMsg:
        with self.lock:
            return self.poses[robot][-1]

    def errors_on(self, key_part: str) -> list[str]:
        with self.lock:
            return [n.error for n in self.notices if key_part in n.key]


def wait_for(pred: Callable[[], bool], timeout_s: float, what: str, svc: Any) -> None:
    deadline = time.monotonic() + timeout_s
    while not pred():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}\n--- service log ---\n{svc.log()}")
        time.sleep(0.01)


def put_map(s: zenoh.Session, map_data: Any, map_id: str) -> None:
    s.put(f"{P}/maps/{map_id}", encode(map_message_of(replace(map_data, map_id=map_id))))


def put_config(s: zenoh.Session, robot: str, map_id: str, method: str, pose: Any) -> None:
    cfg = RobotConfig(map_id=map_id, method=method, initial_pose=[float(v) for v in pose])
    s.put(f"{P}/robots/{robot}/config", encode(cfg))


def scan_msg(setup: Any, i: int, seq: int) -> Scan:
    r, _a = setup.scan(i)
    lz = setup.laser
    return Scan(
        seq=seq,
        stamp=float(seq) * 0.1,
        angle_min=float(lz.angle_min),
        angle_increment=float(lz.angle_increment),
        range_min=0.0,
        range_max=float(lz.config.max_range),
        ranges=np.asarray(r, dtype=np.float64),
        odom=[float(v) for v in setup.odom[i]],
    )


def wait_robots(s: zenoh.Session, n: int, svc: Any, get_health: Callable[..., Any]) -> None:
    def ok() -> bool:
        h = get_health(s)
        return h is not None and h.robots >= n

    wait_for(ok, 20.0, f"{n} robots configured", svc)


# --------------------------------------------------------------------------- tests


def test_health_and_liveliness(
    tmp_path: Path,
    spawn_service: Callable[..., Any],
    open_session: Any,
    service_health: Callable[..., Any],
) -> None:
    get_health = service_health
    svc = spawn_service(tmp_path / "state", "--instance-id", "svc-a")
    s = open_session(svc.endpoint)
    h = get_health(s)
    assert h is not None
    assert (h.status, h.robots, h.maps, h.scans_processed, h.scans_rejected) == ("ok", 0, 0, 0, 0)
    assert h.instance_id == "svc-a"
    alive = [str(r.ok.key_expr) for r in s.liveliness().get(f"{P}/service/alive/*", timeout=2.0)]
    assert alive == [f"{P}/service/alive/svc-a"]
    errs = [r.err for r in s.get(f"{P}/robots/nobody/pose", timeout=2.0)]
    assert len(errs) == 1 and errs[0] is not None
    assert b"unknown robot" in errs[0].payload.to_bytes()
    assert svc.terminate() == 0
    assert "stopped" in svc.log()


def test_two_robots_two_maps(
    tmp_path: Path,
    spawn_service: Callable[..., Any],
    open_session: Any,
    service_health: Callable[..., Any],
) -> None:
    get_health = service_health
    """Robot m on the metric map (shape), robot s on the schematic map (icp), at once; the
    service's estimates equal an offline run of the same method on the same scans."""
    svc = spawn_service(tmp_path / "state", workers=2)
    s = open_session(svc.endpoint)
    rec = Recorder(s)
    setup = make_setup(1, seed=3, max_scans=400)
    idx = list(range(0, 400, 25))  # 16 scans, 25 cm apart
    robots = {
        "m": ("office", office_metric_map(), "shape"),
        "s": ("office-schematic", office_schematic_map(), "icp"),
    }
    for _rid, (map_id, md, _meth) in robots.items():
        put_map(s, md, map_id)
    for rid, (map_id, _md, meth) in robots.items():
        put_config(s, rid, map_id, meth, setup.truth[idx[0]])
    wait_robots(s, 2, svc, get_health)
    for k, i in enumerate(idx):  # lockstep: no scan is skipped
        payload = encode(scan_msg(setup, i, k))
        for rid in robots:
            s.put(f"{P}/robots/{rid}/scan", payload)
        wait_for(lambda k=k: all(rec.count(r) == k + 1 for r in robots), 30.0, f"poses of {k}", svc)
    assert rec.notices == []
    for rid, (map_id, md, meth) in robots.items():
        got = rec.poses[rid]
        assert [p.seq for p in got] == list(range(len(idx)))
        assert all(p.map_id == map_id and p.method == meth for p in got)
        loc = create_localizer(meth, md, setup.truth[idx[0]].copy())
        for k, i in enumerate(idx):
            r, a = setup.scan(i)
            est = loc.update(r, a, setup.odom[i])
            np.testing.assert_allclose(got[k].pose, est.pose, atol=1e-9, err_msg=f"{rid} {k}")
    err_m = [
        np.hypot(*(rec.poses["m"][k].pose[:2] - setup.truth[i][:2])) for k, i in enumerate(idx)
    ]
    assert max(err_m) < 0.10, err_m  # setup 1 proximity threshold (100 mm), exact map
    h = get_health(s)
    assert h is not None and h.scans_processed == 2 * len(idx) and h.maps == 2


def test_kill9_restart_keeps_state(
    tmp_path: Path,
    spawn_service: Callable[..., Any],
    open_session: Any,
    service_health: Callable[..., Any],
) -> None:
    get_health = service_health
    state = tmp_path / "state"
    svc = spawn_service(state, "--pose-save-interval", "0.2")
    s = open_session(svc.endpoint)
    rec = Recorder(s)
    setup = make_setup(1, seed=1, max_scans=60)
    put_map(s, office_metric_map(), "office")
    put_config(s, "r1", "office", "icp", setup.truth[0])
    wait_robots(s, 1, svc, get_health)
    for k in range(6):
        s.put(f"{P}/robots/r1/scan", encode(scan_msg(setup, 10 * k, k)))
        wait_for(lambda k=k: rec.count("r1") == k + 1, 20.0, "pose", svc)
    last = rec.last("r1")
    time.sleep(0.8)  # > pose save interval
    svc.kill()  # SIGKILL: no shutdown code runs
    s.close()

    svc2 = spawn_service(state, endpoint=svc.endpoint)
    s2 = open_session(svc2.endpoint)
    h = get_health(s2)
    assert h is not None and (h.maps, h.robots) == (1, 1)
    maps = [decode(Map, r.ok.payload.to_bytes()) for r in s2.get(f"{P}/maps/*", timeout=2.0)]
    assert [m.map_id for m in maps] == ["office"]
    assert maps[0] == map_message_of(office_metric_map("office"))
    replies = list(s2.get(f"{P}/robots/r1/pose", timeout=2.0))
    assert len(replies) == 1 and replies[0].ok is not None
    restored = decode(PoseMsg, replies[0].ok.payload.to_bytes())
    assert restored.seq == last.seq
    np.testing.assert_allclose(restored.pose, last.pose, atol=1e-9)
    rec2 = Recorder(s2)
    s2.put(f"{P}/robots/r1/scan", encode(scan_msg(setup, 55, 6)))
    wait_for(lambda: rec2.count("r1") == 1, 20.0, "pose after restart", svc2)
    assert np.hypot(*(rec2.last("r1").pose[:2] - setup.truth[55][:2])) < 0.2
    # SIGTERM: clean exit, and the last pose is saved on shutdown (the periodic save is 5 s)
    assert svc2.terminate() == 0
    s2.close()
    svc3 = spawn_service(state, endpoint=svc.endpoint)
    s3 = open_session(svc3.endpoint)
    replies = list(s3.get(f"{P}/robots/r1/pose", timeout=2.0))
    assert len(replies) == 1 and replies[0].ok is not None
    assert decode(PoseMsg, replies[0].ok.payload.to_bytes()).seq == 6


def test_corrupt_state_exits_with_message(
    tmp_path: Path, spawn_service: Callable[..., Any]
) -> None:
    state = tmp_path / "state"
    state.mkdir()
    (state / "shapeloc.sqlite3").write_bytes(b"garbage, not sqlite" * 200)
    svc = spawn_service(state, wait=False)
    assert svc.proc.wait(timeout=60) == 1
    assert "state error" in svc.log() and "shapeloc.sqlite3" in svc.log()


def test_garbage_flood_does_not_stop_good_robot(
    tmp_path: Path,
    spawn_service: Callable[..., Any],
    open_session: Any,
    service_health: Callable[..., Any],
) -> None:
    get_health = service_health
    svc = spawn_service(tmp_path / "state")
    s = open_session(svc.endpoint)
    rec = Recorder(s)
    setup = make_setup(1, seed=2, max_scans=400)
    put_map(s, office_metric_map(), "office")
    put_config(s, "good", "office", "icp", setup.truth[0])
    victims = [f"v{i}" for i in range(8)]  # one robot per kind: latest-wins cannot merge them
    for v in victims:
        put_config(s, v, "office", "icp", setup.truth[0])
    wait_robots(s, 1 + len(victims), svc, get_health)
    good = scan_msg(setup, 0, 0).to_wire()
    scan_garbage: list[tuple[str, bytes]] = [
        ("v0", b"\xc1\xc1\xc1 not msgpack"),
        ("v1", msgpack.packb([1, 2, 3])),
        ("v2", msgpack.packb({**good, "seq": "seven"})),
        ("v3", msgpack.packb({**good, "stamp": float("nan")})),
        ("v4", msgpack.packb({**good, "angle_min": float("inf")})),
        ("v5", msgpack.packb({**good, "ranges": [1.0] * 1_000_000})),
        ("v6", msgpack.packb({**good, "ranges": "lots"})),
        ("v7", msgpack.packb({**good, "odom": [0.0, float("nan"), 0.0]})),
        ("noconfig", msgpack.packb(good)),
    ]
    control_garbage: list[tuple[str, bytes]] = [
        (f"{P}/maps/office2", encode(map_message_of(office_metric_map("x")))),
        (f"{P}/maps/bad", b"{not json"),
        (f"{P}/maps/bad2", msgpack.packb({"map_id": "bad2", "kind": "metric", "polylines": 3})),
        (f"{P}/robots/r9/config", encode(RobotConfig(map_id="nomap"))),
        (f"{P}/robots/r9/config", msgpack.packb({"map_id": "office", "method": "teleport"})),
    ]
    stop = threading.Event()
    sent = {"good": 0}

    def drive_good() -> None:
        k = 0
        while not stop.is_set() and k < 400:
            s.put(f"{P}/robots/good/scan", encode(scan_msg(setup, k, k)))
            sent["good"] = k + 1
            k += 1
            time.sleep(0.03)

    t = threading.Thread(target=drive_good)
    t.start()
    try:
        for _round in range(3):
            for rid, payload in scan_garbage:
                s.put(f"{P}/robots/{rid}/scan", payload)
                time.sleep(0.02)
            for key, payload in control_garbage:
                s.put(key, payload)
            s.put(
                f"{P}/robots/v2/scan",
                b'{"seq": -1}',
                encoding=zenoh.Encoding("application/json"),
            )
        n_before = rec.count("good")
        wait_for(lambda: rec.count("good") >= n_before + 10, 30.0, "good poses after flood", svc)
    finally:
        stop.set()
        t.join()
    # every kind of garbage produced its notice with a precise reason
    needles = ["msgpack", "must be a map", "seq", "stamp", "angle_min", "524288", "ranges", "odom"]
    for v, needle in zip(victims, needles, strict=True):
        errs = rec.errors_on(f"robots/{v}/scan")
        assert errs and all("InvalidMessage" in e and needle in e for e in errs), (v, errs)
    assert any(">= 0" in e for e in rec.errors_on("robots/v2/scan"))  # the JSON one
    assert any("UnknownRobot" in e for e in rec.errors_on("robots/noconfig/scan"))
    assert any("does not match" in e for e in rec.errors_on("maps/office2"))
    assert any("InvalidMessage" in e for e in rec.errors_on("maps/bad"))
    assert any("polylines" in e for e in rec.errors_on("maps/bad2"))
    r9 = rec.errors_on("robots/r9/config")
    assert any("UnknownMap" in e for e in r9) and any("method" in e for e in r9)
    h = get_health(s)
    assert h is not None and h.errors is not None
    # latest-wins may merge garbage scans of one robot, so not every one is seen, but many are
    assert h.scans_rejected >= len(victims)
    assert h.scans_rejected == sum(
        v for k, v in h.errors.items() if k.startswith("scan.") and k != "scan.Skipped"
    )
    assert h.errors.get("map.InvalidMessage", 0) >= 3
    assert h.robots == 1 + len(victims) and h.maps == 1
    # the good robot kept tracking
    last = rec.last("good")
    assert np.hypot(*(last.pose[:2] - setup.truth[last.seq][:2])) < 0.2
    assert svc.proc.poll() is None


def test_two_shards_split_the_robots(
    tmp_path: Path,
    spawn_service: Callable[..., Any],
    open_session: Any,
) -> None:
    """``--robots a$*`` and ``--robots b$*`` on two peered services: each robot is served by
    exactly one of them; a robot of neither shard gets no answer and no notice."""
    sa = spawn_service(tmp_path / "a", "--robots", "a$*", "--instance-id", "A", workers=0)
    sb = spawn_service(
        tmp_path / "b",
        "--robots",
        "b$*",
        "--instance-id",
        "B",
        "--connect",
        sa.endpoint,
        workers=0,
    )
    s = open_session(sa.endpoint)
    rec = Recorder(s)
    none = zenoh.QueryConsolidation(zenoh.ConsolidationMode.NONE)

    def healths() -> dict[str, Any]:
        out = {}
        for r in s.get(f"{P}/service/health", timeout=2.0, consolidation=none):
            if r.ok is not None:
                h = decode(Health, r.ok.payload.to_bytes())
                out[h.instance_id] = h
        return out

    setup = make_setup(1, seed=4, max_scans=5)

    def both_have_map() -> bool:  # routes between peers take a moment to converge
        put_map(s, office_metric_map(), "office")
        time.sleep(0.2)
        hs = healths()
        return set(hs) == {"A", "B"} and all(h.maps == 1 for h in hs.values())

    wait_for(both_have_map, 20.0, "both shards to store the map", sb)
    for rid in ("a1", "b1", "b2"):
        put_config(s, rid, "office", "icp", setup.truth[0])
    wait_for(
        lambda: healths().get("B") is not None and healths()["B"].robots == 2, 20.0, "configs", sb
    )
    for rid in ("a1", "b1", "b2", "c1"):
        s.put(f"{P}/robots/{rid}/scan", encode(scan_msg(setup, 0, 0)))
    wait_for(lambda: all(rec.count(r) == 1 for r in ("a1", "b1", "b2")), 20.0, "poses", sb)
    time.sleep(0.5)
    hs = healths()
    assert (hs["A"].robots, hs["A"].scans_processed) == (1, 1)
    assert (hs["B"].robots, hs["B"].scans_processed) == (2, 2)
    assert all(rec.count(r) == 1 for r in ("a1", "b1", "b2"))  # exactly one answer each
    assert rec.count("c1") == 0 and rec.notices == []  # c1 is nobody's: silently ignored
    assert [r.ok is not None for r in s.get(f"{P}/robots/b1/pose", timeout=2.0)] == [True]
