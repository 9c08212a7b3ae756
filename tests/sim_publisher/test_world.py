"""World files: GeoJSON/WKT loading, named rejections, map export, clearance, free space."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from service.adapters.maps.world import World, load_world
from service.errors import InvalidWorld


def _feature(coords, fid: str | None = "box", gtype: str = "Polygon") -> dict:
    props = {"id": fid} if fid is not None else {}
    return {
        "type": "Feature",
        "properties": props,
        "geometry": {"type": gtype, "coordinates": coords},
    }


def _fc(*features: dict) -> dict:
    return {"type": "FeatureCollection", "features": list(features)}


SQUARE = [[[0, 0], [4, 0], [4, 4], [0, 4], [0, 0]]]
HOLED = [
    [[0, 0], [10, 0], [10, 10], [0, 10], [0, 0]],
    [[1, 1], [1, 9], [9, 9], [9, 1], [1, 1]],
]


def test_geojson_and_wkt_load_the_same_world(tmp_path: Path) -> None:
    gj = tmp_path / "w.geojson"
    gj.write_text(json.dumps(_fc(_feature(HOLED, "room"), _feature(SQUARE, "box"))))
    wkt = tmp_path / "w.wkt"
    wkt.write_text(
        "# a room and a box\n"
        "POLYGON ((0 0, 10 0, 10 10, 0 10, 0 0), (1 1, 1 9, 9 9, 9 1, 1 1))\n\n"
        "POLYGON ((0 0, 4 0, 4 4, 0 4, 0 0))\n"
    )
    a, b = load_world(gj), load_world(wkt)
    assert [o.name for o in a.obstacles] == ["room", "box"]
    assert a.segments().shape == b.segments().shape == (12, 4)
    np.testing.assert_allclose(np.sort(a.segments(), axis=0), np.sort(b.segments(), axis=0))


def test_wkt_geometrycollection(tmp_path: Path) -> None:
    p = tmp_path / "w.wkt"
    p.write_text(
        "GEOMETRYCOLLECTION (POLYGON ((0 0, 1 0, 1 1, 0 0)), "
        "MULTIPOLYGON (((2 2, 3 2, 3 3, 2 2)), ((5 5, 6 5, 6 6, 5 5))))"
    )
    w = load_world(p)
    assert len(w.obstacles) == 3
    assert w.segments().shape == (9, 4)


def test_map_export_has_every_ring_closed() -> None:
    w = World.from_geojson(_fc(_feature(HOLED, "room"), _feature(SQUARE, "box")))
    md = w.to_map_data("m")
    assert md.kind == "metric" and md.map_id == "m"
    assert len(md.polylines) == 3  # exterior + interior of the room, the box
    for p in md.polylines:
        np.testing.assert_array_equal(p[0], p[-1])
    assert sorted(len(p) for p in md.polylines) == [5, 5, 5]
    assert md.segments().shape == (12, 4)


def test_clearance_free_space_and_is_free() -> None:
    w = World.from_geojson(
        _fc(_feature(HOLED, "room"), _feature([[[4, 4], [6, 4], [6, 6], [4, 6], [4, 4]]]))
    )
    c = w.clearance(np.array([[2.0, 5.0], [5.0, 5.0], [8.0, 8.0]]))
    np.testing.assert_allclose(c, [1.0, 0.0, 1.0])
    assert w.free_space.area == pytest.approx(64.0 - 4.0)
    np.testing.assert_array_equal(w.is_free(np.array([[2.0, 5.0], [5.0, 5.0]]), 0.5), [True, False])


@pytest.mark.parametrize(
    ("doc", "match"),
    [
        ([1, 2], "top level must be an object"),
        ({"type": "Feature"}, "FeatureCollection"),
        ({"type": "FeatureCollection", "features": {}}, "'features' must be a list"),
        (_fc(_feature([1.0, 2.0], "p", "Point")), r"feature 0 \('p'\): geometry type 'Point'"),
        (
            _fc(
                _feature(SQUARE, "ok"), _feature([[[0, 0], [2, 2], [2, 0], [0, 2], [0, 0]]], "bow")
            ),
            r"feature 1 \('bow'\): invalid polygon \(Self-intersection",
        ),
        (_fc(_feature([[[0, 0], [1, float("nan")], [1, 1], [0, 0]]], "n")), r"'n'\): non-finite"),
        (_fc(_feature([[[0, 0], [1, "a"], [1, 1], [0, 0]]], "s")), "is not a number"),
        (_fc(_feature([], "e")), r"'e'\): empty coordinate list"),
        (
            _fc(_feature([[[0, 0], [1, 0], [0, 0]]], "short")),
            r"'short'\): invalid polygon \(Too few points",
        ),
        (_fc(_feature([[[0, 0], [1, 0], [2, 0], [0, 0]]], "flat")), r"'flat'\): invalid polygon"),
        (_fc({"type": "Feature", "properties": {"name": "nogeom"}}), "'nogeom'.*missing geometry"),
        (_fc(_feature(SQUARE, None)), None),
        (_fc(), "no features"),
    ],
)
def test_geojson_rejections_name_feature_and_problem(doc, match) -> None:
    if match is None:  # an unnamed valid feature is fine and gets a generated name
        assert World.from_geojson(doc).obstacles[0].name == "feature-0"
        return
    with pytest.raises(InvalidWorld, match=match):
        World.from_geojson(doc)


def test_file_level_rejections(tmp_path: Path) -> None:
    with pytest.raises(InvalidWorld, match="unreadable file"):
        load_world(tmp_path / "missing.geojson")
    bad = tmp_path / "bad.geojson"
    bad.write_text('{"type": "FeatureCollection", "features": [')
    with pytest.raises(InvalidWorld, match="bad JSON"):
        load_world(bad)
    nan = tmp_path / "nan.geojson"
    nan.write_text(json.dumps(_fc(_feature([[[0, 0], [1, float("inf")], [1, 1], [0, 0]]], "inf"))))
    with pytest.raises(InvalidWorld, match=r"nan.geojson: feature 0 \('inf'\): non-finite"):
        load_world(nan)
    wkt = tmp_path / "w.wkt"
    wkt.write_text("POLYGON ((0 0, 1 0, 1 1, 0 0))\nPOLYGON ((0 0, 1 0\n")
    with pytest.raises(InvalidWorld, match="line 2: unreadable"):
        load_world(wkt)
    wkt.write_text("LINESTRING (0 0, 1 1)\n")
    with pytest.raises(InvalidWorld, match="line 1: geometry type LineString"):
        load_world(wkt)
    wkt.write_text("POLYGON ((0 0, 2 2, 2 0, 0 2, 0 0))\n")
    with pytest.raises(InvalidWorld, match="line 1: invalid polygon"):
        load_world(wkt)
    wkt.write_text("# nothing\n\n")
    with pytest.raises(InvalidWorld, match="no geometry"):
        load_world(wkt)
    binary = tmp_path / "b.wkt"
    binary.write_bytes(b"\xff\xfe\x00garbage")
    with pytest.raises(InvalidWorld, match="unreadable"):
        load_world(binary)


def test_bundled_wkt_example_world() -> None:
    path = Path(__file__).resolve().parents[2] / "sim_publisher" / "worlds" / "two_rooms.wkt"
    w = load_world(path)
    assert len(w.obstacles) == 3
    # two 3.9 m square rooms + the door opening, minus a 1.4 x 0.7 desk and a 0.4 m pillar
    assert w.free_space.area == pytest.approx(2 * 3.9**2 + 0.09 - 0.98 - 0.16)
    assert len(w.to_map_data("two-rooms").polylines) == 4
    assert w.is_free(np.array([[4.05, 1.95]]), 0.3)[0]  # door centre
