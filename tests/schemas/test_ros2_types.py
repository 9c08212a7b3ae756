"""The Jazzy type names and RIHS01 hashes of schemas/ros2/types.py against published values
and against zenoh-ros2-sdk's own RIHS01 implementation.

Published values (each seen in use on Jazzy systems, not computed by this project):

* LaserScan ``RIHS01_64c1...``: the project's issue (key of ``/robot1/scan``) and the
  ``sensor_msgs::msg::dds_::LaserScan_`` entry of a Rust rmw_zenoh client's message table
  (ros-z's ``TypeInfo`` / ``TypeHash`` form);
* TFMessage ``RIHS01_e369...``: ZettaScale's zenoh-cpp example of an rmw_zenoh subscriber
  (its ``/tf`` and ``/tf_static`` liveliness tokens), and ``ros2 topic info --verbose
  /robot1/tf`` of an AMCL node on Jazzy in a public Q&A capture;
* Odometry ``RIHS01_3cc9...``: ZettaScaleLabs/ros-z
  ``crates/ros-z-codegen/tests/hash_regression.rs`` (``test_expected_hash_odometry``, checked
  there against rmw_zenoh_cpp interop tests);
* PoseWithCovarianceStamped ``RIHS01_2643...`` and OccupancyGrid ``RIHS01_8d34...``: the
  ``ros2 topic info --verbose`` outputs of RViz on Jazzy in public captures and the generated
  type tables of several independent rmw_zenoh clients (C, C++, Python msgspec).
"""

from __future__ import annotations

import pytest

from schemas.ros2 import types
from service.errors import InvalidMessage
from tests.schemas.ros2_msgdefs import dependencies, msg_text

PUBLISHED = {
    "sensor_msgs/msg/LaserScan": (
        "sensor_msgs::msg::dds_::LaserScan_",
        "RIHS01_64c191398013af96509d518dac71d5164f9382553fce5c1f8cca5be7924bd828",
    ),
    "tf2_msgs/msg/TFMessage": (
        "tf2_msgs::msg::dds_::TFMessage_",
        "RIHS01_e369d0f05a23ae52508854b66f6aa0437f3449d652e8cbf22d5abe85d020f087",
    ),
    "nav_msgs/msg/Odometry": (
        "nav_msgs::msg::dds_::Odometry_",
        "RIHS01_3cc97dc7fb7502f8714462c526d369e35b603cfc34d946e3f2eda2766dfec6e0",
    ),
    "geometry_msgs/msg/PoseWithCovarianceStamped": (
        "geometry_msgs::msg::dds_::PoseWithCovarianceStamped_",
        "RIHS01_26432f9803e43727d3c8f668d1fdb3c630f548af631e2f4e31382371bfea3b6e",
    ),
    "nav_msgs/msg/OccupancyGrid": (
        "nav_msgs::msg::dds_::OccupancyGrid_",
        "RIHS01_8d348150c12913a31ee0ec170fbf25089e4745d17035792a1ba94d6f0bc0cfc7",
    ),
}


def test_the_distribution_is_jazzy() -> None:
    assert types.DISTRIBUTION == "jazzy"
    assert {t.ros for t in types.TYPES} == set(PUBLISHED)


@pytest.mark.parametrize("rtype", types.TYPES, ids=lambda t: t.ros.rsplit("/", 1)[-1])
def test_names_and_hashes_equal_the_published_values(rtype: types.RosType) -> None:
    dds, rihs = PUBLISHED[rtype.ros]
    assert rtype.dds == dds
    assert rtype.hash == rihs
    assert types.is_type_hash(rtype.hash)
    assert types.ros_type_name(rtype.dds) == rtype.ros


@pytest.mark.parametrize("ros_type", sorted(PUBLISHED))
def test_zenoh_ros2_sdk_computes_the_same_hash_from_the_msg_text(ros_type: str) -> None:
    from zenoh_ros2_sdk.utils import compute_type_hash_from_msg, ros2_to_dds_type

    got = compute_type_hash_from_msg(ros_type, msg_text(ros_type), dependencies(ros_type))
    assert got == PUBLISHED[ros_type][1]
    assert ros2_to_dds_type(ros_type) == PUBLISHED[ros_type][0]


@pytest.mark.parametrize(
    "bad", ["", "LaserScan", "sensor_msgs/LaserScan", "a/msg/b/c", "1x/msg/Y", "a/msg/"]
)
def test_bad_type_names_are_rejected(bad: str) -> None:
    with pytest.raises(InvalidMessage):
        types.dds_type_name(bad)


@pytest.mark.parametrize(
    "bad", ["", "a::msg::B_", "a::msg::dds_::B", "a::msg::xx_::B_", "a::b::c::d::e_"]
)
def test_bad_dds_names_are_rejected(bad: str) -> None:
    with pytest.raises(InvalidMessage):
        types.ros_type_name(bad)


def test_a_type_outside_the_store_is_refused() -> None:
    with pytest.raises(InvalidMessage, match="not in the jazzy type store"):
        types.RosType.of("nosuch_msgs/msg/Nothing")
