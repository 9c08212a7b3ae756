"""Foxglove's well-known message types as JSON, for MCAP recordings Foxglove opens natively.

Foxglove recognises a channel by its schema's *name* (``foxglove.PoseInFrame``, ...) and reads
JSON messages (message encoding ``json``, schema encoding ``jsonschema``) whose fields follow
its published schemas (github foxglove/foxglove-sdk, ``schemas/jsonschema``): times are
``{"sec", "nsec"}``, binary fields base64 strings, enums integers. :data:`SCHEMAS` holds the
JSON Schemas of the types :mod:`clients.record` writes, built here from those field tables
(names, types, ranges and required fields); a type's sub-objects that the recorder never fills
(a scene entity's cubes, texts, ...) are declared as arrays of objects without their fields.
The builders below return messages that hold every field the published schemas require.

Pure functions: numpy and the wire models in, JSON-ready dicts out; no I/O.
"""

from __future__ import annotations

import base64
import math
from typing import Any, Final

import numpy as np

from schemas.codec import scan_arrays
from schemas.messages import Map, PoseMsg, Scan

# --------------------------------------------------------------------------- schema pieces

_NUM: Final = {"type": "number"}
_STR: Final = {"type": "string"}
_BOOL: Final = {"type": "boolean"}
_UINT: Final = {"type": "integer", "minimum": 0}


def _obj(title: str | None, props: dict[str, Any], required: bool = True) -> dict[str, Any]:
    out: dict[str, Any] = {"type": "object", "properties": props}
    if title is not None:
        out = {"title": title, **out}
    if required:
        out["required"] = list(props)
    return out


def _enum(title: str, names: tuple[str, ...]) -> dict[str, Any]:
    return {"title": title, "oneOf": [{"title": n, "const": i} for i, n in enumerate(names)]}


def _array(items: dict[str, Any]) -> dict[str, Any]:
    return {"type": "array", "items": items}


_TIME: Final = {
    "type": "object",
    "title": "time",
    "properties": {"sec": _UINT, "nsec": {"type": "integer", "minimum": 0, "maximum": 999999999}},
}
_DURATION: Final = {
    "type": "object",
    "title": "duration",
    "properties": {
        "sec": {"type": "integer"},
        "nsec": {"type": "integer", "minimum": 0, "maximum": 999999999},
    },
}
_VECTOR3: Final = _obj("foxglove.Vector3", {"x": _NUM, "y": _NUM, "z": _NUM})
_POINT3: Final = _obj("foxglove.Point3", {"x": _NUM, "y": _NUM, "z": _NUM})
_QUATERNION: Final = _obj("foxglove.Quaternion", {"x": _NUM, "y": _NUM, "z": _NUM, "w": _NUM})
_POSE: Final = _obj("foxglove.Pose", {"position": _VECTOR3, "orientation": _QUATERNION})
_COLOR: Final = _obj("foxglove.Color", {"r": _NUM, "g": _NUM, "b": _NUM, "a": _NUM})
_KEY_VALUE: Final = _obj("foxglove.KeyValuePair", {"key": _STR, "value": _STR})

LINE_TYPES: Final = ("LINE_STRIP", "LINE_LOOP", "LINE_LIST")
_LINE_PRIMITIVE: Final = _obj(
    "foxglove.LinePrimitive",
    {
        "type": _enum("foxglove.LineType", LINE_TYPES),
        "pose": _POSE,
        "thickness": _NUM,
        "scale_invariant": _BOOL,
        "points": _array(_POINT3),
        "color": _COLOR,
        "colors": _array(_COLOR),
        "indices": _array(_UINT),
    },
)
#: Primitive arrays of a scene entity that the recorder leaves empty.
_UNUSED_PRIMITIVES: Final = {
    "arrows": "foxglove.ArrowPrimitive",
    "cubes": "foxglove.CubePrimitive",
    "spheres": "foxglove.SpherePrimitive",
    "cylinders": "foxglove.CylinderPrimitive",
    "triangles": "foxglove.TriangleListPrimitive",
    "texts": "foxglove.TextPrimitive",
    "models": "foxglove.ModelPrimitive",
}
_SCENE_ENTITY: Final = _obj(
    "foxglove.SceneEntity",
    {
        "timestamp": _TIME,
        "frame_id": _STR,
        "id": _STR,
        "lifetime": _DURATION,
        "frame_locked": _BOOL,
        "metadata": _array(_KEY_VALUE),
        "lines": _array(_LINE_PRIMITIVE),
        **{k: _array({"title": t, "type": "object"}) for k, t in _UNUSED_PRIMITIVES.items()},
    },
)
DELETION_TYPES: Final = ("MATCHING_ID", "ALL")
_SCENE_ENTITY_DELETION: Final = _obj(
    "foxglove.SceneEntityDeletion",
    {
        "timestamp": _TIME,
        "type": _enum("foxglove.SceneEntityDeletionType", DELETION_TYPES),
        "id": _STR,
    },
)
NUMERIC_TYPES: Final = (
    "UNKNOWN",
    "UINT8",
    "INT8",
    "UINT16",
    "INT16",
    "UINT32",
    "INT32",
    "FLOAT32",
    "FLOAT64",
)
_PACKED_FIELD: Final = _obj(
    "foxglove.PackedElementField",
    {"name": _STR, "offset": _UINT, "type": _enum("foxglove.NumericType", NUMERIC_TYPES)},
)
LOG_LEVELS: Final = ("UNKNOWN", "DEBUG", "INFO", "WARNING", "ERROR", "FATAL")


def _top(name: str, props: dict[str, Any]) -> dict[str, Any]:
    return _obj(name, props)


#: Schema name -> JSON Schema, for every Foxglove type the recorder writes.
SCHEMAS: Final[dict[str, dict[str, Any]]] = {
    "foxglove.SceneUpdate": _top(
        "foxglove.SceneUpdate",
        {"deletions": _array(_SCENE_ENTITY_DELETION), "entities": _array(_SCENE_ENTITY)},
    ),
    "foxglove.PoseInFrame": _top(
        "foxglove.PoseInFrame", {"timestamp": _TIME, "frame_id": _STR, "pose": _POSE}
    ),
    "foxglove.PosesInFrame": _top(
        "foxglove.PosesInFrame", {"timestamp": _TIME, "frame_id": _STR, "poses": _array(_POSE)}
    ),
    "foxglove.FrameTransform": _top(
        "foxglove.FrameTransform",
        {
            "timestamp": _TIME,
            "parent_frame_id": _STR,
            "child_frame_id": _STR,
            "translation": _VECTOR3,
            "rotation": _QUATERNION,
        },
    ),
    "foxglove.PointCloud": _top(
        "foxglove.PointCloud",
        {
            "timestamp": _TIME,
            "frame_id": _STR,
            "pose": _POSE,
            "point_stride": _UINT,
            "fields": _array(_PACKED_FIELD),
            "data": {"type": "string", "contentEncoding": "base64"},
        },
    ),
    "foxglove.Log": _top(
        "foxglove.Log",
        {
            "timestamp": _TIME,
            "level": _enum("foxglove.LogLevel", LOG_LEVELS),
            "message": _STR,
            "name": _STR,
            "file": _STR,
            "line": _UINT,
        },
    ),
}

# --------------------------------------------------------------------------- values


def time_of(seconds: float) -> dict[str, int]:
    """Seconds (float, >= 0; negatives clamp to 0) as Foxglove's ``{"sec", "nsec"}``."""
    ns = max(0, round(float(seconds) * 1e9)) if math.isfinite(seconds) else 0
    return {"sec": ns // 1_000_000_000, "nsec": ns % 1_000_000_000}


def yaw_quaternion(theta: float) -> dict[str, float]:
    """A rotation of ``theta`` rad about z."""
    return {"x": 0.0, "y": 0.0, "z": math.sin(theta / 2.0), "w": math.cos(theta / 2.0)}


def pose_of(x: float, y: float, theta: float) -> dict[str, Any]:
    """A planar pose as ``foxglove.Pose`` (z = 0)."""
    return {
        "position": {"x": float(x), "y": float(y), "z": 0.0},
        "orientation": yaw_quaternion(float(theta)),
    }


_IDENTITY: Final = pose_of(0.0, 0.0, 0.0)


def _colour(rgba: dict[str, float]) -> dict[str, float]:
    return {k: float(rgba[k]) for k in ("r", "g", "b", "a")}


# --------------------------------------------------------------------------- messages


def pose_in_frame(msg: PoseMsg) -> dict[str, Any]:
    """``foxglove.PoseInFrame``: the estimate in its map's frame (``frame_id`` = map id)."""
    x, y, th = (float(v) for v in msg.pose)
    return {"timestamp": time_of(msg.stamp), "frame_id": msg.map_id, "pose": pose_of(x, y, th)}


def candidates_in_frame(msg: PoseMsg) -> dict[str, Any]:
    """``foxglove.PosesInFrame``: the search's candidate places, best first (none: empty)."""
    cand = msg.candidates if msg.candidates is not None else np.zeros((0, 4))
    return {
        "timestamp": time_of(msg.stamp),
        "frame_id": msg.map_id,
        "poses": [pose_of(c[0], c[1], c[2]) for c in cand],
    }


def robot_transform(msg: PoseMsg) -> dict[str, Any]:
    """``foxglove.FrameTransform``: map frame -> the robot's frame (named by its id) at the
    estimate, so the robot's scans (in its own frame) are drawn at the published pose."""
    x, y, th = (float(v) for v in msg.pose)
    return {
        "timestamp": time_of(msg.stamp),
        "parent_frame_id": msg.map_id,
        "child_frame_id": msg.robot_id,
        "translation": {"x": x, "y": y, "z": 0.0},
        "rotation": yaw_quaternion(th),
    }


def scan_cloud(robot_id: str, scan: Scan) -> dict[str, Any]:
    """``foxglove.PointCloud``: the scan's returns in the robot's frame (x, y as float32;
    no-return beams left out)."""
    ranges, angles = scan_arrays(scan)
    ok = np.isfinite(ranges)
    pts = np.stack([ranges[ok] * np.cos(angles[ok]), ranges[ok] * np.sin(angles[ok])], axis=1)
    data = pts.astype("<f4").tobytes()
    return {
        "timestamp": time_of(scan.stamp),
        "frame_id": robot_id,
        "pose": _IDENTITY,
        "point_stride": 8,
        "fields": [
            {"name": "x", "offset": 0, "type": NUMERIC_TYPES.index("FLOAT32")},
            {"name": "y", "offset": 4, "type": NUMERIC_TYPES.index("FLOAT32")},
        ],
        "data": base64.b64encode(data).decode("ascii"),
    }


def map_scene(m: Map, stamp: float, rgba: dict[str, float]) -> dict[str, Any]:
    """``foxglove.SceneUpdate`` holding the map as one entity (id and frame = map id) with one
    line list of every polyline's segments."""
    points: list[dict[str, float]] = []
    indices: list[int] = []
    for line in m.polylines:
        base = len(points)
        points.extend({"x": float(x), "y": float(y), "z": 0.0} for x, y in line)
        for i in range(len(line) - 1):
            indices += [base + i, base + i + 1]
    meta = [{"key": "kind", "value": m.kind}]
    if m.name:
        meta.append({"key": "name", "value": m.name})
    entity = {
        "timestamp": time_of(stamp),
        "frame_id": m.map_id,
        "id": m.map_id,
        "lifetime": {"sec": 0, "nsec": 0},
        "frame_locked": False,
        "metadata": meta,
        "lines": [
            {
                "type": LINE_TYPES.index("LINE_LIST"),
                "pose": _IDENTITY,
                "thickness": 2.0,
                "scale_invariant": True,
                "points": points,
                "color": _colour(rgba),
                "colors": [],
                "indices": indices,
            }
        ],
        **{k: [] for k in _UNUSED_PRIMITIVES},
    }
    return {"deletions": [], "entities": [entity]}


def map_deletion(map_id: str, stamp: float) -> dict[str, Any]:
    """``foxglove.SceneUpdate`` removing a map's entity."""
    return {
        "deletions": [
            {"timestamp": time_of(stamp), "type": DELETION_TYPES.index("MATCHING_ID"), "id": map_id}
        ],
        "entities": [],
    }


def log_message(stamp: float, level: str, name: str, message: str) -> dict[str, Any]:
    """``foxglove.Log`` (``level`` one of :data:`LOG_LEVELS`)."""
    return {
        "timestamp": time_of(stamp),
        "level": LOG_LEVELS.index(level),
        "message": message,
        "name": name,
        "file": "",
        "line": 0,
    }
