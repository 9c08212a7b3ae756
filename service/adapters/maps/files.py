"""Map files: the one place that reads and writes every map format shapeloc accepts.

:func:`load_map_file` returns a core :class:`~service.core.types.MapData` (map frame, metres)
whatever the format; :func:`save_map_file` writes the wire JSON. Used by the client library
and the ``shapeloc`` CLI (``shapeloc map put``), the simulator (``--map FILE``) and the office
maps alike. No zenoh here.

Formats, chosen by the file's suffix (:data:`READERS`; any other suffix is sniffed as
``.json`` is):

* ``.json`` / ``.geojson`` / ``.msgpack`` / anything else — JSON, or msgpack if it is not
  JSON, holding either
  - a **wire map** ``{"map_id", "kind", "polylines"[, "name"]}`` (``docs/wire.md``), decoded
    and validated by :class:`schemas.messages.Map`; or
  - **GeoJSON** (a ``FeatureCollection`` or one ``Feature``). Polygons only (and ``kind`` not
    ``schematic``): a metric **world** of obstacle polygons, validated by
    :meth:`service.adapters.maps.world.World.from_geojson`; every ring becomes a closed polyline.
    With any ``LineString`` / ``MultiLineString`` (or ``kind="schematic"``): **outlines**, e.g. a
    schematic floor plan; each line, and each polygon ring, becomes one polyline, kind
    ``schematic`` unless ``kind`` (or a top-level ``"kind"`` member, as
    :func:`save_map_geojson` writes) says otherwise. Z coordinates are dropped.
* ``.wkt`` — a metric world in WKT (:meth:`service.adapters.maps.world.World.from_wkt`).
* ``.yaml`` / ``.yml`` — a ROS ``map_server`` occupancy grid (YAML + PGM/PNG image;
  :func:`service.adapters.maps.grid.read_map_yaml`), turned into polylines along the faces of its
  occupied cells (:func:`service.adapters.maps.grid.grid_to_map`, default settings); kind ``metric``
  unless ``kind`` says otherwise.

Adding a format: write a reader ``(path, map_id, kind) -> MapData`` (``map_id`` / ``kind``
``None`` when not given; use :func:`default_map_id` and raise :class:`InvalidMessage` /
:class:`InvalidWorld` naming the file) and register its suffixes in :data:`READERS`, as
:func:`read_ros_map` is for ``.yaml``.
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any, cast, get_args

import msgpack
import numpy as np

from schemas.codec import encode
from schemas.keys import id_error
from schemas.messages import Map
from service.adapters.convert import map_data_of, map_message_of
from service.adapters.maps.grid import grid_to_map, read_map_yaml
from service.adapters.maps.world import World
from service.core.types import MapData, MapKind
from service.errors import InvalidMessage, InvalidWorld

#: Largest map file read, bytes (a wire map is at most 16 MiB on the wire; GeoJSON is wordier).
MAX_MAP_FILE_BYTES = 64 * 1024 * 1024

#: A map file reader: ``(path, map_id or None, kind or None) -> MapData``.
MapReader = Callable[[Path, str | None, MapKind | None], MapData]

_KINDS: tuple[str, ...] = get_args(MapKind)
_LINE_TYPES = frozenset({"LineString", "MultiLineString"})


def load_map_file(path: str | Path, map_id: str | None = None, kind: str | None = None) -> MapData:
    """Read a map file of any supported format (see the module docstring) as a core map.

    ``map_id`` overrides the id (default: the wire map's own ``map_id``, else the file's
    stem); ``kind`` (``metric`` / ``schematic``) overrides the kind (default: the wire map's
    own, ``metric`` for worlds, ``schematic`` for GeoJSON outlines). Raises
    :class:`InvalidMessage` for unreadable files, bad wire maps and bad arguments,
    :class:`InvalidWorld` for bad GeoJSON / WKT geometry; the text names the file.
    """
    p = Path(path)
    if kind is not None and kind not in _KINDS:
        raise InvalidMessage(f"{p}: kind must be one of {', '.join(_KINDS)}, not {kind!r}")
    if map_id is not None:
        _check_id(p, map_id)
    reader = READERS.get(p.suffix.lower(), read_serialized)
    return reader(p, map_id, cast("MapKind | None", kind))


def save_map_file(map_data: MapData, path: str | Path, name: str | None = None) -> Path:
    """Write ``map_data`` as a wire map in JSON (``{"map_id", "kind", "polylines"[,
    "name"]}``, what :func:`load_map_file` reads back to an equal map); returns the path.

    The path must end in ``.json``. The file is replaced atomically (written beside it, then
    renamed). Raises :class:`InvalidMessage` if the map is not a valid wire map (id, limits)
    and ``OSError`` if the file cannot be written.
    """
    p = Path(path)
    if p.suffix.lower() != ".json":
        raise InvalidMessage(f"{p}: a map is saved as wire JSON; use a .json path")
    data = encode(map_message_of(map_data, name=name), json=True)
    tmp = p.with_name(f".{p.name}.{os.getpid()}.tmp")
    try:
        tmp.write_bytes(data)
        os.replace(tmp, p)
    finally:
        tmp.unlink(missing_ok=True)
    return p


def save_map_geojson(map_data: MapData, path: str | Path, decimals: int = 4) -> Path:
    """Write ``map_data`` as a GeoJSON ``FeatureCollection`` of ``LineString`` features (one per
    polyline, map frame, metres rounded to ``decimals`` places) with the map's ``kind`` and
    ``map_id`` as foreign members, which :func:`load_map_file` honours (so a metric map reads
    back as metric, not as the default schematic outlines). Replaced atomically; returns the
    path. Raises :class:`InvalidMessage` unless the path ends in ``.geojson``.
    """
    p = Path(path)
    if p.suffix.lower() != ".geojson":
        raise InvalidMessage(f"{p}: GeoJSON maps are written to a .geojson path")
    feats = [
        {
            "type": "Feature",
            "properties": {"index": i},
            "geometry": {"type": "LineString", "coordinates": np.round(q, decimals).tolist()},
        }
        for i, q in enumerate(map_data.polylines)
    ]
    doc = {
        "type": "FeatureCollection",
        "map_id": map_data.map_id,
        "kind": map_data.kind,
        "features": feats,
    }
    tmp = p.with_name(f".{p.name}.{os.getpid()}.tmp")
    try:
        tmp.write_text(json.dumps(doc, separators=(",", ":")), encoding="utf-8")
        os.replace(tmp, p)
    finally:
        tmp.unlink(missing_ok=True)
    return p


def default_map_id(path: Path) -> str:
    """The id a map file gets when neither the caller nor the file names one: its stem."""
    return path.stem


# --------------------------------------------------------------------- readers
def read_serialized(path: Path, map_id: str | None, kind: MapKind | None) -> MapData:
    """JSON (or msgpack) holding a wire map or GeoJSON (see the module docstring)."""
    raw = _read_bytes(path)
    data: Any
    try:
        data = json.loads(raw)
    except (UnicodeDecodeError, json.JSONDecodeError):
        try:
            data = msgpack.unpackb(raw, raw=False)
        except Exception as exc:
            raise InvalidMessage(f"{path}: neither JSON nor msgpack") from exc
    if not isinstance(data, dict):
        raise InvalidMessage(f"{path}: expected a JSON object, got {type(data).__name__}")
    if data.get("type") in ("FeatureCollection", "Feature"):
        return _from_geojson(path, data, map_id, kind)
    return _from_wire(path, data, map_id, kind)


def read_wkt(path: Path, map_id: str | None, kind: MapKind | None) -> MapData:
    """A WKT world (obstacle polygons); every ring becomes a closed polyline."""
    mid = _check_id(path, map_id or default_map_id(path))
    try:
        text = _read_bytes(path).decode("utf-8")
    except UnicodeDecodeError as exc:
        raise InvalidWorld(f"{path}: WKT is not UTF-8 text (byte {exc.start})") from None
    try:
        world = World.from_wkt(text)
    except InvalidWorld as exc:
        raise InvalidWorld(f"{path}: {exc}") from None
    md = world.to_map_data(mid)
    return md if kind in (None, md.kind) else MapData(mid, cast("MapKind", kind), md.polylines)


def read_ros_map(path: Path, map_id: str | None, kind: MapKind | None) -> MapData:
    """A ROS ``map_server`` map (YAML naming a PGM/PNG image): polylines along the faces of
    its occupied cells (:func:`~service.adapters.maps.grid.grid_to_map`), map frame, metres."""
    mid = _check_id(path, map_id or default_map_id(path))
    grid = read_map_yaml(path)
    try:
        return grid_to_map(grid, mid, kind=kind or "metric")
    except InvalidMessage as exc:
        raise InvalidMessage(f"{path}: {exc}") from None


#: Reader per lower-case file suffix; unknown suffixes go to :func:`read_serialized`.
READERS: dict[str, MapReader] = {
    ".json": read_serialized,
    ".geojson": read_serialized,
    ".msgpack": read_serialized,
    ".wkt": read_wkt,
    ".yaml": read_ros_map,
    ".yml": read_ros_map,
}


# --------------------------------------------------------------------- helpers
def _read_bytes(path: Path) -> bytes:
    try:
        size = path.stat().st_size
        if size > MAX_MAP_FILE_BYTES:
            raise InvalidMessage(
                f"{path}: map file too large ({size} bytes > {MAX_MAP_FILE_BYTES})"
            )
        return path.read_bytes()
    except OSError as exc:
        raise InvalidMessage(f"cannot read map file {path}: {exc.strerror or exc}") from exc


def _check_id(path: Path, map_id: str) -> str:
    reason = id_error(map_id)
    if reason is not None:
        raise InvalidMessage(f"{path}: map_id: {reason} (give one with map_id / --id)")
    return map_id


def _from_wire(path: Path, data: dict, map_id: str | None, kind: MapKind | None) -> MapData:
    wire = dict(data)
    wire["map_id"] = map_id or data.get("map_id") or default_map_id(path)
    if kind is not None:
        wire["kind"] = kind
    try:
        msg = Map.parse(wire)
    except InvalidMessage as exc:
        raise InvalidMessage(f"{path}: {exc}") from None
    return map_data_of(msg)


def _from_geojson(path: Path, doc: dict, map_id: str | None, kind: MapKind | None) -> MapData:
    mid = _check_id(path, map_id or default_map_id(path))
    feats = doc.get("features") if doc.get("type") == "FeatureCollection" else [doc]
    if not isinstance(feats, list):
        raise InvalidWorld(f"{path}: 'features' must be a list")
    geoms = [f.get("geometry") if isinstance(f, dict) else None for f in feats]
    has_lines = any(isinstance(g, dict) and g.get("type") in _LINE_TYPES for g in geoms)
    if kind is None and doc.get("kind") in _KINDS:  # written by save_map_geojson
        kind = cast("MapKind", doc["kind"])
    if kind == "schematic" or has_lines:
        polylines = geojson_polylines(feats, str(path))
        return MapData.from_lists(mid, kind or "schematic", polylines)
    collection = doc if doc.get("type") == "FeatureCollection" else _collection_of(doc)
    try:
        world = World.from_geojson(collection)
    except InvalidWorld as exc:
        raise InvalidWorld(f"{path}: {exc}") from None
    return world.to_map_data(mid)


def _collection_of(feature: dict) -> dict:
    return {"type": "FeatureCollection", "features": [feature]}


def geojson_polylines(features: list, source: str = "GeoJSON") -> list[np.ndarray]:
    """Every line of GeoJSON ``features`` as a ``(k, 2)`` float64 array (metres): each
    ``LineString``, each part of a ``MultiLineString`` and each ring of a ``Polygon`` /
    ``MultiPolygon`` (rings repeat their first point). Z coordinates are dropped.

    Raises :class:`InvalidWorld` naming ``source`` and the feature: missing or unsupported
    geometry, fewer than 2 points, non-numeric or non-finite coordinates, no lines at all.
    """
    out: list[np.ndarray] = []
    for i, feat in enumerate(features):
        geom = feat.get("geometry") if isinstance(feat, dict) else None
        if not isinstance(geom, dict):
            raise InvalidWorld(f"{source}: feature {i} has no geometry")
        gtype, coords = geom.get("type"), geom.get("coordinates")
        if not isinstance(coords, list):
            raise InvalidWorld(f"{source}: feature {i}: 'coordinates' must be a list")
        if gtype == "LineString":
            parts = [coords]
        elif gtype in ("MultiLineString", "Polygon"):
            parts = coords
        elif gtype == "MultiPolygon":
            parts = [ring for poly in coords if isinstance(poly, list) for ring in poly]
        else:
            raise InvalidWorld(f"{source}: feature {i}: unsupported geometry {gtype!r}")
        for part in parts:
            try:
                a = np.asarray(part, dtype=np.float64)
            except (TypeError, ValueError) as exc:
                raise InvalidWorld(f"{source}: feature {i}: coordinates are not numbers") from exc
            if a.ndim != 2 or a.shape[0] < 2 or a.shape[1] < 2:
                raise InvalidWorld(f"{source}: feature {i}: need >= 2 points of [x, y]")
            a = np.ascontiguousarray(a[:, :2])
            if not np.all(np.isfinite(a)):
                raise InvalidWorld(f"{source}: feature {i}: non-finite coordinate")
            out.append(a)
    if not out:
        raise InvalidWorld(f"{source}: no LineString or Polygon features")
    return out
