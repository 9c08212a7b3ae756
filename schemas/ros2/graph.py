"""rmw_zenoh's names on Zenoh: data key expressions, liveliness tokens, QoS strings, GIDs.

Facts followed (``ros2/rmw_zenoh``, ``rmw_zenoh_cpp/src/detail/liveliness_utils.cpp`` and
``qos.cpp``, Jazzy 0.2.x from 0.2.4 on; Kilted and Rolling write the same):

* Data key of a topic: ``<domain_id>/<topic name without its leading and trailing slash>/
  <DDS type name>/<RIHS01 hash>``; the slashes inside the topic name stay (``0/robot1/scan/
  sensor_msgs::msg::dds_::LaserScan_/RIHS01_64c1...``).
* Liveliness token (the ROS graph): ``@ros2_lv/<domain_id>/<session zid>/<node id>/<entity
  id>/<kind>/<enclave>/<namespace>/<node name>`` for a node (kind ``NN``; its entity id is
  its node id), followed by ``/<topic name>/<DDS type name>/<hash>/<QoS>`` for a publisher
  (``MP``) or subscription (``MS``). Every ``/`` inside a name is written ``%`` (so the root
  namespace and the default enclave ``/`` are ``%`` and ``/robot1/scan`` is
  ``%robot1%scan``). Node and entity ids are one counter per session (context), from 0.
* QoS string: ``<reliability>:<durability>:<history>,<depth>:<deadline s>,<deadline ns>:
  <lifespan s>,<lifespan ns>:<liveliness>,<lease s>,<lease ns>`` with the rmw enum values
  (reliability 1 reliable, 2 best effort; durability 1 transient local, 2 volatile; history 1
  keep last, 2 keep all; liveliness 1 automatic, 3 manual by topic); every part equal to
  rmw_zenoh's default (reliable, volatile, keep last, depth 42, infinite durations, automatic)
  is left empty, so the default profile is ``::,:,:,:,,`` and tf2's listener
  (keep last 100) is ``::,100:,:,:,,``.
* GID of an entity: XXH3-128 of its liveliness token, the low 64 bits then the high 64 bits,
  each little-endian (16 bytes); it is the ``source_gid`` of the attachments it publishes.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, fields
from typing import Final, Literal

from schemas.keys import id_error
from schemas.ros2.types import RosType, dds_type_name, is_type_hash, ros_type_name
from service.errors import InvalidMessage

ADMIN_SPACE: Final[str] = "@ros2_lv"
NODE: Final[str] = "NN"
PUBLISHER: Final[str] = "MP"
SUBSCRIPTION: Final[str] = "MS"
EndpointKind = Literal["MP", "MS"]
_KINDS: Final[tuple[str, ...]] = ("NN", "MP", "MS", "SS", "SC")

#: rmw enum values (``rmw/types.h``).
RELIABLE, BEST_EFFORT = 1, 2
TRANSIENT_LOCAL, VOLATILE = 1, 2
KEEP_LAST, KEEP_ALL = 1, 2
AUTOMATIC, MANUAL_BY_TOPIC = 1, 3
#: ``RMW_DURATION_INFINITE``: (seconds, nanoseconds).
INFINITE: Final[tuple[int, int]] = (9223372036, 854775807)
#: rmw_zenoh's depth for a profile that asks for the system default (depth 0).
DEFAULT_DEPTH: Final[int] = 42

_TOKEN_RE = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")
_MAX_DOMAIN = 2**32 - 1


# --------------------------------------------------------------------------- ROS names
def check_name(name: object, what: str = "name") -> str:
    """A fully qualified ROS name (``/`` or ``/a/b``: tokens of ``[A-Za-z_][A-Za-z0-9_]*``)."""
    if not isinstance(name, str):
        raise InvalidMessage(f"{what}: must be a string, got {type(name).__name__}")
    if name == "/":
        return name
    if not name.startswith("/") or len(name) > 1024:
        raise InvalidMessage(f"{what}: {name[:120]!r} is not a fully qualified ROS name")
    for token in name[1:].split("/"):
        if _TOKEN_RE.fullmatch(token) is None:
            raise InvalidMessage(f"{what}: {name[:120]!r} is not a fully qualified ROS name")
    return name


def join_name(namespace: str, name: str) -> str:
    """``namespace`` + relative ``name`` (``/robot1`` + ``scan`` -> ``/robot1/scan``)."""
    ns = check_name(namespace, "namespace")
    return check_name(("" if ns == "/" else ns) + "/" + name, "name")


def split_name(topic: str) -> tuple[str, str]:
    """``(namespace, last token)`` of a topic name (``/a/b/scan`` -> ``("/a/b", "scan")``)."""
    check_name(topic, "topic")
    if topic == "/":
        raise InvalidMessage("topic: '/' has no name")
    ns, _, leaf = topic.rpartition("/")
    return ns or "/", leaf


def mangle(name: str) -> str:
    """A name as it appears in one chunk of a liveliness token: every ``/`` -> ``%``."""
    return name.replace("/", "%")


def demangle(chunk: str) -> str:
    """Inverse of :func:`mangle`."""
    return chunk.replace("%", "/")


def robot_id_of_namespace(namespace: str, default_id: str) -> str:
    """The robot id of a ROS namespace: the namespace without its leading slash, nested
    levels joined by ``.`` (``/robot1`` -> ``robot1``, ``/site_a/robot1`` ->
    ``site_a.robot1``; ROS names cannot hold ``.``, so this is one to one); the root namespace
    gives ``default_id``. Raises if the result breaks the wire's id rule (1-64 characters)."""
    ns = check_name(namespace, "namespace")
    rid = default_id if ns == "/" else ns[1:].replace("/", ".")
    problem = id_error(rid)
    if problem is not None:
        raise InvalidMessage(f"robot id of namespace {ns[:120]!r}: {problem}")
    return rid


def namespace_of_robot_id(robot_id: str) -> str:
    """Inverse of :func:`robot_id_of_namespace` for a namespaced robot (``a.b`` -> ``/a/b``)."""
    return check_name("/" + robot_id.replace(".", "/"), f"namespace of robot id {robot_id!r}")


def check_domain(domain_id: object) -> int:
    """A ROS domain id (a non-negative integer)."""
    if isinstance(domain_id, bool) or not isinstance(domain_id, int):
        raise InvalidMessage(f"domain id: must be an integer, got {domain_id!r}")
    if not 0 <= domain_id <= _MAX_DOMAIN:
        raise InvalidMessage(f"domain id: {domain_id} is out of range")
    return domain_id


# --------------------------------------------------------------------------- data keys
def topic_key(domain_id: int, topic: str, rtype: RosType) -> str:
    """``<domain>/<topic without leading slash>/<DDS type>/<hash>``."""
    name = check_name(topic, "topic").strip("/")
    if not name:
        raise InvalidMessage("topic: '/' has no name")
    return f"{check_domain(domain_id)}/{name}/{rtype.dds}/{rtype.hash}"


def topic_selector(domain_id: int, leaf: str, rtype: RosType) -> str:
    """Key expression of the topic ``leaf`` of every namespace (``0/**/scan/<type>/<hash>``:
    ``**`` also matches no namespace at all)."""
    if _TOKEN_RE.fullmatch(leaf) is None:
        raise InvalidMessage(f"topic: {leaf[:120]!r} is not one ROS name token")
    return f"{check_domain(domain_id)}/**/{leaf}/{rtype.dds}/{rtype.hash}"


def topic_of_key(domain_id: int, key: str, rtype: RosType) -> str:
    """The fully qualified topic name of a data key of type ``rtype`` (checked)."""
    head = f"{check_domain(domain_id)}/"
    tail = f"/{rtype.dds}/{rtype.hash}"
    if not isinstance(key, str) or not key.startswith(head) or not key.endswith(tail):
        raise InvalidMessage(f"key: {str(key)[:200]!r} is not a {rtype.ros} key of {head}")
    return check_name("/" + key[len(head) : len(key) - len(tail)], "topic")


# --------------------------------------------------------------------------- QoS
@dataclass(frozen=True)
class QoS:
    """A resolved rmw QoS profile (rmw enum values; durations as (seconds, nanoseconds))."""

    reliability: int = RELIABLE
    durability: int = VOLATILE
    history: int = KEEP_LAST
    depth: int = DEFAULT_DEPTH
    deadline: tuple[int, int] = INFINITE
    lifespan: tuple[int, int] = INFINITE
    liveliness: int = AUTOMATIC
    liveliness_lease: tuple[int, int] = INFINITE

    def encode(self) -> str:
        """rmw_zenoh's QoS string (parts equal to the default left empty)."""
        d = QoS()

        def part(value: int, default: int) -> str:
            return "" if value == default else str(value)

        def dur(value: tuple[int, int], default: tuple[int, int]) -> str:
            return f"{part(value[0], default[0])},{part(value[1], default[1])}"

        return ":".join(
            (
                part(self.reliability, d.reliability),
                part(self.durability, d.durability),
                f"{part(self.history, d.history)},{part(self.depth, d.depth)}",
                dur(self.deadline, d.deadline),
                dur(self.lifespan, d.lifespan),
                part(self.liveliness, d.liveliness) + "," + dur(self.liveliness_lease, INFINITE),
            )
        )

    @staticmethod
    def decode(text: str) -> QoS:
        """Parse a QoS string (empty parts take rmw_zenoh's defaults)."""
        parts = text.split(":") if isinstance(text, str) else []
        if len(parts) != 6:
            raise InvalidMessage(f"qos: {str(text)[:80]!r} does not have 6 ':'-separated parts")
        sizes = (1, 1, 2, 2, 2, 3)
        cells = [p.split(",") for p in parts]
        if any(len(c) != n for c, n in zip(cells, sizes, strict=True)):
            raise InvalidMessage(f"qos: {text[:80]!r} has a part with the wrong number of ','")
        flat = [v for c in cells for v in c]
        d = QoS()
        defaults = (
            d.reliability, d.durability, d.history, d.depth, *d.deadline, *d.lifespan,
            d.liveliness, *d.liveliness_lease,
        )  # fmt: skip
        vals = []
        for v, dv in zip(flat, defaults, strict=True):
            if v == "":
                vals.append(dv)
            elif v.isdigit() and len(v) <= 20:
                vals.append(int(v))
            else:
                raise InvalidMessage(f"qos: {v[:40]!r} in {text[:80]!r} is not a number")
        return QoS(
            vals[0], vals[1], vals[2], vals[3], (vals[4], vals[5]), (vals[6], vals[7]),
            vals[8], (vals[9], vals[10]),
        )  # fmt: skip


#: ``rclcpp::SensorDataQoS`` (a laser driver's scans; AMCL's scan subscription).
SENSOR_DATA_QOS: Final[QoS] = QoS(reliability=BEST_EFFORT, depth=5)
#: tf2's TransformBroadcaster and TransformListener on ``tf`` (keep last 100).
TF_QOS: Final[QoS] = QoS(depth=100)
#: tf2's static broadcaster and listener on ``tf_static``; also AMCL's ``map`` subscription
#: and ``amcl_pose`` publisher (reliable, transient local, keep last 1).
LATCHED_QOS: Final[QoS] = QoS(durability=TRANSIENT_LOCAL, depth=1)
#: ``rclcpp::SystemDefaultsQoS`` as rmw_zenoh resolves it (AMCL's ``initialpose``).
SYSTEM_DEFAULT_QOS: Final[QoS] = QoS()
#: A plain ``rclcpp::QoS(10)`` (the odometry fallback's subscription).
DEFAULT_10_QOS: Final[QoS] = QoS(depth=10)


# --------------------------------------------------------------------------- tokens
@dataclass(frozen=True)
class NodeInfo:
    """A ROS node as the graph sees it. ``zid``: the Zenoh session id (``str(session.zid())``);
    ``node_id``: its id in the session's entity counter; ``enclave`` ``/`` by default."""

    domain_id: int
    zid: str
    node_id: int
    namespace: str
    name: str
    enclave: str = "/"

    def __post_init__(self) -> None:
        check_domain(self.domain_id)
        if not re.fullmatch(r"[0-9a-f]{1,32}", self.zid):
            raise InvalidMessage(f"zid: {self.zid[:40]!r} is not a Zenoh id")
        if isinstance(self.node_id, bool) or not isinstance(self.node_id, int) or self.node_id < 0:
            raise InvalidMessage(f"node id: {self.node_id!r} is not a non-negative integer")
        check_name(self.namespace, "namespace")
        if _TOKEN_RE.fullmatch(self.name) is None:
            raise InvalidMessage(f"node name: {self.name[:80]!r} is not a ROS name token")
        check_name(self.enclave, "enclave")


def _node_part(node: NodeInfo, entity_id: int, kind: str) -> str:
    return (
        f"{ADMIN_SPACE}/{node.domain_id}/{node.zid}/{node.node_id}/{entity_id}/{kind}/"
        f"{mangle(node.enclave)}/{mangle(node.namespace)}/{mangle(node.name)}"
    )


def node_token(node: NodeInfo) -> str:
    """Liveliness token of a node (kind ``NN``; entity id = node id)."""
    return _node_part(node, node.node_id, NODE)


def endpoint_token(
    node: NodeInfo, entity_id: int, kind: EndpointKind, topic: str, rtype: RosType, qos: QoS
) -> str:
    """Liveliness token of a publisher (``MP``) or subscription (``MS``) of ``node``."""
    if kind not in (PUBLISHER, SUBSCRIPTION):
        raise InvalidMessage(f"kind: {kind!r} is not MP or MS")
    if isinstance(entity_id, bool) or not isinstance(entity_id, int) or entity_id < 0:
        raise InvalidMessage(f"entity id: {entity_id!r} is not a non-negative integer")
    name = check_name(topic, "topic")
    return (
        f"{_node_part(node, entity_id, kind)}/{mangle(name)}/{mangle(rtype.dds)}/"
        f"{mangle(rtype.hash)}/{qos.encode()}"
    )


@dataclass(frozen=True)
class Token:
    """A parsed liveliness token; ``topic``, ``type_name``, ``type_hash``, ``qos`` only for
    endpoints (``type_name`` the ROS name ``pkg/msg/Name``)."""

    domain_id: int
    zid: str
    node_id: int
    entity_id: int
    kind: str
    enclave: str
    namespace: str
    node_name: str
    topic: str | None = None
    type_name: str | None = None
    type_hash: str | None = None
    qos: QoS | None = None


def parse_token(key: str) -> Token:
    """Parse an rmw_zenoh liveliness token (raises on anything else)."""
    parts = key.split("/") if isinstance(key, str) else []
    if len(parts) not in (9, 13) or parts[0] != ADMIN_SPACE or any(not p for p in parts):
        raise InvalidMessage(f"token: {str(key)[:200]!r} is not an rmw_zenoh liveliness token")
    if parts[5] not in _KINDS or (parts[5] == NODE) != (len(parts) == 9):
        raise InvalidMessage(f"token: {key[:200]!r} has a wrong entity kind for its length")
    if not all(p.isdigit() for p in (parts[1], parts[3], parts[4])):
        raise InvalidMessage(f"token: {key[:200]!r} has a non-numeric domain or id")
    tok = Token(
        int(parts[1]), parts[2], int(parts[3]), int(parts[4]), parts[5],
        check_name(demangle(parts[6]), "enclave"), check_name(demangle(parts[7]), "namespace"),
        demangle(parts[8]),
    )  # fmt: skip
    if len(parts) == 9:
        return tok
    type_hash = demangle(parts[11])
    if not is_type_hash(type_hash):
        raise InvalidMessage(f"token: {type_hash[:80]!r} is not a RIHS01 hash")
    values = {f.name: getattr(tok, f.name) for f in fields(tok)}
    values.update(
        topic=check_name(demangle(parts[9]), "topic"),
        type_name=ros_type_name(demangle(parts[10])),
        type_hash=type_hash,
        qos=QoS.decode(parts[12]),
    )
    return Token(**values)


def gid_of(token: str) -> bytes:
    """The 16-byte GID rmw_zenoh derives from an entity's liveliness token."""
    import xxhash

    h = xxhash.xxh3_128_intdigest(token.encode("utf-8"))
    return (h & (2**64 - 1)).to_bytes(8, "little") + (h >> 64).to_bytes(8, "little")


__all__ = [
    "ADMIN_SPACE",
    "DEFAULT_10_QOS",
    "LATCHED_QOS",
    "NODE",
    "PUBLISHER",
    "SENSOR_DATA_QOS",
    "SUBSCRIPTION",
    "SYSTEM_DEFAULT_QOS",
    "TF_QOS",
    "NodeInfo",
    "QoS",
    "Token",
    "check_domain",
    "check_name",
    "dds_type_name",
    "demangle",
    "endpoint_token",
    "gid_of",
    "join_name",
    "mangle",
    "namespace_of_robot_id",
    "node_token",
    "parse_token",
    "robot_id_of_namespace",
    "split_name",
    "topic_key",
    "topic_of_key",
    "topic_selector",
]
