"""Pydantic v2 models of every ``wire-v1`` message (see ``docs/wire.md``).

Field names, types and defaults are those of the contract; the optional project additions are
marked as such. Validation is strict and precise:

* numbers: ``int`` or ``float`` (numpy scalars too when built in Python); a ``bool`` or a string
  is never a number, and a float is never an integer (``seq``, counters);
* every float is finite, except the values inside ``Scan.ranges`` (there NaN, inf or anything
  outside ``[range_min, range_max]`` means "no return");
* identifiers are 1-64 characters of ``[A-Za-z0-9_.-]``;
* pose angles are normalised to (-pi, pi] on input;
* unknown keys are ignored (forward compatibility with later optional fields).

Array-valued fields are exposed as read-only float64 numpy arrays: poses ``(3,)``, ranges
``(n,)``, polylines a tuple of ``(k, 2)`` arrays, covariance ``(3, 3)``.

Every validation failure raises :class:`service.errors.InvalidMessage` (also when a model is
built directly in Python); the text is ``<field path>: <reason>``, e.g. ``pose[2]: must be
finite``. ``model_copy(update=...)`` does not validate: build a new model instead.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Annotated, Any, ClassVar, Literal, Self, get_args

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator
from pydantic.functional_validators import PlainValidator
from pydantic.json_schema import WithJsonSchema
from pydantic_core import PydanticCustomError

from schemas.keys import id_error
from schemas.limits import (
    ID_CHARS,
    ID_MAX_LEN,
    MAX_BEAMS,
    MAX_CANDIDATES,
    MAX_FOV,
    MAX_KEY_LEN,
    MAX_MAP_POINTS,
    MAX_POLYLINES,
    MAX_TEXT_LEN,
    MAX_UINT,
)
from service.errors import InvalidMessage

__all__ = [
    "MESSAGES",
    "METHODS",
    "ErrorNotice",
    "Health",
    "Map",
    "Method",
    "PoseMsg",
    "RobotConfig",
    "Scan",
    "Truth",
    "WireModel",
    "format_validation_error",
    "wire_type_name",
    "wrap_pi",
]

#: The localisation methods a robot may be configured with (``RobotConfig.method``). The wire
#: owns these names; ``service.core.types.METHODS`` is the core's equal copy (a test checks).
Method = Literal["shape", "icp", "lines"]
METHODS: tuple[str, ...] = get_args(Method)

_TWO_PI = 2.0 * math.pi
_ID_PATTERN = f"^[{ID_CHARS}]{{1,{ID_MAX_LEN}}}$"


# --------------------------------------------------------------------------- errors


class _FieldError(Exception):
    """Internal: a validation failure at ``sub`` (relative path, e.g. ``[2]``) with ``reason``."""

    def __init__(self, reason: str, sub: str = "") -> None:
        super().__init__(reason)
        self.reason = reason
        self.sub = sub


def _custom(fail: _FieldError) -> PydanticCustomError:
    return PydanticCustomError("shapeloc", "{reason}", {"reason": fail.reason, "sub": fail.sub})


def _join(loc: tuple[int | str, ...], sub: str) -> str:
    path = ""
    for part in loc:
        if isinstance(part, int):
            path += f"[{part}]"
        else:
            path += f".{part}" if path else str(part)
    if sub:
        path += sub if (sub.startswith("[") or not path) else f".{sub}"
    return path or "message"


_MAX_REPORTED = 3


def format_validation_error(err: ValidationError) -> str:
    """Compact ``field: reason`` text of a pydantic error (at most three, then a count)."""
    parts: list[str] = []
    errors = err.errors(include_url=False, include_input=False)
    for e in errors[:_MAX_REPORTED]:
        ctx = e.get("ctx") or {}
        if e["type"] == "value_error" and isinstance(ctx.get("error"), InvalidMessage):
            # raised by our own __init__ when pydantic calls it from model_validate
            parts.append(str(ctx["error"]))
            continue
        if e["type"] == "shapeloc":
            path, reason = _join(tuple(e["loc"]), str(ctx.get("sub", ""))), str(ctx["reason"])
        else:
            path = _join(tuple(e["loc"]), "")
            reason = "required field missing" if e["type"] == "missing" else e["msg"]
            if e["type"] == "literal_error":
                reason = "must be " + reason.removeprefix("Input should be ")
        parts.append(f"{path}: {reason}")
    if len(errors) > _MAX_REPORTED:
        parts.append(f"(+{len(errors) - _MAX_REPORTED} more)")
    return "; ".join(parts)


# --------------------------------------------------------------------------- scalar checks

_FAST_NUM = (float, int)


_WIRE_NAMES: dict[type, str] = {
    list: "array",
    tuple: "array",
    dict: "map",
    str: "string",
    bytes: "bytes",
    bytearray: "bytes",
    memoryview: "bytes",
    type(None): "null",
    bool: "bool",
    int: "int",
    float: "float",
}


def wire_type_name(v: object) -> str:
    """Name of a decoded value's type in wire terms (array, map, string, null, ...)."""
    return _WIRE_NAMES.get(type(v), type(v).__name__)


_type_name = wire_type_name


def _is_number(v: object) -> bool:
    t = type(v)
    if t is float or t is int:
        return True
    if isinstance(v, (bool, np.bool_)):
        return False
    return isinstance(v, (int, float, np.integer, np.floating))


def _finite(v: object, sub: str = "") -> float:
    if not _is_number(v):
        raise _FieldError(f"must be a number, got {_type_name(v)}", sub)
    try:
        f = float(v)  # type: ignore[arg-type]
    except OverflowError:
        raise _FieldError("must be finite", sub) from None
    if not math.isfinite(f):
        raise _FieldError("must be finite", sub)
    return f


def _count(v: object, sub: str = "") -> int:
    t = type(v)
    if t is not int and not (isinstance(v, (int, np.integer)) and not isinstance(v, bool)):
        raise _FieldError(f"must be an integer, got {_type_name(v)}", sub)
    i = int(v)  # type: ignore[arg-type]
    if i < 0:
        raise _FieldError(f"must be >= 0, got {i}", sub)
    if i > MAX_UINT:
        raise _FieldError(f"must be <= {MAX_UINT}", sub)
    return i


def wrap_pi(a: float) -> float:
    """Angle ``a`` (radians) normalised to (-pi, pi]."""
    w = math.pi - ((math.pi - a) % _TWO_PI)
    return w + _TWO_PI if w <= -math.pi else w


def _readonly(a: np.ndarray) -> np.ndarray:
    a.setflags(write=False)
    return a


def _seq_items(v: object, sub: str, what: str) -> list | tuple | np.ndarray:
    if isinstance(v, (list, tuple)):
        return v
    if isinstance(v, np.ndarray):
        return v
    raise _FieldError(f"must be {what}, got {_type_name(v)}", sub)


def _numeric_array(v: np.ndarray, sub: str) -> np.ndarray:
    if v.dtype.kind not in "fiu":
        raise _FieldError(f"must hold numbers, got numpy dtype {v.dtype}", sub)
    return np.array(v, dtype=np.float64)


# --------------------------------------------------------------------------- field validators


def _v(check: Callable[[Any], Any]) -> Callable[[Any], Any]:
    """Wrap a check raising ``_FieldError`` into a pydantic plain validator."""

    def validator(value: Any) -> Any:
        try:
            return check(value)
        except _FieldError as f:
            raise _custom(f) from None

    return validator


def _optional(check: Callable[[Any], Any]) -> Callable[[Any], Any]:
    return lambda v: None if v is None else check(v)


def _ident(v: object) -> str:
    reason = id_error(v)
    if reason is not None:
        raise _FieldError(reason)
    return v  # type: ignore[return-value]


def _text(limit: int, allow_empty: bool) -> Callable[[object], str]:
    def check(v: object) -> str:
        if not isinstance(v, str):
            raise _FieldError(f"must be a string, got {_type_name(v)}")
        if not v and not allow_empty:
            raise _FieldError("must not be empty")
        if len(v) > limit:
            raise _FieldError(f"{len(v)} characters exceeds limit {limit}")
        return v

    return check


def _unit_interval(v: object) -> float:
    f = _finite(v)
    if not 0.0 <= f <= 1.0:
        raise _FieldError(f"must be in [0, 1], got {f!r}")
    return f


def _pose3(v: object) -> np.ndarray:
    items = _seq_items(v, "", "a list [x, y, theta]")
    if isinstance(items, np.ndarray) and items.shape != (3,):
        raise _FieldError(f"must have shape (3,), got {items.shape}")
    if len(items) != 3:
        raise _FieldError(f"must be [x, y, theta] (3 numbers), got {len(items)} elements")
    x, y, th = (_finite(items[i], f"[{i}]") for i in range(3))
    return _readonly(np.array([x, y, wrap_pi(th)], dtype=np.float64))


def _covariance(v: object) -> np.ndarray:
    items = _seq_items(v, "", "a list of 9 numbers (row-major 3x3)")
    if isinstance(items, np.ndarray):
        if items.shape not in ((9,), (3, 3)):
            raise _FieldError(f"must have shape (9,) or (3, 3), got {items.shape}")
        items = _numeric_array(items, "").reshape(-1)
    if len(items) != 9:
        raise _FieldError(f"must be 9 numbers (row-major 3x3), got {len(items)} elements")
    vals = [_finite(items[i], f"[{i}]") for i in range(9)]
    return _readonly(np.array(vals, dtype=np.float64).reshape(3, 3))


def _candidates(v: object) -> np.ndarray:
    items = _seq_items(v, "", "a list of [x, y, theta, cost] rows")
    if isinstance(items, np.ndarray):
        if items.ndim != 2 or items.shape[1:] != (4,):
            raise _FieldError(f"must have shape (k, 4), got {items.shape}")
        items = list(_numeric_array(items, ""))
    if len(items) > MAX_CANDIDATES:
        raise _FieldError(f"{len(items)} rows exceeds limit {MAX_CANDIDATES}")
    rows = []
    for i, row in enumerate(items):
        vals = _seq_items(row, f"[{i}]", "a row [x, y, theta, cost]")
        if len(vals) != 4:
            raise _FieldError(f"must be [x, y, theta, cost] (4 numbers), got {len(vals)}", f"[{i}]")
        x, y, th, c = (_finite(vals[j], f"[{i}][{j}]") for j in range(4))
        rows.append([x, y, wrap_pi(th), c])
    return _readonly(np.array(rows, dtype=np.float64).reshape(-1, 4))


def _ranges(v: object) -> np.ndarray:
    if isinstance(v, (bytes, bytearray, memoryview)):
        b = bytes(v)
        if len(b) % 4:
            raise _FieldError(f"{len(b)} bytes is not a multiple of 4 (little-endian float32)")
        n = len(b) // 4
        if n > MAX_BEAMS:
            raise _FieldError(f"{n} float32 values exceeds limit {MAX_BEAMS}")
        if n == 0:
            raise _FieldError("must hold at least 1 value")
        return _readonly(np.frombuffer(b, dtype="<f4").astype(np.float64))
    items = _seq_items(v, "", "a list of numbers or float32 bytes")
    n = len(items)
    if n > MAX_BEAMS:
        raise _FieldError(f"{n} elements exceeds limit {MAX_BEAMS}")
    if n == 0:
        raise _FieldError("must hold at least 1 value")
    if isinstance(items, np.ndarray):
        if items.ndim != 1:
            raise _FieldError(f"must be one-dimensional, got shape {items.shape}")
        return _readonly(_numeric_array(items, ""))
    has_none = False
    for i, r in enumerate(items):
        t = type(r)
        if t is float or t is int:
            continue
        if r is None:
            has_none = True
        elif not _is_number(r):
            raise _FieldError(f"must be a number or null, got {_type_name(r)}", f"[{i}]")
    if has_none:
        items = [math.nan if r is None else r for r in items]
    try:
        arr = np.array(items, dtype=np.float64)
    except OverflowError:
        # An integer beyond float64 is as far away as it gets: no return.
        arr = np.array([_big_to_float(r) for r in items], dtype=np.float64)
    return _readonly(arr)


def _big_to_float(r: object) -> float:
    try:
        return float(r)  # type: ignore[arg-type]
    except OverflowError:
        return math.inf


def _polylines(v: object) -> tuple[np.ndarray, ...]:
    lines = _seq_items(v, "", "a list of polylines")
    if isinstance(lines, np.ndarray):
        lines = list(lines)
    if len(lines) == 0:
        raise _FieldError("must hold at least 1 polyline")
    if len(lines) > MAX_POLYLINES:
        raise _FieldError(f"{len(lines)} polylines exceeds limit {MAX_POLYLINES}")
    total = 0
    out: list[np.ndarray] = []
    for i, line in enumerate(lines):
        pts = _seq_items(line, f"[{i}]", "a list of [x, y] points")
        total += len(pts)
        if total > MAX_MAP_POINTS:
            raise _FieldError(f"more than {MAX_MAP_POINTS} points in total exceeds limit")
        if len(pts) < 2:
            raise _FieldError(f"{len(pts)} point(s), a polyline needs at least 2", f"[{i}]")
        if isinstance(pts, np.ndarray):
            if pts.ndim != 2 or pts.shape[1] != 2:
                raise _FieldError(f"must have shape (k, 2), got {pts.shape}", f"[{i}]")
            a = _numeric_array(pts, f"[{i}]")
        else:
            for j, p in enumerate(pts):
                if not isinstance(p, (list, tuple, np.ndarray)):
                    raise _FieldError(f"must be [x, y], got {_type_name(p)}", f"[{i}][{j}]")
                if len(p) != 2:
                    raise _FieldError(f"must be [x, y], got {len(p)} elements", f"[{i}][{j}]")
                for k in (0, 1):
                    if type(p[k]) not in _FAST_NUM and not _is_number(p[k]):
                        raise _FieldError(
                            f"must be a number, got {_type_name(p[k])}", f"[{i}][{j}][{k}]"
                        )
            try:
                a = np.array(pts, dtype=np.float64)
            except OverflowError:
                a = np.array([[_big_to_float(c) for c in p] for p in pts], dtype=np.float64)
        bad = np.flatnonzero(~np.isfinite(a).reshape(-1))
        if bad.size:
            j, k = divmod(int(bad[0]), 2)
            raise _FieldError("must be finite", f"[{i}][{j}][{k}]")
        out.append(_readonly(a))
    return tuple(out)


# --------------------------------------------------------------------------- annotated types

_NUM_SCHEMA: dict[str, Any] = {"type": "number"}
_POSE_SCHEMA: dict[str, Any] = {
    "type": "array",
    "items": {"type": "number"},
    "minItems": 3,
    "maxItems": 3,
    "description": "[x, y, theta]: metres, metres, radians (theta normalised to (-pi, pi]).",
}


def _nullable(schema: dict[str, Any]) -> dict[str, Any]:
    return {"anyOf": [schema, {"type": "null"}]}


FiniteFloat = Annotated[float, PlainValidator(_v(_finite)), WithJsonSchema(_NUM_SCHEMA)]
Count = Annotated[
    int,
    PlainValidator(_v(_count)),
    WithJsonSchema({"type": "integer", "minimum": 0, "maximum": MAX_UINT}),
]
Ident = Annotated[
    str,
    PlainValidator(_v(_ident)),
    WithJsonSchema({"type": "string", "pattern": _ID_PATTERN}),
]
OptIdent = Annotated[
    str | None,
    PlainValidator(_v(_optional(_ident))),
    WithJsonSchema(_nullable({"type": "string", "pattern": _ID_PATTERN})),
]
Pose3 = Annotated[np.ndarray, PlainValidator(_v(_pose3)), WithJsonSchema(_POSE_SCHEMA)]
OptPose3 = Annotated[
    np.ndarray | None,
    PlainValidator(_v(_optional(_pose3))),
    WithJsonSchema(_nullable(_POSE_SCHEMA)),
]
UnitFloat = Annotated[
    float | None,
    PlainValidator(_v(_optional(_unit_interval))),
    WithJsonSchema(_nullable({"type": "number", "minimum": 0, "maximum": 1})),
]


class WireModel(BaseModel):
    """Base of every wire message: strict, immutable, unknown keys ignored.

    Construction (``Model(**fields)`` or :meth:`parse`) raises ``InvalidMessage`` on any
    violation. Equality compares array fields element-wise (NaN equals NaN).
    """

    model_config = ConfigDict(
        extra="ignore",
        frozen=True,
        arbitrary_types_allowed=True,
        hide_input_in_errors=True,
        revalidate_instances="never",
    )

    #: Key of the file in ``schemas/json/`` (``<schema_name>.schema.json``).
    schema_name: ClassVar[str] = ""

    def __init__(self, /, **data: Any) -> None:
        try:
            super().__init__(**data)
        except ValidationError as e:
            raise InvalidMessage(format_validation_error(e)) from None

    @classmethod
    def parse(cls, obj: object) -> Self:
        """Validate a decoded payload (a dict with string keys) into this model."""
        if not isinstance(obj, dict):
            raise InvalidMessage(f"message: must be a map, got {_type_name(obj)}")
        if not all(isinstance(k, str) for k in obj):
            raise InvalidMessage("message: keys must be strings")
        # Going through __init__ (not model_validate) keeps the error text free of pydantic's
        # "Value error" wrapping: a custom __init__ is what model_validate calls anyway.
        return cls(**obj)

    @classmethod
    def model_validate(cls, obj: Any, *args: Any, **kwargs: Any) -> Self:
        """As pydantic's, but failures raise ``InvalidMessage`` (prefer :meth:`parse`)."""
        try:
            return super().model_validate(obj, *args, **kwargs)
        except ValidationError as e:
            raise InvalidMessage(format_validation_error(e)) from None

    def __eq__(self, other: object) -> bool:
        if type(other) is not type(self):
            return NotImplemented
        for name in type(self).model_fields:
            a, b = getattr(self, name), getattr(other, name)
            if isinstance(a, tuple) and isinstance(b, tuple):
                if len(a) != len(b) or not all(_same(x, y) for x, y in zip(a, b, strict=True)):
                    return False
            elif not _same(a, b):
                return False
        return True

    __hash__ = None  # type: ignore[assignment]

    def to_wire(self, ranges_as_bytes: bool = False) -> dict[str, Any]:
        """Plain dict of wire types (lists of floats, no numpy); ``None`` fields are left out."""
        out: dict[str, Any] = {}
        for name in type(self).model_fields:
            value = getattr(self, name)
            if value is None:
                continue
            out[name] = _plain(value)
        return out


def _same(a: object, b: object) -> bool:
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        return (
            isinstance(a, np.ndarray)
            and isinstance(b, np.ndarray)
            and a.shape == b.shape
            and bool(np.array_equal(a, b, equal_nan=True))
        )
    return a == b


def _plain(value: Any) -> Any:
    if isinstance(value, np.ndarray):
        return value.reshape(-1).tolist() if value.shape == (3, 3) else value.tolist()
    if isinstance(value, tuple):
        return [_plain(v) for v in value]
    if isinstance(value, dict):
        return dict(value)
    return value


# --------------------------------------------------------------------------- messages


class Map(WireModel):
    """A map: ``put <prefix>/maps/<map_id>``. Coordinates in metres, map frame.

    ``polylines``: each at least 2 points; a closed ring repeats its first point last.
    Exposed as a tuple of read-only ``(k, 2)`` float64 arrays.
    """

    schema_name: ClassVar[str] = "map"

    map_id: Ident = Field(description="Must equal the <map_id> of the key.")
    kind: Literal["metric", "schematic"] = Field(
        description="metric: exact map; schematic: room outlines only (no furniture)."
    )
    polylines: Annotated[
        tuple[np.ndarray, ...],
        PlainValidator(_v(_polylines)),
        WithJsonSchema(
            {
                "type": "array",
                "minItems": 1,
                "maxItems": MAX_POLYLINES,
                "items": {
                    "type": "array",
                    "minItems": 2,
                    "items": {
                        "type": "array",
                        "items": {"type": "number"},
                        "minItems": 2,
                        "maxItems": 2,
                    },
                },
                "description": (
                    f"Polylines of [x, y] points in metres (map frame); at most "
                    f"{MAX_MAP_POINTS} points in total; a closed ring repeats its first point."
                ),
            }
        ),
    ]
    name: Annotated[
        str | None,
        PlainValidator(_v(_optional(_text(MAX_TEXT_LEN, allow_empty=True)))),
        WithJsonSchema(_nullable({"type": "string", "maxLength": MAX_TEXT_LEN})),
    ] = Field(default=None, description="Optional human-readable name.")


class RobotConfig(WireModel):
    """Robot configuration: ``put <prefix>/robots/<robot_id>/config`` (resets its localiser)."""

    schema_name: ClassVar[str] = "robot_config"

    map_id: Ident = Field(description="Id of the map to localise against.")
    method: Method = Field(default="shape", description="Localisation method.")
    initial_pose: OptPose3 = Field(
        default=None, description="Initial pose in the map frame; null: global localisation."
    )


class Scan(WireModel):
    """One laser scan: ``put <prefix>/robots/<robot_id>/scan``.

    Beam ``i`` points at ``angle_min + i * angle_increment`` (radians, robot frame, REP 103);
    the laser sits at the robot origin. ``ranges`` (metres) is a read-only float64 array of
    the raw values; NaN, inf or anything outside ``[range_min, range_max]`` means "no return"
    (``schemas.codec.scan_arrays`` maps all of them to NaN).
    """

    schema_name: ClassVar[str] = "scan"

    seq: Count = Field(description="Sequence number, >= 0.")
    stamp: FiniteFloat = Field(description="Acquisition time, seconds.")
    angle_min: FiniteFloat = Field(description="Angle of beam 0, radians, robot frame.")
    angle_increment: Annotated[
        float,
        PlainValidator(_v(_finite)),
        WithJsonSchema({"type": "number", "exclusiveMinimum": 0}),
    ] = Field(description="Angle between consecutive beams, radians, > 0.")
    range_min: Annotated[
        float, PlainValidator(_v(_finite)), WithJsonSchema({"type": "number", "minimum": 0})
    ] = Field(description="Shortest valid range, metres, >= 0.")
    range_max: FiniteFloat = Field(description="Longest valid range, metres, > range_min.")
    ranges: Annotated[
        np.ndarray,
        PlainValidator(_v(_ranges)),
        WithJsonSchema(
            {
                "type": "array",
                "items": {"anyOf": [{"type": "number"}, {"type": "null"}]},
                "minItems": 1,
                "maxItems": MAX_BEAMS,
                "description": (
                    "Ranges in metres, one per beam. In msgpack this may instead be a binary "
                    "string of little-endian float32 values. NaN, inf, null or a value "
                    "outside [range_min, range_max] means no return."
                ),
            }
        ),
    ]
    odom: OptPose3 = Field(
        default=None, description="Odometry pose [x, y, theta] in its own frame (optional)."
    )

    @model_validator(mode="after")
    def _geometry(self) -> Self:
        try:
            if self.angle_increment <= 0.0:
                raise _FieldError(f"must be > 0, got {self.angle_increment!r}", "angle_increment")
            if self.range_min < 0.0:
                raise _FieldError(f"must be >= 0, got {self.range_min!r}", "range_min")
            if not self.range_min < self.range_max:
                raise _FieldError(
                    f"must be > range_min ({self.range_min!r}), got {self.range_max!r}",
                    "range_max",
                )
            fov = (len(self.ranges) - 1) * self.angle_increment
            if fov > MAX_FOV:
                raise _FieldError(
                    f"{len(self.ranges)} beams x {self.angle_increment!r} rad spans "
                    f"{fov:.6g} rad, more than 2*pi",
                    "angle_increment",
                )
        except _FieldError as f:
            raise _custom(f) from None
        return self

    def to_wire(self, ranges_as_bytes: bool = False) -> dict[str, Any]:
        """As :meth:`WireModel.to_wire`; ``ranges_as_bytes`` packs ranges as little-endian
        float32 bytes (msgpack only; values are rounded to float32)."""
        out = super().to_wire()
        if ranges_as_bytes:
            out["ranges"] = self.ranges.astype("<f4").tobytes()
        return out


_STATUS = Literal["tracking", "lost", "initializing"]


class PoseMsg(WireModel):
    """A pose estimate: published on ``<prefix>/robots/<robot_id>/pose`` after every scan.

    ``seq``/``stamp`` are those of the scan it answers; ``pose`` is in the map frame.
    ``covariance``, ``explained``, ``ambiguity``, ``hypotheses``, ``candidates`` and ``odom``
    are project additions (optional).
    """

    schema_name: ClassVar[str] = "pose"

    robot_id: Ident
    seq: Count = Field(description="seq of the scan this estimate answers.")
    stamp: FiniteFloat = Field(description="stamp of the scan this estimate answers, seconds.")
    pose: Pose3 = Field(description="[x, y, theta] in the map frame.")
    status: _STATUS
    score: FiniteFloat = Field(description="Match quality (method-specific; higher is better).")
    method: Ident = Field(description="Localisation method that produced the estimate.")
    map_id: Ident
    latency_ms: FiniteFloat = Field(description="Scan received -> estimate published, ms.")
    covariance: Annotated[
        np.ndarray | None,
        PlainValidator(_v(_optional(_covariance))),
        WithJsonSchema(
            _nullable(
                {
                    "type": "array",
                    "items": {"type": "number"},
                    "minItems": 9,
                    "maxItems": 9,
                    "description": "Row-major 3x3 covariance of [x, y, theta].",
                }
            )
        ),
    ] = Field(default=None, description="Project addition: 3x3 pose covariance (exposed 3x3).")
    explained: UnitFloat = Field(
        default=None,
        description="Project addition: fraction of the scan explained by the map, [0, 1].",
    )
    ambiguity: UnitFloat = Field(
        default=None,
        description="Project addition: best vs second-best hypothesis cost ratio, [0, 1].",
    )
    hypotheses: Annotated[
        int | None,
        PlainValidator(_v(_optional(_count))),
        WithJsonSchema(_nullable({"type": "integer", "minimum": 0, "maximum": MAX_UINT})),
    ] = Field(
        default=None,
        description="Project addition: live pose hypotheses of a global search (initializing "
        "or lost); absent while tracking.",
    )
    candidates: Annotated[
        np.ndarray | None,
        PlainValidator(_v(_optional(_candidates))),
        WithJsonSchema(
            _nullable(
                {
                    "type": "array",
                    "maxItems": MAX_CANDIDATES,
                    "items": {
                        "type": "array",
                        "items": {"type": "number"},
                        "minItems": 4,
                        "maxItems": 4,
                    },
                    "description": "Best hypotheses first: [x, y, theta, cost] (map frame; "
                    "lower cost is better).",
                }
            )
        ),
    ] = Field(
        default=None,
        description="Project addition: the best few pose hypotheses of a global search.",
    )
    odom: OptPose3 = Field(
        default=None,
        description=(
            "Project addition: the odometry pose of the scan this estimate answers (absent "
            "if it carried none), so that another service instance can take the robot over."
        ),
    )


def _count_dict(v: object) -> dict[str, int]:
    if not isinstance(v, dict):
        raise _FieldError(f"must be a map, got {_type_name(v)}")
    if len(v) > 1024:
        raise _FieldError(f"{len(v)} entries exceeds limit 1024")
    out: dict[str, int] = {}
    for k, n in v.items():
        if not isinstance(k, str) or not 1 <= len(k) <= ID_MAX_LEN:
            raise _FieldError(f"key {k!r} must be a string of 1-{ID_MAX_LEN} characters")
        out[k] = _count(n, f"[{k!r}]")
    return out


_COUNT_DICT = Annotated[
    dict[str, int] | None,
    PlainValidator(_v(_optional(_count_dict))),
    WithJsonSchema(
        _nullable({"type": "object", "additionalProperties": {"type": "integer", "minimum": 0}})
    ),
]


class Health(WireModel):
    """Service health: reply to ``get <prefix>/service/health``.

    ``instance_id``, ``uptime_s``, ``errors`` and ``robots_by_status`` are project additions.
    """

    schema_name: ClassVar[str] = "health"

    status: Annotated[
        str,
        PlainValidator(_v(_text(64, allow_empty=False))),
        WithJsonSchema({"type": "string", "minLength": 1, "maxLength": 64}),
    ] = Field(description='"ok" when serving.')
    version: Annotated[
        str,
        PlainValidator(_v(_text(256, allow_empty=False))),
        WithJsonSchema({"type": "string", "minLength": 1, "maxLength": 256}),
    ]
    robots: Count
    maps: Count
    scans_processed: Count
    scans_rejected: Count
    instance_id: OptIdent = Field(
        default=None, description="Project addition: id of the answering service instance."
    )
    uptime_s: Annotated[
        float | None,
        PlainValidator(_v(_optional(_finite))),
        WithJsonSchema(_nullable(_NUM_SCHEMA)),
    ] = Field(default=None, description="Project addition: seconds since the service started.")
    errors: _COUNT_DICT = Field(
        default=None, description="Project addition: rejected messages per error kind."
    )
    robots_by_status: _COUNT_DICT = Field(
        default=None, description="Project addition: number of robots per tracking status."
    )


class ErrorNotice(WireModel):
    """One rejected message: published on ``<prefix>/errors``."""

    schema_name: ClassVar[str] = "error_notice"

    key: Annotated[
        str,
        PlainValidator(_v(_text(MAX_KEY_LEN, allow_empty=False))),
        WithJsonSchema({"type": "string", "minLength": 1, "maxLength": MAX_KEY_LEN}),
    ] = Field(description="Key expression of the rejected message.")
    error: Annotated[
        str,
        PlainValidator(_v(_text(MAX_TEXT_LEN, allow_empty=False))),
        WithJsonSchema({"type": "string", "minLength": 1, "maxLength": MAX_TEXT_LEN}),
    ] = Field(description="Why it was rejected.")

    @classmethod
    def make(cls, key: str, error: str) -> ErrorNotice:
        """Build a notice, truncating over-long ``key``/``error`` text to the limits."""
        k = key[:MAX_KEY_LEN] or "?"
        e = error if len(error) <= MAX_TEXT_LEN else error[: MAX_TEXT_LEN - 3] + "..."
        return cls(key=k, error=e or "unknown error")


class Truth(WireModel):
    """Ground-truth pose from the simulator: ``<prefix>/robots/<robot_id>/truth``."""

    schema_name: ClassVar[str] = "truth"

    seq: Count = Field(description="seq of the scan taken at this pose.")
    stamp: FiniteFloat = Field(description="stamp of that scan, seconds.")
    pose: Pose3 = Field(description="True [x, y, theta] in the map frame.")


#: Every wire message, in a stable order.
MESSAGES: tuple[type[WireModel], ...] = (
    Map,
    RobotConfig,
    Scan,
    PoseMsg,
    Health,
    ErrorNotice,
    Truth,
)
