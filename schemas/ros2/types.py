"""The ROS 2 message types the front speaks, from one distribution's type store.

The target distribution is **Jazzy Jalisco** (:data:`DISTRIBUTION`); its message definitions
come from ``rosbags``' built-in type store ``Stores.ROS2_JAZZY`` (no ROS install), and so do
the RIHS01 type hashes (``hash_rihs01``) that rmw_zenoh puts in every key expression. Kilted
and Rolling have the same definitions (so the same hashes) for the five types used here.

A :class:`RosType` carries the three names a type has on the wire: the ROS name
(``sensor_msgs/msg/LaserScan``), the DDS name rmw_zenoh writes in key expressions
(``sensor_msgs::msg::dds_::LaserScan_``) and the RIHS01 hash (``RIHS01_<64 hex>``).
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from functools import cache
from typing import Any, Final

from service.errors import InvalidMessage

#: The ROS 2 distribution whose type definitions and hashes are used.
DISTRIBUTION: Final[str] = "jazzy"

_ROS_TYPE_RE = re.compile(r"([A-Za-z][A-Za-z0-9_]*)/(msg|srv|action)/([A-Za-z][A-Za-z0-9_]*)")
_HASH_RE = re.compile(r"RIHS01_[0-9a-f]{64}")


@cache
def typestore() -> Any:
    """``rosbags``' type store of :data:`DISTRIBUTION` (built once)."""
    from rosbags.typesys import Stores, get_typestore

    return get_typestore(Stores.ROS2_JAZZY)


def dds_type_name(ros_type: str) -> str:
    """``pkg/msg/Name`` -> ``pkg::msg::dds_::Name_`` (the type name rmw_zenoh uses)."""
    m = _ROS_TYPE_RE.fullmatch(ros_type)
    if m is None:
        raise InvalidMessage(f"type: {ros_type[:120]!r} is not a ROS 2 type name pkg/msg/Name")
    return f"{m.group(1)}::{m.group(2)}::dds_::{m.group(3)}_"


def ros_type_name(dds_type: str) -> str:
    """Inverse of :func:`dds_type_name`: ``pkg::msg::dds_::Name_`` -> ``pkg/msg/Name``."""
    parts = dds_type.split("::")
    name = f"{parts[0]}/{parts[1]}/{parts[3][:-1]}" if len(parts) == 4 else ""
    if parts[2:3] != ["dds_"] or not parts[-1].endswith("_") or not _ROS_TYPE_RE.fullmatch(name):
        raise InvalidMessage(f"type: {dds_type[:120]!r} is not a DDS name pkg::msg::dds_::Name_")
    return name


def is_type_hash(text: str) -> bool:
    """Whether ``text`` is a RIHS01 type hash (``RIHS01_`` and 64 lower-case hex digits)."""
    return _HASH_RE.fullmatch(text) is not None


@dataclass(frozen=True)
class RosType:
    """One message type: ROS name, DDS name and RIHS01 hash of :data:`DISTRIBUTION`."""

    ros: str
    dds: str
    hash: str

    @staticmethod
    def of(ros_type: str) -> RosType:
        """The type ``ros_type`` of the target distribution's type store."""
        store = typestore()
        if ros_type not in store.types:
            raise InvalidMessage(f"type: {ros_type!r} is not in the {DISTRIBUTION} type store")
        return RosType(ros_type, dds_type_name(ros_type), store.hash_rihs01(ros_type))


LASER_SCAN: Final[RosType] = RosType.of("sensor_msgs/msg/LaserScan")
TF_MESSAGE: Final[RosType] = RosType.of("tf2_msgs/msg/TFMessage")
ODOMETRY: Final[RosType] = RosType.of("nav_msgs/msg/Odometry")
POSE_WITH_COVARIANCE_STAMPED: Final[RosType] = RosType.of(
    "geometry_msgs/msg/PoseWithCovarianceStamped"
)
OCCUPANCY_GRID: Final[RosType] = RosType.of("nav_msgs/msg/OccupancyGrid")

#: Every type the front and the simulator use.
TYPES: Final[tuple[RosType, ...]] = (
    LASER_SCAN,
    TF_MESSAGE,
    ODOMETRY,
    POSE_WITH_COVARIANCE_STAMPED,
    OCCUPANCY_GRID,
)
