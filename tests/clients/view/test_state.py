"""The live view's state (clients/view/state.py): raw samples in, page messages out, with no
Zenoh and no web server."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from clients.view.state import ViewState, scan_beams, unpack_ranges
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
    assert st.frame(1000.0)["robots"][0]["trail"] == []
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
    st = ViewState(P)
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
