"""The map as the sensor model sees it: one representation shared by every method.

:class:`MapModel` holds a map's polyline segments with their unit normals and one bucket grid
over them, which answers "which map segment is nearest to this point (within ``reach``), and
is its surface oriented like the scan's?" exactly -- the association step of every
point-to-line fit (:func:`service.core.sensor.refine.refine_pose`) -- and "which segments lie
near these points?" (:meth:`MapModel.nearby_segments`, the global search's fit). It also
rasterises the map into its distance field and casts rays (:attr:`MapModel.caster`). Built
once per map (:meth:`MapModel.shared`); immutable; shared by the robots of a worker (like the
beluga / nav2 sensor-model-owns-the-map split: methods ask the model, they do not grow their
own copy of the map). :class:`service.core.sensor.scoring.SensorModel` scores poses on it.

Units: metres, map frame. Segments ``[x0, y0, x1, y1]``.
"""

from __future__ import annotations

import threading
import weakref
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np
from scipy import ndimage

from service.core import kernels, numeric
from service.core.kernels import map as map_kernels
from service.core.kernels import search as search_kernels
from service.core.sensor.raycast import RayCaster
from service.core.types import MapData
from service.errors import LocalizationError


@dataclass(frozen=True)
class DistanceField:
    """Distance (m) from each cell centre of a regular grid to the nearest map segment.

    ``values`` ``(ny, nx)`` float32; cell ``(iy, ix)`` has its centre at
    ``origin + (ix + 0.5, iy + 0.5) * resolution``.
    """

    values: np.ndarray
    origin: np.ndarray
    resolution: float

    def lookup(self, points: np.ndarray, outside: float = np.inf) -> np.ndarray:
        """Distance at each ``(n, 2)`` point (nearest cell); ``outside`` beyond the grid."""
        p = np.asarray(points, dtype=np.float64).reshape(-1, 2)
        ij = np.floor((p - self.origin) / self.resolution).astype(np.int64)
        ny, nx = self.values.shape
        ok = (ij[:, 0] >= 0) & (ij[:, 0] < nx) & (ij[:, 1] >= 0) & (ij[:, 1] < ny)
        out = np.full(len(p), outside, dtype=np.float64)
        out[ok] = self.values[ij[ok, 1], ij[ok, 0]]
        return out


@dataclass(frozen=True)
class Nearest:
    """Result of :meth:`MapModel.nearest`: per point the segment index (-1: none within
    reach), the distance (inf: none), the foot point and the unit normal used for the
    point-to-line residual."""

    segment: np.ndarray
    distance: np.ndarray
    foot: np.ndarray
    normal: np.ndarray


#: ``id(MapData) -> its shared model`` while something uses the model: see
#: :meth:`MapModel.shared`.
_SHARED: weakref.WeakValueDictionary[int, MapModel] = weakref.WeakValueDictionary()
_SHARED_LOCK = threading.Lock()


def _same_map(a: MapData, b: MapData) -> bool:
    """Whether two maps are equal (id, kind and every polyline's points)."""
    return (
        a.map_id == b.map_id
        and a.kind == b.kind
        and len(a.polylines) == len(b.polylines)
        and all(np.array_equal(p, q) for p, q in zip(a.polylines, b.polylines, strict=True))
    )


@dataclass(eq=False)
class MapModel:
    """Segments, normals and the association grid of one map.

    ``cell`` (m) is the bucket size, ``reach`` (m) the largest association distance any fit
    may ask for (queries beyond it find nothing).
    """

    map_data: MapData
    cell: float = 0.25
    reach: float = 1.0
    _fields: dict[float, DistanceField] = field(default_factory=dict, init=False, repr=False)

    def __post_init__(self) -> None:
        if self.cell <= 0 or self.reach <= 0:
            raise LocalizationError("MapModel: cell and reach must be > 0")
        segs = self.map_data.segments()
        d = segs[:, 2:4] - segs[:, 0:2]
        L = np.hypot(d[:, 0], d[:, 1])
        keep = L > 1e-9
        if not np.any(keep):
            raise LocalizationError(f"map {self.map_data.map_id!r} has no segment of length > 0")
        self.segments = np.ascontiguousarray(segs[keep])
        d = d[keep] / L[keep, None]
        self.normals = np.ascontiguousarray(np.column_stack([-d[:, 1], d[:, 0]]))
        lo = np.minimum(self.segments[:, 0:2], self.segments[:, 2:4]).min(axis=0) - self.reach
        hi = np.maximum(self.segments[:, 0:2], self.segments[:, 2:4]).max(axis=0) + self.reach
        self.origin = lo
        self.nx = int(np.ceil((hi[0] - lo[0]) / self.cell)) + 1
        self.ny = int(np.ceil((hi[1] - lo[1]) / self.cell)) + 1
        if kernels.HAVE_NUMBA:
            self.start, self.items = map_kernels.segment_grid(
                self.segments,
                float(lo[0]),
                float(lo[1]),
                self.nx,
                self.ny,
                float(self.cell),
                float(self.reach),
            )
        else:
            self.start, self.items = _segment_grid_numpy(
                self.segments, lo, self.nx, self.ny, self.cell, self.reach
            )

    @classmethod
    def shared(cls, map_data: MapData) -> MapModel:
        """The default-parameter model of ``map_data``, built once per ``MapData`` object and
        shared by every localiser given that object while any of them (or whoever keeps the
        model) lives: a worker holds one ``MapData`` per map, so its robots share one model (a
        160-polyline building's model costs ~12 ms and its grid's memory once per map, not
        once per robot). A copy of a map that has a model (a localiser unpickled in another
        process) gets that model too. Thread-safe."""
        key = id(map_data)
        with _SHARED_LOCK:
            model = _SHARED.get(key)
            if model is not None and model.map_data is map_data:
                return model
            equal = [m for m in _SHARED.values() if _same_map(m.map_data, map_data)]
            if equal:
                _SHARED[key] = equal[0]
                return equal[0]
        model = cls(map_data)  # outside the lock: another map's model may be built meanwhile
        with _SHARED_LOCK:
            hit = _SHARED.get(key)
            if hit is not None and hit.map_data is map_data:
                return hit
            _SHARED[key] = model
        return model

    def __reduce__(self) -> tuple[object, tuple[MapData, float, float]]:
        # pickled as its map (a robot moved to another worker): the process that loads it
        # shares its own model of that map, caches (distance field, ray caster) not copied
        return _restore, (self.map_data, self.cell, self.reach)

    @property
    def map_id(self) -> str:
        return self.map_data.map_id

    @property
    def kind(self) -> str:
        return self.map_data.kind

    def grid_args(self) -> tuple:
        """The arrays and scalars the compiled kernels take, in their order."""
        return (
            self.segments,
            self.normals,
            float(self.origin[0]),
            float(self.origin[1]),
            self.nx,
            self.ny,
            float(self.cell),
            self.start,
            self.items,
        )

    def nearest(
        self,
        points: np.ndarray,
        max_dist: float,
        point_normals: np.ndarray | None = None,
        max_angle: float = np.pi / 2,
    ) -> Nearest:
        """The nearest map segment to each ``(n, 2)`` point (map frame) within ``max_dist``
        (<= ``reach``) metres; with ``point_normals`` ``(n, 2)`` (unit, map frame; NaN rows:
        no constraint) only segments whose normal lies within ``max_angle`` radians of the
        point's (either sign) qualify."""
        q = np.ascontiguousarray(np.asarray(points, dtype=np.float64).reshape(-1, 2))
        if point_normals is None:
            qn = np.full_like(q, np.nan)
        else:
            qn = np.ascontiguousarray(np.asarray(point_normals, dtype=np.float64).reshape(-1, 2))
        md = float(min(max_dist, self.reach))
        cg = float(np.cos(max_angle)) if max_angle < np.pi / 2 else -1.0
        if kernels.HAVE_NUMBA:
            seg, dist, foot, nrm = map_kernels.nearest_segments(q, qn, *self.grid_args(), md, cg)
        else:
            seg, dist, foot, nrm = nearest_numpy(self, q, qn, md, cg)
        return Nearest(segment=seg, distance=dist, foot=foot, normal=nrm)

    def distance_field(self, resolution: float, margin: float = 1.0) -> DistanceField:
        """The map's distance field at ``resolution`` (m per cell), cached per resolution:
        segments rasterised by dense sampling, then a Euclidean distance transform."""
        got = self._fields.get(resolution)
        if got is not None:
            return got
        segs = self.segments
        lo = np.minimum(segs[:, 0:2], segs[:, 2:4]).min(axis=0) - margin
        hi = np.maximum(segs[:, 0:2], segs[:, 2:4]).max(axis=0) + margin
        w, h = (np.ceil((hi - lo) / resolution).astype(int) + 1).tolist()
        occ = np.zeros((h, w), dtype=bool)
        L = np.hypot(segs[:, 2] - segs[:, 0], segs[:, 3] - segs[:, 1])
        n = np.maximum(2, np.ceil(L / (0.25 * resolution)).astype(int) + 1)
        idx = np.repeat(np.arange(len(segs)), n)
        t = np.concatenate([np.linspace(0.0, 1.0, k) for k in n])
        x = segs[idx, 0] + t * (segs[idx, 2] - segs[idx, 0])
        y = segs[idx, 1] + t * (segs[idx, 3] - segs[idx, 1])
        ix = np.floor((x - lo[0]) / resolution).astype(int)
        iy = np.floor((y - lo[1]) / resolution).astype(int)
        occ[iy, ix] = True
        dist = (ndimage.distance_transform_edt(~occ) * resolution).astype(np.float32)
        df = DistanceField(values=dist, origin=lo, resolution=float(resolution))
        self._fields[resolution] = df
        return df

    @cached_property
    def caster(self) -> RayCaster:
        """The ray caster over the map's segments."""
        return RayCaster(self.segments)

    def nearby_segments(self, points: np.ndarray, radius: float) -> np.ndarray:
        """The segments within ``radius`` (<= ``reach``) metres of any of map-frame ``points``
        ``(n, 2)``, in their stored order; all of them if none is. Up to
        :data:`BRUTE_SEGMENTS` segments every point is measured against every segment (quicker
        than the grid on a floor plan); beyond, only the segments the bucket grid lists for
        the points' cells (each cell lists those within ``reach`` of any point in it) are
        measured. Either way the test is the exact point-to-segment distance, so both give the
        same rows."""
        pts = np.ascontiguousarray(np.asarray(points, dtype=np.float64).reshape(-1, 2))
        if len(self.segments) <= BRUTE_SEGMENTS:
            return nearby_segments_brute(self.segments, pts, radius)
        if radius > self.reach:
            raise LocalizationError(f"nearby_segments: radius {radius} beyond reach {self.reach}")
        f = (pts - self.origin) / self.cell
        ok = np.all(np.isfinite(f), axis=1)
        f = f[ok]
        ok = (f[:, 0] >= 0) & (f[:, 1] >= 0) & (f[:, 0] < self.nx) & (f[:, 1] < self.ny)
        cells = np.unique(f[ok, 0].astype(np.int64) * self.ny + f[ok, 1].astype(np.int64))
        lo, hi = self.start[cells], self.start[cells + 1]
        total = hi - lo
        if not np.any(total > 0):
            return self.segments
        idx = np.repeat(lo - np.concatenate([[0], np.cumsum(total)[:-1]]), total)
        idx += np.arange(int(total.sum()))
        cand = np.unique(self.items[idx])
        near = near_mask(self.segments[cand], pts, radius)
        return self.segments[cand[near]] if np.any(near) else self.segments

    @cached_property
    def length(self) -> float:
        """Total length of the map's segments (m)."""
        d = self.segments[:, 2:4] - self.segments[:, 0:2]
        return float(np.hypot(d[:, 0], d[:, 1]).sum())


#: Up to this many segments (floor plans) measuring every point against every segment is
#: quicker than the bucket grid (0.12 vs 0.30 ms at 50 segments, even at ~400).
BRUTE_SEGMENTS = 256


def near_mask(segments: np.ndarray, points: np.ndarray, radius: float) -> np.ndarray:
    """For each segment, whether it lies within ``radius`` of any of ``points`` (the exact
    point-to-segment distance, squared, compared with ``radius²``); compiled
    (:func:`service.core.kernels.search.near_mask`) where numba is installed."""
    if kernels.HAVE_NUMBA:
        return search_kernels.near_mask(
            np.ascontiguousarray(segments, dtype=np.float64),
            np.ascontiguousarray(points, dtype=np.float64),
            float(radius),
        )
    a = segments[:, 0:2]
    e = segments[:, 2:4] - a
    ee = np.maximum(np.einsum("ij,ij->i", e, e), 1e-18)
    dx = points[:, None, 0] - a[None, :, 0]
    dy = points[:, None, 1] - a[None, :, 1]
    u = np.clip((dx * e[None, :, 0] + dy * e[None, :, 1]) / ee[None, :], 0.0, 1.0)
    d2 = (dx - u * e[None, :, 0]) ** 2 + (dy - u * e[None, :, 1]) ** 2
    return np.min(d2, axis=0) <= radius * radius


def nearby_segments_brute(segments: np.ndarray, points: np.ndarray, radius: float) -> np.ndarray:
    """The segments ``(s, 4)`` within ``radius`` metres of any of ``points`` ``(n, 2)``, in
    their original order; all of them if none is (the reference: every point against every
    segment)."""
    near = near_mask(segments, points, radius)
    return segments[near] if np.any(near) else segments


def _restore(map_data: MapData, cell: float, reach: float) -> MapModel:
    """An unpickled :class:`MapModel`: the shared one when it has the default cell and reach."""
    if cell == MapModel.cell and reach == MapModel.reach:
        return MapModel.shared(map_data)
    return MapModel(map_data, cell, reach)


def _segment_grid_numpy(
    segs: np.ndarray, lo: np.ndarray, nx: int, ny: int, cell: float, reach: float
) -> tuple[np.ndarray, np.ndarray]:
    """Reference of :func:`service.core.kernels.map.segment_grid` (same lists, same order)."""
    pad = reach + 0.7072 * cell
    lists: list[list[int]] = [[] for _ in range(nx * ny)]
    for s, (ax, ay, bx, by) in enumerate(segs):
        ex, ey = bx - ax, by - ay
        ee = max(ex * ex + ey * ey, 1e-18)
        ix0 = max(int(np.floor((min(ax, bx) - pad - lo[0]) / cell)), 0)
        ix1 = min(int(np.floor((max(ax, bx) + pad - lo[0]) / cell)), nx - 1)
        iy0 = max(int(np.floor((min(ay, by) - pad - lo[1]) / cell)), 0)
        iy1 = min(int(np.floor((max(ay, by) + pad - lo[1]) / cell)), ny - 1)
        if ix1 < ix0 or iy1 < iy0:
            continue
        cx = lo[0] + (np.arange(ix0, ix1 + 1) + 0.5) * cell
        cy = lo[1] + (np.arange(iy0, iy1 + 1) + 0.5) * cell
        CX, CY = np.meshgrid(cx, cy, indexing="ij")
        u = np.clip(((CX - ax) * ex + (CY - ay) * ey) / ee, 0.0, 1.0)
        d2 = (CX - ax - u * ex) ** 2 + (CY - ay - u * ey) ** 2
        for a, b in zip(*np.nonzero(d2 <= pad * pad), strict=True):
            lists[(ix0 + a) * ny + (iy0 + b)].append(s)
    count = np.array([0] + [len(x) for x in lists], dtype=np.intp)
    start = np.cumsum(count)
    items = np.array([s for x in lists for s in x], dtype=np.intp)
    return start, items


def nearest_numpy(
    model: MapModel, q: np.ndarray, qn: np.ndarray, max_dist: float, cos_gate: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Reference of :func:`service.core.kernels.map.nearest_segments`."""
    n = len(q)
    seg = np.full(n, -1, dtype=np.intp)
    dist = np.full(n, np.inf)
    foot = np.zeros((n, 2))
    nrm = np.zeros((n, 2))
    f = (q - model.origin) / model.cell
    for i in range(n):
        if f[i, 0] < 0 or f[i, 1] < 0 or f[i, 0] >= model.nx or f[i, 1] >= model.ny:
            continue
        c = int(f[i, 0]) * model.ny + int(f[i, 1])
        cand = model.items[model.start[c] : model.start[c + 1]]
        if not np.isnan(qn[i, 0]):
            cand = cand[np.abs(numeric.matvec(model.normals[cand], qn[i])) >= cos_gate]
        if len(cand) == 0:
            continue
        s = model.segments[cand]
        a = s[:, 0:2]
        e = s[:, 2:4] - a
        ee = np.maximum(np.einsum("ij,ij->i", e, e), 1e-18)
        u = np.clip(((q[i] - a) * e).sum(axis=1) / ee, 0.0, 1.0)
        r = q[i] - a - u[:, None] * e
        d2 = (r * r).sum(axis=1)
        k = int(np.argmin(d2))
        if d2[k] >= max_dist * max_dist:
            continue
        j = int(cand[k])
        seg[i] = j
        dist[i] = float(np.sqrt(d2[k]))
        foot[i] = a[k] + u[k] * e[k]
        nrm[i] = model.normals[j]
        if (u[k] <= 0.0 or u[k] >= 1.0) and dist[i] > 1e-12:
            nrm[i] = (q[i] - foot[i]) / dist[i]
    return seg, dist, foot, nrm
