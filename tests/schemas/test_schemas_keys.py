"""Key expression builders and parsers (schemas.keys)."""

from __future__ import annotations

import pytest

from schemas.keys import (
    DEFAULT_PREFIX,
    ROBOT_LEAVES,
    alive_key,
    alive_wildcard,
    errors_key,
    health_key,
    map_key,
    maps_wildcard,
    parse_alive_key,
    parse_map_key,
    parse_robot_key,
    robot_key,
    robots_wildcard,
    validate_id,
    validate_prefix,
)
from service.errors import InvalidMessage


def test_builders_follow_the_wire_layout() -> None:
    p = DEFAULT_PREFIX
    assert p == "shapeloc"
    assert map_key(p, "office") == "shapeloc/maps/office"
    assert maps_wildcard(p) == "shapeloc/maps/*"
    assert robot_key(p, "r-1", "scan") == "shapeloc/robots/r-1/scan"
    assert robots_wildcard(p, "config") == "shapeloc/robots/*/config"
    assert health_key(p) == "shapeloc/service/health"
    assert errors_key(p) == "shapeloc/errors"
    assert alive_key(p, "i.7") == "shapeloc/service/alive/i.7"
    assert alive_wildcard(p) == "shapeloc/service/alive/*"
    assert ROBOT_LEAVES == ("config", "scan", "pose", "truth")


def test_multi_chunk_prefix() -> None:
    p = validate_prefix("site_a/floor.2")
    assert robot_key(p, "r", "pose") == "site_a/floor.2/robots/r/pose"
    assert parse_robot_key(p, "site_a/floor.2/robots/r/pose") == ("r", "pose")


@pytest.mark.parametrize("leaf", ["config", "scan", "pose", "truth"])
def test_robot_key_round_trip(leaf: str) -> None:
    key = robot_key("shapeloc", "Robot_7", leaf)
    assert parse_robot_key("shapeloc", key) == ("Robot_7", leaf)


def test_map_and_alive_keys_round_trip() -> None:
    assert parse_map_key("shapeloc", map_key("shapeloc", "office-schematic")) == "office-schematic"
    assert parse_alive_key("x", alive_key("x", "svc-12")) == "svc-12"


@pytest.mark.parametrize(
    "prefix", ["", "/shapeloc", "shapeloc/", "a//b", "a/*", "a/**", "sh ape", "caf\u00e9", "a$b", 3]
)
def test_bad_prefixes(prefix: object) -> None:
    with pytest.raises(InvalidMessage, match="prefix: "):
        validate_prefix(prefix)
    with pytest.raises(InvalidMessage, match="prefix: "):
        map_key(prefix, "m")  # type: ignore[arg-type]


@pytest.mark.parametrize("bad", ["", "a" * 65, "a/b", "*", "**", "a b", "\u00e9", "a?b", "a#b"])
def test_builders_reject_bad_ids(bad: str) -> None:
    with pytest.raises(InvalidMessage, match=r"robot_id: .* is not 1-64 characters"):
        robot_key("shapeloc", bad, "scan")
    with pytest.raises(InvalidMessage, match="map_id: "):
        map_key("shapeloc", bad)
    with pytest.raises(InvalidMessage, match="instance_id: "):
        alive_key("shapeloc", bad)
    with pytest.raises(InvalidMessage):
        validate_id(bad, "x")


def test_validate_id_accepts_the_full_alphabet_and_64_chars() -> None:
    assert validate_id("aZ09_.-", "robot_id") == "aZ09_.-"
    assert validate_id("x" * 64, "robot_id") == "x" * 64
    with pytest.raises(InvalidMessage, match="robot_id: must be a string, got int"):
        validate_id(5, "robot_id")


@pytest.mark.parametrize(
    ("key", "reason"),
    [
        ("shapeloc/robots/r1/odom", "leaf: 'odom' is not one of config, scan, pose, truth"),
        ("shapeloc/robots/r1", "is not shapeloc/robots/<robot_id>/<leaf>"),
        ("shapeloc/robots/r1/scan/x", "is not shapeloc/robots/<robot_id>/<leaf>"),
        ("shapeloc/robots//scan", "robot_id: '' is not 1-64 characters"),
        ("shapeloc/robots/*/scan", "robot_id: '*' is not"),
        ("other/robots/r1/scan", "key: 'other/robots/r1/scan' is not below 'shapeloc/robots/'"),
        ("shapeloc/maps/m", "is not below 'shapeloc/robots/'"),
    ],
)
def test_parse_robot_key_rejections(key: str, reason: str) -> None:
    with pytest.raises(InvalidMessage) as exc:
        parse_robot_key("shapeloc", key)
    assert reason in str(exc.value), str(exc.value)


@pytest.mark.parametrize(
    ("key", "reason"),
    [
        ("shapeloc/maps/a/b", "is not shapeloc/maps/<map_id>"),
        ("shapeloc/maps/", "map_id: '' is not"),
        ("shapeloc/maps/" + "m" * 65, "map_id: "),
        ("shapeloc/robots/r/scan", "is not below 'shapeloc/maps/'"),
        ("shapeloc2/maps/m", "is not below 'shapeloc/maps/'"),
    ],
)
def test_parse_map_key_rejections(key: str, reason: str) -> None:
    with pytest.raises(InvalidMessage) as exc:
        parse_map_key("shapeloc", key)
    assert reason in str(exc.value), str(exc.value)


def test_parsers_reject_non_strings_and_bad_leaf_in_builders() -> None:
    with pytest.raises(InvalidMessage, match="key: must be a string"):
        parse_map_key("shapeloc", None)  # type: ignore[arg-type]
    with pytest.raises(InvalidMessage, match="leaf: 'health'"):
        robot_key("shapeloc", "r", "health")
    with pytest.raises(InvalidMessage, match="leaf: "):
        robots_wildcard("shapeloc", "*")
