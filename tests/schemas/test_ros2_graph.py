"""rmw_zenoh's key expressions, liveliness tokens, QoS strings and GIDs (schemas/ros2/graph.py)
against values written by other rmw_zenoh clients and by zenoh-ros2-sdk.

Sources of the literal values:

* ZettaScale's zenoh-cpp example of an rmw_zenoh subscriber (2025) declares
  ``@ros2_lv/0/<zid>/<nid>/<nid>/NN/%/%/zenoh_sub`` and, for its subscriptions,
  ``.../MS/%/%/zenoh_sub/%tf/tf2_msgs::msg::dds_::TFMessage_/RIHS01_e369.../::,100:,:,:,,``
  and ``.../%tf_static/.../:1:,1:,:,:,,`` (tf2's listener QoS, keep last 100; the static
  listener, transient local keep last 1);
* ros2/rmw_zenoh ``liveliness_utils.cpp`` (``qos_to_keyexpr``, ``TopicInfo``) and ``qos.cpp``
  (defaults: reliable, volatile, keep last 42, infinite durations, automatic liveliness);
* ZettaScaleLabs/ros-z ``crates/ros-z-protocol/src/format/rmw_zenoh.rs`` tests: internal
  slashes of a topic stay in the data key (``0/ns/topic/...``) and are ``%`` in a token.
"""

from __future__ import annotations

import pytest

from schemas.ros2 import graph, types
from service.errors import InvalidMessage

ZID = "1234567890abcdef1234567890abcdef"
TF_HASH = "RIHS01_e369d0f05a23ae52508854b66f6aa0437f3449d652e8cbf22d5abe85d020f087"


def test_data_keys_keep_the_slashes_of_the_topic_name() -> None:
    key = graph.topic_key(0, "/robot1/scan", types.LASER_SCAN)
    assert key == (
        "0/robot1/scan/sensor_msgs::msg::dds_::LaserScan_/"
        "RIHS01_64c191398013af96509d518dac71d5164f9382553fce5c1f8cca5be7924bd828"
    )
    assert (
        graph.topic_key(7, "/tf", types.TF_MESSAGE)
        == f"7/tf/tf2_msgs::msg::dds_::TFMessage_/{TF_HASH}"
    )
    assert graph.topic_of_key(0, key, types.LASER_SCAN) == "/robot1/scan"
    sel = graph.topic_selector(0, "scan", types.LASER_SCAN)
    assert sel.startswith("0/**/scan/")


def test_the_token_formats_equal_a_zettascale_rmw_zenoh_client() -> None:
    node = graph.NodeInfo(0, ZID, 0, "/", "zenoh_sub")
    assert graph.node_token(node) == f"@ros2_lv/0/{ZID}/0/0/NN/%/%/zenoh_sub"
    tf = graph.endpoint_token(node, 1, "MS", "/tf", types.TF_MESSAGE, graph.TF_QOS)
    assert tf == (
        f"@ros2_lv/0/{ZID}/0/1/MS/%/%/zenoh_sub/%tf/tf2_msgs::msg::dds_::TFMessage_/"
        f"{TF_HASH}/::,100:,:,:,,"
    )
    static = graph.endpoint_token(node, 2, "MS", "/tf_static", types.TF_MESSAGE, graph.LATCHED_QOS)
    assert static.endswith(f"/%tf_static/tf2_msgs::msg::dds_::TFMessage_/{TF_HASH}/:1:,1:,:,:,,")


def test_namespaced_tokens_mangle_every_slash() -> None:
    node = graph.NodeInfo(3, ZID, 4, "/site_a/robot1", "shapeloc")
    tok = graph.endpoint_token(
        node, 9, "MP", "/site_a/robot1/amcl_pose", types.POSE_WITH_COVARIANCE_STAMPED,
        graph.LATCHED_QOS,
    )  # fmt: skip
    assert tok.startswith(
        f"@ros2_lv/3/{ZID}/4/9/MP/%/%site_a%robot1/shapeloc/%site_a%robot1%amcl_pose/"
    )
    parsed = graph.parse_token(tok)
    assert parsed.namespace == "/site_a/robot1" and parsed.topic == "/site_a/robot1/amcl_pose"
    assert parsed.type_name == "geometry_msgs/msg/PoseWithCovarianceStamped"
    assert parsed.qos == graph.LATCHED_QOS and (parsed.node_id, parsed.entity_id) == (4, 9)


@pytest.mark.parametrize(
    ("qos", "text"),
    [
        (graph.SYSTEM_DEFAULT_QOS, "::,:,:,:,,"),
        (graph.QoS(depth=10), "::,10:,:,:,,"),
        (graph.SENSOR_DATA_QOS, "2::,5:,:,:,,"),
        (graph.TF_QOS, "::,100:,:,:,,"),
        (graph.LATCHED_QOS, ":1:,1:,:,:,,"),
        (graph.QoS(history=graph.KEEP_ALL, depth=1000), "::2,1000:,:,:,,"),
        (graph.QoS(deadline=(1, 500), liveliness=graph.MANUAL_BY_TOPIC), "::,:1,500:,:3,,"),
    ],
)
def test_qos_strings_leave_rmw_zenoh_defaults_empty(qos: graph.QoS, text: str) -> None:
    assert qos.encode() == text
    assert graph.QoS.decode(text) == qos


def test_qos_strings_agree_with_zenoh_ros2_sdk_decoding() -> None:
    from zenoh_ros2_sdk.qos import QosDurability, QosProfile, QosReliability

    for qos in (graph.SENSOR_DATA_QOS, graph.LATCHED_QOS, graph.TF_QOS):
        sdk = QosProfile.decode(qos.encode())
        assert sdk.history_depth == qos.depth
        assert (sdk.reliability == QosReliability.BEST_EFFORT) == (qos.reliability == 2)
        assert (sdk.durability == QosDurability.TRANSIENT_LOCAL) == (qos.durability == 1)


@pytest.mark.parametrize("bad", ["", "::,:,:,", "a::,:,:,:,,", "::,:,:,:,,:", "::,-1:,:,:,,"])
def test_bad_qos_strings_are_rejected(bad: str) -> None:
    with pytest.raises(InvalidMessage):
        graph.QoS.decode(bad)


def test_tokens_agree_with_zenoh_ros2_sdk() -> None:
    from zenoh_ros2_sdk.entity import EndpointEntity, EntityKind, NodeEntity
    from zenoh_ros2_sdk.keyexpr import endpoint_liveliness_keyexpr, node_liveliness_keyexpr

    sdk_node = NodeEntity(0, ZID, 2, "shapeloc", "/robot1")
    ours = graph.NodeInfo(0, ZID, 2, "/robot1", "shapeloc")
    assert graph.node_token(ours) == node_liveliness_keyexpr(sdk_node)
    sdk_ep = EndpointEntity(
        sdk_node, 5, EntityKind.SUBSCRIPTION, "/robot1/scan", types.LASER_SCAN.dds,
        types.LASER_SCAN.hash, graph.SENSOR_DATA_QOS.encode(),
    )  # fmt: skip
    ep = graph.endpoint_token(
        ours, 5, "MS", "/robot1/scan", types.LASER_SCAN, graph.SENSOR_DATA_QOS
    )
    assert ep == endpoint_liveliness_keyexpr(sdk_ep)


@pytest.mark.parametrize(
    ("ns", "rid"), [("/robot1", "robot1"), ("/site_a/robot_2", "site_a.robot_2"), ("/", "dflt")]
)
def test_namespaces_map_to_valid_robot_ids_and_back(ns: str, rid: str) -> None:
    assert graph.robot_id_of_namespace(ns, "dflt") == rid
    if ns != "/":
        assert graph.namespace_of_robot_id(rid) == ns


@pytest.mark.parametrize("bad", ["robot1", "/robot 1", "/1robot", "//a", "/a/", "/a-b", "/a.b"])
def test_bad_namespaces_are_rejected(bad: str) -> None:
    with pytest.raises(InvalidMessage):
        graph.robot_id_of_namespace(bad, "dflt")


def test_a_namespace_longer_than_the_id_rule_is_rejected() -> None:
    with pytest.raises(InvalidMessage, match="robot id of namespace"):
        graph.robot_id_of_namespace("/" + "a" * 70, "dflt")


@pytest.mark.parametrize(
    "bad",
    [
        "@ros2_lv/0/abc/0/0/NN/%/%",  # too short
        "@ros2_lv/0/abc/0/0/XX/%/%/n",  # unknown kind
        "@ros2_lv/0/abc/0/0/MP/%/%/n",  # publisher without topic
        "@ros2_lv/x/abc/0/0/NN/%/%/n",  # domain not a number
        "other/0/abc/0/0/NN/%/%/n",
        "@ros2_lv/0/abc/0/1/MS/%/%/n/%tf/tf2_msgs::msg::dds_::TFMessage_/RIHS01_00/::,:,:,:,,",
    ],
)
def test_malformed_tokens_are_rejected(bad: str) -> None:
    with pytest.raises(InvalidMessage):
        graph.parse_token(bad)


def test_the_gid_is_xxh3_128_of_the_token_low_half_first() -> None:
    import xxhash

    tok = graph.node_token(graph.NodeInfo(0, ZID, 0, "/", "n"))
    gid = graph.gid_of(tok)
    big_endian = xxhash.xxh3_128(tok.encode()).digest()  # canonical form: high 64 bits first
    assert len(gid) == 16
    assert gid == big_endian[8:][::-1] + big_endian[:8][::-1]
