"""A map built from a laser log and its reference poses: occupancy grid and polylines.

Input: scans as ``(ranges, angles)`` pairs in the laser frame (metres, radians CCW from the
laser's forward axis; NaN = no return) and the laser's pose ``[x, y, theta]`` in the map frame
for each scan (e.g. the corrected poses of a SLAM run). Output (:class:`BuiltMap`):

* an **occupancy grid** (:class:`~service.adapters.maps.grid.OccupancyGrid`, writable with
  :func:`~service.adapters.maps.grid.write_map_yaml`): every return adds a *hit* to its cell; every
  beam adds a *pass* to each cell it crosses before it reaches its return (sampled every
  ``resolution`` metres along the beam, stopping ``free_margin`` short of the return); the
  cell's log-odds is ``hits * logit(p_hit) + passes * logit(p_miss)`` and its occupancy
  probability the logistic of that (unknown where a cell was never observed). With the
  defaults (0.55 and 0.49, as in Cartographer) a cell is more likely occupied than free when
  more than 1 in 6 of the beams that reached it ended there: at 2.5 cm, beams grazing a wall
  on their way to a farther return and the reference poses' own errors make real wall cells
  look passed-through often (fr079: median hits / (hits + passes) 0.38 over cells with >= 5
  hits, so the plain counting model would leave most wall cells below map_saver's 0.65).
* **polylines** along the wall surfaces the laser saw: the hit density smoothed by a Gaussian
  of ``smoothing`` metres, and its **ridge** traced to sub-cell precision. At every cell the
  Hessian of the smoothed density gives the direction ``n`` across the ridge (eigenvector of
  its most negative eigenvalue), oriented towards the sensors that made the hits (the
  smoothed sum of unit vectors from each return back to its sensor); the ridge is the zero
  crossing of the density's derivative along ``n`` (marching squares), kept only where the
  density is a ridge (negative curvature across it), where enough returns fell
  (``min_hits``), where it is not a faint echo beside a much stronger surface
  (``relative_density``), where the surface was seen from a consistent side
  (``min_view_consistency``). Ridge pieces whose ends face each other across a small gap are
  joined (``join_gap``, ``join_angle``). The ridge lines are
  simplified (Douglas-Peucker, ``simplify`` metres) and pieces shorter than ``min_length``
  are dropped. Unlike the edge of the blob of returns (which lies half a blob width in front
  of or behind the wall), the ridge is where the returns are densest: the wall surface.

Everything is vectorised numpy/scipy; the grid covers the returns and sensor positions with a
margin of ``4 * smoothing + 2`` cells.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy import ndimage

from service.adapters.maps.contours import (
    dedupe,
    join_polylines,
    marching_squares,
    polyline_length,
    simplify_polylines,
)
from service.adapters.maps.grid import MAX_IMAGE_CELLS, OccupancyGrid
from service.core import numeric
from service.core.types import MapData
from service.errors import InvalidMessage

#: Beam samples traced per chunk (bounds the temporary arrays of the ray traversal: ~60 bytes
#: per sample).
_CHUNK_SAMPLES = 4_000_000


@dataclass(frozen=True, eq=False)
class BuiltMap:
    """Result of :func:`build_map`.

    ``grid``: occupancy from hit and pass counts (log-odds) (row 0 = top, origin ``(x0, y0, 0)``).
    ``map_data``: the ridge polylines (kind ``metric``), map frame, metres.
    ``hits`` / ``passes``: ``(h, w)`` int64 counts in the grid's layout (row 0 = top).
    ``n_scans``: scans used; ``n_returns``: returns that made hits.
    """

    grid: OccupancyGrid
    map_data: MapData
    hits: np.ndarray
    passes: np.ndarray
    n_scans: int
    n_returns: int


def build_map(
    scans: Sequence[tuple[np.ndarray, np.ndarray]],
    poses: np.ndarray,
    *,
    map_id: str = "built",
    resolution: float = 0.025,
    min_range: float = 0.05,
    max_range: float = 30.0,
    free_margin: float | None = None,
    smoothing: float = 0.025,
    min_hits: float = 3.0,
    relative_density: float = 0.2,
    min_view_consistency: float = 0.2,
    p_hit: float = 0.55,
    p_miss: float = 0.49,
    join_gap: float = 0.1,
    join_angle: float = 30.0,
    simplify: float = 0.02,
    min_length: float = 0.1,
) -> BuiltMap:
    """Build an occupancy grid and wall polylines from scans taken at known laser poses.

    ``scans``: sequence of ``(ranges, angles)``, 1-D float arrays of equal length per scan,
    laser frame (metres; radians CCW from the laser's forward axis); NaN or non-finite range =
    no return. ``poses``: ``(n, 3)`` laser poses ``[x, y, theta]`` in the map frame (metres,
    radians), one per scan.

    Parameters (all distances in metres):

    * ``map_id``: id of the returned :class:`MapData`.
    * ``resolution`` (0.025): cell size of the grid and of the hit density.
    * ``min_range`` (0.05), ``max_range`` (30.0): returns outside ``[min_range, max_range)``
      are ignored, neither hits nor passes (a laser's "max range" reading means no return).
    * ``free_margin`` (default ``2 * resolution``): a beam counts as passing through cells only
      up to this distance short of its return, so the wall's own cells are not marked free by
      range noise.
    * ``smoothing`` (0.025): standard deviation of the Gaussian that smooths the hit density
      (the curvature and gradient use the same Gaussian's derivatives).
    * ``min_hits`` (3.0): a ridge point needs about this many returns within ~2 smoothing
      radii (the hit count smoothed at twice ``smoothing``, times the Gaussian's area).
    * ``relative_density`` (0.2): a ridge point's density must be at least this fraction of the
      largest density within 3 smoothing radii (suppresses ridges of stray returns beside a
      wall).
    * ``min_view_consistency`` (0.2): mean resultant length (0..1) of the directions from the
      returns near a point back to their sensors; below it the surface was seen from opposite
      sides or the point is noise, and no ridge is drawn.
    * ``p_hit`` (0.55), ``p_miss`` (0.49): occupancy probabilities of one hit and one pass
      (0 < ``p_miss`` < 0.5 < ``p_hit`` < 1); the grid's log-odds add up their logits.
    * ``join_gap`` (0.1), ``join_angle`` (30 degrees): ridge pieces whose ends face each other
      across at most ``join_gap`` with directions agreeing within ``join_angle`` are joined
      (ends within one cell join regardless; directions over the last 4 cells); the ridge
      breaks where a spurious crossing meets it or the mask has a hole. 0 disables.
    * ``simplify`` (0.02): Douglas-Peucker tolerance of the ridge polylines.
    * ``min_length`` (0.1): ridge polylines shorter than this are dropped.

    Raises :class:`InvalidMessage` for mismatched or malformed inputs, a grid over
    :data:`~service.adapters.maps.grid.MAX_IMAGE_CELLS` cells, or when no ridge survives.
    """
    P = np.asarray(poses, dtype=np.float64)
    if P.ndim != 2 or P.shape[1] != 3:
        raise InvalidMessage(f"build_map: poses must be (n, 3), got {P.shape}")
    if len(scans) != P.shape[0]:
        raise InvalidMessage(f"build_map: {len(scans)} scans but {P.shape[0]} poses")
    if P.shape[0] == 0:
        raise InvalidMessage("build_map: no scans")
    if not np.all(np.isfinite(P)):
        bad = int(np.nonzero(~np.all(np.isfinite(P), axis=1))[0][0])
        raise InvalidMessage(f"build_map: pose {bad} is not finite")
    for name, v in (
        ("resolution", resolution),
        ("max_range", max_range),
        ("smoothing", smoothing),
    ):
        if not (math.isfinite(v) and v > 0.0):
            raise InvalidMessage(f"build_map: {name} must be finite and > 0, got {v}")
    for name, v in (
        ("min_range", min_range),
        ("min_hits", min_hits),
        ("relative_density", relative_density),
        ("min_view_consistency", min_view_consistency),
        ("join_gap", join_gap),
        ("join_angle", join_angle),
        ("simplify", simplify),
        ("min_length", min_length),
    ):
        if not (math.isfinite(v) and v >= 0.0):
            raise InvalidMessage(f"build_map: {name} must be finite and >= 0, got {v}")
    if not (0.0 < p_miss < 0.5 < p_hit < 1.0):
        raise InvalidMessage(
            f"build_map: need 0 < p_miss < 0.5 < p_hit < 1, got p_miss {p_miss}, p_hit {p_hit}"
        )
    margin_free = 2.0 * resolution if free_margin is None else float(free_margin)
    if not (math.isfinite(margin_free) and margin_free >= 0.0):
        raise InvalidMessage(f"build_map: free_margin must be finite and >= 0, got {free_margin}")

    # ---- returns in the map frame
    sx_l, sy_l, ex_l, ey_l = [], [], [], []
    for i, scan in enumerate(scans):
        try:
            r_raw, a_raw = scan
        except (TypeError, ValueError) as exc:
            raise InvalidMessage(f"build_map: scan {i} is not a (ranges, angles) pair") from exc
        r = np.asarray(r_raw, dtype=np.float64)
        a = np.asarray(a_raw, dtype=np.float64)
        if r.ndim != 1 or a.shape != r.shape:
            raise InvalidMessage(
                f"build_map: scan {i}: ranges {r.shape} and angles {a.shape} must be equal 1-D"
            )
        if not np.all(np.isfinite(a)):
            raise InvalidMessage(f"build_map: scan {i}: non-finite beam angle")
        ok = np.isfinite(r) & (r >= min_range) & (r < max_range)
        if not ok.any():
            continue
        x, y, th = P[i]
        b = th + a[ok]
        rr = r[ok]
        ex_l.append(x + rr * np.cos(b))
        ey_l.append(y + rr * np.sin(b))
        sx_l.append(np.full(rr.size, x))
        sy_l.append(np.full(rr.size, y))
    if not ex_l:
        raise InvalidMessage("build_map: no return within [min_range, max_range)")
    ex, ey = np.concatenate(ex_l), np.concatenate(ey_l)
    sx, sy = np.concatenate(sx_l), np.concatenate(sy_l)

    # ---- grid geometry (bottom-up rows internally)
    pad = (4.0 * smoothing / resolution + 2.0) * resolution
    x0 = math.floor((min(ex.min(), P[:, 0].min()) - pad) / resolution) * resolution
    y0 = math.floor((min(ey.min(), P[:, 1].min()) - pad) / resolution) * resolution
    W = math.ceil((max(ex.max(), P[:, 0].max()) + pad - x0) / resolution)
    H = math.ceil((max(ey.max(), P[:, 1].max()) + pad - y0) / resolution)
    if W * H > MAX_IMAGE_CELLS:
        raise InvalidMessage(
            f"build_map: grid {W} x {H} at {resolution} m exceeds {MAX_IMAGE_CELLS} cells "
            f"(coarser resolution or a smaller max_range)"
        )
    ci = np.floor((ex - x0) / resolution).astype(np.int64)
    ri = np.floor((ey - y0) / resolution).astype(np.int64)
    flat = ri * W + ci
    hits = np.bincount(flat, minlength=H * W).reshape(H, W)
    dx, dy = sx - ex, sy - ey
    norm = np.hypot(dx, dy)
    norm[norm == 0.0] = 1.0
    vx = np.bincount(flat, dx / norm, minlength=H * W).reshape(H, W)
    vy = np.bincount(flat, dy / norm, minlength=H * W).reshape(H, W)
    passes = _trace_passes(sx, sy, ex, ey, x0, y0, resolution, W, H, margin_free)

    # ---- occupancy grid (row 0 = top)
    seen = hits + passes
    prob = np.full((H, W), np.nan)
    known = seen > 0
    logodds = hits[known] * _logit(p_hit) + passes[known] * _logit(p_miss)
    prob[known] = 0.5 * (1.0 + numeric.tanh(0.5 * logodds))  # logistic, overflow-free
    grid = OccupancyGrid.from_probability(prob[::-1], resolution, (x0, y0, 0.0))

    # ---- ridge of the hit density
    polys = _ridge_polylines(
        _splat(ex, ey, x0, y0, resolution, W, H),
        vx,
        vy,
        sigma=smoothing / resolution,
        min_hits=min_hits,
        relative_density=relative_density,
        min_view_consistency=min_view_consistency,
    )
    lines = [
        np.column_stack((x0 + (c[:, 1] + 0.5) * resolution, y0 + (c[:, 0] + 0.5) * resolution))
        for c in polys
    ]
    lines = [q for q in (dedupe(q) for q in lines) if q.shape[0] >= 2]
    if join_gap > 0.0:
        lines = join_polylines(
            lines,
            max_gap=join_gap,
            max_angle=join_angle,
            snap=resolution,
            end_window=4.0 * resolution,
        )
    if simplify > 0.0:
        lines = simplify_polylines(lines, simplify)
    lines = [q for q in lines if polyline_length(q) >= min_length]
    if not lines:
        raise InvalidMessage("build_map: no wall ridge survived (too few returns?)")
    map_data = MapData.from_lists(map_id, "metric", lines)
    return BuiltMap(
        grid=grid,
        map_data=map_data,
        hits=np.ascontiguousarray(hits[::-1]),
        passes=np.ascontiguousarray(passes[::-1]),
        n_scans=int(P.shape[0]),
        n_returns=int(ex.size),
    )


def _splat(
    ex: np.ndarray, ey: np.ndarray, x0: float, y0: float, res: float, W: int, H: int
) -> np.ndarray:
    """Hit density ``(H, W)`` (bottom-up rows) with each return shared bilinearly between the
    four cell centres around it: unlike counting each return in its cell, this keeps the
    sub-cell position (a wall on a cell boundary would otherwise be drawn half a cell off)."""
    gx = (ex - x0) / res - 0.5
    gy = (ey - y0) / res - 0.5
    c0 = np.floor(gx).astype(np.int64)
    r0 = np.floor(gy).astype(np.int64)
    fx = gx - c0
    fy = gy - r0
    out = np.zeros(H * W)
    for dr, dc, wgt in (
        (0, 0, (1.0 - fx) * (1.0 - fy)),
        (0, 1, fx * (1.0 - fy)),
        (1, 0, (1.0 - fx) * fy),
        (1, 1, fx * fy),
    ):
        rr = np.clip(r0 + dr, 0, H - 1)
        cc = np.clip(c0 + dc, 0, W - 1)
        out += np.bincount(rr * W + cc, wgt, minlength=H * W)
    return out.reshape(H, W)


def _logit(p: float) -> float:
    return math.log(p / (1.0 - p))


def _trace_passes(
    sx: np.ndarray,
    sy: np.ndarray,
    ex: np.ndarray,
    ey: np.ndarray,
    x0: float,
    y0: float,
    res: float,
    W: int,
    H: int,
    margin: float,
) -> np.ndarray:
    """Pass counts ``(H, W)`` (bottom-up rows): each beam from ``(sx, sy)`` towards its return
    ``(ex, ey)`` adds one to the cell of every sample at ``(k + 0.5) * res`` metres along it,
    up to ``margin`` metres short of the return. Vectorised in chunks of beams."""
    length = np.hypot(ex - sx, ey - sy)
    n_samp = np.floor(np.maximum(length - margin, 0.0) / res).astype(np.int64)
    keep = n_samp > 0
    gx0 = ((sx - x0) / res)[keep]
    gy0 = ((sy - y0) / res)[keep]
    ln = length[keep]
    cx = ((ex - sx)[keep] / ln).astype(np.float64)
    cy = ((ey - sy)[keep] / ln).astype(np.float64)
    n_samp = n_samp[keep]
    out = np.zeros(H * W, dtype=np.int64)
    if n_samp.size == 0:
        return out.reshape(H, W)
    cum = np.cumsum(n_samp)
    start = 0
    while start < n_samp.size:
        base = cum[start - 1] if start > 0 else 0
        stop = int(np.searchsorted(cum, base + _CHUNK_SAMPLES, side="right"))
        stop = max(stop, start + 1)
        ns = n_samp[start:stop]
        total = int(ns.sum())
        beam = np.repeat(np.arange(stop - start, dtype=np.int32), ns)
        first = np.cumsum(ns) - ns
        k = np.arange(total, dtype=np.float32)
        k -= np.repeat(first.astype(np.float32), ns)
        k += 0.5
        gx = gx0[start:stop].astype(np.float32)[beam] + k * cx[start:stop].astype(np.float32)[beam]
        gy = gy0[start:stop].astype(np.float32)[beam] + k * cy[start:stop].astype(np.float32)[beam]
        cell = gy.astype(np.int64)
        cell *= W
        cell += gx.astype(np.int64)
        out += np.bincount(cell, minlength=H * W)
        start = stop
    return out.reshape(H, W)


def _ridge_polylines(
    hits: np.ndarray,
    vx: np.ndarray,
    vy: np.ndarray,
    *,
    sigma: float,
    min_hits: float,
    relative_density: float,
    min_view_consistency: float,
) -> list[np.ndarray]:
    """Ridge lines of the smoothed hit density, ``(row, col)`` index space (bottom-up rows)."""
    g = ndimage.gaussian_filter
    dens = g(hits, sigma)
    Dx = g(hits, sigma, order=(0, 1))
    Dy = g(hits, sigma, order=(1, 0))
    Dxx = g(hits, sigma, order=(0, 2))
    Dyy = g(hits, sigma, order=(2, 0))
    Dxy = g(hits, sigma, order=(1, 1))
    wide = 2.0 * sigma
    H2 = g(hits, wide)
    VX = g(vx, wide)
    VY = g(vy, wide)
    # most negative eigenvalue of the Hessian and its eigenvector (x = col, y = row)
    half_diff = 0.5 * (Dxx - Dyy)
    root = np.sqrt(half_diff * half_diff + Dxy * Dxy)
    lam = 0.5 * (Dxx + Dyy) - root
    lam_other = 0.5 * (Dxx + Dyy) + root
    use_a = np.abs(Dxx - lam) > np.abs(Dyy - lam)
    nx = np.where(use_a, Dxy, lam - Dyy)
    ny = np.where(use_a, lam - Dxx, Dxy)
    nn = np.hypot(nx, ny)
    nn[nn == 0.0] = 1.0
    nx /= nn
    ny /= nn
    # orient n towards the sensors: the derivative along n is > 0 behind the ridge, < 0 in front
    flip = (nx * VX + ny * VY) < 0.0
    deriv = Dx * nx + Dy * ny
    deriv[flip] = -deriv[flip]
    count_near = H2 * (2.0 * math.pi * wide * wide)
    consistency = np.hypot(VX, VY) / np.maximum(H2, 1e-12)
    size = 2 * math.ceil(3.0 * sigma) + 1
    local_max = ndimage.maximum_filter(dens, size=size)
    mask = (
        (lam < -np.abs(lam_other))
        & (count_near >= min_hits)
        & (consistency >= min_view_consistency)
        & (dens >= relative_density * local_max)
    )
    return marching_squares(deriv, 0.0, mask)
