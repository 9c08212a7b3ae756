"""Round trips of every wire message through msgpack and JSON, and the core-facing helpers."""

from __future__ import annotations

import json
import math

import msgpack
import numpy as np
import pytest
import zenoh

from schemas.codec import (
    JSON_ENCODING,
    decode,
    encode,
    is_json_encoding,
    scan_arrays,
)
from schemas.messages import (
    MESSAGES,
    ErrorNotice,
    Health,
    Map,
    PoseMsg,
    RobotConfig,
    Scan,
    Truth,
    WireModel,
    wrap_pi,
)


def _scan(**over: object) -> Scan:
    fields: dict[str, object] = {
        "seq": 7,
        "stamp": 12.5,
        "angle_min": -math.pi / 2,
        "angle_increment": math.pi / 360,
        "range_min": 0.05,
        "range_max": 15.0,
        "ranges": [1.0 + 0.01 * i for i in range(361)],
        "odom": [1.0, -2.0, 0.3],
    }
    fields.update(over)
    return Scan(**fields)


def full_samples() -> list[WireModel]:
    """One instance of every message with every optional field set."""
    return [
        Map(
            map_id="office",
            kind="schematic",
            polylines=[[[0, 0], [4.5, 0], [4.5, 3.25], [0, 3.25], [0, 0]], [[1, 1], [2, 1.5]]],
            name="Office, floor 2",
        ),
        RobotConfig(map_id="office", method="icp", initial_pose=[1.0, 2.0, -0.5]),
        _scan(),
        PoseMsg(
            robot_id="r1",
            seq=7,
            stamp=12.5,
            pose=[1.0, 2.0, 3.0],
            status="tracking",
            score=0.93,
            method="shape",
            map_id="office",
            latency_ms=4.25,
            covariance=np.diag([0.01, 0.02, 0.003]),
            explained=0.8,
            ambiguity=0.1,
        ),
        Health(
            status="ok",
            version="0.1.0",
            robots=2,
            maps=1,
            scans_processed=100,
            scans_rejected=3,
            instance_id="svc-1",
            uptime_s=12.0,
            errors={"InvalidMessage": 3},
            robots_by_status={"tracking": 1, "lost": 1},
        ),
        ErrorNotice(key="shapeloc/robots/r1/scan", error="ranges: 3 bytes is not a multiple"),
        Truth(seq=7, stamp=12.5, pose=[0.5, -0.25, -3.0]),
    ]


def minimal_samples() -> list[WireModel]:
    """One instance of every message with only the required fields."""
    return [
        Map(map_id="m", kind="metric", polylines=[[[0, 0], [1, 0]]]),
        RobotConfig(map_id="m"),
        Scan(
            seq=0, stamp=0, angle_min=0, angle_increment=0.1, range_min=0, range_max=1, ranges=[1]
        ),
        PoseMsg(
            robot_id="r",
            seq=0,
            stamp=0.0,
            pose=[0, 0, 0],
            status="lost",
            score=0,
            method="lines",
            map_id="m",
            latency_ms=0,
        ),
        Health(status="ok", version="1", robots=0, maps=0, scans_processed=0, scans_rejected=0),
        ErrorNotice(key="k", error="e"),
        Truth(seq=0, stamp=0, pose=[0, 0, 0]),
    ]


def test_samples_cover_every_message() -> None:
    assert [type(m) for m in full_samples()] == list(MESSAGES)
    assert [type(m) for m in minimal_samples()] == list(MESSAGES)


@pytest.mark.parametrize("as_json", [False, True], ids=["msgpack", "json"])
@pytest.mark.parametrize("which", ["full", "minimal"])
def test_every_message_round_trips(as_json: bool, which: str) -> None:
    samples = full_samples() if which == "full" else minimal_samples()
    for msg in samples:
        data = encode(msg, json=as_json)
        back = decode(type(msg), data, JSON_ENCODING if as_json else None)
        assert back == msg, type(msg).__name__
        assert encode(back, json=as_json) == data  # stable bytes


def test_json_payload_is_plain_json_and_msgpack_a_string_keyed_map() -> None:
    for msg in full_samples():
        as_json = json.loads(encode(msg, json=True))
        as_pack = msgpack.unpackb(encode(msg), raw=False)
        assert as_json == as_pack
        assert all(isinstance(k, str) for k in as_pack)


def test_none_optionals_are_left_out_and_defaults_apply() -> None:
    cfg = RobotConfig(map_id="m")
    assert msgpack.unpackb(encode(cfg)) == {"map_id": "m", "method": "shape"}
    assert cfg.method == "shape" and cfg.initial_pose is None
    cfg2 = decode(RobotConfig, msgpack.packb({"map_id": "m", "initial_pose": None}))
    assert cfg2.initial_pose is None and cfg2.method == "shape"


def test_covariance_is_nine_row_major_floats_on_the_wire() -> None:
    cov = np.arange(9, dtype=float).reshape(3, 3)
    msg = PoseMsg(
        robot_id="r",
        seq=1,
        stamp=1.0,
        pose=[0, 0, 0],
        status="tracking",
        score=1.0,
        method="shape",
        map_id="m",
        latency_ms=1.0,
        covariance=cov,
    )
    wire = msgpack.unpackb(encode(msg))
    assert wire["covariance"] == [0.0, 1.0, 2.0, 3.0, 4.0, 5.0, 6.0, 7.0, 8.0]
    back = decode(PoseMsg, encode(msg))
    assert back.covariance is not None and back.covariance.shape == (3, 3)
    np.testing.assert_array_equal(back.covariance, cov)


def test_hypotheses_and_candidates_round_trip_and_are_optional() -> None:
    rows = [[1.0, 2.0, 0.5, 0.12], [7.0, 2.0, -3.0, 0.15]]
    fields = dict(
        robot_id="r",
        seq=1,
        stamp=1.0,
        pose=[1.0, 2.0, 0.5],
        status="initializing",
        score=0.8,
        method="shape",
        map_id="m",
        latency_ms=1.0,
    )
    msg = PoseMsg(**fields, hypotheses=5, candidates=rows)
    wire = msgpack.unpackb(encode(msg))
    assert wire["hypotheses"] == 5 and wire["candidates"] == rows
    back = decode(PoseMsg, encode(msg))
    assert back.hypotheses == 5
    assert back.candidates is not None and back.candidates.shape == (2, 4)
    np.testing.assert_array_equal(back.candidates, np.array(rows))
    plain = msgpack.unpackb(encode(PoseMsg(**fields)))
    assert "hypotheses" not in plain and "candidates" not in plain


def test_float32_bytes_ranges_round_trip() -> None:
    ranges = np.array([0.5, 1.25, np.nan, np.inf, 20.0, 3.1], dtype=np.float64)
    scan = _scan(ranges=ranges, angle_increment=0.01)
    data = encode(scan, ranges_as_bytes=True)
    wire = msgpack.unpackb(data, raw=False)
    assert isinstance(wire["ranges"], bytes) and len(wire["ranges"]) == 4 * ranges.size
    back = decode(Scan, data)
    expected = ranges.astype(np.float32).astype(np.float64)
    np.testing.assert_array_equal(back.ranges, expected)
    assert back.ranges.dtype == np.float64
    # bytes are little-endian float32, whatever the host
    raw = np.array([2.5, 7.0], dtype="<f4").tobytes()
    scan2 = decode(Scan, msgpack.packb({**msgpack.unpackb(data), "ranges": raw}))
    np.testing.assert_array_equal(scan2.ranges, [2.5, 7.0])


def test_json_scan_carries_no_return_as_null() -> None:
    scan = _scan(ranges=[1.0, math.nan, math.inf, 2.0], angle_increment=0.01)
    text = encode(scan, json=True)
    assert json.loads(text)["ranges"] == [1.0, None, None, 2.0]
    back = decode(Scan, text, "application/json")
    r, _ = scan_arrays(back)
    np.testing.assert_array_equal(r, [1.0, np.nan, np.nan, 2.0])


def test_scan_arrays_masks_every_no_return_and_computes_robot_frame_angles() -> None:
    scan = _scan(
        ranges=[0.01, 0.05, 5.0, 15.0, 15.01, math.nan, math.inf, -1.0],
        angle_min=-0.5,
        angle_increment=0.25,
    )
    r, a = scan_arrays(scan)
    np.testing.assert_array_equal(r, [np.nan, 0.05, 5.0, 15.0, np.nan, np.nan, np.nan, np.nan])
    np.testing.assert_allclose(a, -0.5 + 0.25 * np.arange(8))
    assert r.dtype == np.float64 and a.dtype == np.float64
    r[0] = 1.0  # the helper returns fresh arrays; the message stays untouched
    assert scan.ranges[0] == 0.01


def test_arrays_are_read_only_float64() -> None:
    m, _, scan, pose, *_ = full_samples()
    assert isinstance(m, Map) and isinstance(scan, Scan) and isinstance(pose, PoseMsg)
    for arr in (*m.polylines, scan.ranges, scan.odom, pose.pose, pose.covariance):
        assert isinstance(arr, np.ndarray) and arr.dtype == np.float64
        with pytest.raises(ValueError):
            arr[0] = 1.0
    assert isinstance(m.polylines, tuple) and m.polylines[0].shape == (5, 2)


def test_map_data_of() -> None:
    from service.adapters.convert import map_data_of, map_message_of

    m = full_samples()[0]
    assert isinstance(m, Map)
    md = map_data_of(m)
    assert (md.map_id, md.kind) == ("office", "schematic")
    assert len(md.polylines) == 2
    np.testing.assert_array_equal(md.polylines[1], [[1.0, 1.0], [2.0, 1.5]])
    assert md.segments().shape == (5, 4)
    back = map_message_of(md, name=m.name)
    assert (back.map_id, back.kind, len(back.polylines)) == (m.map_id, m.kind, 2)


@pytest.mark.parametrize(
    ("theta", "expected"),
    [
        (math.pi, math.pi),
        (-math.pi, math.pi),
        (3 * math.pi, math.pi),
        (1.5 * math.pi, -0.5 * math.pi),
        (-1.5 * math.pi, 0.5 * math.pi),
        (0.25, 0.25),
        (-7.0, -7.0 + 2 * math.pi),
    ],
)
def test_pose_theta_is_normalised_on_input(theta: float, expected: float) -> None:
    t = decode(Truth, msgpack.packb({"seq": 1, "stamp": 0.0, "pose": [1.0, 2.0, theta]}))
    assert -math.pi < t.pose[2] <= math.pi
    assert t.pose[2] == pytest.approx(expected, abs=1e-12)
    assert wrap_pi(theta) == pytest.approx(expected, abs=1e-12)
    cfg = RobotConfig(map_id="m", initial_pose=[0, 0, theta])
    assert cfg.initial_pose is not None and cfg.initial_pose[2] == pytest.approx(expected)


def test_unknown_keys_are_ignored() -> None:
    payload = {"seq": 3, "stamp": 1.0, "pose": [0, 0, 0], "future_field": {"a": [1, 2]}}
    t = decode(Truth, msgpack.packb(payload))
    assert t.seq == 3
    assert "future_field" not in msgpack.unpackb(encode(t))
    t2 = decode(Truth, json.dumps(payload).encode(), "application/json")
    assert t2 == t


def test_integers_are_accepted_where_floats_are_expected() -> None:
    s = decode(
        Scan,
        msgpack.packb(
            {
                "seq": 1,
                "stamp": 5,
                "angle_min": 0,
                "angle_increment": 1,
                "range_min": 0,
                "range_max": 10,
                "ranges": [1, 2, 3],
            }
        ),
    )
    assert isinstance(s.stamp, float) and s.stamp == 5.0
    np.testing.assert_array_equal(s.ranges, [1.0, 2.0, 3.0])


def test_numpy_inputs_are_accepted_when_building_in_python() -> None:
    pose = PoseMsg(
        robot_id="r",
        seq=np.int64(4),
        stamp=np.float64(1.5),
        pose=np.array([1.0, 2.0, 0.5]),
        status="initializing",
        score=np.float32(0.5),
        method="shape",
        map_id="m",
        latency_ms=np.float64(2.0),
    )
    assert pose.seq == 4 and type(pose.seq) is int
    assert type(pose.score) is float
    data = encode(pose)
    assert decode(PoseMsg, data) == pose


@pytest.mark.parametrize(
    "encoding",
    [
        "application/json",
        "application/json;charset=utf-8",
        "APPLICATION/JSON",
        "text/json",
        zenoh.Encoding.APPLICATION_JSON,
        zenoh.Encoding.APPLICATION_JSON.with_schema("shapeloc/scan"),
    ],
)
def test_json_encodings_are_recognised(encoding: object) -> None:
    assert is_json_encoding(encoding)
    t = Truth(seq=1, stamp=2.0, pose=[1, 2, 3])
    assert decode(Truth, encode(t, json=True), encoding) == t  # type: ignore[arg-type]


@pytest.mark.parametrize(
    "encoding",
    [
        None,
        "zenoh/bytes",
        "application/msgpack",
        "application/json-seq",
        zenoh.Encoding.ZENOH_BYTES,
    ],
)
def test_other_encodings_mean_msgpack(encoding: object) -> None:
    assert not is_json_encoding(encoding)
    t = Truth(seq=1, stamp=2.0, pose=[1, 2, 3])
    assert decode(Truth, encode(t), encoding) == t  # type: ignore[arg-type]


def test_decode_accepts_zbytes_bytearray_and_memoryview() -> None:
    t = Truth(seq=9, stamp=2.0, pose=[1, 2, 3])
    data = encode(t)
    for payload in (zenoh.ZBytes(data), bytearray(data), memoryview(data)):
        assert decode(Truth, payload) == t  # type: ignore[arg-type]


def test_error_notice_make_truncates_to_limits() -> None:
    n = ErrorNotice.make("k" * 5000, "e" * 20000)
    assert len(n.key) == 1024 and len(n.error) == 8192 and n.error.endswith("...")
    assert decode(ErrorNotice, encode(n)) == n


def test_equality_distinguishes_arrays() -> None:
    a = Truth(seq=1, stamp=0.0, pose=[0, 0, 0])
    assert a != Truth(seq=1, stamp=0.0, pose=[0, 0, 1e-9])
    assert a != Truth(seq=2, stamp=0.0, pose=[0, 0, 0])
    assert a == Truth(seq=1, stamp=0.0, pose=[0.0, 0.0, 0.0])


@pytest.mark.parametrize(
    "extra", ["self", "model_config", "__class__", "__dict__", "schema_name", "model_fields", ""]
)
def test_hostile_unknown_keys_are_ignored(extra: str) -> None:
    t = decode(Truth, msgpack.packb({"seq": 1, "stamp": 0.0, "pose": [0, 0, 0], extra: [1]}))
    assert t == Truth(seq=1, stamp=0.0, pose=[0, 0, 0])
    assert Truth.schema_name == "truth"
