"""Untrusted payloads: every violation raises InvalidMessage with a precise reason."""

from __future__ import annotations

import json
import math
import re
from typing import Any

import msgpack
import numpy as np
import pytest

from schemas.codec import check_key_id, decode, encode
from schemas.limits import MAX_BEAMS, MAX_MAP_POINTS, MAX_PAYLOAD_BYTES, MAX_POLYLINES
from schemas.messages import Health, Map, PoseMsg, RobotConfig, Scan, Truth, WireModel
from service.errors import InvalidMessage, ShapelocError


def _scan_dict(**over: Any) -> dict[str, Any]:
    d: dict[str, Any] = {
        "seq": 1,
        "stamp": 2.0,
        "angle_min": -1.0,
        "angle_increment": 0.01,
        "range_min": 0.1,
        "range_max": 10.0,
        "ranges": [1.0, 2.0, 3.0],
    }
    d.update(over)
    return d


def _pose_dict(**over: Any) -> dict[str, Any]:
    d: dict[str, Any] = {
        "robot_id": "r1",
        "seq": 1,
        "stamp": 2.0,
        "pose": [0.0, 0.0, 0.0],
        "status": "tracking",
        "score": 0.5,
        "method": "shape",
        "map_id": "m",
        "latency_ms": 3.0,
    }
    d.update(over)
    return d


def _map_dict(**over: Any) -> dict[str, Any]:
    d: dict[str, Any] = {"map_id": "m", "kind": "metric", "polylines": [[[0, 0], [1, 0]]]}
    d.update(over)
    return d


def _reject(model: type[WireModel], payload: dict[str, Any] | bytes, reason: str) -> str:
    """Decode (msgpack) and assert InvalidMessage whose text contains ``reason``."""
    data = payload if isinstance(payload, bytes) else msgpack.packb(payload, use_bin_type=True)
    with pytest.raises(InvalidMessage) as exc:
        decode(model, data)
    text = str(exc.value)
    assert reason in text, text
    assert isinstance(exc.value, ShapelocError)
    return text


@pytest.mark.parametrize(
    ("over", "reason"),
    [
        ({"stamp": "1.0"}, "stamp: must be a number, got string"),
        ({"stamp": True}, "stamp: must be a number, got bool"),
        ({"seq": 1.0}, "seq: must be an integer, got float"),
        ({"seq": True}, "seq: must be an integer, got bool"),
        ({"seq": -1}, "seq: must be >= 0, got -1"),
        ({"seq": "3"}, "seq: must be an integer, got string"),
        ({"angle_min": None}, "angle_min: must be a number, got null"),
        ({"angle_increment": 0.0}, "angle_increment: must be > 0"),
        ({"angle_increment": -0.1}, "angle_increment: must be > 0"),
        ({"angle_increment": math.nan}, "angle_increment: must be finite"),
        ({"angle_min": math.inf}, "angle_min: must be finite"),
        ({"range_min": -0.5}, "range_min: must be >= 0"),
        ({"range_min": 10.0, "range_max": 10.0}, "range_max: must be > range_min"),
        ({"range_max": math.inf}, "range_max: must be finite"),
        ({"ranges": [1.0, "2.0"]}, "ranges[1]: must be a number or null, got string"),
        ({"ranges": [1.0, False]}, "ranges[1]: must be a number or null, got bool"),
        ({"ranges": []}, "ranges: must hold at least 1 value"),
        ({"ranges": b""}, "ranges: must hold at least 1 value"),
        ({"ranges": "1,2,3"}, "ranges: must be a list of numbers or float32 bytes, got string"),
        ({"ranges": [[1.0]]}, "ranges[0]: must be a number or null, got array"),
        ({"ranges": b"\x00\x00\x80"}, "ranges: 3 bytes is not a multiple of 4"),
        ({"ranges": [1.0] * 10**6}, "ranges: 1000000 elements exceeds limit 8192"),
        ({"ranges": b"\x00" * 4 * 10**6}, "ranges: 1000000 float32 values exceeds limit 8192"),
        ({"ranges": [1.0] * 722, "angle_increment": math.pi / 360}, "more than 2*pi"),
        ({"odom": [1.0, 2.0]}, "odom: must be [x, y, theta] (3 numbers), got 2 elements"),
        ({"odom": [1.0, 2.0, math.nan]}, "odom[2]: must be finite"),
    ],
)
def test_scan_rejections(over: dict[str, Any], reason: str) -> None:
    _reject(Scan, _scan_dict(**over), reason)


def test_scan_limits_are_inclusive() -> None:
    ok = decode(Scan, msgpack.packb(_scan_dict(ranges=[1.0] * MAX_BEAMS, angle_increment=1e-4)))
    assert ok.ranges.size == MAX_BEAMS
    full_circle = _scan_dict(ranges=[1.0] * 721, angle_increment=2 * math.pi / 720)
    assert decode(Scan, msgpack.packb(full_circle)).ranges.size == 721
    _reject(Scan, _scan_dict(ranges=[1.0] * (MAX_BEAMS + 1), angle_increment=1e-4), "exceeds limit")


@pytest.mark.parametrize("field", ["seq", "stamp", "angle_min", "ranges"])
def test_scan_missing_fields(field: str) -> None:
    d = _scan_dict()
    del d[field]
    _reject(Scan, d, f"{field}: required field missing")


@pytest.mark.parametrize(
    ("pose", "reason"),
    [
        ([0.0, 0.0, math.nan], "pose[2]: must be finite"),
        ([math.inf, 0.0, 0.0], "pose[0]: must be finite"),
        ([0.0, -math.inf, 0.0], "pose[1]: must be finite"),
        ([0.0, 0.0, 2**1100], "pose[2]: must be finite"),
        ([0.0, 0.0], "pose: must be [x, y, theta] (3 numbers), got 2 elements"),
        ([0.0, 0.0, 0.0, 0.0], "got 4 elements"),
        ([0.0, "1", 0.0], "pose[1]: must be a number, got string"),
        ([0.0, True, 0.0], "pose[1]: must be a number, got bool"),
        ({"x": 1}, "pose: must be a list [x, y, theta], got map"),
        (None, "pose: must be a list [x, y, theta], got null"),
    ],
)
def test_pose_rejections(pose: Any, reason: str) -> None:
    if isinstance(pose, list) and any(isinstance(v, int) and v > 2**64 for v in pose):
        # msgpack cannot carry such an int; JSON can.
        with pytest.raises(InvalidMessage, match=re.escape(reason)):
            decode(PoseMsg, json.dumps(_pose_dict(pose=pose)).encode(), "application/json")
        return
    _reject(PoseMsg, _pose_dict(pose=pose), reason)
    _reject(Truth, {"seq": 1, "stamp": 0.0, "pose": pose}, reason)


def test_nan_and_inf_in_json_tokens_are_rejected_in_poses() -> None:
    for token in ("NaN", "Infinity", "-Infinity"):
        text = f'{{"seq": 1, "stamp": 0.0, "pose": [0.0, 0.0, {token}]}}'.encode()
        with pytest.raises(InvalidMessage, match=re.escape("pose[2]: must be finite")):
            decode(Truth, text, "application/json")


@pytest.mark.parametrize(
    ("over", "reason"),
    [
        ({"status": "happy"}, "status: must be 'tracking', 'lost' or 'initializing'"),
        ({"score": math.nan}, "score: must be finite"),
        ({"latency_ms": "3"}, "latency_ms: must be a number, got string"),
        ({"covariance": [0.0] * 8}, "covariance: must be 9 numbers"),
        ({"covariance": [0.0] * 8 + [math.inf]}, "covariance[8]: must be finite"),
        ({"explained": 1.5}, "explained: must be in [0, 1], got 1.5"),
        ({"ambiguity": -0.1}, "ambiguity: must be in [0, 1], got -0.1"),
        ({"ambiguity": math.nan}, "ambiguity: must be finite"),
        ({"hypotheses": -1}, "hypotheses: must be >= 0"),
        ({"hypotheses": 2.5}, "hypotheses: must be an integer"),
        ({"candidates": [[0.0, 0.0, 0.0]]}, "candidates[0]: must be [x, y, theta, cost]"),
        ({"candidates": [[0.0, 0.0, 0.0, math.nan]]}, "candidates[0][3]: must be finite"),
        ({"candidates": [[0.0] * 4] * 17}, "candidates: 17 rows exceeds limit 16"),
        ({"candidates": "abc"}, "candidates: must be a list of [x, y, theta, cost] rows"),
    ],
)
def test_pose_message_rejections(over: dict[str, Any], reason: str) -> None:
    _reject(PoseMsg, _pose_dict(**over), reason)


BAD_IDS = [
    "",
    "a" * 65,
    "a/b",
    "a*",
    "*",
    "a b",
    "caf\u00e9",
    "\u0440\u043e\u0431\u043e\u0442",
    "a$b",
]


@pytest.mark.parametrize("bad", BAD_IDS, ids=lambda s: repr(s)[:12])
def test_bad_identifiers_are_rejected(bad: str) -> None:
    reason = "is not 1-64 characters of [A-Za-z0-9_.-]"
    _reject(PoseMsg, _pose_dict(robot_id=bad), f"robot_id: {repr(bad)[:20]}")
    _reject(PoseMsg, _pose_dict(robot_id=bad), reason)
    _reject(PoseMsg, _pose_dict(map_id=bad), "map_id: ")
    _reject(RobotConfig, {"map_id": bad}, reason)
    _reject(Map, _map_dict(map_id=bad), reason)


def test_good_identifiers_are_accepted() -> None:
    for good in ("a", "a" * 64, "Robot_1.left-arm", "0", "..."):
        assert RobotConfig(map_id=good).map_id == good
    _reject(RobotConfig, {"map_id": 5}, "map_id: must be a string, got int")


@pytest.mark.parametrize(
    ("over", "reason"),
    [
        ({"polylines": [[[0, 0]]]}, "polylines[0]: 1 point(s), a polyline needs at least 2"),
        ({"polylines": [[[0, 0], [1, 1]], []]}, "polylines[1]: 0 point(s)"),
        ({"polylines": []}, "polylines: must hold at least 1 polyline"),
        ({"polylines": [[[0, 0], [1, 1, 2]]]}, "polylines[0][1]: must be [x, y], got 3 elements"),
        ({"polylines": [[[0, 0], [1, "1"]]]}, "polylines[0][1][1]: must be a number, got string"),
        ({"polylines": [[[0, 0], [True, 1]]]}, "polylines[0][1][0]: must be a number, got bool"),
        ({"polylines": [[[0, 0], [1, math.nan]]]}, "polylines[0][1][1]: must be finite"),
        ({"polylines": [[[0, 0], 5]]}, "polylines[0][1]: must be [x, y], got int"),
        ({"polylines": [[0, 0]]}, "polylines[0][0]: must be [x, y], got int"),
        ({"polylines": "x"}, "polylines: must be a list of polylines, got string"),
        ({"kind": "sketch"}, "kind: must be 'metric' or 'schematic'"),
        ({"name": 3}, "name: must be a string, got int"),
    ],
)
def test_map_rejections(over: dict[str, Any], reason: str) -> None:
    _reject(Map, _map_dict(**over), reason)


def test_map_size_limits() -> None:
    too_many_lines = [[[0, 0], [1, 0]]] * (MAX_POLYLINES + 1)
    _reject(Map, _map_dict(polylines=too_many_lines), "20001 polylines exceeds limit 20000")
    big = [[[float(i), 0.0] for i in range(1000)]] * (MAX_MAP_POINTS // 1000)
    assert len(decode(Map, msgpack.packb(_map_dict(polylines=big))).polylines) == 200
    _reject(
        Map,
        _map_dict(polylines=[*big, [[0, 0], [1, 1]]]),
        f"more than {MAX_MAP_POINTS} points in total",
    )


def test_map_id_not_matching_key() -> None:
    with pytest.raises(InvalidMessage, match=r"^map_id 'a' does not match key 'b'$"):
        check_key_id("a", "b", "map_id")
    check_key_id("b", "b", "map_id")  # no error


def test_health_counters_and_extras() -> None:
    base = {
        "status": "ok",
        "version": "1",
        "robots": 1,
        "maps": 1,
        "scans_processed": 1,
        "scans_rejected": 0,
    }
    _reject(Health, {**base, "robots": -1}, "robots: must be >= 0, got -1")
    _reject(Health, {**base, "maps": 1.5}, "maps: must be an integer, got float")
    _reject(Health, {**base, "errors": {"X": -2}}, "errors['X']: must be >= 0, got -2")
    _reject(Health, {**base, "errors": [1]}, "errors: must be a map, got array")
    _reject(Health, {**base, "uptime_s": math.inf}, "uptime_s: must be finite")
    _reject(Health, {**base, "status": ""}, "status: must not be empty")
    assert decode(Health, msgpack.packb(base)).errors is None


@pytest.mark.parametrize(
    ("payload", "reason"),
    [
        (b"\xc1", "msgpack: malformed (invalid type byte)"),
        (b"\x82\xa1a", "msgpack: truncated payload"),
        (msgpack.packb({"seq": 1}) + b"\x00", "msgpack: trailing data after the message"),
        (msgpack.packb([1, 2, 3]), "message: must be a map, got array"),
        (msgpack.packb(5), "message: must be a map, got int"),
        (msgpack.packb(None), "message: must be a map, got null"),
        (msgpack.packb("x"), "message: must be a map, got string"),
        (msgpack.packb({1: 2}, strict_types=False), "message: map keys must be strings"),
        (msgpack.packb({b"seq": 2}, use_bin_type=True), "message: map keys must be strings"),
        (msgpack.packb({"a": {"b": {5: 1}}}), "message: map keys must be strings"),
        (b"", "payload: empty"),
        (b"\x81\xa1a" + b"\x91" * 5000 + b"\x01", "message: nesting deeper than 16 levels"),
        (msgpack.packb({"a": [[[[[[[[[[[[[[[[1]]]]]]]]]]]]]]]]}), "nesting deeper than 16"),
        (msgpack.packb({"k": b"\xff"}), "seq: required field missing"),
        (b"\x81\xa1\xff\x01", "msgpack: a string is not valid UTF-8"),
    ],
)
def test_malformed_msgpack(payload: bytes, reason: str) -> None:
    _reject(Truth, payload, reason)


@pytest.mark.parametrize(
    ("text", "reason"),
    [
        (b'{"seq": 1,', "json: Expecting property name enclosed in double quotes"),
        (b'{"seq": 1} x', "json: Extra data"),
        (b"[1, 2]", "message: must be a map, got array"),
        (b"\xff\xfe", "json: not UTF-8"),
        (b"[" * 100000 + b"]" * 100000, "nesting deeper than 16 levels"),
        (b'{"seq": true, "stamp": 0, "pose": [0, 0, 0]}', "seq: must be an integer, got bool"),
        (b'{"seq": 1, "stamp": "0", "pose": [0, 0, 0]}', "stamp: must be a number, got string"),
    ],
)
def test_malformed_json(text: bytes, reason: str) -> None:
    with pytest.raises(InvalidMessage) as exc:
        decode(Truth, text, "application/json")
    assert reason in str(exc.value), str(exc.value)


def test_oversize_payload_is_rejected_before_parsing() -> None:
    payload = b"\x00" * (MAX_PAYLOAD_BYTES + 1)
    _reject(Truth, payload, f"payload: {MAX_PAYLOAD_BYTES + 1} bytes exceeds limit 16777216")
    with pytest.raises(InvalidMessage, match="payload: must be bytes, got str"):
        decode(Truth, "abc")  # type: ignore[arg-type]


def test_several_errors_are_reported_compactly() -> None:
    text = _reject(PoseMsg, _pose_dict(robot_id="", seq=-1, pose=[0, 0, math.nan]), "robot_id")
    assert "seq: must be >= 0" in text and "pose[2]: must be finite" in text
    assert text.count(";") == 2
    many = {"seq": "a", "stamp": "b", "angle_min": "c", "angle_increment": "d", "range_min": "e"}
    assert "(+" in _reject(Scan, many, "seq: must be an integer")


def test_building_in_python_raises_the_same_errors() -> None:
    with pytest.raises(InvalidMessage, match=re.escape("pose[2]: must be finite")):
        Truth(seq=1, stamp=0.0, pose=np.array([0.0, 0.0, np.nan]))
    with pytest.raises(InvalidMessage, match=re.escape("pose: must have shape (3,)")):
        Truth(seq=1, stamp=0.0, pose=np.zeros((3, 1)))
    with pytest.raises(InvalidMessage, match="must hold numbers"):
        Scan(**_scan_dict(ranges=np.array(["a", "b"])))
    with pytest.raises(InvalidMessage, match=re.escape("polylines[0]: must have shape (k, 2)")):
        Map(map_id="m", kind="metric", polylines=[np.zeros((3, 3))])


def test_encode_refuses_bytes_ranges_in_json_or_non_scans() -> None:
    t = Truth(seq=1, stamp=0.0, pose=[0, 0, 0])
    with pytest.raises(InvalidMessage, match="msgpack-only"):
        encode(Scan(**_scan_dict()), json=True, ranges_as_bytes=True)
    with pytest.raises(InvalidMessage, match="needs a Scan"):
        encode(t, ranges_as_bytes=True)


def test_model_validate_raises_invalid_message_with_the_plain_reason() -> None:
    with pytest.raises(InvalidMessage) as exc:
        Truth.model_validate({"seq": 1, "stamp": 0.0, "pose": [0, 0, math.inf]})
    assert str(exc.value) == "pose[2]: must be finite"
    with pytest.raises(InvalidMessage, match="message: must be a map, got array"):
        Truth.parse([1, 2])
    assert Truth.model_validate({"seq": 1, "stamp": 0, "pose": [0, 0, 0]}).seq == 1
