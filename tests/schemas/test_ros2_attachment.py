"""rmw_zenoh's sample attachment (schemas/ros2/attachment.py) against Zenoh's own zenoh-ext
serializer (zenoh-python's ``zenoh.ext.z_serialize``, the Rust serializer rmw_zenoh_cpp's
zenoh-cpp serializer is compatible with) and against zenoh-ros2-sdk's attachment codec."""

from __future__ import annotations

import struct

import pytest
import zenoh.ext as zx

from schemas.ros2.attachment import Attachment, decode_attachment, encode_attachment
from service.errors import InvalidMessage

GID = bytes(range(100, 116))


def test_the_positional_layout_equals_zenoh_ext_serialization() -> None:
    att = Attachment(42, 1_700_000_000_123_456_789, GID)
    ours = encode_attachment(att)
    # rmw_zenoh_cpp serialises int64, int64 and a std::array<uint8_t, 16> (a sequence)
    theirs = zx.z_serialize(
        (zx.Int64(42), zx.Int64(1_700_000_000_123_456_789), [zx.UInt8(b) for b in GID])
    )
    assert ours == theirs.to_bytes()
    assert len(ours) == 33 and ours[16] == 16
    assert decode_attachment(ours) == att


def test_the_keyed_layout_of_jazzy_before_0_2_4_is_read() -> None:
    keyed = zx.z_serialize(
        ("sequence_number", zx.Int64(7), "source_timestamp", zx.Int64(-5), "source_gid", GID)
    ).to_bytes()
    assert decode_attachment(keyed) == Attachment(7, -5, GID)


def test_zenoh_ros2_sdk_reads_ours_and_we_read_its() -> None:
    from zenoh_ros2_sdk.attachment import Attachment as SdkAttachment

    ours = encode_attachment(Attachment(3, 99, GID))
    sdk = SdkAttachment.from_bytes(ours)
    assert (sdk.sequence_id, sdk.timestamp_ns, sdk.gid) == (3, 99, GID)
    assert decode_attachment(SdkAttachment(5, 6, GID).to_bytes()) == Attachment(5, 6, GID)


@pytest.mark.parametrize(
    "bad",
    [
        b"",
        b"\x01" * 10,
        struct.pack("<qq", 1, 2) + b"\x10" + b"\x00" * 10,  # truncated gid
        struct.pack("<qq", 1, 2) + b"\x08" + b"\x00" * 16,  # wrong gid length
        b"\x0fsequence_number" + b"\x00" * 3,  # keyed, truncated value
        b"\x0fsequence_numbeX" + b"\x00" * 40,  # keyed, wrong key
        b"\xff" * 12,  # endless varint
        b"\x00" * 2000,  # far too long
    ],
)
def test_malformed_attachments_are_rejected(bad: bytes) -> None:
    with pytest.raises(InvalidMessage):
        decode_attachment(bad)


def test_out_of_range_fields_are_rejected() -> None:
    with pytest.raises(InvalidMessage):
        Attachment(2**63, 0, GID)
    with pytest.raises(InvalidMessage):
        Attachment(0, 0, b"short")
