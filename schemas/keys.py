"""Zenoh key expressions of the wire contract (``wire-v1``).

Layout below a configurable prefix (default ``shapeloc``)::

    <prefix>/maps/<map_id>
    <prefix>/robots/<robot_id>/{config,scan,pose,truth}
    <prefix>/service/health
    <prefix>/service/alive/<instance_id>
    <prefix>/service/state/<instance_id>/{config,pose}/<robot_id>   (project addition)
    <prefix>/errors

Identifiers are 1-64 characters of ``[A-Za-z0-9_.-]``; a prefix is one or more such chunks
joined by ``/``. Builders validate what they are given; parsers validate what they read. All
failures raise :class:`service.errors.InvalidMessage` with a reason naming the field.
"""

from __future__ import annotations

import re
from typing import Final, Literal, get_args

from schemas.limits import ID_CHARS, ID_MAX_LEN, ID_MIN_LEN
from service.errors import InvalidMessage

DEFAULT_PREFIX: Final[str] = "shapeloc"

RobotLeaf = Literal["config", "scan", "pose", "truth"]
StateKind = Literal["config", "pose"]
STATE_KINDS: Final[tuple[str, ...]] = get_args(StateKind)
ROBOT_LEAVES: Final[tuple[str, ...]] = get_args(RobotLeaf)

_ID_RE = re.compile(rf"[{ID_CHARS}]{{{ID_MIN_LEN},{ID_MAX_LEN}}}")


def id_error(value: object) -> str | None:
    """Why ``value`` is not a valid identifier, or ``None`` if it is one."""
    if not isinstance(value, str):
        return f"must be a string, got {type(value).__name__}"
    if _ID_RE.fullmatch(value) is None:
        return f"{value[:80]!r} is not 1-{ID_MAX_LEN} characters of [{ID_CHARS}]"
    return None


def validate_id(value: object, field: str = "id") -> str:
    """Return ``value`` if it is a valid identifier, else raise ``InvalidMessage``."""
    reason = id_error(value)
    if reason is not None:
        raise InvalidMessage(f"{field}: {reason}")
    return value  # type: ignore[return-value]


def validate_prefix(prefix: object) -> str:
    """Return ``prefix`` if it is one or more identifier chunks joined by ``/``."""
    if not isinstance(prefix, str) or not prefix:
        raise InvalidMessage("prefix: must be a non-empty string")
    for chunk in prefix.split("/"):
        if id_error(chunk) is not None:
            raise InvalidMessage(
                f"prefix: chunk {chunk[:80]!r} of {prefix[:200]!r} is not 1-{ID_MAX_LEN} "
                f"characters of [{ID_CHARS}]"
            )
    return prefix


def _leaf(leaf: object) -> str:
    if leaf not in ROBOT_LEAVES:
        raise InvalidMessage(f"leaf: {leaf!r} is not one of {', '.join(ROBOT_LEAVES)}")
    return leaf  # type: ignore[return-value]


def map_key(prefix: str, map_id: str) -> str:
    """``<prefix>/maps/<map_id>``."""
    return f"{validate_prefix(prefix)}/maps/{validate_id(map_id, 'map_id')}"


def maps_wildcard(prefix: str) -> str:
    """``<prefix>/maps/*``: every map (subscriber / queryable / ``get`` of all maps)."""
    return f"{validate_prefix(prefix)}/maps/*"


def robot_key(prefix: str, robot_id: str, leaf: str) -> str:
    """``<prefix>/robots/<robot_id>/<leaf>`` with leaf one of config, scan, pose, truth."""
    return f"{validate_prefix(prefix)}/robots/{validate_id(robot_id, 'robot_id')}/{_leaf(leaf)}"


def robots_wildcard(prefix: str, leaf: str) -> str:
    """``<prefix>/robots/*/<leaf>``: that leaf of every robot."""
    return f"{validate_prefix(prefix)}/robots/*/{_leaf(leaf)}"


def health_key(prefix: str) -> str:
    """``<prefix>/service/health`` (queryable)."""
    return f"{validate_prefix(prefix)}/service/health"


def errors_key(prefix: str) -> str:
    """``<prefix>/errors``: one ``ErrorNotice`` per rejected message."""
    return f"{validate_prefix(prefix)}/errors"


def alive_key(prefix: str, instance_id: str) -> str:
    """``<prefix>/service/alive/<instance_id>`` (liveliness token of one service instance)."""
    return f"{validate_prefix(prefix)}/service/alive/{validate_id(instance_id, 'instance_id')}"


def alive_wildcard(prefix: str) -> str:
    """``<prefix>/service/alive/*``: liveliness of every service instance."""
    return f"{validate_prefix(prefix)}/service/alive/*"


def state_key(prefix: str, instance_id: str, kind: str, robot_id: str) -> str:
    """``<prefix>/service/state/<instance_id>/<kind>/<robot_id>``: a robot's configuration or
    last pose as one instance knows it (kind ``config`` or ``pose``), answered to the instances
    of a cluster catching up (docs/cluster.md)."""
    if kind not in STATE_KINDS:
        raise InvalidMessage(f"kind: {kind!r} is not one of {', '.join(STATE_KINDS)}")
    return (
        f"{validate_prefix(prefix)}/service/state/{validate_id(instance_id, 'instance_id')}"
        f"/{kind}/{validate_id(robot_id, 'robot_id')}"
    )


def state_selector(prefix: str, instance_id: str = "*") -> str:
    """``<prefix>/service/state/<instance_id>/**`` (``*``: every instance's state)."""
    inst = instance_id if instance_id == "*" else validate_id(instance_id, "instance_id")
    return f"{validate_prefix(prefix)}/service/state/{inst}/**"


def parse_state_key(prefix: str, key: str) -> tuple[str, str, str]:
    """``(instance_id, kind, robot_id)`` of a ``<prefix>/service/state/...`` key."""
    rest = _rest(prefix, key, "service/state")
    if len(rest) != 3 or rest[1] not in STATE_KINDS:
        raise InvalidMessage(
            f"key: {key[:200]!r} is not {prefix}/service/state/<instance_id>/<kind>/<robot_id>"
        )
    return validate_id(rest[0], "instance_id"), rest[1], validate_id(rest[2], "robot_id")


def _rest(prefix: str, key: object, section: str) -> list[str]:
    """The chunks of ``key`` after ``<prefix>/<section>/``, or raise."""
    validate_prefix(prefix)
    if not isinstance(key, str):
        raise InvalidMessage(f"key: must be a string, got {type(key).__name__}")
    head = f"{prefix}/{section}/"
    if not key.startswith(head):
        raise InvalidMessage(f"key: {key[:200]!r} is not below {head!r}")
    return key[len(head) :].split("/")


def parse_map_key(prefix: str, key: str) -> str:
    """``map_id`` of a ``<prefix>/maps/<map_id>`` key."""
    rest = _rest(prefix, key, "maps")
    if len(rest) != 1:
        raise InvalidMessage(f"key: {key[:200]!r} is not {prefix}/maps/<map_id>")
    return validate_id(rest[0], "map_id")


def parse_robot_key(prefix: str, key: str) -> tuple[str, str]:
    """``(robot_id, leaf)`` of a ``<prefix>/robots/<robot_id>/<leaf>`` key."""
    rest = _rest(prefix, key, "robots")
    if len(rest) != 2:
        raise InvalidMessage(f"key: {key[:200]!r} is not {prefix}/robots/<robot_id>/<leaf>")
    return validate_id(rest[0], "robot_id"), _leaf(rest[1])


def parse_alive_key(prefix: str, key: str) -> str:
    """``instance_id`` of a ``<prefix>/service/alive/<instance_id>`` key."""
    rest = _rest(prefix, key, "service/alive")
    if len(rest) != 1:
        raise InvalidMessage(f"key: {key[:200]!r} is not {prefix}/service/alive/<instance_id>")
    return validate_id(rest[0], "instance_id")
