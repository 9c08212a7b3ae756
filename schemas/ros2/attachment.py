"""The attachment rmw_zenoh puts on every published sample (source of the layout below:
``rmw_zenoh_cpp/src/detail/attachment_helpers.cpp``, Jazzy from 0.2.4 on, the same in Kilted
and Rolling).

Layout: the zenoh-ext serialisation of, in order, the sequence number (int64 little-endian),
the source timestamp (int64 little-endian, nanoseconds since the Unix epoch) and the source
GID (a 16-byte array, which zenoh-ext writes as a sequence: its LEB128 length, 16, then the
bytes): 33 bytes in all. rmw_zenoh's own subscriptions drop a sample that carries no
attachment, so everything the project publishes on ROS 2 keys carries one.

Jazzy before 0.2.4 wrote a keyed form (each value preceded by its name as a zenoh-ext string:
``sequence_number``, ``source_timestamp``, ``source_gid``); :func:`decode_attachment` reads
both. An attachment is optional on input: a sample without one is accepted by the front.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from typing import Final

from service.errors import InvalidMessage

#: Bytes of a GID (``RMW_GID_STORAGE_SIZE`` since Jazzy).
GID_SIZE: Final[int] = 16
#: Bytes of the positional attachment.
ATTACHMENT_SIZE: Final[int] = 8 + 8 + 1 + GID_SIZE
_KEYS: Final[tuple[str, str, str]] = ("sequence_number", "source_timestamp", "source_gid")
_INT64 = (-(2**63), 2**63 - 1)


@dataclass(frozen=True)
class Attachment:
    """``sequence_number`` (int64), ``source_timestamp`` (int64 ns), ``source_gid`` (16 bytes)."""

    sequence_number: int
    source_timestamp: int
    source_gid: bytes

    def __post_init__(self) -> None:
        for name in ("sequence_number", "source_timestamp"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or not _INT64[0] <= v <= _INT64[1]:
                raise InvalidMessage(f"attachment.{name}: {v!r} is not an int64")
        gid = self.source_gid
        if not isinstance(gid, (bytes, bytearray)) or len(gid) != GID_SIZE:
            raise InvalidMessage(f"attachment.source_gid: must be {GID_SIZE} bytes")
        object.__setattr__(self, "source_gid", bytes(gid))


def encode_attachment(att: Attachment) -> bytes:
    """The 33 bytes rmw_zenoh (Jazzy >= 0.2.4) attaches to a sample."""
    return (
        struct.pack("<qq", att.sequence_number, att.source_timestamp)
        + bytes([GID_SIZE])
        + att.source_gid
    )


def _varint(data: bytes, pos: int) -> tuple[int, int]:
    """LEB128 unsigned integer at ``pos`` (at most 10 bytes) -> (value, next position)."""
    value = shift = 0
    for k in range(10):
        if pos + k >= len(data):
            raise InvalidMessage("attachment: truncated length")
        b = data[pos + k]
        value |= (b & 0x7F) << shift
        if not b & 0x80:
            return value, pos + k + 1
        shift += 7
    raise InvalidMessage("attachment: length longer than 10 bytes")


def _chunk(data: bytes, pos: int, what: str) -> tuple[bytes, int]:
    n, pos = _varint(data, pos)
    if n > len(data) - pos:
        raise InvalidMessage(f"attachment: {what} of {n} bytes runs past the end")
    return data[pos : pos + n], pos + n


def _int64(data: bytes, pos: int, what: str) -> tuple[int, int]:
    if pos + 8 > len(data):
        raise InvalidMessage(f"attachment: truncated {what}")
    return struct.unpack_from("<q", data, pos)[0], pos + 8


def decode_attachment(data: object) -> Attachment:
    """Decode an rmw_zenoh attachment, positional (Jazzy >= 0.2.4) or keyed (earlier)."""
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise InvalidMessage(f"attachment: must be bytes, got {type(data).__name__}")
    raw = bytes(data)
    if len(raw) > 1024:
        raise InvalidMessage(f"attachment: {len(raw)} bytes is longer than any rmw_zenoh one")
    if len(raw) == ATTACHMENT_SIZE and raw[16] == GID_SIZE:
        seq, ts = struct.unpack_from("<qq", raw, 0)
        return Attachment(seq, ts, raw[17:])
    values: list[int | bytes] = []
    pos = 0
    for key in _KEYS:
        name, pos = _chunk(raw, pos, "key")
        if name != key.encode():
            raise InvalidMessage(
                f"attachment: neither the positional nor the keyed layout (expected key "
                f"{key!r}, found {name[:40]!r})"
            )
        if key == "source_gid":
            gid, pos = _chunk(raw, pos, "source_gid")
            values.append(gid)
        else:
            v, pos = _int64(raw, pos, key)
            values.append(v)
    if pos != len(raw):
        raise InvalidMessage(f"attachment: {len(raw) - pos} trailing bytes")
    seq, ts, gid = values
    assert isinstance(seq, int) and isinstance(ts, int) and isinstance(gid, bytes)
    return Attachment(seq, ts, gid)
