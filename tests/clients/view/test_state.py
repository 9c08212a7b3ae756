"""The live view's state (clients/view/state.py): raw samples in, page messages out, with no
Zenoh and no web server."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from clients.view.state import (
    MAX_BEAMS,
    STALE_S,
    ViewState,
    read_pose,
    read_scan_beams,
    scan_beams,
    unpack_ranges,
)
from schemas.codec import encode
from schemas.messages import Map, PoseMsg, Scan

P = "shapeloc"


def pose(rid: str, seq: int, x: float, y: float = 1.0, th: float = 0.5, **kw) -> bytes:
    fields = dict(
        robot_id=rid,
        seq=seq,
        stamp=100.0 + seq,
        pose=[x, y, th],
        status="tracking",
        score=0.9,
        method="shape",
        map_id="office",
        latency_ms=3.25,
    )
    fields.update(kw)
    return encode(PoseMsg(**fields))


def scan(seq: int, n: int = 181, value: float = 2.0) -> bytes:
    r = np.full(n, value)
    r[3] = np.nan
    msg = Scan(
        seq=seq,
        stamp=100.0 + seq,
        angle_min=-math.pi / 2,
        angle_increment=math.pi / (n - 1),
        range_min=0.1,
        range_max=10.0,
        ranges=r,
    )
    return encode(msg, ranges_as_bytes=True)


def square_map(map_id: str = "office") -> bytes:
    ring = [[0, 0], [4, 0], [4, 3], [0, 3], [0, 0]]
    return encode(Map(map_id=map_id, kind="schematic", polylines=[ring], name="room"))


def feed(st: ViewState, key: str, payload: bytes, t: float = 1000.0, delete: bool = False):
    st.ingest(f"{P}/{key}", delete, payload, None, t)


def test_a_pose_becomes_a_robot_with_its_fields_and_path() -> None:
    st = ViewState(P)
    for k in range(3):
        feed(st, "robots/r1/pose", pose("r1", k, 1.0 + k, explained=0.75, ambiguity=0.2), 1000 + k)
    f = st.frame(1002.5, full=True)
    (r,) = f["robots"]
    assert r["id"] == "r1" and r["status"] == "tracking" and r["seq"] == 2
    assert (r["x"], r["y"], r["th"]) == (3.0, 1.0, 0.5)
    assert r["explained"] == 0.75 and r["ambiguity"] == 0.2 and r["lat"] == 3.25
    assert r["path"] == [[1.0, 1.0], [2.0, 1.0], [3.0, 1.0]]
    assert r["age"] == 0.5 and not r["stale"]
    json.dumps(f, allow_nan=False)  # the page gets strict JSON


def test_trails_carry_only_what_arrived_since_the_last_tick() -> None:
    st = ViewState(P)
    feed(st, "robots/r1/pose", pose("r1", 0, 1.0))
    feed(st, "robots/r1/pose", pose("r1", 1, 2.0))
    assert st.frame(1000.0)["robots"][0]["trail"] == [[1.0, 1.0], [2.0, 1.0]]
    st.end_tick(1000.0)
    assert "trail" not in st.frame(1000.0)["robots"][0]  # nothing new: no trail sent
    feed(st, "robots/r1/pose", pose("r1", 2, 3.0))
    assert st.frame(1000.0)["robots"][0]["trail"] == [[3.0, 1.0]]
    # a page connecting now gets the whole path
    assert len(st.frame(1000.0, full=True)["robots"][0]["path"]) == 3


def test_a_search_shows_candidates_but_its_jumping_pose_is_not_a_path() -> None:
    st = ViewState(P)
    cand = [[1.0, 2.0, 0.1, 0.3], [5.0, 6.0, -1.0, 0.4]]
    feed(
        st,
        "robots/r1/pose",
        pose("r1", 0, 0.0, status="initializing", hypotheses=7, candidates=cand),
    )
    r = st.frame(1000.0, full=True)["robots"][0]
    assert r["status"] == "initializing" and r["hyp"] == 7 and r["cand"] == cand
    assert r["path"] == []
    feed(st, "robots/r1/pose", pose("r1", 1, 1.0))
    r = st.frame(1000.0, full=True)["robots"][0]
    assert "cand" not in r and r["path"] == [[1.0, 1.0]]


def test_the_scan_drawn_is_the_one_the_pose_answers_decoded_once_on_demand() -> None:
    st = ViewState(P, max_beams=360)
    for k in range(4):
        feed(st, "robots/r1/scan", scan(k, value=1.0 + k))
    assert st.decoded_scans == 0  # arriving scans are kept raw
    feed(st, "robots/r1/pose", pose("r1", 2, 1.0))
    beams = st.frame(1000.0)["robots"][0]["scan"]
    r = unpack_ranges(beams)
    assert beams["seq"] == 2 and r[0] == 3.0 and np.isnan(r[3]) and r.size == 181
    assert st.decoded_scans == 2  # seq 3 (newer than the pose), then seq 2
    st.frame(1000.0)
    assert st.decoded_scans == 2  # cached
    # a robot no page shows: its scans are not decoded at all
    feed(st, "robots/r2/scan", scan(0))
    feed(st, "robots/r2/pose", pose("r2", 0, 1.0))
    f = st.frame(1000.0, with_scan=lambda rid: rid == "r1")
    assert "scan" not in next(r for r in f["robots"] if r["id"] == "r2")
    assert st.decoded_scans == 2


def test_a_pose_whose_scan_is_gone_draws_no_scan() -> None:
    st = ViewState(P, scan_ring=2)
    for k in range(5):
        feed(st, "robots/r1/scan", scan(k))
    feed(st, "robots/r1/pose", pose("r1", 1, 1.0))
    assert "scan" not in st.frame(1000.0)["robots"][0]


def test_scan_beams_are_thinned_and_rounded() -> None:
    from schemas.codec import decode

    b = scan_beams(decode(Scan, scan(0, n=721, value=1.23456)), max_beams=360)
    r = unpack_ranges(b)
    assert r.size == 241 and r[0] == pytest.approx(1.235)  # every 3rd beam: 241 <= 360
    assert np.isnan(r[1])  # beam 3 of the scan, a NaN
    assert b["da"] == pytest.approx(3 * math.pi / 720) and b["u"] == 0.001
    # a long-range laser is sent in centimetres; what is beyond range_max is no return
    far = Scan(
        seq=0,
        stamp=0.0,
        angle_min=0.0,
        angle_increment=0.01,
        range_min=0.1,
        range_max=120.0,
        ranges=[110.004, 130.0, 0.05, 3.0],
    )
    b = scan_beams(far)
    assert b["u"] == 0.01
    np.testing.assert_allclose(unpack_ranges(b), [110.0, np.nan, np.nan, 3.0])


def test_maps_are_stored_versioned_and_deleted() -> None:
    st = ViewState(P)
    feed(st, "maps/office", square_map())
    v = st.maps_version
    msg = st.maps_message()
    assert [m["id"] for m in msg["maps"]] == ["office"]
    assert msg["maps"][0]["bounds"] == [0.0, 0.0, 4.0, 3.0]
    assert msg["maps"][0]["kind"] == "schematic"
    feed(st, "maps/office", square_map())  # the same map again: nothing to resend
    assert st.maps_version == v
    feed(st, "maps/office", b"", delete=True)
    assert st.maps_message()["maps"] == [] and st.maps_version == v + 1


def test_the_maps_robots_use_but_the_view_lacks_are_reported() -> None:
    st = ViewState(P)
    feed(st, "robots/r1/pose", pose("r1", 0, 1.0))
    assert st.missing_maps() == {"office"}
    feed(st, "maps/office", square_map())
    assert st.missing_maps() == set()


@pytest.mark.parametrize(
    ("key", "payload", "reason"),
    [
        ("robots/r1/pose", b"\xc1garbage", "pose: msgpack"),
        ("robots/r1/pose", pose("other", 0, 1.0), "differs from the key"),
        ("robots/r1/pose", pose("r1", 0, 1.0)[:-3], "pose: msgpack: truncated"),
        ("robots/bad id!/pose", pose("r1", 0, 1.0), "robot_id: 'bad id!' is not"),
        ("maps/m1", square_map("m2"), "map: map_id"),
        ("elsewhere/x", b"1", "key: not a robot or map key"),
    ],
)
def test_untrusted_samples_are_counted_and_change_nothing(key, payload, reason) -> None:
    st = ViewState(P)
    feed(st, key, payload)
    assert st.robots == {} and st.maps == {}
    assert sum(st.rejected.values()) == 1
    assert any(reason in r for r in st.rejected), st.rejected


def test_a_scan_that_does_not_decode_is_counted_when_it_is_needed() -> None:
    st = ViewState(P)
    feed(st, "robots/r1/scan", b"\x93\x01\x02")  # an array, not a map
    feed(st, "robots/r1/pose", pose("r1", 0, 1.0))
    r = st.frame(1000.0)["robots"][0]
    assert "scan" not in r and st.rejected and st.frame(1000.0)["rejected"] == 1


def test_the_network_cannot_make_the_view_keep_unbounded_robots_or_maps() -> None:
    st = ViewState(P, max_robots=3, max_maps=1)
    for k in range(10):
        feed(st, f"robots/r{k}/pose", pose(f"r{k}", 0, 1.0))
        feed(st, f"maps/m{k}", square_map(f"m{k}"))
    assert len(st.robots) == 3 and len(st.maps) == 1
    assert st.rejected["robots: more than 3"] == 7 and st.rejected["maps: more than 1"] == 9


def test_a_robot_changing_maps_starts_a_new_path() -> None:
    st = ViewState(P)
    feed(st, "robots/r1/pose", pose("r1", 0, 1.0))
    feed(st, "robots/r1/pose", pose("r1", 1, 2.0, map_id="other"))
    assert st.frame(1000.0, full=True)["robots"][0]["path"] == [[2.0, 1.0]]


def test_silent_robots_turn_stale_then_are_forgotten() -> None:
    from clients.view.state import FORGET_S, STALE_S

    st = ViewState(P)
    feed(st, "robots/r1/pose", pose("r1", 0, 1.0), t=1000.0)
    assert st.frame(1000.0 + STALE_S + 1)["robots"][0]["stale"]
    st.end_tick(1000.0 + FORGET_S + 1)
    assert st.robots == {}


def test_the_pose_rate_is_measured_over_the_last_two_seconds() -> None:
    st = ViewState(P)
    for k in range(30):  # 10 Hz for 3 s
        feed(st, "robots/r1/pose", pose("r1", k, 1.0), t=1000.0 + 0.1 * k)
    assert st.frame(1002.9)["robots"][0]["hz"] == 10.0
    assert st.frame(1010.0)["robots"][0]["hz"] == 0.0


def test_delta_frames_carry_only_the_robots_that_changed() -> None:
    st = ViewState(P)
    for rid in ("r1", "r2"):
        feed(st, f"robots/{rid}/pose", pose(rid, 0, 1.0), t=1000.0)
    f = st.frame(1000.1, delta=True)
    assert [r["id"] for r in f["robots"]] == ["r1", "r2"] and f["key"] is False
    st.end_tick(1000.1)
    feed(st, "robots/r2/pose", pose("r2", 1, 2.0), t=1000.2)
    assert [r["id"] for r in st.frame(1000.2, delta=True)["robots"]] == ["r2"]
    st.end_tick(1000.2)
    assert st.frame(1000.3, delta=True)["robots"] == []  # nothing new
    key = st.frame(1000.3)
    assert key["key"] is True and [r["id"] for r in key["robots"]] == ["r1", "r2"]
    # turning stale is a change too: the page learns it without waiting for a key frame
    st.end_tick(1000.3)
    f = st.frame(1000.0 + STALE_S + 0.1, delta=True)
    assert [(r["id"], r["stale"]) for r in f["robots"]] == [("r1", True)]


def test_positions_are_sent_to_a_tenth_of_a_millimetre() -> None:
    st = ViewState(P)
    feed(st, "robots/r1/pose", pose("r1", 0, 1.23456789, y=-2.00004999, th=0.123456))
    r = st.frame(1000.0)["robots"][0]
    assert (r["x"], r["y"], r["th"]) == (1.2346, -2.0, 0.1235)


def test_the_lean_readers_agree_with_the_full_decode() -> None:
    from schemas.codec import decode

    cov = [0.04, 0.0, 0.0, 0.0, 0.01, 0.0, 0.0, 0.0, 0.002]
    cand = [[1.0, 2.0, 4.0, 0.3]]  # theta beyond pi: wrapped as the wire model does
    raw = pose("r1", 5, 1.5, covariance=cov, hypotheses=3, candidates=cand, explained=0.5)
    p = read_pose(raw, None)
    m = decode(PoseMsg, raw)
    assert (p.robot_id, p.seq, p.status, p.map_id, p.method) == ("r1", 5, "tracking", "office",
                                                                 "shape")  # fmt: skip
    assert p.pose == tuple(m.pose) and p.cov_xy == (0.04, 0.0, 0.01)
    assert p.candidates == np.round(m.candidates, 4).tolist() and p.hypotheses == 3
    assert read_pose(encode(m, json=True), "application/json") == p  # JSON: the full decode
    for n in (181, 720):
        payload = scan(7, n=n, value=3.21)
        lean = read_scan_beams(payload, None)
        assert lean == scan_beams(decode(Scan, payload))
        assert unpack_ranges(lean).size <= MAX_BEAMS


@pytest.mark.parametrize(
    ("field", "value", "reason"),
    [
        ("pose", [1.0, math.nan, 0.0], "pose: must be finite"),
        ("pose", [1.0, 2.0], "pose: must be 3 numbers"),
        ("pose", [1.0, "2", 0.0], "pose: must be 3 numbers"),
        ("seq", -1, "seq: must be an integer"),
        ("seq", True, "seq: must be an integer"),
        ("status", "", "status: must be a string"),
        ("status", 5, "status: must be a string"),
        ("map_id", "no such/id", "map_id:"),
        ("latency_ms", math.inf, "latency_ms: must be a finite number"),
        ("explained", 1.5, "explained: must be in [0, 1]"),
        ("covariance", [1.0] * 8, "covariance: must be 9 numbers"),
        ("candidates", [[1.0, 2.0, 3.0]] * 2, "candidates: must be 4 numbers"),
        ("candidates", [[1.0, 2.0, 3.0, 4.0]] * 99, "candidates: must be at most"),
    ],
)
def test_the_lean_pose_reader_refuses_what_it_cannot_draw(field, value, reason) -> None:
    import msgpack

    obj = msgpack.unpackb(pose("r1", 0, 1.0))
    obj[field] = value
    st = ViewState(P)
    feed(st, "robots/r1/pose", msgpack.packb(obj))
    assert st.robots == {} and any(reason in r for r in st.rejected), st.rejected


def test_a_status_the_view_does_not_know_is_kept() -> None:
    import msgpack

    obj = msgpack.unpackb(pose("r1", 0, 1.0))
    obj["status"] = "docking"  # a newer service: drawn grey, not refused
    st = ViewState(P)
    feed(st, "robots/r1/pose", msgpack.packb(obj))
    assert st.frame(1000.0)["robots"][0]["status"] == "docking"


def test_a_scan_with_bad_fields_is_counted() -> None:
    import msgpack

    obj = msgpack.unpackb(scan(0))
    obj["ranges"] = obj["ranges"][:-1]  # not a whole number of float32
    st = ViewState(P)
    feed(st, "robots/r1/scan", msgpack.packb(obj))
    feed(st, "robots/r1/pose", pose("r1", 0, 1.0))
    assert "scan" not in st.frame(1000.0)["robots"][0]
    assert any("ranges" in r for r in st.rejected), st.rejected
