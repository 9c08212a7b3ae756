"""Global localisation (no initial pose, kidnapped robot) and an integrity signal for SBL.

The shape-based tracker (:class:`service.core.localizer.ShapeLocalizer`) needs a prior pose:
it compares the scan's configuration with the map's abstract sensor reading *from that pose*.
Without a prior, this module compares the scan with abstract sensor readings from everywhere:

1. :func:`candidate_viewpoints` — a grid over the map's free space. A polyline-only map has no
   notion of "inside", so a grid point is kept when a 360-degree virtual scan from it is
   *enclosed* (hits in nearly every direction), it keeps a clearance from every polyline, and
   it does not lie inside a small closed ring (furniture).
2. :class:`ViewIndex` — per viewpoint the map view (:func:`service.core.configuration.map_view`,
   the same extraction as for scans) reduced to its *units* (each feature and each pair of
   consecutive features, as step 1 of §5.3 uses them) with their shape complexity and range
   from the viewpoint, plus a distance field of the map for fast support tests. Built once per
   map (:func:`build_index`) and cached on disk (:func:`load_or_build_index`), keyed by a hash
   of the map content, the extraction parameters and :data:`FORMAT_VERSION`.
3. :func:`global_search` — the §5.3 step-1 idea applied to every viewpoint: the scan's most
   complex units are compared by S* with the view units at a compatible range; every similar
   pair induces an alignment (:func:`service.core.matching.induced_alignment`), i.e. a pose
   hypothesis. Hypotheses are ranked by support (distance field), refined by a point-to-line
   fit (:func:`service.core.pose.fit_pairs`) and verified beam by beam against the map
   (returns where the map predicts them, no beam passing through a map wall). The result is a
   ranked list of distinct hypotheses with an ambiguity in [0, 1] (1 = tie).
4. :class:`GlobalShapeLocalizer` — the :class:`~service.core.types.Localizer` the factory
   returns for ``shape``: tracks with a :class:`ShapeLocalizer`; with no pose, or once the
   tracker's quality collapses (status ``lost``), runs the global search on every scan, keeps
   the best hypotheses across scans and declares a winner only when it is clearly better than
   the best distinct alternative and the tracker confirms it on the same scan. While the
   hypotheses stay ambiguous it publishes ``initializing`` (or ``lost``) with the ambiguity and
   the best guess, never ``tracking``.

Frames and units: REP 103, metres and radians; poses ``[x, y, theta]`` in the map frame; scan
points in the robot frame (x forward, y left).
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import os
import re
import tempfile
import threading
import time
from collections import OrderedDict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field
from scipy import ndimage
from shapely import contains_xy
from shapely.geometry import Polygon

from service.core import _kernels
from service.core.composite import composite_scan
from service.core.configuration import (
    Configuration,
    ExtractionParams,
    map_view,
    scan_configuration,
)
from service.core.dce import dce
from service.core.localizer import ShapeConfig, ShapeLocalizer
from service.core.matching import induced_alignment
from service.core.motion import check_pose3
from service.core.pose import compose, fit_pairs, invert, transform_points
from service.core.raycast import RayCaster
from service.core.similarity import ShapeArcs, prepare, shape_complexity, shape_distance
from service.core.types import Estimate, MapData, Status, wrap_angle
from service.errors import LocalizationError

log = logging.getLogger("shapeloc.global")

#: Version of the on-disk index format; bump when the file layout or its meaning changes.
FORMAT_VERSION = 1
_CACHE_PREFIX = "viewindex-"


class GlobalConfig(BaseModel):
    """Weights and thresholds of global localisation (metres, radians; "support" fractions).

    :meth:`for_kind` gives the schematic variant (furniture in the scan is never explained by a
    floor plan, so the quality bars are lower there).
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    kind: Literal["metric", "schematic"] = "metric"
    # --- viewpoints and index ----------------------------------------------------------------
    spacing: float = Field(0.6, gt=0, description="Viewpoint grid spacing (m).")
    min_clearance: float = Field(0.3, ge=0, description="Viewpoint distance to any polyline (m).")
    enclosure_beams: int = Field(90, ge=8, description="Beams of the enclosure test.")
    min_enclosed: float = Field(
        0.9, gt=0, le=1, description="Fraction of enclosure beams that must hit within range."
    )
    small_ring_area: float = Field(
        6.0, ge=0, description="Closed rings smaller than this (m²) are obstacles, not rooms."
    )
    grid_resolution: float = Field(0.05, gt=0, description="Distance-field cell size (m).")
    # --- search ------------------------------------------------------------------------------
    scan_units: int = Field(5, ge=1, description="Most complex scan units compared by S*.")
    min_unit_complexity: float = Field(0.05, ge=0, description="Smallest unit complexity (m·rad).")
    range_slack: float = Field(
        0.4, ge=0, description="|range difference| allowed beyond the grid half-diagonal (m)."
    )
    view_complexity_ratio: float = Field(
        0.25,
        ge=0,
        description="View units less complex than this times the scan unit's are skipped.",
    )
    max_shape_distance: float = Field(0.6, gt=0, description="S* gate for a pair (m).")
    max_turn_difference: float = Field(
        0.35, gt=0, description="Corresponding anchor corners turn alike within this (rad)."
    )
    pairs_budget: int = Field(
        360, ge=1, description="Induced poses per scan, shared by the chosen scan units."
    )
    support_points: int = Field(80, ge=10, description="Scan points of the support test.")
    shortlist: int = Field(
        0,
        ge=0,
        description="Coarse pose cells (best induced pose each) polished on the distance field "
        "and ranked by a quick beam check before the refine_top best are chosen; 0 = rank the "
        "raw induced poses by point support. Schematic: 150 (furniture hides the walls that "
        "point support needs; on the exact map support ranks well and this is off).",
    )
    shortlist_cell: float = Field(0.4, gt=0, description="Coarse pose cell size (m).")
    shortlist_angle: float = Field(0.2, gt=0, description="Coarse pose cell heading width (rad).")
    shortlist_beams: int = Field(90, ge=8, description="Beams of the shortlist's quick check.")
    refine_top: int = Field(
        16, ge=1, description="Hypotheses refined and verified. Schematic: 32 (twin rooms)."
    )
    refine_iterations: int = Field(6, ge=1, description="Point-to-line fit steps per stage.")
    fine_scale: float = Field(
        0.05, gt=0, description="Cauchy scale (m) of the second, tight refinement stage."
    )
    verify_beams: int = Field(
        240, ge=10, description="Beams of the per-hypothesis verification. Schematic: 720."
    )
    keep: int = Field(8, ge=1, description="Hypotheses kept from one scan to the next.")
    distinct_distance: float = Field(
        0.8, gt=0, description="Hypotheses farther apart than this (m) are distinct."
    )
    distinct_angle: float = Field(
        0.5, gt=0, description="... or whose headings differ more than this (rad)."
    )
    violation_weight: float = Field(
        2.0, ge=0, description="Cost weight of beams that pass through a map wall."
    )
    violation_margin: float = Field(
        0.0,
        ge=0,
        description="A return counts as a violation only this far (m) beyond the predicted "
        "wall (at least the support tolerance). Schematic: 0.5 — a floor plan leaves out "
        "niches and door-jamb faces, so the true pose sees shallow 'violations' too.",
    )
    short_credit: float = Field(
        0.0,
        ge=0,
        le=1,
        description="Credit for a return short of the predicted wall (an unmapped object in "
        "front of it). Schematic: 0.5 (a floor plan has no furniture).",
    )
    cost_floor: float = Field(0.05, gt=0, description="Added to every hypothesis' cost.")
    ambiguity_scale: float = Field(
        0.1,
        gt=0,
        description="Cost margin of the best over the best distinct alternative at which the "
        "ambiguity reaches 0 (ambiguity = 1 - margin / scale, clipped); on an exact map "
        "small margins are significant. Schematic: 0.2.",
    )
    composite_scans: int = Field(
        3,
        ge=1,
        description="While searching, the last this many scans are fused into one virtual "
        "360-degree scan from the newest pose (service.core.composite), when they came with "
        "odometry; 1 = every scan alone.",
    )
    composite_bins: int = Field(
        720,
        ge=8,
        description="Beams of the virtual composite scan (fewer when the laser's own beams are "
        "coarser: never finer than them).",
    )
    composite_travel: float = Field(
        0.5,
        gt=0,
        description="Older scans taken farther than this (m, by odometry) from the newest one "
        "are left out of the composite (their occlusions would no longer hold).",
    )
    odom_turn_assist: float = Field(
        1.0,
        gt=0,
        description="While tracking without the odometry prior (``motion.use_odometry`` "
        "false), an odometry turn larger than this (rad) since the last scan still moves the "
        "tracker's pose first (the tracker follows turns up to its max_turn of 1.3 rad).",
    )
    # --- decision ----------------------------------------------------------------------------
    window: int = Field(3, ge=1, description="Scans over which a hypothesis' cost is averaged.")
    max_fix_cost: float = Field(
        0.2, gt=0, description="A winner's mean cost must be below this. Schematic: 0.3."
    )
    max_fix_ambiguity: float = Field(
        0.5, gt=0, le=1, description="A winner's ambiguity must be below this. Schematic: 0.35."
    )
    fused_fix_ambiguity: float = Field(
        0.5,
        gt=0,
        le=1,
        description="max_fix_ambiguity for a composite scan (look-around): it holds every "
        "scan of the window at once, so a smaller margin is as telling. Schematic: 0.7 "
        "(margin >= 0.06; safe only together with the self-similarity check: without it the "
        "twin rooms W1/W4 and E1/E3 won by noise, 2 % confident wrong fixes over 200 poses).",
    )
    fused_fix_cost: float = Field(
        0.2,
        gt=0,
        description="max_fix_cost for a composite scan. Schematic: 0.45 (a 360-degree view "
        "of a furnished room leaves a third of its beams unexplained by a floor plan).",
    )
    fused_single_ambiguity: float = Field(
        0.35,
        ge=0,
        le=1,
        description="single_scan_ambiguity for a composite scan (the fit must also meet "
        "max_fix_cost then). Schematic: 0 (always two scans: a 270-degree composite can miss "
        "the one door that tells twin rooms apart).",
    )
    single_scan_ambiguity: float = Field(
        0.35,
        ge=0,
        le=1,
        description="Below this ambiguity one scan suffices; else two. Schematic: 0 (always "
        "two: similar rooms of a floor plan differ by little more than noise).",
    )
    min_information: float = Field(
        0.0,
        ge=0,
        description="No fix from a scan whose most complex units sum to less shape complexity "
        "(m·rad): facing a bare wall, any wall fits. Schematic: 8.0.",
    )
    confirm_distance: float = Field(
        0.3, gt=0, description="The tracker's first pose must be this close to the winner (m)."
    )
    confirm_angle: float = Field(
        0.1,
        gt=0,
        description="... and turned less than this from it (rad): a tracker fit that swings the "
        "heading away from the verified pose is not a confirmation.",
    )
    # --- recovery near the lost track ------------------------------------------------------
    near_radius: float = Field(
        1.0,
        gt=0,
        description="After a loss, hypotheses within this (m) of the dead-reckoned last pose "
        "(moved by odometry, or held without it) are 'near the track': one of them is fixed "
        "on one scan if its cost is within near_cost_margin of the best (the motion history is "
        "the prior that twin places far away lack).",
    )
    near_growth: float = Field(
        0.2,
        ge=0,
        description="The near radius grows by this share of the odometry travel since the "
        "loss; without odometry by twice the robot's recent speed per scan.",
    )
    near_turn: float = Field(
        0.6,
        gt=0,
        description="With odometry, a near hypothesis must also be turned less than this "
        "(rad) from the dead-reckoned heading.",
    )
    near_cost_margin: float = Field(
        0.1,
        ge=0,
        description="A near hypothesis wins over a far one unless the far one's cost is lower "
        "by more than this.",
    )
    far_confirm_scans: int = Field(
        4,
        ge=1,
        description="A fix far from the dead-reckoned last pose must have been the best "
        "hypothesis on this many consecutive scans (never on one scan alone).",
    )
    reacquire_support: float = Field(
        0.5,
        ge=0,
        le=1,
        description="After a loss with odometry, the tracker is also run from the "
        "dead-reckoned last pose on every scan; when it accepts reacquire_scans scans in a "
        "row from there, each fit explaining at least this share of the scan, tracking "
        "resumes without a search fix (a stretch the map explained too little of is "
        "behind the robot).",
    )
    reacquire_scans: int = Field(3, ge=1, description="See reacquire_support.")
    # --- integrity ---------------------------------------------------------------------------
    collapse_score: float = Field(
        0.5,
        ge=0,
        le=1,
        description="A rejected scan scoring below this means 'lost' at once. Schematic: 0.45.",
    )

    @classmethod
    def for_kind(cls, kind: str) -> GlobalConfig:
        """Defaults for a map ``kind`` (``metric`` or ``schematic``)."""
        if kind == "metric":
            return cls()
        if kind == "schematic":
            return cls(
                kind="schematic",
                max_fix_cost=0.3,
                short_credit=0.5,
                ambiguity_scale=0.2,
                collapse_score=0.45,
                min_information=8.0,
                max_fix_ambiguity=0.35,
                single_scan_ambiguity=0.0,
                refine_top=32,
                fused_fix_ambiguity=0.7,
                fused_single_ambiguity=0.0,
                fused_fix_cost=0.45,
                shortlist=150,
                verify_beams=720,
                violation_margin=0.5,
            )
        raise LocalizationError(f"unknown map kind {kind!r}; expected metric or schematic")


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


def _nearby_segments(segments: np.ndarray, points: np.ndarray, radius: float) -> np.ndarray:
    """The segments within ``radius`` metres of any of ``points`` (all if none is)."""
    a = segments[:, 0:2]
    e = segments[:, 2:4] - a
    ee = np.maximum(np.einsum("ij,ij->i", e, e), 1e-18)
    dx = points[:, None, 0] - a[None, :, 0]
    dy = points[:, None, 1] - a[None, :, 1]
    u = np.clip((dx * e[None, :, 0] + dy * e[None, :, 1]) / ee[None, :], 0.0, 1.0)
    d2 = (dx - u * e[None, :, 0]) ** 2 + (dy - u * e[None, :, 1]) ** 2
    near = np.min(d2, axis=0) <= radius * radius
    return segments[near] if np.any(near) else segments


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


# --------------------------------------------------------------------------------------------
# Global search
# --------------------------------------------------------------------------------------------


@dataclass
class Hypothesis:
    """A pose hypothesis ``[x, y, theta]`` (map frame) with its verification on one scan:
    ``hit`` fraction of beams returned where the map predicts (within the support tolerance),
    ``violation`` fraction of beams that passed through a map wall, ``cost`` (lower is
    better), ``explained`` length fraction of the scan's polylines lying on the map there."""

    pose: np.ndarray
    cost: float
    hit: float = 0.0
    violation: float = 0.0
    explained: float = 0.0
    short: float = 0.0


@dataclass
class SearchResult:
    """Ranked distinct hypotheses (best first) and the best-vs-second ambiguity in [0, 1]
    (1 = tie, 0 = a single hypothesis). ``candidates`` how many pose hypotheses the shape
    pairs induced; ``information`` the summed shape complexity (m·rad) of the scan units
    used — how much distinctive shape the scan holds at all."""

    hypotheses: list[Hypothesis]
    ambiguity: float
    candidates: int
    information: float = 0.0


def _scan_units(P: Configuration, threshold: float) -> list[np.ndarray]:
    """Vertices of each scan feature and of each pair of consecutive ones (robot frame)."""
    out = [f.vertices for f in P.features]
    for a, b in zip(P.features[:-1], P.features[1:], strict=True):
        out.append(_joined(a.vertices, b.vertices, threshold))
    return out


def _subsample(points: np.ndarray, k: int) -> np.ndarray:
    if len(points) <= k:
        return points
    return points[np.linspace(0, len(points) - 1, k).round().astype(int)]


def _support_many(index: ViewIndex, poses: np.ndarray, pts: np.ndarray, tol: float) -> np.ndarray:
    """Fraction of robot-frame ``pts`` within ``tol`` of the map at each of ``poses`` (k, 3)."""
    c, s = np.cos(poses[:, 2]), np.sin(poses[:, 2])
    x = c[:, None] * pts[None, :, 0] - s[:, None] * pts[None, :, 1] + poses[:, 0:1]
    y = s[:, None] * pts[None, :, 0] + c[:, None] * pts[None, :, 1] + poses[:, 1:2]
    d = index.distance(np.column_stack([x.ravel(), y.ravel()])).reshape(len(poses), -1)
    return np.mean(d <= tol, axis=1)


def _field_scores(index: ViewIndex, poses: np.ndarray, pts: np.ndarray, sigma: float) -> np.ndarray:
    """Mean of ``exp(-d² / 2 sigma²)`` over robot-frame ``pts`` at each of ``poses`` ``(m, 3)``,
    ``d`` the distance-field value (capped at 10 m). A numba kernel when available, else the
    numpy reference (same arithmetic)."""
    if len(pts) == 0 or len(poses) == 0:
        return np.zeros(len(poses))
    if _kernels.HAVE_NUMBA:
        return _kernels.field_scores(
            index.dist,
            float(index.origin[0]),
            float(index.origin[1]),
            float(index.resolution),
            np.ascontiguousarray(poses, dtype=np.float64),
            np.ascontiguousarray(pts, dtype=np.float64),
            float(sigma),
            10.0,
        )
    c, s = np.cos(poses[:, 2]), np.sin(poses[:, 2])
    x = c[:, None] * pts[None, :, 0] - s[:, None] * pts[None, :, 1] + poses[:, 0:1]
    y = s[:, None] * pts[None, :, 0] + c[:, None] * pts[None, :, 1] + poses[:, 1:2]
    d = index.distance(np.column_stack([x.ravel(), y.ravel()])).reshape(len(poses), -1)
    return np.mean(np.exp(-0.5 * (np.minimum(d, 10.0) / sigma) ** 2), axis=1)


def _polish(
    index: ViewIndex,
    poses: np.ndarray,
    pts: np.ndarray,
    sigma: float,
    stages: tuple[tuple[float, float], ...] = ((0.05, 0.02), (0.015, 0.006)),
) -> tuple[np.ndarray, np.ndarray]:
    """Local search around each pose ``(k, 3)`` on the distance field: per stage a 5 x 5 x 5
    grid of ``(step_xy m, step_theta rad)`` (default +-0.1 m / +-0.04 rad, then +-0.03 m /
    +-0.012 rad) maximising the mean of ``exp(-d² / 2 s²)`` over the robot-frame ``pts``,
    ``s = max(sigma, step_xy)``. Unlike the least-squares fit it cannot be dragged by points
    that have no counterpart in the map. Returns the poses and their final scores ``(k,)``."""
    out = np.asarray(poses, dtype=np.float64).copy()
    best_score = np.zeros(len(out))
    for step_xy, step_th in stages:
        s_eff = max(sigma, step_xy)
        o = np.arange(-2, 3)
        dx, dy, dth = np.meshgrid(o * step_xy, o * step_xy, o * step_th, indexing="ij")
        delta = np.column_stack([dx.ravel(), dy.ravel(), dth.ravel()])
        cand = (out[:, None, :] + delta[None, :, :]).reshape(-1, 3)
        score = _field_scores(index, cand, pts, s_eff).reshape(len(out), -1)
        best = np.argmax(score, axis=1)
        best_score = score[np.arange(len(out)), best]
        out = cand.reshape(len(out), -1, 3)[np.arange(len(out)), best]
    out[:, 2] = wrap_angle(out[:, 2])
    return out, best_score


def _beam_fractions(
    r: np.ndarray, pred: np.ndarray, tol: float, gconfig: GlobalConfig
) -> tuple[float, float, float]:
    """Fractions of beams (measured ``r``, map-predicted ``pred``, NaN = nothing within range)
    that hit (within ``tol``), violate (return beyond the predicted wall by more than
    ``max(tol, gconfig.violation_margin)``) and fall short (something unmapped in front)."""
    hit = float(np.mean(np.abs(r - pred) <= tol))  # NaN prediction compares False
    viol = float(np.mean(np.isfinite(pred) & (r > pred + max(tol, gconfig.violation_margin))))
    short = float(np.mean(r < pred - tol))
    return hit, viol, short


def _beam_costs(
    index: ViewIndex,
    poses: np.ndarray,
    ranges: np.ndarray,
    angles: np.ndarray,
    beams: int,
    config: ShapeConfig,
    gconfig: GlobalConfig,
) -> np.ndarray:
    """The beam part of :func:`verify`'s cost for each of ``poses`` ``(k, 3)`` on ``beams``
    evenly chosen valid beams: ``1 - hit - short_credit * short + violation_weight *
    violation``. A quick ranking: unlike the point support it sees beams that pass through a
    wall, and it does not reward a wrong place for lining up furniture with map walls."""
    ok = np.nonzero(np.isfinite(ranges))[0]
    sel = _subsample(ok, beams)
    out = np.full(len(poses), np.inf)
    if sel.size == 0:
        return out
    r = ranges[sel]
    ang = angles[sel]
    tol = config.support_tolerance
    caster = index.caster
    for k, pose in enumerate(np.asarray(poses, dtype=np.float64)):
        pred = caster.cast(pose, ang, config.view_max_range)
        hit, viol, short = _beam_fractions(r, pred, tol, gconfig)
        out[k] = 1.0 - hit - gconfig.short_credit * short + gconfig.violation_weight * viol
    return out


def _refine(
    index: ViewIndex,
    poses: np.ndarray,
    sp: np.ndarray,
    config: ShapeConfig,
    gconfig: GlobalConfig,
) -> np.ndarray:
    """Refine poses ``(k, 3)`` against the map with the robot-frame scan points ``sp``: a
    point-to-line fit (Cauchy scale of the tracker), a tight second stage on the segments
    right under the points, a polish on the distance field and a last continuous fit."""
    poses = np.asarray(poses, dtype=np.float64)
    n = len(poses)
    refined, _ = fit_pairs(
        [sp] * n,
        [_nearby_segments(index.segments, transform_points(p, sp), 0.5) for p in poses],
        poses,
        iterations=gconfig.refine_iterations,
        robust_scale=config.align_robust_scale,
        damping=config.align_damping,
    )
    # second, tighter stage: only the segments right under the points and a small robust
    # scale, so returns from unmapped objects (furniture on a floor plan) stop pulling
    refined, _ = fit_pairs(
        [sp] * n,
        [
            _nearby_segments(index.segments, transform_points(p, sp), 2.0 * gconfig.fine_scale)
            for p in refined
        ],
        refined,
        iterations=gconfig.refine_iterations,
        robust_scale=gconfig.fine_scale,
        damping=config.align_damping,
    )
    refined, _ = _polish(index, refined, sp, gconfig.fine_scale)
    # and a last continuous fit from there (the distance field is quantised to its cells)
    refined, _ = fit_pairs(
        [sp] * n,
        [
            _nearby_segments(index.segments, transform_points(p, sp), 2.0 * gconfig.fine_scale)
            for p in refined
        ],
        refined,
        iterations=gconfig.refine_iterations,
        robust_scale=gconfig.fine_scale,
        damping=config.align_damping,
    )
    return refined


def _distinct(a: np.ndarray, b: np.ndarray, gconfig: GlobalConfig) -> bool:
    return bool(
        np.hypot(*(a[:2] - b[:2])) > gconfig.distinct_distance
        or abs(wrap_angle(a[2] - b[2])) > gconfig.distinct_angle
    )


def _near(a: np.ndarray, b: np.ndarray, dist: float = 0.3, ang: float = 0.15) -> bool:
    return bool(np.hypot(*(a[:2] - b[:2])) < dist and abs(wrap_angle(a[2] - b[2])) < ang)


def verify(
    index: ViewIndex,
    pose: np.ndarray,
    ranges: np.ndarray,
    angles: np.ndarray,
    P: Configuration,
    config: ShapeConfig,
    gconfig: GlobalConfig,
) -> Hypothesis:
    """Check a pose against the map beam by beam and feature by feature.

    ``gconfig.verify_beams`` valid beams of the scan are compared with the ranges the map
    predicts from ``pose``: a *hit* lies within ``config.support_tolerance`` of the predicted
    range, a *violation* is a return beyond the predicted range plus the tolerance (the beam
    went through a map wall), a *short* one ends before the predicted wall (something
    unmapped in front of it). ``explained`` is the length fraction of the scan's polylines with
    at least half their points within the tolerance of the map. Cost
    ``1 - hit + violation_weight * violation + cost_floor``.
    """
    tol = config.support_tolerance
    ok = np.isfinite(ranges)
    idx = np.nonzero(ok)[0]
    idx = _subsample(idx, gconfig.verify_beams)
    if idx.size == 0:
        return Hypothesis(pose=pose.copy(), cost=1.0 + gconfig.cost_floor)
    r = ranges[idx]
    pred = index.caster.cast(pose, angles[idx], config.view_max_range)
    hit, viol, short = _beam_fractions(r, pred, tol, gconfig)
    total = 0.0
    good = 0.0
    for f in P.features:
        d = index.distance(transform_points(pose, _subsample(f.points, 16)))
        total += f.length
        if np.mean(d <= tol) >= 0.5:
            good += f.length
    explained = good / total if total > 0 else 0.0
    cost = (
        1.0
        - hit
        - gconfig.short_credit * short
        + gconfig.violation_weight * viol
        + gconfig.cost_floor
    )
    return Hypothesis(
        pose=pose.copy(),
        cost=cost,
        hit=hit,
        violation=viol,
        explained=explained,
        short=short,
    )


def global_search(
    index: ViewIndex,
    ranges: np.ndarray,
    angles: np.ndarray,
    config: ShapeConfig,
    gconfig: GlobalConfig | None = None,
    seeds: list[np.ndarray] | tuple[np.ndarray, ...] = (),
    P: Configuration | None = None,
) -> SearchResult:
    """Rank pose hypotheses for one scan over the whole map (no prior pose).

    ``ranges`` metres (NaN = no return), ``angles`` radians (robot frame); ``config`` the
    tracker's :class:`ShapeConfig` (extraction, S* weights, support tolerance); ``seeds``
    extra poses to consider (the hypotheses kept from earlier scans, moved by odometry).
    ``P`` the scan's configuration if already computed.

    Steps: the ``gconfig.scan_units`` most complex scan units (features and consecutive pairs)
    are compared by S* (:func:`service.core.similarity.shape_distance`, the tracker's weights)
    with every index unit whose range from its viewpoint is within the grid half-diagonal plus
    ``gconfig.range_slack`` of the scan unit's range; the most (``gconfig.pairs_budget`` shared)
    similar pairs (S* <= ``gconfig.max_shape_distance``) each induce a pose
    (:func:`service.core.matching.induced_alignment`). All poses and the seeds are ranked by
    support (distance field); the best ``gconfig.refine_top`` distinct ones are refined by a
    point-to-line fit against the map and verified (:func:`verify`). Returns distinct
    hypotheses, best (lowest cost) first, and their :func:`ambiguity`.
    """
    gconfig = gconfig or GlobalConfig.for_kind(config.kind)
    r = np.asarray(ranges, dtype=np.float64)
    a = np.asarray(angles, dtype=np.float64)
    if P is None:
        P = scan_configuration(r, a, config.extraction())
    pts_all = (
        np.vstack([f.points for f in P.features]) if P.features else np.zeros((0, 2), dtype=float)
    )
    poses: list[np.ndarray] = [np.asarray(s, dtype=np.float64) for s in seeds]
    anchor_poses: list[np.ndarray] = []
    n_induced = 0
    information = 0.0
    if P.features and len(index):
        units = _scan_units(P, config.dce_threshold)
        comp = [(shape_complexity(u), k) for k, u in enumerate(units)]
        comp.sort(key=lambda t: (-t[0], t[1]))
        chosen = [k for c, k in comp[: gconfig.scan_units] if c >= gconfig.min_unit_complexity]
        information = float(sum(c for c, _k in comp[: gconfig.scan_units]))
        gate = 0.5 * np.sqrt(2.0) * gconfig.spacing + gconfig.range_slack
        ew, sw = config.shape_end_weight, config.shape_skip_weight
        for k in chosen:
            pu = units[k]
            pa = prepare(pu)
            dp = np.hypot(pu[:, 0], pu[:, 1])
            cp = shape_complexity(pu)
            p_anc, p_dir, p_turn = _anchor(pu)
            cand = np.nonzero(
                (index.unit_rmin <= dp.max() + gate)
                & (index.unit_rmax >= dp.min() - gate)
                & (index.unit_complexity >= gconfig.view_complexity_ratio * cp)
            )[0]
            cornered = abs(p_turn) > 0.2
            if cornered:  # corresponding corners turn alike
                dturn = np.mod(index.unit_anchor[cand, 3] - p_turn + np.pi, 2.0 * np.pi) - np.pi
                cand = cand[np.abs(dturn) < gconfig.max_turn_difference]
            # The same physical corner is seen from many viewpoints (one group): S* is
            # computed for one view of each group (the first), and a similar group lends its
            # views' anchors to every view of it; the budget of S*-induced alignments thus
            # covers many distinct places instead of one corner many times.
            groups = index.unit_group[cand]
            _, first = np.unique(groups, return_index=True)
            scored = []
            for u in cand[np.sort(first)].tolist():
                s = shape_distance(
                    pa,
                    index.arcs(u),
                    end_weight=ew,
                    skip_weight=sw,
                    upper_bound=gconfig.max_shape_distance,
                )
                if s < gconfig.max_shape_distance:
                    scored.append((s, u))
            scored.sort()
            for _s, u in scored[: gconfig.pairs_budget // len(chosen)]:
                poses.append(induced_alignment(pu, index.verts(u)))
                n_induced += 1
            if scored and cornered:
                # every view of a similar group fixes a pose by the anchors (corner vertex
                # and leaving edge): vectorised, cheap enough for all of them
                similar = np.isin(groups, index.unit_group[[u for _s, u in scored]])
                qa = index.unit_anchor[cand[similar]]
                phi = np.mod(qa[:, 2] - p_dir + np.pi, 2.0 * np.pi) - np.pi
                c, s_ = np.cos(phi), np.sin(phi)
                tx = qa[:, 0] - (c * p_anc[0] - s_ * p_anc[1])
                ty = qa[:, 1] - (s_ * p_anc[0] + c * p_anc[1])
                anchor_poses.append(np.column_stack([tx, ty, phi]))
                n_induced += len(qa)
    if not poses and not anchor_poses:
        return SearchResult(hypotheses=[], ambiguity=1.0, candidates=0, information=information)
    H = np.vstack([np.asarray(poses).reshape(-1, 3), *anchor_poses])
    sp = _subsample(pts_all, gconfig.support_points)
    if len(sp) == 0:
        return SearchResult(
            hypotheses=[], ambiguity=1.0, candidates=n_induced, information=information
        )
    sup = _support_many(index, H, sp, config.support_tolerance)
    order = np.argsort(-sup, kind="stable")
    if gconfig.shortlist > 0:
        # An induced pose near the truth is often 0.2-0.4 m / 5-10 deg off, so its raw support
        # trails a wrong place's that happens to line up. Keep the best pose per coarse pose
        # cell, polish the best cells' poses on the distance field (coarse then fine grid) and
        # rank by the polished score instead.
        cells = np.column_stack(
            [
                np.floor(H[:, 0] / gconfig.shortlist_cell),
                np.floor(H[:, 1] / gconfig.shortlist_cell),
                np.floor((wrap_angle(H[:, 2]) + np.pi) / gconfig.shortlist_angle),
            ]
        )
        _, first = np.unique(cells[order], axis=0, return_index=True)
        short = order[np.sort(first)][: gconfig.shortlist]
        polished, _score = _polish(
            index, H[short], sp, gconfig.fine_scale, stages=((0.15, 0.06), (0.05, 0.02))
        )
        quick = _beam_costs(index, polished, r, a, gconfig.shortlist_beams, config, gconfig)
        H = polished
        order = np.argsort(quick, kind="stable")
    picked: list[np.ndarray] = []
    for i in order.tolist():
        if len(picked) >= gconfig.refine_top:
            break
        if any(_near(H[i], p) for p in picked):
            continue
        picked.append(H[i])
    refined = _refine(index, np.vstack(picked), sp, config, gconfig)
    hyps = [verify(index, refined[k], r, a, P, config, gconfig) for k in range(len(picked))]
    hyps.sort(key=lambda h: h.cost)
    out: list[Hypothesis] = []
    for h in hyps:
        if all(not _near(h.pose, o.pose) for o in out):
            out.append(h)
    return SearchResult(
        hypotheses=out,
        ambiguity=ambiguity(out, gconfig),
        candidates=n_induced,
        information=information,
    )


def self_similar(
    index: ViewIndex,
    best: Hypothesis,
    ranges: np.ndarray,
    angles: np.ndarray,
    P: Configuration,
    config: ShapeConfig,
    gconfig: GlobalConfig,
) -> Hypothesis | None:
    """The map's own twin of ``best``, verified on the real scan, or ``None``.

    A search can miss the true place altogether (furniture hides its walls) and then crown a
    congruent room elsewhere with no close rival. So before a fix the map is asked where else
    it looks the same: the scan the MAP would give at ``best.pose`` (a ray cast over the real
    scan's beams that have returns) runs through :func:`global_search` itself; every
    resulting pose distinct from ``best`` is a place the map cannot tell from it, and is
    verified (:func:`verify`) on the real ``ranges`` / ``angles`` both as found and refined on
    the real scan's points (:func:`_refine`), whichever fits better. Returns the best verified
    twin (lowest cost)."""
    ok = np.isfinite(ranges)
    pred = index.caster.cast(best.pose, angles, config.view_max_range)
    pred = np.where(ok, pred, np.nan)
    if np.count_nonzero(np.isfinite(pred)) < 10:
        return None
    res = global_search(index, pred, angles, config, gconfig)
    cands = [h.pose for h in res.hypotheses if _distinct(h.pose, best.pose, gconfig)]
    pts = np.vstack([f.points for f in P.features]) if P.features else np.zeros((0, 2))
    sp = _subsample(pts, gconfig.support_points)
    if not cands or len(sp) == 0:
        return None
    # the map-only search aligned the twins to the map's own view; each is verified as found
    # and fitted to the real scan, whichever verifies better (furniture can drag the fit off)
    refined = _refine(index, np.vstack(cands), sp, config, gconfig)
    out: Hypothesis | None = None
    for pose in [*cands, *refined]:
        if not _distinct(pose, best.pose, gconfig):
            continue
        v = verify(index, pose, ranges, angles, P, config, gconfig)
        if out is None or v.cost < out.cost:
            out = v
    return out


def ambiguity(hyps: list[Hypothesis], gconfig: GlobalConfig) -> float:
    """Best vs best distinct alternative in [0, 1]: ``1 - (cost_2 - cost_1) / ambiguity_scale``
    clipped (1 = tie, 0 = the alternative is worse by the scale or more, or there is none);
    1 with no hypothesis at all (nothing is known).

    A margin rather than a ratio: on a floor plan every hypothesis, the true one included,
    leaves the furniture unexplained, so costs share a large common part that a ratio would
    read as ambiguity."""
    if not hyps:
        return 1.0
    best = hyps[0]
    for h in hyps[1:]:
        if _distinct(h.pose, best.pose, gconfig):
            margin = h.cost - best.cost
            return float(np.clip(1.0 - margin / gconfig.ambiguity_scale, 0.0, 1.0))
    return 0.0


# --------------------------------------------------------------------------------------------
# The localiser: tracking, global search, integrity
# --------------------------------------------------------------------------------------------


#: A hypothesis of this scan continues a track of the last one within this distance (m) and
#: heading change (rad): between two scans a robot may move a few decimetres and turn a lot.
_ASSOCIATE = (0.6, 1.0)
#: Heading offsets (rad) under which a kept hypothesis seeds the next scan's search.
_SEED_TURNS = (0.0, -0.4, 0.4, -0.8, 0.8)


@dataclass
class _Track:
    """A hypothesis followed across scans: its pose and the costs of the last scans (1.0
    stands for a scan on which it was not among the verified hypotheses)."""

    pose: np.ndarray
    costs: list[float]
    hyp: Hypothesis
    wins: int = 0


class GlobalShapeLocalizer:
    """Shape-based localisation with global search (implements
    :class:`service.core.types.Localizer`, method ``shape``).

    ``map_data`` the map; ``initial_pose`` ``[x, y, theta]`` map frame, or ``None`` (unknown:
    global localisation); ``config`` the tracker's :class:`ShapeConfig` (default per map
    kind); ``gconfig`` a :class:`GlobalConfig`; ``cache_dir`` where the map's
    :class:`ViewIndex` is cached (``None``: built in memory). The index is built on the first
    scan that needs a global search, not before.

    Modes: *tracking* — every scan goes to the wrapped :class:`ShapeLocalizer`; its estimate is
    published, except that a rejected scan whose score is below ``gconfig.collapse_score``
    (the scan's shapes no longer fit the map at all) or the tracker's own ``lost`` (after
    ``lost_after`` rejections) switches to *searching* at once and publishes ``lost``.
    The published ``ambiguity`` is the global search's (best vs best distinct hypothesis);
    while tracking it is ``None`` (the tracker's own value is in ``extras``).
    *searching* — every scan runs :func:`global_search`, seeded with the hypotheses kept from
    the previous scans (and, after a loss, the last tracked pose); each hypothesis' cost is
    averaged over the last ``gconfig.window`` scans. The best one wins when its mean cost is
    below ``gconfig.max_fix_cost``, its ambiguity against the best distinct alternative is
    below ``gconfig.max_fix_ambiguity``, it has been best on two consecutive scans and seen on
    every scan of the window (or is best on one with ambiguity below
    ``gconfig.single_scan_ambiguity``), the scan holds enough shape
    (``gconfig.min_information``), and the tracker, reset to it, accepts the same scan within
    ``gconfig.confirm_distance``. Until then the estimate is the
    best guess with status ``initializing`` (never had a fix) or ``lost`` (lost it) and the
    ambiguity; a confident ``tracking`` is only published after a win.
    """

    method = "shape"

    def __init__(
        self,
        map_data: MapData,
        initial_pose: np.ndarray | None,
        config: ShapeConfig | None = None,
        *,
        gconfig: GlobalConfig | None = None,
        cache_dir: Path | None = None,
    ) -> None:
        if config is not None and not isinstance(config, ShapeConfig):
            raise LocalizationError(f"config must be a ShapeConfig, got {type(config).__name__}")
        self.map_data = map_data
        self.config = config or ShapeConfig.for_kind(map_data.kind)
        self.gconfig = gconfig or GlobalConfig.for_kind(map_data.kind)
        self.cache_dir = None if cache_dir is None else Path(cache_dir)
        self.tracker = ShapeLocalizer(map_data, initial_pose, self.config)
        self._index: ViewIndex | None = None
        self._tracks: list[_Track] = []
        self._searching = False
        self._search_status: Status = "initializing"
        self._episode = 0
        self._last_odom: np.ndarray | None = None
        #: Scans of the current search, ``(ranges, angles, odometry pose)``, oldest first.
        self._history: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
        #: Scans that ran a global search since the last reset (for tests and benchmarks).
        self.searches = 0
        self.reset(initial_pose)

    @property
    def index(self) -> ViewIndex:
        """The map's view index (loaded or built on first use)."""
        if self._index is None:
            self._index = load_or_build_index(
                self.map_data, self.config, self.gconfig, self.cache_dir
            )
        return self._index

    @property
    def pose(self) -> np.ndarray | None:
        """Last tracked pose (map frame), ``None`` while searching without a fix."""
        return None if self._searching else self.tracker.pose

    @property
    def searching(self) -> bool:
        """``True`` while the pose is unknown (global search on every scan)."""
        return self._searching

    def reset(self, initial_pose: np.ndarray | None, odom: np.ndarray | None = None) -> None:
        """Forget the history; ``None`` starts a global search (status ``initializing``).
        ``odom``: odometry pose at ``initial_pose`` (the next increment starts from it)."""
        self.tracker.reset(initial_pose, odom)
        self._tracks = []
        self._history = []
        self._last_odom = (
            None if initial_pose is None or odom is None else check_pose3(odom, "odom")
        )
        self._searching = initial_pose is None
        self._search_status = "initializing"
        self._unfit = 0  # consecutive tracked scans that did not fit the map at all
        self._episode = 0
        self._anchor: np.ndarray | None = None  # dead-reckoned last tracked pose after a loss
        self._anchor_travel = 0.0
        self._reacquired = 0  # scans in a row the tracker accepted from the anchor
        self._speed: np.ndarray | None = None  # the tracker's known speed before the loss

    def update(
        self, ranges: np.ndarray, angles: np.ndarray, odom: np.ndarray | None = None
    ) -> Estimate:
        """Localise one scan (see the class docstring). ``ranges`` metres (NaN = no return),
        ``angles`` radians robot frame, ``odom`` optional odometry pose (own frame; only used
        to move the kept hypotheses between scans)."""
        if not self._searching:
            delta = self._remember_odom(odom)
            if (
                delta is not None
                and not self.tracker.config.motion.use_odometry
                and abs(float(delta[2])) > self.gconfig.odom_turn_assist
            ):
                # a turn the shape tracker cannot bridge (e.g. a look-around spin that goes on
                # after the fix): trust the odometry's heading change for the prior
                self.tracker.predict(delta)
            est = self.tracker.update(ranges, angles, odom)
            # The tracker's own ambiguity compares its step-2 hypotheses, which often converge
            # to the same pose (a "tie" of one pose with itself): not an integrity signal.
            # It stays in extras; the published ambiguity is the global one (None here).
            if est.ambiguity is not None:
                est.extras["tracker_ambiguity"] = float(est.ambiguity)
            est.ambiguity = None
            rejected = "rejected" in est.extras
            # scans that no longer fit the map at all collapse the track: one such scan
            # without an odometry prior, ``lost_after`` in a row with one (a furnished room on
            # a floor plan, or a crowd, can leave a scan unexplained while odometry holds)
            odometry_prior = odom is not None and self.tracker.config.motion.use_odometry
            unfit = rejected and est.score < self.gconfig.collapse_score
            self._unfit = self._unfit + 1 if unfit else 0
            need = self.tracker.config.lost_after if odometry_prior else 1
            collapsed = self._unfit >= need
            if est.status == "lost" or collapsed:
                speed = self.tracker.known_speed()
                self._start_search(est.pose)
                self._speed = speed
                est.status = "lost"
                est.ambiguity = 1.0  # no hypotheses yet: nothing tells the places apart
            return est
        r = np.asarray(ranges, dtype=np.float64)
        a = np.asarray(angles, dtype=np.float64)
        # validate exactly like the tracker (same errors for the same bad input)
        if r.ndim != 1 or a.ndim != 1 or r.shape != a.shape:
            raise LocalizationError(
                f"ranges and angles must be 1-D of equal length, got {r.shape} and {a.shape}"
            )
        if r.size == 0:
            raise LocalizationError("empty scan")
        if not np.all(np.isfinite(a)):
            raise LocalizationError("beam angles must be finite")
        if np.any(np.isinf(r)) or np.any(r[~np.isnan(r)] < 0):
            raise LocalizationError("ranges must be >= 0 or NaN (no return)")
        return self._search(r, a, odom)

    # ---------------------------------------------------------------- internals
    def _remember_odom(self, odom: np.ndarray | None) -> np.ndarray | None:
        """Odometry delta since the previous scan (robot frame) or ``None``."""
        if odom is None:
            self._last_odom = None
            return None
        o = np.asarray(odom, dtype=np.float64)
        if o.shape != (3,) or not np.all(np.isfinite(o)):
            raise LocalizationError(f"odom: expected 3 finite values, got {o.shape}")
        delta = None if self._last_odom is None else compose(invert(self._last_odom), o)
        self._last_odom = o
        return delta

    def _composite(self, r: np.ndarray, a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The scan the search matches: this one alone, or, when this scan and earlier ones of
        the search came with odometry, the virtual 360-degree composite of the last
        ``gconfig.composite_scans`` of them (:func:`service.core.composite.composite_scan`)
        taken within ``gconfig.composite_travel`` of this pose."""
        g = self.gconfig
        if self._last_odom is None or g.composite_scans <= 1:
            self._history = []
            return r, a
        here = self._last_odom
        self._history = [
            h
            for h in self._history[-(g.composite_scans - 1) :]
            if np.hypot(*(h[2][:2] - here[:2])) <= g.composite_travel
        ]
        self._history.append((r, a, here.copy()))
        if len(self._history) == 1:
            return r, a
        # bins no finer than the laser's beams (a coarser laser would leave holes that split
        # every polyline)
        inc = float(np.median(np.abs(np.diff(a)))) if a.size > 1 else 0.0
        bins = g.composite_bins
        if inc > 0.0:
            bins = int(min(bins, max(8, np.floor(2.0 * np.pi / inc + 1e-6))))
        return composite_scan(self._history, bins)

    def _seeds(self) -> list[np.ndarray]:
        """The kept hypotheses as seeds of this scan's search, each also turned by +-0.4 and
        +-0.8 rad: a robot may turn that much between two scans, more than the fit recovers."""
        out = []
        for t in self._tracks:
            for dth in _SEED_TURNS:
                out.append(np.array([t.pose[0], t.pose[1], wrap_angle(t.pose[2] + dth)]))
        return out

    def _start_search(self, last_pose: np.ndarray | None) -> None:
        self._searching = True
        self._unfit = 0
        self._search_status = "lost"
        self._episode = 0
        self._tracks = []
        self._history = []
        self._anchor = None
        self._anchor_travel = 0.0
        self._reacquired = 0
        if last_pose is not None:
            p = np.asarray(last_pose, dtype=np.float64).copy()
            self._anchor = p.copy()
            # the last tracked pose was verified by the tracker a scan ago: it enters with that
            # history, so a transient loss (an occlusion) recovers to it first
            floor = self.gconfig.cost_floor
            self._tracks = [_Track(p, [floor], Hypothesis(pose=p, cost=floor))]

    def _search(self, r: np.ndarray, a: np.ndarray, odom: np.ndarray | None) -> Estimate:
        g = self.gconfig
        self.searches += 1
        self._episode += 1
        prev_odom = self._last_odom
        delta = self._remember_odom(odom)
        moved = False  # the anchor already holds this scan's motion (an accepted fit)
        if self._anchor is not None and delta is not None:
            # (with odometry only: without it the held anchor is no motion prior the
            # tracker could be trusted from; tuning seeds 11 and 16 tracked wrong places)
            before = self._anchor
            back = self._reacquire(r, a, prev_odom, odom)
            if back is not None:
                return back
            moved = self._anchor is not before
        if delta is not None:
            for t in self._tracks:
                t.pose = compose(t.pose, delta)
            if self._anchor is not None:
                if not moved:
                    self._anchor = compose(self._anchor, delta)
                self._anchor_travel += float(np.hypot(delta[0], delta[1]))
        rs, as_ = self._composite(r, a)
        P = scan_configuration(rs, as_, self.config.extraction())
        seeds = self._seeds() + self._anchor_seeds(delta is not None)
        res = global_search(self.index, rs, as_, self.config, g, seeds=seeds, P=P)
        # associate this scan's hypotheses with the tracks
        new_tracks: list[_Track] = []
        for h in res.hypotheses[: g.keep]:
            prev = next((t for t in self._tracks if _near(t.pose, h.pose, *_ASSOCIATE)), None)
            costs = (prev.costs if prev is not None else []) + [h.cost]
            wins = prev.wins if prev is not None else 0
            if any(_near(t.pose, h.pose, *_ASSOCIATE) for t in new_tracks):
                continue
            new_tracks.append(_Track(h.pose.copy(), costs[-g.window :], h, wins))
        # mean cost over the window; a hypothesis seen on fewer of this search's scans pays
        # 1.0 for each scan it was missing from
        n = min(self._episode, g.window)
        fused = len(self._history) > 1
        for t in new_tracks:
            if fused:
                # the composite already holds the earlier scans: its cost is the evidence
                # (a mean over the window would count them twice and punish a hypothesis
                # that only the wider view revealed)
                continue
            missing = max(0, n - len(t.costs))
            t.hyp.cost = (sum(t.costs) + missing) / (len(t.costs) + missing)
        new_tracks.sort(key=lambda t: t.hyp.cost)
        for k, t in enumerate(new_tracks):
            t.wins = t.wins + 1 if k == 0 else 0
        self._tracks = new_tracks
        amb = ambiguity([t.hyp for t in new_tracks], g)
        if not new_tracks:
            return Estimate(
                pose=np.zeros(3) if self._anchor is None else self._anchor.copy(),
                status=self._search_status,
                score=0.0,
                explained=0.0,
                ambiguity=1.0,
                extras={"hypotheses": 0.0, "candidates": float(res.candidates)},
            )
        best = new_tracks[0]
        near_track = self._near_track(new_tracks, delta is not None)
        if near_track is not None:
            best = near_track
        far = self._anchor is not None and near_track is None
        extras = {
            "hypotheses": float(len(new_tracks)),
            "candidates": float(res.candidates),
            "search_cost": best.hyp.cost,
            "hit": best.hyp.hit,
            "violation": best.hyp.violation,
            "information": res.information,
        }
        # confirmed: best on two consecutive scans and seen on every scan of the window (a
        # hypothesis that just appeared may be a twin the true one briefly lost to), or clear
        # enough on one scan -- which on a composite also needs the plain (not the composite)
        # cost bar: a lone mediocre fit far ahead of the rest can mean the true place was not
        # found at all
        steady = best.wins >= 2 and (fused or len(best.costs) >= min(self._episode, g.window))
        if fused:
            single = amb < g.fused_single_ambiguity and best.hyp.cost <= g.max_fix_cost
        else:
            single = amb < g.single_scan_ambiguity
        confirmed = steady or single
        if far:
            # a fix far from where the track was lost moves the estimate across the building:
            # it must win scan after scan first
            confirmed = best.wins >= g.far_confirm_scans
        informative = res.information >= g.min_information
        max_amb = g.fused_fix_ambiguity if fused else g.max_fix_ambiguity
        fix_cost = g.fused_fix_cost if fused else g.max_fix_cost
        if near_track is not None:
            # recovered near the lost track: the motion history rules out the far twins, but
            # the fit itself must be as good as a single scan's fix (the dead-reckoned pose is
            # published meanwhile, and is better than a mediocre fit next to it)
            confirmed, informative, amb = True, True, 0.0
            fix_cost = g.max_fix_cost
            extras["near_track"] = 1.0
        if best.hyp.cost <= fix_cost and amb <= max_amb and confirmed and informative:
            twin = None
            if near_track is None:
                twin = self_similar(self.index, best.hyp, rs, as_, P, self.config, g)
            if twin is not None:
                twin_amb = ambiguity([best.hyp, twin], g)
                extras["twin_ambiguity"] = twin_amb
                if twin_amb > max_amb:
                    # the map looks alike at another place and the scan cannot tell them apart:
                    # keep both as tracks and wait for evidence
                    self._tracks.append(_Track(twin.pose.copy(), [twin.cost], twin))
                    amb = max(amb, twin_amb)
                    extras["twin_rejected"] = 1.0
                    return self._unresolved(best, amb, extras)
            # the tracker starts at the fix with this scan's odometry, so the next scan's
            # increment (e.g. the rest of a look-around turn) is its motion prior
            self.tracker.reset(best.pose, self._last_odom)
            if self._speed is not None:
                self.tracker.set_speed(self._speed)
            est = self.tracker.update(r, a, self._last_odom)
            close = (
                np.hypot(*(est.pose[:2] - best.pose[:2])) <= g.confirm_distance
                and abs(float(wrap_angle(est.pose[2] - best.pose[2]))) <= g.confirm_angle
            )
            if est.status == "tracking" and "rejected" not in est.extras and close:
                self._searching = False
                self._tracks = []
                est.ambiguity = amb
                est.extras.update({"global_fix": 1.0, **extras})
                return est
            self.tracker.reset(None)
            extras["confirm_rejected"] = 1.0
        if far and self._anchor is not None and best.wins < g.far_confirm_scans:
            # the best guess to publish is still the dead-reckoned track, not a far place
            # that has not yet proven itself
            guess = _Track(self._anchor.copy(), best.costs, best.hyp, best.wins)
            return self._unresolved(guess, amb, extras)
        return self._unresolved(best, amb, extras)

    def _reacquire(
        self,
        r: np.ndarray,
        a: np.ndarray,
        prev_odom: np.ndarray | None,
        odom: np.ndarray | None,
    ) -> Estimate | None:
        """Run the tracker from the dead-reckoned last pose with this scan's odometry
        increment as its motion prior. Returns the estimate that
        resumes tracking after ``reacquire_scans`` accepted scans in a row with support
        ``>= reacquire_support``; ``None`` meanwhile (the anchor follows the accepted fits)."""
        g = self.gconfig
        assert self._anchor is not None
        self.tracker.reset(self._anchor, prev_odom)
        est = self.tracker.update(r, a, odom if prev_odom is not None else None)
        good = (
            est.status == "tracking"
            and "rejected" not in est.extras
            and (est.explained or 0.0) >= g.reacquire_support
        )
        self._reacquired = self._reacquired + 1 if good else 0
        if not good:
            self.tracker.reset(None)
            return None
        if self._reacquired < g.reacquire_scans:
            # follow the fit; the odometry increment is applied from here on the next scan
            self._anchor = est.pose.copy()
            self.tracker.reset(None)
            return None
        self._searching = False
        self._tracks = []
        self._history = []
        self._reacquired = 0
        est.ambiguity = None
        est.extras["reacquired"] = 1.0
        return est

    def _near_radius(self, odometry: bool) -> float:
        g = self.gconfig
        if odometry:
            return g.near_radius + g.near_growth * self._anchor_travel
        speed = float(np.hypot(*self.tracker.motion.velocity.velocity))
        return g.near_radius + 2.0 * speed * self._episode

    def _anchor_seeds(self, odometry: bool) -> list[np.ndarray]:
        """The dead-reckoned last pose as seeds: turned by the usual offsets with odometry,
        all round the circle without (the heading may have turned any amount)."""
        if self._anchor is None:
            return []
        turns = _SEED_TURNS if odometry else tuple(np.arange(8) * (np.pi / 4))
        x, y, th = self._anchor
        return [np.array([x, y, wrap_angle(th + t)]) for t in turns]

    def _near_track(self, tracks: list[_Track], odometry: bool) -> _Track | None:
        """The best hypothesis near the dead-reckoned last pose, if its cost is within
        ``near_cost_margin`` of the best overall; ``None`` otherwise (or before any loss)."""
        if self._anchor is None or not tracks:
            return None
        g = self.gconfig
        radius = self._near_radius(odometry)
        for t in tracks:  # sorted by cost
            if t.hyp.cost > tracks[0].hyp.cost + g.near_cost_margin:
                return None
            if np.hypot(*(t.pose[:2] - self._anchor[:2])) > radius:
                continue
            if odometry and abs(float(wrap_angle(t.pose[2] - self._anchor[2]))) > g.near_turn:
                continue
            return t
        return None

    def _unresolved(self, best: _Track, amb: float, extras: dict[str, float]) -> Estimate:
        """The best guess while the search goes on (status ``initializing`` or ``lost``)."""
        g = self.gconfig
        score = float(np.clip(1.0 - best.hyp.cost + g.cost_floor, 0.0, 1.0))
        return Estimate(
            pose=best.pose.copy(),
            status=self._search_status,
            score=score,
            explained=float(best.hyp.explained),
            ambiguity=float(amb),
            extras=extras,
        )
