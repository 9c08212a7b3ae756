"""Map files (service.adapters.maps.files): every format load_map_file reads, save_map_file round
trips, precise errors naming the file, and the suffix dispatch another format plugs into."""

from __future__ import annotations

import json
from pathlib import Path

import msgpack
import numpy as np
import pytest

from service.adapters.maps import files
from service.adapters.maps.files import READERS, load_map_file, save_map_file, save_map_geojson
from service.core.types import MapData
from service.errors import InvalidMessage, InvalidWorld

REPO = Path(__file__).resolve().parents[4]
WORLDS = REPO / "sim_publisher" / "worlds"

SQUARE = [[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0], [0.0, 0.0]]


def _feature(gtype: str, coords: object) -> dict:
    return {"type": "Feature", "properties": {}, "geometry": {"type": gtype, "coordinates": coords}}


def _collection(*features: dict) -> dict:
    return {"type": "FeatureCollection", "features": list(features)}


def test_load_map_file_formats(tmp_path: Path) -> None:
    wire = tmp_path / "w.json"
    wire.write_text(
        json.dumps({"map_id": "a", "kind": "schematic", "polylines": [[[0, 0], [1, 0]]]})
    )
    assert load_map_file(wire).map_id == "a"
    assert load_map_file(wire, map_id="b", kind="metric").kind == "metric"
    gj = tmp_path / "rooms.geojson"
    gj.write_text(
        json.dumps(
            _collection(
                _feature("LineString", [[0, 0], [2, 0], [2, 2]]),
                _feature("Polygon", [[[5, 5], [6, 5], [6, 6], [5, 5]]]),
            )
        )
    )
    m = load_map_file(gj, kind="schematic")
    assert m.map_id == "rooms" and len(m.polylines) == 2
    bad = tmp_path / "bad.json"
    bad.write_text("[1, 2]")
    with pytest.raises(InvalidMessage, match="expected a JSON object"):
        load_map_file(bad)
    with pytest.raises(InvalidMessage, match="cannot read map file"):
        load_map_file(tmp_path / "missing.json")


def test_wire_map_in_msgpack_and_its_validation(tmp_path: Path) -> None:
    p = tmp_path / "hall.msgpack"
    p.write_bytes(msgpack.packb({"map_id": "hall", "kind": "metric", "polylines": [SQUARE]}))
    md = load_map_file(p)
    assert (md.map_id, md.kind) == ("hall", "metric")
    np.testing.assert_array_equal(md.polylines[0], np.array(SQUARE))
    assert not md.polylines[0].flags.writeable  # the core's read-only arrays
    # an unknown suffix is sniffed (JSON first, then msgpack); the id defaults to the stem
    q = tmp_path / "no_id.bin"
    q.write_bytes(msgpack.packb({"kind": "schematic", "polylines": [SQUARE]}))
    assert load_map_file(q).map_id == "no_id"
    # validated by the wire model: the message names the file and the field
    r = tmp_path / "r.json"
    r.write_text(json.dumps({"map_id": "r", "kind": "metric", "polylines": [[[0, 0]]]}))
    with pytest.raises(InvalidMessage, match=r"r\.json: polylines\[0\]"):
        load_map_file(r)
    r.write_text(json.dumps({"map_id": "r", "kind": "fuzzy", "polylines": [SQUARE]}))
    with pytest.raises(InvalidMessage, match="kind"):
        load_map_file(r)
    g = tmp_path / "garbage.dat"
    g.write_bytes(b"\xc1\xc1 neither")
    with pytest.raises(InvalidMessage, match="neither JSON nor msgpack"):
        load_map_file(g)


def test_geojson_world_is_every_polygon_ring_metric(tmp_path: Path) -> None:
    office = load_map_file(WORLDS / "office.geojson")
    assert (office.map_id, office.kind) == ("office", "metric")
    from service.adapters.maps.world import load_world

    rings = load_world(WORLDS / "office.geojson").rings()
    assert len(office.polylines) == len(rings)
    for a, b in zip(office.polylines, rings, strict=True):
        np.testing.assert_array_equal(a, b)
    # one polygon with a hole: exterior and interior ring, closed
    holed = [SQUARE, [[0.4, 0.4], [0.6, 0.4], [0.6, 0.6], [0.4, 0.4]]]
    p = tmp_path / "holed.json"
    p.write_text(json.dumps(_collection(_feature("Polygon", holed))))
    md = load_map_file(p)
    assert md.kind == "metric" and len(md.polylines) == 2
    assert all(np.array_equal(pl[0], pl[-1]) for pl in md.polylines)
    # a world polygon must be valid: a bow tie is rejected with the feature named
    bow = tmp_path / "bow.geojson"
    bow.write_text(
        json.dumps(_collection(_feature("Polygon", [[[0, 0], [1, 1], [1, 0], [0, 1], [0, 0]]])))
    )
    with pytest.raises(InvalidWorld, match=r"bow\.geojson: feature 0.*invalid polygon"):
        load_map_file(bow)


def test_geojson_outlines_are_schematic_by_default(tmp_path: Path) -> None:
    md = load_map_file(WORLDS / "office_schematic.geojson", map_id="office-schematic")
    assert (md.map_id, md.kind) == ("office-schematic", "schematic")
    doc = json.loads((WORLDS / "office_schematic.geojson").read_text())
    assert len(md.polylines) == len(doc["features"])
    np.testing.assert_array_equal(
        md.polylines[0], np.asarray(doc["features"][0]["geometry"]["coordinates"])
    )
    # MultiLineString parts are separate polylines; Z is dropped; one bare Feature is fine
    p = tmp_path / "z.geojson"
    p.write_text(
        json.dumps(_feature("MultiLineString", [[[0, 0, 5], [1, 0, 5]], [[2, 2], [3, 3]]]))
    )
    z = load_map_file(p, kind="metric")
    assert z.kind == "metric" and [pl.shape for pl in z.polylines] == [(2, 2), (2, 2)]
    np.testing.assert_array_equal(z.polylines[0], [[0.0, 0.0], [1.0, 0.0]])


@pytest.mark.parametrize(
    ("feature", "reason"),
    [
        (_feature("LineString", [[0, 0]]), "feature 0: need >= 2 points"),
        (_feature("LineString", [[0, 0], [1, "x"]]), "feature 0: coordinates are not numbers"),
        (_feature("LineString", [[0, 0], [1, 1e400]]), "feature 0: non-finite coordinate"),
        (_feature("Point", [0, 0]), "feature 0: unsupported geometry 'Point'"),
        ({"type": "Feature", "properties": {}}, "feature 0 has no geometry"),
    ],
)
def test_geojson_outline_errors_name_file_and_feature(
    tmp_path: Path, feature: dict, reason: str
) -> None:
    p = tmp_path / "lines.geojson"
    p.write_text(json.dumps(_collection(feature)))
    with pytest.raises(InvalidWorld, match=f"lines.geojson: {reason}"):
        load_map_file(p, kind="schematic")


def test_wkt_world(tmp_path: Path) -> None:
    md = load_map_file(WORLDS / "two_rooms.wkt")
    assert (md.map_id, md.kind) == ("two_rooms", "metric") and len(md.polylines) >= 2
    p = tmp_path / "box.wkt"
    p.write_text("POLYGON ((0 0, 2 0, 2 1, 0 1, 0 0))\n")
    box = load_map_file(p, map_id="box-1", kind="schematic")
    assert (box.map_id, box.kind) == ("box-1", "schematic")
    np.testing.assert_array_equal(box.polylines[0], [[0, 0], [2, 0], [2, 1], [0, 1], [0, 0]])
    p.write_text("LINESTRING (0 0, 1 1)\n")
    with pytest.raises(InvalidWorld, match=r"box\.wkt: WKT line 1.*not a Polygon"):
        load_map_file(p)


def test_bad_arguments_are_named(tmp_path: Path) -> None:
    p = tmp_path / "my map.json"
    p.write_text(json.dumps(_collection(_feature("LineString", [[0, 0], [1, 0]]))))
    with pytest.raises(InvalidMessage, match="map_id"):
        load_map_file(p)  # the stem has a space: not a valid id
    assert load_map_file(p, map_id="mine").map_id == "mine"
    with pytest.raises(InvalidMessage, match="kind must be one of metric, schematic"):
        load_map_file(p, map_id="mine", kind="exact")


def test_save_and_load_round_trip(tmp_path: Path) -> None:
    md = MapData.from_lists(
        "lab", "schematic", [SQUARE, [[0.1234567890123, -2.5], [3.0, 1e-9], [4.0, 4.0]]]
    )
    out = save_map_file(md, tmp_path / "lab.json", name="The lab")
    doc = json.loads(out.read_text())
    assert doc["map_id"] == "lab" and doc["kind"] == "schematic" and doc["name"] == "The lab"
    back = load_map_file(out)
    assert (back.map_id, back.kind) == (md.map_id, md.kind)
    for a, b in zip(back.polylines, md.polylines, strict=True):
        np.testing.assert_array_equal(a, b)  # exact: JSON floats round trip
    assert [f.name for f in tmp_path.iterdir()] == ["lab.json"]  # no temporary left behind
    with pytest.raises(InvalidMessage, match=r"use a \.json path"):
        save_map_file(md, tmp_path / "lab.yaml")
    with pytest.raises(InvalidMessage, match="map_id"):
        save_map_file(MapData.from_lists("bad id", "metric", [SQUARE]), tmp_path / "x.json")


def test_readers_dispatch_on_the_suffix(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    assert {".json", ".geojson", ".msgpack", ".wkt"} <= set(READERS)
    seen: list[tuple[str, str | None, str | None]] = []

    def read_plan(path: Path, map_id: str | None, kind: str | None) -> MapData:
        seen.append((path.name, map_id, kind))
        return MapData.from_lists(map_id or files.default_map_id(path), "metric", [SQUARE])

    monkeypatch.setitem(READERS, ".plan", read_plan)
    p = tmp_path / "floor.PLAN"
    p.write_text("anything")
    assert load_map_file(p).map_id == "floor"
    assert load_map_file(p, map_id="f2", kind="schematic").map_id == "f2"
    assert seen == [("floor.PLAN", None, None), ("floor.PLAN", "f2", "schematic")]


def test_ros_map_yaml_through_load_map_file(tmp_path: Path) -> None:
    # a 2 x 1 m grid at 0.1 m, negated (255 = occupied), origin (-1, 2): its top row occupied
    pix = np.zeros((10, 20), dtype=np.uint8)
    pix[0, :] = 255
    (tmp_path / "hall.pgm").write_bytes(b"P5\n20 10\n255\n" + pix.tobytes())
    (tmp_path / "hall.yaml").write_text(
        "image: hall.pgm\nresolution: 0.1\norigin: [-1.0, 2.0, 0.0]\nnegate: 1\n"
        "occupied_thresh: 0.65\nfree_thresh: 0.196\n"
    )
    m = load_map_file(tmp_path / "hall.yaml")
    assert (m.map_id, m.kind) == ("hall", "metric")
    verts = np.vstack(m.polylines)
    # the occupied row spans y = 2.9 .. 3.0 m and x = -1 .. 1 m (faces within half a cell)
    assert verts[:, 0].min() == pytest.approx(-1.0, abs=0.051)
    assert verts[:, 0].max() == pytest.approx(1.0, abs=0.051)
    assert verts[:, 1].min() == pytest.approx(2.9, abs=0.051)
    assert verts[:, 1].max() == pytest.approx(3.0, abs=0.051)
    assert load_map_file(tmp_path / "hall.yaml", map_id="h2", kind="schematic").kind == "schematic"
    (tmp_path / "empty.pgm").write_bytes(b"P5\n4 4\n255\n" + bytes([254] * 16))
    (tmp_path / "empty.yaml").write_text(
        "image: empty.pgm\nresolution: 0.1\norigin: [0, 0, 0]\nnegate: 0\n"
        "occupied_thresh: 0.65\nfree_thresh: 0.196\n"
    )
    with pytest.raises(InvalidMessage, match=r"empty\.yaml: .*no occupied cells"):
        load_map_file(tmp_path / "empty.yaml")


def test_save_map_geojson_keeps_the_kind(tmp_path: Path) -> None:
    md = MapData.from_lists("lab", "metric", [SQUARE, [[0.123456789, -2.5], [3.0, 1.0]]])
    out = save_map_geojson(md, tmp_path / "lab.geojson")
    back = load_map_file(out)
    assert (back.map_id, back.kind) == ("lab", "metric")  # not the outlines' default schematic
    assert np.allclose(back.polylines[1], [[0.1235, -2.5], [3.0, 1.0]], atol=1e-12)
    assert load_map_file(out, kind="schematic").kind == "schematic"
    with pytest.raises(InvalidMessage, match=r"\.geojson path"):
        save_map_geojson(md, tmp_path / "lab.json")
