"""Simulation worlds: solid obstacle polygons in the map frame (metres).

File formats (see docs/simulator.md):

* GeoJSON ``FeatureCollection`` whose features carry ``Polygon`` or ``MultiPolygon`` geometries
  (coordinates in metres, map frame). Optional properties ``id``/``name`` (used in error
  messages) and ``kind`` (e.g. ``wall``, ``furniture``; informational).
* WKT: one ``POLYGON``/``MULTIPOLYGON`` per line (blank lines and lines starting with ``#``
  ignored), or a single ``GEOMETRYCOLLECTION`` of them.

Everything read from a file is untrusted: problems raise :class:`InvalidWorld` naming the
feature (its index and ``id``/``name``) and the problem.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import shapely
from shapely.geometry import MultiPolygon, Polygon, box, shape
from shapely.validation import explain_validity

from service.core.types import MapData
from service.errors import InvalidWorld

_MAX_FILE_BYTES = 20_000_000


@dataclass(frozen=True)
class Obstacle:
    """One solid obstacle: a valid, non-empty polygon (metres, map frame) with a label."""

    geometry: Polygon
    name: str
    kind: str = "obstacle"


@dataclass
class World:
    """A set of solid obstacles. Free space is the obstacles' bounding box minus the obstacles.

    Build with :meth:`from_geojson`, :meth:`from_wkt` or :func:`load_world`; obstacles passed
    directly must already be valid polygons.
    """

    obstacles: list[Obstacle]
    _union: Any = field(default=None, init=False, repr=False)
    _free: Any = field(default=None, init=False, repr=False)

    def __post_init__(self) -> None:
        if not self.obstacles:
            raise InvalidWorld("world has no obstacles")

    # ----------------------------------------------------------------- construction
    @staticmethod
    def from_geojson(doc: Any) -> World:
        """Build from a parsed GeoJSON FeatureCollection (``dict``). Raises InvalidWorld."""
        if not isinstance(doc, dict):
            raise InvalidWorld(f"GeoJSON: top level must be an object, got {type(doc).__name__}")
        if doc.get("type") != "FeatureCollection":
            raise InvalidWorld(
                f"GeoJSON: type must be 'FeatureCollection', got {doc.get('type')!r}"
            )
        feats = doc.get("features")
        if not isinstance(feats, list):
            raise InvalidWorld("GeoJSON: 'features' must be a list")
        obstacles: list[Obstacle] = []
        for i, feat in enumerate(feats):
            label = _feature_label(i, feat)
            if not isinstance(feat, dict) or feat.get("type") != "Feature":
                raise InvalidWorld(f"{label}: not a GeoJSON Feature")
            geom = feat.get("geometry")
            if not isinstance(geom, dict):
                raise InvalidWorld(f"{label}: missing geometry")
            gtype = geom.get("type")
            if gtype not in ("Polygon", "MultiPolygon"):
                raise InvalidWorld(
                    f"{label}: geometry type {gtype!r} is not a Polygon/MultiPolygon"
                )
            _check_coordinates(label, geom.get("coordinates"))
            try:
                g = shape(geom)
            except Exception as exc:  # shapely raises assorted errors on malformed rings
                raise InvalidWorld(f"{label}: malformed coordinates ({exc})") from exc
            props = feat.get("properties") or {}
            kind = str(props.get("kind", "obstacle")) if isinstance(props, dict) else "obstacle"
            obstacles.extend(_split_checked(label, g, _feature_name(i, feat), kind))
        if not obstacles:
            raise InvalidWorld("GeoJSON: no features")
        return World(obstacles)

    @staticmethod
    def from_wkt(text: str) -> World:
        """Build from WKT text: one polygon per line or one GEOMETRYCOLLECTION. Raises
        InvalidWorld."""
        lines = [
            (n + 1, ln.strip())
            for n, ln in enumerate(text.splitlines())
            if ln.strip() and not ln.strip().startswith("#")
        ]
        if not lines:
            raise InvalidWorld("WKT: no geometry")
        geoms: list[tuple[str, Any]] = []
        if len(lines) == 1 and lines[0][1].upper().startswith("GEOMETRYCOLLECTION"):
            coll = _read_wkt(f"line {lines[0][0]}", lines[0][1])
            geoms = [(f"geometry {k}", g) for k, g in enumerate(coll.geoms)]
        else:
            geoms = [(f"line {n}", _read_wkt(f"line {n}", ln)) for n, ln in lines]
        obstacles: list[Obstacle] = []
        for k, (label, g) in enumerate(geoms):
            if g.geom_type not in ("Polygon", "MultiPolygon"):
                raise InvalidWorld(f"WKT {label}: geometry type {g.geom_type} is not a Polygon")
            coords = shapely.get_coordinates(g)
            if not np.all(np.isfinite(coords)):
                raise InvalidWorld(f"WKT {label}: non-finite coordinate")
            obstacles.extend(_split_checked(f"WKT {label}", g, f"obstacle-{k}", "obstacle"))
        return World(obstacles)

    # ----------------------------------------------------------------- geometry
    @property
    def union(self) -> Any:
        """Union of all obstacles (shapely geometry)."""
        if self._union is None:
            self._union = shapely.union_all([o.geometry for o in self.obstacles])
        return self._union

    @property
    def bounds(self) -> tuple[float, float, float, float]:
        """``(xmin, ymin, xmax, ymax)`` of all obstacles, metres."""
        return tuple(float(v) for v in self.union.bounds)  # type: ignore[return-value]

    @property
    def free_space(self) -> Any:
        """Bounding box of the obstacles minus the obstacles (shapely geometry, metres;
        cached)."""
        if self._free is None:
            self._free = box(*self.bounds).difference(self.union)
        return self._free

    def rings(self) -> list[np.ndarray]:
        """Every obstacle ring (exteriors and interiors) as a closed ``(k, 2)`` array."""
        out: list[np.ndarray] = []
        for o in self.obstacles:
            out.append(np.asarray(o.geometry.exterior.coords, dtype=np.float64)[:, :2])
            out.extend(np.asarray(r.coords, dtype=np.float64)[:, :2] for r in o.geometry.interiors)
        return out

    def segments(self) -> np.ndarray:
        """All ring edges as an ``(s, 4)`` array ``[x0, y0, x1, y1]`` (metres)."""
        return np.vstack([np.hstack([r[:-1], r[1:]]) for r in self.rings()])

    def to_map_data(self, map_id: str) -> MapData:
        """The exact metric map: every obstacle ring as a closed polyline."""
        return MapData.from_lists(map_id, "metric", self.rings())

    def clearance(self, points: np.ndarray) -> np.ndarray:
        """Distance (m) from each ``(n, 2)`` point to the nearest obstacle (0 inside one)."""
        pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
        return np.asarray(shapely.distance(self.union, shapely.points(pts)), dtype=np.float64)

    def is_free(self, points: np.ndarray, margin: float = 0.0) -> np.ndarray:
        """True where a point lies inside the bounding box and more than ``margin`` metres
        from every obstacle."""
        pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
        x0, y0, x1, y1 = self.bounds
        inside = (pts[:, 0] > x0) & (pts[:, 0] < x1) & (pts[:, 1] > y0) & (pts[:, 1] < y1)
        return inside & (self.clearance(pts) > margin)


def load_world(path: str | Path) -> World:
    """Read a world file: ``.geojson``/``.json`` (GeoJSON) or anything else as WKT.

    Raises :class:`InvalidWorld` for unreadable files, bad JSON/WKT and invalid geometry.
    """
    p = Path(path)
    try:
        size = p.stat().st_size
        if size > _MAX_FILE_BYTES:
            raise InvalidWorld(f"{p}: file too large ({size} bytes > {_MAX_FILE_BYTES})")
        text = p.read_text(encoding="utf-8")
    except InvalidWorld:
        raise
    except (OSError, UnicodeDecodeError) as exc:
        raise InvalidWorld(f"{p}: unreadable file ({exc})") from exc
    stripped = text.lstrip()
    if p.suffix.lower() in (".geojson", ".json") or stripped.startswith("{"):
        try:
            doc = json.loads(text)
        except json.JSONDecodeError as exc:
            raise InvalidWorld(f"{p}: bad JSON ({exc})") from exc
        try:
            return World.from_geojson(doc)
        except InvalidWorld as exc:
            raise InvalidWorld(f"{p}: {exc}") from exc
    try:
        return World.from_wkt(text)
    except InvalidWorld as exc:
        raise InvalidWorld(f"{p}: {exc}") from exc


# --------------------------------------------------------------------- helpers
def _feature_name(i: int, feat: Any) -> str:
    props = feat.get("properties") if isinstance(feat, dict) else None
    if isinstance(props, dict):
        for key in ("id", "name"):
            if props.get(key) is not None:
                return str(props[key])[:64]
    if isinstance(feat, dict) and feat.get("id") is not None:
        return str(feat["id"])[:64]
    return f"feature-{i}"


def _feature_label(i: int, feat: Any) -> str:
    return f"feature {i} ({_feature_name(i, feat)!r})"


def _check_coordinates(label: str, coords: Any) -> None:
    """Walk nested coordinate lists; every leaf must be a finite number."""
    stack = [coords]
    count = 0
    while stack:
        c = stack.pop()
        if isinstance(c, list):
            if not c:
                raise InvalidWorld(f"{label}: empty coordinate list")
            stack.extend(c)
        elif isinstance(c, bool) or not isinstance(c, (int, float)):
            raise InvalidWorld(f"{label}: coordinate {c!r} is not a number")
        elif not math.isfinite(c):
            raise InvalidWorld(f"{label}: non-finite coordinate {c!r}")
        else:
            count += 1
    if count == 0:
        raise InvalidWorld(f"{label}: empty geometry")


def _read_wkt(label: str, text: str) -> Any:
    try:
        return shapely.from_wkt(text)
    except Exception as exc:  # shapely.errors.GEOSException and friends
        raise InvalidWorld(f"WKT {label}: unreadable ({exc})") from exc


def _split_checked(label: str, g: Any, name: str, kind: str) -> list[Obstacle]:
    """Validate a (Multi)Polygon and return one Obstacle per polygon part."""
    if g.is_empty:
        raise InvalidWorld(f"{label}: empty geometry")
    if not g.is_valid:
        raise InvalidWorld(f"{label}: invalid polygon ({explain_validity(g)})")
    parts = list(g.geoms) if isinstance(g, MultiPolygon) else [g]
    out = []
    for k, part in enumerate(parts):
        if part.is_empty or part.area <= 0.0:
            raise InvalidWorld(f"{label}: polygon part {k} has zero area")
        part_name = name if len(parts) == 1 else f"{name}#{k}"
        out.append(Obstacle(geometry=shapely.force_2d(part), name=part_name, kind=kind))
    return out
