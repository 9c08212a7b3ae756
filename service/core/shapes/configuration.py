"""Configurations of shape features (paper §4.2) and the map's abstract sensor reading (§2.1).

A *configuration* is the cyclically (angularly) ordered vector of polylines seen from one
viewpoint, each polyline carrying its metric position. Two kinds are built here, by exactly
the same code (grouping §4.1 + first-stage DCE eq. 2):

* :func:`scan_configuration` — from a laser scan; coordinates in the **robot frame** of the
  scan (metres, x forward, y left), viewpoint = the robot origin.
* :func:`map_view` — the map's *abstract sensor reading* from a pose: the map's segments are
  ray cast from that pose with a (by default 360-degree) virtual scan, and the virtual ranges
  go through the same grouping and DCE. Coordinates in the **map frame**; every polyline also
  remembers which map segments its rays hit, so that the pose step can use the exact map
  geometry (:mod:`service.core.pose`).

:class:`MapViewCache` keeps one :class:`~service.core.sensor.raycast.RayCaster` per map and reuses
the last view while the viewpoint has moved less than a threshold (a 360-degree view does not
depend on the heading).
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from service.core import kernels, numeric
from service.core.kernels import extract as extract_kernels
from service.core.pose import transform_points
from service.core.sensor.mapmodel import MapModel
from service.core.sensor.raycast import RayCaster
from service.core.shapes.dce import dce
from service.core.shapes.polylines import Polyline, group_polylines, group_spans, polylines_of_spans
from service.core.types import MapData, scan_arrays, wrap_angle
from service.errors import LocalizationError


@dataclass(frozen=True)
class ExtractionParams:
    """How polylines are extracted from (virtual or real) range readings.

    ``min_object_distance`` (m) and ``range_factor`` control grouping (§4.1, see
    :func:`service.core.shapes.polylines.group_polylines`); ``min_points`` drops smaller groups;
    ``dce_threshold`` (m) is the first-stage DCE stop relevance (eq. 2); ``min_length`` (m)
    drops polylines shorter than that after grouping; ``piece_length`` (m, 0 = off) cuts a
    simplified polyline at its vertices into pieces of about that length (see
    :func:`split_pieces`).
    """

    min_object_distance: float = 0.10
    range_factor: float = 4.0
    min_points: int = 3
    dce_threshold: float = 0.02
    min_length: float = 0.05
    piece_length: float = 1.5


@dataclass(eq=False)
class Feature:
    """One polyline of a configuration.

    ``vertices`` ``(v, 2)`` the DCE-simplified polyline and ``points`` ``(k, 2)`` the grouped
    raw returns, both in the configuration's frame (metres). ``bearing_start``/``bearing_end``
    (rad) bearings of the first/last point seen from the viewpoint, relative to the
    viewpoint's heading; ``angular_size`` (rad) the angle it subtends. ``segments`` ``(s, 4)``
    map-frame map segments its rays hit (map views only, else ``None``).
    """

    vertices: np.ndarray
    points: np.ndarray
    bearing_start: float
    bearing_end: float
    angular_size: float
    segments: np.ndarray | None = None
    cache: dict = field(default_factory=dict, repr=False)
    #: row of its first point among the grouped points of the reading, all groups stacked in
    #: angular order (:attr:`ScanGroups.points`); pieces cut from one group share their cut
    #: vertex, so a piece starts on the row where the previous one ends
    first_point: int = 0

    @cached_property
    def length(self) -> float:
        """Length of the simplified polyline (m)."""
        d = np.diff(self.vertices, axis=0)
        return float(np.sum(np.hypot(d[:, 0], d[:, 1])))

    @cached_property
    def centroid(self) -> np.ndarray:
        """Mean of the raw points (m, configuration frame)."""
        return self.points.mean(axis=0)

    @cached_property
    def bearing_mid(self) -> float:
        """Bearing (rad, relative to the viewpoint heading) of the middle of the polyline's
        angular extent."""
        return float(wrap_angle(self.bearing_start + 0.5 * self.angular_size))


@dataclass(eq=False)
class Configuration:
    """Angularly ordered polylines seen from ``viewpoint`` (paper §4.2).

    ``frame`` is ``"robot"`` (a scan: coordinates in the robot frame, viewpoint ``[0, 0, 0]``)
    or ``"map"`` (a map view: coordinates in the map frame, viewpoint = the pose the map was
    viewed from). ``cyclic`` is ``True`` for a 360-degree reading. ``fov`` ``(lo, hi)`` (rad,
    relative to the viewpoint heading) is the angular range covered by the beams.
    """

    features: list[Feature]
    frame: str
    viewpoint: np.ndarray
    cyclic: bool
    fov: tuple[float, float]

    def __len__(self) -> int:
        return len(self.features)

    def __getitem__(self, i: int) -> Feature:
        return self.features[i]


def split_pieces(keep: np.ndarray, points: np.ndarray, piece_length: float) -> list[np.ndarray]:
    """Cut a DCE-simplified polyline into pieces of about ``piece_length`` metres.

    ``keep`` are the DCE vertex indices into ``points`` (raw, ``(k, 2)`` m). Edges longer than
    ``2 * piece_length`` first get extra vertices at raw points about every ``piece_length``
    (they are collinear, so the shape is unchanged). Walking along the vertices, a cut is made
    at the first vertex where the piece has reached ``piece_length``, unless the rest would be
    shorter than half of it. Returns per piece its vertex indices (into ``points``);
    consecutive pieces share the cut vertex. A wall seen in one sweep thus becomes a sequence of
    wall-sized features in the same angular order, which the n:m correspondences of eq. 5 can
    re-join, and a wall that furniture cuts into several pieces in the scan can still find one
    counterpart per piece.
    """
    if piece_length <= 0 or len(points) < 3:
        return [keep]
    if kernels.HAVE_NUMBA:
        single, v, bounds = extract_kernels.split_cuts(
            np.ascontiguousarray(keep, dtype=np.intp),
            np.ascontiguousarray(points, dtype=np.float64),
            float(piece_length),
        )
        if single:
            return [keep]
        b = bounds.tolist()
        return [v[b[p] : b[p + 1] + 1] for p in range(len(b) - 1)]
    return _split_pieces_numpy(keep, points, piece_length)


def _split_pieces_numpy(
    keep: np.ndarray, points: np.ndarray, piece_length: float
) -> list[np.ndarray]:
    """Numpy reference of :func:`split_pieces` (``piece_length > 0``, >= 3 points)."""
    d = np.hypot(*np.diff(points, axis=0).T)
    cum_raw = np.concatenate(([0.0], np.cumsum(d)))
    verts = [int(keep[0])]
    for a, b in itertools.pairwise(keep):
        span = cum_raw[b] - cum_raw[a]
        nsub = int(span // piece_length)
        if nsub >= 2 and b - a > nsub:
            targets = cum_raw[a] + span * np.arange(1, nsub) / nsub
            extra = np.searchsorted(cum_raw[a : b + 1], targets) + a
            verts.extend(int(x) for x in np.unique(np.clip(extra, a + 1, b - 1)))
        verts.append(int(b))
    v = np.asarray(verts, dtype=np.intp)
    if len(v) <= 2 and cum_raw[-1] < 2.0 * piece_length:
        return [keep]
    cum = cum_raw[v]
    total = cum[-1]
    out = []
    start = 0
    for k in range(1, len(v) - 1):
        if cum[k] - cum[start] >= piece_length and total - cum[k] >= 0.5 * piece_length:
            out.append(v[start : k + 1])
            start = k
    out.append(v[start:])
    return out


def _groups(
    ranges: np.ndarray, angles: np.ndarray, params: ExtractionParams, wrap: bool
) -> list[Polyline]:
    """Grouping (§4.1) with the ``min_length`` filter, in the sensor frame, angular order."""
    groups = group_polylines(
        ranges,
        angles,
        min_object_distance=params.min_object_distance,
        range_factor=params.range_factor,
        min_points=params.min_points,
        wrap=wrap,
    )
    lengths = _lengths([g.points for g in groups])
    return [g for g, length in zip(groups, lengths, strict=True) if length >= params.min_length]


def _features_from_groups(
    groups: list[Polyline], params: ExtractionParams
) -> list[tuple[Polyline, np.ndarray, int]]:
    """First-stage DCE (eq. 2) and cutting into pieces of grouped polylines.

    Returns ``(raw polyline piece, simplified vertices, row of its first point among the
    groups' stacked points)`` per feature, in angular order."""
    out: list[tuple[Polyline, np.ndarray, int]] = []
    if not groups:
        return out
    off = np.cumsum([0, *(len(g.points) for g in groups)])
    if not kernels.HAVE_NUMBA or min(len(g.points) for g in groups) < 2:
        for gi, g in enumerate(groups):
            keep = dce(g.points, params.dce_threshold)
            pieces = split_pieces(keep, g.points, params.piece_length)
            if len(pieces) == 1:
                out.append((g, g.points[keep], int(off[gi])))
                continue
            for pk in pieces:
                out.append((_piece(g, int(pk[0]), int(pk[-1])), g.points[pk], int(off[gi] + pk[0])))
        return out
    # The same DCE and cuts for all groups in one compiled call.
    pts = np.vstack([g.points for g in groups])
    if not np.all(np.isfinite(pts)):
        raise LocalizationError("DCE input has non-finite coordinates")
    verts, voff, pieces = extract_kernels.simplify_groups(
        pts, off.astype(np.intp), float(params.dce_threshold), float(params.piece_length)
    )
    vo = voff.tolist()
    rows = pieces.tolist()
    whole = [vo[g + 1] - vo[g] - 1 == b and a == 0 for g, a, b in rows]
    cut = [r for r, w in zip(rows, whole, strict=True) if not w]
    # bearings of the cut pieces' end points, one np.arctan2 over all (as _piece takes them)
    ends = np.array([(verts[vo[g] + a], verts[vo[g] + b]) for g, a, b in cut], dtype=np.intp)
    ends = ends.reshape(-1, 2) + off[[g for g, _, _ in cut]].reshape(-1, 1)
    bear = numeric.atan2(pts[ends, 1], pts[ends, 0]).tolist()
    first = off.tolist()
    k = 0
    for (g, a, b), w in zip(rows, whole, strict=True):
        grp = groups[g]
        pk = verts[vo[g] + a : vo[g] + b + 1]
        if w:
            out.append((grp, grp.points[pk], first[g]))
            continue
        k0 = int(pk[0])
        out.append((_piece(grp, k0, int(pk[-1]), *bear[k]), grp.points[pk], first[g] + k0))
        k += 1
    return out


def _features_from_ranges(
    ranges: np.ndarray, angles: np.ndarray, params: ExtractionParams, wrap: bool
) -> list[tuple[Polyline, np.ndarray, int]]:
    """Grouping (§4.1), first-stage DCE (eq. 2) and cutting into pieces, in the sensor frame
    (:func:`_groups`, :func:`_features_from_groups`)."""
    return _features_from_groups(_groups(ranges, angles, params, wrap), params)


def _lengths(parts: list[np.ndarray]) -> list[float]:
    """:attr:`Polyline.length` of each ``(k, 2)`` point array, with one numpy pass over all
    (the same edge lengths, summed per polyline by the same ``np.sum``)."""
    if not parts:
        return []
    d = np.diff(np.vstack(parts), axis=0)
    h = np.hypot(d[:, 0], d[:, 1])
    off = list(itertools.accumulate((len(p) for p in parts), initial=0))
    total = np.add.reduce  # what np.sum calls, without its wrappers
    return [float(total(h[a : b - 1])) for a, b in itertools.pairwise(off)]


def _angular_sizes(parts: list[np.ndarray]) -> list[float]:
    """:attr:`Polyline.angular_size` of each ``(k, 2)`` point array (sensor frame), with one
    numpy pass over all (the same bearing steps, summed per polyline by the same ``np.sum``)."""
    if not parts:
        return []
    p = np.vstack(parts)
    steps = np.diff(numeric.atan2(p[:, 1], p[:, 0]))
    steps = (steps + np.pi) % (2.0 * np.pi) - np.pi
    off = list(itertools.accumulate((len(p) for p in parts), initial=0))
    total = np.add.reduce  # what np.sum calls, without its wrappers
    return [float(abs(total(steps[a : b - 1]))) for a, b in itertools.pairwise(off)]


def _piece(
    g: Polyline, k0: int, k1: int, start: float | None = None, end: float | None = None
) -> Polyline:
    """Points ``k0..k1`` (inclusive) of ``g`` as a polyline of their own (``start`` /
    ``end``: their bearings when already known)."""
    pts = g.points[k0 : k1 + 1]
    ids = g.idx[k0 : k1 + 1]
    return Polyline(
        points=pts,
        idx=ids,
        first_beam=int(ids[0]),
        last_beam=int(ids[-1]),
        bearing_start=numeric.atan2(pts[0, 1], pts[0, 0]) if start is None else start,
        bearing_end=numeric.atan2(pts[-1, 1], pts[-1, 0]) if end is None else end,
    )


@dataclass(frozen=True)
class ScanGroups:
    """A scan's polylines after grouping (§4.1) and the ``min_length`` filter, robot frame,
    angular order: the first half of :func:`scan_configuration`, all a precise fit of the
    scan's points needs; :meth:`configuration` adds the first-stage DCE (eq. 2) and the
    pieces. A tracked scan whose odometry prior fits needs no more, so the DCE waits until a
    shape matching asks for it."""

    beams: np.ndarray  # every beam's point (n, 2), NaN rows for no return
    spans: np.ndarray  # first and last beam (inclusive) of each group, (k, 2)
    cyclic: bool
    fov: tuple[float, float]
    params: ExtractionParams

    @cached_property
    def groups(self) -> list[Polyline]:
        """The groups as polylines (angular order); made when asked for: a precise fit
        needs only :attr:`points` and :attr:`starts`."""
        return polylines_of_spans(self.beams, self.spans)

    @cached_property
    def points(self) -> np.ndarray:
        """All groups' points stacked ``(n, 2)`` (angular order)."""
        sizes = self.spans[:, 1] - self.spans[:, 0] + 1
        first = np.cumsum(sizes) - sizes
        rows = np.arange(int(sizes.sum())) + np.repeat(self.spans[:, 0] - first, sizes)
        return self.beams[rows]

    @cached_property
    def starts(self) -> np.ndarray:
        """Row in :attr:`points` where each group after the first begins."""
        return np.cumsum(self.spans[:-1, 1] - self.spans[:-1, 0] + 1)

    @cached_property
    def configuration(self) -> Configuration:
        """The scan's configuration (§4.2) from these groups."""
        raw = _features_from_groups(self.groups, self.params)
        sizes = _angular_sizes([g.points for g, _v, _f in raw])
        feats = [
            Feature(
                vertices=v,
                points=g.points,
                bearing_start=g.bearing_start,
                bearing_end=g.bearing_end,
                angular_size=size,
                first_point=first,
            )
            for (g, v, first), size in zip(raw, sizes, strict=True)
        ]
        return Configuration(
            features=feats,
            frame="robot",
            viewpoint=np.zeros(3),
            cyclic=self.cyclic,
            fov=self.fov,
        )

    @cached_property
    def feature_of_point(self) -> np.ndarray:
        """Per row of :attr:`points`, the index of the :attr:`configuration`'s feature it
        belongs to (a cut vertex shared by two pieces: the later piece)."""
        own = np.zeros(len(self.points), dtype=np.intp)
        for i, f in enumerate(self.configuration.features):
            own[f.first_point : f.first_point + len(f.points)] = i
        return own


def scan_groups(
    ranges: np.ndarray, angles: np.ndarray, params: ExtractionParams | None = None
) -> ScanGroups:
    """The scan's grouped polylines (:class:`ScanGroups`), robot frame (metres).

    ``ranges`` metres with NaN for no return, ``angles`` radians in the robot frame. Raises
    :class:`LocalizationError` on mismatched or malformed arrays.
    """
    params = params or ExtractionParams()
    r, a = scan_arrays(ranges, angles)
    span = float(np.max(a) - np.min(a)) if a.size > 1 else 0.0
    beams, spans = group_spans(
        r,
        a,
        min_object_distance=params.min_object_distance,
        range_factor=params.range_factor,
        min_points=params.min_points,
        min_length=params.min_length,
    )
    return ScanGroups(
        beams=beams,
        spans=spans,
        cyclic=span >= 2.0 * np.pi - 1e-6,
        fov=(float(np.min(a)), float(np.max(a))),
        params=params,
    )


def scan_configuration(
    ranges: np.ndarray, angles: np.ndarray, params: ExtractionParams | None = None
) -> Configuration:
    """The scan's configuration (§4.2): polylines in angular order, robot frame (metres).

    ``ranges`` metres with NaN for no return, ``angles`` radians in the robot frame. Raises
    :class:`LocalizationError` on mismatched or malformed arrays.
    """
    return scan_groups(ranges, angles, params).configuration


def _hit_segments(points: np.ndarray, segments: np.ndarray, chunk: int = 256) -> np.ndarray:
    """Index of the segment nearest to each point (the segment a ray hit), ``(k,)``.
    A numba kernel when available (same arithmetic and ties), else chunked numpy."""
    if kernels.HAVE_NUMBA:
        return extract_kernels.nearest_segment(
            np.ascontiguousarray(points, dtype=np.float64),
            np.ascontiguousarray(segments, dtype=np.float64),
        )
    a = segments[:, 0:2]
    e = segments[:, 2:4] - a
    ee = np.maximum(np.einsum("ij,ij->i", e, e), 1e-18)
    out = np.empty(points.shape[0], dtype=np.intp)
    for s in range(0, points.shape[0], chunk):
        p = points[s : s + chunk]
        dx = p[:, None, 0] - a[None, :, 0]
        dy = p[:, None, 1] - a[None, :, 1]
        u = np.clip((dx * e[None, :, 0] + dy * e[None, :, 1]) / ee[None, :], 0.0, 1.0)
        rx = dx - u * e[None, :, 0]
        ry = dy - u * e[None, :, 1]
        out[s : s + chunk] = np.argmin(rx * rx + ry * ry, axis=1)
    return out


def map_view(
    source: MapData | RayCaster,
    pose: np.ndarray,
    fov: float = 2.0 * np.pi,
    beams: int = 720,
    max_range: float = 15.0,
    params: ExtractionParams | None = None,
    model: MapModel | None = None,
) -> Configuration:
    """The map's abstract sensor reading from ``pose`` (§2.1, §5.2): a configuration.

    ``pose`` ``[x, y, theta]`` map frame (metres, rad). ``beams`` virtual beams evenly cover
    ``fov`` radians centred on the heading (``fov = 2 pi``: a full circle starting behind the
    robot, so the configuration is cyclic); ranges beyond ``max_range`` metres are "no
    return". The virtual ranges are grouped and simplified exactly like a scan
    (:func:`scan_configuration`); the result is in the map frame, and every feature knows the
    map segments its rays hit (``Feature.segments``). With the map's ``model``
    (:class:`~service.core.sensor.mapmodel.MapModel`, whose segments ``source`` must cast) the hit
    segments come from its bucket grid instead of a search over every segment.
    """
    params = params or ExtractionParams()
    caster = source if isinstance(source, RayCaster) else RayCaster(source.segments())
    pose = np.asarray(pose, dtype=np.float64)
    if pose.shape != (3,) or not np.all(np.isfinite(pose)):
        raise LocalizationError(f"pose: expected 3 finite values, got {pose.shape}")
    if beams < 8:
        raise LocalizationError(f"map view needs >= 8 beams, got {beams}")
    full = fov >= 2.0 * np.pi - 1e-9
    if full:
        angles = -np.pi + (np.arange(beams) + 0.5) * (2.0 * np.pi / beams)
    else:
        angles = np.linspace(-0.5 * fov, 0.5 * fov, beams)
    ranges = caster.cast(pose, angles, max_range)
    raw = _features_from_ranges(ranges, angles, params, wrap=full)
    segs_all = caster.segments
    feats: list[Feature] = []
    if raw:
        # All features' points and vertices transformed at once (elementwise, so the same
        # numbers as per feature), one nearest-segment pass over all points, and per feature
        # the sorted hit segments (one np.unique over (feature, segment) codes).
        n_pts = [len(g.points) for g, _v, _f in raw]
        p_off = np.cumsum([0, *n_pts]).tolist()
        v_off = np.cumsum([0, *(len(v) for _g, v, _f in raw)]).tolist()
        pts = transform_points(pose, np.vstack([g.points for g, _v, _f in raw]))
        verts = transform_points(pose, np.vstack([v for _g, v, _f in raw]))
        sizes = _angular_sizes([g.points for g, _v, _f in raw])
        S = len(segs_all)
        ids = np.zeros(0, dtype=np.intp)
        bounds = [0] * (len(raw) + 1)
        if S:
            if model is not None:
                hit = model.nearest(pts, 0.05).segment
                if np.any(hit < 0):  # not on any segment (cannot happen for ray hits): search all
                    bad = hit < 0
                    hit[bad] = _hit_segments(pts[bad], segs_all)
            else:
                hit = _hit_segments(pts, segs_all)
            code = np.unique(np.repeat(np.arange(len(raw)), n_pts) * S + hit)
            ids = code % S
            bounds = np.searchsorted(code, np.arange(len(raw) + 1) * S).tolist()
        for f, (g, _v, first) in enumerate(raw):
            feats.append(
                Feature(
                    vertices=verts[v_off[f] : v_off[f + 1]],
                    points=pts[p_off[f] : p_off[f + 1]],
                    bearing_start=g.bearing_start,
                    bearing_end=g.bearing_end,
                    angular_size=sizes[f],
                    segments=segs_all[ids[bounds[f] : bounds[f + 1]]],
                    first_point=first,
                )
            )
    lo, hi = (-np.pi, np.pi) if full else (float(angles[0]), float(angles[-1]))
    return Configuration(
        features=feats, frame="map", viewpoint=pose.copy(), cyclic=full, fov=(lo, hi)
    )


class MapViewCache:
    """Map views of one map with a cached :class:`RayCaster` and view reuse.

    :meth:`view` returns the last view again while the requested pose is within
    ``reuse_distance`` metres of that view's viewpoint (a 360-degree view is heading
    independent); otherwise it ray casts a new one.
    """

    def __init__(
        self,
        map_data: MapData,
        beams: int = 720,
        max_range: float = 15.0,
        reuse_distance: float = 0.1,
        params: ExtractionParams | None = None,
        model: MapModel | None = None,
    ) -> None:
        self.map_data = map_data
        self.model = model
        self.caster = RayCaster(map_data.segments()) if model is None else model.caster
        self.beams = beams
        self.max_range = max_range
        self.reuse_distance = reuse_distance
        self.params = params or ExtractionParams()
        self._last: Configuration | None = None
        #: Number of views actually ray cast (for tests and benchmarks).
        self.casts = 0

    def view(self, pose: np.ndarray) -> Configuration:
        """Map view from ``pose`` (map frame), reused when the pose barely moved."""
        last = self._last
        if last is not None and np.hypot(*(last.viewpoint[:2] - pose[:2])) < self.reuse_distance:
            return last
        self._last = map_view(
            self.caster, pose, 2.0 * np.pi, self.beams, self.max_range, self.params, self.model
        )
        self.casts += 1
        return self._last

    def clear(self) -> None:
        """Forget the cached view."""
        self._last = None
