"""Candidate viewpoints and the per-map view index of global localisation.

:func:`candidate_viewpoints` (a grid over the free space), :class:`ViewIndex` (per viewpoint the
map view reduced to its units, plus a distance field), :func:`build_index` and the on-disk
cache (:func:`load_or_build_index`, keyed by map content, extraction parameters and
:data:`FORMAT_VERSION`). See :mod:`service.core.global_localization` for the whole method."""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import math
import os
import re
import tempfile
import threading
import time
from collections import OrderedDict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from scipy import ndimage
from shapely import contains_xy
from shapely.geometry import Polygon

from service.core import _search_kernels
from service.core.configuration import (
    Configuration,
    ExtractionParams,
    map_view,
)
from service.core.dce import dce
from service.core.global_config import GlobalConfig
from service.core.localizer import ShapeConfig
from service.core.raycast import RayCaster
from service.core.segment_grid import SegmentGrid, nearby_segments_brute
from service.core.similarity import ShapeArcs, prepare, shape_complexity
from service.core.types import MapData
from service.errors import LocalizationError

log = logging.getLogger("shapeloc.global")

#: Version of the on-disk index format; bump when the file layout or its meaning changes.
FORMAT_VERSION = 1
_CACHE_PREFIX = "viewindex-"

# --------------------------------------------------------------------------------------------
# Candidate viewpoints
# --------------------------------------------------------------------------------------------


def _closed_rings(map_data: MapData, max_area: float) -> list[Polygon]:
    out = []
    for p in map_data.polylines:
        if len(p) >= 4 and np.allclose(p[0], p[-1]):
            poly = Polygon(p)
            if poly.is_valid and 0.0 < poly.area < max_area:
                out.append(poly)
    return out


def candidate_viewpoints(
    map_data: MapData,
    spacing: float = 0.6,
    *,
    min_clearance: float = 0.3,
    enclosure_beams: int = 90,
    min_enclosed: float = 0.9,
    max_range: float = 15.0,
    small_ring_area: float = 6.0,
    caster: RayCaster | None = None,
) -> np.ndarray:
    """Grid points over the map's free space, ``(v, 2)`` map frame (metres).

    A point of the ``spacing``-metre grid (offset half a cell from the map's bounds) is kept
    when (a) it is farther than ``min_clearance`` from every polyline, (b) at least
    ``min_enclosed`` of ``enclosure_beams`` evenly spread rays hit a polyline within
    ``max_range`` (outside a building most rays escape), and (c) it does not lie inside a
    closed ring of area below ``small_ring_area`` m² (furniture and pillars are small closed
    rings; rooms are larger or drawn open at their doors).
    """
    if spacing <= 0:
        raise LocalizationError(f"spacing must be > 0, got {spacing}")
    caster = caster or RayCaster(map_data.segments())
    x0, y0, x1, y1 = map_data.bounds()
    xs = np.arange(x0 + 0.5 * spacing, x1, spacing)
    ys = np.arange(y0 + 0.5 * spacing, y1, spacing)
    if xs.size == 0 or ys.size == 0:
        return np.zeros((0, 2))
    gx, gy = np.meshgrid(xs, ys)
    pts = np.column_stack([gx.ravel(), gy.ravel()])
    clear = _segment_clearance(pts, caster.segments)
    pts = pts[clear > min_clearance]
    rings = _closed_rings(map_data, small_ring_area)
    if rings and len(pts):
        inside = np.zeros(len(pts), dtype=bool)
        for r in rings:
            inside |= contains_xy(r, pts[:, 0], pts[:, 1])
        pts = pts[~inside]
    angles = -np.pi + (np.arange(enclosure_beams) + 0.5) * (2.0 * np.pi / enclosure_beams)
    keep = np.zeros(len(pts), dtype=bool)
    for k, p in enumerate(pts):
        r = caster.cast(np.array([p[0], p[1], 0.0]), angles, max_range)
        keep[k] = np.mean(np.isfinite(r)) >= min_enclosed
    return pts[keep]


def _segment_clearance(points: np.ndarray, segments: np.ndarray, chunk: int = 512) -> np.ndarray:
    """Distance (m) from each point to the nearest segment."""
    a = segments[:, 0:2]
    e = segments[:, 2:4] - a
    ee = np.maximum(np.einsum("ij,ij->i", e, e), 1e-18)
    out = np.empty(len(points))
    for s in range(0, len(points), chunk):
        p = points[s : s + chunk]
        dx = p[:, None, 0] - a[None, :, 0]
        dy = p[:, None, 1] - a[None, :, 1]
        u = np.clip((dx * e[None, :, 0] + dy * e[None, :, 1]) / ee[None, :], 0.0, 1.0)
        out[s : s + chunk] = np.sqrt(
            np.min((dx - u * e[None, :, 0]) ** 2 + (dy - u * e[None, :, 1]) ** 2, axis=1)
        )
    return out


# --------------------------------------------------------------------------------------------
# The per-map index
# --------------------------------------------------------------------------------------------


#: Up to this many segments (floor plans) measuring every point against every segment is
#: quicker than the bucket grid (0.12 vs 0.30 ms at 50 segments, even at ~400).
_BRUTE_SEGMENTS = 256


@dataclass(eq=False)
class ViewIndex:
    """Everything global search needs about one map, precomputed (see :func:`build_index`).

    ``viewpoints`` ``(v, 2)`` map frame. Units (a view feature or two consecutive ones) are
    stored flat: ``unit_view`` (viewpoint index), ``unit_rmin``/``unit_rmax`` (nearest and farthest
    vertex distance from its viewpoint, m), ``unit_complexity`` (m·rad), ``unit_group`` (units
    of different viewpoints with the same anchor — the same physical corner — share it),
    ``unit_anchor`` ``(u, 4)`` the anchor vertex x, y (map frame), the direction of the edge
    leaving it and its signed turn (rad), vertices
    ``unit_verts[unit_vert_off[u]:unit_vert_off[u+1]]`` (map frame). ``segments`` ``(s, 4)``
    the map's segments. ``dist`` the distance field (m, float32, row = y, column = x) with
    cell ``resolution`` metres and ``origin`` its lower-left corner. ``key`` the cache key,
    ``build_seconds`` how long the build took.
    """

    key: str
    map_id: str
    kind: str
    viewpoints: np.ndarray
    unit_view: np.ndarray
    unit_rmin: np.ndarray
    unit_rmax: np.ndarray
    unit_complexity: np.ndarray
    unit_group: np.ndarray
    unit_anchor: np.ndarray
    unit_vert_off: np.ndarray
    unit_verts: np.ndarray
    segments: np.ndarray
    dist: np.ndarray
    origin: np.ndarray
    resolution: float
    build_seconds: float = 0.0
    _arcs: list[ShapeArcs | None] = field(default_factory=list, repr=False)
    _caster: RayCaster | None = field(default=None, repr=False)
    _grid: SegmentGrid | None = field(default=None, repr=False)
    _tables: dict[tuple[float, float], tuple[np.ndarray, float]] = field(
        default_factory=dict, repr=False
    )

    def __len__(self) -> int:
        return int(self.unit_view.size)

    def verts(self, u: int) -> np.ndarray:
        """Vertices ``(k, 2)`` of unit ``u`` (map frame, m)."""
        return self.unit_verts[self.unit_vert_off[u] : self.unit_vert_off[u + 1]]

    def arcs(self, u: int) -> ShapeArcs:
        """Unit ``u`` prepared for S* (lazily, kept)."""
        if not self._arcs:
            self._arcs = [None] * len(self)
        a = self._arcs[u]
        if a is None:
            a = prepare(self.verts(u))
            self._arcs[u] = a
        return a

    @property
    def caster(self) -> RayCaster:
        """Ray caster over the map's segments."""
        if self._caster is None:
            self._caster = RayCaster(self.segments)
        return self._caster

    def nearby_segments(self, points: np.ndarray, radius: float) -> np.ndarray:
        """The map's segments within ``radius`` m of any of map-frame ``points`` ``(n, 2)``,
        in their stored order, all of them if none is (a :class:`SegmentGrid`, built lazily;
        the same rows as :func:`nearby_segments_brute`)."""
        if len(self.segments) <= _BRUTE_SEGMENTS:
            return nearby_segments_brute(self.segments, points, radius)
        if self._grid is None:
            self._grid = SegmentGrid(self.segments)
        return self._grid.nearby(points, radius)

    def score_table(self, sigma: float, cap: float) -> tuple[np.ndarray, float]:
        """The polish's per-cell score ``exp(-0.5 (min(d, cap) / sigma)²)`` over the distance
        field, and its value outside the field (built once per ``sigma`` / ``cap``, kept;
        :mod:`service.core._search_kernels`)."""
        key = (float(sigma), float(cap))
        got = self._tables.get(key)
        if got is None:
            table = _search_kernels.score_table(self.dist, key[0], key[1])
            outside = float(_search_kernels._score(math.inf, key[0], key[1]))
            got = (table, outside)
            self._tables[key] = got
        return got

    def distance(self, points: np.ndarray) -> np.ndarray:
        """Distance (m) from map-frame points ``(n, 2)`` to the map (distance field lookup,
        error <= one cell); ``inf`` outside the field."""
        ij = np.floor((points - self.origin) / self.resolution).astype(np.int64)
        h, w = self.dist.shape
        ok = (ij[:, 0] >= 0) & (ij[:, 0] < w) & (ij[:, 1] >= 0) & (ij[:, 1] < h)
        out = np.full(len(points), np.inf)
        out[ok] = self.dist[ij[ok, 1], ij[ok, 0]]
        return out

    def to_arrays(self) -> dict[str, np.ndarray]:
        """Plain arrays for :func:`numpy.savez` (no pickled objects)."""
        meta = {
            "format": FORMAT_VERSION,
            "key": self.key,
            "map_id": self.map_id,
            "kind": self.kind,
            "resolution": self.resolution,
            "build_seconds": self.build_seconds,
        }
        return {
            "meta": np.array(json.dumps(meta)),
            "viewpoints": self.viewpoints,
            "unit_view": self.unit_view,
            "unit_rmin": self.unit_rmin,
            "unit_rmax": self.unit_rmax,
            "unit_complexity": self.unit_complexity,
            "unit_group": self.unit_group,
            "unit_anchor": self.unit_anchor,
            "unit_vert_off": self.unit_vert_off,
            "unit_verts": self.unit_verts,
            "segments": self.segments,
            "dist": self.dist,
            "origin": self.origin,
        }

    @staticmethod
    def from_arrays(arrays: Any, expect_key: str) -> ViewIndex:
        """Rebuild from :meth:`to_arrays` output, checking every field; raises
        :class:`LocalizationError` on anything unexpected (the cache is never trusted)."""
        try:
            meta = json.loads(str(arrays["meta"][()]))
            if meta.get("format") != FORMAT_VERSION or meta.get("key") != expect_key:
                raise LocalizationError("cache key or format version mismatch")
            vp = np.asarray(arrays["viewpoints"], dtype=np.float64)
            uv = np.asarray(arrays["unit_view"], dtype=np.int64)
            rmin = np.asarray(arrays["unit_rmin"], dtype=np.float64)
            rmax = np.asarray(arrays["unit_rmax"], dtype=np.float64)
            uc = np.asarray(arrays["unit_complexity"], dtype=np.float64)
            ug = np.asarray(arrays["unit_group"], dtype=np.int64)
            ua = np.asarray(arrays["unit_anchor"], dtype=np.float64)
            off = np.asarray(arrays["unit_vert_off"], dtype=np.int64)
            verts = np.asarray(arrays["unit_verts"], dtype=np.float64)
            segs = np.asarray(arrays["segments"], dtype=np.float64)
            dist = np.asarray(arrays["dist"], dtype=np.float32)
            origin = np.asarray(arrays["origin"], dtype=np.float64)
            res = float(meta["resolution"])
        except LocalizationError:
            raise
        except Exception as exc:  # any malformed content: not trusted
            raise LocalizationError(f"malformed index: {exc}") from exc
        u = uv.size
        ok = (
            vp.ndim == 2
            and vp.shape[1] == 2
            and rmin.shape == (u,)
            and rmax.shape == (u,)
            and uc.shape == (u,)
            and ug.shape == (u,)
            and ua.shape == (u, 4)
            and off.shape == (u + 1,)
            and verts.ndim == 2
            and verts.shape[1] == 2
            and segs.ndim == 2
            and segs.shape[1] == 4
            and dist.ndim == 2
            and origin.shape == (2,)
            and res > 0
        )
        ok = ok and (u == 0 or (uv.min() >= 0 and uv.max() < len(vp)))
        ok = ok and off[0] == 0 and off[-1] == len(verts) and bool(np.all(np.diff(off) >= 2))
        finite = [vp, rmin, rmax, uc, ua, verts, segs, origin]
        ok = ok and all(bool(np.all(np.isfinite(a))) for a in finite)
        ok = ok and not bool(np.any(np.isnan(dist)))
        if not ok:
            raise LocalizationError("index arrays are inconsistent")
        return ViewIndex(
            key=expect_key,
            map_id=str(meta["map_id"]),
            kind=str(meta["kind"]),
            viewpoints=vp,
            unit_view=uv,
            unit_rmin=rmin,
            unit_rmax=rmax,
            unit_complexity=uc,
            unit_group=ug,
            unit_anchor=ua,
            unit_vert_off=off,
            unit_verts=verts,
            segments=segs,
            dist=dist,
            origin=origin,
            resolution=res,
            build_seconds=float(meta.get("build_seconds", 0.0)),
        )


def index_key(map_data: MapData, config: ShapeConfig, gconfig: GlobalConfig) -> str:
    """Cache key: SHA-256 (hex) of the map content and every parameter the index depends on."""
    h = hashlib.sha256()
    h.update(f"shapeloc-viewindex-v{FORMAT_VERSION}\n{map_data.kind}\n".encode())
    for p in map_data.polylines:
        a = np.ascontiguousarray(p, dtype="<f8")
        h.update(len(a).to_bytes(8, "little"))
        h.update(a.tobytes())
    params = {
        "extraction": config.extraction().__dict__,
        "view_beams": config.view_beams,
        "view_max_range": config.view_max_range,
        "index": gconfig.model_dump(
            include={
                "spacing",
                "min_clearance",
                "enclosure_beams",
                "min_enclosed",
                "small_ring_area",
                "grid_resolution",
            }
        ),
    }
    h.update(json.dumps(params, sort_keys=True).encode())
    return h.hexdigest()


def _anchor(verts: np.ndarray) -> tuple[np.ndarray, float, float]:
    """The unit's most salient vertex ``(2,)`` (largest ``|turn| * min(adjacent arm)``, the
    vertex contributing most to the shape complexity), the direction (rad) of the edge
    leaving it and its signed turn angle (rad). Many viewpoints see the same corner: the
    anchor identifies it, and two corresponding anchors fix a pose by themselves."""
    if len(verts) < 3:
        d = verts[-1] - verts[0]
        return verts.mean(axis=0), float(np.arctan2(d[1], d[0])), 0.0
    d = np.diff(verts, axis=0)
    ln = np.hypot(d[:, 0], d[:, 1])
    ang = np.arctan2(d[:, 1], d[:, 0])
    turn = np.mod(np.diff(ang) + np.pi, 2.0 * np.pi) - np.pi
    k = int(np.argmax(np.abs(turn) * np.minimum(ln[:-1], ln[1:])))
    return verts[1 + k], float(ang[1 + k]), float(turn[k])


def _joined(a: np.ndarray, b: np.ndarray, threshold: float) -> np.ndarray:
    """Two consecutive features' vertices as one unit, re-simplified by DCE (eq. 2) so that
    the short junction between them (the two pieces of a corner share about one point) does
    not hide the corner from the shape complexity."""
    u = np.vstack([a, b])
    return u[dce(u, threshold)]


def _view_units(Q: Configuration, threshold: float) -> list[np.ndarray]:
    """Vertices of each feature and of each pair of consecutive features (cyclic view)."""
    n = len(Q.features)
    out = [f.vertices for f in Q.features]
    if n >= 2:
        last = n if n > 2 else 1
        for i in range(last):
            out.append(_joined(Q.features[i].vertices, Q.features[(i + 1) % n].vertices, threshold))
    return out


def _distance_field(
    segments: np.ndarray, resolution: float, margin: float = 1.0
) -> tuple[np.ndarray, np.ndarray]:
    """Distance (m) from each grid cell centre to the nearest segment, float32, and the grid
    origin (lower-left corner, map frame)."""
    lo = np.minimum(segments[:, 0:2], segments[:, 2:4]).min(axis=0) - margin
    hi = np.maximum(segments[:, 0:2], segments[:, 2:4]).max(axis=0) + margin
    w, h = (np.ceil((hi - lo) / resolution).astype(int) + 1).tolist()
    occ = np.zeros((h, w), dtype=bool)
    for s in segments:
        n = max(2, int(np.ceil(np.hypot(s[2] - s[0], s[3] - s[1]) / (0.25 * resolution))) + 1)
        t = np.linspace(0.0, 1.0, n)
        x = s[0] + t * (s[2] - s[0])
        y = s[1] + t * (s[3] - s[1])
        ix = np.floor((x - lo[0]) / resolution).astype(int)
        iy = np.floor((y - lo[1]) / resolution).astype(int)
        occ[iy, ix] = True
    dist = ndimage.distance_transform_edt(~occ) * resolution
    return dist.astype(np.float32), lo


#: Anchor cell (m) and edge direction bucket (rad) that make units "the same corner".
_GROUP_CELL = 0.25
_GROUP_ANGLE = np.pi / 6.0


def _group_ids(keys: list[tuple[int, int, int]]) -> np.ndarray:
    ids: dict[tuple[int, int, int], int] = {}
    return np.asarray([ids.setdefault(k, len(ids)) for k in keys], dtype=np.int64)


def build_index(
    map_data: MapData, config: ShapeConfig | None = None, gconfig: GlobalConfig | None = None
) -> ViewIndex:
    """Precompute the :class:`ViewIndex` of a map (no disk access).

    For every :func:`candidate_viewpoints` point, the 360-degree map view is extracted with
    the tracker's own parameters (``config``: view beams, range, grouping, DCE, pieces), and
    its units are stored with their complexity and range. Cost: one map view per viewpoint.
    """
    config = config or ShapeConfig.for_kind(map_data.kind)
    gconfig = gconfig or GlobalConfig.for_kind(map_data.kind)
    t0 = time.perf_counter()
    caster = RayCaster(map_data.segments())
    params: ExtractionParams = config.extraction()
    vps = candidate_viewpoints(
        map_data,
        gconfig.spacing,
        min_clearance=gconfig.min_clearance,
        enclosure_beams=gconfig.enclosure_beams,
        min_enclosed=gconfig.min_enclosed,
        max_range=config.view_max_range,
        small_ring_area=gconfig.small_ring_area,
        caster=caster,
    )
    uview: list[int] = []
    rmin: list[float] = []
    rmax: list[float] = []
    ucomp: list[float] = []
    ukey: list[tuple[int, int, int]] = []
    uanc: list[tuple[float, float, float, float]] = []
    verts: list[np.ndarray] = []
    for v, p in enumerate(vps):
        Q = map_view(
            caster,
            np.array([p[0], p[1], 0.0]),
            2.0 * np.pi,
            config.view_beams,
            config.view_max_range,
            params,
        )
        for uv in _view_units(Q, params.dce_threshold):
            if len(uv) < 2:
                continue
            uview.append(v)
            d = np.hypot(uv[:, 0] - p[0], uv[:, 1] - p[1])
            rmin.append(float(d.min()))
            rmax.append(float(d.max()))
            ucomp.append(shape_complexity(uv))
            anc, direction, turn = _anchor(uv)
            uanc.append((float(anc[0]), float(anc[1]), direction, turn))
            cell = np.floor(anc / _GROUP_CELL).astype(int)
            ukey.append((int(cell[0]), int(cell[1]), int(np.floor(direction / _GROUP_ANGLE))))
            verts.append(uv)
    off = np.zeros(len(verts) + 1, dtype=np.int64)
    if verts:
        off[1:] = np.cumsum([len(v) for v in verts])
    dist, origin = _distance_field(caster.segments, gconfig.grid_resolution)
    return ViewIndex(
        key=index_key(map_data, config, gconfig),
        map_id=map_data.map_id,
        kind=map_data.kind,
        viewpoints=vps,
        unit_view=np.asarray(uview, dtype=np.int64),
        unit_rmin=np.asarray(rmin, dtype=np.float64),
        unit_rmax=np.asarray(rmax, dtype=np.float64),
        unit_complexity=np.asarray(ucomp, dtype=np.float64),
        unit_group=_group_ids(ukey),
        unit_anchor=np.asarray(uanc, dtype=np.float64).reshape(-1, 4),
        unit_vert_off=off,
        unit_verts=np.vstack(verts) if verts else np.zeros((0, 2)),
        segments=caster.segments.copy(),
        dist=dist,
        origin=origin,
        resolution=gconfig.grid_resolution,
        build_seconds=time.perf_counter() - t0,
    )


def cache_path(cache_dir: Path, map_id: str, key: str) -> Path:
    """File of a map's index: ``<cache_dir>/viewindex-<safe map id>-<key[:20]>.npz``."""
    safe = re.sub(r"[^A-Za-z0-9_.-]", "_", map_id)[:80]
    return Path(cache_dir) / f"{_CACHE_PREFIX}{safe}-{key[:20]}.npz"


def save_index(index: ViewIndex, cache_dir: Path) -> Path:
    """Write ``index`` atomically (temporary file, fsync, rename) and remove older index files
    of the same map id. Returns the path."""
    cache_dir = Path(cache_dir)
    cache_dir.mkdir(parents=True, exist_ok=True)
    path = cache_path(cache_dir, index.map_id, index.key)
    fd, tmp = tempfile.mkstemp(prefix=".tmp-", suffix=".npz", dir=cache_dir)
    try:
        with os.fdopen(fd, "wb") as f:
            np.savez(f, **index.to_arrays())
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise
    stem = cache_path(cache_dir, index.map_id, "").name[: -len(".npz")]
    stale = re.compile(re.escape(stem) + r"[0-9a-f]{20}\.npz")
    for old in cache_dir.glob(f"{stem}*.npz"):
        if old != path and stale.fullmatch(old.name):
            with contextlib.suppress(OSError):
                old.unlink()
    return path


def load_index(path: Path, key: str) -> ViewIndex:
    """Read an index file, checking its key and content; raises :class:`LocalizationError`."""
    try:
        with np.load(path, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
    except LocalizationError:
        raise
    except Exception as exc:
        raise LocalizationError(f"unreadable index {path}: {exc}") from exc
    return ViewIndex.from_arrays(arrays, key)


_MEMO: OrderedDict[str, ViewIndex] = OrderedDict()
_MEMO_LOCK = threading.Lock()
_MEMO_SIZE = 4


def load_or_build_index(
    map_data: MapData,
    config: ShapeConfig | None = None,
    gconfig: GlobalConfig | None = None,
    cache_dir: Path | None = None,
) -> ViewIndex:
    """The map's index: from this process' memory, else from ``cache_dir`` (if given and the
    file is valid), else built (and then saved to ``cache_dir``). A corrupt or mismatched file
    is logged as a warning and rebuilt, never trusted. Robots on the same map share it."""
    config = config or ShapeConfig.for_kind(map_data.kind)
    gconfig = gconfig or GlobalConfig.for_kind(map_data.kind)
    key = index_key(map_data, config, gconfig)
    with _MEMO_LOCK:
        idx = _MEMO.get(key)
        if idx is not None:
            _MEMO.move_to_end(key)
            return idx
    idx = None
    if cache_dir is not None:
        path = cache_path(Path(cache_dir), map_data.map_id, key)
        if path.exists():
            try:
                idx = load_index(path, key)
                log.info("view index of map %s loaded from %s", map_data.map_id, path)
            except LocalizationError as exc:
                log.warning("view index %s not usable (%s); rebuilding", path, exc)
    if idx is None:
        idx = build_index(map_data, config, gconfig)
        log.info(
            "view index of map %s built: %d viewpoints, %d units, %.1f s",
            map_data.map_id,
            len(idx.viewpoints),
            len(idx),
            idx.build_seconds,
        )
        if cache_dir is not None:
            try:
                save_index(idx, Path(cache_dir))
            except OSError as exc:
                log.warning("view index of map %s not saved: %s", map_data.map_id, exc)
    with _MEMO_LOCK:
        _MEMO[key] = idx
        while len(_MEMO) > _MEMO_SIZE:
            _MEMO.popitem(last=False)
    return idx


def clear_memory_cache() -> None:
    """Forget the indexes held in this process (tests, benchmarks)."""
    with _MEMO_LOCK:
        _MEMO.clear()
