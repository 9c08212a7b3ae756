"""Bytes <-> wire models, and wire models -> core arrays.

Payloads are msgpack maps with string keys; a payload whose Zenoh encoding is JSON
(``application/json``, optionally with ``;``-parameters, or ``text/json``) is the same map as
JSON. Every failure raises :class:`service.errors.InvalidMessage` with a compact
``<field>: <reason>`` text.
"""

from __future__ import annotations

import json as _json
import math
from typing import Any, TypeVar

import msgpack
import numpy as np

from schemas.limits import MAX_NESTING, MAX_PAYLOAD_BYTES
from schemas.messages import Scan, WireModel, wire_type_name
from service.errors import InvalidMessage

__all__ = [
    "JSON_ENCODING",
    "MSGPACK_ENCODING",
    "check_key_id",
    "decode",
    "encode",
    "is_json_encoding",
    "scan_arrays",
]

#: Encoding strings to attach to published samples.
JSON_ENCODING = "application/json"
MSGPACK_ENCODING = "application/msgpack"

M = TypeVar("M", bound=WireModel)


def is_json_encoding(encoding: object) -> bool:
    """True if a Zenoh encoding (object or its ``str`` form) says the payload is JSON."""
    if encoding is None:
        return False
    text = (encoding if isinstance(encoding, str) else str(encoding)).strip().lower()
    base = text.split(";", 1)[0].strip()
    return base in ("application/json", "text/json")


def _as_bytes(payload: object) -> bytes:
    if isinstance(payload, bytes):
        return payload
    if isinstance(payload, (bytearray, memoryview)):
        return bytes(payload)
    to_bytes = getattr(payload, "to_bytes", None)  # zenoh.ZBytes
    if callable(to_bytes):
        out = to_bytes()
        if isinstance(out, (bytes, bytearray, memoryview)):
            return bytes(out)
    raise InvalidMessage(f"payload: must be bytes, got {type(payload).__name__}")


def _check_structure(obj: dict, known: frozenset[str]) -> None:
    """Reject nesting deeper than ``MAX_NESTING`` and maps with non-string keys.

    Values of the model's own fields are skipped: their validators accept only the exact
    shape of the field, so any extra depth there is reported precisely by them. This walk
    guards the ignored unknown keys (and the top level).
    """
    for k in obj:
        if not isinstance(k, str):
            raise InvalidMessage(f"message: map keys must be strings, got {wire_type_name(k)}")
    stack: list[tuple[Any, int]] = [
        (v, 2) for k, v in obj.items() if k not in known and isinstance(v, _CONTAINERS)
    ]
    while stack:
        node, depth = stack.pop()
        if depth > MAX_NESTING:
            raise InvalidMessage(f"message: nesting deeper than {MAX_NESTING} levels")
        if isinstance(node, dict):
            for k, v in node.items():
                if not isinstance(k, str):
                    raise InvalidMessage(
                        f"message: map keys must be strings, got {wire_type_name(k)}"
                    )
                if isinstance(v, _CONTAINERS):
                    stack.append((v, depth + 1))
        else:
            stack.extend((v, depth + 1) for v in node if isinstance(v, _CONTAINERS))


_CONTAINERS = (dict, list, tuple)


def _loads(data: bytes, as_json: bool) -> Any:
    if as_json:
        try:
            text = data.decode("utf-8")
        except UnicodeDecodeError as e:
            raise InvalidMessage(f"json: not UTF-8 (byte {e.start})") from None
        try:
            return _json.loads(text)
        except _json.JSONDecodeError as e:
            raise InvalidMessage(f"json: {e.msg} at line {e.lineno} column {e.colno}") from None
        except RecursionError:
            raise InvalidMessage(f"message: nesting deeper than {MAX_NESTING} levels") from None
    try:
        # Tuples, not lists: faster for big maps, and every validator accepts both.
        return msgpack.unpackb(data, raw=False, strict_map_key=True, use_list=False)
    except msgpack.ExtraData:
        raise InvalidMessage("msgpack: trailing data after the message") from None
    except msgpack.StackError:
        raise InvalidMessage(f"message: nesting deeper than {MAX_NESTING} levels") from None
    except UnicodeDecodeError:
        raise InvalidMessage("msgpack: a string is not valid UTF-8") from None
    except msgpack.FormatError:
        raise InvalidMessage("msgpack: malformed (invalid type byte)") from None
    except (ValueError, TypeError, msgpack.UnpackException) as e:
        text = str(e) or type(e).__name__
        if "map key" in text:
            raise InvalidMessage("message: map keys must be strings") from None
        if "incomplete" in text or "exceeds max_" in text:
            # msgpack caps declared lengths by the payload size: a header promising more
            # elements than the payload could hold means the payload was cut short.
            raise InvalidMessage("msgpack: truncated payload") from None
        raise InvalidMessage(f"msgpack: malformed ({text[:160]})") from None


def decode(model_cls: type[M], payload: bytes, encoding: str | None = None) -> M:
    """Decode and validate one message.

    ``payload``: bytes (or bytearray/memoryview/``zenoh.ZBytes``), at most 16 MiB.
    ``encoding``: the sample's Zenoh encoding (``str`` or ``zenoh.Encoding``); JSON if it is
    ``application/json[;...]`` or ``text/json``, msgpack otherwise.
    Raises ``InvalidMessage`` naming the offending field.
    """
    data = _as_bytes(payload)
    if len(data) > MAX_PAYLOAD_BYTES:
        raise InvalidMessage(f"payload: {len(data)} bytes exceeds limit {MAX_PAYLOAD_BYTES}")
    if not data:
        raise InvalidMessage("payload: empty")
    obj = _loads(data, is_json_encoding(encoding))
    if not isinstance(obj, dict):
        raise InvalidMessage(f"message: must be a map, got {wire_type_name(obj)}")
    _check_structure(obj, frozenset(model_cls.model_fields))
    return model_cls.parse(obj)


def encode(msg: WireModel, json: bool = False, ranges_as_bytes: bool = False) -> bytes:
    """Serialise a message: msgpack (default) or JSON (``json=True``; non-finite ranges become
    ``null``). ``ranges_as_bytes`` (msgpack only) sends ``Scan.ranges`` as little-endian
    float32 bytes. Raises ``InvalidMessage`` if the payload would exceed 16 MiB."""
    if json and ranges_as_bytes:
        raise InvalidMessage("encode: ranges_as_bytes is msgpack-only (JSON has no bytes)")
    if ranges_as_bytes and not isinstance(msg, Scan):
        raise InvalidMessage(f"encode: ranges_as_bytes needs a Scan, got {type(msg).__name__}")
    wire = msg.to_wire(ranges_as_bytes=ranges_as_bytes)
    if json:
        if isinstance(msg, Scan):
            wire["ranges"] = [r if math.isfinite(r) else None for r in wire["ranges"]]
        data = _json.dumps(wire, allow_nan=False, separators=(",", ":")).encode("utf-8")
    else:
        data = msgpack.packb(wire, use_bin_type=True)
    if len(data) > MAX_PAYLOAD_BYTES:
        raise InvalidMessage(f"payload: {len(data)} bytes exceeds limit {MAX_PAYLOAD_BYTES}")
    return data


def check_key_id(msg_id: str, key_id: str, field: str) -> None:
    """Raise ``InvalidMessage`` unless the id inside a message equals the id in its key."""
    if msg_id != key_id:
        raise InvalidMessage(f"{field} {msg_id!r} does not match key {key_id!r}")


def scan_arrays(scan: Scan) -> tuple[np.ndarray, np.ndarray]:
    """``(ranges, angles)`` for the core, both float64 ``(n,)``.

    ``ranges`` in metres with NaN for every "no return" (NaN, inf, or outside
    ``[range_min, range_max]``); ``angles`` in radians in the robot frame,
    ``angle_min + i * angle_increment``.
    """
    r = np.array(scan.ranges, dtype=np.float64)
    with np.errstate(invalid="ignore"):
        bad = ~np.isfinite(r) | (r < scan.range_min) | (r > scan.range_max)
    r[bad] = np.nan
    angles = scan.angle_min + np.arange(r.size, dtype=np.float64) * scan.angle_increment
    return r, angles
