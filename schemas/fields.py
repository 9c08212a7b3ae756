"""How one field of a ``wire-v1`` message is checked: the validators and annotated types
the message models of :mod:`schemas.messages` are built from, and the text of a validation
error (``<field path>: <reason>``). The rules are listed in :mod:`schemas.messages`."""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Annotated, Any

import numpy as np
from pydantic import ValidationError
from pydantic.functional_validators import PlainValidator
from pydantic.json_schema import WithJsonSchema
from pydantic_core import PydanticCustomError

from schemas.keys import id_error
from schemas.limits import (
    ID_CHARS,
    ID_MAX_LEN,
    MAX_BEAMS,
    MAX_CANDIDATES,
    MAX_MAP_POINTS,
    MAX_POLYLINES,
    MAX_UINT,
)
from service.errors import InvalidMessage

_TWO_PI = 2.0 * math.pi
ID_PATTERN = f"^[{ID_CHARS}]{{1,{ID_MAX_LEN}}}$"


# --------------------------------------------------------------------------- errors


class FieldError(Exception):
    """Internal: a validation failure at ``sub`` (relative path, e.g. ``[2]``) with ``reason``."""

    def __init__(self, reason: str, sub: str = "") -> None:
        super().__init__(reason)
        self.reason = reason
        self.sub = sub


def custom_error(fail: FieldError) -> PydanticCustomError:
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


type_name = wire_type_name


def _is_number(v: object) -> bool:
    t = type(v)
    if t is float or t is int:
        return True
    if isinstance(v, (bool, np.bool_)):
        return False
    return isinstance(v, (int, float, np.integer, np.floating))


def check_finite(v: object, sub: str = "") -> float:
    if not _is_number(v):
        raise FieldError(f"must be a number, got {type_name(v)}", sub)
    try:
        f = float(v)  # type: ignore[arg-type]
    except OverflowError:
        raise FieldError("must be finite", sub) from None
    if not math.isfinite(f):
        raise FieldError("must be finite", sub)
    return f


def check_count(v: object, sub: str = "") -> int:
    t = type(v)
    if t is not int and not (isinstance(v, (int, np.integer)) and not isinstance(v, bool)):
        raise FieldError(f"must be an integer, got {type_name(v)}", sub)
    i = int(v)  # type: ignore[arg-type]
    if i < 0:
        raise FieldError(f"must be >= 0, got {i}", sub)
    if i > MAX_UINT:
        raise FieldError(f"must be <= {MAX_UINT}", sub)
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
    raise FieldError(f"must be {what}, got {type_name(v)}", sub)


def _numeric_array(v: np.ndarray, sub: str) -> np.ndarray:
    if v.dtype.kind not in "fiu":
        raise FieldError(f"must hold numbers, got numpy dtype {v.dtype}", sub)
    return np.array(v, dtype=np.float64)


# --------------------------------------------------------------------------- field validators


def as_validator(check: Callable[[Any], Any]) -> Callable[[Any], Any]:
    """Wrap a check raising ``FieldError`` into a pydantic plain validator."""

    def validator(value: Any) -> Any:
        try:
            return check(value)
        except FieldError as f:
            raise custom_error(f) from None

    return validator


def optional_check(check: Callable[[Any], Any]) -> Callable[[Any], Any]:
    return lambda v: None if v is None else check(v)


def check_ident(v: object) -> str:
    reason = id_error(v)
    if reason is not None:
        raise FieldError(reason)
    return v  # type: ignore[return-value]


def text_check(limit: int, allow_empty: bool) -> Callable[[object], str]:
    def check(v: object) -> str:
        if not isinstance(v, str):
            raise FieldError(f"must be a string, got {type_name(v)}")
        if not v and not allow_empty:
            raise FieldError("must not be empty")
        if len(v) > limit:
            raise FieldError(f"{len(v)} characters exceeds limit {limit}")
        return v

    return check


def _unit_interval(v: object) -> float:
    f = check_finite(v)
    if not 0.0 <= f <= 1.0:
        raise FieldError(f"must be in [0, 1], got {f!r}")
    return f


def _pose3(v: object) -> np.ndarray:
    items = _seq_items(v, "", "a list [x, y, theta]")
    if isinstance(items, np.ndarray) and items.shape != (3,):
        raise FieldError(f"must have shape (3,), got {items.shape}")
    if len(items) != 3:
        raise FieldError(f"must be [x, y, theta] (3 numbers), got {len(items)} elements")
    x, y, th = (check_finite(items[i], f"[{i}]") for i in range(3))
    return _readonly(np.array([x, y, wrap_pi(th)], dtype=np.float64))


def check_covariance(v: object) -> np.ndarray:
    items = _seq_items(v, "", "a list of 9 numbers (row-major 3x3)")
    if isinstance(items, np.ndarray):
        if items.shape not in ((9,), (3, 3)):
            raise FieldError(f"must have shape (9,) or (3, 3), got {items.shape}")
        items = _numeric_array(items, "").reshape(-1)
    if len(items) != 9:
        raise FieldError(f"must be 9 numbers (row-major 3x3), got {len(items)} elements")
    vals = [check_finite(items[i], f"[{i}]") for i in range(9)]
    return _readonly(np.array(vals, dtype=np.float64).reshape(3, 3))


def check_candidates(v: object) -> np.ndarray:
    items = _seq_items(v, "", "a list of [x, y, theta, cost] rows")
    if isinstance(items, np.ndarray):
        if items.ndim != 2 or items.shape[1:] != (4,):
            raise FieldError(f"must have shape (k, 4), got {items.shape}")
        items = list(_numeric_array(items, ""))
    if len(items) > MAX_CANDIDATES:
        raise FieldError(f"{len(items)} rows exceeds limit {MAX_CANDIDATES}")
    rows = []
    for i, row in enumerate(items):
        vals = _seq_items(row, f"[{i}]", "a row [x, y, theta, cost]")
        if len(vals) != 4:
            raise FieldError(f"must be [x, y, theta, cost] (4 numbers), got {len(vals)}", f"[{i}]")
        x, y, th, c = (check_finite(vals[j], f"[{i}][{j}]") for j in range(4))
        rows.append([x, y, wrap_pi(th), c])
    return _readonly(np.array(rows, dtype=np.float64).reshape(-1, 4))


def check_ranges(v: object) -> np.ndarray:
    if isinstance(v, (bytes, bytearray, memoryview)):
        b = bytes(v)
        if len(b) % 4:
            raise FieldError(f"{len(b)} bytes is not a multiple of 4 (little-endian float32)")
        n = len(b) // 4
        if n > MAX_BEAMS:
            raise FieldError(f"{n} float32 values exceeds limit {MAX_BEAMS}")
        if n == 0:
            raise FieldError("must hold at least 1 value")
        return _readonly(np.frombuffer(b, dtype="<f4").astype(np.float64))
    items = _seq_items(v, "", "a list of numbers or float32 bytes")
    n = len(items)
    if n > MAX_BEAMS:
        raise FieldError(f"{n} elements exceeds limit {MAX_BEAMS}")
    if n == 0:
        raise FieldError("must hold at least 1 value")
    if isinstance(items, np.ndarray):
        if items.ndim != 1:
            raise FieldError(f"must be one-dimensional, got shape {items.shape}")
        return _readonly(_numeric_array(items, ""))
    has_none = False
    for i, r in enumerate(items):
        t = type(r)
        if t is float or t is int:
            continue
        if r is None:
            has_none = True
        elif not _is_number(r):
            raise FieldError(f"must be a number or null, got {type_name(r)}", f"[{i}]")
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


def check_polylines(v: object) -> tuple[np.ndarray, ...]:
    lines = _seq_items(v, "", "a list of polylines")
    if isinstance(lines, np.ndarray):
        lines = list(lines)
    if len(lines) == 0:
        raise FieldError("must hold at least 1 polyline")
    if len(lines) > MAX_POLYLINES:
        raise FieldError(f"{len(lines)} polylines exceeds limit {MAX_POLYLINES}")
    total = 0
    out: list[np.ndarray] = []
    for i, line in enumerate(lines):
        pts = _seq_items(line, f"[{i}]", "a list of [x, y] points")
        total += len(pts)
        if total > MAX_MAP_POINTS:
            raise FieldError(f"more than {MAX_MAP_POINTS} points in total exceeds limit")
        if len(pts) < 2:
            raise FieldError(f"{len(pts)} point(s), a polyline needs at least 2", f"[{i}]")
        if isinstance(pts, np.ndarray):
            if pts.ndim != 2 or pts.shape[1] != 2:
                raise FieldError(f"must have shape (k, 2), got {pts.shape}", f"[{i}]")
            a = _numeric_array(pts, f"[{i}]")
        else:
            for j, p in enumerate(pts):
                if not isinstance(p, (list, tuple, np.ndarray)):
                    raise FieldError(f"must be [x, y], got {type_name(p)}", f"[{i}][{j}]")
                if len(p) != 2:
                    raise FieldError(f"must be [x, y], got {len(p)} elements", f"[{i}][{j}]")
                for k in (0, 1):
                    if type(p[k]) not in _FAST_NUM and not _is_number(p[k]):
                        raise FieldError(
                            f"must be a number, got {type_name(p[k])}", f"[{i}][{j}][{k}]"
                        )
            try:
                a = np.array(pts, dtype=np.float64)
            except OverflowError:
                a = np.array([[_big_to_float(c) for c in p] for p in pts], dtype=np.float64)
        bad = np.flatnonzero(~np.isfinite(a).reshape(-1))
        if bad.size:
            j, k = divmod(int(bad[0]), 2)
            raise FieldError("must be finite", f"[{i}][{j}][{k}]")
        out.append(_readonly(a))
    return tuple(out)


# --------------------------------------------------------------------------- annotated types

NUM_SCHEMA: dict[str, Any] = {"type": "number"}
_POSE_SCHEMA: dict[str, Any] = {
    "type": "array",
    "items": {"type": "number"},
    "minItems": 3,
    "maxItems": 3,
    "description": "[x, y, theta]: metres, metres, radians (theta normalised to (-pi, pi]).",
}


def nullable_schema(schema: dict[str, Any]) -> dict[str, Any]:
    return {"anyOf": [schema, {"type": "null"}]}


FiniteFloat = Annotated[
    float, PlainValidator(as_validator(check_finite)), WithJsonSchema(NUM_SCHEMA)
]
Count = Annotated[
    int,
    PlainValidator(as_validator(check_count)),
    WithJsonSchema({"type": "integer", "minimum": 0, "maximum": MAX_UINT}),
]
Ident = Annotated[
    str,
    PlainValidator(as_validator(check_ident)),
    WithJsonSchema({"type": "string", "pattern": ID_PATTERN}),
]
OptIdent = Annotated[
    str | None,
    PlainValidator(as_validator(optional_check(check_ident))),
    WithJsonSchema(nullable_schema({"type": "string", "pattern": ID_PATTERN})),
]
Pose3 = Annotated[np.ndarray, PlainValidator(as_validator(_pose3)), WithJsonSchema(_POSE_SCHEMA)]
OptPose3 = Annotated[
    np.ndarray | None,
    PlainValidator(as_validator(optional_check(_pose3))),
    WithJsonSchema(nullable_schema(_POSE_SCHEMA)),
]
UnitFloat = Annotated[
    float | None,
    PlainValidator(as_validator(optional_check(_unit_interval))),
    WithJsonSchema(nullable_schema({"type": "number", "minimum": 0, "maximum": 1})),
]


def _count_dict(v: object) -> dict[str, int]:
    if not isinstance(v, dict):
        raise FieldError(f"must be a map, got {type_name(v)}")
    if len(v) > 1024:
        raise FieldError(f"{len(v)} entries exceeds limit 1024")
    out: dict[str, int] = {}
    for k, n in v.items():
        if not isinstance(k, str) or not 1 <= len(k) <= ID_MAX_LEN:
            raise FieldError(f"key {k!r} must be a string of 1-{ID_MAX_LEN} characters")
        out[k] = check_count(n, f"[{k!r}]")
    return out


CountDict = Annotated[
    dict[str, int] | None,
    PlainValidator(as_validator(optional_check(_count_dict))),
    WithJsonSchema(
        nullable_schema(
            {"type": "object", "additionalProperties": {"type": "integer", "minimum": 0}}
        )
    ),
]
