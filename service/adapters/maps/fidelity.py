"""Map fidelity: how far the scan returns at their reference poses lie from a map's polylines.

For every return of every ``stride``-th scan, placed in the map frame by its scan's reference
pose, the exact Euclidean distance to the nearest polyline segment of the map; summarised as
median, 90th percentile and mean (metres). A low median says the polylines sit on the surfaces
the laser sees; the p90 grows with clutter and moving things that the map does not hold.

Nearest segments are found with a k-d tree over points sampled along the segments, and the
result is exact: for each return the ``k`` nearest samples name candidate segments whose exact
point-to-segment distances are taken; when the ``k``-th sample is not farther than the best
distance plus half the sampling step (so an unseen segment could still be nearer), the return
is resolved by a shapely STRtree nearest query instead.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import shapely
from scipy.spatial import cKDTree

from service.core.types import MapData
from service.errors import InvalidMessage

_K = 4


@dataclass(frozen=True)
class Fidelity:
    """Distances (metres) of scan returns to the nearest map polyline: ``median``, ``p90``
    (90th percentile), ``mean``, over ``n_points`` returns."""

    median: float
    p90: float
    mean: float
    n_points: int


def scan_points(
    scans: Sequence[tuple[np.ndarray, np.ndarray]],
    poses: np.ndarray,
    *,
    stride: int = 1,
    max_range: float = 30.0,
    min_range: float = 0.05,
) -> np.ndarray:
    """Returns of every ``stride``-th scan in the map frame, ``(m, 2)`` metres.

    ``scans``: ``(ranges, angles)`` pairs in the laser frame (NaN = no return); ``poses``
    ``(n, 3)`` laser poses ``[x, y, theta]`` in the map frame. Returns outside
    ``[min_range, max_range)`` are skipped (max-range readings are no returns).
    """
    P = np.asarray(poses, dtype=np.float64)
    if P.ndim != 2 or P.shape[1] != 3:
        raise InvalidMessage(f"poses must be (n, 3), got {P.shape}")
    if len(scans) != P.shape[0]:
        raise InvalidMessage(f"{len(scans)} scans but {P.shape[0]} poses")
    if stride < 1:
        raise InvalidMessage(f"stride must be >= 1, got {stride}")
    out = []
    for i in range(0, P.shape[0], stride):
        r_raw, a_raw = scans[i]
        r = np.asarray(r_raw, dtype=np.float64)
        a = np.asarray(a_raw, dtype=np.float64)
        if r.ndim != 1 or a.shape != r.shape:
            raise InvalidMessage(f"scan {i}: ranges {r.shape} and angles {a.shape} differ")
        if not np.all(np.isfinite(P[i])):
            raise InvalidMessage(f"pose {i} is not finite")
        ok = np.isfinite(r) & np.isfinite(a) & (r >= min_range) & (r < max_range)
        b = P[i, 2] + a[ok]
        out.append(np.column_stack((P[i, 0] + r[ok] * np.cos(b), P[i, 1] + r[ok] * np.sin(b))))
    return np.vstack(out) if out else np.zeros((0, 2))


def distances_to_map(map_data: MapData, points: np.ndarray) -> np.ndarray:
    """Exact distance (metres) from each ``(m, 2)`` point to the nearest polyline segment."""
    pts = np.asarray(points, dtype=np.float64).reshape(-1, 2)
    if pts.shape[0] == 0:
        return np.zeros(0)
    segs = map_data.segments()
    a = segs[:, 0:2]
    e = segs[:, 2:4] - a
    ee = np.einsum("ij,ij->i", e, e)
    seg_len = np.sqrt(ee)
    # sample every segment at spacing <= step (ends included)
    total = float(seg_len.sum())
    step = max(total / 200_000.0, 0.02)
    n_s = np.maximum(np.ceil(seg_len / step).astype(np.int64), 1) + 1
    sid = np.repeat(np.arange(len(segs)), n_s)
    first = np.cumsum(n_s) - n_s
    t = (np.arange(int(n_s.sum())) - np.repeat(first, n_s)) / np.repeat(n_s - 1, n_s)
    samples = a[sid] + t[:, None] * e[sid]
    spacing = float((seg_len / (n_s - 1)).max())
    tree = cKDTree(samples)
    k = min(_K, samples.shape[0])
    dk, ik = tree.query(pts, k=k)
    if k == 1:
        dk, ik = dk[:, None], ik[:, None]
    cand = sid[ik]  # (m, k) candidate segment ids
    ap = pts[:, None, :] - a[cand]
    ec = e[cand]
    eec = np.where(ee[cand] > 0.0, ee[cand], 1.0)
    tt = np.clip(np.einsum("mkj,mkj->mk", ap, ec) / eec, 0.0, 1.0)
    d = ap - tt[..., None] * ec
    dist = np.hypot(d[..., 0], d[..., 1]).min(axis=1)
    # exact unless an unseen segment could be nearer than the best candidate
    unsure = dk[:, -1] <= dist + 0.5 * spacing + 1e-12
    if k < samples.shape[0] and np.any(unsure):
        lines = shapely.linestrings(segs.reshape(-1, 2, 2))
        strtree = shapely.STRtree(lines)
        _, dd = strtree.query_nearest(
            shapely.points(pts[unsure]), return_distance=True, all_matches=False
        )
        dist[unsure] = dd
    return dist


def map_fidelity(
    map_data: MapData,
    scans: Sequence[tuple[np.ndarray, np.ndarray]],
    poses: np.ndarray,
    *,
    stride: int = 1,
    max_range: float = 30.0,
    min_range: float = 0.05,
) -> Fidelity:
    """Fidelity of ``map_data`` to the returns of ``scans`` at the laser poses ``poses``.

    ``scans``: ``(ranges, angles)`` in the laser frame (NaN = no return); ``poses`` ``(n, 3)``
    laser poses in the map frame; every ``stride``-th scan is used; returns outside
    ``[min_range, max_range)`` are skipped. Distances are exact point-to-segment distances
    (metres) to the nearest polyline (:func:`distances_to_map`). Raises
    :class:`InvalidMessage` for malformed input or when no return is left.
    """
    pts = scan_points(scans, poses, stride=stride, max_range=max_range, min_range=min_range)
    if pts.shape[0] == 0:
        raise InvalidMessage("map_fidelity: no scan return to measure")
    d = distances_to_map(map_data, pts)
    return Fidelity(
        median=float(np.median(d)),
        p90=float(np.percentile(d, 90.0)),
        mean=float(d.mean()),
        n_points=int(d.size),
    )
